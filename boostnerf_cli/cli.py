"""Thin Typer commands: parse options, load the recipe, call one stage, print.

A `BoostNerfError` becomes one line on stderr and exit code 2, with no traceback.
"""

from __future__ import annotations

import functools
import inspect
import logging
import sys
from pathlib import Path
from typing import Annotated, NamedTuple, Optional

import typer
from rich.console import Console
from rich.table import Table

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
def _app(version: Annotated[bool, typer.Option("--version", is_eager=True, callback=_version,
                                               help="Print boostnerf's version and exit.")] = False) -> None:
    """Boost Your NeRF: train Fast-NeRF experts, mix them with a gate, render and measure."""
    say_messages()
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
    """The stages' messages (the `boostnerf_cli` log), one line each on stderr, as written: "[0.34, 0.66]" or a path
    "ws[2]" is no Rich markup tag."""

    def emit(self, record: logging.LogRecord) -> None:
        err.print(record.getMessage(), markup=False)


def say_messages() -> None:
    """Send the `boostnerf_cli` log, from INFO up, to stderr (once per process)."""
    logger = logging.getLogger("boostnerf_cli")
    if not any(isinstance(h, _Stderr) for h in logger.handlers):
        logger.addHandler(_Stderr())
        logger.setLevel(logging.INFO)


log = logging.getLogger(__name__).info


def _context():
    try:
        from typer._click.globals import get_current_context  # Typer vendors Click (0.29: a Click of its own)
    except ImportError:  # an older Typer: Click itself
        from click import get_current_context
    return get_current_context()


def _settings() -> dict:
    """{recipe key: value} of the running command's options that set one (`RECIPE_OPTIONS`), those given."""
    ctx = _context()
    table = RECIPE_OPTIONS[ctx.info_name]
    return {opt.key: ctx.params[name] for name, opt in table.items() if ctx.params.get(name) is not None}


def _flag(key: str) -> str:
    """The running command's option that set recipe key `key`, as given (`--no-renormalize` for False)."""
    ctx = _context()
    name = next(n for n, opt in RECIPE_OPTIONS[ctx.info_name].items() if opt.key == key)
    option = next(p for p in ctx.command.params if p.name == name)
    return option.secondary_opts[0] if option.secondary_opts and ctx.params[name] is False else option.opts[0]


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


def _reader(workspace: Path):
    """The workspace, checked to be one, with a reader's lock (`Workspace.reading`): shared with other readers."""
    from boostnerf_cli.workspace import Workspace

    _one_process()
    ws = Workspace(workspace)
    ws.require_manifest()
    return ws, ws.reading()


def _int_list(text: str, what: str) -> list[int]:
    parts = text.replace(" ", "").split(",")
    if "" in parts[:-1]:  # "8,,12" or ",8": a value lost (a trailing comma is tolerated)
        raise BoostNerfError(f"{what} has an empty entry (got {text!r}): give comma-separated whole numbers, e.g. "
                             "160,200,256")
    try:
        values = [int(v) for v in parts if v]
    except ValueError:
        raise BoostNerfError(f"{what} must be comma-separated whole numbers, e.g. 160,200,256 (got {text!r})") from None
    if not values:
        raise BoostNerfError(f"{what} needs at least one value (got {text!r})")
    return values  # each value's range: the recipe's check (pretrain.res), as for a YAML recipe


class RecipeOption(NamedTuple):
    """An option that sets a recipe key: the key, and the option's declaration (its type and `typer.Option`)."""

    key: str
    declaration: object


def _sets(key: str, kind: type, *names: str, **option) -> RecipeOption:
    """The option `names` (`typer.Option` with `option`) of type `kind` that sets recipe key `key`; not given: None."""
    return RecipeOption(key, Annotated[Optional[kind], typer.Option(*names, **option)])


