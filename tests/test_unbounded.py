"""Unbounded scenes: the contraction (render/contraction.py), the scene kinds (scenes/kind.py), the procedural
unbounded capture (make-scene --rig unbounded), the distortion loss, and training on it against a bounded box."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
import yaml
from conftest import run_cli

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.lineage import Survey
from boostnerf_cli.render.contraction import Contraction, contraction_around
from boostnerf_cli.render.rays import image_rays
from boostnerf_cli.render.renderer import RenderSettings, sample_rays
from boostnerf_cli.render.volrend import distortion
from boostnerf_cli.scenes import load_scene, make_scene
from boostnerf_cli.scenes.kind import auto_kind
from boostnerf_cli.scenes.procedural import content_outside, intersect
from boostnerf_cli.workspace import Workspace

UNBOUNDED_MARGIN = 1.0  # dB the contracted expert must gain over the boxed one on the held-out views
DEPTH_TOLERANCE = 0.1  # the centre depth's largest relative error against the exact one


def test_contraction_keeps_the_sphere_squashes_the_rest_and_inverts():
    c = Contraction((0.5, -1.0, 2.0), 2.0, 2000.0)
    centre = torch.tensor(c.centre)
    inside = centre + 1.9 * torch.nn.functional.normalize(torch.randn(50, 3), dim=-1) * torch.rand(50, 1)
    assert torch.allclose(c.contract(inside), inside, atol=1e-6)
    far = centre + 1e6 * torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    r = (c.contract(far) - centre).norm(dim=-1)
    assert bool((r < 4.0).all()) and bool((r > 3.99).all())  # infinity lands on the ball of radius 2 r
    pts = centre + torch.randn(200, 3).double() * 10
    assert torch.allclose(c.uncontract(c.contract(pts)), pts, atol=1e-6)
    box = c.box()
    assert torch.allclose(box, torch.stack([centre - 4, centre + 4]))
    with pytest.raises(ValueError):
        Contraction((0, 0, 0), 0.0, 1.0)


def test_depth_pngs_of_unbounded_scenes_are_contracted_and_read_back():
    """An unbounded scene's depth PNG holds the depth contracted as the scene is (32768 one radius off, 65535 infinitely
    far), which reads back to world units; a bounded scene's stays depth / far."""
    from boostnerf_cli.images import depth_to_uint16

    r = 1.5
    t = torch.tensor([0.0, 0.3, r, 2 * r, 10 * r, 100 * r])
    u = depth_to_uint16(t, 1000 * r, r).astype(np.float64) / 65535
    assert list(np.round(u[[0, 2, 3]] * 65535)) == [0, 32768, 49151] and u[-1] > 0.99
    back = np.where(u <= 0.5, 2 * r * u, r / (2 * (1 - u)))
    assert np.allclose(back[1:5], t[1:5].numpy(), rtol=2e-3), back
    assert list(depth_to_uint16(torch.tensor([0.0, 2.0, 9.0]), 4.0)) == [0, 32768, 65535]


def test_samples_run_linear_inside_then_in_disparity_to_the_far_bound_and_stay_in_the_box():
    c = contraction_around(torch.zeros(3), 1.0)
    settings = RenderSettings(step=0.05, near=0.01, far=c.far, bbox=c.box(), contraction=c)
    origins = torch.zeros(4, 3)
    dirs = torch.nn.functional.normalize(torch.randn(4, 3), dim=-1)
    t, valid, xyz, step = sample_rays(origins, dirs, settings, jitter=False)
    n_in, n_out = c.slots(step)
    assert t.shape == (4, n_in + n_out) == (4, settings.sampling[0])
    inner = t[:, :n_in][valid[:, :n_in]].reshape(4, -1)
    assert torch.allclose(inner.diff(dim=1), torch.full_like(inner[:, 1:], 0.05), atol=1e-5)  # linear inside
    disparity = 1 / t[:, n_in:]
    assert torch.allclose(disparity.diff(dim=1), disparity.diff(dim=1)[:, :1].expand(-1, n_out - 1), atol=1e-5)
    assert float(t[:, -1].min()) > 20 and float(t.max()) <= c.far  # the last samples lie far out, short of far
    assert bool(((xyz - 0).norm(dim=-1) <= 2.0 + 1e-5).all())
    deltas = Contraction.deltas(xyz)
    assert float(deltas[:, n_in + 1 :].max()) < 2.5 * step  # about the step through the shell too


def test_distortion_loss_matches_its_pairwise_definition():
    torch.manual_seed(0)
    w = torch.rand(3, 7) / 7
    d = torch.rand(3, 7) + 0.1
    ends = d.cumsum(-1)
    mids = ends - d / 2
    brute = (w[:, :, None] * w[:, None, :] * (mids[:, :, None] - mids[:, None, :]).abs()).sum((1, 2))
    brute = brute + (w**2 * d).sum(-1) / 3
    assert torch.allclose(distortion(w, d), brute, atol=1e-6)
    # one sharp peak costs less than the same weight spread along the ray
    peak = torch.zeros(1, 7)
    peak[0, 3] = 1.0
    assert float(distortion(peak, torch.ones(1, 7))) < float(distortion(torch.full((1, 7), 1 / 7), torch.ones(1, 7)))


