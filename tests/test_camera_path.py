"""Camera paths (viewpoint/camera_path.py, `render --camera-path`, the viewer's camera path panel): keyframe
operations, the path sampled through the keyframes, the nerfstudio-layout file written and read back, every bad file
refused in one line, and paths written from a dataset's own pose files (as another tool writes them) rendering what
`render` renders of those views, on a 360-degree scene and a forward-facing one."""

from __future__ import annotations

import contextlib
import json
import math
import shutil
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from conftest import assert_clean_failure, cli_in_process, make_recipe, no_temp_files, run_cli

from boostnerf_cli.cameras import DataFrame
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.lineage import Survey
from boostnerf_cli.models import ALL_SKIPS, load_model
from boostnerf_cli.render.paths import look_at
from boostnerf_cli.render.renderer import render_view
from boostnerf_cli.scenes import make_scene
from boostnerf_cli.stages import render as render_stage
from boostnerf_cli.viewpoint.camera import dataset_camera
from boostnerf_cli.viewpoint.camera_path import (
    CameraPath,
    Keyframe,
    path_cameras,
    path_json,
    read_camera_path,
    write_camera_path,
)
from boostnerf_cli.viewpoint.frame import Look, picture
from boostnerf_cli.workspace import Workspace


def keyframes(n: int = 5, seed: int = 0) -> list[Keyframe]:
    """`n` cameras scattered around the origin, looking at it, with fields of view 40, 45, ... degrees."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        position = torch.tensor(rng.normal(size=3) * 2 + [0.0, 0.0, 4.0])
        up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
        pose = look_at(position, torch.zeros(3, dtype=torch.float64), up)
        out.append(Keyframe(pose.numpy(), 40.0 + 5 * i))
    return out


def angle(a: np.ndarray, b: np.ndarray) -> float:
    """The angle in radians between two rotations (3, 3)."""
    return math.acos(min(1.0, max(-1.0, (np.trace(a.T @ b) - 1) / 2)))


# ----------------------------------------------------------------------------- the path


@pytest.mark.parametrize("cycle", [False, True])
@pytest.mark.parametrize("smoothness", [0.0, 0.5, 1.0])
def test_the_path_passes_each_keyframe_at_its_time(smoothness, cycle):
    path = CameraPath(keyframes(), seconds=4.0, fps=10, smoothness=smoothness, cycle=cycle)
    times = path.key_times()
    assert times[1] == pytest.approx(4.0 / (5 if cycle else 4))
    for k, t in zip(path.keyframes, times):
        f = path.at(float(t))
        assert np.allclose(f.pose, k.pose, atol=1e-9) and f.fov == pytest.approx(k.fov)
    frames = path.frames()
    assert len(frames) == (40 if cycle else 41)  # a frame every 0.1 s: an open path has both ends
    if not cycle:  # every keyframe's time is a multiple of 0.1 s: each keyframe is a frame
        for k, t in zip(path.keyframes, times):
            assert np.allclose(frames[round(t * 10)].pose, k.pose, atol=1e-9)
    assert np.allclose(frames[0].pose, path.keyframes[0].pose, atol=1e-9)
    if not cycle:  # the last frame is the last keyframe; a loop's last frame is one short of the first again
        assert np.allclose(frames[-1].pose, path.keyframes[-1].pose, atol=1e-9)
    for f in frames:  # every pose is rigid
        assert np.allclose(f.pose[:3, :3].T @ f.pose[:3, :3], np.eye(3), atol=1e-9)
        assert np.allclose(f.pose[3], [0, 0, 0, 1])


def test_a_smooth_path_has_no_corners_and_a_straight_one_runs_on_segments_and_arcs():
    smooth = CameraPath(keyframes(), seconds=4.0, smoothness=1.0)
    h = 1e-5
    for t in smooth.key_times()[1:-1]:  # the velocity just before and just after an inner keyframe: the same
        before = (smooth.at(t).pose - smooth.at(t - h).pose) / h
        after = (smooth.at(t + h).pose - smooth.at(t).pose) / h
        scale = np.abs(after).max()
        assert np.abs(before - after).max() < 1e-3 * scale, (t, before - after)
    # the straight path (smoothness 0): positions on the segment between two keyframes, rotations on the great arc
    straight = CameraPath(keyframes(), seconds=4.0, smoothness=0.0)
    times = straight.key_times()
    for a in range(4):
        pa, pb = straight.keyframes[a].pose, straight.keyframes[a + 1].pose
        for u in (0.25, 0.5, 0.8):
            f = straight.at(times[a] + u * (times[a + 1] - times[a]))
            p = f.pose[:3, 3] - pa[:3, 3]
            seg = pb[:3, 3] - pa[:3, 3]
            assert np.linalg.norm(np.cross(p, seg)) < 1e-9 * np.linalg.norm(seg) ** 2 and 0 < p @ seg < seg @ seg
            r = f.pose[:3, :3]
            assert angle(pa[:3, :3], r) + angle(r, pb[:3, :3]) == pytest.approx(angle(pa[:3, :3], pb[:3, :3]), abs=1e-7)
            assert min(straight.keyframes[a].fov, straight.keyframes[a + 1].fov) <= f.fov <= max(
                straight.keyframes[a].fov, straight.keyframes[a + 1].fov)
    # the smooth path leaves the segments: it is not the straight one
    assert not np.allclose(smooth.at(0.5).pose, straight.at(0.5).pose, atol=1e-3)
    # two keyframes, smooth: a straight line at constant speed and a constant turn rate
    two = CameraPath(keyframes(2), seconds=1.0, smoothness=1.0)
    pos = np.array([two.at(t).pose[:3, 3] for t in np.linspace(0, 1, 11)])
    assert np.allclose(np.diff(pos, axis=0), (pos[-1] - pos[0]) / 10, atol=1e-9)
    turns = [angle(two.at(t).pose[:3, :3], two.at(t + 0.1).pose[:3, :3]) for t in np.linspace(0, 0.9, 10)]
    assert np.allclose(turns, turns[0], atol=1e-7)


def test_keyframe_operations():
    k = keyframes(3)
    path = CameraPath()
    assert path.add(k[0]) == 0 and path.add(k[2]) == 1 and path.add(k[1], at=1) == 1
    assert [kf.fov for kf in path.keyframes] == [40.0, 45.0, 50.0]
    assert path.move(0, 1) == 1 and [kf.fov for kf in path.keyframes] == [45.0, 40.0, 50.0]
    assert path.move(1, -5) == 0 and [kf.fov for kf in path.keyframes] == [40.0, 45.0, 50.0]  # clipped at the start
    assert path.move(2, 1) == 2  # already last
    path.set_fov(1, 30.0)
    assert path.keyframes[1].fov == 30.0 and np.array_equal(path.keyframes[1].pose, k[1].pose)
    path.delete(0)
    assert [kf.fov for kf in path.keyframes] == [30.0, 50.0]
    with pytest.raises(BoostNerfError, match="there is no keyframe 2: the path has keyframes 0 to 1"):
        path.delete(2)
    with pytest.raises(BoostNerfError, match="keyframe 0's fov is 180"):
        path.set_fov(0, 180)
    with pytest.raises(BoostNerfError, match="the smoothness is 2"):
        path.configure(4.0, 24, 2, False, 32, 32)
    with pytest.raises(BoostNerfError, match="are 2,400,000 frames: at most 100,000"):
        path.configure(1e5, 24, 1.0, False, 32, 32)
    path.configure(2.0, 12, 0.5, True, 40, 30)
    settings = (path.seconds, path.fps, path.smoothness, path.cycle, path.width, path.height)
    assert settings == (2.0, 12, 0.5, True, 40, 30)
    assert "2 keyframes (0: 30.0 deg at 0.00 s, 1: 50.0 deg at 1.00 s); 24 frames of 40x30 px" in path.summary()


# ----------------------------------------------------------------------------- the file

FRAME = DataFrame(np.array([[0.0, -2.0, 0.0, 1.0], [2.0, 0.0, 0.0, -3.0], [0.0, 0.0, 2.0, 0.5], [0, 0, 0, 1]]))


def test_a_path_written_reads_back_in_nerfstudio_layout_in_the_data_frame(tmp_path):
    path = CameraPath(keyframes(4), seconds=2.0, fps=5, smoothness=0.7, cycle=True, width=48, height=32)
    file = write_camera_path(tmp_path / "paths" / "p.json", path, FRAME)
    assert no_temp_files(tmp_path)
    data = json.loads(file.read_text())
    assert data["camera_type"] == "perspective" and (data["render_width"], data["render_height"]) == (48, 32)
    assert (data["fps"], data["seconds"], data["is_cycle"]) == (5, 2.0, True)
    assert data["smoothness_value"] == pytest.approx(0.3)  # nerfstudio's tension: 1 - smoothness
    assert len(data["camera_path"]) == 10 and len(data["keyframes"]) == 4
    first = data["camera_path"][0]
    assert len(first["camera_to_world"]) == 16 and first["aspect"] == 1.5 and first["fov"] == 40.0
    # row by row, in the data's frame: the translation is entries 3, 7, 11
    data_pose = FRAME.poses_to_data(path.keyframes[0].pose)
    assert np.allclose(np.reshape(first["camera_to_world"], (4, 4)), data_pose)
    assert np.allclose(np.array(first["camera_to_world"])[[3, 7, 11]], data_pose[:3, 3])
    assert not np.allclose(data_pose, path.keyframes[0].pose)
    read = read_camera_path(file, FRAME)
    assert (read.path.seconds, read.path.fps, read.path.cycle, read.path.width, read.path.height) == (2.0, 5, True, 48,
                                                                                                       32)
    assert read.path.smoothness == pytest.approx(0.7)
    for a, b in zip(read.path.keyframes, path.keyframes):
        assert np.allclose(a.pose, b.pose, atol=1e-9) and a.fov == b.fov
    assert len(read.frames) == 10
    for a, b in zip(read.frames, path.frames()):
        assert np.allclose(a.pose, b.pose, atol=1e-9) and a.fov == pytest.approx(b.fov)
    cameras = path_cameras(read.frames, 32, 48)
    assert cameras[0].width == 48 and cameras[0].height == 32
    assert float(cameras[0].intrinsics[1]) == pytest.approx(16 / math.tan(math.radians(20)), rel=1e-6)


def test_a_file_with_keyframes_only_is_sampled_and_a_uniform_scale_is_divided_out(tmp_path):
    path = CameraPath(keyframes(3), seconds=1.0, fps=8, width=32, height=32)
    data = path_json(path, FRAME)
    del data["camera_path"]
    scaled = np.reshape(data["keyframes"][1]["matrix"], (4, 4)).copy()
    scaled[:3, :3] *= 2.5  # a scaled camera object (Blender's matrix_world)
    data["keyframes"][1]["matrix"] = scaled.ravel().tolist()
    file = tmp_path / "k.json"
    file.write_text(json.dumps(data))
    read = read_camera_path(file, FRAME)
    assert len(read.frames) == 9 and np.allclose(read.path.keyframes[1].pose, path.keyframes[1].pose, atol=1e-9)
    for a, b in zip(read.frames, path.frames()):
        assert np.allclose(a.pose, b.pose, atol=1e-9)


def nerfstudio_file() -> dict:
    """A file as nerfstudio's viewer writes one, in the identity frame."""
    path = CameraPath(keyframes(3), seconds=1.0, fps=4, width=32, height=24)
    return path_json(path, DataFrame(np.eye(4)))


