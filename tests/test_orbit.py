"""A phone walk around an object: the procedural half- and quarter-orbit captures (make-scene --rig half-orbit |
quarter-orbit), the kind `auto` gives them and every other scene, and the warnings that lead to the remedy."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import yaml
from conftest import cli_in_process, need_pycolmap, run_cli

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.scenes import load_scene, make_scene
from boostnerf_cli.scenes.alignment import pose_errors, scene_poses
from boostnerf_cli.scenes.kind import past_the_box_remedy

RIGS = ("half-orbit", "quarter-orbit")
KIND_MARGIN = 1.0  # dB the kind auto picks must hold out above the other one


@pytest.mark.parametrize("rig, degrees", [("half-orbit", 180), ("quarter-orbit", 90)])
def test_the_orbit_rigs_walk_part_way_round_an_object_in_an_opaque_room(tmp_path, rig, degrees):
    folder = make_scene(tmp_path / rig, size=16, n_train=10, n_test=2, layout="nerfstudio", rig=rig)
    meta = json.loads((folder / "transforms.json").read_text())
    photo = iio.imread(folder / meta["frames"][0]["file_path"])
    assert photo.shape == (16, 16, 3)  # opaque: every pixel shows the room, the table or the objects
    centres = np.array([f["transform_matrix"] for f in meta["frames"]])[:, :3, 3]
    target = np.array([0.0, 0.0, -0.25])
    way = centres - target
    azimuth = np.degrees(np.arctan2(way[:, 1], way[:, 0]))
    assert azimuth.max() - azimuth.min() == pytest.approx(degrees, abs=1e-3)
    elevation = np.degrees(np.arcsin(way[:, 2] / np.linalg.norm(way, axis=1)))
    assert np.allclose(np.sort(np.unique(elevation.round(3))), [10.0, 25.0])
    with pytest.raises(BoostNerfError, match=f"--rig {rig} writes an opaque capture in the nerfstudio layout"):
        make_scene(tmp_path / "x", size=8, layout="blender", rig=rig)


@pytest.mark.parametrize("rig", ["sphere", "orbit"])
def test_the_llff_layout_refuses_a_rig_all_around(tmp_path, rig):
    """LLFF is forward-facing (boostnerf samples it in NDC; docs/datasets.md): a 360-degree rig written in it trained
    to 10 dB with a warning whose two remedies were then refused."""
    with pytest.raises(BoostNerfError, match=f"the llff layout is forward-facing: --rig {rig}"):
        make_scene(tmp_path / "x", size=8, layout="llff", rig=rig)
    assert not (tmp_path / "x").exists()


def _opaque_on_white(folder: Path) -> Path:
    """The nerfstudio scene in `folder` with its RGBA photos flattened onto white (alpha dropped): an object
    photographed on a plain background."""
    for png in (folder / "images").glob("*.png"):
        rgba = iio.imread(png).astype(np.float64) / 255
        iio.imwrite(png, np.round(255 * (rgba[..., :3] * rgba[..., 3:] + 1 - rgba[..., 3:])).astype(np.uint8))
    return folder


def test_auto_picks_unbounded_for_a_walk_round_an_object_and_keeps_every_other_kind(tmp_path):
    for rig in RIGS:
        scene = load_scene(make_scene(tmp_path / rig, size=16, n_train=10, n_test=2, layout="nerfstudio", rig=rig))
        kind = scene.extra["kind"]
        assert kind["kind"] == "unbounded" and scene.contraction is not None, (rig, kind)
        assert "scenery at their edges" in kind["why"] and "one side" in kind["why"]
    # the scenes that load as they always have: the layouts that give a box or alpha, LLFF, the quickstart's scene,
    # the procedural unbounded capture, a COLMAP model on white, nerfstudio with alpha and on a plain background
    kept = {
        "blender": ({"layout": "blender"}, "bounded"),
        "nsvf": ({"layout": "nsvf"}, "bounded"),
        "tanks": ({"layout": "tanks"}, "bounded"),
        "llff": ({"layout": "llff"}, "forward"),
        "quickstart": ({"layout": "blender", "content": "detail"}, "bounded"),
        "unbounded": ({"layout": "nerfstudio", "rig": "unbounded"}, "unbounded"),
        "colmap": ({"layout": "colmap"}, "bounded"),
        "colmap-forward": ({"layout": "colmap", "rig": "forward"}, "forward"),
        "nerfstudio": ({"layout": "nerfstudio"}, "bounded"),
        "nerfstudio-orbit": ({"layout": "nerfstudio", "rig": "orbit"}, "bounded"),
    }
    for name, (kw, want) in kept.items():
        folder = make_scene(tmp_path / name, size=16, n_train=10, n_test=2, **kw)
        assert load_scene(folder).extra["kind"]["kind"] == want, name
    on_white = _opaque_on_white(make_scene(tmp_path / "white", size=16, n_train=10, n_test=2, layout="nerfstudio"))
    scene = load_scene(on_white)
    assert scene.splits["train"].alpha is None and scene.extra["kind"]["kind"] == "bounded", scene.extra["kind"]
    assert "plain background" in scene.extra["kind"]["why"]


def test_the_remedy_for_rays_past_the_box_names_the_kind_that_fixes_it(tmp_path):
    half = load_scene(make_scene(tmp_path / "half", size=16, n_train=10, n_test=2, layout="nerfstudio",
                                 rig="half-orbit"), kind="bounded")
    remedy = past_the_box_remedy(half)
    assert remedy.startswith("the views show scenery past the box: set recipe key data.scene: unbounded"), remedy
    assert "data.bbox" in remedy and remedy.index("data.scene: unbounded") < remedy.index("data.bbox")
    subject = load_scene(make_scene(tmp_path / "blender", size=16, n_train=10, n_test=2, layout="blender"))
    remedy = past_the_box_remedy(subject)  # a subject on its background: the box comes first
    assert remedy.index("data.bbox") < remedy.index("data.scene: unbounded"), remedy


RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "unbounded-dvgo-cpu.yaml"


def _recipe(path: Path, kind: str) -> Path:
    """recipes/unbounded-dvgo-cpu.yaml cut to one 16^3 expert, 150 steps, at 32 px, as `kind`."""
    rec = yaml.safe_load(RECIPE.read_text())
    rec["data"].update(image_size=32, scene=kind)
    rec["pretrain"].update(res=[16], iters=150)
    rec["pretrain"]["geometry"]["iters"] = 150
    path.write_text(yaml.safe_dump(rec, sort_keys=False))
    return path


@pytest.mark.slow
@pytest.mark.parametrize("rig", RIGS)
def test_the_kind_auto_picks_for_a_walk_round_an_object_trains_best(tmp_path, rig):
    """One DVGO expert trained briefly as each kind on the orbit twin: the kind auto picks holds out at least
    KIND_MARGIN above the other; trained bounded, the box-face warning names data.scene: unbounded."""
    scene = make_scene(tmp_path / "scene", size=32, n_train=16, n_test=2, layout="nerfstudio", rig=rig,
                       content="textured")
    auto = load_scene(scene).extra["kind"]["kind"]
    psnr, warnings = {}, {}
    for kind in ("bounded", "unbounded"):
        ws = tmp_path / kind
        proc = run_cli("pretrain", "--workspace", str(ws), "--data", str(scene), "--recipe",
                       str(_recipe(tmp_path / f"{kind}.yaml", kind)), "--device", "cpu", check=True, timeout=3600)
        psnr[kind] = json.loads((ws / "experts" / "dvgo-16.json").read_text())["test_psnr"]
        warnings[kind] = [line for line in proc.stderr.splitlines() if "faces of the scene box" in line]
    other = "bounded" if auto == "unbounded" else "unbounded"
    print(f"{rig}: dvgo-16 held out {psnr}, auto picks {auto}")
    assert psnr[auto] >= psnr[other] + KIND_MARGIN, (auto, psnr)
    assert warnings["bounded"] and "data.scene: unbounded" in warnings["bounded"][0], warnings
    assert not warnings["unbounded"], warnings


@pytest.mark.slow
def test_a_half_orbit_through_capture_is_placed_and_found_unbounded(tmp_path, monkeypatch, capsys):
    """The half-orbit twin's photos through `capture`: every camera placed where it was (after a similarity), and
    the scene it writes loads as unbounded, its sphere from the sparse points."""
    need_pycolmap()
    src = make_scene(tmp_path / "src", size=256, n_train=24, n_test=0, layout="nerfstudio", rig="half-orbit",
                     content="textured")
    out = tmp_path / "cap"
    code, err = cli_in_process(monkeypatch, capsys, "capture", "--images", str(src / "images"), "--out", str(out))
    assert code == 0, err
    report = json.loads((out / "capture.json").read_text())
    assert report["registered"] == report["given"] == 24, report
    captured = load_scene(out, holdout_every=0)
    by_name = lambda scene: {Path(k).name: v for k, v in scene_poses(scene).items()}  # noqa: E731
    errors = pose_errors(by_name(captured), by_name(load_scene(src, holdout_every=0)))
    assert errors["cameras"] == 24
    assert errors["median_rotation_deg"] < 0.5 and errors["median_centre_error"] < 0.01, errors
    assert captured.extra["kind"]["kind"] == "unbounded" and captured.points is not None
