"""Cameras as they are: lenses (distortion read and rays bent through it), COLMAP models as a format, bounds from
their sparse points, and `boostnerf capture` from photos or a video to a scene folder."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from boostnerf_cli.cameras import (
    CHECK_EVERY,
    GRIDS,
    MODELS,
    PINHOLE,
    WITH_LENS,
    WITH_RATIONAL,
    Intrinsics,
    Lens,
    rendered_models,
    rows,
)
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.render.rays import image_rays, pixel_directions, project_points
from boostnerf_cli.scenes import load_scene, make_scene
from boostnerf_cli.scenes.colmap_model import ModelCamera, read_model, write_model
from boostnerf_cli.scenes.procedural import LENSES
from tests.conftest import REMOVE, cli_in_process, make_recipe, need_pycolmap, run_cli

LENSES_TRIED = {
    "opencv": Lens(k1=-0.3, k2=0.1, p1=0.003, p2=-0.002),
    "opencv-k3": Lens(k1=-0.25, k2=0.08, k3=-0.02, p1=0.001, p2=0.002),
    "pincushion": Lens(k1=0.2, k2=0.05),
    "full-opencv": Lens(k1=-0.2, k2=0.05, k3=0.01, p1=0.002, p2=-0.001, d1=0.1, d2=-0.02, d3=0.005),
    "fisheye": Lens(k1=0.08, k2=-0.03, k3=0.01, k4=-0.002, fisheye=True),
}


@pytest.mark.parametrize("lens", LENSES_TRIED, ids=list(LENSES_TRIED))
def test_undistort_inverts_distort(lens):
    lens = LENSES_TRIED[lens]
    xy = torch.rand(2000, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 1.4 - 0.7
    assert (lens.undistort(lens.distort(xy)) - xy).abs().max() < 1e-10
    assert (lens.distort(xy) - xy).abs().max() > 1e-3  # the lens does bend


@pytest.mark.parametrize("lens", [k for k, v in LENSES_TRIED.items() if not v.fisheye])
def test_the_analytic_jacobian_is_the_distortions_derivative(lens):
    lens = LENSES_TRIED[lens]
    xy = torch.rand(500, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 1.4 - 0.7
    (a, b), (c, d) = lens.jacobian(xy)
    eps = 1e-6
    for axis, (dx, dy) in ((0, (a, c)), (1, (b, d))):
        step = torch.zeros(2, dtype=torch.float64)
        step[axis] = eps
        numeric = (lens.distort(xy + step) - lens.distort(xy - step)) / (2 * eps)
        assert torch.allclose(numeric, torch.stack([dx, dy], -1), atol=1e-7)


def test_the_camera_models_are_colmaps():
    """Every model of `cameras.MODELS`: COLMAP's id and parameter names in its order (pycolmap's `params_info`)."""
    pycolmap = need_pycolmap()
    for m in MODELS.values():
        cam = pycolmap.Camera.create_from_model_name(1, m.name, 100.0, 64, 48)
        assert int(cam.model.value) == m.colmap_id, m.name
        assert tuple(cam.params_info.split(", ")) == m.params, m.name
    assert rendered_models() == ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE",
                                 "FULL_OPENCV", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE")


# a camera of each model boostnerf renders, with COLMAP's parameters (in its order) of a strong phone-like lens
COLMAP_CAMERAS = {
    "SIMPLE_PINHOLE": [100, 32, 24], "PINHOLE": [100, 110, 32, 24], "SIMPLE_RADIAL": [100, 32, 24, -0.15],
    "RADIAL": [100, 32, 24, -0.2, 0.05], "OPENCV": [100, 110, 32, 24, -0.2, 0.05, 0.002, -0.001],
    "OPENCV_FISHEYE": [100, 110, 32, 24, 0.08, -0.03, 0.01, -0.002],
    "FULL_OPENCV": [100, 110, 32, 24, -0.2, 0.05, 0.002, -0.001, 0.01, 0.1, -0.02, 0.005],
    "SIMPLE_RADIAL_FISHEYE": [100, 32, 24, 0.05], "RADIAL_FISHEYE": [100, 32, 24, 0.05, -0.01],
}


@pytest.mark.parametrize("model", COLMAP_CAMERAS)
def test_distortion_and_undistortion_are_colmaps(model):
    """Each model boostnerf renders: the pixel COLMAP's own camera gives for a camera-space point (`img_from_cam`),
    and the normalized point it gives for a pixel (`cam_from_img`, its undistortion)."""
    pycolmap = need_pycolmap()
    cam = pycolmap.Camera.create_from_model_name(1, model, 100.0, 64, 48)
    cam.params = COLMAP_CAMERAS[model]
    ours = Intrinsics.from_colmap(model, COLMAP_CAMERAS[model], "test")
    assert ours.colmap(model) == pytest.approx(COLMAP_CAMERAS[model])
    xy = np.random.default_rng(0).uniform(-0.5, 0.5, (50, 2))
    assert np.abs(cam.img_from_cam(np.c_[xy, np.ones(len(xy))]) - ours.pixels(torch.tensor(xy)).numpy()).max() < 1e-9
    uv = np.random.default_rng(1).uniform([0, 0], [64, 48], (200, 2))
    theirs = cam.cam_from_img(uv)
    theirs = theirs[:, :2] / theirs[:, 2:] if theirs.shape[1] == 3 else theirs
    assert np.abs(ours.normalized(torch.tensor(uv)).numpy() - theirs).max() < 1e-9, model


def test_full_opencv_reads_and_renders_through_its_rational_terms(tmp_path):
    """FULL_OPENCV (refused before whenever k4, k5, k6 were set): a COLMAP model with one loads, its rays go through
    the rational distortion and project back to their pixels."""
    params = COLMAP_CAMERAS["FULL_OPENCV"]
    k = Intrinsics.from_colmap("FULL_OPENCV", params, "test")
    assert k.lens == Lens(k1=-0.2, k2=0.05, k3=0.01, p1=0.002, p2=-0.001, d1=0.1, d2=-0.02, d3=0.005)
    pose = torch.eye(4)
    pose[:3, 3] = torch.tensor([0.3, -0.2, 4.0])
    o, d = image_rays(pose, k, 48, 64)
    uv, _ = project_points(o + 3.0 * d, pose, k)
    v, u = torch.meshgrid(torch.arange(48) + 0.5, torch.arange(64) + 0.5, indexing="ij")
    assert torch.allclose(uv, torch.stack([u.reshape(-1), v.reshape(-1)], -1), atol=1e-3)
    folder = make_scene(tmp_path / "s", size=32, n_train=6, n_test=1, layout="colmap", lens="opencv")
    model = read_model(folder / "sparse" / "0")
    cam = model.cameras[1]
    model.cameras[1] = ModelCamera("FULL_OPENCV", cam.width, cam.height, cam.params + [0.0, 0.05, 0.0, 0.0])
    write_model(model, folder / "sparse" / "0", "bin")
    row = load_scene(folder).splits["train"].intrinsics[0]
    assert Intrinsics.of(row).lens.d1 == pytest.approx(0.05)


def test_per_image_cameras_keep_their_undistorted_grids():
    """The undistorted pixel grids are kept per camera within a byte budget: a split of 40 cameras, each its own, is
    undistorted once, not once a pass (an LRU of 16 grids recomputed every one of them on every pass)."""
    GRIDS.grids.clear()
    cams = [Intrinsics(50.0 + i, 50.0 + i, 16.0, 12.0, Lens(k1=-0.1 - 0.001 * i)) for i in range(40)]
    calls = []
    real = Intrinsics.normalized
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Intrinsics, "normalized", lambda self, uv: calls.append(1) or real(self, uv))
        for _ in range(3):
            for c in cams:
                pixel_directions(24, 32, c)
    assert len(calls) == 40


def test_undistortion_reads_its_residual_every_few_steps_only(monkeypatch):
    """Newton's steps run without waiting for the device: the residual is read once every `CHECK_EVERY` steps."""
    reads = []
    real = torch.Tensor.__float__
    monkeypatch.setattr(torch.Tensor, "__float__", lambda t: reads.append(1) or real(t))
    lens = LENSES_TRIED["opencv"]
    lens.undistort(torch.rand(100, 2, dtype=torch.float64) - 0.5, iterations=40)
    assert len(reads) <= 40 // CHECK_EVERY


