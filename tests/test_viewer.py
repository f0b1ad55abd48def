"""`boostnerf view` and `render --camera`: the page's scene, what a camera renders, switching model and map, saved
views rendered again, following training, bad input, and one test in a real (headless) browser."""

from __future__ import annotations

import json
import logging
import os
import shutil
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import assert_clean_failure, cli_in_process, run_cli, unavailable

from boostnerf_cli.cameras import Intrinsics
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.images import to_uint8
from boostnerf_cli.lineage import Survey
from boostnerf_cli.models import load_model
from boostnerf_cli.render.renderer import render_view
from boostnerf_cli.stages import view
from boostnerf_cli.viewpoint.camera import camera_for_view, dataset_camera, fov_of, opencv_pose
from boostnerf_cli.viewpoint.frame import Look
from boostnerf_cli.viewpoint.geometry import CELL_SHARE, box_edges, first_view, frustum_size, hidden_frustums, world_box
from boostnerf_cli.viewpoint.saved import read_view
from boostnerf_cli.viewpoint.viewer import PREVIEW, SNAP, STILL, Phase
from boostnerf_cli.workspace import Workspace

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def viewer(mixture_ws):
    ws = Workspace(mixture_ws)
    return view.Viewer(ws, Survey(ws).scene(), view.Models(ws, "cpu"))


@pytest.fixture
def served(viewer):
    """`viewer` served on a free port by its render loop (a thread), stopped afterwards."""
    page = view.start_server(viewer, "127.0.0.1", 0)
    stop = threading.Event()
    loop = threading.Thread(target=view.serve, args=(page, stop), daemon=True)
    loop.start()
    yield viewer, page
    stop.set()
    loop.join(timeout=30)
    page.server.stop()


def test_the_page_draws_every_camera_the_box_and_the_routed_cells(served):
    viewer, page = served
    server, scene = page.server, viewer.scene
    n = len(scene.split("train")) + len(scene.split("test"))
    names = [f"/cameras/{s}/{k:04d}" for k, s in enumerate(["train"] * len(scene.split("train")) + ["test"] * 3)]
    assert len(names) == n and all(server.scene.get_handle_by_name(name) is not None for name in names)
    assert server.scene.get_handle_by_name("/box") is not None
    points, colours, width = viewer.model_parts()[1]
    assert server.scene.get_handle_by_name("/cells") is not None and len(points) > 0
    assert width == pytest.approx(CELL_SHARE * viewer.model.field.vd.unit)
    lo, hi = viewer.model.bbox.numpy()
    assert ((points >= lo - 1e-6) & (points <= hi + 1e-6)).all()
    assert len({tuple(c) for c in colours}) == 2  # the gate picks both experts somewhere
    assert viewer.label == "top2" and list(page.controls.model.options) == ["dvgo-12", "dvgo-16", "top2"]


def test_a_dataset_camera_renders_what_render_renders_and_its_psnr(viewer):
    snap = viewer.go_to("test", 0)
    camera, shot, score = snap.camera, snap.shot, snap.psnr
    model = load_model(viewer.ws, "top2", "cpu")
    split = viewer.scene.split("test")
    expected = render_view(model.field, split, 0, *model.render_setup(viewer.scene, model_skips()), "cpu")["rgb"]
    assert np.array_equal(shot.image, to_uint8(expected))
    mse = float(((expected.double() - split.images[0].double()) ** 2).mean())
    assert score == pytest.approx(-10 * np.log10(mse), abs=1e-4)
    assert shot.gflops > 0 and shot.seconds > 0
    # the browser's camera (OpenCV, a vertical field of view) at the same place renders the same picture
    pose = opencv_pose(camera.pose)
    browser = camera_for_view(pose[:3, :3], pose[:3, 3], fov_of(camera), camera.width / camera.height, camera.height)
    assert torch.allclose(browser.pose, camera.pose, atol=1e-6)
    assert torch.allclose(browser.intrinsics, camera.intrinsics, atol=1e-4)


def model_skips():
    from boostnerf_cli.models import ALL_SKIPS

    return ALL_SKIPS


def test_switching_model_and_map_changes_the_picture(viewer, caplog):
    camera = dataset_camera(viewer.scene.split("test"), 0)
    pictures = {}
    for mode in ("colour", "depth", "routing"):
        viewer.show(Look(mode))
        pictures[mode] = viewer.draw(camera).image
    for e in (0, 1):
        for mode in ("share", "gate"):
            viewer.show(Look(mode, e))
            pictures[mode, e] = viewer.draw(camera).image
    keys = list(pictures)
    assert all(not np.array_equal(pictures[a], pictures[b]) for i, a in enumerate(keys) for b in keys[i + 1:])
    viewer.choose("dvgo-12")
    assert viewer.look == Look("colour")  # an expert has no gate: back to its colour
    assert not np.array_equal(viewer.draw(camera).image, pictures["colour"])
    with caplog.at_level(logging.INFO, logger="boostnerf_cli"):
        viewer.show(Look("routing"))
    assert viewer.look == Look("colour") and "dvgo-12 is an expert, not a mixture" in caplog.text


def test_the_maps_are_those_render_per_expert_writes(viewer, tmp_path):
    ws = tmp_path / "ws"
    shutil.copytree(viewer.ws.root, ws)
    run_cli("render", "-w", str(ws), "--model", "top2", "--per-expert", "--views", "1", "--device", "cpu", check=True)
    import imageio.v3 as iio

    stem = viewer.scene.split("test").stems[0]
    folder = ws / "renders" / "top2" / "test"
    camera = dataset_camera(viewer.scene.split("test"), 0)
    for e, name in enumerate(("dvgo-12", "dvgo-16")):
        for mode, kind in (("share", "expert"), ("gate", "gate")):
            viewer.show(Look(mode, e))
            assert np.array_equal(viewer.draw(camera).image, iio.imread(folder / f"{stem}_{kind}{e}-{name}.png"))


