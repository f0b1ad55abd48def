"""Thin Typer commands: parse options, load the recipe, call one stage, print.

A `BoostNerfError` becomes one line on stderr and exit code 2, with no traceback.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Annotated, Any, Optional

import typer
from rich.console import Console
from rich.table import Table

from boostnerf_cli import faults
from boostnerf_cli.errors import BoostNerfError, out_of_memory
from boostnerf_cli.startup import CLOCK

app = typer.Typer(
    name="boostnerf",
    help="Boost Your NeRF: train Fast-NeRF experts, mix them with a gate, render and measure.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,  # Click's plain help: it wraps at any width; Rich's boxes cut words and option names
    context_settings={"max_content_width": 120},  # the terminal's width up to 120 (Click's own cap is 80)
)
err = Console(stderr=True, highlight=False, soft_wrap=True)


def _version(value: bool) -> None:
    if value:
        from boostnerf_cli import __version__

        print(f"boostnerf {__version__}")
        raise typer.Exit()


@app.callback()
def _app(
    version: Annotated[bool, typer.Option("--version", is_eager=True, callback=_version,
                                          help="Print boostnerf's version and exit.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help=(
        "Any command: say only warnings and errors on stderr, no notes or progress (results still print); before "
        "the command: boostnerf -q pretrain ..."))] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help=(
        "Any command: say more on stderr, the recipe read and what the stage decides about each artifact it finds "
        "(boostnerf -v finetune ...)."))] = False,
) -> None:
    """Boost Your NeRF: train Fast-NeRF experts, mix them with a gate, render and measure."""
    if quiet and verbose:
        raise BoostNerfError("--quiet and --verbose ask for opposite things: give one")
    say_messages(logging.WARNING if quiet else logging.DEBUG if verbose else logging.INFO)
out = Console(highlight=False)


def show(table: Table) -> None:
    """Print `table` on stdout: fitted to a terminal, and as wide as its cells in a file or pipe (Rich lays out
    80 columns there and cuts what does not fit). On a narrow terminal a cell folds onto more lines: Rich's default
    cut its end ("11.…" for a PSNR, "top1-pru…" for a model)."""
    for column in table.columns:
        column.overflow = "fold"
    if out.is_terminal:
        out.print(table)
        return
    from rich.measure import Measurement

    width = out.width
    out.width = max(width, Measurement.get(out, out.options.update_width(10_000), table).maximum)
    try:
        out.print(table)
    finally:
        out.width = width

WorkspaceOpt = Annotated[Path, typer.Option("--workspace", "-w", help="Workspace directory (created if missing).")]
DeviceOpt = Annotated[str, typer.Option("--device", help="auto (CUDA when available), cpu or cuda.")]
RecipeOpt = Annotated[Optional[Path], typer.Option(
    "--recipe", help="YAML recipe supplying defaults; flags override it.")]
SplitOpt = Annotated[str, typer.Option("--split", help="Split: test (val when it has none), val or train.")]
ModelsOpt = Annotated[Optional[list[str]], typer.Option(
    "--model", help="Model name(s); default: every model of the workspace.",
    callback=lambda names: list(dict.fromkeys(names)) if names else names)]  # a name given twice counts once
NoSkipOpt = Annotated[bool, typer.Option(
    "--no-skip", help="Turn every skip off: dense sampling, every sample evaluated.")]
SkipOffOpt = Annotated[Optional[list[str]], typer.Option(
    "--skip-off", help="Turn one skip off (repeatable): empty (occupancy, V_D) or terminated.")]
ExactGateOpt = Annotated[bool, typer.Option(
    "--exact-gate", help="Mixtures: the gate's grid + MLP per sample, not its baked logits.")]
ViewsOpt = Annotated[Optional[int], typer.Option("--views", min=1, help="Only the first N views of the split.")]


class _Stderr(logging.Handler):
    """The stages' messages (the `boostnerf_cli` log), one line each on stderr, as written, a warning's starting
    `warning: `: "[0.34, 0.66]" or a path "ws[2]" is no Rich markup tag."""

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        err.print(f"warning: {text}" if record.levelno >= logging.WARNING else text, markup=False)


def say_messages(level: int = logging.INFO) -> None:
    """Send the `boostnerf_cli` log, from `level` up, to stderr (-q: warnings; -v: debug)."""
    logger = logging.getLogger("boostnerf_cli")
    if not any(isinstance(h, _Stderr) for h in logger.handlers):
        logger.addHandler(_Stderr())
    logger.setLevel(level)


log = logging.getLogger(__name__).info


def _flag(ctx: typer.Context, param: str) -> str:
    """The option of the running command's parameter `param` as given (`--no-renormalize` for False)."""
    option = next(p for p in ctx.command.params if p.name == param)
    return option.secondary_opts[0] if option.secondary_opts and ctx.params[param] is False else option.opts[0]


def _one_process() -> None:
    """Refuse to run under torchrun (a command other than pretrain and finetune: its ranks would race)."""
    from boostnerf_cli import distributed as dist

    if dist.launched():
        raise BoostNerfError("only pretrain and finetune run under torchrun (docs/distributed.md): "
                             "run this command as one process")


def _writer(workspace: Path, must_exist: bool = True, distributed: bool = False):
    """The workspace, locked against a second writer (and checked to be one, unless it is being made).

    `distributed`: the command may run under torchrun (every rank shares rank 0's lock); the others refuse to.
    """
    from boostnerf_cli import distributed as dist
    from boostnerf_cli.workspace import Workspace

    if not distributed:
        _one_process()
    ws = Workspace(workspace)
    if must_exist:
        ws.require_manifest()
    return ws, dist.writer_lock(ws)


def _survey(ws):
    """What workspace `ws` holds, read once and handed to the stage (`lineage.Survey`; it reads when first asked,
    so inside the command's lock)."""
    from boostnerf_cli.lineage import Survey

    return Survey(ws)


def _reader(workspace: Path):
    """The workspace, checked to be one, with a reader's lock (`Workspace.reading`): shared with other readers."""
    from boostnerf_cli.workspace import Workspace

    _one_process()
    ws = Workspace(workspace)
    ws.require_manifest()
    return ws, ws.reading()


