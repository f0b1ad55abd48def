"""Gate bake (128^3, a 24^3 gate) timed alone and beside N busy torch processes, with 2 and 1 intra-op threads:
`python research/oversubscription.py` (docs/benchmarks.md, "How should several jobs share one machine?")."""

import subprocess
import sys
import time

import torch

from boostnerf_cli.moe.gate import Gate, GateConfig

BUSY = "import torch\nx=torch.randn(512,512)\nwhile True: x=(x@x).clamp(-1,1)"


def bake(gate: Gate, threads: int) -> tuple[float, float]:
    """The fastest and slowest of three bakes with `threads` intra-op threads, in seconds."""
    torch.set_num_threads(threads)
    times = []
    for _ in range(3):
        t = time.perf_counter()
        gate.baked(128)
        times.append(time.perf_counter() - t)
    return min(times), max(times)


def main() -> None:
    gate = Gate(GateConfig(gate_type="grid", gate_res=24), 3, torch.tensor([[-1.0] * 3, [1.0] * 3]))
    for n_busy in (0, 1, 3):
        procs = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(n_busy)]
        time.sleep(3)
        try:
            for threads in (2, 1):
                lo, hi = bake(gate, threads)
                print(f"{n_busy} busy torch processes (2 threads each), bake with {threads} thread(s): "
                      f"{lo:.2f}-{hi:.2f} s", flush=True)
        finally:
            for p in procs:
                p.kill()


if __name__ == "__main__":
    main()
