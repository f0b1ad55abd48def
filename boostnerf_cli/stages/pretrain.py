"""`boostnerf pretrain`: train M experts independently, one per resolution.

1. Geometry (once per workspace): a small DVGO-style grid with direct colour (no MLP) is trained on
   the whole camera-derived box; its opacity gives an occupancy mask and the occupied box, saved as
   `experts/geometry.safetensors`. Every expert starts from it, so they all share one scene box.
2. Each expert trains inside that box with progressive grid growth, skipping samples in empty
   cells (the mask, refreshed from the expert's own density) and computing colour only for samples
   whose rendering weight is above a threshold.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor, nn

from boostnerf_cli import distributed as dist
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.dvgo import DVGOConfig, DVGOExpert
from boostnerf_cli.fields.registry import build_expert
from boostnerf_cli.lineage import (
    REFUSE,
    SKIP,
    ExpertSpec,
    Found,
    GeometrySpec,
    SceneSpec,
    Survey,
    decide,
    describe_change,
    scene_digest,
)
from boostnerf_cli.metrics import mse_to_psnr
from boostnerf_cli.models import load_expert, save_expert
from boostnerf_cli.recipe import (
    GeometryRecipe,
    PretrainRecipe,
    Recipe,
    TrainRecipe,
    nearest_listed,
    recipe_dict,
    unused_family_note,
)
from boostnerf_cli.render.coverage import (
    ALPHA_FOREGROUND,
    cover_foreground,
    foreground_masks,
    foreground_tol,
    hull_cells,
    known_background,
)
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.render.packing import packer_for
from boostnerf_cli.render.renderer import COLOR_THRESHOLD, RenderSettings, render_view
from boostnerf_cli.scenes import Scene, Split, load_scene, make_scene
from boostnerf_cli.scenes.bounds import box_text
from boostnerf_cli.scenes.kind import past_the_box_remedy
from boostnerf_cli.stages.common import slow_notice, train_and_report
from boostnerf_cli.startup import CLOCK
from boostnerf_cli.tasks import FieldTask, train_rays
from boostnerf_cli.train import Schedule, TrainCheckpoint, train
from boostnerf_cli.workspace import Workspace, read_json, remove, write_json

log = logging.getLogger(__name__).info  # the stage's messages, on stderr (cli.py says them)
warn = logging.getLogger(__name__).warning


def growth_schedule(iters: int, fractions: list[float]) -> tuple[int, ...]:
    """The steps (of 0 .. iters - 1) at which the grid doubles its voxels: one per fraction, those that fall on the
    same step or past the last one dropped, so that the grid always reaches its final size."""
    steps = {max(1, int(round(f * iters))) for f in fractions if 0 < f < 1}
    return tuple(sorted(s for s in steps if s < iters))


def _test_psnr(model: nn.Module, split: Split, settings: RenderSettings, skip, device, max_views: int = 1000) -> float:
    """Mean held-out PSNR, rendered as `eval` renders the expert: colour where a sample's weight exceeds the
    renderer's default threshold, not train.color_threshold (a threshold near 1 skips the colour of samples that
    `eval` shades, and the report and `eval` would score the expert differently)."""
    settings = dataclasses.replace(settings, color_threshold=COLOR_THRESHOLD)
    psnrs = []
    packer = packer_for(device)  # one for the views: each reuses the budgets the ones before it sized
    for i in range(min(len(split), max_views)):
        out = render_view(model, split, i, settings, skip, device, packer)
        mse = float(torch.mean((out["rgb"] - split.images[i]) ** 2))
        psnrs.append(mse_to_psnr(mse))
    return sum(psnrs) / max(1, len(psnrs))


# More than this share of the foreground training rays finding their surface within a coarse cell of the scene
# box's faces means content reaches past the box (a floor out to radius 3: 14%; the procedural objects and thin
# scenes: 0; lego at 100 px: 0 of 280,324; docs/datasets.md, "The scene box").
EDGE_WARN = 0.01


@dataclass(frozen=True)
class Site:
    """Where pretraining works: what the workspace holds (its survey), the scene, its id (`lineage.SceneSpec.id`),
    the device."""

    survey: Survey
    scene: Scene
    tag: str
    device: str

    @property
    def ws(self) -> Workspace:
        return self.survey.ws


@dataclass(frozen=True)
class Geometry:
    """What the shared coarse stage gives every expert: the occupied box (2, 3), the occupancy mask, the coarse model
    (a DVGO grid with direct colour) whose density warm-starts them."""

    box: Tensor
    occupancy: OccupancyGrid
    model: nn.Module


# ----------------------------------------------------------------------------------------------
def geometry_spec(site: Site, rec: GeometryRecipe, seed: int) -> GeometrySpec:
    """What the geometry is made from (its first round's spec: the settings, the seed, the scene's box and id); the
    refining round follows from it."""
    return GeometrySpec.of("geometry", site.tag, rec, seed, site.scene.bbox.flatten().tolist())


def ensure_geometry(site: Site, rec: GeometryRecipe, seed: int, checkpoint_every: int = 500,
                    retrain: bool = False) -> Geometry:
    """The shared occupied box, occupancy mask and coarse density (trained once per workspace, and again when
    `retrain`: its settings changed, and --force was given).

    The coarse grid trains over the scene's box; the box is drawn around the visible surface it finds (every
    foreground training ray's, render/coverage.py). With `refine`, when that box holds less than half the
    volume, a second coarse grid of the same size trains inside it (finer cells, so a floor or a wall is smeared
    over fewer of them) and draws the box again. The occupancy is over the last coarse grid's box.
    """
    ws = site.ws
    if ws.geometry_path.exists() and not retrain:
        model, occ, meta = load_expert(ws.geometry_path, site.device)
        return Geometry(torch.tensor(meta["fine_bbox"], device=site.device), occ, model)
    t0 = time.perf_counter()
    bbox = site.scene.bbox.to(site.device)
    box, occ, model, cover = _coarse_round(site, rec, bbox, "geometry", seed, checkpoint_every)
    if cover is not None and cover["edge_rays"] > EDGE_WARN * cover["foreground_rays"]:  # over the scene's own box
        warn(f"geometry: {cover['edge_rays']} of {cover['foreground_rays']} foreground training rays "
            f"({100 * cover['edge_rays'] / cover['foreground_rays']:.1f}%) find their surface on the faces of the "
            f"scene box {box_text(bbox)}: the scene reaches past it, and what lies "
            f"beyond is drawn on its faces; {past_the_box_remedy(site.scene)}")
    if cover is not None and cover["missed_after"] > EDGE_WARN * cover["foreground_rays"]:  # a refined box: those too
        warn(f"geometry: {cover['missed_after']} of {cover['foreground_rays']} foreground training rays "
            f"({100 * cover['missed_after'] / cover['foreground_rays']:.1f}%) miss the scene box {box_text(bbox)} "
            f"altogether: what they show lies outside it and cannot be learned; {past_the_box_remedy(site.scene)}")
    rounds = [cover]
    shrink = float((box[1] - box[0]).prod() / (bbox[1] - bbox[0]).prod())
    if rec.refine and cover is not None and shrink < 0.5:  # cells at least 1.26x finer: worth a second round
        log(f"geometry: again inside that box ({shrink:.2f} of the volume), at finer cells")
        CLOCK.begin()  # the refining round's start-up starts when the first round is done
        box, occ, model, cover = _coarse_round(site, rec, box, "geometry-refine", seed, checkpoint_every)
        rounds.append(cover)
    seconds = round(time.perf_counter() - t0, 2)
    save_expert(ws.geometry_path, model, occ, {"name": "geometry", "fine_bbox": box.tolist(), "iters": rec.iters,
                                               "seconds": seconds, "occupied_fraction": occ.fraction(),
                                               "coverage": rounds[-1], "rounds": rounds,
                                               "signature": geometry_spec(site, rec, seed).signature()})
    for name in ("geometry", "geometry-refine"):
        remove(ws.checkpoint_path(name))
    log(f"geometry: occupied {100 * occ.fraction():.1f}% of cells, box {box_text(box)} "
        f"({seconds:.1f}s)")
    CLOCK.begin()  # the first expert's start-up starts when the geometry is done
    return Geometry(box, occ, model)


def _coarse_round(site: Site, rec: GeometryRecipe, bbox: Tensor, name: str, seed: int,
                  checkpoint_every: int) -> tuple[Tensor, OccupancyGrid, nn.Module, dict | None]:
    """Train the coarse grid over `bbox` and find the box and the mask from it.

    -> (box (2, 3), occupancy over `bbox`, the coarse model, the covering's counts (None without cover_foreground))
    """
    log(f"{name}: training a {rec.res}^3 coarse grid for {rec.iters} steps to find the occupied box")
    scene, device = site.scene, site.device
    torch.manual_seed(seed)
    model = DVGOExpert(DVGOConfig(res=rec.res, hidden=0, alpha_init=rec.alpha_init), bbox).to(device)
    step = 0.5 * model.voxel_size
    settings = scene.render_settings(step, bbox)
    tcfg = TrainRecipe(batch_rays=rec.batch_rays, lr_grid=rec.lr, weight_rgbper=0.0, weight_entropy=rec.weight_entropy,
                       occupancy_every=0, log_every=max(1, rec.iters // 5), checkpoint_every=checkpoint_every)
    task = FieldTask(model, settings, tcfg, skip=None, base_mask=None)
    rays = train_rays(scene, bbox, device, tcfg)
    ckpt = site.ws.checkpoint_path(name)  # removed once the geometry is saved
    spec = GeometrySpec.of(name, site.tag, rec, seed, bbox.flatten().tolist())
    train(task, rays, Schedule.of(rec.iters, tcfg), seed, name, TrainCheckpoint(ckpt, spec.signature()))
    model.eval()
    occ = OccupancyGrid.from_density(model.density, bbox, model.shape, step, rec.alpha_threshold)
    cover = None
    if rec.cover_foreground:  # nothing the training views show may be cut away for good
        train_split = scene.splits["train"]
        framed = occ
        if rec.hull_box:
            framed = hull_cells(occ, train_split.images, train_split.poses, train_split.intrinsics,
                                known_background(scene.background, scene.ndc, scene.contraction),
                                foreground_tol(scene.extra),
                                train_split.alpha)
        outside = int((occ.occupied & ~framed.occupied).sum())
        if outside:
            log(f"{name}: {outside} of {int(occ.occupied.sum())} occupied cells lie outside the training views' "
                "visual hull (floaters, hidden space); they stay in the mask but do not count as surface")
        log(f"{name}: checking that every foreground ray of the {len(train_split)} training views reaches kept "
            "space")  # a pass over every training ray: minutes for a large capture
        framed, box, cover = cover_foreground(framed, model.density, train_split, scene, foreground_tol(scene.extra))
        cover["outside_hull"] = outside
        log(f"{name}: {cover['missed_before']} of {cover['foreground_rays']} foreground training rays reach no surface "
            f"in occupied cells; {cover['cells_added']} cells added along them ({cover['missed_after']} missed)"
            + ("; the box holds every ray's surface" if not cover["missed_after"] else ""))
        occ = OccupancyGrid(occ.occupied | framed.occupied, bbox)  # the mask only grows
        if scene.contraction is not None:  # unbounded: the background fills the contracted box out to its edge
            box = bbox.clone()
    else:
        box = occ.occupied_bbox(margin_cells=1)
    if not occ.occupied.any():
        warn(f"{name}: the coarse stage found no occupied space (too few geometry.iters?); "
            "experts will train on the whole camera box without skipping")
        occ, box, cover = OccupancyGrid(torch.ones_like(occ.occupied), bbox), bbox.clone(), None
    return box, occ, model, cover


def expert_name(model: str, res: int) -> str:
    return f"{model}-{res}"


def expert_options(rec: PretrainRecipe, res: int, say: bool = False) -> dict:
    """The family options of the expert at `res`. A mapping from resolution to value sets an option
    per expert (e.g. `hidden: {64: 64, 80: 96, 96: 128}` widens the colour MLP with the grid); for a
    resolution the mapping does not list (`--res 48` over such a recipe) the nearest listed resolution's
    value is taken (the larger on a tie), and with `say` the log says so."""
    opts = {}
    for key, value in rec.family_config().items():
        if isinstance(value, dict):
            try:  # JSON (the manifest) turns the keys into strings
                value = {int(k): v for k, v in value.items()}
            except ValueError:
                raise BoostNerfError(f"recipe key pretrain.{rec.model}.{key}: the keys of a per-expert mapping must be "
                                     f"resolutions (integers), got {list(value)}") from None
            if not value:
                raise BoostNerfError(f"recipe key pretrain.{rec.model}.{key} is an empty mapping: give a value per "
                                     "resolution, or a single value")
            res_key = nearest_listed(value, res)
            if res_key != res and say:
                log(f"recipe key pretrain.{rec.model}.{key} lists no value for res {res}: using {value[res_key]!r}, "
                    f"the value for the nearest listed resolution ({res_key})")
            value = value[res_key]
        opts[key] = value
    return {**opts, "res": res}


def pretrain_expert(site: Site, rec: PretrainRecipe, res: int, geometry: Geometry, force: bool = False) -> dict:
    """Train one expert at `res`, starting from `geometry`, and write its safetensors file and JSON report (with
    `rec.skip` off: on the scene's whole box instead of the geometry's, without its mask)."""
    ws, scene, device = site.ws, site.scene, site.device
    name = expert_name(rec.model, res)
    box, geom, tcfg = geometry.box, geometry.occupancy, rec.train
    if not rec.skip:  # the reference without skipping: the whole scene box, no occupancy mask or refresh
        box, geom = scene.bbox.to(device), None
        tcfg = dataclasses.replace(tcfg, occupancy_every=0)
    # Seed before building: the colour MLP's initialisation must not depend on what ran before in this
    # process (geometry trained now or loaded, other experts trained or skipped), or a resumed
    # pretrain would not reproduce an uninterrupted one.
    torch.manual_seed(rec.seed + res)
    model = build_expert(rec.model, expert_options(rec, res), box).to(device)
    final_voxels = res ** 3
    growth = growth_schedule(rec.iters, tcfg.growth) if model.grows else ()
    if growth:
        model.regrid(final_voxels // (2 ** len(growth)))
    model.init_density(geometry.model.density)  # warm start: colour is then computed near surfaces only
    settings = scene.render_settings(tcfg.step_ratio * model.unit, box, tcfg.color_threshold)
    task = FieldTask(model, settings, tcfg, skip=geom, base_mask=geom, growth_steps=growth, final_voxels=final_voxels)
    rays = train_rays(scene, box, device, tcfg)
    ckpt = ws.checkpoint_path(name)
    signature = ExpertSpec.of(rec, res, expert_options(rec, res), site.tag, site.survey.digest("geometry")).signature()
    _, trained = train_and_report(task, rays, Schedule.of(rec.iters, tcfg), rec.seed + res, name,
                                  TrainCheckpoint(ckpt, signature, restart_other=force), model)
    task.refresh_occupancy()
    report = {
        "name": name,
        "model": rec.model,
        "res": res,
        "seed": rec.seed,  # pretrain.seed: this expert's initialisation and batches draw from seed + res
        **trained,
        "grid_shape": list(model.shape),
        "occupied_fraction": task.skip.fraction() if task.skip is not None else 1.0,
        "skip": rec.skip,
    }
    test = scene.held_out()
    if test is not None:
        with slow_notice(f"{name}: scoring its {len(test)} held-out views"):
            report["test_psnr"] = round(_test_psnr(model, test, settings, task.skip, device), 3)
    save_expert(ws.expert_path(name), model, task.skip, {"name": name, "step": settings.step, "scene": site.tag,
                                                         "signature": signature})
    write_json(ws.expert_report_path(name), report)
    remove(ckpt)
    CLOCK.begin()  # the next expert's start-up starts when this one is written
    return report


def assign(res: list[int], world: int) -> list[list[int]]:
    """Share experts out over `world` ranks by cost: the largest first, each to the rank with the least work so far
    (an expert's cost taken as its `res`, which its samples per ray grow with); -> each rank's, ascending."""
    shares: list[list[int]] = [[] for _ in range(world)]
    for r in sorted(res, reverse=True):
        min(shares, key=sum).append(r)
    return [sorted(s) for s in shares]


def run(survey: Survey, data: Path | None, rec: Recipe, device: str, force: bool) -> list[dict]:
    """Train every expert of the recipe that is not finished yet; -> the reports of all of them.

    Under torchrun, rank 0 first prepares the workspace (scene, manifest, the shared geometry) while the
    other ranks wait, then they read what it wrote; the experts left to train are shared out (`assign`),
    each rank trains its own and writes their files, and once every rank has succeeded rank 0 alone
    records them in the manifest. A rank's failure stops every rank with its message (docs/distributed.md).
    """
    with dist.others_quiet():  # what every rank would repeat is said once
        site, geometry, todo = dist.main_first(lambda: _prepare(survey, data, rec, device, force))
        ws = survey.ws
        if not rec.pretrain.skip:
            log("pretrain.skip is off (--no-skip): experts train on the whole scene box without an occupancy mask "
                "(colour is still computed only where a sample's rendering weight exceeds train.color_threshold)")
    with dist.together():
        for res in assign(todo, dist.world_size())[dist.rank()]:
            report = pretrain_expert(site, rec.pretrain, res, geometry, force)
            if force and dist.is_main():  # retrained by this --force run: kept if it is interrupted and rerun
                ws.update_manifest(**{FORCED: [recipe_dict(rec), [*forced_done(ws, rec), report["name"]]]})
            log(f"{report['name']}: {report['iterations']} steps in {report['seconds']:.0f}s, train PSNR "
                f"{report['train_psnr']:.2f}"
                + (f", held-out PSNR {report['test_psnr']:.2f}" if "test_psnr" in report else ""))
    reports = [read_json(ws.expert_report_path(expert_name(rec.pretrain.model, res)), "expert report")
               for res in sorted(rec.pretrain.res)]
    dist.on_main(lambda: ws.update_manifest(experts={r["name"]: {"res": r["res"], "params": r["params"]}
                                                     for r in reports}))
    if force and dist.is_main() and FORCED in (manifest := ws.manifest()):  # the run is over: a new one retrains all
        manifest.pop(FORCED)
        write_json(ws.manifest_path, manifest)
    return reports


# The manifest's record of a `pretrain --force` run under way: [its recipe, the experts it has retrained]. Rerun with
# the same recipe after an interruption (as the interrupt line says), it does not retrain those again; the run's end
# removes it.
FORCED = "forced"


def forced_done(ws, rec: Recipe) -> list[str]:
    """The experts an interrupted `pretrain --force` run of recipe `rec` retrained already (`FORCED`), else []."""
    record = ws.manifest().get(FORCED)
    return list(record[1]) if isinstance(record, list) and len(record) == 2 and record[0] == recipe_dict(rec) else []


def check_foreground(scene: Scene, data: Path) -> None:
    """Refuse, before anything is written, a scene whose training views show nothing but its known background
    (every image's alpha transparent, a wrong folder): there is nothing to fit, and the geometry stage would
    find no surface. One view with any foreground is enough (a small object is fine). A forward-facing scene (NDC)
    has no background to tell from: its white wall or sky is content, as in the geometry stage's covering."""
    train_split = scene.splits["train"]
    if scene.background is None or scene.ndc is not None or scene.contraction is not None:
        return
    tol = foreground_tol(scene.extra)
    alphas = train_split.alpha if train_split.alpha is not None else [None] * len(train_split)
    if any(bool(foreground_masks(image[None], scene.background, tol, None if a is None else a[None]).any())
           for image, a in zip(train_split.images, alphas)):
        return
    colour = ", ".join(f"{c:g}" for c in scene.background)
    raise BoostNerfError(
        f"the {len(train_split)} training views of {data} show nothing but the background: no pixel differs from "
        f"its colour ({colour}) by more than {tol}"
        + (f" nor has an alpha above {ALPHA_FOREGROUND}" if train_split.alpha is not None else "")
        + "; check that the images hold the scene (an all-"
        "transparent alpha channel, a wrong folder)"
    )


def _prepare(survey: Survey, data: Path | None, rec: Recipe, device: str,
             force: bool) -> tuple[Site, Geometry, list[int]]:
    """Check the inputs, record them, load the scene and the shared geometry (trained if missing).

    -> (where pretraining works, the geometry, resolutions of the experts left to train).
    Under torchrun rank 0 runs this first and alone writes; the other ranks then find everything made.
    """
    ws = survey.ws
    scene, spec, tag, digest = _scene(survey, data, rec, force)
    site = Site(survey, scene, tag, device)
    retrain = _geometry_changed(site, rec.pretrain, force)
    decisions = {}  # every finished expert's, before anything is written (a refusal leaves the manifest as it is)
    # a --force run of this recipe that was interrupted: the experts it retrained already are kept (FORCED)
    done = forced_done(ws, rec) if force else []
    for res in sorted(rec.pretrain.res):
        name = expert_name(rec.pretrain.model, res)
        if (found := survey.finished(name)) is not None:
            geometry = (found.signature or {}).get("geometry")  # the geometry stage checks its own settings
            wanted = ExpertSpec.of(rec.pretrain, res, expert_options(rec.pretrain, res), tag, geometry).signature()
            decisions[res] = decide(found, wanted, force and not (
                name in done and decide(found, wanted).action == SKIP)).check()
    if dist.is_main():
        ws.update_manifest(data=spec.record(), scene_id=tag, scene_digest=digest, scene=scene.describe(),
                           recipe=recipe_dict(rec), **({FORCED: [recipe_dict(rec), done]} if force else {}))
    _describe(scene)
    geometry = ensure_geometry(site, rec.pretrain.geometry, rec.pretrain.seed, rec.pretrain.train.checkpoint_every,
                               retrain)
    todo = []
    for res in sorted(rec.pretrain.res):
        if decisions.get(res) is not None and decisions[res].action == SKIP:
            name = expert_name(rec.pretrain.model, res)
            log(f"{name}: already retrained by this --force run, skipping" if force else
                f"{name}: already trained, skipping (use --force to retrain)")
        else:
            todo.append(res)  # with --force, a checkpoint of other settings is dropped when training starts
    if retrain:  # the experts this run does not train again were trained on the old geometry
        training = {expert_name(rec.pretrain.model, res) for res in todo}
        for name in ws.expert_names():
            if name not in training and (why := survey.stale(name)) is not None:
                warn(f"{name} is stale: {why[0]}; make it again with {why[1]}")
    return site, geometry, todo


def _geometry_changed(site: Site, rec: PretrainRecipe, force: bool) -> bool:
    """Whether the geometry is to be trained again: a finished one of other settings is refused (`decide`), with
    --force retrained (said). --force alone does not retrain it: the same settings make the same geometry."""
    survey = site.survey
    found = Found("geometry", survey.signature("geometry")) if survey.meta("geometry") is not None else None
    wanted = geometry_spec(site, rec.geometry, rec.seed).signature()
    decision = decide(found, wanted)
    if decision.action == REFUSE and force:
        log(f"geometry: trained with other settings ({describe_change(found.signature, wanted)}): retraining it")
        return True
    decision.check()
    return False


def _describe(scene: Scene) -> None:
    """Say what was loaded: the format found, the loader's warnings and notes, the views."""
    if "detected" in scene.extra:
        log(f"format: {scene.extra['detected']}")
    for warning in scene.extra.get("warnings", []):
        warn(warning)
    for note in scene.extra.get("notes", []):
        log(f"note: {note}")
    if "box_from" in scene.extra:
        log(f"scene box {box_text(scene.bbox)} from {scene.extra['box_from']}")
    if "kind" in scene.extra:
        log(f"scene kind: {scene.extra['kind']['kind']} ({scene.extra['kind']['why']})"
            + (f"; space contracted around {[round(v, 4) for v in scene.contraction.centre]}, "
               f"sphere radius {scene.contraction.radius:.4g} kept linear, far {scene.contraction.far:.4g}"
               if scene.contraction is not None else ""))
    log(f"scene {scene.name}: {len(scene.splits['train'])} train views "
        f"{scene.splits['train'].width}x{scene.splits['train'].height}"
        + (f", {scene.holdout}" if scene.holdout else ""))


def _scene(survey: Survey, data: Path | None, rec: Recipe, force: bool) -> tuple[Scene, SceneSpec, str, str]:
    """The scene to train on: `data`, or the workspace's own (recorded, or generated when there is none). Another
    scene than the workspace's is refused (with --force: what was trained on it is forgotten); the same images and
    cameras at another path are the workspace's scene, moved (`Survey.scene_moved`, `Survey.scene_id`).
    -> (scene, its spec, its id, its digest)."""
    ws, previous = survey.ws, survey.manifest(required=False).get("data")
    if data is None and previous:  # a rerun without --data: the workspace's own scene, wherever it is
        data = survey.scene_path()
    generate = data is None and not (ws.root / "scene" / "transforms_train.json").exists()
    data = Path(ws.root / "scene" if data is None else data)
    spec = SceneSpec.of(data, rec.data, ws.root)
    is_moved, other = survey.scene_moved(data, spec)
    if other:  # before a default scene is generated: nothing written
        _forget_or_refuse(survey, force, other)
    if generate:
        log(f"no --data given: generating the default procedural scene in {data}")
        make_scene(data, size=rec.data.image_size or 64, seed=rec.pretrain.seed)  # atomic: never half a scene
    with slow_notice(f"reading the scene at {data} (its images are read and scaled once per stage)"):
        scene = load_scene(data, image_size=rec.data.image_size, holdout_every=rec.data.holdout_every,
                           format=rec.data.format, bbox=rec.data.bbox, cache=ws.scene_cache, kind=rec.data.scene)
    for res in rec.pretrain.res:  # per-expert options are checked (and chosen, said once) before anything trains
        expert_options(rec.pretrain, res, say=True)
    if note := unused_family_note(rec.pretrain):
        log(note)
    check_foreground(scene, data)
    digest = scene_digest(scene)
    tag, changed = survey.scene_id(data, spec, digest, is_moved)
    if changed:
        _forget_or_refuse(survey, force, changed)
    was = ws.root / previous["path"] if previous else None
    if is_moved and not changed and was.resolve() != data.resolve():  # not just re-recorded
        log(f"note: the workspace's scene is now {data} (it was {was}; the same images and cameras): nothing is "
            "retrained for the move")
    return scene, spec, tag, digest


def _forget_or_refuse(survey: Survey, force: bool, message: str) -> None:
    """Another scene than the workspace's: refused in one line, or with --force its experts, geometry and training
    checkpoints go."""
    if not force:
        raise BoostNerfError(message)
    for folder in (survey.ws.experts_dir, survey.ws.checkpoints_dir):
        for p in list(folder.glob("*")) if folder.exists() else []:
            remove(p)