def broken(change) -> dict:
    data = nerfstudio_file()
    change(data)
    return data


def entry(data, i, key, value):
    data["camera_path"][i][key] = value


def nan_matrix(data):
    data["camera_path"][2]["camera_to_world"][5] = float("nan")


def sheared(data):
    m = np.reshape(data["keyframes"][1]["matrix"], (4, 4)).copy()
    m[:3, 0] *= 1.2  # one axis stretched
    data["keyframes"][1]["matrix"] = m.ravel().tolist()


def mirrored(data):
    m = np.reshape(data["camera_path"][0]["camera_to_world"], (4, 4)).copy()
    m[:3, 0] *= -1
    data["camera_path"][0]["camera_to_world"] = m.ravel().tolist()


BAD = [
    ("empty", lambda d: d.update(camera_path=[], keyframes=[]), 'no "camera_path" frames and no "keyframes"'),
    ("nan", nan_matrix, "camera_path[2].camera_to_world has a NaN or infinite value"),
    ("infinite", lambda d: entry(d, 1, "camera_to_world", [math.inf] * 16), "camera_path[1].camera_to_world has a NaN"),
    ("bottom row", lambda d: entry(d, 3, "camera_to_world", [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 1, 1]),
     "camera_path[3].camera_to_world's bottom row is 0 0 1 1, not 0 0 0 1"),
    ("shear", sheared, "keyframes[1].matrix is not a rigid camera pose"),
    ("reflection", mirrored, "camera_path[0].camera_to_world is not a rigid camera pose: its rotation is not "
                             "orthonormal (a reflection"),
    ("12 numbers", lambda d: entry(d, 1, "camera_to_world", [1, 0, 0, 0] * 3), "camera_path[1].camera_to_world must "
                                                                                "be 16 numbers"),
    ("fisheye", lambda d: d.update(camera_type="fisheye"),
     '"camera_type" is \'fisheye\': boostnerf renders perspective'),
    ("equirectangular", lambda d: d.update(camera_type="equirectangular"), "'equirectangular'"),
    ("version", lambda d: d.update(version="2"), "\"version\" '2'"),
    ("no height", lambda d: d.pop("render_height"), 'it has no "render_height"'),
    ("no width", lambda d: d.pop("render_width"), 'it has no "render_width"'),
    ("fractional width", lambda d: d.update(render_width=32.5), '"render_width" is 32.5'),
    ("fov", lambda d: entry(d, 2, "fov", 0), "camera_path[2].fov is 0"),
    ("no fov", lambda d: d["camera_path"][1].pop("fov"),
     'camera_path[1] needs "camera_to_world" (16 numbers) and "fov"'),
    ("aspect", lambda d: entry(d, 0, "aspect", 1.0), "camera_path[0].aspect is 1, not render_width / render_height"),
    ("crop", lambda d: d.update(crop={"crop_center": [0, 0, 0]}), 'it has a "crop"'),
    ("too many frames", lambda d: d.update(seconds=1e6), "1e+06 seconds at 4 frames per second are 4,000,000 frames: "
                                                          "at most 100,000"),
    ("too many entries", lambda d: d.update(camera_path=d["camera_path"][:1] * 100_001),
     '"camera_path" has 100,001 entries: at most 100,000'),
    ("smoothness", lambda d: d.update(smoothness_value=1.5), '"smoothness_value" is 1.5'),
    ("not a list", lambda d: d.update(camera_path={"0": {}}), '"camera_path" must be a list of objects'),
]


