"""Every dataset format on generated scenes: same cameras and images, known projections, NDC, errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from boostnerf_cli.cameras import WITH_LENS, DataFrame
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.render.rays import NDC, image_rays, project_points
from boostnerf_cli.scenes import LAYOUTS, detect_format, load_scene, make_scene
from boostnerf_cli.scenes.frames import resolve_image
from boostnerf_cli.scenes.procedural import CAMERA_ANGLE_X, camera_poses, forward_poses, sequence_order
from tests.conftest import cli_in_process, run_cli

SIZE, N_TRAIN, N_TEST = 16, 14, 3  # 14 train views leave room for 3 test views at every 8th place
# layouts that store 8-bit RGBA (compared exactly) vs RGB composited on white before quantising
COMPOSITED = {"tanks", "llff", "colmap"}
SEQUENCE = {"llff", "nerfstudio", "colmap"}  # one sequence of views, test views at every 8th place (sequence_order)


@pytest.fixture(scope="module")
def forward(tmp_path_factory):
    """The same forward-facing views written in every layout."""
    root = tmp_path_factory.mktemp("formats")
    return {lay: make_scene(root / lay, size=SIZE, n_train=N_TRAIN, n_test=N_TEST, layout=lay, rig="forward")
            for lay in LAYOUTS}


def _all_views(scene, order=None):
    """Every view of a scene loaded with holdout_every=0, in written order (train, then val/test), or in
    `order` ((split, index) pairs) for the Blender reference of a one-sequence layout."""
    if order is not None:
        pick = lambda attr: torch.stack([getattr(scene.splits[s], attr)[i] for s, i in order])  # noqa: E731
        return pick("images"), pick("poses").double(), pick("intrinsics")
    splits = [scene.splits[s] for s in ("train", "val", "test") if s in scene.splits]
    return (torch.cat([s.images for s in splits]), torch.cat([s.poses for s in splits]).double(),
            torch.cat([s.intrinsics for s in splits]))


@pytest.mark.parametrize("layout", [lay for lay in LAYOUTS if lay != "blender"])
def test_every_format_loads_the_same_cameras_and_images(forward, layout):
    ref = load_scene(forward["blender"], holdout_every=0)
    scene = load_scene(forward[layout], holdout_every=0)
    assert scene.format == layout
    assert scene.extra["detected"].startswith(layout)
    images, poses, k = _all_views(scene)
    ref_images, ref_poses, ref_k = _all_views(ref, sequence_order(N_TRAIN, N_TEST) if layout in SEQUENCE else None)
    atol = 2.0 / 255 if layout in COMPOSITED else 1e-6
    torch.testing.assert_close(images, ref_images, atol=atol, rtol=0)
    torch.testing.assert_close(k, ref_k, atol=1e-4, rtol=1e-6)
    torch.testing.assert_close(DataFrame.of(scene.extra).poses_to_data(poses), ref_poses, atol=1e-5, rtol=0)


def _known_pixel(layout):
    """A world point on the ray through the centre of pixel (5, 7) of view 0 of the generating camera,
    at depth 3.3 (computed here from the generator's camera definition, not from any loader)."""
    train, test = (forward_poses if layout == "llff" else camera_poses)(N_TRAIN, N_TEST)
    split, i = sequence_order(N_TRAIN, N_TEST)[0] if layout in SEQUENCE else ("train", 0)  # the first view loaded
    pose = (train if split == "train" else test)[i]
    f = 0.5 * SIZE / math.tan(0.5 * CAMERA_ANGLE_X)
    u, v = 5.5, 7.5
    d_cam = np.array([(u - SIZE / 2) / f, -(v - SIZE / 2) / f, -1.0])
    point = pose[:3, 3] + 3.3 * (pose[:3, :3] @ d_cam)
    return point, (u, v)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_known_point_projects_to_the_expected_pixel(tmp_path, layout):
    folder = make_scene(tmp_path / layout, size=SIZE, n_train=N_TRAIN, n_test=N_TEST, layout=layout)
    scene = load_scene(folder, holdout_every=0, format=layout)
    point, (u, v) = _known_pixel(layout)
    p = torch.tensor(point, dtype=torch.float64)
    p = DataFrame.of(scene.extra).points_to_world(p)
    pose, k = scene.splits["train"].poses[0], scene.splits["train"].intrinsics[0]
    uv, depth = project_points(p[None].float(), pose, k)
    torch.testing.assert_close(uv[0], torch.tensor([u, v]), atol=2e-3, rtol=0)
    assert float(depth[0]) > 0
    # the loaded camera's ray through that pixel passes through the point (in NDC for LLFF)
    o, d = image_rays(pose, k, SIZE, SIZE, scene.ndc)
    o, d = o[7 * SIZE + 5].double(), d[7 * SIZE + 5].double()
    q = scene.ndc.points(p[None])[0] if scene.ndc is not None else p
    off = (q - o) - torch.dot(q - o, d) * d
    assert float(off.norm()) < 1e-4 * max(1.0, float((q - o).norm()))
    if scene.ndc is not None:  # the NDC box holds the point's NDC image
        assert bool(((q >= scene.bbox[0].double()) & (q <= scene.bbox[1].double())).all())


def test_auto_detection_names_what_it_found_and_what_it_looked_for(forward, tmp_path):
    assert detect_format(forward["llff"]) == ("llff", "poses_bounds.npy and images/, images_2/")
    assert detect_format(forward["tanks"])[0] == "tanks"
    assert detect_format(forward["nsvf"])[0] == "nsvf"
    assert detect_format(forward["nerfstudio"]) == ("nerfstudio", "transforms.json")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BoostNerfError) as e:
        detect_format(tmp_path / "empty")
    for name in LAYOUTS:
        assert name in str(e.value)
    assert "poses_bounds.npy" in str(e.value) and "transforms.json" in str(e.value)


