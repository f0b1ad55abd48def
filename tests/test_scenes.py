"""Scene loading (Blender format), the procedural scene generator and camera-derived bounds."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from conftest import run_cli
from hypothesis import given, settings
from hypothesis import strategies as st

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.render.rays import image_rays, project_points
from boostnerf_cli.scenes import Scene, load_blender, load_scene, make_scene
from boostnerf_cli.scenes.bounds import frustum_overlap_bbox, frustum_planes, lattice_visible_counts
from boostnerf_cli.scenes.frames import area_downscale, area_matrix
from boostnerf_cli.scenes.procedural import CAMERA_ANGLE_X, camera_poses, scene_objects

SIZE, N_TRAIN, N_TEST = 32, 6, 3


@pytest.fixture(scope="module")
def generated(tmp_path_factory) -> Path:
    return make_scene(tmp_path_factory.mktemp("gen") / "scene", size=SIZE, n_train=N_TRAIN, n_test=N_TEST, seed=0)


def write_blender(folder: Path, splits: dict[str, list[np.ndarray]], **meta) -> Path:
    """A tiny Blender-format dataset: uint8 images per split, cameras from the procedural spiral."""
    folder.mkdir(parents=True, exist_ok=True)
    meta.setdefault("camera_angle_x", CAMERA_ANGLE_X)
    for split, images in splits.items():
        poses, _ = camera_poses(len(images), 0)
        (folder / split).mkdir(exist_ok=True)
        frames = []
        for i, (img, pose) in enumerate(zip(images, poses)):
            iio.imwrite(folder / split / f"r_{i}.png", img)
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": pose.tolist()})
        (folder / f"transforms_{split}.json").write_text(json.dumps({**meta, "frames": frames}))
    return folder


def rgba(h: int, w: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 4), dtype=np.uint8)


def raises_one_line(match: str, fn, *args, **kwargs) -> str:
    with pytest.raises(BoostNerfError, match=match) as info:
        fn(*args, **kwargs)
    assert "\n" not in str(info.value)
    return str(info.value)


# ----------------------------------------------------------------------------- generated scene


def test_generated_scene_loads(generated):
    scene = load_scene(generated)
    assert isinstance(scene, Scene) and scene.format == "blender" and scene.holdout == ""
    assert set(scene.splits) == {"train", "test"}
    train, test = scene.split("train"), scene.split("test")
    assert train.images.shape == (N_TRAIN, SIZE, SIZE, 3) and test.images.shape == (N_TEST, SIZE, SIZE, 3)
    assert train.images.dtype == torch.float32 and 0 <= float(train.images.min()) <= float(train.images.max()) <= 1
    focal = 0.5 * SIZE / math.tan(0.5 * CAMERA_ANGLE_X)
    assert torch.allclose(train.intrinsics[0], torch.tensor([focal, focal, SIZE / 2, SIZE / 2]))
    # the files record no near / far: they come from the cameras (radius 4 -> 0.1 r and 2 r)
    assert scene.extra["near_far_source"] == "cameras"
    assert (scene.near, scene.far) == pytest.approx((0.4, 8.0), rel=1e-3)
    assert train.names[0] == "train/r_0"
    # test cameras are not train cameras
    dist = torch.cdist(test.poses[:, :3, 3], train.poses[:, :3, 3])
    assert float(dist.min()) > 0.1
    assert (generated / "README.txt").read_text().startswith("Procedurally generated")


def test_generation_is_deterministic(tmp_path):
    kwargs = dict(size=16, n_train=3, n_test=1)
    a = make_scene(tmp_path / "a", seed=3, **kwargs)
    b = make_scene(tmp_path / "b", seed=3, **kwargs)
    c = make_scene(tmp_path / "c", seed=4, **kwargs)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert all((a / f).read_bytes() == (b / f).read_bytes() for f in files)
    pngs = [f for f in files if f.suffix == ".png"]
    assert any((a / f).read_bytes() != (c / f).read_bytes() for f in pngs)


def test_analytic_render_hits_known_geometry(generated):
    objects = scene_objects(0)
    spheres = [o for o in objects if o["kind"] == "sphere"]
    reach = max(np.linalg.norm(o["centre"]) + max(o.get("radius", 0), np.linalg.norm(o.get("half", 0)))
                for o in objects)
    meta = json.loads((generated / "transforms_train.json").read_text())
    focal = 0.5 * SIZE / math.tan(0.5 * meta["camera_angle_x"])
    k = torch.tensor([focal, focal, SIZE / 2, SIZE / 2])
    far_from_objects = 0
    for frame in meta["frames"]:
        alpha = iio.imread(generated / f"{frame['file_path']}.png")[..., 3]
        pose = torch.tensor(frame["transform_matrix"])
        uv, depth = project_points(torch.tensor([s["centre"] for s in spheres]), pose, k)
        assert (depth > 0).all()
        for u, v in uv.floor().long().tolist():
            assert alpha[v, u] == 255  # the ray through a sphere's centre pixel hits something opaque
        o, d = image_rays(pose, k, SIZE, SIZE)
        miss = (torch.linalg.cross(o, d).norm(dim=-1) > reach + 0.1).reshape(SIZE, SIZE).numpy()
        assert (alpha[miss] == 0).all()  # rays passing far from every object are transparent
        far_from_objects += int(miss.sum())
    assert far_from_objects > 0


def test_bbox_contains_generated_objects(generated):
    scene = load_scene(generated)
    lo, hi = scene.bbox[0].numpy(), scene.bbox[1].numpy()
    for o in scene_objects(0):
        c = np.array(o["centre"])
        if o["kind"] == "box":
            ext = np.array([math.hypot(*o["half"][:2])] * 2 + [o["half"][2]])
        elif o["kind"] == "disc":
            ext = np.array([o["radius"], o["radius"], 0.0])
        else:
            ext = np.full(3, o["radius"])
        assert (c - ext >= lo).all() and (c + ext <= hi).all(), o["kind"]


def test_data_bbox_replaces_the_box_the_loader_gives_and_workspaces_reload_it(generated, tmp_path):
    """`data.bbox` (a floor past the camera-derived box: make-scene --content large) replaces the loader's box, in
    pretrain and in every later stage, which reloads the scene from the manifest; a forward-facing scene's NDC box
    cannot be replaced."""
    from boostnerf_cli.lineage import Survey
    from boostnerf_cli.workspace import Workspace

    wide = [-3.0, -3.0, -0.7, 3.0, 3.0, 0.5]
    scene = load_scene(generated, bbox=wide)
    assert torch.equal(scene.bbox, torch.tensor(wide).view(2, 3)) and scene.extra["bbox"] == "data.bbox"
    assert not torch.equal(load_scene(generated).bbox, scene.bbox)
    ws = Workspace(tmp_path / "ws")
    ws.update_manifest(data={"path": str(generated), "image_size": None, "holdout_every": 8, "format": "auto",
                             "bbox": wide})
    assert torch.equal(Survey(ws).scene().bbox, scene.bbox)
    llff = make_scene(tmp_path / "llff", size=16, n_train=3, n_test=0, layout="llff")
    raises_one_line("data.bbox does not apply .* forward-facing", load_scene, llff, bbox=wide)
    # a box edited by hand in a manifest: one line, not a traceback
    raises_one_line("bounding box must be", load_scene, generated, bbox=[1.0, 2.0])
    raises_one_line("bounding box must be", load_scene, generated, bbox=[0, 0, 0, -1, 1, 1])
    raises_one_line("data.bbox = .* must be six numbers", load_scene, generated, bbox=["a", 1, 1, 1, 1, 1])


def test_lattice_counts_match_projection():
    poses = torch.tensor(camera_poses(7, 0)[0]).float()
    k = torch.tensor([[30.0, 28.0, 15.0, 13.0]]).repeat(7, 1)
    axes = tuple(torch.linspace(-1.9, 2.1, n) + 0.0123 for n in (9, 10, 11))
    counts = lattice_visible_counts(axes, frustum_planes(poses, k, 26, 30, 2.0, 6.0))
    pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    expected = torch.zeros(len(pts), dtype=torch.long)
    for pose, kk in zip(poses, k):
        uv, depth = project_points(pts, pose, kk)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= 30) & (uv[:, 1] >= 0) & (uv[:, 1] <= 26)
        expected += (inside & (depth >= 2) & (depth <= 6)).long()
    assert torch.equal(counts.reshape(-1), expected)
    assert 0 < int(expected.sum()) < 7 * len(pts)


def test_bbox_falls_back_to_frustum_box():
    poses = torch.tensor(camera_poses(2, 0)[0]).float()
    poses[1, :3, 3] *= -1  # second camera looks away from the first one's view
    poses[1, :3, :3] *= -1
    k = torch.tensor([[10.0, 10.0, 5.0, 5.0]]).repeat(2, 1)
    views = SimpleNamespace(poses=poses, intrinsics=k, height=10, width=10)
    box = frustum_overlap_bbox(views, 2.0, 6.0, min_fraction=1.0, grid=16)
    assert box.shape == (2, 3) and (box[1] > box[0]).all()


# ----------------------------------------------------------------------------- downscaling


def test_area_downscale_is_block_mean_after_premultiplying(tmp_path):
    img = rgba(8, 8)
    bg = (0.2, 0.4, 0.6)
    scene = load_blender(write_blender(tmp_path / "d", {"train": [img, rgba(8, 8, 1)]}), image_size=4,
                         holdout_every=0, background=bg)
    x = img.astype(np.float64) / 255
    premult = np.concatenate([x[..., :3] * x[..., 3:], x[..., 3:]], -1)
    expected = np.zeros((4, 4, 3))
    for i in range(4):
        for j in range(4):
            block = premult[2 * i : 2 * i + 2, 2 * j : 2 * j + 2].reshape(4, 4).mean(0)
            expected[i, j] = block[:3] + (1 - block[3]) * np.array(bg)
    got = scene.split("train").images[0].double().numpy()
    assert np.allclose(got, expected, atol=1e-5)
    # the wrong order (average straight colour, then composite) gives a different answer
    straight = x.reshape(4, 2, 4, 2, 4).mean((1, 3))
    wrong = straight[..., :3] * straight[..., 3:] + (1 - straight[..., 3:]) * np.array(bg)
    assert not np.allclose(wrong, expected, atol=1e-3)


def test_area_weights_non_integer_factor():
    w = area_matrix(3, 2).double()  # output pixels cover [0, 1.5) and [1.5, 3)
    assert torch.allclose(w, torch.tensor([[2 / 3, 1 / 3, 0], [0, 1 / 3, 2 / 3]], dtype=torch.float64))
    img = torch.rand(6, 8, 3)
    assert torch.allclose(area_downscale(img, 3, 4), img.reshape(3, 2, 4, 2, 3).mean((1, 3)))


@settings(max_examples=25, deadline=None)
@given(st.integers(2, 17), st.integers(2, 17), st.data())
def test_area_downscale_preserves_mean(h, w, data):
    nh, nw = data.draw(st.integers(1, h)), data.draw(st.integers(1, w))
    img = torch.rand(h, w, 2, generator=torch.Generator().manual_seed(h * 31 + w))
    out = area_downscale(img, nh, nw)
    assert out.shape == (nh, nw, 2)
    assert torch.allclose(out.mean((0, 1)), img.mean((0, 1)), atol=1e-5)
    assert torch.allclose(area_downscale(torch.full((h, w, 1), 0.3), nh, nw), torch.tensor(0.3), atol=1e-6)


def test_intrinsics_scale_per_axis(tmp_path):
    imgs = [rgba(6, 8, i) for i in range(2)]
    folder = write_blender(tmp_path / "k", {"train": imgs}, fl_x=10.0, fl_y=12.0, cx=3.0, cy=2.5)
    scene = load_blender(folder, image_size=4, holdout_every=0)
    train = scene.split("train")
    assert (train.height, train.width) == (3, 4)
    assert torch.allclose(train.intrinsics[0], torch.tensor([5.0, 6.0, 1.5, 1.25]))
    native = load_blender(folder, holdout_every=0).split("train")
    assert torch.allclose(native.intrinsics[0], torch.tensor([10.0, 12.0, 3.0, 2.5]))
    raises_one_line("never upscaled", load_blender, folder, image_size=16)


def test_rgb_images_and_near_far_keys(tmp_path):
    folder = write_blender(tmp_path / "rgb", {"train": [rgba(4, 4)[..., :3]] * 2}, near=0.5, far=3.0)
    scene = load_blender(folder, holdout_every=0)
    assert (scene.near, scene.far) == (0.5, 3.0) and scene.extra["near_far_source"] == "transforms"
    assert torch.allclose(scene.split("train").images[0], torch.from_numpy(rgba(4, 4)[..., :3] / 255).float())


def test_palette_colour_keyed_and_cmyk_images_keep_their_transparency_and_colours(tmp_path):
    """A palette PNG with transparency (what pngquant writes) loaded its transparent pixels black instead of the
    background (a scene trained to 1.7 dB), and so did an RGB PNG with a colour key; a CMYK JPEG's K was alpha."""
    from PIL import Image

    from boostnerf_cli.scenes.frames import read_image

    colours = np.array([[0, 0, 0, 0], [200, 30, 30, 255], [20, 180, 60, 255], [40, 40, 220, 255]], np.uint8)
    images = [colours[np.random.default_rng(i).integers(0, 4, (6, 6))] for i in range(2)]
    plain = load_blender(write_blender(tmp_path / "rgba", {"train": images}), holdout_every=0).split("train").images
    folder = write_blender(tmp_path / "palette", {"train": images})
    for png in (folder / "train").glob("*.png"):
        Image.open(png).quantize(8).save(png)  # mode P, the transparent colour in its tRNS chunk
        assert Image.open(png).mode == "P" and "transparency" in Image.open(png).info
    assert torch.allclose(load_blender(folder, holdout_every=0).split("train").images, plain, atol=1 / 255)
    assert float(plain[0][images[0][..., 3] == 0].min()) == 1.0  # the transparent pixels: the white background

    keyed = tmp_path / "keyed.png"
    Image.fromarray(images[0][..., :3]).save(keyed, transparency=(0, 0, 0))  # black: transparent
    assert torch.equal(read_image(keyed)[..., 3] == 0, torch.from_numpy(images[0][..., 3] == 0))
    jpeg = tmp_path / "cmyk.jpg"
    Image.new("RGB", (8, 8), (200, 30, 30)).convert("CMYK").save(jpeg, quality=95)
    img = read_image(jpeg)
    assert img.shape == (8, 8, 3) and torch.allclose(img[0, 0], torch.tensor([200, 30, 30]) / 255, atol=0.05)