@pytest.mark.parametrize("change,message", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_a_bad_camera_path_file_is_one_line_naming_the_entry(tmp_path, change, message):
    file = tmp_path / "bad.json"
    file.write_text(json.dumps(broken(change)))
    with pytest.raises(BoostNerfError) as e:
        read_camera_path(file, DataFrame(np.eye(4)))
    line = str(e.value)
    assert "\n" not in line and line.startswith(f"camera path {file}: ") and message in line, line


def test_the_file_nerfstudio_writes_reads(tmp_path):
    """Its extra keys (default_fov, default_transition_sec, render_time, override_*) and a null crop are accepted;
    a fov given as an integer, frames given as 4 rows of 4."""
    data = nerfstudio_file()
    data.update(crop=None, default_time=0.0)
    data["camera_path"][0]["render_time"] = 0.5
    data["camera_path"][1]["fov"] = 50
    data["camera_path"][2]["camera_to_world"] = np.reshape(data["camera_path"][2]["camera_to_world"], (4, 4)).tolist()
    file = tmp_path / "ns.json"
    file.write_text(json.dumps(data))
    read = read_camera_path(file, DataFrame(np.eye(4)))
    assert len(read.frames) == 5 and read.frames[1].fov == 50.0  # 1 s at 4 fps, both ends


# ----------------------------------------------------------------------------- rendering


def views_file(poses: list[np.ndarray], fov: float, height: int, width: int, target: Path) -> Path:
    """A camera-path file of `poses` (data frame, OpenGL), as another tool writes one: frames only."""
    frames = [{"camera_to_world": np.asarray(p, dtype=float).ravel().tolist(), "fov": fov, "aspect": width / height}
              for p in poses]
    target.write_text(json.dumps({"camera_type": "perspective", "render_height": height, "render_width": width,
                                  "seconds": float(len(poses)), "camera_path": frames}))
    return target


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)) / 255.0**2
    return -10 * math.log10(max(mse, 1e-12))