# ----------------------------------------------------------------------------- NDC


def test_ndc_maps_world_rays_onto_ndc_rays():
    ndc = NDC(sx=2.3, sy=1.7, near=1.0)
    g = torch.Generator().manual_seed(0)
    o = torch.randn(64, 3, generator=g, dtype=torch.float64) * 0.3
    d = torch.randn(64, 3, generator=g, dtype=torch.float64) * 0.3 + torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    on, dn = ndc.rays(o, d)
    torch.testing.assert_close(on[:, 2], torch.full((64,), -1.0, dtype=torch.float64))  # on the NDC near plane
    torch.testing.assert_close(dn.norm(dim=-1), torch.ones(64, dtype=torch.float64))
    for depth in (1.5, 3.0, 50.0):  # world points on each ray map onto its NDC ray, in order
        t = (depth + o[:, 2]) / -d[:, 2]
        q = ndc.points(o + t[:, None] * d)
        s = ((q - on) * dn).sum(-1)
        torch.testing.assert_close(on + s[:, None] * dn, q, atol=1e-9, rtol=0)
        assert bool((s > 0).all())
    far = ndc.points(torch.tensor([[0.2, -0.1, -1e9]], dtype=torch.float64))
    assert abs(float(far[0, 2]) - 1.0) < 1e-8


def test_llff_ndc_box_holds_every_training_ray(forward):
    scene = load_scene(forward["llff"], holdout_every=8)
    train = scene.splits["train"]
    for i in range(len(train)):
        o, d = image_rays(train.poses[i], train.intrinsics[i], train.height, train.width, scene.ndc)
        end = o + ((1 - o[:, 2]) / d[:, 2])[:, None] * d
        for pts in (o, end):
            assert bool(((pts >= scene.bbox[0] - 1e-4) & (pts <= scene.bbox[1] + 1e-4)).all())
    assert scene.near == 0 and scene.far >= float((scene.bbox[1] - scene.bbox[0]).norm()) - 1e-6
    assert scene.holdout.startswith("every 8th")
    assert scene.splits["test"].names == ("image000", "image008", "image016")


def test_llff_axis_convention_bounds_and_recentring(forward):
    scene = load_scene(forward["llff"], holdout_every=0)
    poses = scene.splits["train"].poses.double()
    # recentred: the mean camera centre is the origin and the mean viewing direction is -z
    torch.testing.assert_close(poses[:, :3, 3].mean(0), torch.zeros(3, dtype=torch.float64), atol=1e-5, rtol=0)
    view = -poses[:, :3, 2].sum(0)
    assert float(view[2] / view.norm()) < -1 + 1e-6
    # rescaled: the smallest near bound is 1 / 0.75
    assert abs(min(b[0] for b in scene.extra["bounds"]) - 1 / 0.75) < 1e-9
    assert all(abs(float(torch.linalg.det(p[:3, :3])) - 1) < 1e-5 for p in poses)