@pytest.mark.parametrize("look", [Look("colour"), Look("gate", 1)])
def test_a_saved_view_renders_again_identically(mixture_ws, tmp_path, look):
    shutil.copytree(mixture_ws, tmp_path / "ws")
    ws = Workspace(tmp_path / "ws")
    viewer = view.Viewer(ws, Survey(ws).scene(), view.Models(ws, "cpu"))
    viewer.show(look)
    train = viewer.scene.split("train")
    pose = opencv_pose(train.poses[3])  # a browser's camera: not a dataset view's size or aspect
    camera = camera_for_view(pose[:3, :3], pose[:3, 3] * 1.1, 0.7, 1.5, 24)
    shot = viewer.draw(camera)
    png = viewer.save(camera, shot)
    assert png.name == "view-001.png" and read_view(png.with_suffix(".json"))[0].width == 36
    proc = run_cli("render", "-w", str(ws.root), "--camera", str(png.with_suffix(".json")), "--device", "cpu",
                   check=True)
    again = Path(proc.stdout.strip())
    assert again == ws.root / "renders" / "top2" / "views" / "view-001.png"
    assert again.read_bytes() == png.read_bytes()
    assert viewer.save(camera, shot).name == "view-002.png"


def test_a_broken_view_file_is_one_line(mixture_ws, tmp_path):
    bad = tmp_path / "view.json"
    bad.write_text('{"pose": [[1, 0], [0, 1]], "intrinsics": [1, 1, 1, 1], "height": 4, "width": 4, "model": "top2"}')
    assert_clean_failure(run_cli("render", "-w", str(mixture_ws), "--camera", str(bad)), "is not a saved view")
    bad.write_text("{")
    assert_clean_failure(run_cli("render", "-w", str(mixture_ws), "--camera", str(bad)), str(bad))
    zero = {"pose": [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]], "intrinsics": [44, 44, 16, 16],
            "height": 32, "width": 32, "model": "top2"}
    bad.write_text(json.dumps(zero))  # crashed deep in the renderer (a NaN ray) with a traceback
    assert_clean_failure(run_cli("render", "-w", str(mixture_ws), "--camera", str(bad)), "not a rigid camera pose")


GOOD_VIEW = {"pose": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]], "intrinsics": [44, 44, 16, 16],
             "height": 32, "width": 32, "model": "top2"}


@pytest.mark.parametrize("change, message", [
    ({"pose": [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]]}, "not a rigid camera pose"),
    ({"pose": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]}, "not a rigid camera pose"),
    ({"pose": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [1, 1, 1, 1]]}, "bottom row"),
    ({"pose": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3]]}, "16 numbers"),
    ({"height": True}, "height and width"),
    ({"width": 100000}, "height and width"),
    ({"intrinsics": [44, 44, 16, 16, 0, 0, 0, 0, 0, 0, 7]}, "fisheye"),
])
def test_a_saved_view_is_checked_as_a_camera_path_s_entry_is(tmp_path, change, message):
    """A saved view's pose must be rigid (as a camera path's: `camera_path.rigid`), its size whole numbers of pixels up
    to a camera path's largest, and a lens's fisheye flag 0 or 1: each else one line naming the file."""
    file = tmp_path / "view.json"
    file.write_text(json.dumps(GOOD_VIEW))
    assert read_view(file)[0].height == 32
    file.write_text(json.dumps({**GOOD_VIEW, **change}))
    with pytest.raises(BoostNerfError, match=message) as e:
        read_view(file)
    assert str(file) in str(e.value) and "\n" not in str(e.value)


def test_without_viser_one_line_says_how_to_install_it(mixture_ws, monkeypatch, capsys):
    monkeypatch.setitem(__import__("sys").modules, "viser", None)
    code, err = cli_in_process(monkeypatch, capsys, "view", "-w", str(mixture_ws))
    assert code == 2 and err.strip() == f"error: {view.INSTALL}"


def test_a_workspace_without_models_shows_its_cameras(trained_ws, tmp_path, caplog):
    shutil.copytree(trained_ws, tmp_path / "ws", ignore=shutil.ignore_patterns("*.safetensors", "moe"))
    ws = Workspace(tmp_path / "ws")
    with caplog.at_level(logging.INFO, logger="boostnerf_cli"):
        viewer = view.Viewer(ws, Survey(ws).scene(), view.Models(ws, "cpu"))
    assert viewer.model is None and viewer.draw(dataset_camera(viewer.scene.split("train"), 0)) is None
    assert "has no models yet: the page shows the scene's cameras" in caplog.text
    server = view.start_server(viewer, "127.0.0.1", 0).server
    try:
        assert server.scene.get_handle_by_name("/cameras/train/0000") is not None
    finally:
        server.stop()


def test_a_port_in_use_is_one_line_and_the_next_one_serves(caplog):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with caplog.at_level(logging.INFO, logger="boostnerf_cli"):
            free = view.free_port("127.0.0.1", port)
    assert free > port and f"port {port} is in use (another viewer?): serving on {free} instead" in caplog.text


