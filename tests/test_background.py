"""train.random_background: each training ray composited on a random colour instead of the scene's background.

For captures whose every pixel is opaque (LLFF): against a fixed white background a white wall can be learned as
empty space (right colour, depth 0; docs/datasets.md). Checked against a float64 reference, across data-parallel
shards, and on a toy scene where the white background lets the wall stay empty. For scenes with alpha (Blender) the
pixel moves to the same colour by its alpha, so a transparent pixel still asks for empty space.
"""

import re

import pytest
import torch
from torch import Tensor

from boostnerf_cli import distributed as dist
from boostnerf_cli.fields.dvgo import DVGOConfig, DVGOExpert
from boostnerf_cli.recipe import TrainRecipe
from boostnerf_cli.render.renderer import RayBundle, RenderSettings, render_rays
from boostnerf_cli.scenes import load_scene, make_scene
from boostnerf_cli.tasks import photometric_loss, random_background, train_rays
from boostnerf_cli.train import RayData

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def _bundle(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    acc = torch.rand(n, generator=g, dtype=torch.float64)
    fore = torch.rand(n, 3, generator=g, dtype=torch.float64) * acc[:, None]  # premultiplied colour of the samples
    white = torch.ones(3, dtype=torch.float64)
    return RayBundle(fore + (1 - acc)[:, None] * white, torch.zeros(n), acc, 0, 0, {}), fore


def test_each_ray_is_composited_on_its_own_random_colour():
    bundle, fore = _bundle(64)
    rgb = torch.rand(64, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    tcfg = TrainRecipe(random_background=True, weight_rgbper=0.0, weight_entropy=0.0)
    loss, _ = photometric_loss(bundle, rgb, None, tcfg, (1.0, 1.0, 1.0), step=7)
    bg = random_background(64, 7, "cpu").double()
    ref = sum(float(((fore[i] + (1 - bundle.acc[i]) * bg[i] - rgb[i]) ** 2).sum()) for i in range(64)) / (64 * 3)
    assert float(loss) == pytest.approx(ref, rel=1e-12)
    assert 0.2 < float(bg.mean()) < 0.8 and float(bg.std()) > 0.2  # colours, not one grey
    off, _ = photometric_loss(bundle, rgb, None, TrainRecipe(weight_rgbper=0.0, weight_entropy=0.0), (1.0, 1.0, 1.0), 7)
    assert float(off) == pytest.approx(float(((bundle.color - rgb) ** 2).mean()), rel=1e-12)  # off: as before


def test_a_pixel_with_alpha_moves_to_the_random_colour_by_its_alpha():
    """float64 reference: target = premultiplied colour + (1 - alpha) * random colour, i.e. the pixel composited
    on white moved by (1 - alpha) * (random - white); alpha 1 leaves the pixel, as no alpha does."""
    bundle, fore = _bundle(64)
    g = torch.Generator().manual_seed(2)
    alpha = torch.rand(64, generator=g, dtype=torch.float64)
    alpha[:8], alpha[8:16] = 0.0, 1.0
    pixel = torch.rand(64, 3, generator=g, dtype=torch.float64) * alpha[:, None]  # premultiplied
    on_white = pixel + (1 - alpha)[:, None]
    tcfg = TrainRecipe(random_background=True, weight_rgbper=0.0, weight_entropy=0.0)
    loss, _ = photometric_loss(bundle, on_white, alpha, tcfg, (1.0, 1.0, 1.0), step=7)
    bg = random_background(64, 7, "cpu").double()
    ref = sum(float(((fore[i] + (1 - bundle.acc[i]) * bg[i] - pixel[i] - (1 - alpha[i]) * bg[i]) ** 2).sum())
              for i in range(64)) / (64 * 3)
    assert float(loss) == pytest.approx(ref, rel=1e-12)
    opaque, _ = photometric_loss(bundle, on_white, torch.ones(64, dtype=torch.float64), tcfg, (1.0, 1.0, 1.0), 7)
    none, _ = photometric_loss(bundle, on_white, None, tcfg, (1.0, 1.0, 1.0), 7)
    assert float(opaque) == pytest.approx(float(none), rel=1e-12)


def test_scenes_keep_their_alpha_and_training_rays_carry_it_only_when_asked(tmp_path):
    blender = load_scene(make_scene(tmp_path / "b", size=24, n_train=8, n_test=2), holdout_every=4)
    train, test = blender.splits["train"], blender.splits["test"]
    assert train.alpha is not None and train.alpha.shape == train.images.shape[:3]
    assert test.alpha is not None and test.alpha.shape == test.images.shape[:3]  # held out with their images
    assert float(train.alpha.min()) == 0.0 and float(train.alpha.max()) == 1.0
    empty = train.alpha == 0  # where nothing covers a pixel it is the background, white
    assert torch.allclose(train.images[empty], torch.ones(3))
    on = RayData.from_split(train, blender.bbox, blender.near, blender.far, keep_alpha=True)
    assert on.alpha is not None and on.alpha.shape == (len(on),)
    assert RayData.from_split(train, blender.bbox, blender.near, blender.far).alpha is None  # not asked: not kept
    assert train_rays(blender, blender.bbox, "cpu", TrainRecipe(random_background=True)).alpha is not None
    assert train_rays(blender, blender.bbox, "cpu", TrainRecipe()).alpha is None
    llff = load_scene(make_scene(tmp_path / "l", size=24, n_train=8, n_test=2, layout="llff"), holdout_every=4)
    assert llff.splits["train"].alpha is None  # opaque photographs: nothing to move
    assert train_rays(llff, llff.bbox, "cpu", TrainRecipe(random_background=True)).alpha is None


@pytest.mark.parametrize("layout,has_alpha", [("blender", True), ("nsvf", True), ("nerfstudio", True),
                                              ("tanks", False), ("llff", False)])
def test_every_loader_keeps_the_alpha_its_images_have(tmp_path, layout, has_alpha):
    """Every format's loader keeps its images' alpha with the split (and the held-out split), or None for images
    without one (Tanks and Temples comes composited on white, LLFF photographs are opaque)."""
    scene = load_scene(make_scene(tmp_path / layout, size=24, n_train=8, n_test=2, layout=layout))
    for split in scene.splits.values():
        if not has_alpha:
            assert split.alpha is None
            continue
        assert split.alpha is not None and split.alpha.shape == split.images.shape[:3]
        assert float(split.alpha.min()) == 0.0 and float(split.alpha.max()) == 1.0
        assert torch.allclose(split.images[split.alpha == 0], torch.ones(3))  # transparent: the white background

def test_images_without_alpha_among_images_with_alpha_are_named(tmp_path):
    """A Blender scene whose test images were saved as RGB (their transparent pixels black) while its train images are
    RGBA: the RGB images cannot be composited on the background and were used as they are without a word (a probe's
    PSNR fell from 10.4 to 0.8 dB against them). pretrain now says which images have no alpha."""
    import imageio.v3 as iio
    from conftest import make_recipe, run_cli

    scene = make_scene(tmp_path / "s", size=16, n_train=4, n_test=2)
    for image in sorted((scene / "test").glob("*.png")):
        iio.imwrite(image, iio.imread(image)[..., :3])
    (warning,) = load_scene(scene).extra["warnings"]
    assert re.search(r"2 of 6 images have no alpha channel .*test/r_0\.png", warning), warning
    assert "warnings" not in load_scene(make_scene(tmp_path / "rgba", size=16, n_train=4, n_test=2)).extra
    recipe = make_recipe(tmp_path / "r.yaml", data={"image_size": 16},
                         pretrain={"res": [8], "iters": 2, "geometry": {"iters": 2}})
    proc = run_cli("pretrain", "-w", str(tmp_path / "ws"), "--data", str(scene), "--recipe", str(recipe), "--device",
                   "cpu", check=True)
    assert "warning: 2 of 6 images have no alpha channel" in proc.stdout + proc.stderr


def test_the_colours_depend_on_the_step_alone_and_leave_torchs_random_stream_alone():
    torch.manual_seed(3)
    before = torch.rand(5)
    torch.manual_seed(3)
    a = random_background(16, 11, "cpu")
    after = torch.rand(5)
    assert torch.equal(before, after)  # the renderer's jitter draws what it drew without the option
    assert torch.equal(a, random_background(16, 11, "cpu"))  # a resumed run composites on the same colours
    assert not torch.equal(a, random_background(16, 12, "cpu"))


def test_data_parallel_shards_get_the_rows_of_the_global_batch(monkeypatch):
    whole = random_background(12, 5, "cpu")  # one process, the global batch of 12 rays
    monkeypatch.setattr(dist, "world_size", lambda: 3)
    shards = []
    for r in range(3):
        monkeypatch.setattr(dist, "rank", lambda r=r: r)
        shards.append(random_background(4, 5, "cpu"))
    assert torch.equal(torch.cat(shards), whole)


def _toy_opacity(random: bool, alpha: Tensor | None) -> float:
    """Train a toy field for 60 steps on rays seen head-on, every pixel white (composited on the white background,
    with `alpha`, or opaque when None), and return the rays' mean opacity."""
    torch.manual_seed(0)
    field = DVGOExpert(DVGOConfig(res=12, hidden=0, alpha_init=0.01), BOX)
    settings = RenderSettings(step=0.08, near=0.0, far=6.0, bbox=BOX, background=(1.0, 1.0, 1.0), color_threshold=0.0)
    tcfg = TrainRecipe(random_background=random, weight_rgbper=0.0, weight_entropy=0.0)
    g = torch.Generator().manual_seed(0)
    opt = torch.optim.Adam(field.parameters(), lr=0.1)
    for step in range(60):
        xy = torch.rand(256, 2, generator=g) * 1.6 - 0.8
        origins = torch.cat([xy, torch.full((256, 1), 3.0)], dim=-1)
        dirs = torch.tensor([0.0, 0.0, -1.0]).expand(256, 3)
        bundle = render_rays(field, origins, dirs, settings, jitter=True)
        loss, _ = photometric_loss(bundle, torch.ones(256, 3), alpha, tcfg, settings.background, step)
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        return float(render_rays(field, origins, dirs, settings).acc.mean())


@pytest.mark.parametrize("random", [False, True])
def test_a_white_wall_is_learned_as_a_surface_only_against_a_random_background(random):
    """A white wall behind empty space, seen head-on against the white background: the target is white
    everywhere. With the fixed background nothing asks for density and the rays stay mostly empty (depth 0);
    with a random one only an opaque white surface matches every draw."""
    acc = _toy_opacity(random, None)
    if random:
        assert acc > 0.9
    else:
        assert acc < 0.5


def test_empty_space_in_front_of_a_transparent_background_stays_empty_against_random_colours():
    """Blender's case: the pixels are transparent (alpha 0), composited on the white background. Against random
    colours the pixel moves with them, so empty space still matches every draw and the rays stay empty; a loss that
    kept the pixel white would ask for an opaque white surface (the white wall of the test above)."""
    assert _toy_opacity(True, torch.zeros(256)) < 0.1


def test_a_white_subject_on_white_is_told_by_its_alpha(tmp_path):
    """Images with alpha whose subject is white on the white background: foreground was decided by colour alone, so
    `pretrain` refused the scene as "nothing but the background" (and a white part of a coloured subject fell out of
    the visual hull, which carves the geometry). The alpha tells them apart: the scene trains, every pixel of the
    subject a foreground ray of the covering pass. (Its colour cannot place the subject: white on white looks the same
    with or without it, so only the alpha, through train.random_background, can teach an expert where it is.)"""
    import numpy as np
    from conftest import REMOVE, make_recipe, run_cli
    from PIL import Image

    from boostnerf_cli.render.coverage import foreground_masks
    from boostnerf_cli.workspace import read_meta

    scene = make_scene(tmp_path / "white", size=24, n_train=10, n_test=2, seed=0)
    for png in scene.rglob("*.png"):
        rgba = np.array(Image.open(png).convert("RGBA"))
        rgba[..., :3] = 255  # every pixel white: only the alpha shows the subject
        Image.fromarray(rgba, "RGBA").save(png)
    recipe = make_recipe(tmp_path / "r.yaml", data={"image_size": 24},
                         pretrain={"res": [8], "iters": 5, "geometry": {"res": 12, "iters": 60, "batch_rays": 256}},
                         moe=REMOVE)
    ws = tmp_path / "ws"
    run_cli("pretrain", "-w", str(ws), "--data", str(scene), "--recipe", str(recipe), "--device", "cpu", check=True)
    tr = load_scene(scene).splits["train"]
    assert not bool(foreground_masks(tr.images, (1.0, 1.0, 1.0)).any())
    assert bool(foreground_masks(tr.images, (1.0, 1.0, 1.0), alpha=tr.alpha).any())
    meta = read_meta(ws / "experts" / "geometry.safetensors")
    assert meta["rounds"][0]["foreground_rays"] == int((tr.alpha > 0.5).sum()) > 0
    # an alpha that marks no background (images saved composited, RGBA 255 everywhere, or without alpha: the loader
    # fills in 1) tells nothing: colour alone decides there, or every pixel of such a view would be foreground
    flat = make_scene(tmp_path / "flat", size=24, n_train=4, n_test=1, seed=0)
    for i, png in enumerate(sorted((flat / "train").glob("*.png"))):
        rgba = np.array(Image.open(png).convert("RGBA")).astype(float) / 255
        rgb = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])  # on white
        out = np.round(255 * np.concatenate([rgb, np.ones_like(rgb[..., :1])], -1)).astype(np.uint8)
        Image.fromarray(out if i % 2 else out[..., :3], "RGBA" if i % 2 else "RGB").save(png)
    tr = load_scene(flat).splits["train"]
    assert torch.equal(foreground_masks(tr.images, (1.0, 1.0, 1.0), alpha=tr.alpha),
                       foreground_masks(tr.images, (1.0, 1.0, 1.0)))