def check_path_renders_the_views(ws_root: Path, model_name: str, file: Path,
                                 views: dict[str, list[int]]) -> list[np.ndarray]:
    """The file's frames, rendered in this process, are `render_view`'s pictures of the views they pass:
    `views[split][i]` is the frame that shows view i of the split -> the frames."""
    ws = Workspace(ws_root)
    scene = Survey(ws).scene()
    read = read_camera_path(file, DataFrame.of(scene.extra))
    for split_name, frames in views.items():  # the file's poses, taken to the scene's world, are the views' own
        split = scene.split(split_name)
        for i, k in enumerate(frames):
            assert np.allclose(read.frames[k].pose, split.poses[i].double().numpy(), atol=2e-5), (split_name, i)
    model = load_model(ws, model_name, "cpu")
    cameras = path_cameras(read.frames, read.path.height, read.path.width)
    shots = render_stage.film(model, scene, cameras, "cpu", ALL_SKIPS, "test")
    settings = model.render_setup(scene, ALL_SKIPS)
    for split_name, frames in views.items():
        for i, k in enumerate(frames):
            rgb = render_view(model.field, scene.split(split_name), i, *settings, "cpu")["rgb"].numpy()
            assert psnr(shots.rgb[k], (rgb * 255 + 0.5).clip(0, 255).astype(np.uint8)) > 40, (split_name, i)
    return shots.rgb


def check_videos(proc, folder: Path, stem: str, n: int, kinds: tuple[str, ...]) -> list[np.ndarray]:
    """The command wrote `stem.mp4` and `stem_<kind>.mp4` of `n` frames each -> the colour video's frames."""
    written = [Path(p) for p in proc.stdout.split()]
    expected = [folder / f"{stem}{'_' + k if k else ''}.mp4" for k in ("", *kinds)]
    assert written == expected, proc.stdout
    videos = {p: iio.imread(p) for p in expected}
    assert all(v.shape[0] == n for v in videos.values()), {p.name: v.shape for p, v in videos.items()}
    assert no_temp_files(folder)
    return list(videos[expected[0]])


def test_a_path_through_the_test_views_renders_what_render_renders(trained_ws, tmp_path):
    """The tiny Blender scene's test views, written from transforms_test.json as another tool would: the frames are
    `render`'s pictures of those views; the command writes colour and depth MP4s of 3 frames (no routing: an
    expert), whose frames match the PNGs `render` writes."""
    ws = Workspace(trained_ws)
    scene_dir = ws.root / ws.manifest()["data"]["path"]
    meta = json.loads((scene_dir / "transforms_test.json").read_text())
    poses = [np.array(f["transform_matrix"]) for f in meta["frames"]]
    file = views_file(poses, math.degrees(meta["camera_angle_x"]), 32, 32, tmp_path / "test-views.json")  # square
    frames = check_path_renders_the_views(trained_ws, "dvgo-16", file, {"test": [0, 1, 2]})
    proc = run_cli("render", "-w", str(trained_ws), "--model", "dvgo-16", "--camera-path", str(file), "--video",
                   str(tmp_path / "out" / "test-views.mp4"), "--device", "cpu", check=True)
    video = check_videos(proc, tmp_path / "out", "test-views", 3, ("depth",))
    for k in range(3):
        assert psnr(video[k], frames[k]) > 35  # H.264's loss