def test_a_blender_scene_at_another_scale_gives_the_scaled_bounds(generated, tmp_path):
    """The same capture with every camera 4x farther out (a scene modelled in other units): near, far and the
    box scale with it. With the old fixed near 2 / far 6 the cameras 16 units out saw nothing (far 6 ends
    every ray 10 units short of the subject)."""
    import shutil

    folder = tmp_path / "far"
    shutil.copytree(generated, folder)
    for split in ("train", "test"):
        path = folder / f"transforms_{split}.json"
        meta = json.loads(path.read_text())
        for frame in meta["frames"]:
            m = np.array(frame["transform_matrix"])
            m[:3, 3] *= 4
            frame["transform_matrix"] = m.tolist()
        path.write_text(json.dumps(meta))
    a, b = load_scene(generated), load_scene(folder)
    assert (b.near, b.far) == pytest.approx((4 * a.near, 4 * a.far), rel=1e-5)
    assert torch.allclose(b.bbox, 4 * a.bbox, atol=1e-3 * float((b.bbox[1] - b.bbox[0]).max()))
    # one recorded bound is honoured, the other still comes from the cameras
    meta = json.loads((folder / "transforms_train.json").read_text())
    (folder / "transforms_train.json").write_text(json.dumps({**meta, "near": 1.5}))
    c = load_scene(folder)
    assert (c.near, c.far) == pytest.approx((1.5, b.far)) and c.extra["near_far_source"] == "transforms,cameras"