def test_llff_image_folder_choice(forward):
    half = load_scene(forward["llff"], image_size=SIZE // 2, holdout_every=0)
    full = load_scene(forward["llff"], image_size=None, holdout_every=0)
    assert half.extra["images_folder"] == "images_2" and full.extra["images_folder"] == "images"
    torch.testing.assert_close(half.splits["train"].intrinsics * 2, full.splits["train"].intrinsics)
    with pytest.raises(BoostNerfError, match="never upscaled"):
        load_scene(forward["llff"], image_size=SIZE * 2)


def test_nerfstudio_per_frame_intrinsics(forward, tmp_path):
    import shutil

    folder = tmp_path / "ns"
    shutil.copytree(forward["nerfstudio"], folder)
    meta = json.loads((folder / "transforms.json").read_text())
    glob = {k: meta.pop(k) for k in ("fl_x", "fl_y", "cx", "cy", "w", "h")}
    for i, frame in enumerate(meta["frames"]):
        frame.update(glob)
        if i == 1:
            frame.update(fl_x=glob["fl_x"] * 1.5, cy=glob["cy"] + 2)
    (folder / "transforms.json").write_text(json.dumps(meta))
    k = load_scene(folder, holdout_every=0).splits["train"].intrinsics
    assert abs(float(k[0, 0]) - glob["fl_x"]) < 1e-4 and abs(float(k[1, 0]) - 1.5 * glob["fl_x"]) < 1e-3
    assert abs(float(k[1, 3]) - (glob["cy"] + 2)) < 1e-4 and abs(float(k[1, 1]) - glob["fl_y"]) < 1e-4


# ----------------------------------------------------------------------------- malformed inputs, through the CLI


def _copy(src, dst):
    import shutil

    shutil.copytree(src, dst)
    return dst


def _break_llff_count(f):
    (f / "images" / "image005.png").unlink()
    (f / "images_2" / "image005.png").unlink()


def _break_llff_nan(f):
    arr = np.load(f / "poses_bounds.npy")
    arr[3, 3] = np.nan
    np.save(f / "poses_bounds.npy", arr)


def _break_llff_sizes(f):
    iio.imwrite(f / "images" / "image004.png", np.zeros((SIZE + 2, SIZE, 3), np.uint8))


def _break_nsvf_intrinsics(f):
    (f / "intrinsics.txt").unlink()


def _break_nsvf_nan(f):
    path = sorted((f / "pose").glob("0_*.txt"))[2]
    pose = np.loadtxt(path)
    pose[1, 3] = np.nan
    np.savetxt(path, pose)


def _break_tanks_count(f):
    (f / "pose" / "0_train_0099.txt").write_text(" ".join(["1", "0", "0", "0"] * 4))


def _break_ns_intrinsics(f):
    meta = json.loads((f / "transforms.json").read_text())
    del meta["fl_x"], meta["fl_y"]
    (f / "transforms.json").write_text(json.dumps(meta))


def _break_ns_camera_model(f):
    meta = json.loads((f / "transforms.json").read_text())
    meta["frames"][2]["camera_model"] = "EQUIRECTANGULAR"
    (f / "transforms.json").write_text(json.dumps(meta))


def _break_ns_zero_size(f):
    meta = json.loads((f / "transforms.json").read_text())
    meta.update(w=0, h=0)
    (f / "transforms.json").write_text(json.dumps(meta))


def _break_ns_size_text(f):
    meta = json.loads((f / "transforms.json").read_text())
    meta.update(w="32px", h="32px")
    (f / "transforms.json").write_text(json.dumps(meta))


def _break_blender_empty_train(f):
    meta = json.loads((f / "transforms_train.json").read_text())
    meta["frames"] = []
    (f / "transforms_train.json").write_text(json.dumps(meta))


def _break_ns_sizes(f):
    iio.imwrite(f / "images" / "frame_00003.png", np.zeros((SIZE, SIZE + 4, 4), np.uint8))


MALFORMED = [
    ("llff", _break_llff_count, "has 17 poses but images/ holds 16 images"),
    ("llff", _break_llff_nan, "row 3 (image 3) contains NaN"),
    ("llff", _break_llff_sizes, "all views must have the same size"),
    ("nsvf", _break_nsvf_intrinsics, "has no intrinsics.txt"),
    ("nsvf", _break_nsvf_nan, "contains NaN or infinite values"),
    ("tanks", _break_tanks_count, "has 14 images but 15 poses"),
    ("nerfstudio", _break_ns_intrinsics, "no fl_x"),
    ("nerfstudio", _break_ns_camera_model, "camera_model EQUIRECTANGULAR is not supported"),
    ("nerfstudio", _break_ns_sizes, "all views must have the same size"),
    ("nerfstudio", _break_ns_zero_size, "w = 0 must be a positive number"),
    ("nerfstudio", _break_ns_size_text, "w = '32px' is not a number"),
    ("blender", _break_blender_empty_train, "transforms_train.json has an empty 'frames' list"),
]


@pytest.mark.parametrize("layout,breaker,message", MALFORMED, ids=[m[1].__name__[7:] for m in MALFORMED])
def test_malformed_input_is_one_clear_line_through_the_cli(forward, tmp_path, monkeypatch, capsys, layout, breaker,
                                                           message):
    folder = _copy(forward[layout], tmp_path / layout)
    breaker(folder)
    code, stderr = cli_in_process(monkeypatch, capsys, "pretrain", "--data", str(folder), "--workspace",
                                   str(tmp_path / "ws"), "--device", "cpu")
    assert code == 2, stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], stderr