def _entries(text: str, what: str, give: str) -> list[str]:
    """A comma-separated option's entries; one lost ("8,,12", ",8") is refused, a trailing comma tolerated."""
    parts = text.replace(" ", "").split(",")
    if "" in parts[:-1]:
        raise BoostNerfError(f"{what} has an empty entry (got {text!r}): give {give}")
    return [p for p in parts if p]


def _int_list(text: str, what: str) -> list[int]:
    entries = _entries(text, what, "comma-separated whole numbers, e.g. 160,200,256")
    try:
        values = [int(v) for v in entries]
    except ValueError:
        raise BoostNerfError(f"{what} must be comma-separated whole numbers, e.g. 160,200,256 (got {text!r})") from None
    if not values:
        raise BoostNerfError(f"{what} needs at least one value (got {text!r})")
    return values  # each value's range: the recipe's check (pretrain.res), as for a YAML recipe


def _name_list(text: Optional[str], what: str) -> Optional[list[str]]:
    """Comma-separated names -> the list (None for none given); no name at all ("", ",") is refused as an entry lost
    is, never read as "all"."""
    if text is None:
        return None
    give = f"comma-separated names, or leave {what} out for all"
    names = _entries(text, what, give)
    if not names:
        raise BoostNerfError(f"{what} has an empty entry (got {text!r}): give {give}")
    return names


def _res_list(text: Optional[str]) -> Optional[list[int]]:
    return _int_list(text, "--res") if text else None


# The options that set a recipe key, declared once and named in each command's signature next to the recipe key they
# set (`_recipe(..., {"pretrain.iters": iters})`); --set sets any other key. Not given: None, the recipe's value.
SetOpt = Annotated[Optional[list[str]], typer.Option(
    "--set", metavar="KEY=VALUE", help="Set any recipe key (repeatable), checked as in a recipe file: "
    "--set pretrain.geometry.iters=300 (docs/recipe-keys.md).")]
ModelFamilyOpt = Annotated[Optional[str], typer.Option(
    "--model", help="Expert family: dvgo (dense grid), tensorf (VM) or ngp (hash grid).")]
ResOpt = Annotated[Optional[str], typer.Option(
    "--res", callback=_res_list, help="Comma-separated: one expert each, res^3 voxels (ngp: res levels).")]
ImageSizeOpt = Annotated[Optional[int], typer.Option(
    "--image-size", min=8, help="Longer image side in pixels after area downscaling.")]
HoldoutOpt = Annotated[Optional[int], typer.Option(
    "--holdout-every", help="No test split: hold out every N-th train view, N >= 2 (0: none).")]
FormatOpt = Annotated[Optional[str], typer.Option(
    "--format", help="Dataset format: auto, blender, nsvf, tanks, llff, colmap or nerfstudio.")]
SeedOpt = Annotated[Optional[int], typer.Option("--seed")]
SkipOpt = Annotated[Optional[bool], typer.Option(
    "--skip/--no-skip", show_default=False,
    help="--no-skip: train on the whole box, no occupancy mask (pretrain.skip).")]
GateResOpt = Annotated[Optional[int], typer.Option(
    "--gate-res", min=2, help="Gate grid resolution (gate_res^3 voxels; 128 in the paper).")]
GateTypeOpt = Annotated[Optional[str], typer.Option("--gate-type", help="grid (paper), linear or switch.")]
GateGridOpt = Annotated[Optional[str], typer.Option(
    "--gate-grid", help="Gate's feature grid: dense, tensorf, hash, or auto (the experts').")]
ThresholdOpt = Annotated[Optional[float], typer.Option(
    "--threshold", min=0.0, help="T: V_D filters samples whose opacity per step is below T.")]
MoEItersOpt = Annotated[Optional[int], typer.Option("--iters", min=1)]
LambdaOpt = Annotated[Optional[float], typer.Option(
    "--lambda", min=0.0, help="Auxiliary-loss weight (1e-3 in the paper).")]
PenaltyOpt = Annotated[Optional[str], typer.Option(
    "--penalty", help="geometric (paper), linear, quadratic, none or '1, 1.5, 2.23'.")]
RenormalizeOpt = Annotated[Optional[bool], typer.Option(
    "--renormalize/--no-renormalize", help="Top-k weights sum to 1 (default); off: raw gate probabilities.")]


@app.command("make-scene")
def make_scene_cmd(
    out_dir: Annotated[Path, typer.Argument(help="Folder to write the scene to.")],
    size: Annotated[int, typer.Option(help="Image side in pixels.", min=16, max=4096)] = 64,
    n_train: Annotated[int, typer.Option("--train-views", min=1)] = 24,
    n_test: Annotated[int, typer.Option("--test-views", min=0)] = 8,
    seed: Annotated[int, typer.Option()] = 0,
    layout: Annotated[str, typer.Option(
        "--format", help="Layout: blender, nsvf, tanks, llff, nerfstudio or colmap.")] = "blender",
    rig: Annotated[str | None, typer.Option(
        "--rig", help="Cameras: sphere, forward, orbit (a walk around the scene), unbounded (a ring inside a world "
        "of ground and sky), half-orbit or quarter-orbit (a phone walk part way round an object on a table in a "
        "room); the last three --format nerfstudio only (default: forward for llff, else sphere).")] = None,
    content: Annotated[str, typer.Option("--content", help=(
        "objects, thin (rods and a cable 1-2 px wide), large (a floor past the box), empty, or detail (fine "
        "patterns on one half, smooth content on the other: the quickstart's scene), or textured (dots SIFT "
        "matches: photos for boostnerf capture); docs/datasets.md."))] = "objects",
    lens: Annotated[str, typer.Option("--lens", help=(
        "pinhole, opencv (radial and tangential distortion) or fisheye: the views are ray-cast through it and the "
        "files record it (nerfstudio and colmap layouts)."))] = "pinhole",
) -> None:
    """Write a small procedural scene (exact ray casting) in any dataset layout boostnerf reads."""
    from boostnerf_cli.scenes import make_scene
    from boostnerf_cli.scenes.procedural import SEQUENCE_LAYOUTS, written_test_views

    _one_process()
    path = make_scene(out_dir, size=size, n_train=n_train, n_test=n_test, seed=seed, layout=layout, rig=rig,
                      content=content, lens=lens)
    written = written_test_views(layout, n_train, n_test)
    note = (f" ({layout} holds out every 8th view: with {n_train} train views that is {written} test views, not the "
            f"{n_test} asked for)") if written != n_test else ""
    if written == 0 and layout in SEQUENCE_LAYOUTS and n_train > 1:
        note = (f" ({layout} has no test split: its loader holds out every 8th of these train views unless the recipe "
                "sets data.holdout_every: 0)")
    log(f"wrote a {size}x{size} {layout} scene with {n_train} train and {written} test views to {path}{note}")