# ----------------------------------------------------------------------------- splits


def test_holdout_every_8th(tmp_path):
    folder = write_blender(tmp_path / "h", {"train": [rgba(4, 4, i) for i in range(17)]})
    scene = load_scene(folder)
    assert scene.split("test").names == ("train/r_0", "train/r_8", "train/r_16")
    assert len(scene.split("train")) == 14 and "train/r_8" not in scene.split("train").names
    assert "every 8th" in scene.holdout and "(3 of 17)" in scene.holdout
    off = load_scene(folder, holdout_every=0)
    assert set(off.splits) == {"train"} and off.holdout == ""


def test_own_test_split_is_used(tmp_path):
    folder = write_blender(tmp_path / "t", {"train": [rgba(4, 4, i) for i in range(9)], "test": [rgba(4, 4)] * 2})
    scene = load_scene(folder)
    assert len(scene.split("train")) == 9 and len(scene.split("test")) == 2 and scene.holdout == ""


# ----------------------------------------------------------------------------- errors


def test_error_missing_folder(tmp_path):
    raises_one_line("does not exist", load_scene, tmp_path / "nope")
    raises_one_line("does not exist", load_blender, tmp_path / "nope")


def test_error_unknown_layout(tmp_path):
    msg = raises_one_line("cannot tell the dataset format", load_scene, tmp_path)
    assert "transforms_" in msg
    raises_one_line("no transforms_", load_blender, tmp_path)
    raises_one_line("unknown scene format", load_scene, tmp_path, format="colmap2000")