# Every option that sets a recipe key, by command: {parameter: RecipeOption}. The stages read the recipe alone; the
# option's spelling is its declaration's (`_flag`). `_recipe_options` adds them to their command.
RECIPE_OPTIONS = {
    "pretrain": {
        "model": _sets("pretrain.model", str, "--model",
                       help="Expert family: dvgo (dense grid), tensorf (VM) or ngp (hash grid)."),
        "res": _sets("pretrain.res", str, "--res", callback=lambda text: _int_list(text, "--res") if text else text,
                     help="Comma-separated: one expert each, res^3 voxels (ngp: res levels)."),
        "iters": _sets("pretrain.iters", int, "--iters", min=1, help="Training steps per expert."),
        "image_size": _sets("data.image_size", int, "--image-size", min=8,
                            help="Longer image side in pixels after area downscaling."),
        "holdout_every": _sets("data.holdout_every", int, "--holdout-every",
                               help="No test split: hold out every N-th train view, N >= 2 (0: none)."),
        "data_format": _sets("data.format", str, "--format",
                             help="Dataset format: auto, blender, nsvf, tanks, llff or nerfstudio."),
        "seed": _sets("pretrain.seed", int, "--seed"),
        "skip": _sets("pretrain.skip", bool, "--skip/--no-skip", show_default=False,
                      help="--no-skip: train on the whole box, no occupancy mask (pretrain.skip)."),
    },
    "build-moe": {
        "gate_res": _sets("moe.gate_res", int, "--gate-res", min=2,
                          help="Gate grid resolution (gate_res^3 voxels; 128 in the paper)."),
        "gate_type": _sets("moe.gate_type", str, "--gate-type", help="grid (paper), linear or switch."),
        "gate_grid": _sets("moe.gate_grid", str, "--gate-grid",
                           help="Gate's feature grid: dense, tensorf, hash, or auto (the experts')."),
        "threshold": _sets("moe.density_threshold", float, "--threshold", min=0.0,
                           help="T: V_D filters samples whose opacity per step is below T."),
    },
    "finetune": {
        "iters": _sets("moe.iters", int, "--iters", min=1),
        "lam": _sets("moe.lam", float, "--lambda", min=0.0, help="Auxiliary-loss weight (1e-3 in the paper)."),
        "penalty": _sets("moe.penalty", str, "--penalty",
                         help="geometric (paper), linear, quadratic, none or '1, 1.5, 2.23'."),
        "renormalize": _sets("moe.renormalize", bool, "--renormalize/--no-renormalize",
                             help="Top-k weights sum to 1 (default); off: raw gate probabilities."),
        "seed": _sets("moe.seed", int, "--seed"),
    },
}


def _recipe_options(command: str):
    """Declare `RECIPE_OPTIONS[command]` as options of the decorated command, after its --recipe: Typer reads the
    signature made here, and the command reads their values with `_settings()`, so its own parameters are the
    options that set no recipe key."""
    table = RECIPE_OPTIONS[command]

    def decorate(fn):
        signature = inspect.signature(fn, eval_str=True)
        own = list(signature.parameters.values())
        at = [p.name for p in own].index("recipe") + 1
        added = [inspect.Parameter(name, inspect.Parameter.POSITIONAL_OR_KEYWORD, default=None,
                                   annotation=opt.declaration) for name, opt in table.items()]
        params = own[:at] + added + own[at:]

        @functools.wraps(fn)
        def command_with_recipe_options(**kwargs):
            return fn(**{name: value for name, value in kwargs.items() if name not in table})

        command_with_recipe_options.__signature__ = signature.replace(parameters=params)
        command_with_recipe_options.__annotations__ = {p.name: p.annotation for p in params}
        return command_with_recipe_options

    return decorate


@app.command("make-scene")
def make_scene_cmd(
    out_dir: Annotated[Path, typer.Argument(help="Folder to write the scene to.")],
    size: Annotated[int, typer.Option(help="Image side in pixels.", min=16)] = 64,
    n_train: Annotated[int, typer.Option("--train-views", min=1)] = 24,
    n_test: Annotated[int, typer.Option("--test-views", min=0)] = 8,
    seed: Annotated[int, typer.Option()] = 0,
    layout: Annotated[str, typer.Option(
        "--format", help="Layout: blender, nsvf, tanks, llff or nerfstudio.")] = "blender",
    rig: Annotated[str | None, typer.Option(
        "--rig", help="Cameras: sphere, forward, or unbounded (a ring inside a world of ground and sky; --format "
                      "nerfstudio) (default: forward for llff, else sphere).")] = None,
    content: Annotated[str, typer.Option("--content", help=(
        "objects, thin (rods and a cable 1-2 px wide), large (a floor past the box), empty, or detail (fine "
        "patterns on one half, smooth content on the other: the quickstart's scene); docs/datasets.md."))] = "objects",
) -> None:
    """Write a small procedural scene (exact ray casting) in any dataset layout boostnerf reads."""
    from boostnerf_cli.scenes import make_scene
    from boostnerf_cli.scenes.procedural import SEQUENCE_LAYOUTS, written_test_views

    _one_process()
    path = make_scene(out_dir, size=size, n_train=n_train, n_test=n_test, seed=seed, layout=layout, rig=rig,
                      content=content)
    written = written_test_views(layout, n_train, n_test)
    note = (f" ({layout} holds out every 8th view: with {n_train} train views that is {written} test views, not the "
            f"{n_test} asked for)") if written != n_test else ""
    if written == 0 and layout in SEQUENCE_LAYOUTS and n_train > 1:
        note = (f" ({layout} has no test split: its loader holds out every 8th of these train views unless the recipe "
                "sets data.holdout_every: 0)")
    log(f"wrote a {size}x{size} {layout} scene with {n_train} train and {written} test views to {path}{note}")