@pytest.fixture(scope="module")
def forward_ws(tmp_path_factory) -> tuple[Path, Path]:
    """A trained forward-facing (LLFF layout) workspace: 24 px, 10 + 2 views, one 30-step expert -> (ws, scene)."""
    root = tmp_path_factory.mktemp("forward")
    scene = make_scene(root / "llff", size=24, n_train=10, n_test=2, layout="llff")
    run_cli("pretrain", "--data", str(scene), "--recipe", str(make_recipe(root / "tiny.yaml")), "--workspace",
            str(root / "ws"), "--res", "12", "--image-size", "24", "--device", "cpu", check=True)
    return root / "ws", scene


@pytest.mark.slow  # trains a model of its own
def test_a_path_through_a_forward_facing_captures_own_poses_renders_its_views(forward_ws, tmp_path):
    """poses_bounds.npy's cameras (LLFF axes turned to OpenGL, the file's world: not the scene's rescaled and
    recentred one) render the views `render` renders, and the command writes the videos under WS/renders/MODEL."""
    ws_root, scene_dir = forward_ws
    scene = Survey(Workspace(ws_root)).scene()
    assert not DataFrame.of(scene.extra).identity  # the data's frame is not the scene's world
    rows = np.load(scene_dir / "poses_bounds.npy")
    poses, fovs = [], set()
    for row in rows:
        m = row[:15].reshape(3, 5)
        down, right, back, centre = m[:, 0], m[:, 1], m[:, 2], m[:, 3]
        pose = np.eye(4)
        pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, -down, back, centre
        poses.append(pose)
        fovs.add(round(math.degrees(2 * math.atan(m[0, 4] / (2 * m[2, 4]))), 9))
    assert len(fovs) == 1 and int(rows[0, 4]) == 24
    file = views_file(poses, fovs.pop(), 24, 24, tmp_path / "all-views.json")
    names = sorted(p.stem for p in (scene_dir / "images").iterdir())  # the views' names: the images' stems
    frames = check_path_renders_the_views(ws_root, "dvgo-12", file, {
        name: [names.index(n) for n in scene.split(name).names] for name in ("train", "test")})
    proc = run_cli("render", "-w", str(ws_root), "--model", "dvgo-12", "--camera-path", str(file), "--device", "cpu",
                   check=True)
    video = check_videos(proc, ws_root / "renders" / "dvgo-12", "all-views", len(rows), ("depth",))
    for k in range(len(rows)):
        assert psnr(video[k], frames[k]) > 35  # H.264's loss


def test_a_hand_written_camera_path_file_may_start_with_a_bom_and_a_broken_one_is_to_be_fixed(tmp_path):
    """Editors that save UTF-8 with a byte-order mark: read as any other file. A file that is not UTF-8 JSON is the
    user's to fix, not "delete it and rerun the stage" (a workspace file's advice)."""
    file = tmp_path / "p.json"
    file.write_bytes(b"\xef\xbb\xbf" + json.dumps(nerfstudio_file()).encode())
    assert len(read_camera_path(file, DataFrame.of({})).frames) == len(nerfstudio_file()["camera_path"])
    file.write_bytes(b"\xff\xfe{}")
    with pytest.raises(BoostNerfError, match="is not valid JSON") as e:
        read_camera_path(file, DataFrame.of({}))
    assert "rerun the stage" not in str(e.value) and "fix it" in str(e.value)


@pytest.mark.parametrize("blocked", ["y_depth.mp4", "y_routing.mp4", "y.mp4", "file"])
def test_a_video_set_is_written_whole_or_not_at_all(mixture_ws, tmp_path, monkeypatch, capsys, blocked):
    """A folder where one of a path's videos goes (or a file where its folder goes) is one line before a frame is
    rendered, and none of the set is written: the colour video was left beside a refused depth video."""
    file = tmp_path / "p.json"
    file.write_text(json.dumps(nerfstudio_file()))
    out = tmp_path / "vid"
    if blocked == "file":
        out.write_text("in the way")
    else:
        (out / blocked).mkdir(parents=True)
    rendered = []
    monkeypatch.setattr(render_stage, "render_image", lambda *a, **k: rendered.append(1))
    code, err = cli_in_process(monkeypatch, capsys, "render", "-w", str(mixture_ws), "--model", "top2",
                               "--camera-path", str(file), "--video", str(out / "y.mp4"), "--device", "cpu")
    assert code == 2 and "in the way" in err and not rendered, err
    if blocked != "file":
        assert sorted(p.name for p in out.iterdir()) == [blocked]