def test_error_bad_camera_values_and_a_singular_rotation(tmp_path):
    """Each was a traceback: ZeroDivisionError, ValueError, TypeError from float(), linalg.eigh not converging."""
    folder = write_blender(tmp_path / "cam", {"train": [rgba(4, 4)] * 2})
    meta_path = folder / "transforms_train.json"
    good = json.loads(meta_path.read_text())
    for key, value, message in [("camera_angle_x", 0, r"camera_angle_x = 0.0: a field of view must be in \(0, pi\)"),
                                ("camera_angle_x", 3.2, r"camera_angle_x = 3.2: a field of view"),
                                ("camera_angle_x", "abc", r"camera_angle_x = 'abc' is not a number"),
                                ("camera_angle_x", [0.7], r"camera_angle_x = \[0.7\] is not a number"),
                                ("w", "abc", r"w = 'abc' is not a number"),
                                ("fl_x", True, r"fl_x = True is not a number")]:
        meta_path.write_text(json.dumps({**good, key: value}))
        raises_one_line(message, load_scene, folder)
    singular = json.loads(json.dumps(good))
    singular["frames"][1]["transform_matrix"] = [[0, 0, 0, 1], [0, 0, 0, 2], [0, 0, 0, 3], [0, 0, 0, 1]]
    meta_path.write_text(json.dumps(singular))
    raises_one_line(r"frame 1.*rotation .* is singular", load_scene, folder)


def test_make_scene_refuses_a_folder_with_files_a_file_and_a_negative_seed(tmp_path):
    """make-scene over an existing blender scene with --format llff wrote the llff files beside the old ones, and
    pretrain then found transforms_train.json and trained on the old scene; a smaller rerun left old views behind.
    A file as the folder and a negative seed were tracebacks (FileExistsError, numpy's ValueError)."""
    make_scene(tmp_path / "s", size=8, n_train=2, n_test=0)
    before = sorted(p.name for p in (tmp_path / "s").rglob("*"))
    raises_one_line(r"already holds files: .*choose a new folder", make_scene, tmp_path / "s", size=8, n_train=2,
                    n_test=0, layout="llff")
    assert sorted(p.name for p in (tmp_path / "s").rglob("*")) == before
    (tmp_path / "f.yaml").write_text("x")
    raises_one_line(r"f\.yaml is a file", make_scene, tmp_path / "f.yaml", size=8, n_train=2, n_test=0)
    raises_one_line(r"seed >= 0 .*seed=-1", make_scene, tmp_path / "n", size=8, n_train=2, n_test=0, seed=-1)
    assert not (tmp_path / "n").exists()
    (tmp_path / "empty").mkdir()
    make_scene(tmp_path / "empty", size=8, n_train=2, n_test=0)  # an empty folder is fine


def test_error_missing_image(tmp_path):
    folder = write_blender(tmp_path / "m", {"train": [rgba(4, 4)] * 2})
    (folder / "train" / "r_1.png").unlink()
    raises_one_line(r"frame 1.*r_1.*not found", load_scene, folder)


def test_error_corrupt_png(tmp_path):
    folder = write_blender(tmp_path / "c", {"train": [rgba(4, 4)] * 2})
    (folder / "train" / "r_1.png").write_bytes(b"\x89PNG garbage, not an image")
    raises_one_line(r"cannot read image .*r_1\.png", load_scene, folder)


def test_error_mixed_sizes(tmp_path):
    folder = write_blender(tmp_path / "s", {"train": [rgba(4, 4), rgba(4, 6)]})
    raises_one_line(r"r_1\.png is 6x4 .* same size", load_scene, folder)


def test_error_bad_poses(tmp_path):
    folder = write_blender(tmp_path / "p", {"train": [rgba(4, 4)] * 2})
    meta_path = folder / "transforms_train.json"
    meta = json.loads(meta_path.read_text())
    meta["frames"][1]["transform_matrix"][0][3] = float("nan")
    meta_path.write_text(json.dumps(meta))  # json writes NaN, which Python reads back
    raises_one_line(r"transforms_train\.json frame 1.*NaN", load_scene, folder)
    meta["frames"][1]["transform_matrix"] = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
    meta_path.write_text(json.dumps(meta))
    raises_one_line(r"frame 1.*4x4", load_scene, folder)


def test_error_bad_json_and_missing_focal(tmp_path):
    folder = write_blender(tmp_path / "j", {"train": [rgba(4, 4)] * 2})
    meta_path = folder / "transforms_train.json"
    meta = json.loads(meta_path.read_text())
    meta_path.write_text(json.dumps({"frames": meta["frames"]}))
    raises_one_line("no focal length", load_scene, folder)
    meta_path.write_text("{ not json")
    raises_one_line(r"cannot parse .*transforms_train\.json", load_scene, folder)


def test_error_bad_holdout(tmp_path):
    folder = write_blender(tmp_path / "o", {"train": [rgba(4, 4)]})
    raises_one_line("--holdout-every 0", load_scene, folder)  # the flag (not a key=value)
    raises_one_line("at least 2", load_scene, folder, holdout_every=1)


def test_output_stems_tell_every_view_apart():
    """A view's output file stem: its last path part, a longer suffix where two views share it, a counter where
    whole names repeat."""
    from boostnerf_cli.scenes.scene import Split

    def stems(*names):
        n = len(names)
        return Split(torch.zeros(n, 2, 2, 3), torch.eye(4).repeat(n, 1, 1), torch.ones(n, 4), names).stems

    assert stems("train/r_0", "train/r_8") == ("r_0", "r_8")  # unique last parts: unchanged names
    assert stems("images/cam0/0000", "images/cam1/0000", "images/cam1/0001") == ("cam0_0000", "cam1_0000", "cam1_0001")
    assert stems("a\\x", "b\\x") == ("a_x", "b_x")
    assert stems("./x", "x", "y") == ("x", "x_2", "y")


