"""`boostnerf view` and `render --camera`: the page's scene, what a camera renders, switching model and map, saved
views rendered again, following training, bad input, and one test in a real (headless) browser."""

from __future__ import annotations

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
    points, colours = viewer.model_parts()[1]
    assert server.scene.get_handle_by_name("/cells") is not None and len(points) > 0
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
    """The 3D canvas, cut from the page beside the control panel, shows the viewer's frame: picking depth in the page
    changes the canvas over much of its area; picking another model draws that model. The same canvas hidden (blank)
    fails that check, though the whole page, its panel, would pass it."""
    from cdp import INSTALL, Browser, chromium_binary

    binary = chromium_binary()
    if binary is None:
        unavailable("Chromium", INSTALL)
    viewer, page = served
    browser = Browser(binary)
    try:
        browser.open(f"http://127.0.0.1:{page.server.get_port()}/")
        first = wait_for(lambda: shown_full(page, "top2"), "the first full frame")
        browser.js("document.querySelectorAll('.mantine-Notification-root button').forEach(b => b.click())")
        time.sleep(1.0)  # the frame reaches the page; the browser's notice (software WebGL) is closed
        if os.environ.get(SCREENSHOT_ENV):
            Path(os.environ[SCREENSHOT_ENV]).write_bytes(browser.screenshot())
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
    assert cells is not None and cells.visible
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