@pytest.fixture(scope="module")
def unbounded_scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("unb") / "scene", size=24, n_train=14, n_test=2, seed=0,
                      layout="nerfstudio", rig="unbounded")


def test_auto_tells_unbounded_captures_and_never_moves_bounded_or_forward_ones(unbounded_scene, tmp_path):
    scene = load_scene(unbounded_scene)
    assert scene.extra["kind"]["kind"] == "unbounded" and scene.contraction is not None
    assert "cameras all around" in scene.extra["kind"]["why"]
    poses = scene.splits["train"].poses[:, :3, 3]
    centre = torch.tensor(scene.contraction.centre, dtype=torch.float32)
    assert abs(float((poses - centre).norm(dim=-1).median()) - 2 * scene.contraction.radius) < 1e-3  # half their way
    assert torch.allclose(scene.bbox, scene.contraction.box())
    # the same views made bounded on request: the camera box, as before kinds existed
    bounded = load_scene(unbounded_scene, kind="bounded")
    assert bounded.contraction is None and float((bounded.bbox[1] - bounded.bbox[0]).max()) < 5
    for layout, want in (("blender", "bounded"), ("nerfstudio", "bounded"), ("tanks", "bounded"), ("llff", "forward")):
        s = load_scene(make_scene(tmp_path / layout, size=16, n_train=8, n_test=2, layout=layout))
        assert s.extra["kind"]["kind"] == want and s.contraction is None, (layout, s.extra["kind"])
    # an opaque nerfstudio capture of an object on white (no alpha) stays bounded: its edges show the background
    s = load_scene(tmp_path / "nerfstudio")
    opaque = dataclasses.replace(s, splits={k: dataclasses.replace(v, alpha=None) for k, v in s.splits.items()})
    assert auto_kind(opaque, False)[0] == "bounded"


def test_kinds_are_refused_where_they_cannot_work(unbounded_scene, tmp_path):
    llff = make_scene(tmp_path / "llff", size=16, n_train=8, n_test=2, layout="llff")
    for kind in ("bounded", "unbounded"):
        with pytest.raises(BoostNerfError, match="forward-facing"):
            load_scene(llff, kind=kind)
    with pytest.raises(BoostNerfError, match="needs a forward-facing LLFF capture"):
        load_scene(unbounded_scene, kind="forward")
    with pytest.raises(BoostNerfError, match="takes no data.bbox"):
        load_scene(unbounded_scene, kind="unbounded", bbox=[-1, -1, -1, 1, 1, 1])
    with pytest.raises(BoostNerfError, match="unbounded writes an opaque capture"):
        make_scene(tmp_path / "x", size=8, layout="blender", rig="unbounded")


def test_the_unbounded_capture_shows_mostly_content_outside_the_bounded_box(unbounded_scene):
    bounded = load_scene(unbounded_scene, kind="bounded")
    test = bounded.splits["test"]
    share = content_outside(unbounded_scene, test.poses, test.intrinsics, test.height, test.width, bounded.bbox)
    print(f"share of test pixels whose content lies outside the bounded box: {100 * share:.1f}%")
    assert 0.3 < share < 0.95
    assert not math.isnan(share)


RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "unbounded-dvgo-cpu.yaml"


def _chain_recipe(path, scene_kind: str, res: list[int]):
    """recipes/unbounded-dvgo-cpu.yaml at 32 px, 150 steps a stage, as `scene_kind`, experts `res`."""
    rec = yaml.safe_load(RECIPE.read_text())
    rec["data"].update(image_size=32, scene=scene_kind)
    rec["pretrain"].update(res=res, iters=150)
    rec["pretrain"]["geometry"]["iters"] = 150
    rec["moe"]["iters"] = 150
    path.write_text(yaml.safe_dump(rec, sort_keys=False))
    return path