@pytest.mark.parametrize("content", ["thin", "large"])
def test_llff_depth_bounds_hold_every_object(tmp_path, content):
    """make-scene's poses_bounds.npy bounded every view's depth by the default content's radius (1.25): the thin
    content's wire (1.57 from the origin) and the large content's floor (radius 3) lay past `far`, wrong for any
    other tool that reads the bounds. Points on each object, from the object list, lie within every view's bounds."""
    out = make_scene(tmp_path / content, size=16, n_train=4, n_test=0, layout="llff", content=content)
    bounds = np.load(out / "poses_bounds.npy")
    centres = bounds[:, :15].reshape(-1, 3, 5)[:, :, 3]
    points = []
    for obj in scene_objects(0, content):
        if obj["kind"] == "capsule":
            points += [obj["a"], obj["b"]]
        elif obj["kind"] == "disc":
            cx, cy, cz = obj["centre"]
            points += [[cx + obj["radius"] * math.cos(a), cy + obj["radius"] * math.sin(a), cz]
                       for a in np.linspace(0, 2 * math.pi, 64, endpoint=False)]
    dist = np.linalg.norm(np.asarray(points)[None] - centres[:, None], axis=-1)  # (views, points)
    assert (dist <= bounds[:, 16:17]).all(), (dist.max(1), bounds[:, 16])
    assert (dist >= bounds[:, 15:16]).all()


def test_layouts_without_splits_hold_out_exactly_the_test_views_they_write(tmp_path):
    """LLFF and nerfstudio keep one sequence of views, of which the loaders hold out every 8th. Test views that found
    no such place (the 3rd of 3 beside 12 train views; 4 of the default 8 beside 24) were written after the train
    views and trained on: 13 train views where 12 were asked for. With fewer test views than places (1 beside 16),
    train views were held out: 14 train views and 3 test views, 2 of them Blender's train views. Now these layouts
    write the test views that fill the places, the views of a Blender scene with that many, and make-scene says so."""
    for n_train, n_test, written in ((12, 3, 2), (16, 1, 3)):
        blender = load_scene(make_scene(tmp_path / f"b{n_train}", size=16, n_train=n_train, n_test=written))
        ns = load_scene(make_scene(tmp_path / f"ns{n_train}", size=16, n_train=n_train, n_test=n_test,
                                   layout="nerfstudio"))
        assert len(ns.splits["train"]) == n_train and len(ns.splits["test"]) == written
        torch.testing.assert_close(ns.splits["train"].poses, blender.splits["train"].poses)
        torch.testing.assert_close(ns.splits["test"].poses, blender.splits["test"].poses)
    proc = run_cli("make-scene", str(tmp_path / "llff"), "--format", "llff", "--size", "16", "--train-views", "24")
    assert proc.returncode == 0, proc.stderr
    text = proc.stdout + proc.stderr
    assert "24 train and 4 test views" in text and "that is 4 test views, not the 8 asked for" in text, text
    llff = load_scene(tmp_path / "llff")
    assert len(llff.splits["train"]) == 24 and len(llff.splits["test"]) == 4
    proc = run_cli("make-scene", str(tmp_path / "none"), "--format", "nerfstudio", "--size", "16", "--train-views", "8",
                   "--test-views", "0")
    assert "holds out every 8th of these train views unless the recipe sets data.holdout_every: 0" in proc.stderr + \
        proc.stdout