def test_a_video_set_whose_encoding_fails_leaves_no_file(trained_ws, tmp_path, monkeypatch):
    """The depth video's encoding failing after the colour video's leaves neither (nor a temporary file)."""
    from boostnerf_cli import images

    real = images.encode_video
    calls = []

    def fail_second(path, frames, fps, fmt):
        calls.append(path)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        real(path, frames, fps, fmt)

    monkeypatch.setattr(images, "encode_video", fail_second)
    model = load_model(Workspace(trained_ws), "dvgo-12", "cpu")
    scene = Survey(Workspace(trained_ws)).scene()
    shots = render_stage.film(model, scene, [render_stage.Camera(*c) for c in [
        (scene.split("test").poses[0], scene.split("test").intrinsics[0], 16, 16)]], "cpu", ALL_SKIPS, "test")
    with pytest.raises(BoostNerfError, match="could not write .*x_depth.gif \\(No space left"):
        render_stage.write_film(shots, tmp_path / "v" / "x.gif", "gif", 4, "test")
    assert len(calls) == 2 and list((tmp_path / "v").iterdir()) == []
    calls.clear()  # of three videos, the second failing is named, not the last one entered
    frames = shots.rgb
    with pytest.raises(BoostNerfError, match="could not write .*b.gif \\(No space left"):
        images.write_videos([(tmp_path / "w" / f"{n}.gif", frames) for n in "abc"], 4, "gif")
    assert list((tmp_path / "w").iterdir()) == []


def test_a_mixtures_path_has_a_routing_video_of_the_maps_the_viewer_shows(mixture_ws, tmp_path):
    ws = Workspace(mixture_ws)
    scene = Survey(ws).scene()
    test = scene.split("test")
    fov = math.degrees(2 * math.atan(test.height / (2 * float(test.intrinsics[0, 1]))))
    file = views_file([p.double().numpy() for p in test.poses], fov, test.height, test.width, tmp_path / "mix.json")
    proc = run_cli("render", "-w", str(mixture_ws), "--model", "top2", "--camera-path", str(file), "--video",
                   str(tmp_path / "out" / "mix.mp4"), "--device", "cpu", check=True)
    check_videos(proc, tmp_path / "out", "mix", 3, ("depth", "routing"))
    video = iio.imread(tmp_path / "out" / "mix_routing.mp4")
    model = load_model(ws, "top2", "cpu")
    read = read_camera_path(file, DataFrame.of(scene.extra))
    shots = render_stage.film(model, scene, path_cameras(read.frames, 32, 32), "cpu", ALL_SKIPS, "test", routing=True)
    for i in range(3):
        expected = picture(model, scene, dataset_camera(test, i), Look("routing"), "cpu")[0]
        assert psnr(shots.routing[i], expected) > 40, i
        assert psnr(video[i], expected) > 20, i  # H.264 halves the colours' resolution: 32 px of sharp colour edges
    colours = {tuple(c) for frame in shots.routing for c in frame.reshape(-1, 3)}
    assert len(colours) > 2  # blended: the gate gives both experts weight somewhere


# ----------------------------------------------------------------------------- the command refuses


def test_a_bad_file_is_refused_before_anything_is_read_or_written(trained_ws, tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(broken(nan_matrix)))
    before = sorted(p.relative_to(trained_ws) for p in trained_ws.rglob("*"))
    proc = run_cli("render", "-w", str(trained_ws), "--model", "dvgo-12", "--camera-path", str(bad), "--device", "cpu")
    assert_clean_failure(proc, f"camera path {bad}: camera_path[2].camera_to_world has a NaN or infinite value")
    proc = run_cli("render", "-w", str(trained_ws), "--camera-path", str(bad), "--device", "cpu")
    assert_clean_failure(proc, "--camera-path renders one model: add --model NAME")
    proc = run_cli("render", "-w", str(trained_ws), "--model", "dvgo-12", "--camera-path", str(bad), "--path", "orbit")
    assert_clean_failure(proc, "are separate outputs")
    for option in ("--frames", "--fps"):  # --path's options, silently ignored elsewhere (a camera path sets its own)
        proc = run_cli("render", "-w", str(trained_ws), "--model", "dvgo-12", "--camera-path", str(bad), option, "10")
        assert_clean_failure(proc, f"{option} sets a --path video's")
    assert sorted(p.relative_to(trained_ws) for p in trained_ws.rglob("*")) == before


def test_an_mp4_without_ffmpeg_is_refused_before_a_frame_is_rendered(trained_ws, tmp_path, monkeypatch, capsys):
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    file = tmp_path / "p.json"
    file.write_text(json.dumps(nerfstudio_file()))
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    rendered = []
    monkeypatch.setattr(render_stage, "render_image", lambda *a, **k: rendered.append(1))
    code, err = cli_in_process(monkeypatch, capsys, "render", "-w", str(ws), "--model", "dvgo-12", "--camera-path",
                               str(file), "--device", "cpu")
    assert code == 2 and "cannot write p.mp4" in err and not rendered
    assert not (ws / "renders").exists()


# ----------------------------------------------------------------------------- the viewer


