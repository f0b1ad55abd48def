"""`boostnerf chain`: every stage, in one process, from a scene folder to the reports, the pictures and a video.

    pretrain -> build-moe -> finetune (baseline, topK, ens: `--models`) -> eval --report -> count-params
    -> render --compare (the first `COMPARE_VIEWS` test views) -> render --path (the best model: an orbit, or a
    spiral for a forward-facing scene)

Each stage is the command's own stage function, run as that command runs it, under one writer lock; so a rerun skips
what every stage skips (finished experts and models; an unchanged moe/init is kept), and eval and count-params run
again, so the reports cover every model and the whole test split. The pictures and the video are kept while they are
newer than every model they show. The chain stops at the first stage that fails, naming it.

Which recipe, when none is given (`pick_recipe`): the one the workspace records (a rerun), else the CPU-sized recipe
of the scene's layout (`RECIPE_FOR`), its kind (bounded, unbounded, forward) left to `auto`. The paper-sized recipes
(`<layout>-dvgo-paper.yaml`: 800 px and more, five experts up to 384^3, 20,000 steps) are never picked, on a GPU
either: a mixture of the five needs a card over 24 GB and hours; on a GPU the line says which one to ask for.
"""

from __future__ import annotations

import copy
import logging
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from boostnerf_cli.errors import BoostNerfError, out_of_memory
from boostnerf_cli.lineage import Survey
from boostnerf_cli.recipe import Recipe
from boostnerf_cli.scenes import FORMATS, Scene, detect_format
from boostnerf_cli.workspace import Workspace

log = logging.getLogger(__name__).info  # the stage's messages, on stderr (cli.py says them)

COMPARE_VIEWS = 2  # render --compare: the first views of the test split (the quickstart's number)
VIDEO_FRAMES = 48
VIDEO_FPS = 24
PROCEDURAL = "-"  # DATA for the embedded procedural scene (pretrain without --data)

# the scene's layout (scenes.FORMATS; "-": the embedded procedural scene) -> the recipe picked for it
RECIPE_FOR = {
    "blender": "blender-dvgo-cpu",
    "nsvf": "nsvf-dvgo-cpu",
    "tanks": "tanks-dvgo-cpu",
    "llff": "llff-dvgo-cpu",
    "colmap": "capture-dvgo-cpu",
    "nerfstudio": "nerfstudio-dvgo-cpu",
    PROCEDURAL: "demo-dvgo-cpu",
}
PAPER_FOR = {"blender": "blender-dvgo-paper", "nsvf": "nsvf-dvgo-paper", "tanks": "tanks-dvgo-paper",
             "llff": "llff-dvgo-paper", "nerfstudio": "nerfstudio-dvgo-paper"}  # named on a GPU, never picked
LAYOUT_NAMES = {"blender": "a Blender scene", "nsvf": "an NSVF scene", "tanks": "a Tanks and Temples scene",
                "llff": "an LLFF forward-facing capture", "nerfstudio": "a nerfstudio capture",
                "colmap": "a COLMAP capture, the layout boostnerf capture writes"}


# --- recipes -----------------------------------------------------------------------------------------------------
def recipes_dir() -> Path | None:
    """The folder of the shipped recipes: the clone's recipes/ (beside the package), else ./recipes; None if neither."""
    for folder in (Path(__file__).resolve().parents[2] / "recipes", Path.cwd() / "recipes"):
        if folder.is_dir():
            return folder
    return None


def recipe_names() -> list[str]:
    folder = recipes_dir()
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder else []