def _look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """A camera-to-world pose (OpenGL: the camera looks down its -z) at `centre` looking at `target`."""
    back = centre - target
    back = back / np.linalg.norm(back)
    right = np.cross([0.0, 0.0, 1.0], back)
    right = right / np.linalg.norm(right) if np.linalg.norm(right) > 1e-6 else np.array([1.0, 0.0, 0.0])
    up = np.cross(back, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, up, back, centre
    return pose


def _ring(n: int, radius, height: float = 0.5, outward: bool = False) -> list[np.ndarray]:
    poses = []
    for i in range(n):
        a = 2 * math.pi * i / n
        r = radius[i % len(radius)] if isinstance(radius, list) else radius
        c = np.array([r * math.cos(a), r * math.sin(a), height])
        poses.append(_look_at(c, 2 * c * np.array([1, 1, 0]) + np.array([0, 0, height])) if outward
                     else _look_at(c, np.zeros(3)))
    return poses


def test_cameras_at_mixed_distances_reach_the_subject_from_the_farthest(tmp_path):
    """Half the cameras 3x farther from the subject (4 and 12): far was 2 x the median distance, 8, so the far
    cameras' rays ended 4 units short of the subject and the box (the region most cameras see) came out 16 x 20 x 15
    units around nothing; held-out PSNR 10.4 against 18.9."""
    images = [rgba(16, 16, i) for i in range(8)]
    folder = write_blender(tmp_path / "mixed", {"train": images})
    meta = json.loads((folder / "transforms_train.json").read_text())
    for frame, pose in zip(meta["frames"], _ring(8, [4.0, 12.0])):
        frame["transform_matrix"] = pose.tolist()
    (folder / "transforms_train.json").write_text(json.dumps(meta))
    scene = load_scene(folder, holdout_every=0)
    assert scene.far >= 12 + 1.0, scene.far  # the subject's far side from the farthest camera
    assert abs(scene.near - 0.4) < 0.05 and scene.extra.get("warnings") is None
    assert float((scene.bbox[1] - scene.bbox[0]).max()) < 8, scene.bbox  # around the subject, not the cameras
    # cameras all at one distance keep 0.1 r / 2 r
    for frame, pose in zip(meta["frames"], _ring(8, 4.0)):
        frame["transform_matrix"] = pose.tolist()
    (folder / "transforms_train.json").write_text(json.dumps(meta))
    same, r = load_scene(folder, holdout_every=0), math.hypot(4.0, 0.5)
    assert abs(same.near - 0.1 * r) < 1e-4 and abs(same.far - 2 * r) < 1e-4


def test_cameras_inside_the_content_looking_out_are_named_and_data_bbox_gives_near_and_far(tmp_path):
    """A room captured from inside (cameras 0.2 from the centre, looking out): near / far came from the camera
    cluster (0.02 / 0.41) and the box from every frustum's corners (+-0.64), around no content, with no word but a
    box-faces warning; data.bbox then replaced the box but rays still ended at far 0.41, and the warning went
    away. Now the loader says so, and data.bbox widens near / far to reach the box."""
    images = [rgba(16, 16, i) for i in range(8)]
    folder = write_blender(tmp_path / "room", {"train": images})
    meta = json.loads((folder / "transforms_train.json").read_text())
    for frame, pose in zip(meta["frames"], _ring(8, 0.2, outward=True)):
        frame["transform_matrix"] = pose.tolist()
    (folder / "transforms_train.json").write_text(json.dumps(meta))
    said = " | ".join(load_scene(folder, holdout_every=0).extra["warnings"])
    assert "do not face a common point" in said and "is seen by 8 of the 8 training cameras" in said, said
    box = [-3.6, -3.6, -0.7, 3.6, 3.6, 1.2]
    scene = load_scene(folder, holdout_every=0, bbox=box)
    assert scene.extra.get("warnings") is None  # moot once the box is given
    corner = math.dist((0.2, 0.0, 0.5), (-3.6, -3.6, -0.7))
    assert scene.far >= corner - 1e-3 and scene.near < 0.1, (scene.near, scene.far)
    assert "widened" in scene.extra["notes"][0]
    # one camera inside the box does not keep a recorded near of 2 for a camera 0.05 above the box's top face
    mixed = write_blender(tmp_path / "mixed", {"train": images[:2]}, near=2.0, far=6.0)
    meta = json.loads((mixed / "transforms_train.json").read_text())
    meta["frames"][0]["transform_matrix"] = _look_at(np.zeros(3), np.array([3.0, 0.0, 0.0])).tolist()
    meta["frames"][1]["transform_matrix"] = _look_at(np.array([0.0, 0.3, 1.05]), np.zeros(3)).tolist()
    (mixed / "transforms_train.json").write_text(json.dumps(meta))
    scene = load_scene(mixed, holdout_every=0, bbox=[-1, -1, -1, 1, 1, 1])
    assert scene.near <= 0.9 * 0.05 + 1e-6 and scene.far >= 6.0, (scene.near, scene.far)
    # a box inside what near / far already reach changes nothing and says nothing
    plain = load_scene(write_blender(tmp_path / "plain", {"train": images}), holdout_every=0)
    boxed = load_scene(tmp_path / "plain", holdout_every=0, bbox=[-1, -1, -1, 1, 1, 1])
    assert (boxed.near, boxed.far) == (plain.near, plain.far) and "notes" not in boxed.extra


def test_image_kinds_real_captures_come_in(tmp_path):
    """A 32-bit integer image (Pillow's mode "I": integer TIFFs, and 16-bit grey PNGs in some
    Pillow releases) was divided by 2^31 and trained as black, exit 0; HDR float images were clipped without a word;
    a folder named like an image was "not found"; an animated PNG got a bare shape error."""
    from PIL import Image

    from boostnerf_cli.scenes.frames import read_image

    grey = np.random.default_rng(0).integers(0, 65536, (6, 6)).astype(np.int32)
    Image.fromarray(grey).save(tmp_path / "i.tif")
    assert Image.open(tmp_path / "i.tif").mode == "I"
    assert torch.allclose(read_image(tmp_path / "i.tif")[..., 0], torch.from_numpy(grey / 65535).float())
    Image.fromarray((grey * 2).astype(np.int32)).save(tmp_path / "wide.tif")  # past 16 bits: no scale to trust
    raises_one_line("outside 16 bits", read_image, tmp_path / "wide.tif")
    # float images: values past 0..1 are clipped when composited, and said once for the scene
    folder = write_blender(tmp_path / "hdr", {"train": [rgba(4, 4)[..., :3]] * 3})
    meta = json.loads((folder / "transforms_train.json").read_text())
    for i, frame in enumerate(meta["frames"]):
        Image.fromarray(np.full((4, 4), 4.0 if i else 0.5, np.float32)).save(folder / "train" / f"r_{i}.tif")
        frame["file_path"] = f"./train/r_{i}.tif"
    (folder / "transforms_train.json").write_text(json.dumps(meta))
    said = load_scene(folder, holdout_every=0).extra["warnings"]
    assert len(said) == 1 and "2 of 3 images hold floating-point values outside 0..1" in said[0], said
    # a folder where an image should be; an animated image
    folder = write_blender(tmp_path / "odd", {"train": [rgba(4, 4)] * 2})
    (folder / "train" / "r_1.png").unlink()
    (folder / "train" / "r_1.png").mkdir()
    raises_one_line(r"frame 1.*r_1.* is a folder .*not an image file", load_scene, folder)
    (folder / "train" / "r_1.png").rmdir()
    frames = [Image.fromarray(rgba(4, 4, i)) for i in range(2)]
    frames[0].save(folder / "train" / "r_1.png", save_all=True, append_images=frames[1:])
    raises_one_line(r"r_1\.png holds 2 frames \(an animated image\)", load_scene, folder)
    # a NaN passes every range test and survived clamping into the training images
    nan = np.full((4, 4), 0.5, np.float32)
    nan[1, 2] = np.nan
    Image.fromarray(nan).save(tmp_path / "nan.tif")
    raises_one_line("holds NaN or infinite values", read_image, tmp_path / "nan.tif")


def test_one_training_view_is_warned():
    """One training view trained and evaluated as if normal (held-out PSNR of a white image, ||w||_0 0)."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        folder = write_blender(Path(tmp) / "one", {"train": [rgba(4, 4)], "test": [rgba(4, 4, 1)]})
        said = load_scene(folder).extra["warnings"]
        assert any("has 1 training view" in w for w in said), said
        two = write_blender(Path(tmp) / "two", {"train": [rgba(4, 4)] * 2, "test": [rgba(4, 4, 1)]})
        assert "warnings" not in load_scene(two).extra


def test_jpeg_ringing_around_the_subject_is_not_foreground(tmp_path):
    """The procedural scene saved as JPEG (q85, 4:2:0, on white): its ringing put 1,708 background pixels past the
    lossless foreground tolerance, whose rays drew a surface on the box's faces (a data.bbox warning for content
    that does not exist, and a box never shrunk). Lossy images get the looser tolerance."""
    from PIL import Image

    from boostnerf_cli.render.coverage import foreground_masks, foreground_tol

    clean = make_scene(tmp_path / "clean", size=64, n_train=6, n_test=0)
    jpeg = make_scene(tmp_path / "jpeg", size=64, n_train=6, n_test=0)
    meta = json.loads((jpeg / "transforms_train.json").read_text())
    for frame in meta["frames"]:
        png = jpeg / (frame["file_path"] + ".png")
        rgba_ = np.asarray(Image.open(png).convert("RGBA")).astype(np.float32) / 255
        on_white = rgba_[..., :3] * rgba_[..., 3:] + (1 - rgba_[..., 3:])
        Image.fromarray((on_white * 255 + 0.5).astype(np.uint8)).save(png.with_suffix(".jpg"), quality=85)
        png.unlink()
        frame["file_path"] += ".jpg"
    (jpeg / "transforms_train.json").write_text(json.dumps(meta))
    a, b = load_scene(clean, holdout_every=0), load_scene(jpeg, holdout_every=0)
    assert b.extra.get("lossy") is True and "lossy" not in a.extra
    truth = foreground_masks(a.split("train").images, a.background, foreground_tol(a.extra))
    seen = foreground_masks(b.split("train").images, b.background, foreground_tol(b.extra))
    assert int((seen & ~truth).sum()) < 0.01 * int(truth.sum()), (int((seen & ~truth).sum()), int(truth.sum()))
    assert int((truth & ~seen).sum()) < 0.002 * int(truth.sum())


def test_boxes_in_messages_keep_their_digits_at_any_scale():
    """The geometry log printed a 2 mm box as [-0.001, -0.001, -0.001, 0.001, 0.001, 0.0] (fixed 3 decimals)."""
    from boostnerf_cli.scenes.bounds import box_text

    box = torch.tensor([[-1.8406, -1.66, -2.04], [1.76, 1.73, 1.63]], dtype=torch.float64)
    assert box_text(box) == [-1.841, -1.66, -2.04, 1.76, 1.73, 1.63]
    assert box_text(box * 1e-3) == [-0.001841, -0.00166, -0.00204, 0.00176, 0.00173, 0.00163]
    assert box_text(box * 1e3) == [-1841, -1660, -2040, 1760, 1730, 1630]


def test_cameras_far_from_the_origin_are_warned(tmp_path):
    """Every camera 1e5 from the origin (georeferenced coordinates) loaded without a word,
    while float32 rays and boxes there are known to 0.008 (the box moved by a lattice cell, the geometry kept 82%
    of its cells instead of 73%). 1000 units out is fine and says nothing."""
    images = [rgba(16, 16, i) for i in range(6)]
    for offset, warned in ((1e5, True), (1e3, False)):
        folder = write_blender(tmp_path / f"off{offset:g}", {"train": images})
        meta = json.loads((folder / "transforms_train.json").read_text())
        for frame in meta["frames"]:
            m = np.array(frame["transform_matrix"])
            m[:3, 3] += offset
            frame["transform_matrix"] = m.tolist()
        (folder / "transforms_train.json").write_text(json.dumps(meta))
        said = " | ".join(load_scene(folder, holdout_every=0).extra.get("warnings", []))
        assert ("recentre the poses" in said) == warned, (offset, said)
    # cameras sharing one spot near the origin (a panorama from a tripod): nothing is coarse there
    folder = write_blender(tmp_path / "tripod", {"train": images})
    meta = json.loads((folder / "transforms_train.json").read_text())
    for frame, pose in zip(meta["frames"], _ring(6, 1e-4, outward=True)):
        pose[:3, 3] += (0.3, 0.0, 0.0)
        frame["transform_matrix"] = pose.tolist()
    (folder / "transforms_train.json").write_text(json.dumps(meta))
    said = " | ".join(load_scene(folder, holdout_every=0).extra.get("warnings", []))
    assert "recentre the poses" not in said, said


def test_held_out_cameras_farther_than_the_training_ones_reach_the_box(tmp_path):
    """Near / far came from the training cameras alone, so test cameras 3x farther out ended
    every ray before the box: each held-out view rendered as pure background, scored as if the model were at fault,
    with no word. far now reaches the box from every split's cameras, with a note."""
    images = [rgba(16, 16, i) for i in range(6)]
    folder = write_blender(tmp_path / "far-test", {"train": images, "test": images[:2]})
    plain = load_scene(folder)
    meta = json.loads((folder / "transforms_test.json").read_text())
    for frame in meta["frames"]:
        m = np.array(frame["transform_matrix"])
        m[:3, 3] *= 3
        frame["transform_matrix"] = m.tolist()
    (folder / "transforms_test.json").write_text(json.dumps(meta))
    scene = load_scene(folder)
    corners = scene.bbox[[0, 1]]
    farthest = max(float((scene.splits["test"].poses[i, :3, 3] - torch.stack(
        [corners[(k >> a) & 1, a] for a in range(3)])).norm()) for i in range(2) for k in range(8))
    assert scene.far >= farthest - 1e-4 > plain.far, (scene.far, farthest, plain.far)
    assert "train and test" in scene.extra["notes"][0] and "notes" not in plain.extra