def test_unknown_layout_through_the_cli(tmp_path, monkeypatch, capsys):
    (tmp_path / "empty").mkdir()
    code, stderr = cli_in_process(monkeypatch, capsys, "pretrain", "--data", str(tmp_path / "empty"),
                                   "--workspace", str(tmp_path / "ws"), "--device", "cpu")
    assert code == 2
    (line,) = stderr.strip().splitlines()
    assert line.startswith("error: cannot tell the dataset format") and "llff: poses_bounds.npy" in line


# ----------------------------------------------------------------------------- end to end


def test_llff_pretrain_and_render_end_to_end(tmp_path, tiny_recipe):
    """A forward-facing scene in the LLFF layout trains in NDC and renders through the real CLI."""
    folder = make_scene(tmp_path / "llff", size=24, n_train=10, n_test=2, layout="llff")
    ws = tmp_path / "ws"
    proc = run_cli("pretrain", "--data", str(folder), "--recipe", str(tiny_recipe), "--workspace", str(ws),
                   "--res", "12", "--image-size", "24", "--device", "cpu", check=True)
    assert "format: llff (found poses_bounds.npy and images/, images_2/)" in proc.stderr
    report = json.loads((ws / "experts" / "dvgo-12.json").read_text())
    scene = load_scene(folder, image_size=24)
    test = scene.splits["test"].images
    mean_colour = -10 * math.log10(float(((test - scene.splits["train"].images.mean((0, 1, 2))) ** 2).mean()))
    assert report["test_psnr"] > mean_colour + 2.5  # 30 steps: measured 14.7 dB against 11.3 dB for the mean colour
    manifest = json.loads((ws / "manifest.json").read_text())
    assert manifest["scene"]["format"] == "llff" and manifest["scene"]["ndc"]["near"] == 1.0
    run_cli("render", "--workspace", str(ws), "--device", "cpu", check=True)
    out = sorted((ws / "renders" / "dvgo-12" / "test").glob("image*.png"))
    assert [p.name for p in out] == ["image000.png", "image000_depth.png", "image008.png", "image008_depth.png"]
    img = iio.imread(out[0])
    assert img.shape == (24, 24, 3) and img.std() > 5


INTRINSICS_FORMS = {  # intrinsics.txt texts that all say fx 40, fy 42, cx 16, cy 12
    "3x3": "40 0 16\n0 42 12\n0 0 1\n",
    "4x4": "40 0 16 0\n0 42 12 0\n0 0 1 0\n0 0 0 1\n",
    "3x4": "40 0 16 0\n0 42 12 0\n0 0 1 0\n",
    "3x3 on one line": "40 0 16 0 42 12 0 0 1\n",
    "4x4 on one line": "40 0 16 0 0 42 12 0 0 0 1 0 0 0 0 1\n",
    "3x3 and a row of zeros": "40 0 16\n0 42 12\n0 0 1\n0 0 0\n",
}