def find_recipe(text: str) -> Path:
    """`--recipe`: a file (a path, or a name ending .yaml), or the name of one in recipes/ (`blender-dvgo-cpu`);
    one line listing the shipped recipes when it is neither."""
    path = Path(text)
    if path.is_file():
        return path
    folder = recipes_dir()
    if "/" not in text and os.sep not in text and folder is not None:
        for candidate in (folder / text, folder / f"{text}.yaml"):
            if candidate.is_file():
                return candidate
    if path.is_dir():
        raise BoostNerfError(f"--recipe {text} is a folder: give a recipe file, or the name of one of "
                             f"{', '.join(recipe_names()) or 'the recipes in recipes/'}")
    shipped = f"the recipes in {folder}: {', '.join(recipe_names())}" if folder else "no recipes/ folder found here"
    raise BoostNerfError(f"recipe {text} not found: give a recipe file or one of {shipped}")


@dataclass(frozen=True)
class Pick:
    """The recipe chosen for a scene: its name, its file, and why (one line)."""

    name: str
    path: Path
    why: str


def pick_recipe(data: Path | None, device: str = "cpu", data_format: str | None = None) -> Pick:
    """The recipe for the scene at `data` (None: the embedded procedural scene): the CPU-sized recipe of its layout,
    `data_format` when asked for (not auto), else the one `detect_format` finds (one line when it finds none). On a
    GPU the line also names the layout's paper-sized recipe; it is not picked (the module's docstring says why)."""
    if data is None:
        layout, found = PROCEDURAL, ""
        what = "the embedded procedural scene"
    elif data_format not in (None, "auto"):
        if data_format not in FORMATS:
            raise BoostNerfError(f"--format {data_format}: use auto or one of {', '.join(FORMATS)}")
        layout, found = data_format, ""
        what = f"a scene in the {data_format} layout (--format {data_format})"
    else:
        layout, found = layout_of(data)
        what = f"{LAYOUT_NAMES.get(layout, layout)} (found {found})"
    name = RECIPE_FOR[layout]
    folder = recipes_dir()
    path = folder / f"{name}.yaml" if folder else None
    if path is None or not path.is_file():
        raise BoostNerfError(f"the recipe for {what}, {name}.yaml, is not in "
                             f"{folder or 'recipes/ (no such folder here)'}: give --recipe FILE")
    sized = "its CPU-sized recipe" if layout != PROCEDURAL else "the quickstart's recipe"
    hint = ""
    if device.startswith("cuda") and layout in PAPER_FOR:
        hint = f"; the paper's settings, hours on a large GPU (docs/gpu.md): --recipe {PAPER_FOR[layout]}"
    where = "" if data is None else f"{data} is "
    return Pick(name, path, f"recipe {name}: {where}{what}, {sized} (scene kind: auto){hint}")


# --- the inputs, checked before anything is written ---------------------------------------------------------------
def check_data(data: Path) -> None:
    """Refuse, in one line and before the workspace is made, a scene folder that is missing, not a folder, unreadable
    or empty (its layout: `detect_format`, by the caller)."""
    if not data.exists():
        raise BoostNerfError(f"scene folder {data} does not exist: check the path (or give - for the embedded "
                             "procedural scene)")
    if not data.is_dir():
        raise BoostNerfError(f"{data} is a file, not a scene folder: give the folder that holds the scene")
    try:
        entries = [p for p in data.iterdir() if not p.name.startswith(".")]
        readable = os.access(data, os.R_OK | os.X_OK)
    except OSError as e:
        entries, readable = [], False
        why = e.strerror or type(e).__name__
    else:
        why = "permission denied"
    if not readable:
        raise BoostNerfError(f"cannot read scene folder {data} ({why}): fix its permissions and rerun")
    if not entries:
        raise BoostNerfError(f"scene folder {data} is empty: give the folder that holds the scene's images and "
                             f"cameras ({', '.join(FORMATS)} layouts; docs/datasets.md)")


def layout_of(data: Path) -> tuple[str, str]:
    """`detect_format`'s (layout, what it found) of `data`: one line when it finds none, and for an unreadable
    sub-folder too."""
    try:
        return detect_format(data)
    except OSError as e:
        raise BoostNerfError(f"cannot read scene folder {data} ({e.filename}: {e.strerror or type(e).__name__}): "
                             "fix its permissions and rerun") from None