@app.command()
def pretrain(
    workspace: WorkspaceOpt,
    data: Annotated[Optional[Path], typer.Option(
        "--data", help="Scene folder (default: a procedural demo scene made in WS/scene).")] = None,
    recipe: RecipeOpt = None,
    model: ModelFamilyOpt = None,
    res: ResOpt = None,
    iters: Annotated[Optional[int], typer.Option("--iters", min=1, help="Training steps per expert.")] = None,
    image_size: ImageSizeOpt = None,
    holdout_every: HoldoutOpt = None,
    data_format: FormatOpt = None,
    seed: SeedOpt = None,
    skip: SkipOpt = None,
    sets: SetOpt = None,
    device: DeviceOpt = "auto",
    force: Annotated[bool, typer.Option("--force", help="Retrain experts that are already finished.")] = False,
) -> None:
    """Train one expert per resolution, independently (stage 1 of the paper)."""
    from boostnerf_cli import distributed as dist
    from boostnerf_cli.stages import pretrain as stage
    from boostnerf_cli.stages.common import resolve_device
    from boostnerf_cli.workspace import number

    rec = _recipe(workspace, recipe, sets, {  # a rerun (a moved scene, one more expert) keeps the workspace's recipe
        "pretrain.model": model, "pretrain.res": res, "pretrain.iters": iters, "data.image_size": image_size,
        "data.holdout_every": holdout_every, "data.format": data_format, "pretrain.seed": seed, "pretrain.skip": skip})
    ws, lock = _writer(workspace, must_exist=False, distributed=True)
    with dist.session(resolve_device(device)) as dev, lock:
        reports = stage.run(_survey(ws), data, rec, dev, force)
        if not dist.is_main():
            return
    table = Table("expert", "params", "steps", "seconds", "train PSNR", "held-out PSNR")
    for r in reports:
        table.add_row(r["name"], f"{r['params']:,}", str(r["iterations"]), f"{r['seconds']:.0f}",
                      number(r["train_psnr"], ".2f"), number(r.get("test_psnr"), ".2f"))
    show(table)


def _recipe(workspace: Path, recipe: Optional[Path], sets: Optional[list[str]], options: dict[str, Any]):
    """The recipe given, else the one recorded by pretrain in the workspace, else defaults (every stage's), with the
    `--set KEY=VALUE` settings, then the command's options `{recipe key: value}` (None: not given) applied, and
    checked again."""
    from boostnerf_cli.recipe import Recipe, load_recipe, recorded_recipe
    from boostnerf_cli.workspace import Workspace

    if recipe is not None:
        rec, source = load_recipe(recipe), str(recipe)
    else:
        ws = Workspace(workspace)
        rec, source = recorded_recipe(ws.manifest().get("recipe"), ws.manifest_path), f"{ws.manifest_path}"
        rec, source = (rec, source) if rec is not None else (Recipe(), "the defaults")
    return _changed(rec, source, sets, options)


def _changed(rec, source: str, sets: Optional[list[str]], options: dict[str, Any]):
    """Recipe `rec` (read from `source`) with the `--set KEY=VALUE` settings, then the command's options
    `{recipe key: value}` (None: not given) applied, and checked again."""
    from boostnerf_cli.recipe import parse_setting

    changes = dict(parse_setting(text) for text in sets or [])
    changes.update((key, value) for key, value in options.items() if value is not None)
    logging.getLogger(__name__).debug(f"recipe {rec.name} (from {source})"
                                      + "".join(f"; {key} = {value!r}" for key, value in changes.items()))
    return rec.override(changes)


@app.command("build-moe")
def build_moe(
    workspace: WorkspaceOpt,
    experts: Annotated[Optional[str], typer.Option(
        "--experts", help="Comma-separated expert names (default: all).")] = None,
    recipe: RecipeOpt = None,
    gate_res: GateResOpt = None,
    gate_type: GateTypeOpt = None,
    gate_grid: GateGridOpt = None,
    threshold: ThresholdOpt = None,
    sets: SetOpt = None,
    device: DeviceOpt = "auto",
) -> None:
    """Assemble the pretrained experts, the density volume V_D and an untrained gate."""
    from boostnerf_cli.stages import build_moe as stage
    from boostnerf_cli.stages.common import resolve_device

    rec = _recipe(workspace, recipe, sets, {"moe.gate_res": gate_res, "moe.gate_type": gate_type,
                                            "moe.gate_grid": gate_grid, "moe.density_threshold": threshold})
    names = _name_list(experts, "--experts")
    ws, lock = _writer(workspace)
    with lock:
        stage.build(_survey(ws), names, rec.moe, resolve_device(device))


