"""Several browser pages on one `boostnerf view` at once, as users would have them: headless Chromium pages
(tests/cdp.py) on the viewer of a workspace.

1. Layers: two pages; the second ticks "routed cells" (off at first), then unticks "box": each page's screenshot
   must change (the nodes are the viewer's, one each, shown or hidden for every page).
2. Clients: N pages, each moving its camera along its own orbit of the box for 2 s and holding it 1 s, over and over
   (the camera is set from the server, as a drag would set it; the page reports it back as a drag does), one of them
   slowed (`--slow`: its CPU throttled 20 times by CDP). Per page: the frames it was shown (low resolution and full),
   frames per second, the longest wait between two frames while its camera moved; the server's resident memory
   (this process's: the viewer runs in it) before, at its highest and at the end; every log line that says a frame
   failed, and any traceback.

Usage: python scripts/view_clients.py -w WS [--pages 4] [--seconds 30] [--slow 1] [--size N] [--window WxH]
                                      [--json FILE]
Needs viser and Chromium ($CHROMIUM, /usr/bin/chromium or one on the PATH).
"""

from __future__ import annotations

import argparse
import io
import json
import logging
import math
import os
import sys
import threading
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

import imageio.v3 as iio  # noqa: E402
import numpy as np  # noqa: E402

from boostnerf_cli.lineage import Survey  # noqa: E402
from boostnerf_cli.stages import view  # noqa: E402
from boostnerf_cli.viewpoint.viewer import Models, Viewer  # noqa: E402
from boostnerf_cli.workspace import Workspace  # noqa: E402


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def click_label(browser, label: str) -> None:
    """Click the page's checkbox labelled `label` in its centre, as a user does."""
    element = (f"document.getElementById(Array.from(document.querySelectorAll('label'))"
               f".find(l => l.textContent === {label!r}).htmlFor)")
    deadline = time.monotonic() + 20
    while not browser.js(f"!!({element})"):
        if time.monotonic() > deadline:
            raise RuntimeError(f"no {label!r} on the page")
        time.sleep(0.1)
    x, y = browser.js(f"(() => {{ const r = ({element}).getBoundingClientRect(); "
                      "return [r.x + r.width / 2, r.y + r.height / 2] })()")
    for kind in ("mousePressed", "mouseReleased"):
        browser.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1)


def changed(a: bytes, b: bytes) -> int:
    """Pixels that differ by more than 30 (summed over RGB) between two screenshots."""
    x, y = (iio.imread(io.BytesIO(s))[..., :3].astype(int) for s in (a, b))
    return int((np.abs(x - y).sum(-1) > 30).sum())


def settle(page, seconds: float = 2.0) -> None:
    """Wait until no frame is due for any page, then `seconds` more (the frames reach the browsers)."""
    deadline = time.monotonic() + 60
    while page.viewer.next_job(now=time.monotonic() + 10) is not None and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(seconds)


def layers(page, browsers) -> dict:
    """The second page ticks routed cells, then unticks box: how many pixels of each page's screenshot changed."""
    settle(page)
    out = {}
    for label in ("routed cells", "box"):
        before = [b.screenshot() for b in browsers]
        click_label(browsers[1], label)
        time.sleep(2.0)
        after = [b.screenshot() for b in browsers]
        out[label] = {"pixels_changed_per_page": [changed(x, y) for x, y in zip(before, after)],
                      "layer_shown": page.viewer.layers["cells" if label == "routed cells" else "box"]}
    return out