@pytest.mark.parametrize("form", INTRINSICS_FORMS, ids=list(INTRINSICS_FORMS))
def test_every_layout_of_a_k_matrix_reads_the_same_camera(tmp_path, form):
    """A K matrix as 3x3, 3x4 or 4x4, on separate lines or one, reads as K (a 3x4 K was read as the DeepVoxels
    line `f cx cy`: cx 0, cy 16, held-out PSNR 10.7 instead of 24.8, silently)."""
    from boostnerf_cli.scenes.nsvf import read_intrinsics

    (tmp_path / "intrinsics.txt").write_text(INTRINSICS_FORMS[form])
    assert read_intrinsics(tmp_path) == [40.0, 42.0, 16.0, 12.0]


def test_deepvoxels_intrinsics_and_what_is_neither(tmp_path):
    from boostnerf_cli.scenes.nsvf import read_intrinsics

    (tmp_path / "intrinsics.txt").write_text("40 16 12 0.\n0. 0. 0.\n1.\n32 32\n")
    assert read_intrinsics(tmp_path) == [40.0, 40.0, 16.0, 12.0]
    for text in ("40 0 16\n0 42 12\n0.5 0 1\n", "40 0 16 0 42 12 0 0\n", "1 2\n3 4\n"):
        (tmp_path / "intrinsics.txt").write_text(text)
        with pytest.raises(BoostNerfError, match="intrinsics.txt: expected"):
            read_intrinsics(tmp_path)


def test_what_real_transforms_files_do_loads_as_the_plain_file(forward, tmp_path):
    """Shapes real transforms files take that mean the same cameras: an empty val split (left out), a frame's
    intrinsics set to null (the top-level value applies), a 3x4 transform_matrix, a file_path without its .jpg."""
    import shutil

    ref = load_scene(forward["blender"], holdout_every=0)
    folder = tmp_path / "blender"
    shutil.copytree(forward["blender"], folder)
    (folder / "transforms_val.json").write_text(json.dumps({"camera_angle_x": CAMERA_ANGLE_X, "frames": []}))
    meta = json.loads((folder / "transforms_train.json").read_text())
    meta["frames"][0]["transform_matrix"] = meta["frames"][0]["transform_matrix"][:3]
    meta["frames"][1]["camera_angle_x"] = None
    first = folder / (meta["frames"][2]["file_path"] + ".png")
    iio.imwrite(first.with_suffix(".jpg"), iio.imread(first)[..., :3], quality=100)
    first.unlink()
    meta["frames"][2]["file_path"] = str(Path(meta["frames"][2]["file_path"]).with_suffix(""))
    (folder / "transforms_train.json").write_text(json.dumps(meta))
    got = load_scene(folder, holdout_every=0)
    assert sorted(got.splits) == sorted(ref.splits)
    for s in ref.splits:
        torch.testing.assert_close(got.splits[s].poses, ref.splits[s].poses)
        torch.testing.assert_close(got.splits[s].intrinsics, ref.splits[s].intrinsics)

    ns = tmp_path / "ns"
    shutil.copytree(forward["nerfstudio"], ns)
    meta = json.loads((ns / "transforms.json").read_text())
    for frame in meta["frames"]:
        frame.update(fl_x=None, cx=None)
    (ns / "transforms.json").write_text(json.dumps(meta))
    torch.testing.assert_close(load_scene(ns, holdout_every=0).splits["train"].intrinsics,
                               load_scene(forward["nerfstudio"], holdout_every=0).splits["train"].intrinsics)


def _tag_orientation(path: Path, turn: int = 6) -> None:
    """Store `path`'s pixels turned a quarter and tagged with EXIF orientation `turn` (a phone's portrait shot)."""
    from PIL import Image

    with Image.open(path) as im:
        turned = im.transpose(Image.Transpose.ROTATE_90)
    exif = Image.Exif()
    exif[0x0112] = turn
    turned.save(path, exif=exif)


def test_llff_images_of_another_aspect_than_hwf_are_refused_and_an_exif_turn_is_named(forward, tmp_path):
    """hwf says 16 x 12 (h x w) but the images are square: refused, not trained with fx != fy stretched per axis. A
    portrait image whose EXIF tag turns it is named: boostnerf, like COLMAP, reads the pixels as stored."""
    import shutil

    folder = shutil.copytree(forward["llff"], tmp_path / "llff")
    arr = np.load(folder / "poses_bounds.npy")
    arr[:, 9] *= 0.75  # row-major 3x5: hwf's w is element (1, 4)
    np.save(folder / "poses_bounds.npy", arr)
    with pytest.raises(BoostNerfError, match="does not match the images' aspect"):
        load_scene(folder)
    shutil.rmtree(folder / "images_2", ignore_errors=True)
    for image in sorted((folder / "images").iterdir()):
        _tag_orientation(image)
    with pytest.raises(BoostNerfError, match="EXIF orientation 6"):
        load_scene(folder)