@app.command()
def finetune(
    ctx: typer.Context,
    workspace: WorkspaceOpt,
    topk: Annotated[Optional[int], typer.Option(
        "--topk", min=1, help="Route each sample to its top-k experts (model topK).")] = None,
    ensemble: Annotated[bool, typer.Option("--ensemble", help="All experts, equal weights (model ens).")] = False,
    baseline: Annotated[bool, typer.Option(
        "--baseline", help="The largest expert alone, as many steps (model baseline).")] = False,
    recipe: RecipeOpt = None,
    iters: MoEItersOpt = None,
    lam: LambdaOpt = None,
    penalty: PenaltyOpt = None,
    renormalize: RenormalizeOpt = None,
    seed: SeedOpt = None,
    sets: SetOpt = None,
    device: DeviceOpt = "auto",
    force: Annotated[bool, typer.Option("--force", help="Redo a model that is already finetuned.")] = False,
) -> None:
    """Train gate and experts jointly (Algorithm 1), or the ensemble / baseline comparison models."""
    from boostnerf_cli import distributed as dist
    from boostnerf_cli.stages import finetune as stage
    from boostnerf_cli.stages.common import resolve_device

    name = stage.model_name(topk, ensemble, baseline)
    rec = _recipe(workspace, recipe, sets, {"moe.iters": iters, "moe.lam": lam, "moe.penalty": penalty,
                                            "moe.renormalize": renormalize, "moe.seed": seed})
    moot = {"moe.lam": "lam", "moe.penalty": "penalty", "moe.renormalize": "renormalize"}  # keys some models ignore
    ws, lock = _writer(workspace, distributed=True)
    with dist.session(resolve_device(device)) as dev, lock, dist.others_quiet():
        given = {key for key, param in moot.items() if ctx.params[param] is not None}
        survey = _survey(ws)  # what the workspace holds, read once for both questions below
        unused, why = stage.unused_settings(survey, name, topk, rec.moe, given)
        if unused:  # said also when the model is finished and skipped
            log(f"note: {', '.join(_flag(ctx, moot[key]) for key in unused)} cannot change "
                f"{'the baseline' if name == 'baseline' else name} ({why}): ignored")
        stage.run(survey, name, topk, rec.moe, dev, force)


@app.command()
def render(
    workspace: WorkspaceOpt,
    model: ModelsOpt = None,
    split: SplitOpt = "test",
    views: ViewsOpt = None,
    no_skip: NoSkipOpt = False,
    skip_off: SkipOffOpt = None,
    per_expert: Annotated[bool, typer.Option(
        "--per-expert", help="Mixtures: also each expert's share and gate map, and a montage.")] = False,
    compare: Annotated[bool, typer.Option(
        "--compare", help="Instead: ground truth and each model over its error map, side by side.")] = False,
    path: Annotated[Optional[str], typer.Option(
        "--path", help="Instead: a video along an orbit or spiral path; needs one --model.")] = None,
    frames: Annotated[Optional[int], typer.Option("--frames", min=1, help="--path: number of frames (default 60).")]
    = None,
    fps: Annotated[Optional[int], typer.Option("--fps", min=1, help="--path: frames per second (default 24).")] = None,
    video: Annotated[Optional[Path], typer.Option(
        "--video", help="--path, --camera-path: .mp4 or .gif (default WS/renders/MODEL/NAME.mp4).")] = None,
    camera: Annotated[Optional[Path], typer.Option(
        "--camera", help="Instead: a view `boostnerf view` saved (JSON), at its full size.")] = None,
    camera_path: Annotated[Optional[Path], typer.Option(
        "--camera-path", help="Instead: a video along a camera-path JSON (nerfstudio's layout, `boostnerf view` saves "
        "one); needs one --model.")] = None,
    exact_gate: ExactGateOpt = False,
    device: DeviceOpt = "auto",
) -> None:
    """Render a split with each model (PNG colour, 16-bit depth), a comparison, a video or a saved view."""
    from boostnerf_cli.models import Skips, Viewing
    from boostnerf_cli.stages import render as stage
    from boostnerf_cli.stages.common import resolve_device

    if sum((path is not None, compare, per_expert, camera is not None, camera_path is not None)) > 1:
        raise BoostNerfError("--path, --compare, --per-expert, --camera and --camera-path are separate outputs: use "
                             "one per command")
    if path is None and camera_path is None and video is not None:
        raise BoostNerfError("--video needs --path orbit, --path spiral or --camera-path FILE")
    for option, value in (("--frames", frames), ("--fps", fps)):
        if path is None and value is not None:
            raise BoostNerfError(f"{option} sets a --path video's: add --path orbit or --path spiral (a camera path's "
                                 "file sets its own frames and rate)")
    viewing = Viewing(split, views, Skips.from_flags(no_skip, skip_off), exact_gate)
    ws, lock = _writer(workspace)
    with lock:
        if path is not None:
            video_path = stage.VideoPath(path, frames or stage.VideoPath.frames, fps or stage.VideoPath.fps, video)
            written = stage.run_video(_survey(ws), model, video_path, resolve_device(device), viewing.skips)
        elif camera_path is not None:
            written = stage.run_camera_path(_survey(ws), model, camera_path, video, resolve_device(device),
                                            viewing.skips)
        elif camera is not None:
            written = stage.run_camera(_survey(ws), model, camera, resolve_device(device), viewing.skips)
        elif compare:
            written = stage.run_compare(_survey(ws), model, viewing, resolve_device(device))
        else:
            written = stage.run(_survey(ws), model, viewing, resolve_device(device), per_expert=per_expert)
    for p in written:  # stdout: the files written, one per line, for a script (the prose above is on stderr)
        print(p)


@app.command("camera-path")
def camera_path_cmd(
    workspace: WorkspaceOpt,
    views: Annotated[str, typer.Option(
        "--views", help="The dataset views the path passes, in order, e.g. 0,4,8 (indices into --split).")],
    split: Annotated[str, typer.Option("--split", help="The split whose views are the keyframes.")] = "train",
    seconds: Annotated[float, typer.Option("--seconds", help="The path's duration.")] = 4.0,
    fps: Annotated[float, typer.Option("--fps", help="Frames per second.")] = 24.0,
    smoothness: Annotated[float, typer.Option(
        "--smoothness", help="0: straight from keyframe to keyframe; 1: smooth (Catmull-Rom).")] = 1.0,
    loop: Annotated[bool, typer.Option("--loop", help="Close the path: the last keyframe leads back to the first.")]
    = False,
    out: Annotated[Optional[Path], typer.Option(
        "--out", help="The camera-path JSON (default WS/camera_paths/views.json).")] = None,
) -> None:
    """A camera path through the dataset's own views (nerfstudio's layout), for `render --camera-path` and `view`."""
    from boostnerf_cli.stages import render as stage

    keys = _int_list(views, "--views")
    ws, lock = _writer(workspace)
    with lock:
        print(stage.run_path_through_views(_survey(ws), split, keys, seconds, fps, smoothness, loop, out))


