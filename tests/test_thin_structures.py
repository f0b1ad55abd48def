"""Skipping never cuts away what the training views show (the coarse geometry stage is conservative).

The procedural scene with thin content (`make-scene --content thin`) adds rods and a cable about one pixel
wide, reaching the edge of the scene's bounds, far from the main mass. The coarse 32^3 grid alone
cannot hold them (the box it found cut the corner wire away); with every foreground
ray required to cross kept space (render/coverage.py) an expert trained with skipping matches the same
expert trained with `--no-skip` (the whole scene box, every sample evaluated).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest
import torch
from conftest import REMOVE, make_recipe, run_cli

from boostnerf_cli.render.coverage import cover_foreground, foreground_masks, ray_cells
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.render.rays import image_rays
from boostnerf_cli.scenes import load_scene, make_scene
from boostnerf_cli.workspace import read_meta

# the tiny recipe's changes: one larger expert, 64 px images (the rods and cable 0.8 px wide), the default geometry
# alpha_init, no moe section
RECIPE_CHANGES = {
    "data": {"image_size": 64},
    "pretrain": {
        "res": [40],
        "iters": 400,
        "geometry": {"res": 32, "iters": 150, "batch_rays": 1024, "alpha_init": REMOVE},
        "train": {"batch_rays": 1024, "log_every": 100, "checkpoint_every": 5000, "occupancy_every": 200},
        "dvgo": {"hidden": 32},
    },
    "moe": REMOVE,
}


@pytest.fixture(scope="module")
def thin(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("thin")
    make_recipe(root / "r.yaml", **RECIPE_CHANGES)
    for layout in ("blender", "nsvf", "nerfstudio"):  # 24 views: nerfstudio holds out every 8th, Blender's 3 test views
        make_scene(root / layout, size=64, n_train=21, n_test=3, content="thin", layout=layout)
    return root


_RUNS: dict = {}  # (root, layout, flags) -> result: the layout tests share their runs (one xdist worker per file)


def _pretrain(root: Path, layout: str, *flags: str) -> dict:
    """The layout's expert, trained by `pretrain FLAGS`. With flags, in a copy of the plain run's workspace with
    --force: the expert is trained again, the geometry stage (the same scene and settings) is not."""
    key = (root, layout, flags)
    if key in _RUNS:
        return _RUNS[key]
    ws = root / f"ws-{layout}{''.join(flags)}"
    if flags:
        _pretrain(root, layout)
        shutil.copytree(root / f"ws-{layout}", ws)
    run_cli("pretrain", "-w", str(ws), "--data", str(root / layout), "--recipe", str(root / "r.yaml"),
            "--device", "cpu", *flags, *(["--force"] if flags else []), check=True)
    report = json.loads((ws / "experts" / "dvgo-40.json").read_text())
    meta = json.loads(__import__("safetensors").safe_open(str(ws / "experts" / "geometry.safetensors"), "pt")
                      .metadata()["boostnerf"])
    _RUNS[key] = {"psnr": report["test_psnr"], "box": torch.tensor(meta["fine_bbox"]), "coverage": meta["coverage"],
                  "rounds": meta["rounds"]}
    return _RUNS[key]


def covered(origins, dirs, grid: OccupancyGrid, near: float, far: float, box: torch.Tensor | None = None):
    """(R,) bool: some sample of the ray, a quarter cell apart inside the grid's box, lies in an occupied cell
    (and inside `box`)."""
    xyz, valid, _ = ray_cells(origins, dirs, grid, near, far)
    if box is not None:
        valid = valid & ((xyz >= box[0]) & (xyz <= box[1])).all(-1)
    hit = torch.zeros(valid.shape, dtype=torch.bool)
    hit[valid] = grid(xyz[valid])
    return hit.any(-1)


def test_cover_foreground_reaches_every_foreground_ray(thin):
    """An empty mask grows until each foreground training ray crosses an occupied cell inside the box, and the
    cells it adds are on the foreground rays, not the whole box."""
    scene = load_scene(thin / "blender")
    tr = scene.splits["train"]
    empty = OccupancyGrid(torch.zeros(24, 24, 24, dtype=torch.bool), scene.bbox)
    colour_only = dataclasses.replace(tr, alpha=None)  # foreground told by colour alone, as `masks` below
    grown, box, stats = cover_foreground(empty, lambda x: torch.zeros(x.shape[0]), colour_only, scene)
    masks = foreground_masks(tr.images, scene.background)
    assert stats["foreground_rays"] == int(masks.sum()) > 0
    # no density: no ray reaches a surface, each gets a cell of its own
    assert stats["missed_before"] == stats["foreground_rays"] and stats["missed_after"] == 0
    for i in range(len(tr)):
        o, d = image_rays(tr.poses[i], tr.intrinsics[i], tr.height, tr.width)
        fg = masks[i].reshape(-1)
        assert bool(covered(o[fg], d[fg], grown, scene.near, scene.far, box).all())
        assert not bool(covered(o[~fg], d[~fg], grown, scene.near, scene.far, box).all())  # background rays not all
    assert 0 < grown.fraction() < 0.3  # the visual hull of the views, not the whole box


def _slab(x: torch.Tensor) -> torch.Tensor:
    """A floor disc (radius 1, top at z -0.44) as a coarse model might learn it: an opaque slab over space under
    it that no view from above sees but the model filled (density smeared down to z -1.3)."""
    r = x[:, :2].norm(dim=-1)
    floor = (r < 1.0) & ((x[:, 2] + 0.5).abs() < 0.06)
    hidden = (r < 1.0) & (x[:, 2] < -0.5) & (x[:, 2] > -1.3)
    return torch.where(floor, 400.0, torch.where(hidden, 5.0, 0.0))


def test_the_box_holds_the_visible_surface_not_the_space_hidden_under_it(thin):
    """The box is drawn around the point where each foreground ray's surface starts (widened by half its pixel's
    footprint), so it ends inside the floor slab, just under its top (a coarse cell's widening would end under it).
    Space no view sees (filled here under the floor, inside the views' visual hull) stays in the mask but does not
    stretch the box: a box drawn around every occupied cell in the hull would reach below z -1 here (the thin
    scene's own pretrain box, -1.25)."""
    from boostnerf_cli.render.coverage import hull_cells

    scene = load_scene(thin / "blender")
    tr = scene.splits["train"]
    bg = torch.tensor(scene.background)
    images = []
    for i in range(len(tr)):  # the views of the disc alone: dark where a pixel's ray meets the floor's top
        o, d = image_rays(tr.poses[i], tr.intrinsics[i], tr.height, tr.width)
        t = (-0.44 - o[:, 2]) / d[:, 2]
        hit = (t > 0) & ((o + t[:, None] * d)[:, :2].norm(dim=-1) < 0.97)  # inside the slab's rim
        images.append(torch.where(hit[:, None], torch.tensor([0.2, 0.2, 0.2]), bg).reshape(tr.height, tr.width, 3))
    images = torch.stack(images)
    occ = OccupancyGrid.from_density(_slab, scene.bbox, (32, 32, 32), 0.05, 1e-3)
    framed = hull_cells(occ, images, tr.poses, tr.intrinsics, scene.background)
    assert framed.occupied_bbox(1)[0, 2] < -1.0  # the hidden space is (mostly) inside the hull
    grown, box, stats = cover_foreground(framed, _slab, dataclasses.replace(tr, images=images, alpha=None), scene)
    cell = (scene.bbox[1] - scene.bbox[0]) / 32
    assert -0.44 - 1.5 * float(cell[2]) < float(box[0, 2]) < -0.44, box  # within the slab, under its top
    assert float(box[1, 2]) < -0.44 + 0.5 * float(cell[2]), box  # the top: the floor's top and half a pixel
    assert bool((box[0, :2] > -1 - 1.5 * cell[:2]).all() & (box[1, :2] < 1 + 1.5 * cell[:2]).all()), box
    assert bool((grown.occupied >= framed.occupied).all())  # the mask only grows
    assert stats["missed_before"] == stats["missed_after"] == 0


def test_a_cells_footprint_in_the_hull_follows_each_axis_focal_length():
    """One 0.2-wide cell 4 units in front of a camera with fy = 2 fx (pixels twice as tall as they are wide in the
    scene: anamorphic, or resampled along one axis): a foreground pixel 4 px under the cell's centre lies inside its
    footprint (4.3 px tall), so the hull keeps the cell. The footprint was a square of fx's size (2.2 px): cut."""
    from boostnerf_cli.render.coverage import visual_hull

    occ = OccupancyGrid(torch.ones(1, 1, 1, dtype=torch.bool), torch.tensor([[-0.1, -0.1, -0.1], [0.1, 0.1, 0.1]]))
    pose = torch.eye(4)
    pose[2, 3] = 4.0  # at z = 4, looking down -z at the cell
    for fx, fy, below in ((50.0, 100.0, 4), (100.0, 50.0, 2)):
        mask = torch.zeros(1, 40, 40, dtype=torch.bool)
        mask[0, 20 + below, 20] = True
        assert bool(visual_hull(occ, pose[None], torch.tensor([[fx, fy, 20.0, 20.0]]), mask).all()), (fx, fy)
        mask = mask.transpose(1, 2)  # the same pixel to the right of the centre: fx's footprint, not fy's
        assert bool(visual_hull(occ, pose[None], torch.tensor([[fy, fx, 20.0, 20.0]]), mask).all()), (fy, fx)
    mask = torch.zeros(1, 40, 40, dtype=torch.bool)
    mask[0, 20 + 4, 20] = True  # outside a square fx = fy = 50 footprint (2.2 px): left out
    assert not bool(visual_hull(occ, pose[None], torch.tensor([[50.0, 50.0, 20.0, 20.0]]), mask).any())


def test_a_scene_without_a_known_background_covers_every_ray():
    from boostnerf_cli.render.coverage import foreground_masks as fm

    assert bool(fm(torch.rand(2, 3, 4, 3), None).all())
    assert not bool(fm(torch.ones(2, 3, 4, 3), (1.0, 1.0, 1.0)).any())


@pytest.mark.slow
def test_skipping_keeps_thin_structures(thin):
    """The same expert with and without skipping: within 0.3 dB held out (1.6 dB apart before the fix)."""
    skip, no_skip = _pretrain(thin, "blender"), _pretrain(thin, "blender", "--no-skip")
    assert skip["coverage"]["missed_before"] > 0 and skip["coverage"]["missed_after"] == 0
    assert len(skip["rounds"]) == 2 and sum(r["cells_added"] for r in skip["rounds"]) > 0
    assert skip["psnr"] > no_skip["psnr"] - 0.3, (skip["psnr"], no_skip["psnr"])


def _same_box(a: dict, b: dict) -> None:
    cell = float((a["box"][1] - a["box"][0]).max()) / 32
    assert torch.allclose(b["box"], a["box"], atol=1.5 * cell), (b["box"], a["box"])


@pytest.mark.slow
def test_layouts_without_a_box_file_give_the_same_box(thin):
    """Blender and nerfstudio copies of one scene (same views, same held-out views) give the same box to a coarse
    cell. Before the box was drawn inside the views' visual hull, the nerfstudio copy's box reached z = 1.69
    (floaters in front of its cameras, which its near plane of 0.1 r lets the coarse stage sample) against 0.72."""
    _same_box(_pretrain(thin, "blender"), _pretrain(thin, "nerfstudio"))


@pytest.mark.slow
def test_layouts_without_a_box_file_give_the_same_psnr(thin):
    """Blender and nerfstudio copies of one scene train to the same held-out PSNR. Both now take near / far from
    the cameras when the files record none; with Blender's fixed 2 / 6 moved the initial box's
    lattice and clipped the coarse stage at far 6, and the copies trained to 25.11 against 25.72 dB."""
    blender, nerfstudio = load_scene(thin / "blender"), load_scene(thin / "nerfstudio")
    assert (blender.near, blender.far) == pytest.approx((nerfstudio.near, nerfstudio.far), rel=1e-4)
    a, b = _pretrain(thin, "blender"), _pretrain(thin, "nerfstudio")
    assert abs(b["psnr"] - a["psnr"]) < 0.3, (b["psnr"], a["psnr"])


@pytest.mark.slow
def test_a_box_file_gives_the_same_box_as_the_cameras(thin):
    """An NSVF copy (its bbox.txt bounds every seed's objects) and a Blender copy (the box from the views alone) give
    the same box to a coarse cell and the same held-out PSNR. A views-only box ended at z -0.72 (0.12 under
    the floor: rays through the floor's anti-aliased rim pixels pass beyond the rim and gathered 0.1 opacity only under
    it, and the box kept a coarse cell on each side), and the copies trained 0.60 dB apart (25.93 against 26.53)."""
    a, b = _pretrain(thin, "blender"), _pretrain(thin, "nsvf")
    _same_box(a, b)
    assert abs(b["psnr"] - a["psnr"]) < 0.3, (b["psnr"], a["psnr"])


def test_an_unknown_content_is_one_line_and_writes_nothing(tmp_path):
    proc = run_cli("make-scene", str(tmp_path / "s"), "--content", "wires")
    assert proc.returncode == 2 and proc.stderr.strip().splitlines() == [
        "error: unknown scene content 'wires': use one of objects, thin, large, empty, detail, textured"]
    assert not (tmp_path / "s").exists()


def test_the_box_leaves_out_floaters_outside_the_visual_hull_but_covers_every_foreground_ray(thin):
    """A coarse model that filled its whole box (floaters everywhere): the box is drawn around the occupied
    cells inside the views' visual hull, which hold every object of the scene, and covering the foreground rays
    from those cells misses none (docs/results.md, "Does skipping keep thin structures?")."""
    from boostnerf_cli.render.coverage import hull_cells
    from boostnerf_cli.scenes.procedural import scene_objects

    scene = load_scene(thin / "blender")
    tr = scene.splits["train"]
    full = OccupancyGrid(torch.ones(32, 32, 32, dtype=torch.bool), scene.bbox)
    framed = hull_cells(full, tr.images, tr.poses, tr.intrinsics, scene.background)
    box = framed.occupied_bbox(margin_cells=1)
    size, whole = box[1] - box[0], scene.bbox[1] - scene.bbox[0]
    assert bool((size < 0.9 * whole).all()), (box, scene.bbox)  # floaters above the scene are out of the box
    # every object (the floor disc's rim, the rods' tops, the wire's far end) lies inside the box
    ends = []
    for obj in scene_objects(0, "thin"):
        if obj["kind"] == "capsule":
            ends += [torch.tensor(obj["a"], dtype=torch.float32), torch.tensor(obj["b"], dtype=torch.float32)]
    ends = torch.stack(ends)
    assert bool(((ends >= box[0]) & (ends <= box[1])).all()), (ends, box)
    _, _, stats = cover_foreground(framed, lambda x: torch.zeros(x.shape[0]), dataclasses.replace(tr, alpha=None),
                                   scene)
    assert stats["missed_after"] == 0
    # without a known background the hull says nothing: the grid is kept whole
    assert hull_cells(full, tr.images, tr.poses, tr.intrinsics, None) is full


def test_in_a_forward_facing_scene_every_pixel_is_foreground_even_the_background_coloured_ones(tmp_path):
    """A forward-facing capture (NDC, LLFF) has no background to tell from: a white wall or sky is content. Every
    training ray, white ones too, must cross kept space (before, pixels within 0.03 of white were left out: on fern,
    32,000 rays of the white ceiling)."""
    scene = load_scene(make_scene(tmp_path / "llff", size=24, n_train=6, n_test=0, layout="llff"))
    tr = scene.splits["train"]
    assert scene.ndc is not None and scene.background == (1.0, 1.0, 1.0)
    white = ~foreground_masks(tr.images, scene.background)
    assert int(white.sum()) > 100  # the procedural scene shows white behind its objects
    empty = OccupancyGrid(torch.zeros(16, 16, 16, dtype=torch.bool), scene.bbox)
    grown, _, stats = cover_foreground(empty, lambda x: torch.zeros(x.shape[0]), dataclasses.replace(tr, alpha=None),
                                       scene)
    assert stats["foreground_rays"] == tr.images.shape[0] * tr.height * tr.width
    assert stats["missed_before"] == stats["foreground_rays"] and stats["missed_after"] == 0
    # each white pixel's ray crosses a kept cell
    for i in range(tr.images.shape[0]):
        o, d = image_rays(tr.poses[i], tr.intrinsics[i], tr.height, tr.width, scene.ndc)
        fg = white[i].reshape(-1)
        assert bool(covered(o[fg], d[fg], grown, scene.near, scene.far).all())


def test_foreground_rays_that_miss_the_scene_box_are_warned_not_said_to_be_held(tmp_path, tiny_scene):
    """A box that leaves out part of what the views show (here data.bbox around the middle only, or images
    widened without their transforms): rays that miss the box cannot learn what they show. The covering pass
    counted them ("N missed") and then said "the box holds every ray's surface", with no warning."""
    recipe = make_recipe(tmp_path / "r.yaml", data={"image_size": 24, "bbox": [-0.4, -0.4, -0.5, 0.4, 0.4, 0.3]},
                         pretrain={"res": [8], "iters": 1, "geometry": {"res": 8, "iters": 30, "batch_rays": 256}},
                         moe=REMOVE)
    proc = run_cli("pretrain", "-w", str(tmp_path / "ws"), "--data", str(tiny_scene), "--recipe", str(recipe),
                   "--device", "cpu", check=True)
    meta = read_meta(tmp_path / "ws" / "experts" / "geometry.safetensors")
    missed, total = meta["rounds"][0]["missed_after"], meta["rounds"][0]["foreground_rays"]
    assert missed > 0.05 * total, meta["rounds"]
    assert (f"warning: geometry: {missed} of {total} foreground training rays" in proc.stderr
            and "miss the scene box" in proc.stderr)
    assert "the box holds every ray's surface" not in proc.stderr


@pytest.mark.slow
def test_content_past_the_scene_box_is_named_and_data_bbox_holds_it(tmp_path):
    """`make-scene --content large`: the floor reaches radius 3, past the box of the region most cameras see (about
    +-1.7), so the coarse model draws what lies beyond on the box's faces. The geometry stage says so and names
    data.bbox; with that key the box holds the floor and the warning is gone. The objects scene gets no warning, nor
    in the NSVF layout, whose bbox.txt make-scene writes with a coarse cell of room around the content (it was the
    content's own box, and 4-5% of the rays, the floor's, lay within a cell of its bottom face)."""
    recipe = {"pretrain": {"res": [8], "iters": 1, "geometry": {"res": 16, "iters": 150, "batch_rays": 512}},
              "moe": REMOVE}
    # a coarse cell (0.22) of room around the content: nearer, it is on the faces
    wide = [-3.3, -3.3, -0.9, 3.3, 3.3, 0.6]
    runs = {}
    for name, content, data, layout in (("large", "large", {}, "blender"),
                                        ("large-box", "large", {"bbox": wide}, "blender"),
                                        ("objects", "objects", {}, "blender"), ("objects-nsvf", "objects", {}, "nsvf")):
        scene = tmp_path / f"{content}-{layout}"
        if not scene.exists():
            make_scene(scene, size=32, n_train=12, n_test=0, content=content, layout=layout)
        make_recipe(tmp_path / f"{name}.yaml", data=data, **recipe)
        ws = tmp_path / f"ws-{name}"
        proc = run_cli("pretrain", "-w", str(ws), "--data", str(scene), "--recipe", str(tmp_path / f"{name}.yaml"),
                       "--device", "cpu", check=True)
        runs[name] = (proc.stdout + proc.stderr, read_meta(ws / "experts" / "geometry.safetensors"))
    text, meta = runs["large"]
    first = meta["rounds"][0]
    assert first["edge_rays"] > 0.05 * first["foreground_rays"], first
    assert "warning: geometry: " in text and "find their surface on the faces of the scene box" in text
    assert "data.bbox" in text
    text, meta = runs["large-box"]
    assert "faces of the scene box" not in text, text
    box = torch.tensor(meta["fine_bbox"])
    assert bool((box[0, :2] < -2.5).all() and (box[1, :2] > 2.5).all()), box  # the floor out to radius 3
    text, meta = runs["objects"]
    assert meta["rounds"][0]["edge_rays"] == 0 and "faces of the scene box" not in text
    text, meta = runs["objects-nsvf"]
    assert "faces of the scene box" not in text, meta["rounds"]