@app.command()
@_recipe_options("pretrain")
def pretrain(
    workspace: WorkspaceOpt,
    data: Annotated[Optional[Path], typer.Option(
        "--data", help="Scene folder (default: a procedural demo scene made in WS/scene).")] = None,
    recipe: RecipeOpt = None,
    device: DeviceOpt = "auto",
    force: Annotated[bool, typer.Option("--force", help="Retrain experts that are already finished.")] = False,
) -> None:
    """Train one expert per resolution, independently (stage 1 of the paper)."""
    from boostnerf_cli import distributed as dist
    from boostnerf_cli.stages import pretrain as stage
    from boostnerf_cli.stages.common import resolve_device
    from boostnerf_cli.workspace import number

    rec = _recipe(workspace, recipe).override(_settings())  # a rerun (a moved scene, one more expert) keeps the recipe
    ws, lock = _writer(workspace, must_exist=False, distributed=True)
    with dist.session(resolve_device(device)) as dev, lock:
        reports = stage.run(ws, data, rec, dev, force)
        if not dist.is_main():
            return
    table = Table("expert", "params", "steps", "seconds", "train PSNR", "held-out PSNR")
    for r in reports:
        table.add_row(r["name"], f"{r['params']:,}", str(r["iterations"]), f"{r['seconds']:.0f}",
                      number(r["train_psnr"], ".2f"), number(r.get("test_psnr"), ".2f"))
    show(table)


def _recipe(workspace: Path, recipe: Optional[Path]):
    """The recipe given, else the one recorded by pretrain in the workspace, else defaults (every stage's)."""
    from boostnerf_cli.recipe import Recipe, load_recipe, recorded_recipe
    from boostnerf_cli.workspace import Workspace

    if recipe is not None:
        return load_recipe(recipe)
    ws = Workspace(workspace)
    return recorded_recipe(ws.manifest().get("recipe"), ws.manifest_path) or Recipe()


@app.command("build-moe")
@_recipe_options("build-moe")
def build_moe(
    workspace: WorkspaceOpt,
    experts: Annotated[Optional[str], typer.Option(
        "--experts", help="Comma-separated expert names (default: all).")] = None,
    recipe: RecipeOpt = None,
    device: DeviceOpt = "auto",
) -> None:
    """Assemble the pretrained experts, the density volume V_D and an untrained gate."""
    from boostnerf_cli.stages import build_moe as stage
    from boostnerf_cli.stages.common import resolve_device

    rec = _recipe(workspace, recipe).override(_settings())
    names = [n for n in experts.split(",") if n] if experts else None
    ws, lock = _writer(workspace)
    with lock:
        stage.build(ws, names, rec.moe, resolve_device(device))