@app.command("eval")
def eval_cmd(
    workspace: WorkspaceOpt,
    model: ModelsOpt = None,
    split: SplitOpt = "test",
    views: ViewsOpt = None,
    no_skip: NoSkipOpt = False,
    skip_off: SkipOffOpt = None,
    report: Annotated[bool, typer.Option(
        "--report", help="Write WS/reports/eval.json and eval.md (the table in Markdown).")] = False,
    no_costs: Annotated[bool, typer.Option(
        "--no-costs", help="Skip ||w||_0 and GFLOPs (they need an extra pass).")] = False,
    exact_gate: ExactGateOpt = False,
    device: DeviceOpt = "auto",
) -> None:
    """PSNR, SSIM, LPIPS (when its weights are on disk) and seconds per image for every model."""
    from boostnerf_cli.models import Skips, Viewing
    from boostnerf_cli.stages import evaluate as stage
    from boostnerf_cli.stages.common import resolve_device

    viewing = Viewing(split, views, Skips.from_flags(no_skip, skip_off), exact_gate)
    ws, lock = _writer(workspace) if report else _reader(workspace)
    with lock:
        result = stage.run(_survey(ws), model, viewing, resolve_device(device), report, costs=not no_costs)
    if report:
        log(f"wrote {ws.reports_dir / 'eval.json'} and eval.md")
    show(_eval_table(result))


def _eval_table(result: dict) -> Table:
    """eval's table of `result` (its `models` rows), as `eval` and `chain` print it."""
    from boostnerf_cli.workspace import number

    table = Table("model", "PSNR", "SSIM", "LPIPS", "||w||_0", "GFLOPs/image", "s/image", "params")
    for r in result["models"]:
        table.add_row(r["name"], number(r["psnr"], ".3f"), number(r["ssim"], ".4f"), number(r["lpips"], ".4f"),
                      f"{r['w0']:,}" if "w0" in r else "-", f"{r['gflops_per_image']:.3f}" if "w0" in r else "-",
                      f"{r['seconds_per_image']:.3f}", f"{r['params']:,}")
    return table


@app.command("count-params")
def count_params_cmd(
    workspace: WorkspaceOpt,
    model: ModelsOpt = None,
    split: SplitOpt = "test",
    views: ViewsOpt = None,
    device: DeviceOpt = "auto",
) -> None:
    """Parameters, ||w||_0 and GFLOPs per image -> WS/reports/count-params.json."""
    from boostnerf_cli.stages import count_params as stage
    from boostnerf_cli.stages.common import resolve_device

    ws, lock = _writer(workspace)
    with lock:
        result = stage.run(_survey(ws), model, split, resolve_device(device), views)
    log(f"wrote {ws.reports_dir / 'count-params.json'}")
    table = Table("model", "params", "||w||_0", "GFLOPs/image")
    for r in result["models"]:
        table.add_row(r["name"], f"{r['params']:,}", f"{r['w0']:,}", f"{r['gflops_per_image']:.3f}")
    show(table)


@app.command("export")
def export_cmd(
    kind: Annotated[str, typer.Argument(help="pointcloud, mesh or routing (mixtures).")],
    workspace: WorkspaceOpt,
    model: Annotated[str, typer.Option("--model", help="The model to export (e.g. dvgo-160, top2).")],
    out: Annotated[Path, typer.Option("--out", help="File to write: .ply (mesh: or .obj).")],
    points: Annotated[int, typer.Option("--points", min=1, help="pointcloud: points at most, drawn from every kept "
                                        "pixel of the training views.")] = 100_000,
    min_opacity: Annotated[float, typer.Option("--min-opacity", help="pointcloud: a pixel's accumulated opacity "
                                               "from which it is a point.")] = 0.5,
    views: Annotated[Optional[int], typer.Option("--views", min=1, help="pointcloud: only the first N training "
                                                 "views.")] = None,
    resolution: Annotated[int, typer.Option("--resolution", min=8, max=1024, help="mesh: density samples along the "
                                            "longest side of the region meshed.")] = 128,
    threshold: Annotated[float, typer.Option("--threshold", help="mesh: the surface where the opacity over one "
                                             "render step crosses this.")] = 0.2,
    device: DeviceOpt = "auto",
) -> None:
    """A model as a point cloud, a mesh or its routing, in the frame of the data as given (PLY or OBJ)."""
    from boostnerf_cli.stages import export as stage
    from boostnerf_cli.stages.common import resolve_device

    options = stage.ExportOptions(points, min_opacity, views, resolution, threshold)
    stage.check_request(kind, out, options)  # before the workspace is read: plyfile missing, a wrong suffix
    ws, lock = _reader(workspace)
    with lock:
        stage.run(_survey(ws), kind, model, out, options, resolve_device(device))
    print(out)  # stdout: the file written, for a script (the prose is on stderr)