@pytest.mark.parametrize("layout", ["blender", "llff"])
def test_a_cached_scene_is_the_decoded_scene_until_its_files_or_settings_change(tmp_path, monkeypatch, layout):
    """load_scene(cache=...) decodes once and reads the same scene back (images, alpha, cameras, box, NDC, notes);
    a changed file or another setting decodes again."""
    import os

    from boostnerf_cli import scenes

    folder = make_scene(tmp_path / "scene", size=16, n_train=4, n_test=2, seed=0, layout=layout)
    cache = tmp_path / "ws" / "cache" / "scene.safetensors"
    decoded = load_scene(folder, image_size=12, cache=cache)
    assert cache.exists()
    real = scenes._decode
    monkeypatch.setattr(scenes, "_decode", lambda *a: pytest.fail("decoded although the cache fits"))
    again = load_scene(folder, image_size=12, cache=cache)
    assert again.describe() == decoded.describe() and again.extra == decoded.extra and again.ndc == decoded.ndc
    for name, split in decoded.splits.items():
        other = again.splits[name]
        assert split.names == other.names
        for a, b in ((split.images, other.images), (split.poses, other.poses), (split.intrinsics, other.intrinsics),
                     (split.alpha, other.alpha)):
            assert (a is None and b is None) or torch.equal(a, b)
    calls = []
    monkeypatch.setattr(scenes, "_decode", lambda *a: calls.append(a) or real(*a))
    load_scene(folder, image_size=8, cache=cache)  # another setting
    image = next(p for p in sorted(folder.rglob("*.png")))
    stat = image.stat()
    os.utime(image, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))  # a file changed (its time)
    load_scene(folder, image_size=8, cache=cache)
    assert len(calls) == 2
    data = bytearray(cache.read_bytes())  # the cache's own bytes changed (a flipped bit): decoded again, not read
    data[-200:-190] = b"\x7f" * 10
    cache.write_bytes(bytes(data))
    again = load_scene(folder, image_size=8, cache=cache)
    assert len(calls) == 3 and torch.isfinite(again.splits["train"].images).all()