@pytest.mark.parametrize("model", COLMAP_CAMERAS)
def test_every_camera_model_through_the_reader_projects_as_colmap_does(model, tmp_path):
    """A camera of each model written by pycolmap's own writer, read by the model reader and turned into intrinsics by
    the loaders' table (`Intrinsics.from_colmap`): points project to the pixels pycolmap's `img_from_cam` gives, and
    the rays through pixels go where its `cam_from_img` says."""
    pycolmap = need_pycolmap()
    cam = pycolmap.Camera.create_from_model_name(1, model, 100.0, 64, 48)
    cam.params = COLMAP_CAMERAS[model]
    written = pycolmap.Reconstruction()
    written.add_camera_with_trivial_rig(cam)
    written.write_binary(str(tmp_path))
    read = read_model(tmp_path).cameras[1]
    k = Intrinsics.from_colmap(read.model, read.params, "test")
    assert (k.lens is not None) == ("PINHOLE" not in model)  # a lens is read wherever the model has one
    xy = np.random.default_rng(0).uniform([-0.35, -0.25], [0.35, 0.25], (200, 2))  # OpenCV axes, z = 1
    points = torch.tensor(np.c_[xy[:, 0], -xy[:, 1], -np.ones(len(xy))], dtype=torch.float32)  # OpenGL axes
    uv, _ = project_points(points, torch.eye(4), k)
    assert np.abs(uv.double().numpy() - cam.img_from_cam(np.c_[xy, np.ones(len(xy))])).max() < 2e-3, model
    _, d = image_rays(torch.eye(4), k, 48, 64)
    grid = np.stack(np.meshgrid(np.arange(64) + 0.5, np.arange(48) + 0.5), -1).reshape(-1, 2)
    ours = d.double().numpy()
    ours = np.c_[ours[:, 0] / -ours[:, 2], -ours[:, 1] / -ours[:, 2]]
    theirs = cam.cam_from_img(grid)
    theirs = theirs[:, :2] / theirs[:, 2:] if theirs.shape[1] == 3 else theirs
    assert np.abs(ours - theirs).max() < 1e-4, model