@app.command()
def chain(
    data: Annotated[str, typer.Argument(metavar="DATA", help=(
        "Scene folder (any layout pretrain reads), or - for the embedded procedural scene (made in WS/scene)."))],
    workspace: WorkspaceOpt,
    recipe: Annotated[Optional[str], typer.Option("--recipe", help=(
        "Recipe file, or the name of one in recipes/ (blender-dvgo-cpu); default: the workspace's, else the CPU "
        "recipe of the scene's layout (said in one line)."))] = None,
    models: Annotated[str, typer.Option("--models", help=(
        "Finetuned models, comma-separated, made in this order: baseline, topK (top1, top2, ...), ens."))] = (
        "baseline,top1,top2,ens"),
    top1_weight: Annotated[str, typer.Option("--top1-weight", help=(
        "renormalized (Top-1's weight is 1) or raw (the gate's probability, as the official code weighs Top-1: "
        "finetune --topk 1 --no-renormalize); the other models are unchanged."))] = "renormalized",
    data_format: FormatOpt = None,
    image_size: ImageSizeOpt = None,
    res: ResOpt = None,
    seed: Annotated[Optional[int], typer.Option("--seed", help=(
        "The experts' seed (pretrain.seed; also the procedural scene's)."))] = None,
    sets: SetOpt = None,
    frames: Annotated[int, typer.Option("--frames", min=1, help="The video's frames.")] = 48,
    video_model: Annotated[Optional[str], typer.Option("--video-model", help=(
        "The video's model, one of --models (default: the one with the highest held-out PSNR)."))] = None,
    device: DeviceOpt = "auto",
) -> None:
    """Every stage in one run: pretrain, build-moe, finetune the --models, eval --report, count-params, render
    --compare, and a video of the best model (an orbit; a spiral for a forward-facing scene). Rerun to go on."""
    from boostnerf_cli.images import ffmpeg_available
    from boostnerf_cli.recipe import load_recipe, recorded_recipe
    from boostnerf_cli.stages import chain as stage
    from boostnerf_cli.stages.common import resolve_device
    from boostnerf_cli.workspace import Workspace

    _one_process()
    names = stage.parse_models(models)  # before any stage: a typo found after an hour of pretraining costs the hour
    if top1_weight not in ("renormalized", "raw"):
        raise BoostNerfError(f"--top1-weight {top1_weight}: use renormalized or raw")
    if video_model is not None and video_model not in names:
        raise BoostNerfError(f"--video-model {video_model}: give one of the models the chain makes "
                             f"({', '.join(names)})")
    dev = resolve_device(device)
    if not ffmpeg_available():
        raise BoostNerfError("the chain ends with an MP4 video, and its writer imageio-ffmpeg (a boostnerf dependency) "
                             "is not installed or has no ffmpeg binary: pip install imageio-ffmpeg")
    scene = None if data == stage.PROCEDURAL else Path(data)
    if scene is not None:
        stage.check_data(scene)
    ws = Workspace(workspace)
    recorded = recorded_recipe(ws.manifest().get("recipe"), ws.manifest_path) if ws.manifest_path.is_file() else None
    why = None
    if recipe is not None:
        source = stage.find_recipe(recipe)
        rec = load_recipe(source)
    elif recorded is not None:
        rec, source = recorded, ws.manifest_path
        why = f"recipe {recorded.name}: the one {ws.manifest_path} records (--recipe: another)"
    else:
        pick = stage.pick_recipe(scene, dev, data_format)
        rec, source, why = load_recipe(pick.path), pick.path, pick.why
    rec = _changed(rec, str(source), sets, {"data.format": data_format, "data.image_size": image_size,
                                            "pretrain.res": res, "pretrain.seed": seed})
    stage.check_models(names, rec)
    if scene is not None and rec.data.format == "auto":
        stage.layout_of(scene)  # a folder of no layout: one line, before the workspace is made
    if why:
        log(why)
    plan = stage.Plan(scene, rec, names, top1_weight == "raw", video_model, frames)
    ws, lock = _writer(workspace, must_exist=False)
    with lock:
        outcome = stage.run(ws, plan, dev)
    show(_eval_table(outcome.eval))
    pictures = outcome.pictures[0].parent if outcome.pictures else ws.renders_dir("compare", "test")
    log("chain: seconds by stage: " + ", ".join(f"{name} {s:.0f}" for name, s in outcome.stages.items()))
    log(f"chain: done in {outcome.seconds:.0f} s: {ws.reports_dir / 'eval.md'}, {ws.reports_dir / 'count-params.json'}"
        f", {pictures}/, {outcome.video[0]}")


@app.command()
def prune(
    workspace: WorkspaceOpt,
    model: Annotated[str, typer.Option("--model", help="The model to prune (e.g. top1); writes model NAME-pruned.")],
    split: Annotated[str, typer.Option("--split", help="Views whose loss gradient decides what is kept.")] = "train",
    views: ViewsOpt = None,
    device: DeviceOpt = "auto",
    force: Annotated[bool, typer.Option("--force", help="Redo a model that is already pruned.")] = False,
) -> None:
    """Drop the grid entries no training view uses -> WS/moe/NAME-pruned.safetensors + .json."""
    from boostnerf_cli.stages import prune as stage
    from boostnerf_cli.stages.common import resolve_device
    from boostnerf_cli.workspace import number

    ws, lock = _writer(workspace)
    with lock:
        r = stage.run(_survey(ws), model, split, resolve_device(device), views, force)
    table = Table("model", "params", "file MB", "test PSNR", "train views max |diff|")
    table.add_row(r["from"], f"{r['params_before']:,}", f"{r['file_bytes_before'] / 1e6:.2f}",
                  number(r["test_psnr_before"], ".3f"), "")
    table.add_row(r["name"], f"{r['params_after']:,}", f"{r['file_bytes_after'] / 1e6:.2f}",
                  number(r["test_psnr_after"], ".3f"), f"{r['train_max_abs_diff']:.1e}")
    show(table)