def test_an_aspect_mismatch_in_nerfstudio_names_the_exif_turn(forward, tmp_path):
    import shutil

    folder = shutil.copytree(forward["nerfstudio"], tmp_path / "ns")
    meta = json.loads((folder / "transforms.json").read_text())
    meta.update(h=meta["h"] * 0.75, cy=meta["cy"] * 0.75)
    (folder / "transforms.json").write_text(json.dumps(meta))
    _tag_orientation(folder / meta["frames"][0]["file_path"])
    with pytest.raises(BoostNerfError, match="aspect.*EXIF orientation 6.*reads the pixels as stored"):
        load_scene(folder)


def test_a_k_matrix_with_skew_is_refused(tmp_path):
    """Pixels are square and axes orthogonal in every camera boostnerf renders: a skew s != 0 in K was dropped
    without a word (rays up to 1.8 px off on a 40 px image with s = 5)."""
    from boostnerf_cli.scenes.nsvf import read_intrinsics

    (tmp_path / "intrinsics.txt").write_text("40 5 16\n0 42 12\n0 0 1\n")
    with pytest.raises(BoostNerfError, match=r"skew s = 5 .*not zero.*skew-free"):
        read_intrinsics(tmp_path)
    (tmp_path / "intrinsics.txt").write_text("40 1e-12 16\n-1e-13 42 12\n0 0 1.0000001\n")  # float noise: a K
    assert read_intrinsics(tmp_path) == [40.0, 42.0, 16.0, 12.0]


def _crop_blender(folder: Path, keep_wh: bool) -> None:
    """Crop every image of a Blender copy to 37 x 27 (from the 40 x 40 of `make-scene --size 40`) with the principal
    point moved by the crop: still an exact pinhole camera of the same scene, if `w` / `h` follow the crop."""
    for split in ("train", "test"):
        path = folder / f"transforms_{split}.json"
        meta = json.loads(path.read_text())
        focal = 0.5 * 40 / math.tan(0.5 * meta.pop("camera_angle_x"))
        meta.update(fl_x=focal, fl_y=focal, cx=20 - 3, cy=20 - 5, w=37 if keep_wh else 40, h=27 if keep_wh else 40)
        path.write_text(json.dumps(meta))
        for frame in meta["frames"]:
            image = resolve_image(folder, frame["file_path"], "")
            iio.imwrite(image, iio.imread(image)[5:32, 3:40])


def test_blender_w_and_h_that_do_not_match_the_image_are_refused(tmp_path):
    """A cropped Blender scene whose transforms kept the old w and h (40 x 40 for 37 x 27 images) was read with its
    intrinsics squeezed per axis, silently (held-out PSNR 15.0 dB against 21.2 with w and h right); nerfstudio
    refused the same file. Both loaders now check one way (`frame_intrinsics`)."""
    import shutil

    scene = make_scene(tmp_path / "b", size=40, n_train=4, n_test=1, layout="blender")
    good = shutil.copytree(scene, tmp_path / "good")
    _crop_blender(good, keep_wh=True)
    k = load_scene(good).splits["train"].intrinsics[0].tolist()
    focal = 0.5 * 40 / math.tan(0.5 * json.loads((scene / "transforms_train.json").read_text())["camera_angle_x"])
    assert k == pytest.approx([focal, focal, 17.0, 15.0])
    _crop_blender(scene, keep_wh=False)
    with pytest.raises(BoostNerfError, match=r"w x h = 40 x 40 does not match the image's 37 x 27 aspect"):
        load_scene(scene)