def test_rays_through_a_lens_project_back_to_their_pixels():
    pose = torch.eye(4)
    pose[:3, 3] = torch.tensor([0.3, -0.2, 4.0])
    k = Intrinsics(50.0, 55.0, 16.0, 12.0, LENSES_TRIED["opencv"])
    o, d = image_rays(pose, k, 24, 32)
    uv, depth = project_points(o + 3.0 * d, pose, k)
    v, u = torch.meshgrid(torch.arange(24) + 0.5, torch.arange(32) + 0.5, indexing="ij")
    assert torch.allclose(uv, torch.stack([u.reshape(-1), v.reshape(-1)], -1), atol=1e-3)
    pinhole = image_rays(pose, Intrinsics(50.0, 55.0, 16.0, 12.0), 24, 32)[1]
    assert (pinhole - d).norm(dim=-1).max() > 0.01  # the corners' rays differ from a pinhole camera's
    row = torch.tensor(k.row(), dtype=torch.float64)
    assert torch.equal(image_rays(pose, row, 24, 32)[1], d)  # a split's row is the same camera


@pytest.fixture(scope="module")
def colmap_scene(tmp_path_factory) -> Path:
    return make_scene(tmp_path_factory.mktemp("colmap") / "s", size=32, n_train=10, n_test=2, layout="colmap",
                      lens="opencv")


def test_a_colmap_model_loads_as_the_scene_it_was_written_from(colmap_scene, tmp_path):
    """make-scene's COLMAP layout (binary, an OPENCV lens) against its nerfstudio layout of the same views: the same
    cameras, lens and images; the text form of the model loads the same; each recorded keypoint is where its point
    projects through the lens."""
    scene = load_scene(colmap_scene)
    twin = load_scene(make_scene(tmp_path / "ns", size=32, n_train=10, n_test=2, layout="nerfstudio", lens="opencv"))
    assert scene.format == "colmap" and scene.extra["detected"].startswith("colmap")
    for name in ("train", "test"):
        a, b = scene.splits[name], twin.splits[name]
        assert torch.allclose(a.poses, b.poses, atol=1e-5) and torch.allclose(a.intrinsics, b.intrinsics, atol=1e-4)
        assert (a.images - b.images).abs().max() <= 2 / 255 + 1e-6  # on white before 8-bit rounding
    assert scene.splits["train"].camera(0).lens == Lens(**{k: float(torch.tensor(v, dtype=torch.float32))
                                                          for k, v in LENSES["opencv"][0].items()})
    text = shutil.copytree(colmap_scene, tmp_path / "txt")
    model = read_model(text / "sparse" / "0")
    for f in (text / "sparse" / "0").iterdir():
        f.unlink()
    write_model(model, text / "sparse" / "0", "txt")
    again = load_scene(text)
    assert torch.equal(again.points.xyz, scene.points.xyz)
    assert torch.allclose(again.splits["train"].poses, scene.splits["train"].poses)
    image = model.images[3]  # image002: train view 1 (view 0 is held out)
    pose = scene.splits["train"].poses[1]
    seen = image.point_ids >= 0
    index = {int(p): i for i, p in enumerate(model.point_ids)}
    pts = torch.tensor(model.xyz[[index[int(p)] for p in image.point_ids[seen]]], dtype=torch.float32)
    uv, _ = project_points(pts, pose, scene.splits["train"].intrinsics[1])
    assert np.abs(uv.numpy() - image.xys[seen]).max() < 1e-3
    rows = scene.points.visible["train"]
    assert set(rows[rows[:, 0] == 1, 1].tolist()) == {index[int(p)] for p in image.point_ids[seen]}


def test_bounds_come_from_the_sparse_points(colmap_scene):
    """Around an object the box holds the points the views see (the floor disc of radius 1 and the solids): tighter
    than the box the cameras alone give, and the scene says where it came from."""
    scene = load_scene(colmap_scene)
    assert scene.ndc is None and scene.extra["box_from"].startswith("the sparse points")
    lo, hi = scene.bbox
    assert (lo < torch.tensor([-0.95, -0.95, -0.5])).all() and (hi > torch.tensor([0.95, 0.95, 0.1])).all()
    assert (lo > torch.tensor([-1.3, -1.3, -0.8])).all() and (hi < torch.tensor([1.3, 1.3, 0.6])).all()
    depth_far = max(float((p[:3, 3]).norm()) for p in scene.splits["train"].poses) + 1.25
    assert scene.near > 1.5 and scene.far <= 1.2 * depth_far


def test_a_forward_facing_colmap_capture_is_sampled_in_ndc(tmp_path):
    scene = load_scene(make_scene(tmp_path / "f", size=32, n_train=10, n_test=2, layout="colmap", rig="forward"))
    assert scene.ndc is not None and scene.extra["forward_facing"]
    bounds = np.array(scene.extra["bounds"])
    assert (bounds[:, 0] >= 1 / 0.75 - 1e-6).all() and (bounds[:, 1] > bounds[:, 0]).all()