_MODEL = re.compile(r"baseline|ens|top[1-9][0-9]*")


def parse_models(text: str) -> list[str]:
    """`--models baseline,top1,top2,ens` (commas or spaces) -> the names, each once, in the order given; one line for
    an unknown one."""
    names = [n for n in re.split(r"[,\s]+", text.strip()) if n]
    if not names:
        raise BoostNerfError(f"--models {text!r} names no model: give some of baseline, topK (top1, top2, ...), ens")
    for n in names:
        if not _MODEL.fullmatch(n):
            hint = " (the ensemble is ens)" if n.startswith("ensemble") else ""
            raise BoostNerfError(f"--models: unknown model {n!r}{hint}: use baseline, topK (top1, top2, ...) or ens")
    return list(dict.fromkeys(names))


def check_models(names: list[str], rec: Recipe) -> None:
    """Every topK of `names` has at most as many experts as the recipe pretrains: one line before any stage."""
    from boostnerf_cli.moe.router import check_topk
    from boostnerf_cli.stages.pretrain import expert_name

    experts = [expert_name(rec.pretrain.model, r) for r in dict.fromkeys(rec.pretrain.res)]
    for name in names:
        if (k := finetune_args(name)) is not None:
            check_topk(k, experts, f"--models {name}'s K")


def finetune_args(name: str) -> int | None:
    """The top-k of finetuned model `name` (None for baseline and ens)."""
    return int(name[3:]) if name.startswith("top") else None


def video_kind(scene: Scene) -> str:
    """The camera path for the scene's video: spiral for a forward-facing capture (rays in NDC, or training cameras
    that all look one way), else orbit; the rule `render --path`'s notes give."""
    from boostnerf_cli.stages.render import FORWARD, facing

    return "spiral" if scene.ndc is not None or facing(scene.split("train").poses) > FORWARD else "orbit"


def best_model(result: dict, made: list[str]) -> str:
    """The model of the chain (`made`, in eval's order) with the highest held-out PSNR in eval's `result`."""
    rows = {r["name"]: r for r in result["models"]}
    scored = [n for n in made if n in rows and rows[n].get("psnr") is not None]
    if not scored:
        return made[-1]
    return max(scored, key=lambda n: rows[n]["psnr"])


def newer_than(files: list[Path], models: list[Path]) -> bool:
    """Every file of `files` is there and newer than every model file of `models`."""
    if not files or not all(f.is_file() for f in files):
        return False
    newest = max((m.stat().st_mtime_ns for m in models if m.exists()), default=0)
    return min(f.stat().st_mtime_ns for f in files) > newest


# --- the run -------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Plan:
    """What the chain makes: its data (None: the embedded procedural scene), recipe (with every setting applied),
    finetuned models, Top-1's weighting, the video's model (None: the best) and frames."""

    data: Path | None
    recipe: Recipe
    models: list[str]
    top1_raw: bool = False
    video_model: str | None = None
    frames: int = VIDEO_FRAMES


@dataclass
class Outcome:
    eval: dict
    counts: dict
    pictures: list[Path]
    video: list[Path]
    seconds: float
    stages: dict[str, float]  # each stage's seconds, in order


class Stages:
    """The chain's stages, each announced `[i/n] name` before it runs; a failure is re-raised naming its stage."""

    def __init__(self, names: list[str]):
        self.names = names
        self.seconds: dict[str, float] = {}

    def run(self, name: str, work: Callable[[], object]):
        i = self.names.index(name) + 1
        label = f"stage {i}/{len(self.names)}, {name}"
        log(f"[{i}/{len(self.names)}] {name}")
        t = time.perf_counter()
        try:
            out = work()
            self.seconds[name] = time.perf_counter() - t
            return out
        except BoostNerfError as e:
            wrapped = BoostNerfError(f"chain stopped at {label}: {e}")
            wrapped.exit_code = e.exit_code
            raise wrapped from None
        except Exception as e:  # out of memory (the CLI says it in one line), or a bug (its traceback follows)
            logging.getLogger(__name__).warning(f"chain stopped at {label}"
                                                + ("" if out_of_memory(e) else ": an unexpected error"))
            raise