@app.command()
@_recipe_options("finetune")
def finetune(
    workspace: WorkspaceOpt,
    topk: Annotated[Optional[int], typer.Option(
        "--topk", min=1, help="Route each sample to its top-k experts (model topK).")] = None,
    ensemble: Annotated[bool, typer.Option("--ensemble", help="All experts, equal weights (model ens).")] = False,
    baseline: Annotated[bool, typer.Option(
        "--baseline", help="The largest expert alone, as many steps (model baseline).")] = False,
    recipe: RecipeOpt = None,
    device: DeviceOpt = "auto",
    force: Annotated[bool, typer.Option("--force", help="Redo a model that is already finetuned.")] = False,
) -> None:
    """Train gate and experts jointly (Algorithm 1), or the ensemble / baseline comparison models."""
    from boostnerf_cli import distributed as dist
    from boostnerf_cli.stages import finetune as stage
    from boostnerf_cli.stages.common import resolve_device

    name = stage.model_name(topk, ensemble, baseline)
    settings = _settings()
    rec = _recipe(workspace, recipe).override(settings)
    ws, lock = _writer(workspace, distributed=True)
    with dist.session(resolve_device(device)) as dev, lock, dist.others_quiet():
        unused, why = stage.unused_settings(ws, name, topk, rec.moe, set(settings))
        if unused:  # said also when the model is finished and skipped
            log(f"note: {', '.join(map(_flag, unused))} cannot change {'the baseline' if name == 'baseline' else name} "
                f"({why}): ignored")
        stage.run(ws, name, topk, rec.moe, dev, force)


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
    frames: Annotated[int, typer.Option("--frames", min=1, help="--path: number of frames.")] = 60,
    fps: Annotated[int, typer.Option("--fps", min=1, help="--path: frames per second.")] = 24,
    video: Annotated[Optional[Path], typer.Option(
        "--video", help="--path: output .mp4 or .gif (default WS/renders/MODEL/PATH.mp4).")] = None,
    exact_gate: ExactGateOpt = False,
    device: DeviceOpt = "auto",
) -> None:
    """Render a split with each model (PNG colour, 16-bit depth), a comparison or a video."""
    from boostnerf_cli.models import Skips, Viewing
    from boostnerf_cli.stages import render as stage
    from boostnerf_cli.stages.common import resolve_device

    if sum((path is not None, compare, per_expert)) > 1:
        raise BoostNerfError("--path, --compare and --per-expert are separate outputs: use one per command")
    if path is None and video is not None:
        raise BoostNerfError("--video needs --path orbit or --path spiral")
    viewing = Viewing(split, views, Skips.from_flags(no_skip, skip_off), exact_gate)
    ws, lock = _writer(workspace)
    with lock:
        if path is not None:
            video_path = stage.VideoPath(path, frames, fps, video)
            written = stage.run_video(ws, model, video_path, resolve_device(device), viewing.skips)
        elif compare:
            written = stage.run_compare(ws, model, viewing, resolve_device(device))
        else:
            written = stage.run(ws, model, viewing, resolve_device(device), per_expert=per_expert)
    for p in written:  # stdout: the files written, one per line, for a script (the prose above is on stderr)
        print(p)


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
    from boostnerf_cli.workspace import number

    viewing = Viewing(split, views, Skips.from_flags(no_skip, skip_off), exact_gate)
    ws, lock = _writer(workspace) if report else _reader(workspace)
    with lock:
        result = stage.run(ws, model, viewing, resolve_device(device), report, costs=not no_costs)
    if report:
        log(f"wrote {ws.reports_dir / 'eval.json'} and eval.md")
    table = Table("model", "PSNR", "SSIM", "LPIPS", "||w||_0", "GFLOPs/image", "s/image", "params")
    for r in result["models"]:
        table.add_row(r["name"], number(r["psnr"], ".3f"), number(r["ssim"], ".4f"), number(r["lpips"], ".4f"),
                      f"{r['w0']:,}" if "w0" in r else "-", f"{r['gflops_per_image']:.3f}" if "w0" in r else "-",
                      f"{r['seconds_per_image']:.3f}", f"{r['params']:,}")
    show(table)


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
        result = stage.run(ws, model, split, resolve_device(device), views)
    log(f"wrote {ws.reports_dir / 'count-params.json'}")
    table = Table("model", "params", "||w||_0", "GFLOPs/image")
    for r in result["models"]:
        table.add_row(r["name"], f"{r['params']:,}", f"{r['w0']:,}", f"{r['gflops_per_image']:.3f}")
    show(table)


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
        r = stage.run(ws, model, split, resolve_device(device), views, force)
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
    names = [n for n in only.replace(" ", "").split(",") if n] if only else None
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


PATH_OPTIONS = ("-w", "--workspace", "--data", "--recipe", "--video")  # the options that take a path


def main() -> None:
    import signal

    CLOCK.begin()  # a stage's start-up counts from here (boostnerf_cli/startup.py)

    try:
        from typer._click import exceptions as click  # Typer vendors Click (0.29: a Click of its own)
    except ImportError:  # an older Typer: Click itself
        from click import exceptions as click

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
            code = app(standalone_mode=False)
        except Exception as e:  # an interrupt that unwound through cleanup which failed in turn (a torch.save's writer)
            if (interrupt := _during_interrupt(e)) is not None:
                raise Interrupted(getattr(interrupt, "signum", None)) from None
            raise
    except BoostNerfError as e:
        err.print(f"error: {e}", markup=False)
        sys.exit(e.exit_code)
    except click.NoArgsIsHelpError as e:  # `boostnerf` alone: its help
        e.show()
        sys.exit(e.exit_code)
    except click.ClickException as e:
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
        err.print(f"error: out of memory ({textwrap.shorten(first, 160, placeholder=' ...')}): lower the recipe's "
                  "sizes: grid resolutions (pretrain.res, moe.gate_res, moe.vd_res, moe.bake_res), network widths "
                  "and ranks (hidden, app_dim, app_rank, moe.gate_channels), batch_rays (train, geometry) or a small "
                  "train.step_ratio, or use a device with more memory; finished files are kept", markup=False)
        sys.exit(3)
    sys.exit(code if isinstance(code, int) else 0)  # --help and --version give 0, as a finished command does