def test_a_point_only_two_photos_see_does_not_set_a_forward_views_near_bound(tmp_path):
    """A two-view point far in front of the content leaves the depth bounds, and so the scale, the poses and the
    NDC box, as they were: bounds come from the points three or more photos see."""
    folder = make_scene(tmp_path / "f", size=32, n_train=10, n_test=2, layout="colmap", rig="forward")
    clean = load_scene(folder)
    model = read_model(folder / "sparse" / "0")
    assert min(len(t) for t in model.tracks) >= 3
    (a, first), (b, second) = list(model.images.items())[:2]
    centre = first.world_from_camera()[:3, 3]
    nearest = min(float(np.linalg.norm(x - centre)) for x in model.xyz)
    outlier = centre + 0.2 * nearest * first.world_from_camera()[:3, 2]  # on the first camera's axis, 5x nearer
    pid = int(model.point_ids.max()) + 1
    track = []
    for iid, image in ((a, first), (b, second)):
        track.append((iid, len(image.xys)))
        image.xys = np.concatenate([image.xys, [[16.0, 16.0]]])
        image.point_ids = np.concatenate([image.point_ids, [pid]])
    model.xyz = np.concatenate([model.xyz, [outlier]])
    model.rgb = np.concatenate([model.rgb, [[0, 0, 0]]]).astype(np.uint8)
    model.error = np.concatenate([model.error, [0.5]])
    model.point_ids = np.concatenate([model.point_ids, [pid]])
    model.tracks = [*model.tracks, np.array(track, dtype=np.int64)]
    write_model(model, folder / "sparse" / "0", "bin")
    again = load_scene(folder)
    assert len(again.points.xyz) == len(clean.points.xyz) + 1
    assert np.allclose(again.extra["bounds"], clean.extra["bounds"])
    assert torch.allclose(again.splits["train"].poses, clean.splits["train"].poses)
    assert torch.equal(again.bbox, clean.bbox)


def test_an_unsupported_colmap_camera_model_is_one_line(colmap_scene, tmp_path, monkeypatch, capsys):
    folder = shutil.copytree(colmap_scene, tmp_path / "fov")
    model = read_model(folder / "sparse" / "0")
    model.cameras[1] = ModelCamera("FOV", 32, 32, [44.0, 44.0, 16.0, 16.0, 0.9])
    write_model(model, folder / "sparse" / "0")
    code, err = cli_in_process(monkeypatch, capsys, "pretrain", "--data", str(folder), "--workspace",
                               str(tmp_path / "ws"), "--device", "cpu")
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1 and "camera model FOV is not supported" in lines[0], err


def test_frames_whose_photos_are_gone_are_left_out_with_a_count(tmp_path):
    folder = make_scene(tmp_path / "ns", size=16, n_train=12, n_test=2, layout="nerfstudio")
    for name in ("frame_00003.png", "frame_00007.png"):
        (folder / "images" / name).unlink()
    scene = load_scene(folder)
    assert len(scene.splits["train"]) + len(scene.splits["test"]) == 12
    assert any("2 of 14 frames of transforms.json name images that are not there" in w and "training on the other 12"
               in w for w in scene.extra["warnings"])
    for f in (folder / "images").iterdir():
        f.unlink()
    with pytest.raises(BoostNerfError, match="not found"):
        load_scene(folder)


# ----------------------------------------------------------------------------- capture: bad input, no SfM needed


def _photos(folder: Path, n: int, size=(40, 30)) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        iio.imwrite(folder / f"p{i:02d}.png", rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))
    return folder


def _refused(monkeypatch, capsys, tmp_path, *args, needle: str) -> str:
    out = tmp_path / "out"
    code, err = cli_in_process(monkeypatch, capsys, "capture", *args, "--out", str(out))
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], err
    assert not out.exists()  # nothing a later stage would take for a scene
    return lines[0]