@pytest.mark.slow
def test_on_the_unbounded_capture_contraction_beats_the_box_and_top2_beats_its_baseline(tmp_path):
    """The procedural unbounded capture (half its pixels show ground and sky past the cameras' box), with the unbounded
    CPU recipe cut to 32 px and 150 steps a stage: the same expert trained on the contracted scene beats the one
    trained in the cameras' box on the held-out views, Top-2 beats its same-steps baseline there, and the contracted
    depth PNG reads back to the distance of the surface it shows."""
    def cli(*args):  # an hour a stage: on a loaded machine one takes over the default 10 minutes
        return run_cli(*args, "--device", "cpu", check=True, timeout=3600)

    scene = make_scene(tmp_path / "scene", size=32, n_train=16, n_test=2, seed=0, layout="nerfstudio",
                       rig="unbounded")
    psnr = {}
    for kind, res in (("bounded", [16]), ("unbounded", [16, 24, 32])):
        ws, recipe = str(tmp_path / kind), str(_chain_recipe(tmp_path / f"{kind}.yaml", kind, res))
        cli("pretrain", "--workspace", ws, "--data", str(scene), "--recipe", recipe)
        psnr[kind] = json.loads((tmp_path / kind / "experts" / "dvgo-16.json").read_text())["test_psnr"]
    print(f"held-out PSNR of dvgo-16: bounded {psnr['bounded']:.2f}, unbounded {psnr['unbounded']:.2f}")
    assert psnr["unbounded"] > psnr["bounded"] + UNBOUNDED_MARGIN, psnr
    ws, recipe = str(tmp_path / "unbounded"), str(tmp_path / "unbounded.yaml")
    cli("build-moe", "--workspace", ws, "--recipe", recipe)
    for flag in (["--baseline"], ["--topk", "2"]):
        cli("finetune", "--workspace", ws, "--recipe", recipe, *flag)
    cli("eval", "--workspace", ws, "--split", "test", "--report", "--model", "baseline", "--model", "top2")
    rows = {r["name"]: r["psnr"] for r in json.loads((tmp_path / "unbounded" / "reports" / "eval.json").read_text())
            ["models"]}
    print(f"held-out PSNR on the contracted scene: baseline {rows['baseline']:.2f}, top2 {rows['top2']:.2f}")
    assert rows["top2"] > rows["baseline"], rows
    # the depth PNG, contracted: the centre pixel of the first held-out view reads back as the distance at which its
    # ray meets the scene's first surface (exact ray casting of its objects), not as black (65535 = the far bound, a
    # thousand radii off)
    cli("render", "--workspace", ws, "--model", "top2", "--views", "1")
    depth = iio.imread(next((tmp_path / "unbounded" / "renders" / "top2" / "test").glob("*_depth.png"))) / 65535.0
    radius = json.loads((tmp_path / "unbounded" / "manifest.json").read_text())["scene"]["contraction"]["radius"]
    (h, w), centre = depth.shape, (depth.shape[0] // 2) * depth.shape[1] + depth.shape[1] // 2
    u = float(depth[h // 2, w // 2])
    t = 2 * radius * u if u <= 0.5 else radius / (2 * (1 - u))
    test = Survey(Workspace(tmp_path / "unbounded")).scene().split("test")  # the views render drew
    o, d = (v[centre:centre + 1].double() for v in image_rays(test.poses[0], test.intrinsics[0], h, w))
    objects = json.loads((scene / "objects.json").read_text())["objects"]
    surface = min(float(intersect(obj, o, d)[0]) for obj in objects)
    assert abs(t / surface - 1) < DEPTH_TOLERANCE, (t, surface, radius)


def test_the_scene_cache_keeps_the_contraction_and_the_kind_is_part_of_its_key(unbounded_scene, tmp_path):
    cache = tmp_path / "scene.safetensors"
    first = load_scene(unbounded_scene, cache=cache)
    again = load_scene(unbounded_scene, cache=cache)
    assert again.contraction == first.contraction and again.extra["kind"] == first.extra["kind"]
    assert load_scene(unbounded_scene, cache=cache, kind="bounded").contraction is None


def test_the_distortion_key_adds_the_loss_and_is_in_no_signature_while_off():
    from types import SimpleNamespace

    from boostnerf_cli.lineage import shaping
    from boostnerf_cli.recipe import TrainRecipe
    from boostnerf_cli.tasks import photometric_loss

    w = torch.tensor([[0.2, 0.0, 0.5, 0.1]])
    bundle = SimpleNamespace(color=torch.zeros(1, 3), acc=w.sum(-1), extras={"weights": w, "step": 0.5})
    rgb = torch.zeros(1, 3)
    off = TrainRecipe(weight_rgbper=0.0, weight_entropy=0.0)
    on = dataclasses.replace(off, weight_distortion=0.1)
    base, _ = photometric_loss(bundle, rgb, None, off, (1.0, 1.0, 1.0), 0)
    with_it, _ = photometric_loss(bundle, rgb, None, on, (1.0, 1.0, 1.0), 0)
    assert torch.allclose(with_it - base, 0.1 * distortion(w, torch.full_like(w, 0.5)))
    assert "weight_distortion" not in shaping(off) and shaping(on)["weight_distortion"] == 0.1


def test_sparse_points_choose_the_sphere_when_a_scene_has_them(unbounded_scene):
    """A capture with a structure-from-motion model (`Scene.points`, whose `xyz` holds them, as COLMAP's) gets the
    sphere around its points, not around its cameras."""
    from boostnerf_cli.scenes.kind import contracted
    from boostnerf_cli.scenes.scene import SparsePoints

    scene = load_scene(unbounded_scene, kind="bounded")
    by_cameras = contracted(scene).contraction
    gen = torch.Generator().manual_seed(0)
    xyz = torch.randn(200, 3, generator=gen) * 0.3 + torch.tensor([0.2, 0.0, -0.1])
    points = SparsePoints(xyz, torch.zeros(200, 3, dtype=torch.uint8), torch.zeros(200), {})  # as COLMAP's loader keeps
    object.__setattr__(scene, "points", points)
    by_points = contracted(scene).contraction
    assert by_points.radius < 0.6 * by_cameras.radius and abs(by_points.centre[0] - 0.2) < 0.1
    assert by_points.reach > 2 * by_points.radius  # the cameras, outside it, still reach through it
