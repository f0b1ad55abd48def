"""Camera paths for videos, the heat map, panel grids and video files (no training needed)."""

import math

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from boostnerf_cli import images
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.render.paths import (
    camera_path,
    focus_point,
    look_at,
    orbit_path,
    scene_up,
    spiral_path,
)


def _random_rotation(seed: int) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def _ring(n=12, radius=3.0, height=1.5, centre=(0.2, -0.1, 0.3), rot=None):
    """Cameras on a circle around the z axis (rotated by `rot`), looking at `centre`."""
    rot = torch.eye(3, dtype=torch.float64) if rot is None else rot
    c = torch.tensor(centre, dtype=torch.float64)
    up = rot @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    poses = []
    for i in range(n):
        t = 2 * math.pi * (i + 0.3) / n
        pos = c + rot @ torch.tensor([radius * math.cos(t), radius * math.sin(t), height], dtype=torch.float64)
        poses.append(look_at(pos, c, up))
    return torch.stack(poses), c, up


def _check_orthonormal(poses):
    rot = poses[:, :3, :3]
    eye = torch.eye(3, dtype=poses.dtype).expand_as(rot)
    assert torch.allclose(rot.transpose(1, 2) @ rot, eye, atol=1e-9)
    assert torch.allclose(torch.det(rot), torch.ones(len(poses), dtype=poses.dtype), atol=1e-9)


def test_look_at_points_the_camera_minus_z_at_the_target():
    pose = look_at(torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                   torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    forward = -pose[:3, 2]
    assert torch.allclose(forward, -torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64) / math.sqrt(14), atol=1e-12)
    assert pose[2, 1] > 0  # image up has a positive z component
    _check_orthonormal(pose[None])


@pytest.mark.parametrize("seed", [0, 1])
def test_orbit_follows_the_training_ring_in_any_orientation(seed):
    rot = _random_rotation(seed) if seed else None
    poses, centre, up = _ring(rot=rot)
    assert torch.allclose(focus_point(poses), centre, atol=1e-9)
    assert torch.allclose(scene_up(poses), up, atol=0.1)  # mean camera up: close to the axis, not equal
    path = orbit_path(poses, 16)
    assert path.shape == (16, 4, 4)
    _check_orthonormal(path)
    rel = path[:, :3, 3] - centre
    axis = scene_up(poses)
    height = rel @ axis
    radial = torch.linalg.norm(rel - height[:, None] * axis, dim=-1)
    train_rel = poses[:, :3, 3] - centre
    train_h = train_rel @ axis
    train_r = torch.linalg.norm(train_rel - train_h[:, None] * axis, dim=-1)
    assert torch.allclose(height, train_h.mean().expand(16), atol=1e-9)
    assert torch.allclose(radial, train_r.mean().expand(16), atol=1e-9)
    to_centre = torch.nn.functional.normalize(centre - path[:, :3, 3], dim=-1)
    assert torch.allclose((-path[:, :3, 2] * to_centre).sum(-1), torch.ones(16, dtype=torch.float64), atol=1e-9)
    # one full turn, evenly spaced, starting at the first training camera's azimuth
    a0 = torch.nn.functional.normalize(train_rel[0] - train_h[0] * axis, dim=0)
    a1 = torch.nn.functional.normalize(rel[0] - height[0] * axis, dim=0)
    assert float(a0 @ a1) > 1 - 1e-9
    steps = torch.linalg.norm(path[1:, :3, 3] - path[:-1, :3, 3], dim=-1)
    assert torch.allclose(steps, steps[0].expand_as(steps), atol=1e-9)


def _forward_facing(n=20, seed=0):
    """Cameras spread over a small patch of the plane z = 0, all looking down -z (an LLFF-like capture)."""
    g = torch.Generator().manual_seed(seed)
    poses = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    poses[:, 0, 3] = torch.rand(n, generator=g, dtype=torch.float64) * 0.6 - 0.3
    poses[:, 1, 3] = torch.rand(n, generator=g, dtype=torch.float64) * 0.4 - 0.2
    poses[:, 2, 3] = torch.rand(n, generator=g, dtype=torch.float64) * 0.1 - 0.05
    bbox = torch.tensor([[-2.0, -1.5, -8.0], [2.0, 1.5, -2.0]], dtype=torch.float64)
    return poses, bbox


def test_spiral_circles_the_mean_pose_and_looks_at_the_box_centre_depth():
    poses, bbox = _forward_facing()
    path = spiral_path(poses, bbox, 0.5, 20.0, 30)
    _check_orthonormal(path)
    mean_pos = poses[:, :3, 3].mean(0)
    focus = float(bbox.mean(0)[2] - mean_pos[2]) * -1  # the box centre is 5 units in front
    target = mean_pos + torch.tensor([0.0, 0.0, -focus], dtype=torch.float64)
    to_target = torch.nn.functional.normalize(target - path[:, :3, 3], dim=-1)
    assert torch.allclose((-path[:, :3, 2] * to_target).sum(-1), torch.ones(30, dtype=torch.float64), atol=1e-9)
    offsets = (path[:, :3, 3] - mean_pos).abs()
    spread = (poses[:, :3, 3] - mean_pos).abs().amax(0)
    assert (offsets <= spread + 1e-9).all()  # stays within the cameras' spread (90th percentile radii)
    assert offsets[:, 0].max() > 0.5 * spread[0] and offsets[:, 1].max() > 0.5 * spread[1]
    assert (path[:, 1, 1] > 0.99).all()  # keeps the cameras' up