def test_capture_refuses_bad_photos_in_one_line(tmp_path, monkeypatch, capsys):
    need_pycolmap()
    (tmp_path / "empty").mkdir()
    _refused(monkeypatch, capsys, tmp_path, "--images", str(tmp_path / "empty"), needle="holds no photos")
    _refused(monkeypatch, capsys, tmp_path, "--images", str(_photos(tmp_path / "two", 2)), needle="at least 3")
    mixed = _photos(tmp_path / "mixed", 3)
    iio.imwrite(mixed / "p09.png", np.zeros((20, 20, 3), np.uint8))
    _refused(monkeypatch, capsys, tmp_path, "--images", str(mixed), needle="one capture needs photos of one size")
    broken = _photos(tmp_path / "broken", 3)
    (broken / "p01.png").write_bytes(b"not a png")
    _refused(monkeypatch, capsys, tmp_path, "--images", str(broken), needle="cannot read photo")
    cut = tmp_path / "cut"  # a JPEG cut short, as an interrupted copy leaves it: its header reads, its pixels do not
    cut.mkdir()
    for i, photo in enumerate(np.random.default_rng(1).integers(0, 255, (3, 60, 80, 3), dtype=np.uint8)):
        iio.imwrite(cut / f"p{i:02d}.jpg", photo, quality=90)
    whole = (cut / "p01.jpg").read_bytes()
    (cut / "p01.jpg").write_bytes(whole[: len(whole) * 6 // 10])
    _refused(monkeypatch, capsys, tmp_path, "--images", str(cut), needle="cannot read photo")
    _refused(monkeypatch, capsys, tmp_path, "--images", str(cut), needle="p01.jpg")
    (tmp_path / "clip.mp4").write_bytes(b"\x00" * 64)
    _refused(monkeypatch, capsys, tmp_path, "--video", str(tmp_path / "clip.mp4"), needle="cannot read the video")
    # ffmpeg's own reason, its last line, not the banner of its version and build it prints first
    err = _refused(monkeypatch, capsys, tmp_path, "--video", str(tmp_path / "clip.mp4"), needle="Invalid data found")
    assert "configuration" not in err and "Copyright" not in err
    _refused(monkeypatch, capsys, tmp_path, needle="give either --images DIR (photos) or --video FILE")


def test_photos_colmap_cannot_place_are_one_line_without_colmap_s_own_log(tmp_path, capfd):
    """Noise photos: COLMAP finds no model and logs an error line of its own (glog, on the process's stderr) before
    boostnerf's one line; only boostnerf's is said."""
    need_pycolmap()
    noise = tmp_path / "noise"
    noise.mkdir()
    for i, photo in enumerate(np.random.default_rng(0).integers(0, 255, (4, 80, 100, 3), dtype=np.uint8)):
        iio.imwrite(noise / f"p{i}.png", photo)
    proc = run_cli("capture", "--images", str(noise), "--out", str(tmp_path / "out"))
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip() and not ln.startswith(("[", "images:"))]
    assert proc.returncode == 2 and lines == [lines[-1]] and lines[-1].startswith("error: no camera could be placed"), \
        proc.stderr
    assert not (tmp_path / "out").exists()


def test_capture_without_pycolmap_says_how_to_install(tmp_path, monkeypatch, capsys):
    import builtins

    real = builtins.__import__
    monkeypatch.setattr(builtins, "__import__", lambda name, *a, **k: (_ for _ in ()).throw(ImportError(name))
                        if name == "pycolmap" else real(name, *a, **k))
    _refused(monkeypatch, capsys, tmp_path, "--images", str(_photos(tmp_path / "p", 3)), needle='.[capture]"')


def test_a_photo_replaced_in_place_is_another_input(tmp_path, monkeypatch):
    """A photo overwritten under the same name, with the same size in bytes and its old modification time (the
    folder's own time unchanged), is another input: the images phase a stopped capture finished is done again from
    the new photo."""
    need_pycolmap()
    import os

    from PIL import Image

    from boostnerf_cli.stages import capture

    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):  # uncompressed: the same size in bytes for any content
        Image.fromarray(rng.integers(0, 255, (30, 40, 3), dtype=np.uint8)).save(photos / f"p{i}.png", compress_level=0)

    def stop(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(capture, "_extract", stop)  # the images phase finishes, the features are never made
    work = tmp_path / ".cap.capture" / "images"
    with pytest.raises(KeyboardInterrupt):
        capture.run(photos, None, tmp_path / "cap", capture.CaptureOptions(), force=False)
    assert (work / "p1.png").read_bytes() == (photos / "p1.png").read_bytes()
    before, folder = (photos / "p1.png").stat(), photos.stat()
    Image.fromarray(rng.integers(0, 255, (30, 40, 3), dtype=np.uint8)).save(photos / "p1.png", compress_level=0)
    os.utime(photos / "p1.png", ns=(before.st_atime_ns, before.st_mtime_ns))
    os.utime(photos, ns=(folder.st_atime_ns, folder.st_mtime_ns))
    assert (photos / "p1.png").stat().st_size == before.st_size
    with pytest.raises(KeyboardInterrupt):
        capture.run(photos, None, tmp_path / "cap", capture.CaptureOptions(), force=False)
    assert (work / "p1.png").read_bytes() == (photos / "p1.png").read_bytes()


def test_too_few_registered_photos_say_how_many_and_what_to_do():
    from boostnerf_cli.stages.capture import check_registered

    check_registered(12, 24, 1)
    with pytest.raises(BoostNerfError, match=r"only 5 of the 12 images could be placed .* overlap too little"):
        check_registered(5, 12, 3)
    with pytest.raises(BoostNerfError, match="no camera could be placed"):
        check_registered(0, 12, 0)


def test_a_video_gives_evenly_spaced_sharp_frames(tmp_path):
    """Frames in windows of equal length, the sharpest of each: a blurred copy next to every sharp frame is never
    chosen, and where in the video each one kept is (its second) is said; a video with no frames is refused in one
    line."""
    import imageio_ffmpeg

    from boostnerf_cli.stages.capture import video_frames

    rng = np.random.default_rng(0)
    sharp = [np.kron(rng.integers(0, 255, (12, 16, 3), dtype=np.uint8), np.ones((4, 4, 1), np.uint8))
             for _ in range(6)]
    blurred = [((f[:-2].astype(int) + f[1:-1] + f[2:]) // 3).astype(np.uint8) for f in sharp]
    blurred = [np.concatenate([b, f[-2:]]) for b, f in zip(blurred, sharp)]
    writer = imageio_ffmpeg.write_frames(str(tmp_path / "v.mp4"), (64, 48), fps=10, quality=10, macro_block_size=16)
    writer.send(None)
    for b, f in zip(blurred, sharp):
        writer.send(np.ascontiguousarray(b))
        writer.send(np.ascontiguousarray(f))
    writer.close()
    kept = video_frames(tmp_path / "v.mp4", 6, tmp_path / "frames")
    # each window's sharp frame: the 2nd, 4th, ... of the video, at 10 frames per second
    assert kept == {f"frame_{i + 1:04d}.jpg": round((2 * i + 1) / 10, 4) for i in range(6)}, kept
    got = [iio.imread(p).astype(float) for p in sorted((tmp_path / "frames").iterdir())]
    for g, s, b in zip(got, sharp, blurred):
        assert np.abs(g - s).mean() < np.abs(g - b).mean()


# ----------------------------------------------------------------------------- capture: the real thing
# What a capture of the orbit's photos must recover (docs/data/capture-test-scenes.json holds the figures measured):
# every camera within these of the rendered ones after a similarity, its focal lengths within FOCAL of the true
# one, and its lens no farther from the true lens, where the photos have features, than LENS of what the true lens
# bends (a capture that drops the lens is as far as the whole bend).
ROTATION_DEG = (0.3, 0.6)  # median, largest
CENTRE = (0.006, 0.012)  # median, largest; fractions of the cameras' spread
FOCAL = 0.01
LENS = 0.5


@pytest.fixture(scope="module")
def orbit(tmp_path_factory) -> Path:
    """24 photos of 256 px ray-cast through an OPENCV lens on a walk around a textured procedural scene, with the
    cameras they were rendered with (a COLMAP model)."""
    return make_scene(tmp_path_factory.mktemp("orbit") / "src", size=256, n_train=24, n_test=0, layout="colmap",
                      content="textured", rig="orbit", lens="opencv")


def _lens_error(captured: Path, truth: Path) -> tuple[float, float]:
    """Within the radius that holds 90% of the captured model's placed keypoints: the RMS distance in pixels between
    where the captured camera (focal lengths and lens) and the true camera put the same rays, and the RMS distance
    the true lens moves a pixel from where a pinhole camera would put it."""
    (cap,) = [Intrinsics.from_colmap(c.model, c.params, "test") for c in
              read_model(captured / "sparse" / "0").cameras.values()]
    model = read_model(captured / "sparse" / "0")
    (camera,) = read_model(truth / "sparse" / "0").cameras.values()
    true = Intrinsics.from_colmap(camera.model, camera.params, "test")
    centre = torch.tensor([true.cx, true.cy], dtype=torch.float64)
    focal = torch.tensor([true.fx, true.fy], dtype=torch.float64)
    seen = np.concatenate([im.xys[im.point_ids >= 0] for im in model.images.values()])
    radius = np.percentile(np.linalg.norm(seen - centre.numpy(), axis=1), 90)
    v, u = np.mgrid[0:camera.height, 0:camera.width] + 0.5
    pixels = torch.tensor(np.stack([u.ravel(), v.ravel()], -1))
    pixels = pixels[(pixels - centre).norm(dim=1) <= radius]
    there = cap.pixels(true.normalized(pixels))
    bent = true.pixels((pixels - centre) / focal)
    return (float((there - pixels).norm(dim=1).pow(2).mean().sqrt()),
            float((bent - pixels).norm(dim=1).pow(2).mean().sqrt()))


def _assert_recovered(captured: Path, truth: Path, names: dict[str, str] | None = None) -> dict:
    """The captured cameras against the true ones (`ROTATION_DEG`, `CENTRE`, `FOCAL`, `LENS`); `names`: a captured
    view's name -> the true view's (a video's frames); -> the errors."""
    from boostnerf_cli.scenes.alignment import pose_errors, scene_poses

    report = json.loads((captured / "capture.json").read_text())
    assert report["registered"] == report["given"] == 24 and report["mean_reprojection_error"] < 1.0, report
    estimated = scene_poses(load_scene(captured, holdout_every=0))
    estimated = {(names or {}).get(k, k): v for k, v in estimated.items()}
    errors = pose_errors(estimated, scene_poses(load_scene(truth, holdout_every=0)))
    (cap,) = read_model(captured / "sparse" / "0").cameras.values()
    (true,) = read_model(truth / "sparse" / "0").cameras.values()
    errors["focal"] = max(abs(f / true.params[0] - 1) for f in cap.params[:2])
    errors["lens_px"], errors["bend_px"] = _lens_error(captured, truth)
    assert errors["cameras"] == 24, errors
    assert errors["median_rotation_deg"] < ROTATION_DEG[0] and errors["max_rotation_deg"] < ROTATION_DEG[1], errors
    assert errors["median_centre_error"] < CENTRE[0] and errors["max_centre_error"] < CENTRE[1], errors
    assert errors["focal"] < FOCAL, errors
    assert errors["lens_px"] < LENS * errors["bend_px"], errors
    return errors


def _same_model(a: Path, b: Path) -> None:
    for part in ("cameras.bin", "images.bin", "points3D.bin"):
        assert (a / "sparse" / "0" / part).read_bytes() == (b / "sparse" / "0" / part).read_bytes(), part


@pytest.mark.slow
def test_capture_recovers_the_cameras_and_the_lens_of_rendered_photos(orbit, tmp_path, monkeypatch, capsys):
    """Photos ray-cast through a lens from a textured procedural scene (a walk around it) with known cameras: capture
    places every one, and after a similarity each camera, its focal lengths and its lens are the known ones (within
    `ROTATION_DEG`, `CENTRE`, `FOCAL`, `LENS`). A run stopped in the middle leaves no scene folder, and the next run
    goes on from the phases it finished; a second run over the finished scene answers "already captured", and
    refuses once a photo is replaced; the same photos captured again give the same model, bit for bit. pretrain reads
    the folder directly."""
    need_pycolmap()
    from boostnerf_cli.stages import capture

    photos = shutil.copytree(orbit / "images", tmp_path / "photos")
    out = tmp_path / "cap"

    def stop(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(capture, "_map", stop)
    with pytest.raises(KeyboardInterrupt):
        capture.run(photos, None, out, capture.CaptureOptions(), force=False)
    monkeypatch.undo()
    assert not out.exists() and (tmp_path / ".cap.capture" / "database.db").is_file()
    code, err = cli_in_process(monkeypatch, capsys, "capture", "--images", str(photos), "--out", str(out))
    assert code == 0, err
    assert "features: done before, reused" in err and "matching: done before, reused" in err
    _assert_recovered(out, orbit)
    code, err = cli_in_process(monkeypatch, capsys, "capture", "--images", str(photos), "--out", str(out))
    assert code == 0 and "already captured" in err
    shutil.copy(orbit / "images" / "image005.png", photos / "image004.png")  # replaced in place, the same size
    code, err = cli_in_process(monkeypatch, capsys, "capture", "--images", str(photos), "--out", str(out))
    assert code == 2 and "was captured from other inputs or settings" in err, err
    again = tmp_path / "again"  # the same photos captured afresh: the same cameras, lens and points, bit for bit
    code, err = cli_in_process(monkeypatch, capsys, "capture", "--images", str(orbit / "images"), "--out",
                               str(again))
    assert code == 0, err
    _same_model(again, out)
    proc = run_cli("pretrain", "--data", str(out), "--workspace", str(tmp_path / "ws"), "--recipe",
                   str(make_recipe(tmp_path / "r.yaml", pretrain={"res": [12], "iters": 10,
                                                                   "geometry": {"iters": 20}})), "--device", "cpu")
    assert proc.returncode == 0, proc.stderr
    assert "format: colmap" in proc.stderr and "from the sparse points" in proc.stderr


@pytest.mark.slow
def test_retrieval_matches_neighbours_and_recovers_the_cameras(orbit, tmp_path):
    """Retrieval on the orbit's photos: the vocabulary learned from their own features, the same at every run, makes
    most photos' most similar one a neighbour on the walk, and pairs the walk's start with its end, which file order
    puts 23 apart; matching only those pairs places every camera as exhaustive matching does, and the same
    photos captured again give the same model, bit for bit."""
    pycolmap = need_pycolmap()
    from boostnerf_cli.stages import capture

    options = capture.CaptureOptions(matching="retrieval")
    out, again = tmp_path / "cap", tmp_path / "again"
    report = capture.run(orbit / "images", None, out, options, force=False)
    assert report["matching"] == "retrieval"
    _assert_recovered(out, orbit)
    capture.run(orbit / "images", None, again, options, force=False)
    _same_model(again, out)

    with pycolmap.Database.open(out / "database.db") as db:
        by_name = {im.name: im.image_id for im in db.read_all_images()}
        descriptors = [db.read_descriptors(by_name[n]).data for n in sorted(by_name)]
    vectors = capture._vocabulary_vectors(descriptors, capture.VOCABULARY_WORDS, 0)
    assert np.array_equal(vectors, capture._vocabulary_vectors(descriptors, capture.VOCABULARY_WORDS, 0))
    n = len(descriptors)
    apart = [min(abs(i - j), n - abs(i - j)) for i, j in capture.similar(vectors, 1)]
    assert sum(a <= 2 for a in apart) >= 2 * n // 3, apart  # most photos' most similar: 1 or 2 steps on the walk
    chosen = capture.pairs(n, "retrieval", vectors)
    assert len(chosen) < n * (n - 1) // 2 and (0, n - 1) in chosen  # fewer than every pair; the walk closed


@pytest.mark.slow
def test_a_video_of_the_walk_recovers_its_cameras(orbit, tmp_path):
    """The orbit's photos as the frames of a video: capture keeps every frame (24 windows of one), matches them
    sequentially with loop closures by retrieval (the walk's end with its start), places every camera as from the
    photos, and a second capture of the video gives the same model, bit for bit."""
    need_pycolmap()
    import imageio_ffmpeg

    from boostnerf_cli.stages import capture

    video = tmp_path / "walk.mp4"
    writer = imageio_ffmpeg.write_frames(str(video), (256, 256), fps=4, quality=10, macro_block_size=16)
    writer.send(None)
    names = sorted((orbit / "images").iterdir())
    for photo in names:
        writer.send(np.ascontiguousarray(iio.imread(photo)[..., :3]))
    writer.close()
    options = capture.CaptureOptions(frames=24)
    report = capture.run(None, video, tmp_path / "cap", options, force=False)
    assert report["matching"] == "sequential" and len(report["video_seconds"]) == 24
    frames = {f"frame_{i + 1:04d}": p.stem for i, p in enumerate(names)}
    _assert_recovered(tmp_path / "cap", orbit, frames)
    capture.run(None, video, tmp_path / "again", options, force=False)
    _same_model(tmp_path / "again", tmp_path / "cap")


LENS_RECIPE = {"data": {"holdout_every": 8, "image_size": REMOVE},  # the photos' own 48 px
               "pretrain": {"res": [24], "iters": 300,
                            "geometry": {"res": 16, "iters": 150, "batch_rays": 512},
                            "train": {"batch_rays": 512, "log_every": 100, "checkpoint_every": 1000,
                                      "occupancy_every": 100}}}


@pytest.mark.slow
def test_a_distorted_capture_trains_to_its_pinhole_twin(tmp_path):
    """The same cameras and scene, photographed through a pinhole and through an OPENCV lens (k1 -0.3, up to 2.4 px
    at the corners of 48 px views): DVGO-24 trained on the distorted photos with the lens read, rendered at the
    twin's held-out pinhole views, reaches the pinhole-trained expert's PSNR, while the same photos read as pinhole
    photos (the lens dropped from transforms.json) fall short: the geometry it learns is bent (docs/datasets.md,
    "Lenses", gives the figures)."""
    from boostnerf_cli.metrics.image import psnr
    from boostnerf_cli.models import load_model
    from boostnerf_cli.render.renderer import render_view
    from boostnerf_cli.workspace import Workspace

    kw = {"size": 48, "n_train": 14, "n_test": 2, "layout": "nerfstudio"}
    pin = make_scene(tmp_path / "pin", **kw)
    lens = make_scene(tmp_path / "lens", **kw, lens="opencv")
    flat = shutil.copytree(lens, tmp_path / "flat")
    meta = json.loads((flat / "transforms.json").read_text())
    for key in ("k1", "k2", "p1", "p2"):
        meta.pop(key)
    (flat / "transforms.json").write_text(json.dumps(meta))
    recipe = make_recipe(tmp_path / "lens.yaml", **LENS_RECIPE)
    twin = load_scene(pin).split("test")
    scores = {}
    for folder in (pin, lens, flat):
        ws = tmp_path / f"ws-{folder.name}"
        run_cli("pretrain", "--data", str(folder), "--workspace", str(ws), "--recipe", str(recipe), "--device",
                "cpu", check=True, timeout=1800)  # about 30 s each alone; minutes on a busy machine
        model = load_model(Workspace(ws), "dvgo-24", "cpu")
        settings = model.settings(load_scene(pin))
        scores[folder.name] = np.mean([psnr(render_view(model.field, twin, i, settings, model.skip)["rgb"],
                                            twin.images[i]) for i in range(len(twin))])
    assert scores["lens"] >= scores["pin"] - 0.1, scores
    assert scores["flat"] <= scores["pin"] - 0.3, scores


def test_the_scene_cache_keeps_the_points_and_the_lens(colmap_scene, tmp_path, monkeypatch):
    from boostnerf_cli import scenes

    first = load_scene(colmap_scene, cache=tmp_path / "scene.safetensors")
    detect, _, what = scenes.FORMATS["colmap"]
    monkeypatch.setitem(scenes.FORMATS, "colmap", (detect, lambda *a, **k: pytest.fail("decoded again"), what))
    again = load_scene(colmap_scene, cache=tmp_path / "scene.safetensors")
    assert (tmp_path / "scene.safetensors").is_file()
    assert torch.equal(again.points.xyz, first.points.xyz) and torch.equal(again.points.rgb, first.points.rgb)
    assert all(torch.equal(again.points.visible[k], first.points.visible[k]) for k in first.points.visible)
    assert torch.equal(again.splits["train"].intrinsics, first.splits["train"].intrinsics)
    assert again.splits["train"].intrinsics.shape[1] == WITH_LENS


def test_a_splits_rows_are_as_wide_as_its_cameras_need_and_read_back():
    """A split's intrinsics rows: 4 numbers for pinhole cameras, 11 with a lens (the layout scene caches and workspace
    digests made before FULL_OPENCV was read: those stay valid), 14 with a rational one; each reads back the same."""
    pinhole = Intrinsics(50.0, 55.0, 16.0, 12.0)
    opencv = Intrinsics(50.0, 55.0, 16.0, 12.0, LENSES_TRIED["opencv"])
    full = Intrinsics(50.0, 55.0, 16.0, 12.0, LENSES_TRIED["full-opencv"])
    fisheye = Intrinsics(50.0, 55.0, 16.0, 12.0, Lens(fisheye=True))
    for cams, width in (([pinhole], PINHOLE), ([pinhole, opencv, fisheye], WITH_LENS), ([opencv, full], WITH_RATIONAL)):
        table = rows(cams)
        assert table.shape == (len(cams), width)
        for cam, row in zip(cams, table):
            assert Intrinsics.of(row) == Intrinsics.of(rows([cam])[0])
    assert Intrinsics.of(rows([fisheye])[0]).lens == Lens(fisheye=True)
    with pytest.raises(BoostNerfError, match="cannot hold"):
        full.row(WITH_LENS)