def run(ws: Workspace, plan: Plan, device: str) -> Outcome:
    """Run every stage of `plan` in workspace `ws` (locked by the caller) on `device`."""
    from boostnerf_cli.models import Viewing
    from boostnerf_cli.stages import build_moe, count_params, evaluate, finetune, pretrain

    t0 = time.perf_counter()
    rec = plan.recipe
    top1 = copy.deepcopy(rec).override({"moe.renormalize": False}) if plan.top1_raw else rec
    names = (["pretrain", "build-moe"] + [f"finetune {m}" for m in plan.models]
             + ["eval", "count-params", "render --compare", "render --path"])
    stages = Stages(names)
    survey = Survey(ws)  # one for the whole chain: it reads again what a stage writes, and loads the scene once
    stages.run("pretrain", lambda: pretrain.run(survey, plan.data, rec, device, False))
    stages.run("build-moe", lambda: build_moe.build(survey, None, rec.moe, device))
    for m in plan.models:
        moe = top1.moe if m == "top1" else rec.moe
        stages.run(f"finetune {m}", lambda m=m, moe=moe: finetune.run(survey, m, finetune_args(m), moe, device, False))
    result = stages.run("eval", lambda: evaluate.run(survey, None, Viewing("test"), device, True, costs=True))
    log(f"wrote {ws.reports_dir / 'eval.json'} and eval.md")
    counts = stages.run("count-params", lambda: count_params.run(survey, None, "test", device, None))
    log(f"wrote {ws.reports_dir / 'count-params.json'}")
    pictures = stages.run("render --compare", lambda: _compare(survey, device))
    video = stages.run("render --path", lambda: _video(survey, plan, result, device))
    return Outcome(result, counts, pictures, video, time.perf_counter() - t0, stages.seconds)


def _compare(survey: Survey, device: str) -> list[Path]:
    """`render --compare --views COMPARE_VIEWS`, kept while its pictures are newer than every model they show."""
    from boostnerf_cli.models import Viewing, n_views
    from boostnerf_cli.stages import render

    ws = survey.ws
    shown = render.compared_models(survey, None)
    split = survey.scene().split("test")
    folder = ws.renders_dir("compare", "test")
    files = [folder / f"{stem}.png" for stem in split.stems[:n_views(split, COMPARE_VIEWS)]]
    if newer_than(files, [ws.model_file(n) for n in shown]):
        log(f"compare: the {len(files)} pictures in {folder} are newer than the models they show "
            f"({', '.join(shown)}): kept (remove them to draw them again)")
        return files
    return render.run_compare(survey, None, Viewing("test", COMPARE_VIEWS), device)


def _video(survey: Survey, plan: Plan, result: dict, device: str) -> list[Path]:
    """`render --model BEST --path orbit|spiral`, kept while the video is newer than its model."""
    from boostnerf_cli.models import ALL_SKIPS
    from boostnerf_cli.stages import render

    ws = survey.ws
    if plan.video_model is not None:
        name, why = plan.video_model, "--video-model"
    else:
        name = best_model(result, plan.models)
        why = "the highest held-out PSNR of " + ", ".join(plan.models)
    kind = video_kind(survey.scene())
    target = ws.renders_dir(name) / f"{kind}.mp4"
    files = [target, target.with_name(f"{kind}_depth.mp4")]
    log(f"video: {name} ({why}), {kind} path")
    if newer_than(files, [ws.model_file(name)]):
        log(f"video: {target} is newer than {name}: kept (remove it to draw it again)")
        return files
    return render.run_video(survey, [name], render.VideoPath(kind, plan.frames, VIDEO_FPS), device, ALL_SKIPS)