@pytest.mark.parametrize("lens, model", [("pinhole", "OPENCV"), ("opencv", "OPENCV"), ("fisheye", "OPENCV_FISHEYE")])
def test_make_scene_s_readme_says_the_camera_model_its_transforms_hold(tmp_path, lens, model):
    """README.txt of a nerfstudio scene said "camera_model OPENCV ... zero distortion" whatever the lens."""
    folder = make_scene(tmp_path / lens, size=16, n_train=2, n_test=1, layout="nerfstudio", rig="half-orbit",
                        lens=lens)
    meta = json.loads((folder / "transforms.json").read_text())
    readme = (folder / "README.txt").read_text()
    assert meta["camera_model"] == model
    assert ("zero distortion" in readme) == (lens == "pinhole") and f"camera_model {model}" in readme, readme


def test_a_forward_facing_colmap_folder_is_not_called_an_llff_capture(tmp_path):
    """`auto` said "an LLFF capture" of any forward-facing scene, a COLMAP folder's too."""
    from boostnerf_cli.scenes.kind import auto_kind

    scene = load_scene(make_scene(tmp_path / "c", size=32, n_train=6, n_test=1, layout="colmap", rig="forward"))
    kind, why = auto_kind(scene, False)
    assert scene.ndc is not None and kind == "forward"
    assert "LLFF" not in why and why.startswith("a colmap capture whose cameras face one way"), why
    llff = load_scene(make_scene(tmp_path / "l", size=16, n_train=3, n_test=1, layout="llff"))
    assert auto_kind(llff, False)[1].startswith("an LLFF capture")


def test_the_sparse_points_box_leaves_every_side_a_tenth_of_its_longest(tmp_path):
    """A flat subject (a table top: points 2 wide, 0.2 high) got 10% of each axis' own extent: 0.02 below its
    floor, less than one coarse cell, so pretrain warned that make-scene's own COLMAP scenes reach past their box."""
    from boostnerf_cli.scenes.bounds import BOX_MARGIN, point_bounds

    g = torch.Generator().manual_seed(0)
    xyz = torch.rand(400, 3, generator=g, dtype=torch.float64) * torch.tensor([2.0, 2.0, 0.2])
    poses = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    poses[:, 2, 3] = 5.0  # two cameras above, looking down the -z axis at the points
    near, far, box, _ = point_bounds(xyz, poses, [torch.arange(400), torch.arange(400)])
    lo, hi = torch.quantile(xyz, torch.tensor([0.01, 0.99], dtype=torch.float64), dim=0)
    room = torch.cat([lo - box[0].double(), box[1].double() - hi])
    assert torch.allclose(room, torch.full_like(room, BOX_MARGIN * float((hi - lo).max())), atol=1e-6), room


def test_a_forward_facing_scene_s_rays_past_its_box_get_a_remedy_that_applies_to_it(tmp_path):
    """Rays of an LLFF capture ending past its box were told to set data.bbox or data.scene: unbounded, both
    refused for an LLFF capture (a 360-degree capture in that layout: NDC holds only what lies in front)."""
    from boostnerf_cli.scenes.kind import past_the_box_remedy, refusal

    folder = make_scene(tmp_path / "l", size=16, n_train=3, n_test=1, layout="llff")
    scene = load_scene(folder)
    remedy = past_the_box_remedy(scene)
    assert "data.bbox" not in remedy and "data.scene" not in remedy, remedy
    assert f"boostnerf capture --images {folder / 'images'}" in remedy, remedy
    assert refusal("unbounded", scene, folder, False)  # what it no longer names is refused indeed
    shots = tmp_path / "shots"  # the largest photos it has (images_16 sorts before images_2), as the loader picks
    for name, side in (("images_16", 4), ("images_2", 32), ("images_masks", 64)):
        (shots / name).mkdir(parents=True)
        iio.imwrite(shots / name / "p0.png", np.zeros((side, side, 3), np.uint8))
    import dataclasses

    assert f"--images {shots / 'images_2'} " in past_the_box_remedy(dataclasses.replace(scene, source=str(shots)))