@app.command()
def bench(
    workspace: Annotated[Path, typer.Option(
        "--workspace", "-w", help="Bench folder: variants in WS/variants, tables in WS/reports.")],
    data: Annotated[Optional[Path], typer.Option(
        "--data", help="Scene folder (default: a procedural demo scene made in WS/scene).")] = None,
    recipe: RecipeOpt = None,
    suite: Annotated[str, typer.Option("--suite", help="quick (the main rows) or full (+ ablations).")] = "quick",
    only: Annotated[Optional[str], typer.Option(
        "--only", help="Comma-separated row or group names of the suite to run (see --list).")] = None,
    list_rows: Annotated[bool, typer.Option(
        "--list", help="Print the suite's rows and whether each is finished; run nothing.")] = False,
    views: Annotated[Optional[int], typer.Option(
        "--views", min=1, help="Evaluate on the first N test views only.")] = None,
    device: DeviceOpt = "auto",
) -> None:
    """Run time against error on one scene: train, evaluate and tabulate every variant (resumable)."""
    from boostnerf_cli.recipe import load_recipe
    from boostnerf_cli.stages import bench as stage
    from boostnerf_cli.stages.common import resolve_device

    rec = (stage.folder_recipe(workspace) if recipe is None else None) or load_recipe(recipe)  # a rerun: its own
    names = _name_list(only, "--only")
    if list_rows:
        _, rows = stage.catalogue(rec, suite)
        for note in stage.catalogue_notes(rec, suite):
            log(f"note: {note}")
        # rows of a bench made with another recipe are not "finished"
        stage.check_config(workspace, data, views, rec, listing=True)
        table = Table("row", "group", "workspace", "model", "finished")
        for r in stage.select(rows, names, suite):
            done = stage.row_path(workspace, r.name).exists()
            table.add_row(r.name, r.group, f"variants/{r.setup}", r.model, "yes" if done else "no")
        show(table)
        return
    from boostnerf_cli.workspace import number

    _, lock = _writer(workspace, must_exist=False)
    with lock:
        result = stage.run(workspace, data, rec, suite, names, resolve_device(device), views)
    table = Table(*stage.COLUMNS)
    for r in result["rows"]:
        table.add_row(r["name"], r["group"], number(r["psnr"], ".3f"), number(r["ssim"], ".4f"),
                      f"{r['train_seconds']:.0f}", f"{r['seconds_per_image']:.3f}", f"{r['gflops_per_image']:.3f}",
                      f"{r['params']:,}", f"{r['w0']:,}")
    show(table)
    log(f"wrote {workspace / 'reports' / 'bench.json'} and bench.csv"
        + (f" and {len(result['plots'])} plots" if result["plots"] else ""))


@app.command()
def view(
    workspace: WorkspaceOpt,
    model: Annotated[Optional[str], typer.Option("--model", help="The model shown first (default: top2, top1 or the "
                                                 "largest; with --follow the newest).")] = None,
    port: Annotated[int, typer.Option("--port", min=0, max=65535, help="Port (the next free one if taken).")] = 8080,
    host: Annotated[str, typer.Option("--host", help="Address to serve on; 0.0.0.0 opens it to the network.")] = (
        "127.0.0.1"),
    follow: Annotated[bool, typer.Option(
        "--follow", help="Show the newest model or training checkpoint; reload it as training writes it.")] = False,
    size: Annotated[Optional[int], typer.Option(
        "--size", min=16, help="Height of a still frame in pixels (default: the images', within 128-256).")] = None,
    device: DeviceOpt = "auto",
) -> None:
    """A web page showing the scene, its cameras and each model's render, live (needs the viewer extra)."""
    from boostnerf_cli.stages import view as stage
    from boostnerf_cli.stages.common import resolve_device
    from boostnerf_cli.workspace import Workspace

    _one_process()
    stage.import_viser()  # before the scene is read: without viser, the one line saying how to install it
    try:
        stage.run(_survey(Workspace(workspace)), resolve_device(device), host, port, model, follow, size)
    except Interrupted:
        log("viewer stopped")


@app.command()
def capture(
    out: Annotated[Path, typer.Option("--out", help="Scene folder to write (a COLMAP model and its images).")],
    images: Annotated[Optional[Path], typer.Option(
        "--images", help="Folder of photos (.jpg, .png) of one size.")] = None,
    video: Annotated[Optional[Path], typer.Option("--video", help="A video file (read with ffmpeg).")] = None,
    frames: Annotated[int, typer.Option("--frames", min=3, help="A video's frames to keep: evenly spaced, each the "
                                        "sharpest of its stretch.")] = 100,
    camera_model: Annotated[str, typer.Option("--camera-model", help=(
        "COLMAP camera model: OPENCV, SIMPLE_RADIAL, RADIAL, PINHOLE, SIMPLE_PINHOLE, FULL_OPENCV, OPENCV_FISHEYE, "
        "SIMPLE_RADIAL_FISHEYE or RADIAL_FISHEYE."))] = "OPENCV",
    per_image_cameras: Annotated[bool, typer.Option(
        "--per-image-cameras", help="One camera per image (photos from several cameras or zoom levels); default: "
        "one shared camera.")] = False,
    force: Annotated[bool, typer.Option(
        "--force", help="Redo every phase, even those a previous run finished.")] = False,
) -> None:
    """Photos or a video in, a COLMAP scene folder out that pretrain --data reads (structure from motion by pycolmap:
    SIFT at 1024 px, matching that fits the input, incremental mapping; docs/capture.md)."""
    from boostnerf_cli.stages import capture as stage

    _one_process()
    if camera_model.upper() not in stage.CAMERA_MODELS:
        raise BoostNerfError(f"--camera-model {camera_model}: use one of {', '.join(stage.CAMERA_MODELS)}")
    options = stage.CaptureOptions(camera_model.upper(), per_image_cameras, frames=frames)
    r = stage.run(images, video, out, options, force)
    table = Table("phase", "seconds", "result")
    results = {"images": f"{r['given']} images", "features": f"{r['keypoints']:,} keypoints",
               "matching": f"{r['verified_pairs']:,} verified pairs ({r['matching']})",
               "mapping": f"{r['registered']} of {r['given']} registered, {r['points']:,} points, mean reprojection "
                          f"error {r['mean_reprojection_error']:.2f} px",
               "downscale": ", ".join(r["folders"])}
    for phase, seconds in r["seconds"].items():
        table.add_row(phase, f"{seconds:.1f}", results[phase])
    show(table)
    log(f"wrote {out} (report: {out / 'capture.json'}); train on it with: boostnerf pretrain --data {out}")


class Interrupted(BaseException):
    """Ctrl-C or SIGTERM. A BaseException like KeyboardInterrupt (no `except Exception` swallows it),
    but not one, because Typer turns KeyboardInterrupt into a silent exit."""

    def __init__(self, signum: int | None = None):
        super().__init__()
        self.signum = signum