def test_the_viewer_adds_keyframes_from_a_page_and_saves_and_loads_the_path(mixture_ws, tmp_path):
    from boostnerf_cli.stages import view
    from boostnerf_cli.viewpoint.camera import camera_for_view, opencv_pose

    shutil.copytree(mixture_ws, tmp_path / "ws")
    ws = Workspace(tmp_path / "ws")
    viewer = view.Viewer(ws, Survey(ws).scene(), view.Models(ws, "cpu"))
    with pytest.raises(BoostNerfError, match="this page has reported no camera yet"):
        viewer.add_keyframe(1)
    train = viewer.scene.split("train")
    for i in (0, 3, 6):
        pose = opencv_pose(train.poses[i])
        viewer.moved(1, camera_for_view(pose[:3, :3], pose[:3, 3], math.radians(45), 1.5, 24), now=float(i))
        assert viewer.add_keyframe(1) == len(viewer.path.keyframes) - 1
    assert [k.fov for k in viewer.path.keyframes] == pytest.approx([45.0] * 3, abs=1e-4)
    assert np.allclose(viewer.path.keyframes[1].pose, train.poses[3].double().numpy(), atol=1e-5)
    assert (viewer.path.width, viewer.path.height) == (train.width, train.height)  # the training views' size
    viewer.path.move(2, -1)
    viewer.path.configure(1.0, 6, 1.0, False, 32, 32)
    file = viewer.save_path("walk")
    assert file == ws.root / "camera_paths" / "walk.json" and viewer.saved_paths() == ["walk"]
    with pytest.raises(BoostNerfError, match="is no camera path name"):
        viewer.save_path("../elsewhere")
    saved = viewer.path
    viewer.path = CameraPath()
    loaded = viewer.load_path("walk")
    assert loaded is viewer.path and len(loaded.keyframes) == 3
    for a, b in zip(loaded.keyframes, saved.keyframes):
        assert np.allclose(a.pose, b.pose, atol=1e-9)
    frames_only = json.loads(file.read_text())
    frames_only["keyframes"] = []
    (ws.root / "camera_paths" / "frames.json").write_text(json.dumps(frames_only))
    with pytest.raises(BoostNerfError, match="has frames but no keyframes to edit"):
        viewer.load_path("frames")
    # the file renders: one frame per entry (6 fps over 1 s, both ends)
    proc = run_cli("render", "-w", str(ws.root), "--model", "dvgo-12", "--camera-path", str(file), "--device", "cpu",
                   check=True)
    check_videos(proc, ws.root / "renders" / "dvgo-12", "walk", 7, ("depth",))


class Page:
    """What the preview drives of a browser's page: its camera, each change sent in one message (`atomic`)."""

    def __init__(self) -> None:
        self.camera = type("Camera", (), {})()
        self.shown: list = []

    @contextlib.contextmanager
    def atomic(self):
        yield
        self.shown.append((np.array(self.camera.position), self.camera.fov))


def test_the_page_has_the_camera_path_panel_and_draws_the_path(mixture_ws, tmp_path):
    import threading

    from boostnerf_cli.stages import view
    from boostnerf_cli.viewpoint.camera import camera_for_view, opencv_pose

    shutil.copytree(mixture_ws, tmp_path / "ws")
    ws = Workspace(tmp_path / "ws")
    viewer = view.Viewer(ws, Survey(ws).scene(), view.Models(ws, "cpu"))
    page = view.start_server(viewer, "127.0.0.1", 0)
    try:
        panel = page.path_panel
        train = viewer.scene.split("train")

        class Event:  # what viser passes a button's callback
            client, client_id = None, 7

        for i in (0, 4):
            pose = opencv_pose(train.poses[i])
            viewer.moved(7, camera_for_view(pose[:3, :3], pose[:3, 3], 0.8, 1.0, 24), now=float(i))
            panel.edit(Event(), lambda: panel.select(viewer.add_keyframe(7)))
        assert len(viewer.path.keyframes) == 2 and int(panel.index.value) == 1
        assert page.server.scene.get_handle_by_name("/camera_path/keyframe1") is not None
        assert page.server.scene.get_handle_by_name("/camera_path/line") is not None
        panel.fov.value = 30.0  # a widget set calls its callback: keyframe N's field of view
        assert viewer.path.keyframes[1].fov == 30.0 and "1: 30.0 deg" in panel.listing.content
        panel.seconds.value = 2.0
        panel.smoothness.value = 0.0
        assert (viewer.path.seconds, viewer.path.smoothness) == (2.0, 0.0)
        panel.edit(Event(), lambda: viewer.path.delete(5))  # refused: the path is unchanged
        assert len(viewer.path.keyframes) == 2
        panel.name.value = "two"
        panel.edit(Event(), lambda: viewer.save_path(panel.name.value))
        assert list(panel.saved.options) == ["two"]
        panel.fps.value, panel.seconds.value = 10.0, 0.5  # the preview: 6 frames, a tenth of a second apart
        client = Page()
        panel.play(client)
        for _ in range(100):
            if panel.playing is None:
                break
            threading.Event().wait(0.1)
        frames = viewer.path.frames()
        assert len(client.shown) == len(frames) == 6
        for (position, fov), f in zip(client.shown, frames):
            assert np.allclose(position, f.pose[:3, 3]) and fov == pytest.approx(math.radians(f.fov))
    finally:
        page.server.stop()


