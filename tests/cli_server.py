"""A fork server for the tests: imports torch and the CLI once, then runs each `boostnerf ...` call in a
forked child, so the hundreds of CLI calls of the suite (`conftest.run_cli`) and the documented commands
(the docs test's `boostnerf` shim) do not each pay torch's import (seconds). It runs a script the same way
(`python SCRIPT ARGS`: `conftest.run_script`, for scripts/ and research/).

    python tests/cli_server.py SOCKET          # serve until killed
    python tests/cli_server.py --client SOCKET ARGS...   # what the `boostnerf` shim runs

The client sends its arguments, working folder and environment as JSON and its stdin, stdout and
stderr as file descriptors; the child adopts them, runs `boostnerf_cli.cli.main()` and the client
exits with the child's exit code. A script runs as `python SCRIPT` runs it: as `__main__`, with its own folder
first on `sys.path` and then PYTHONPATH's entries (modules the server imported stay the ones it imported). One
command at a time (each xdist worker starts its own server). The
child is a fresh process as far as the CLI can tell: its own pid (a kill test's SIGKILL ends the child
only), folder, environment and file descriptors; the server never runs a parallel region before forking,
so the child's OpenMP threads start fresh.
"""

from __future__ import annotations

import json
import os
import runpy
import socket
import sys


def serve(path: str) -> None:
    import torch

    import boostnerf_cli.cli
    import boostnerf_cli.scenes  # noqa: F401
    from boostnerf_cli.stages import (  # noqa: F401
        bench,
        build_moe,
        count_params,
        evaluate,
        export,
        finetune,
        pretrain,
        prune,
        render,
    )

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))  # no parallel region before a fork
    torch.optim.Adam([torch.zeros(1, requires_grad=True)], fused=True)  # loads the optimiser's lazy imports
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(path)
    srv.listen(1)
    print("ready", flush=True)
    while True:
        conn, _ = srv.accept()
        msg, fds, _, _ = socket.recv_fds(conn, 1 << 20, 3)
        request = json.loads(msg.decode())
        pid = os.fork()
        if pid == 0:
            srv.close()
            for target, fd in enumerate(fds):
                os.dup2(fd, target)
            os.chdir(request["cwd"])
            os.environ.clear()
            os.environ.update(request["env"])
            if "OMP_NUM_THREADS" in os.environ:  # what a fresh process takes from it when it imports torch
                torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
            script = request.get("script")
            sys.argv = [script or "boostnerf", *request["args"]]
            code = 0
            try:
                if script:
                    paths = [os.path.dirname(os.path.abspath(script)),
                             *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
                    sys.path[0:1] = [p for p in paths if p not in sys.path[1:]]
                    runpy.run_path(script, run_name="__main__")
                else:
                    boostnerf_cli.cli.main()
            except SystemExit as e:  # as the interpreter ends: a code that is not a number is printed, exit 1
                if e.code is None or isinstance(e.code, int):
                    code = e.code or 0
                else:
                    print(e.code, file=sys.stderr)
                    code = 1
            except BaseException:  # noqa: BLE001  (report any crash as a failed command)
                import traceback

                traceback.print_exc()
                code = 1
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
        for fd in fds:
            os.close(fd)
        _, status = os.waitpid(pid, 0)
        # the exit code as subprocess gives it: -N when signal N ended the child (a kill test's SIGKILL)
        conn.sendall(str(os.waitstatus_to_exitcode(status)).encode())
        conn.close()


def request(path: str, args: list[str], cwd: str, env: dict[str, str], fds: list[int],
            timeout: float | None = None, script: str | None = None) -> int:
    """Run `boostnerf ARGS` (with `script`: `python SCRIPT ARGS`) in a child of the server at `path`, in folder
    `cwd` with environment `env` and `fds` as its stdin, stdout and stderr -> its exit code (-N when signal N
    ended it)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
        conn.settimeout(timeout)
        conn.connect(path)
        msg = {"args": args, "cwd": cwd, "env": env, "script": script}
        socket.send_fds(conn, [json.dumps(msg).encode()], fds)
        reply = conn.recv(16)
    return int(reply or b"1")


def client(path: str, args: list[str]) -> int:
    code = request(path, args, os.getcwd(), dict(os.environ), [0, 1, 2])
    return code if code >= 0 else 128 - code  # a shell's code for a signalled command


if __name__ == "__main__":
    if sys.argv[1] == "--client":
        sys.exit(client(sys.argv[2], sys.argv[3:]))
    serve(sys.argv[1])