INTERRUPTED = ("interrupted: finished files are kept; rerun the same command to go on (a model in training resumes "
               "from its last checkpoint, if it had written one)")


def _interrupt(signum, frame) -> None:
    raise Interrupted(signum)


def _interrupt_at_start(signum, frame) -> None:
    """An interrupt before the heavy imports are done (nothing written yet): the line, and the end at once. Raised
    inside numpy's or torch's import it would leave them half imported (an ImportError traceback), or be lost
    (exit 0)."""
    err.print(INTERRUPTED, markup=False)
    _die_by(signum)


def _die_by(signum: int) -> None:
    """End by the signal received, as the shell expects of an interrupted command (status 128 + N): a script or a
    loop running boostnerf stops at a Ctrl-C too, where a plain exit 130 lets it run the next command."""
    import os
    import signal

    sys.stdout.flush()
    sys.stderr.flush()
    signal.signal(signum, signal.SIG_DFL)
    os.kill(os.getpid(), signum)
    sys.exit(128 + signum)  # where a signal cannot end the process


def _usage_error(e) -> str:
    """A command-line mistake Click found (an unknown option, a value of the wrong type, a missing option), as the
    one line every other refusal is (Typer draws a multi-line box around it, wrapped mid-word on a narrow terminal)."""
    message = " ".join(e.format_message().split())
    ctx = getattr(e, "ctx", None)
    if ctx is not None:
        return f"{message} (see `{ctx.command_path} --help`)"
    commands = typer.main.get_command(app).list_commands(None)  # an option missing its value: Click gives no context
    command = next((a for a in sys.argv[1:] if a in commands), None)
    return f"{message} (see `boostnerf {command + ' ' if command else ''}--help`)"


def _during_interrupt(e: BaseException) -> BaseException | None:
    """The interrupt (Ctrl-C, SIGTERM) among the exceptions `e` was raised while handling, if any."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, (Interrupted, KeyboardInterrupt)):
            return e
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return None


# Click's base exception (a mistake on the command line), of whichever Click Typer runs on (0.29 vendors its own),
# reached through Typer's public BadParameter: no private import.
CLICK_ERROR = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")
PATH_OPTIONS = ("-w", "--workspace", "--data", "--recipe", "--video", "--camera")  # the options that take a path


def main() -> None:
    import signal

    CLOCK.begin()  # a stage's start-up counts from here (boostnerf_cli/startup.py)

    signal.signal(signal.SIGINT, _interrupt_at_start)
    signal.signal(signal.SIGTERM, _interrupt_at_start)
    args = sys.argv[1:]
    empty = next((i for i, a in enumerate(args) if a == "" or (a.startswith("--") and a.endswith("="))), None)
    if empty is not None:  # an unset shell variable: `-w ""` would mean the current folder
        what = (f"an empty value for {args[empty].rstrip('=')}" if args[empty] else
                f"an empty argument after {args[empty - 1]}" if empty else "an empty command")
        option = args[empty].rstrip("=") if args[empty] else args[empty - 1] if empty else ""
        folder = option in PATH_OPTIONS or (empty == 1 and option == "make-scene")  # a path: '.' may be meant
        err.print(f"error: {what} (an unset shell variable?): give it a value"
                  + (", or '.' for the current folder" if folder else ""), markup=False)
        sys.exit(2)
    glued = next((a for a in args if len(a) > 2 and a[0] == "-" and a[1] != "-" and a[2] == "="), None)
    if glued is not None:  # Click reads `-w=ws` as -w with the value "=ws": a folder named "=ws"
        err.print(f"error: {glued} names the folder {glued[2:]!r} (a short option takes no '='): write "
                  f"{glued[:2]} {glued[3:]}", markup=False)
        sys.exit(2)
    if args and not {"--help", "--version"} & set(args):
        import torch  # noqa: F401  the seconds of importing it, under the handler that ends at once
    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        try:
            faults.install()  # a test's kill point, when one is asked for; inert otherwise
            code = app(standalone_mode=False)
        except Exception as e:  # an interrupt that unwound through cleanup which failed in turn (a torch.save's writer)
            if (interrupt := _during_interrupt(e)) is not None:
                raise Interrupted(getattr(interrupt, "signum", None)) from None
            raise
    except BoostNerfError as e:
        err.print(f"error: {e}", markup=False)
        sys.exit(e.exit_code)
    except CLICK_ERROR as e:
        if type(e).__name__ == "NoArgsIsHelpError":  # `boostnerf` alone: its help
            e.show()
        else:
            err.print(f"error: {_usage_error(e)}", markup=False)
        sys.exit(e.exit_code)
    except (Interrupted, KeyboardInterrupt) as e:  # the stage's cleanup (lock, temporary files) has run
        err.print(INTERRUPTED, markup=False)
        _die_by(getattr(e, "signum", None) or signal.SIGINT)
    except (NotADirectoryError, IsADirectoryError, FileExistsError, PermissionError) as e:
        if e.filename is None:  # a path in the workspace or scene is in the way: the user's to move
            raise
        err.print(f"error: {e.filename}: {e.strerror or type(e).__name__}: a file or folder is in the way or not "
                  "writable; move it or fix its permissions and rerun", markup=False)
        sys.exit(2)
    except (MemoryError, RuntimeError) as e:  # RuntimeError: torch's allocators (OutOfMemoryError is one)
        if not out_of_memory(e):
            raise
        import textwrap

        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        err.print(f"error: out of memory ({textwrap.shorten(first, 160, placeholder=' ...')}): lower the sizes that "
                  "set it: the images' (data.image_size or --image-size, make-scene's --size, a saved view's or camera "
                  "path's height and width), the recipe's grid resolutions (pretrain.res, moe.gate_res, moe.vd_res, "
                  "moe.bake_res), network widths and ranks (hidden, app_dim, app_rank, moe.gate_channels), batch_rays "
                  "(train, geometry) or a small train.step_ratio; or use a device with more memory; finished files "
                  "are kept", markup=False)
        sys.exit(3)
    sys.exit(code if isinstance(code, int) else 0)  # --help and --version give 0, as a finished command does