def test_a_path_through_a_colmap_models_own_poses_is_its_views_in_the_scenes_world(tmp_path):
    """A forward-facing COLMAP capture (rescaled and recentred inside boostnerf): a path written from images.bin's
    world-to-camera OpenCV poses (turned to camera-to-world OpenGL, the model's world kept) reads back as the
    scene's own cameras."""
    from boostnerf_cli.scenes import load_scene
    from boostnerf_cli.scenes.colmap_model import read_model

    folder = make_scene(tmp_path / "colmap", size=16, n_train=8, n_test=0, layout="colmap", rig="forward")
    scene = load_scene(folder)
    frame = DataFrame.of(scene.extra)
    assert scene.extra.get("forward_facing") and not frame.identity
    images = sorted(read_model(folder / "sparse" / "0").images.values(), key=lambda im: im.name)
    poses = []
    for im in images:
        w, x, y, z = im.qvec
        r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])  # world to camera
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = r.T, -r.T @ np.asarray(im.tvec)
        poses.append(pose @ np.diag([1.0, -1.0, -1.0, 1.0]))  # OpenCV's camera axes to OpenGL's
    read = read_camera_path(views_file(poses, 40.0, 16, 16, tmp_path / "p.json"), frame)
    names = [Path(im.name).stem for im in images]
    for split in scene.splits.values():
        for i, name in enumerate(split.names):
            assert np.allclose(read.frames[names.index(name)].pose, split.poses[i].double().numpy(), atol=2e-5)


def test_camera_path_through_the_datasets_views_passes_them_and_renders_them(trained_ws, tmp_path):
    """`boostnerf camera-path --views` writes a path whose keyframes are those views, in order, frames of the split's
    size; its frames at the keyframes' times are those views, so `render --camera-path` draws them; a view the split
    does not have is one line, and nothing is written."""
    out = tmp_path / "through.json"
    proc = run_cli("camera-path", "-w", str(trained_ws), "--views", "2,0,1", "--split", "test", "--seconds", "2",
                   "--fps", "3", "--smoothness", "0.5", "--out", str(out), check=True)
    assert proc.stdout.split() == [str(out)]
    scene = Survey(Workspace(trained_ws)).scene()
    test = scene.split("test")
    read = read_camera_path(out, DataFrame.of(scene.extra))
    assert (read.path.width, read.path.height, read.path.fps, read.path.smoothness) == (test.width, test.height, 3,
                                                                                          0.5)
    for k, i in zip(read.path.keyframes, (2, 0, 1)):
        assert np.allclose(k.pose, test.poses[i].double().numpy(), atol=1e-5)
    assert len(read.frames) == 7  # 2 s at 3 fps, both ends
    for frame, i in ((0, 2), (3, 0), (6, 1)):
        assert np.allclose(read.frames[frame].pose, test.poses[i].double().numpy(), atol=1e-5)
    bad = run_cli("camera-path", "-w", str(trained_ws), "--views", "0,99", "--out", str(tmp_path / "bad.json"))
    assert bad.returncode == 2 and bad.stderr.strip().splitlines()[-1].startswith("error: there is no view 99")
    assert "Traceback" not in bad.stderr and not (tmp_path / "bad.json").exists()


def test_camera_path_never_writes_over_the_workspace_s_own_files(trained_ws, tmp_path):
    """`camera-path --out` naming the manifest or a file among the models, reports, checkpoints or cache is one line,
    and the file is left as it was (written over, the manifest made the workspace unreadable)."""
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    (ws / "reports").mkdir(exist_ok=True)
    for own in ("manifest.json", "experts/dvgo-12.json", "reports/eval.json", "moe/top2.json", "cache/x.json"):
        target = ws / own
        before = target.read_bytes() if target.exists() else None
        proc = run_cli("camera-path", "-w", str(ws), "--views", "0,1", "--out", str(target))
        assert_clean_failure(proc, "is the workspace's own")
        assert (target.read_bytes() if target.exists() else None) == before, own
    elsewhere = tmp_path / "scratch"  # the cache on another disk, through a link: still the workspace's own
    elsewhere.mkdir()
    shutil.rmtree(ws / "cache", ignore_errors=True)
    (ws / "cache").symlink_to(elsewhere, target_is_directory=True)
    for own in (ws / "cache" / "x.json", ws / "scene" / "transforms_train.json"):  # scene: a generated default one
        assert_clean_failure(run_cli("camera-path", "-w", str(ws), "--views", "0,1", "--out", str(own)),
                             "is the workspace's own")
    assert not (elsewhere / "x.json").exists() and not (ws / "scene").exists()
    out = ws / "camera_paths" / "mine.json"
    run_cli("camera-path", "-w", str(ws), "--views", "0,1", "--out", str(out), check=True)
    assert out.exists()