def test_paths_reject_degenerate_cameras():
    poses, bbox = _forward_facing()
    with pytest.raises(BoostNerfError, match="spiral"):
        orbit_path(poses, 8)  # forward-facing: every optical axis parallel
    with pytest.raises(BoostNerfError, match="orbit or spiral"):
        camera_path("zoom", poses, bbox, 0.5, 20.0, 8)
    with pytest.raises(BoostNerfError, match="--frames"):
        spiral_path(poses, bbox, 0.5, 20.0, 0)


def test_heat_map_is_monotonic_in_brightness_and_clips():
    v = np.linspace(-0.5, 1.5, 201)
    rgb = images.heat(v).astype(float)
    lum = rgb @ np.array([0.299, 0.587, 0.114])
    assert (np.diff(lum) >= -1e-9).all()
    assert (rgb[0] == 0).all() and rgb[-1].min() > 200  # black below the range, near-white above


def test_panel_grid_places_labelled_enlarged_panels():
    a = np.zeros((16, 20, 3), np.uint8)
    b = np.full((16, 20, 3), 255, np.uint8)
    grid = images.panel_grid([[("a", a), ("b", b)], [("c", None), ("d", a)]], min_width=60, caption="x")
    assert grid.dtype == np.uint8 and grid.ndim == 3
    k = 3  # 20 px enlarged to >= 60
    assert grid.shape[1] == 2 * (20 * k + 4) + 4
    assert grid.shape[0] == 2 * (16 * k + 18 + 4) + 4 + 20


def test_video_mp4_and_gif(tmp_path, monkeypatch):
    frames = [np.full((15, 21, 3), 20 * i, np.uint8) for i in range(5)]  # odd sides: padded for yuv420p
    assert images.ffmpeg_available()  # imageio-ffmpeg is a core dependency
    target, fmt = images.video_target(tmp_path / "v.mp4")
    assert (target.name, fmt) == ("v.mp4", "mp4")
    images.write_videos([(target, frames)], 10, fmt)
    read = list(iio.imiter(target))
    assert len(read) == 5 and read[0].shape[:2] == (16, 22)
    assert abs(float(read[3].mean()) - 60) < 4
    target, fmt = images.video_target(tmp_path / "v.gif")
    assert (target.name, fmt) == ("v.gif", "gif")
    images.write_videos([(target, frames)], 10, fmt)
    read = iio.imread(target, index=None)
    assert read.shape[:3] == (5, 15, 21) and abs(float(read[3][..., :3].mean()) - 60) < 2
    with pytest.raises(BoostNerfError, match=".mp4 or .gif"):
        images.video_target(tmp_path / "v.avi")
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary files left


def test_an_mp4_without_the_ffmpeg_backend_is_refused_not_turned_into_a_gif(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # `import imageio_ffmpeg` raises ImportError
    assert not images.ffmpeg_available()
    with pytest.raises(BoostNerfError, match="cannot write v.mp4: .*imageio-ffmpeg"):
        images.video_target(tmp_path / "v.mp4")
    assert images.video_target(tmp_path / "v.gif") == (tmp_path / "v.gif", "gif")  # GIF needs no ffmpeg
    monkeypatch.undo()

    class NoBinary:
        @staticmethod
        def get_ffmpeg_exe():
            raise RuntimeError("No ffmpeg exe could be found")

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", NoBinary)  # installed, but no ffmpeg binary
    assert not images.ffmpeg_available()
    assert list(tmp_path.iterdir()) == []


def test_gate_by_detail_splits_pixels_at_the_median_detail():
    from boostnerf_cli.stages.render import gate_by_detail

    gt = np.zeros((8, 8, 3))
    gt[:, 4:] = np.random.default_rng(0).random((8, 4, 1))  # noise (detail) on the right half, flat left
    probs = np.zeros((8, 8, 2))
    probs[:, :4, 0] = 1.0  # expert 0 on the flat half
    probs[:, 4:, 1] = 1.0  # expert 1 on the checkerboard
    detailed, smooth = gate_by_detail(probs, gt, np.ones((8, 8), bool))
    assert detailed[1] > 0.7 and smooth[0] > 0.7
    assert np.allclose(detailed.sum(), 1.0) and np.allclose(smooth.sum(), 1.0)
    # a flat colour: no pixel more detailed than the median, so no detailed half (it was nan: "no pixel is opaque")
    detailed, smooth = gate_by_detail(probs, np.full((8, 8, 3), 0.5), np.ones((8, 8), bool))
    assert np.allclose(detailed, [0.5, 0.5]) and np.allclose(smooth, [0.5, 0.5])


def test_a_spiral_on_a_forward_facing_scene_looks_where_its_cameras_look(tmp_path):
    """`render --path spiral` on an LLFF scene (NDC) wrote all-white videos: the focus depth was read off the NDC box
    as if in world units (0.0006 in front of the mean camera), so every frame looked sideways. Every frame now looks
    within a few degrees of the training cameras' direction, at a focus past the NDC near plane."""
    from boostnerf_cli.render.paths import camera_path
    from boostnerf_cli.scenes import load_scene, make_scene

    scene = load_scene(make_scene(tmp_path / "llff", size=24, n_train=8, n_test=0, layout="llff"))
    train = scene.split("train")
    box = scene.bbox.clone()
    box[:, 2] = torch.tensor([-1.002, 1.0])  # an expert's NDC box, its content reaching to infinity
    path = camera_path("spiral", train.poses, box, scene.near, scene.far, 12, scene.ndc)
    look = torch.nn.functional.normalize(train.poses[:, :3, 2].mean(0), dim=0)  # cameras look down -z
    cosines = path[:, :3, 2] @ look
    assert bool((cosines > math.cos(math.radians(15))).all()), cosines