def clients(page, browsers, seconds: float, slow: int) -> dict:
    """Every page moves its camera (2 s moving, 1 s still, again); frames and waits per page, memory, failures."""
    viewer = page.viewer
    shown: dict[int, list[tuple[float, bool]]] = {}
    real = viewer.drawn

    def drawn(job, shot):
        shown.setdefault(job.client, []).append((time.monotonic(), job.full))
        real(job, shot)

    viewer.drawn = drawn
    for b in browsers[:slow]:
        b.call("Emulation.setCPUThrottlingRate", rate=20)
    handles = list(page.server.get_clients().values())
    box = viewer.model.bbox.double().cpu().numpy()
    centre, radius = box.mean(0), 1.2 * float(np.linalg.norm(box[1] - box[0]))
    memory, moving = [rss_mb()], {h.client_id: [] for h in handles}
    start = time.monotonic()
    while (t := time.monotonic() - start) < seconds:
        still = (t % 3.0) >= 2.0
        for k, h in enumerate(handles):
            if not still:
                a = 2 * math.pi * (k / len(handles) + 0.05 * t)
                with h.atomic():
                    h.camera.position = tuple(centre + radius * np.array([math.cos(a), math.sin(a), 0.4]))
                    h.camera.look_at = tuple(centre)
                moving[h.client_id].append(time.monotonic())
        memory.append(rss_mb())
        time.sleep(0.1)
    time.sleep(2.0)
    memory.append(rss_mb())
    viewer.drawn = real
    pages = []
    for k, h in enumerate(handles):
        times = [s for s, _ in shown.get(h.client_id, [])]
        waits = [b - a for a, b in zip(times, times[1:])]
        pages.append({"page": k + 1, "slow": k < slow,
                      "frames_low": sum(not f for _, f in shown.get(h.client_id, [])),
                      "frames_full": sum(f for _, f in shown.get(h.client_id, [])),
                      "frames_per_second": round(len(times) / seconds, 2),
                      "longest_wait_s": round(max(waits), 2) if waits else None})
    return {"seconds": seconds, "pages": pages, "frame_height": viewer.size,
            "rss_mb": {"before": round(memory[0]), "highest": round(max(memory)), "end": round(memory[-1])}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-w", "--workspace", required=True)
    ap.add_argument("--pages", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--slow", type=int, default=1, help="how many pages are slowed (CPU throttled 20 times)")
    ap.add_argument("--size", type=int, default=None, help="frame height (default: the viewer's)")
    ap.add_argument("--window", default="1000x700", help="each page's size in pixels, WxH")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    from cdp import INSTALL, Browser, chromium_binary

    binary = chromium_binary()
    if binary is None:
        sys.exit(f"no Chromium: {INSTALL}")
    lines: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record):
            lines.append(record.getMessage() + (("\n" + "".join(traceback.format_exception(*record.exc_info)))
                                                if record.exc_info else ""))

    logging.getLogger().addHandler(Keep())
    logging.getLogger().setLevel(logging.INFO)
    errors: list[str] = []
    threading.excepthook = lambda a: errors.append("".join(traceback.format_exception(a.exc_type, a.exc_value,
                                                                                        a.exc_traceback)))
    ws = Workspace(Path(args.workspace))
    viewer = Viewer(ws, Survey(ws).scene(), Models(ws, args.device), args.size)
    page = view.start_server(viewer, "127.0.0.1", 0)
    stop = threading.Event()
    loop = threading.Thread(target=view.serve, args=(page, stop), daemon=True)
    loop.start()
    url = f"http://127.0.0.1:{page.server.get_port()}/"
    browsers = []
    result: dict = {"workspace": str(ws.root), "model": viewer.label, "window": args.window,
                    "load_before": os.getloadavg()}
    try:
        for _ in range(max(2, args.pages)):
            browsers.append(Browser(binary, *(int(v) for v in args.window.split("x"))))
            browsers[-1].open(url)
        deadline = time.monotonic() + 60
        while len(page.server.get_clients()) < len(browsers) and time.monotonic() < deadline:
            time.sleep(0.2)
        result["layers"] = layers(page, browsers[:2])
        result["clients"] = clients(page, browsers[: args.pages], args.seconds, args.slow)
    finally:
        stop.set()
        loop.join(timeout=30)
        for b in browsers:
            b.close()
        page.server.stop()
    result["load_after"] = os.getloadavg()
    result["failures"] = [line for line in lines if "could not render" in line or "Traceback" in line] + errors
    text = json.dumps(result, indent=2)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")


if __name__ == "__main__":
    main()