def test_a_model_file_being_written_keeps_the_last_good_model(mixture_ws, tmp_path, caplog):
    shutil.copytree(mixture_ws, tmp_path / "ws")
    ws = Workspace(tmp_path / "ws")
    models = view.Models(ws, "cpu", follow=True)
    good = models.get("top2")
    path = ws.model_path("top2")
    whole = path.read_bytes()
    path.write_bytes(whole[: len(whole) // 2])  # another process, half way through a plain (not atomic) copy
    with caplog.at_level(logging.INFO, logger="boostnerf_cli"):
        assert models.changed("top2") and models.get("top2") is good
        assert models.get("top2") is good  # said once per version of the file
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and lines[0].startswith(f"cannot read {path}") and "keeping the one read before" in lines[0]
    path.write_bytes(whole)
    assert models.changed("top2")
    again = models.get("top2")
    assert again is not good and torch.equal(again.field.gate.logit_table, good.field.gate.logit_table)


@pytest.mark.slow
def test_follow_shows_a_model_in_training_from_its_checkpoint(mixture_ws, tmp_path):
    """A finetune killed after its first checkpoint leaves top1's training state: --follow offers it, reads it, and
    reads it again when training writes the next one."""
    shutil.copytree(mixture_ws, tmp_path / "ws")
    ws = Workspace(tmp_path / "ws")
    proc = run_cli("finetune", "-w", str(ws.root), "--topk", "1", "--device", "cpu",
                   env_extra={"BOOSTNERF_TEST_KILL": "checkpoint:1"})
    assert proc.returncode != 0 and ws.checkpoint_path("top1").exists()
    models = view.Models(ws, "cpu", follow=True)
    assert "top1 (training)" in models.labels() and models.newest() == "top1 (training)"
    assert "top1 (training)" not in view.Models(ws, "cpu").labels()
    viewer = view.Viewer(ws, Survey(ws).scene(), models)
    assert viewer.label == "top1 (training)" and viewer.model.field.cfg.topk == 1
    camera = dataset_camera(viewer.scene.split("test"), 0)
    first = viewer.draw(camera).image
    proc = run_cli("finetune", "-w", str(ws.root), "--topk", "1", "--device", "cpu",
                   env_extra={"BOOSTNERF_TEST_KILL": "checkpoint:1"})  # resumed: its next checkpoint
    assert models.changed("top1 (training)")
    assert viewer.poll()
    assert not np.array_equal(viewer.draw(camera).image, first)
    run_cli("finetune", "-w", str(ws.root), "--topk", "1", "--device", "cpu", check=True)  # finished: the model
    assert viewer.poll() and viewer.label == "top1" and "top1 (training)" not in models.labels()


def test_the_command_serves_the_page_on_the_next_port_and_stops_at_ctrl_c(mixture_ws):
    import signal
    import subprocess
    import sys
    import urllib.request

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        proc = subprocess.Popen([sys.executable, "-m", "boostnerf_cli", "view", "-w", str(mixture_ws), "--port",
                                 str(port), "--device", "cpu"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, env={**os.environ, "PYTHONWARNINGS": "ignore"})
        try:
            lines = []
            while not lines or not lines[-1].startswith("viewer at "):
                line = proc.stderr.readline()
                assert line, f"the viewer ended: {''.join(lines)}"
                lines.append(line)
            url = lines[-1].split()[2]
            assert f"port {port} is in use (another viewer?): serving on" in "".join(lines)
            page = urllib.request.urlopen(url.replace("localhost", "127.0.0.1"), timeout=30).read().decode()
            assert "<html" in page.lower()
        finally:
            proc.send_signal(signal.SIGINT)
            out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0 and out == "" and "Traceback" not in err
    assert err.strip().splitlines()[-1] == "viewer stopped"


# --- a real browser -----------------------------------------------------------------------------------------------
SCREENSHOT_ENV = "BOOSTNERF_VIEWER_SCREENSHOT"  # a path: the test writes its first screenshot there (docs/viewer.md)


@pytest.mark.slow
def test_the_page_in_headless_chromium_draws_the_frames_on_its_canvas(served):
    """The 3D canvas, cut from the page beside the control panel, shows the viewer's frame: the first is the render of
    the training view the page opens at (the subject, not the first camera's frustum in front of it); picking depth
    in the page changes the canvas over much of its area; picking another model draws that model. The same canvas
    hidden (blank) fails that check, though the whole page, its panel, would pass it."""
    from cdp import INSTALL, Browser, chromium_binary

    from boostnerf_cli.viewpoint.camera import scaled

    binary = chromium_binary()
    if binary is None:
        unavailable("Chromium", INSTALL)
    viewer, page = served
    train = viewer.scene.split("train")
    reference = viewer.draw(scaled(dataset_camera(train, first_view(train.poses)), 128)).image
    browser = Browser(binary)
    try:
        browser.open(f"http://127.0.0.1:{page.server.get_port()}/")
        first = wait_for(lambda: shown_full(page, "top2"), "the first full frame")
        browser.js("document.querySelectorAll('.mantine-Notification-root button').forEach(b => b.click())")
        time.sleep(1.0)  # the frame reaches the page; the browser's notice (software WebGL) is closed
        far, overlay = shows_view(browser, reference)
        colour = drawn_canvas(browser)
        pick(browser, "show", "depth")
        wait_for(lambda: viewer.look.mode == "depth" and shown_full(page, "top2"), "a depth frame")
        depth, depth_page = drawn_canvas(browser, unlike=colour), browser.screenshot()
        pick(browser, "model", "dvgo-12")
        wait_for(lambda: shown_full(page, "dvgo-12"), "a frame of the model picked in the page")
        press(browser, "go to view N")  # train view 0
        wait_for(lambda: "PSNR" in page.controls.truth.content, "the dataset view's PSNR")
        time.sleep(2.0)  # the page reports the camera it was snapped to: it stays on the dataset view
        assert [v.pinned for v in viewer.clients.values()] == [("train", 0)] and page.controls.truth_image.visible
        browser.js("document.querySelectorAll('canvas').forEach(c => c.style.visibility = 'hidden')")  # draws nothing
        time.sleep(0.5)
        blank, whole = browser.screenshot(canvas_area(browser)), browser.screenshot()
    finally:
        browser.close()
    assert first
    assert reference[32:96, 32:96].std() > 10 and far < SHOWS_VIEW and overlay < 0.05, (far, overlay)
    assert_frames_differ(colour, depth)
    with pytest.raises(AssertionError, match="blank"):
        assert_frames_differ(blank, depth)
    assert_frames_differ(whole, depth_page, what="the whole page")  # its control panel is not blank


def canvas_area(browser) -> tuple[float, float, float, float]:
    """The page's 3D canvas (its largest) left of the control panel that lies over it (x, y, width, height): where
    the frames are drawn."""
    return tuple(browser.js("""(() => {
        const canvas = Array.from(document.querySelectorAll('canvas'))
            .reduce((a, b) => (b.width * b.height > a.width * a.height ? b : a)).getBoundingClientRect();
        let panel = Array.from(document.querySelectorAll('label')).find(l => l.textContent === 'model');
        while (panel.parentElement && panel.parentElement.getBoundingClientRect().width < 0.6 * canvas.width) {
            panel = panel.parentElement;
        }
        const left = Math.min(canvas.right, panel.getBoundingClientRect().left);
        return [canvas.x, canvas.y, left - canvas.x, canvas.height];
    })()"""))


def drawn_canvas(browser, unlike: bytes | None = None, seconds: float = 30.0) -> bytes:
    """A screenshot of the canvas once it shows a frame (not blank; unlike `unlike`'s, when given): a loaded machine
    draws a frame the page has received a while later. After `seconds` the last screenshot, for the checks to judge."""
    deadline = time.monotonic() + seconds
    while True:
        shot = browser.screenshot(canvas_area(browser))
        try:
            assert_frames_differ(shot, unlike) if unlike is not None else assert_not_blank(shot)
            return shot
        except AssertionError:
            if time.monotonic() > deadline:
                return shot
            time.sleep(0.5)


def assert_not_blank(shot: bytes, what: str = "the canvas") -> None:
    import imageio.v3 as iio

    a = iio.imread(shot)[..., :3].astype(int)
    assert a.std() > 10, f"{what} is blank (std {a.std():.1f})"


def assert_frames_differ(first: bytes, second: bytes, what: str = "the canvas") -> None:
    """Two screenshots of two frames: the first is not blank (one colour), and they differ over a tenth of it."""
    import imageio.v3 as iio

    a, b = iio.imread(first)[..., :3].astype(int), iio.imread(second)[..., :3].astype(int)
    assert a.shape == b.shape and a.shape[0] > 100 and a.shape[1] > 100, (a.shape, b.shape)
    assert_not_blank(first, what)
    changed = (np.abs(a - b).sum(-1) > 30).mean()
    assert changed > 0.1, f"{what} did not change: {100 * changed:.1f}% of its pixels"


def shown_full(page, label: str) -> bool:
    viewer = page.viewer
    return viewer.label == label and any(v.last is not None and v.phase is Phase.SHOWN and
                                         page.controls.stats.content.startswith(f"**{label}**")
                                         for v in viewer.clients.values())


def wait_for(condition, what: str, seconds: float = 60.0):
    deadline = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"no {what} within {seconds:.0f} s")
        time.sleep(0.1)
    return True


def click(browser, element: str) -> None:
    """Click the page's `element` (a JavaScript expression) in its centre, as a user does."""
    wait_for(lambda: browser.js(f"!!({element})"), f"the page's {element}", 20)
    centre = browser.js(f"(() => {{ const r = ({element}).getBoundingClientRect(); "
                        "return [r.x + r.width / 2, r.y + r.height / 2] })()")
    for kind in ("mousePressed", "mouseReleased"):
        browser.call("Input.dispatchMouseEvent", type=kind, x=centre[0], y=centre[1], button="left", clickCount=1)
    time.sleep(0.3)


def press(browser, text: str) -> None:
    click(browser, f"Array.from(document.querySelectorAll('button')).find(b => b.textContent.trim() === {text!r})")


def pick(browser, label: str, option: str) -> None:
    """Choose `option` in the page's dropdown `label` by clicking it, as a user does."""
    field = (f"document.getElementById(Array.from(document.querySelectorAll('label'))"
             f".find(l => l.textContent === {label!r}).htmlFor)")
    item = f"Array.from(document.querySelectorAll('[role=option]')).find(e => e.textContent === {option!r})"
    for element in (field, item):
        click(browser, element)


def test_a_camera_with_a_lens_scales_to_a_smaller_frame(tmp_path):
    """`scaled` (the viewer's low-resolution frames, scripts/view_bench.py) on a dataset camera with a lens: it
    multiplied the whole intrinsics row (11 numbers then) by 4 factors and failed; now the focal lengths and principal
    point scale, the lens stays, and the half-size frame's rays are the full frame's at its pixel corners' mean."""
    from boostnerf_cli.render.rays import image_rays
    from boostnerf_cli.scenes import load_scene, make_scene
    from boostnerf_cli.viewpoint.camera import scaled

    split = load_scene(make_scene(tmp_path / "s", size=16, n_train=2, n_test=1, layout="nerfstudio",
                                  lens="opencv")).splits["train"]
    camera = dataset_camera(split, 0)
    small = scaled(camera, 8)
    assert (small.height, small.width) == (8, 8)
    k, k2 = split.camera(0), Intrinsics.of(small.intrinsics)
    assert k2.lens == k.lens and k2.fx == pytest.approx(k.fx / 2) and k2.cx == pytest.approx(k.cx / 2)
    _, d = image_rays(small.pose, small.intrinsics, 8, 8)
    assert torch.isfinite(d).all() and d.shape == (64, 3)


# --- the viewer's states, without a browser -------------------------------------------------------------------------
def _camera(viewer, shift: float = 0.0):
    pose = opencv_pose(viewer.scene.split("train").poses[2])
    return camera_for_view(pose[:3, :3], pose[:3, 3] + shift, 0.8, 1.0, viewer.size)


def test_a_page_goes_from_preview_to_full_frame_and_back_on_any_change(viewer):
    """One page: no camera, nothing due; a move: a low-resolution frame (a quarter a side); shown, nothing until the
    camera is still; then the full frame; then nothing; a new map: due again. A frame rendered for a camera the page
    has since left is shown but leaves it due."""
    viewer.connect(1)
    t = 100.0
    assert viewer.clients[1].phase is Phase.WAITING and viewer.next_job(now=t) is None
    assert viewer.moved(1, _camera(viewer), now=t)
    job = viewer.next_job(now=t)
    assert viewer.clients[1].phase is Phase.MOVED and not job.full
    assert job.camera.height == max(16, viewer.size // PREVIEW)
    viewer.drawn(job, viewer.draw(job.camera))
    assert viewer.clients[1].phase is Phase.PREVIEWED and viewer.next_job(now=t + 0.01) is None
    job = viewer.next_job(now=t + STILL)
    assert job.full and job.camera.height == viewer.size
    viewer.drawn(job, viewer.draw(job.camera))
    assert viewer.clients[1].phase is Phase.SHOWN and viewer.clients[1].last[0] is job.camera
    assert viewer.next_job(now=t + 10) is None
    assert viewer.show(Look("routing"))
    assert viewer.clients[1].phase is Phase.MOVED and viewer.next_job(now=t + 10).full
    stale = viewer.next_job(now=t + 10)
    viewer.moved(1, _camera(viewer, 0.1), now=t + 10)
    viewer.drawn(stale, viewer.draw(stale.camera))
    assert viewer.clients[1].phase is Phase.MOVED


def test_a_page_that_keeps_moving_does_not_starve_the_others(viewer):
    """Two pages: page 1 moves again after each of its frames, page 2 moved once: page 2's frame comes second, not
    after page 1 stops (the old loop served the first page of the list whenever it had a frame due)."""
    for cid in (1, 2):
        viewer.connect(cid)
    viewer.moved(1, _camera(viewer), now=10.0)
    viewer.moved(2, _camera(viewer, 0.2), now=10.1)
    served = []
    for k in range(4):
        job = viewer.next_job(now=10.2 + k * 0.01)
        served.append(job.client)
        viewer.drawn(job, viewer.draw(job.camera))
        viewer.moved(1, _camera(viewer, 0.01 * (k + 1)), now=10.2 + k * 0.01)  # page 1 never stops
    assert served[:2] == [1, 2], served
    assert viewer.next_job(connected={1}, now=20.0).client == 1  # a page gone is not drawn for


def test_a_page_snapped_to_a_dataset_view_stays_there_while_it_reports_moving_there(viewer):
    """go to view N pins the page: its full frame is shown at once; the cameras it reports on its way there are not
    moves (within SNAP seconds, or close to the view's); a camera elsewhere after that is."""
    viewer.connect(3)
    snap = viewer.go_to("train", 1, client=3)
    view = viewer.clients[3]
    assert view.pinned == ("train", 1) and view.phase is Phase.SHOWN and view.last == (snap.camera, snap.shot)
    assert not viewer.moved(3, _camera(viewer), now=view.changed_at + SNAP / 2)
    assert view.pinned == ("train", 1) and viewer.next_job(now=view.changed_at + 1) is None
    assert viewer.moved(3, _camera(viewer), now=view.changed_at + SNAP + 1)
    assert view.pinned is None and view.phase is Phase.MOVED


def test_layers_and_their_nodes_are_held_once_by_the_page(served):
    """A layer hidden stays hidden when its node is drawn again (a new model's box and cells): each scene node is
    held once (`Nodes`), drawn as the viewer's `layers` say; the old node is removed, not left beside the new one."""
    viewer, page = served
    cells = page.nodes.cells
    assert cells is not None and not cells.visible  # off until ticked: the kept cells fill the subject
    page.set_layer("cells", True)
    assert viewer.layers["cells"] is True and cells.visible
    page.set_layer("cells", False)
    assert viewer.layers["cells"] is False and not cells.visible and page.nodes.box.visible
    page.set_layer("box", False)
    page.draw_model_parts()  # what a new model does
    assert page.nodes.cells is not cells and not page.nodes.cells.visible and not page.nodes.box.visible
    assert page.server.scene.get_handle_by_name("/cells") is page.nodes.cells
    page.set_layer("cells", True)
    assert page.nodes.cells.visible
    with pytest.raises(BoostNerfError, match="unknown layer"):
        viewer.set_layer("grid", True)


def test_a_checkpoint_is_read_through_the_task_code(mixture_ws, tmp_path):
    """An expert in training is read from its checkpoint with `models.new_expert` and `tasks.load_field_state`, its
    step the recipe's step_ratio: the same field and skip as the finished expert's file."""
    from boostnerf_cli.tasks import load_field_state
    from boostnerf_cli.viewpoint.viewer import checkpoint_model

    ws = Workspace(mixture_ws)
    finished = load_model(ws, "dvgo-12", "cpu")
    state = {"meta": finished.field.config_dict(), "model": finished.field.state_dict(),
             "skip": None, "skip_bbox": None}
    ws.checkpoints_dir.mkdir(parents=True, exist_ok=True)
    torch.save({"task": state, "signature": {}}, ws.checkpoint_path("dvgo-12"))
    read = checkpoint_model(ws, "dvgo-12", "cpu")
    assert read.name == "dvgo-12 (training)" and read.step == pytest.approx(finished.step)
    for k, v in finished.field.state_dict().items():
        assert torch.equal(read.field.state_dict()[k], v)
    assert load_field_state(read.field, state) is None


# --- the first view, the frustums' and the cells' sizes ---------------------------------------------------------------
def test_the_first_view_is_a_training_camera_looking_at_its_subject(served):
    """The page opens at the training camera `first_view` picks, with its field of view and up, looking down its
    axis at the subject (the sphere rig's cameras all look at it); go to view N stands at that view likewise."""
    viewer, page = served
    train = viewer.scene.split("train")
    k = first_view(train.poses)
    camera = dataset_camera(train, k)
    pose = camera.pose.double().numpy()
    start = page.server.initial_camera
    assert np.allclose(start.position, pose[:3, 3], atol=1e-6) and start.fov == pytest.approx(fov_of(camera))
    assert np.allclose(start.up, pose[:3, 1], atol=1e-6)
    axis = (start.look_at - start.position) / np.linalg.norm(start.look_at - start.position)
    assert axis @ -pose[:3, 2] > 1 - 1e-9
    assert np.linalg.norm(start.look_at - viewer.subject) < 1e-3 * np.linalg.norm(start.position - viewer.subject)
    assert np.linalg.norm(viewer.subject) < 0.05  # the procedural cameras look at the world's origin
    test = dataset_camera(viewer.scene.split("test"), 1)
    eye = viewer.eye("test", 1)
    assert np.allclose(eye.position, test.pose[:3, 3].double().numpy()) and eye.fov == pytest.approx(fov_of(test))


def test_the_first_view_is_the_camera_nearest_the_cameras_mean_direction():
    """A walk part way round: its middle view; cameras all round at one height (no mean direction to speak of): the
    first of them."""
    from boostnerf_cli.render.paths import look_at

    def arc(degrees):
        return torch.stack([look_at(torch.tensor([4 * np.sin(a), -4 * np.cos(a), 1.0], dtype=torch.float64),
                                    torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0, 1], dtype=torch.float64))
                            for a in np.radians(degrees)])

    assert first_view(arc([-70, -40, -20, 0, 25, 45, 60])) == 3
    assert first_view(arc(np.arange(0, 360, 30))) == 0


def frustum_cover(poses: np.ndarray, fov: float, size: float) -> np.ndarray:
    """For each camera (OpenGL poses (N, 4, 4), square images, vertical field of view `fov`): the share of its image
    the other cameras' frustums `size` deep cover (each its projected bounding box; those `hidden_frustums` hides
    are not drawn), over the whole image and over its central half -> (N, 2)."""
    t, n = np.tan(fov / 2), 200
    corners = [np.zeros(3)] + [np.array([sx * t, sy * t, -1.0]) * size for sx in (-1, 1) for sy in (-1, 1)]
    out = []
    for pose in poses:
        hidden = hidden_frustums(poses[:, :3, 3], [pose[:3, 3]], size)
        to_camera = np.linalg.inv(pose)
        cover = np.zeros((n, n), bool)
        for j in set(range(len(poses))) - hidden:
            points = np.array([poses[j, :3, :3] @ c + poses[j, :3, 3] for c in corners])
            local = points @ to_camera[:3, :3].T + to_camera[:3, 3]
            if (local[:, 2] >= 0).any():
                continue  # behind the camera, or beside it: not in its view
            xy = local[:, :2] / (-local[:, 2:] * t)
            lo = np.clip(((xy.min(0) + 1) / 2 * n).astype(int), 0, n)
            hi = np.clip(np.ceil((xy.max(0) + 1) / 2 * n).astype(int), 0, n)
            cover[lo[1]:hi[1], lo[0]:hi[0]] = True
        out.append((cover.mean(), cover[n // 4:3 * n // 4, n // 4:3 * n // 4].mean()))
    return np.array(out)


def test_frustums_are_sized_by_the_cameras_spacing_and_leave_every_view_clear():
    """The frustums' depth follows the scene's scale (ten times larger: ten times deeper), and from every view of the
    procedural sphere and ring rigs (24 training and 8 held-out cameras) the frustums drawn cover (their bounding
    boxes) under 8% of the image and 12% of its middle; four times as deep, they would cover a fifth of it."""
    from boostnerf_cli.render.paths import focus_point
    from boostnerf_cli.scenes.procedural import CAMERA_ANGLE_X, RING_ANGLE_X, camera_poses, ring_poses

    for poses_of, fov in ((camera_poses, CAMERA_ANGLE_X), (ring_poses, RING_ANGLE_X)):
        train, test = poses_of(24, 8)
        poses = np.concatenate([train, test]).astype(np.float64)
        target = focus_point(torch.as_tensor(train, dtype=torch.float64)).numpy()
        size = frustum_size(poses[:, :3, 3], target)
        assert frustum_size(10 * poses[:, :3, 3], 10 * target) == pytest.approx(10 * size)
        assert frustum_size(poses[:, :3, 3] + 100.0, target + 100.0) == pytest.approx(size)
        cover = frustum_cover(poses, fov, size)
        assert cover[:, 0].max() < 0.08 and cover[:, 1].max() < 0.12, (poses_of.__name__, cover.max(0))
        assert frustum_cover(poses, fov, 4 * size)[:, 0].max() > 0.2


def test_the_frustum_at_a_pages_camera_is_not_drawn(served):
    """A page standing at a dataset camera (its first view, go to view N) does not see that camera's frustum in
    front of it (its own image would fill the view); the page moved on, the frustum is drawn again."""
    viewer, page = served
    train = viewer.scene.split("train")
    k = first_view(train.poses)
    pose = opencv_pose(train.poses[k])
    viewer.moved(7, camera_for_view(pose[:3, :3], pose[:3, 3], 0.8, 1.0, viewer.size))
    page.hide_frustums()
    assert k in page.nodes.hidden and not page.nodes.frustums[k].visible
    assert len(page.nodes.hidden) < len(page.nodes.frustums) // 2 and all(
        f.visible for i, f in enumerate(page.nodes.frustums) if i not in page.nodes.hidden)
    far = viewer.subject + 10 * (pose[:3, 3] - viewer.subject)
    viewer.moved(7, camera_for_view(pose[:3, :3], far, 0.8, 1.0, viewer.size), now=time.monotonic() + 1)
    page.hide_frustums()
    assert page.nodes.hidden == set() and page.nodes.frustums[k].visible


def test_an_unbounded_volumes_cells_are_drawn_in_the_world_at_their_size():
    """A density volume over an unbounded scene's contracted box (every cell kept, the gate picking by side): the
    cells drawn are those of the sphere kept linear, where a contracted point is the world point (the shell's hold
    the rest of the world squashed: not drawn), each `CELL_SHARE` of its cell's side wide; scaled by 10, the scene's
    cells are drawn 10 times wider. A bounded scene's box draws all its cells."""
    from types import SimpleNamespace

    from boostnerf_cli.moe.density_volume import DensityVolume
    from boostnerf_cli.render.contraction import Contraction
    from boostnerf_cli.viewpoint.geometry import routed_cells

    def drawn(contraction: Contraction, bounded: bool = False):
        box = contraction.box()
        vd = DensityVolume(box, 12)
        mix = SimpleNamespace(vd=vd, m=2, skip=lambda p: torch.ones(len(p), dtype=torch.bool),
                              gate=SimpleNamespace(logits=lambda p: torch.stack([p[:, 0], -p[:, 0]], -1)))
        return vd, routed_cells(mix, None if bounded else contraction)

    contraction = Contraction((0.5, -1.0, 2.0), 1.5, 1500.0)
    vd, (points, colours, width) = drawn(contraction)
    centre = np.array(contraction.centre)
    distance = np.linalg.norm(points - centre, axis=-1)
    assert distance.max() <= contraction.radius + 1e-5 and len(points) > 0.03 * vd.table.shape[0]
    world = contraction.uncontract(torch.from_numpy(points).double()).numpy()
    assert np.allclose(world, points, atol=1e-5)  # where they are in the world
    side = float(vd.bbox[1, 0] - vd.bbox[0, 0]) / (vd.shape[0] - 1)
    assert width == pytest.approx(CELL_SHARE * side, rel=1e-4) and len(points) < vd.table.shape[0] / 4
    assert len({tuple(c) for c in colours}) == 2
    bigger = Contraction(tuple(10 * centre), 10 * contraction.radius, 10 * contraction.far)
    assert drawn(bigger)[1].width == pytest.approx(10 * width, rel=1e-4)
    assert len(drawn(contraction, bounded=True)[1].points) == vd.table.shape[0]
    edges = box_edges(world_box(vd.bbox, contraction))
    assert np.allclose(edges.min((0, 1)), centre - 1.5) and np.allclose(edges.max((0, 1)), centre + 1.5)


@pytest.fixture(scope="module")
def unbounded_scene(tmp_path_factory):
    from boostnerf_cli.scenes import make_scene

    return make_scene(tmp_path_factory.mktemp("unbounded") / "scene", size=32, n_train=12, n_test=2, seed=0,
                      layout="nerfstudio", rig="unbounded")


def unbounded_mixture(folder: Path, scene: Path, **pretrain) -> Path:
    """A workspace on the unbounded capture (contracted): two tiny experts (`pretrain` changes the tiny recipe's
    pretrain section) and top2, 5 steps."""
    from conftest import make_recipe

    recipe = make_recipe(folder / "unbounded.yaml", data={"scene": "unbounded"}, pretrain=pretrain)
    ws = str(folder / "ws")
    run_cli("pretrain", "--data", str(scene), "--recipe", str(recipe), "--workspace", ws, "--device", "cpu",
            check=True)
    run_cli("build-moe", "--workspace", ws, "--device", "cpu", check=True)
    run_cli("finetune", "--workspace", ws, "--topk", "2", "--iters", "5", "--device", "cpu", check=True)
    return folder / "ws"


# the colours the page draws over the render: train and held-out frustums, the box, the cells (`maps.PALETTE`)
OVERLAY = np.array([(40, 90, 230), (230, 120, 30), (250, 160, 40), (40, 90, 255), (0, 200, 220), (60, 200, 60),
                    (255, 160, 0), (230, 30, 30)])
SHOWS_VIEW = 12.0  # mean absolute difference (0-255, 16x16 averages) under which the canvas shows a view's render


def shows_view(browser, reference: np.ndarray, seconds: float = 30.0) -> tuple[float, float]:
    """How far the middle of the page's canvas (a square half its height a side, about its centre) is from the same
    part of `reference`, the model's render of the view the page should show (a camera of the page's vertical field
    of view: its square middle is the canvas's), once the canvas shows it (a loaded machine draws a frame a while
    after it arrives; after `seconds` the last look) -> (mean absolute difference (0-255) of the two averaged down
    to 16x16, the share of the square's pixels in the colours drawn over the render: frustums, box, cells)."""
    import imageio.v3 as iio
    import torch.nn.functional as F

    def small(image: np.ndarray) -> np.ndarray:
        t = torch.from_numpy(np.ascontiguousarray(image[..., :3])).double().permute(2, 0, 1)[None]
        return F.interpolate(t, size=(16, 16), mode="area")[0].numpy()

    h = reference.shape[0]
    want = small(reference[h // 4:h - h // 4, reference.shape[1] // 2 - h // 4:reference.shape[1] // 2 + h // 4])
    deadline = time.monotonic() + seconds
    while True:
        x, y, width, height = browser.js("""(() => {
            const r = Array.from(document.querySelectorAll('canvas'))
                .reduce((a, b) => (b.width * b.height > a.width * a.height ? b : a)).getBoundingClientRect();
            return [r.x, r.y, r.width, r.height];
        })()""")
        side = height / 2
        shot = iio.imread(browser.screenshot((x + width / 2 - side / 2, y + height / 4, side, side)))[..., :3]
        far = np.abs(small(shot) - want).mean()
        overlay = (np.abs(shot[:, :, None, :].astype(int) - OVERLAY[None, None]).max(-1) <= 30).any(-1).mean()
        if far < SHOWS_VIEW or time.monotonic() > deadline:
            print(f"canvas against the view's render: {far:.1f} apart, {100 * overlay:.1f}% overlay colours")
            return float(far), float(overlay)
        time.sleep(0.5)


@pytest.mark.slow
def test_the_first_view_in_chromium_is_a_training_views_render_unobstructed(unbounded_scene, tmp_path):
    """On the unbounded capture (contracted; a mixture trained briefly), the first frame the browser shows is the
    render of the training view `first_view` picks: the page reports that camera and its field of view, and the
    middle of its canvas is the model's own render of the view, not the frustums, box or cells drawn over it (the
    first view stood behind the first camera, with a field of view of its own, the cells as large squares all over
    it). Go to view N shows view N's render the same way. The mixture's cells drawn are in the sphere kept linear."""
    from cdp import INSTALL, Browser, chromium_binary

    from boostnerf_cli.viewpoint.camera import scaled

    binary = chromium_binary()
    if binary is None:
        unavailable("Chromium", INSTALL)
    ws = Workspace(unbounded_mixture(tmp_path, unbounded_scene, iters=150, train={"batch_rays": 1024},
                                     dvgo={"hidden": 32}))
    viewer = view.Viewer(ws, Survey(ws).scene(), view.Models(ws, "cpu"))
    train = viewer.scene.split("train")
    k = first_view(train.poses)
    n = (k + len(train) // 2) % len(train)  # across the ring
    reference = {i: viewer.draw(scaled(dataset_camera(train, i), 128)).image for i in (k, n)}
    page = view.start_server(viewer, "127.0.0.1", 0)
    stop = threading.Event()
    loop = threading.Thread(target=view.serve, args=(page, stop), daemon=True)
    loop.start()
    browser = Browser(binary)
    try:
        browser.open(f"http://127.0.0.1:{page.server.get_port()}/")
        wait_for(lambda: shown_full(page, "top2"), "the first full frame")
        browser.js("document.querySelectorAll('.mantine-Notification-root button').forEach(b => b.click())")
        first = shows_view(browser, reference[k])
        if os.environ.get(SCREENSHOT_ENV):
            Path(os.environ[SCREENSHOT_ENV]).write_bytes(browser.screenshot())
        reported = next(iter(viewer.clients.values())).camera
        page.controls.view.value = n
        press(browser, "go to view N")
        wait_for(lambda: f"train view {n}**" in page.controls.truth.content, "the dataset view's PSNR")
        time.sleep(2.0)  # the page moves to the view
        then = shows_view(browser, reference[n])
    finally:
        browser.close()
        stop.set()
        loop.join(timeout=30)
        page.server.stop()
    camera = dataset_camera(train, k)
    assert torch.allclose(reported.pose, camera.pose, atol=1e-3), (reported.pose, camera.pose)
    assert fov_of(reported) == pytest.approx(fov_of(camera), rel=1e-3)
    for i, (far, overlay) in ((k, first), (n, then)):
        middle = reference[i][32:96, 32:96].astype(float)
        assert middle.std() > 10  # the view's middle shows something to match
        assert far < SHOWS_VIEW and overlay < 0.05, (i, far, overlay)
    contraction, points = viewer.scene.contraction, viewer.model_parts()[1].points
    assert len(points) and np.linalg.norm(points - np.array(contraction.centre), axis=-1).max() <= contraction.radius