def test_w_without_h_is_refused(forward, tmp_path):
    """nerfstudio `w` without `h`: only x was scaled from w, y kept the image's height (fy doubled, cy on the bottom
    edge: 15.9 dB against 21.4), silently."""
    import shutil

    folder = shutil.copytree(forward["nerfstudio"], tmp_path / "ns")
    meta = json.loads((folder / "transforms.json").read_text())
    meta.update(w=meta["w"] * 2, fl_x=meta["fl_x"] * 2, fl_y=meta["fl_y"] * 2, cx=meta["cx"] * 2, cy=meta["cy"] * 2)
    del meta["h"]
    (folder / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(BoostNerfError, match=r"w is given without h: give both"):
        load_scene(folder)


def test_a_frames_own_field_of_view_wins_over_the_files_focal_length(forward, tmp_path):
    """A frame that gives its own camera_angle_x takes it, even where the file's top level gives fl_x: the frame's
    value merged with the file's made the file's fl_x win (fl_x is read before any angle), silently."""
    import shutil

    folder = shutil.copytree(forward["nerfstudio"], tmp_path / "ns")
    meta = json.loads((folder / "transforms.json").read_text())
    frame = meta["frames"][0]
    frame["camera_angle_x"] = 2 * math.atan(0.5 * meta["w"] / (2 * meta["fl_x"]))  # twice the file's focal length
    (folder / "transforms.json").write_text(json.dumps(meta))
    k = load_scene(folder, holdout_every=0).splits["train"].intrinsics
    assert float(k[0, 0]) == pytest.approx(2 * float(k[1, 0]), rel=1e-5)
    assert float(k[0, 1]) == pytest.approx(float(k[1, 1]))  # fl_y: no frame value, the file's


def test_a_blender_transforms_file_with_lens_distortion_is_read_as_it_is(tmp_path):
    """instant-ngp writes k1 k2 p1 p2 and camera_model into Blender-layout transforms, and applies them: such a camera
    is read with its lens (a frame's own value wins), a fisheye too; a camera model with no lens boostnerf renders
    (equirectangular) and tangential terms on a fisheye are refused in one line."""
    import shutil

    scene = make_scene(tmp_path / "b", size=16, n_train=3, n_test=1)
    folder = shutil.copytree(scene, tmp_path / "k1")
    meta = json.loads((folder / "transforms_train.json").read_text())
    meta.update(k1=-0.2, k2=0.05, camera_model="OPENCV")
    meta["frames"][1]["p1"] = 0.001
    (folder / "transforms_train.json").write_text(json.dumps(meta))
    train = load_scene(folder).splits["train"]
    assert train.intrinsics.shape == (3, WITH_LENS)
    assert train.camera(0).lens.coefficients() == pytest.approx({"k1": -0.2, "k2": 0.05})
    assert not train.camera(0).lens.fisheye
    assert train.camera(1).lens.coefficients() == pytest.approx({"k1": -0.2, "k2": 0.05, "p1": 0.001})
    assert load_scene(folder).splits["test"].intrinsics.shape == (1, 4)  # its own file: a pinhole camera
    for change, message in (({"camera_model": "EQUIRECTANGULAR"}, "camera_model EQUIRECTANGULAR is not supported"),
                            ({"camera_model": "OPENCV_FISHEYE", "p1": 0.01}, "has no tangential distortion")):
        meta = json.loads((scene / "transforms_train.json").read_text())
        meta.update(change)
        (scene / "transforms_train.json").write_text(json.dumps(meta))
        with pytest.raises(BoostNerfError, match=message):
            load_scene(scene)


def test_w_and_h_are_checked_to_a_pixel_of_rounding_not_to_2_percent():
    """`w` x `h` against the image's own aspect: a stored image may be a pixel off from a downscale's rounding (a
    1297 x 731 capture cut by 32 is 40 x 22, 2.5% off: refused before), but a 960 x 540 image with w x h 960 x 550
    (1.9% off, its principal point 5 px out) passed the old 2% check and was rendered squeezed."""
    from boostnerf_cli.scenes.frames import frame_intrinsics

    camera = {k: None for k in ("camera_angle_x", "camera_angle_y", "fl_y", "cx", "cy")}
    k = frame_intrinsics({**camera, "fl_x": 1000.0, "w": 1297, "h": 731}, (22, 40), (22, 40), "f")
    assert k.fx == pytest.approx(1000 * 40 / 1297) and k.fy == pytest.approx(1000 * 22 / 731)
    with pytest.raises(BoostNerfError, match="w x h = 960 x 550 does not match the image's 960 x 540 aspect"):
        frame_intrinsics({**camera, "fl_x": 1000.0, "w": 960, "h": 550}, (540, 960), (540, 960), "f")


def test_a_principal_point_far_from_the_image_centre_is_named(forward, tmp_path):
    """Images downscaled after the transforms were written, without `w` / `h`: the intrinsics are the full size's, so
    the principal point lands on the images' corner (held-out 9.9 dB against 23.1 with w and h), silently. A scene
    whose principal point lies more than a quarter of the image from its centre now carries a warning."""
    import shutil

    folder = shutil.copytree(forward["nerfstudio"], tmp_path / "ns")
    meta = json.loads((folder / "transforms.json").read_text())
    for key in ("fl_x", "fl_y", "cx", "cy"):
        meta[key] *= 2  # a capture twice the size, its images halved afterwards
    del meta["w"], meta["h"]
    (folder / "transforms.json").write_text(json.dumps(meta))
    (warning,) = load_scene(folder).extra["warnings"]
    assert "principal point" in warning and "w and h" in warning, warning
    assert "warnings" not in load_scene(forward["nerfstudio"]).extra


def test_a_focal_length_given_for_y_alone_serves_both_axes():
    """A transforms file with camera_angle_y (or fl_y) and nothing for x, as some exporters write for portrait
    images: refused before ("no camera_angle_x and no fl_x"); instant-ngp reads it as square pixels, and so now does
    boostnerf."""
    from boostnerf_cli.scenes.frames import frame_intrinsics

    camera = {k: None for k in ("camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h")}
    k = frame_intrinsics({**camera, "camera_angle_y": 2 * math.atan(0.5)}, (40, 20), (40, 20), "f")
    assert k.row() == pytest.approx([40.0, 40.0, 10.0, 20.0])
    assert frame_intrinsics({**camera, "fl_y": 33.0}, (40, 20), (40, 20), "f").row() == pytest.approx([33, 33, 10, 20])
    with pytest.raises(BoostNerfError, match="no focal length"):
        frame_intrinsics(camera, (40, 20), (40, 20), "f")


def test_an_impossible_focal_length_names_the_view_and_its_values(forward, tmp_path):
    """fl_x 0, negative, NaN or infinite: `camera intrinsics must be finite with positive focal lengths`, naming no
    file, view or value."""
    import shutil

    folder = shutil.copytree(forward["nerfstudio"], tmp_path / "ns")
    meta = json.loads((folder / "transforms.json").read_text())
    meta["frames"][2]["fl_x"] = -20.0
    (folder / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(BoostNerfError, match=r"intrinsics of view images/frame_\d+ are fx, fy, cx, cy = -20, "):
        load_scene(folder)


def test_a_folder_named_like_an_image_in_llff_images_is_not_an_image(forward, tmp_path):
    """A folder `images/zzz.png` counted as an image: "poses_bounds.npy has 17 poses but images/ holds 18 images",
    which sent the user looking for a missing pose."""
    import shutil

    folder = tmp_path / "llff"
    shutil.copytree(forward["llff"], folder)
    (folder / "images" / "zzz.png").mkdir()
    scene = load_scene(folder, holdout_every=0)
    assert len(scene.splits["train"]) == N_TRAIN + N_TEST


def test_data_frame_round_trips_points_and_poses_and_keeps_rotations_orthonormal():
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = 2.5 * q, [1.0, -2.0, 0.5]
    frame = DataFrame(t)
    assert frame.scale == pytest.approx(2.5) and not frame.identity and DataFrame.of({}).identity
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, :3, :3] = [np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(3)]
    poses[:, :3, 3] = rng.normal(size=(3, 3))
    world = frame.poses_to_world(torch.tensor(poses, dtype=torch.float32))
    assert world.dtype == torch.float32
    np.testing.assert_allclose(world[:, :3, :3].double() @ world[:, :3, :3].double().mT, np.tile(np.eye(3), (3, 1, 1)),
                               atol=1e-6)
    np.testing.assert_allclose(world[:, :3, 3], poses[:, :3, 3] @ t[:3, :3].T + t[:3, 3], atol=1e-5)
    np.testing.assert_allclose(frame.poses_to_data(world).numpy(), poses, atol=1e-5)
    xyz = rng.normal(size=(10, 3))
    np.testing.assert_allclose(frame.points_to_data(frame.points_to_world(xyz)), xyz, atol=1e-12)
    with pytest.raises(BoostNerfError, match="similarity"):
        DataFrame(np.full((4, 4), np.nan))
