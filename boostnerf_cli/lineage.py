"""Lineage: what every artifact of a workspace is made from and with, and what a stage does about what it finds.

Each artifact has a frozen spec: the settings that make it what it is and the digests of its inputs.

    GeometrySpec      the shared coarse grid (pretrain's first stage): the geometry settings, seed, box, scene
    ExpertSpec        an expert: family and options, resolution, steps, seed, skipping, shaping training settings,
                      the geometry it starts from, the scene
    MixtureInitSpec   moe/init: the experts it is built from (their digests) and build-moe's settings
    FinetuneSpec      a finetuned mixture (topK, ens): moe/init's digest, steps, seed, routing, lambda, training
    BaselineSpec      the finetuned baseline: the largest expert's digest, steps, seed, training
    PrunedSpec        a pruned model: the model it is pruned from (its digest)

A spec's signature is its canonical dict (JSON types, the artifact's kind first); it is stored in the artifact's
file and in its training checkpoint. One function, `decide`, tells every stage what to do with what it finds where
it writes: make it, skip it (finished with the same signature), resume it (a checkpoint of the same signature),
remake it (made from an input that changed since: the one-line reason and the command to run), or refuse (finished,
or checkpointed, with other settings). Learning rates, `log_every` and `checkpoint_every` are in no signature: they
do not change what is trained, and a diverged run may resume from its last good checkpoint with lower rates.

The scene a workspace trains on has its spec too (`SceneSpec`, the manifest's `data`) and a digest of its images
and cameras (`scene_digest`); `moved` tells the same scene, or bench, at another path.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.registry import CONFIGS
from boostnerf_cli.recipe import DataRecipe, GeometryRecipe, MoERecipe, PretrainRecipe, TrainRecipe
from boostnerf_cli.scenes import Scene, load_scene
from boostnerf_cli.startup import timed
from boostnerf_cli.workspace import Workspace, read_meta, recorded_path, writes

_log = logging.getLogger(__name__)

UNSHAPING = ("log_every", "checkpoint_every", "compile")  # training settings that do not change what is trained
# training settings added after artifacts were made without them: in a signature only when set away from this value
# (which trains what was trained before they existed), so those artifacts stay current
LATER = {"weight_distortion": 0.0}


def shaping(tcfg: TrainRecipe) -> dict:
    """The training settings that shape what is trained: all of `tcfg` but `UNSHAPING`, the learning rates and the
    `LATER` keys at their old value."""
    return {f.name: getattr(tcfg, f.name) for f in dataclasses.fields(tcfg)
            if f.name not in UNSHAPING and not f.name.startswith("lr_")
            and not (f.name in LATER and getattr(tcfg, f.name) == LATER[f.name])}


# --- specs ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Spec:
    """A frozen description of one artifact; subclasses name their kind (`artifact`), the recipe section their
    settings are keys of (`section`), and the other names messages use for some fields (`names`)."""

    artifact: ClassVar[str] = ""
    section: ClassVar[str] = ""
    names: ClassVar[dict[str, str]] = {}

    def signature(self) -> dict:
        """The spec as a canonical dict: JSON's types (a mapping's keys as text, tuples as lists)."""
        return json.loads(json.dumps({"artifact": self.artifact, **dataclasses.asdict(self)}))


@dataclass(frozen=True)
class GeometrySpec(Spec):
    artifact: ClassVar[str] = "geometry"
    section: ClassVar[str] = "pretrain.geometry"
    names: ClassVar[dict[str, str]] = {"seed": "pretrain.seed", "settings": "pretrain.geometry",
                                       "bbox": "the box it trains in"}

    name: str  # geometry, or geometry-refine (the second round inside the box the first found)
    scene: str
    seed: int
    bbox: tuple[float, ...]
    settings: dict

    @staticmethod
    def of(name: str, scene: str, rec: GeometryRecipe, seed: int, bbox: list[float]) -> "GeometrySpec":
        return GeometrySpec(name, scene, seed, tuple(round(v, 6) for v in bbox), dataclasses.asdict(rec))


@dataclass(frozen=True)
class ExpertSpec(Spec):
    artifact: ClassVar[str] = "expert"
    section: ClassVar[str] = "pretrain"

    model: str
    res: int
    options: dict  # the family's config at this resolution, every option (`pretrain.<model>`, defaults filled in)
    iters: int
    seed: int  # pretrain.seed; the expert draws from seed + res
    skip: bool
    train: dict
    geometry: str | None  # the digest of the coarse geometry it starts from
    scene: str

    @staticmethod
    def of(rec: PretrainRecipe, res: int, options: dict, scene: str, geometry: str | None) -> "ExpertSpec":
        tcfg = rec.train if rec.skip else dataclasses.replace(rec.train, occupancy_every=0)
        options = {k: v for k, v in dataclasses.asdict(CONFIGS[rec.model](**options)).items() if k != "res"}
        return ExpertSpec(rec.model, res, options, rec.iters, rec.seed, rec.skip, shaping(tcfg), geometry, scene)

    def signature(self) -> dict:
        sig = super().signature()
        sig[self.model] = sig.pop("options")  # named as its recipe section: `pretrain.dvgo.hidden` in messages
        return sig


@dataclass(frozen=True)
class MixtureInitSpec(Spec):
    artifact: ClassVar[str] = "init"
    section: ClassVar[str] = "moe"

    inputs: dict  # {expert: digest}, the gate's source among them
    settings: dict  # the moe section build-moe read


@dataclass(frozen=True)
class BaselineSpec(Spec):
    artifact: ClassVar[str] = "baseline"
    section: ClassVar[str] = "moe"

    inputs: dict  # {the largest expert: its digest}
    iters: int
    seed: int
    train: dict

    @staticmethod
    def of(rec: MoERecipe, largest: str, digest: str | None) -> "BaselineSpec":
        return BaselineSpec({largest: digest}, rec.iters, rec.seed, shaping(rec.train))


@dataclass(frozen=True)
class FinetuneSpec(Spec):
    artifact: ClassVar[str] = "finetuned"
    section: ClassVar[str] = "moe"
    names: ClassVar[dict[str, str]] = {"routing": "moe"}  # its keys are the moe section's (`moe.penalty`)

    model: str  # top1, top2, ..., ens
    inputs: dict  # {"init": moe/init's digest}
    iters: int
    seed: int
    routing: dict  # the mixture's routing as finetuning sets it (`moe.mixture.Routing`: top-k, weights, penalty, ...)
    lam: float | None  # None: no auxiliary loss to weigh (the ensemble)
    train: dict

    @staticmethod
    def of(name: str, rec: MoERecipe, digest: str | None, routing: dict) -> "FinetuneSpec":
        return FinetuneSpec(name, {"init": digest}, rec.iters, rec.seed, routing, None if name == "ens" else rec.lam,
                            shaping(rec.train))


@dataclass(frozen=True)
class PrunedSpec(Spec):
    artifact: ClassVar[str] = "pruned"

    inputs: dict  # {the model it is pruned from: its digest}


MOE_KEYS = {f.name for f in dataclasses.fields(MoERecipe)}  # the moe section's keys, by which moe/init's are named
SPECS = {cls.artifact: cls for cls in (GeometrySpec, ExpertSpec, MixtureInitSpec, BaselineSpec, FinetuneSpec,
                                       PrunedSpec)}
DOING = {"geometry": ("trained", "retrain it"), "expert": ("trained", "retrain it"), "init": ("built", "rebuild it"),
         "finetuned": ("finetuned", "finetune it again"), "baseline": ("finetuned", "finetune it again"),
         "pruned": ("pruned", "prune it again")}


# --- what differs -----------------------------------------------------------------------------------
def first_difference(saved: dict, wanted: dict) -> str | None:
    """The first entry, in `wanted`'s order, whose value differs between two signatures, as a dotted path into
    nested mappings (`train.batch_rays`); None when they agree."""
    for key in [*wanted, *(k for k in saved if k not in wanted)]:
        was, now = saved.get(key), wanted.get(key)
        if isinstance(was, dict) and isinstance(now, dict) and key != "inputs":
            inner = first_difference(was, now)
            if inner is not None:
                return f"{key}.{inner}"
        elif was != now:
            return key
    return None


def _at(signature: dict, path: str) -> Any:
    for key in path.split("."):
        signature = signature.get(key) if isinstance(signature, dict) else None
    return signature


def describe_change(saved: dict, wanted: dict) -> str | None:
    """The first setting in which signature `saved` differs from `wanted`, for a message: named by its recipe key
    (`moe.lam: 0.001, now 0.5`), or an input made again since, its digests shortened; None when they agree."""
    if not isinstance(saved, dict):
        raise TypeError(f"a signature is a mapping, not {type(saved).__name__}")
    key = first_difference(saved, wanted)
    if key is None:
        return None
    was, now = _at(saved, key), _at(wanted, key)
    spec = SPECS.get(wanted.get("artifact"), Spec)
    if key in ("inputs", "geometry", "scene"):
        what = {"inputs": "the model it is made from", "geometry": "the geometry it starts from",
                "scene": "the scene it is trained on"}[key]
        return f"{what} was made again since{_digests(was, now)}"
    head, _, rest = key.partition(".")
    name = spec.names.get(head) or (f"{spec.section}.{head}" if spec.section else head)
    leaf = key.rpartition(".")[2]
    if spec is MixtureInitSpec:  # its settings nest the mixture's and the gate's configs: named by the recipe key
        name, rest = (f"moe.{leaf}", "") if leaf in MOE_KEYS else (f"moe/init's {key.partition('.')[2]}", "")
    return f"{name}{'.' + rest if rest else ''}: {'the default' if was is None else repr(was)}, now {now!r}"


def _digests(was: Any, now: Any) -> str:
    """` (digest abcd1234..., now ef567890...)` for two digests, or two mappings of one input each; else ""."""
    if isinstance(was, dict) and isinstance(now, dict) and len(was) == len(now) == 1:
        was, now = next(iter(was.values())), next(iter(now.values()))
    if isinstance(was, str) and isinstance(now, str):
        return f" (digest {was[:8]}..., now {now[:8]}...)"
    return ""


# --- staleness ----------------------------------------------------------------------------------------
def finetune_flag(name: str) -> str:
    """The finetune option that makes model `name`: --baseline, --ensemble or --topk K."""
    return {"baseline": "--baseline", "ens": "--ensemble"}.get(name, f"--topk {name[3:]}")


def _remake(artifact: str, root: Path, name: str, source: str, removed: bool) -> tuple[str, str]:
    """(what changed, the command that makes `name` again) when its input `source` was removed or remade."""
    changed = "removed" if removed else "retrained"
    if artifact == "expert":  # its one input: the geometry it starts from
        model, _, res = name.rpartition("-")
        return (f"the geometry was {changed} after {name} was trained on it",
                f"`boostnerf pretrain -w {root} --model {model} --res {res} --force`")
    if artifact == "init":
        return (f"expert {source} was {changed} after build-moe",
                f"`boostnerf build-moe -w {root}`, then finetune the mixtures again with --force")
    if artifact == "pruned":
        return (f"{source} was {'removed' if removed else 'changed'} after {name} was pruned from it",
                f"`boostnerf prune -w {root} --model {source} --force`")
    what = "moe/init was rebuilt" if source == "init" else f"expert {source} was {changed}"
    return f"{what} after {name} was finetuned from it", f"`boostnerf finetune -w {root} {finetune_flag(name)} --force`"


SCENE_KEYS = {"image_size": "image size", "holdout_every": "held-out views (holdout_every)", "format": "format",
              "bbox": "box (data.bbox)", "scene": "scene kind (data.scene)"}


class Survey:
    """What one command finds in its workspace, each thing read once: every artifact's header (signature, digest),
    its staleness, the manifest, and the scene it records (loaded and checked when first asked for). A command makes
    one survey at its start and hands it to its stage, which asks it rather than the files. Any file written or
    removed through the workspace module since (`workspace.writes`) makes it read the headers, the model list and the
    manifest again when next asked; the scene is loaded again only when the manifest records another one."""

    def __init__(self, ws: Workspace):
        self.ws = ws
        self._meta: dict[str, dict | None] = {}
        self._stale: dict[str, tuple[str, str] | None] = {}
        self._manifest: dict | None = None
        self._models: list[str] | None = None
        self._scene: Scene | None = None
        self._scene_record: tuple | None = None  # the manifest's record the scene was loaded from
        self._seen = writes()

    def _fresh(self) -> None:
        """Forget what was read before the last write through the workspace module (`workspace.writes`)."""
        if (now := writes()) != self._seen:
            self._seen = now
            self._meta.clear()
            self._stale.clear()
            self._manifest = None
            self._models = None

    # --- artifacts
    def _path(self, name: str) -> Path:
        return self.ws.geometry_path if name == "geometry" else self.ws.model_file(name)

    def meta(self, name: str) -> dict | None:
        """Model, expert or geometry `name`'s header (`read_meta`); None when its file is not there."""
        self._fresh()
        if name not in self._meta:
            path = self._path(name)
            self._meta[name] = read_meta(path) if path.exists() else None
        return self._meta[name]

    def digest(self, name: str) -> str | None:
        return (self.meta(name) or {}).get("digest")

    def signature(self, name: str) -> dict | None:
        return (self.meta(name) or {}).get("signature")

    @property
    def models(self) -> list[str]:
        """Every model's name: experts smallest first, then mixtures (`Workspace.all_model_names`)."""
        self._fresh()
        if self._models is None:
            self._models = self.ws.all_model_names()
        return self._models

    def stale(self, name: str) -> tuple[str, str] | None:
        """Why model `name` must be made again, as (what changed, the command that makes it again), or None when it
        is current: an input recorded in its signature (moe/init's experts, a finetuned model's moe/init or largest
        expert, a pruned model's source, an expert's geometry) changed or went since. The first stale link from the
        geometry up is named, since remaking it comes first. A pruned model without its report (a prune stopped
        before its check) is stale too. A model not there is never stale."""
        self._fresh()
        if name not in self._stale:
            self._stale[name] = self._why_stale(name)
        return self._stale[name]

    def _why_stale(self, name: str) -> tuple[str, str] | None:
        if name == "geometry" or self.meta(name) is None:
            return None
        signature = self.signature(name) or {}
        artifact, inputs, root = signature.get("artifact"), signature.get("inputs") or {}, self.ws.root
        scene = self.manifest(required=False).get("scene_id")
        if artifact == "expert" and signature.get("scene") and scene and signature["scene"] != scene:  # copied in
            model, _, res = name.rpartition("-")
            return ("it was trained on another scene than this workspace's",
                    f"`boostnerf pretrain -w {root} --model {model} --res {res} --force`")
        if artifact == "expert" and signature.get("geometry"):
            now = self.digest("geometry")
            return None if now == signature["geometry"] else _remake(artifact, root, name, "geometry", now is None)
        if artifact == "baseline" and self.meta("init") is not None:  # the largest expert of moe/init's mixture
            largest = ((self.meta("init").get("mixture") or {}).get("expert_names") or [None])[-1]
            if largest is not None and largest not in inputs:
                # what it was made from, remade first, is said first (the geometry up)
                earlier = next((e for e in map(self.stale, (*inputs, largest)) if e is not None), None)
                return earlier or (f"moe/init was rebuilt with {largest} as its largest expert after {name} was "
                                   f"finetuned from {', '.join(inputs)}",
                                   f"`boostnerf finetune -w {root} --baseline --force`")
        if artifact == "pruned" and not self.ws.report_path(name).exists():  # written last, after prune's check
            return (f"its prune did not finish (no moe/{name}.json, the check of its renders)",
                    f"`boostnerf prune -w {root} --model {next(iter(inputs))}`")
        for source, digest in inputs.items():
            if (earlier := self.stale(source)) is not None:  # the source's own staleness is remade first
                return earlier
            now = self.digest(source)
            if now != digest:
                return _remake(artifact, root, name, source, now is None)
        return None

    def finished(self, name: str) -> Found | None:
        """Model or expert `name` when it is finished (its file and its report), with its signature and staleness."""
        if not self.ws.report_path(name).exists() or self.meta(name) is None:  # no report: not finished, unread
            return None
        return Found(name, self.signature(name), self.stale(name))

    def usable(self) -> list[str]:
        """The models that are current (not stale), in `models`' order."""
        return [n for n in self.models if self.stale(n) is None]

    def current(self, names: list[str] | None = None) -> list[str]:
        """`names` (default: every model of the workspace), refused in one line when one is not there or is stale
        (`stale`): a table or picture of a model made from an expert since retrained would compare it with what it no
        longer is."""
        have = self.models
        names = names or have
        unknown = [n for n in names if n not in have]
        if unknown:  # before any model is loaded or rendered, as load_model says it
            raise BoostNerfError(f"no model named {unknown[0]!r} in {self.ws.root} (models: "
                                 f"{', '.join(self.ws.all_model_names()) or 'none yet'})")
        stale_ones = {n: self.stale(n) for n in names if self.stale(n) is not None}
        if not stale_ones:
            return names
        what = next(iter(stale_ones.values()))[0]
        by_remedy: dict[str, list[str]] = {}  # each way of making stale models again, and the models it makes
        for n, (_, remedy) in stale_ones.items():
            by_remedy.setdefault(remedy, []).append(n)
        others = self.usable()
        raise BoostNerfError(
            f"{', '.join(stale_ones)} {'is' if len(stale_ones) == 1 else 'are'} stale: {what}; make "
            + "; ".join(f"{', '.join(made)} again with {remedy}" if i == 0 else f"{', '.join(made)} with {remedy}"
                        for i, (remedy, made) in enumerate(by_remedy.items()))
            + (f" (or name current models: {' '.join('--model ' + n for n in others)})" if others else ""))

    # --- the manifest and the scene
    def manifest(self, required: bool = True) -> dict:
        """The workspace's manifest, refused in one line when there is none (`required`; else {}: a new workspace)."""
        self._fresh()
        if self._manifest is None:
            found = self.ws.require_manifest() if required else self.ws.manifest()
            if not found:
                return {}
            self._manifest = found
        return self._manifest

    def scene_moved(self, data: Path, spec: SceneSpec) -> tuple[bool, str | None]:
        """Whether `spec` (a scene pretrain is given, at `data`) is the workspace's scene at another path, and the one
        line that refuses another scene, image size or box than the one it records (None when it is not another)."""
        previous, now = self.manifest(required=False).get("data"), spec.record()
        is_moved = moved(previous, now) and data.exists()  # not a default scene to generate: another scene
        if not previous or previous == now or is_moved:
            return is_moved, None
        changed = [k for k in now if k != "path" and previous.get(k) != now[k]]
        what = ", ".join(f"{SCENE_KEYS.get(k, k)} {previous.get(k)!r}, now {now[k]!r}" for k in changed)
        return False, (f"workspace {self.ws.root} was made for another scene, image size or box "
                       f"({self.ws.root / previous['path']}" + (f"; {what}" if what else "") + "): use a new "
                       "--workspace, or --force to retrain everything")

    def scene_id(self, data: Path, spec: SceneSpec, digest: str, is_moved: bool) -> tuple[str, str | None]:
        """The id the workspace's artifacts record for the scene at `data` (`SceneSpec.id`; kept when the same images
        and cameras moved), and the one line that refuses other content (`digest` against the manifest's; None
        when it is the same)."""
        m = self.manifest(required=False)
        previous, recorded = m.get("data"), m.get("scene_digest")
        if recorded and recorded != digest:
            was = self.ws.root / previous["path"]
            return spec.id(), ((f"the scene at {data} is not the one this workspace was trained on, at {was} (its "
                                "images or cameras differ)" if is_moved else f"the scene at {data} changed since this "
                                "workspace was trained on it (its images or cameras differ)")
                               + ": restore it, use a new --workspace, or --force to retrain everything")
        same = previous and m.get("scene_id") and (previous == spec.record() or is_moved)
        return (m["scene_id"] if same else spec.id()), None

    def scene_path(self) -> Path:
        """The path of the scene the manifest records, its content unchecked; one line saying how to point to where
        it went when it is gone."""
        ws, data = self.ws, self.manifest().get("data")
        if not data:
            raise BoostNerfError(f"{ws.manifest_path} records no scene: rerun `boostnerf pretrain --workspace "
                                 f"{ws.root}`")
        recorded = ws.root / data["path"]
        if not recorded.exists():
            raise BoostNerfError(
                f"the workspace's scene {recorded} is gone: restore it, or if it moved, say where to once with "
                f"`boostnerf pretrain --workspace {ws.root} --data NEW_PLACE` (the same images and cameras: nothing "
                "is retrained)")
        return recorded

    def scene(self) -> Scene:
        """The scene the workspace was trained on, loaded exactly as `pretrain` loaded it, once; refused when its
        images or cameras changed since (`scene_digest` against the manifest's)."""
        m = self.manifest()
        record = (m.get("data"), m.get("scene_digest"))
        if self._scene is None or record != self._scene_record:
            path = self.scene_path()
            spec = SceneSpec.recorded(m["data"])
            scene = load_scene(path, image_size=spec.image_size, holdout_every=spec.holdout_every, format=spec.format,
                               bbox=spec.bbox, cache=self.ws.scene_cache, kind=spec.scene)
            if m.get("scene_digest") and scene_digest(scene) != m["scene_digest"]:
                raise BoostNerfError(
                    f"the workspace's scene {path} changed since pretrain (its images or cameras differ): restore it, "
                    f"or retrain with `boostnerf pretrain --workspace {self.ws.root} --data {path} --force`")
            self._scene, self._scene_record = scene, record
        return self._scene


# --- the one decision -----------------------------------------------------------------------------------
MAKE, SKIP, RESUME, REMAKE, REFUSE = "make", "skip", "resume", "remake", "refuse"


@dataclass(frozen=True)
class Found:
    """What a stage finds where it writes: a finished artifact `name` (its stored signature; `stale`: why it must be
    made again, from `stale`) or a training checkpoint (`checkpoint`: its path, named in messages)."""

    name: str
    signature: dict | None
    stale: tuple[str, str] | None = None
    checkpoint: bool = False


@dataclass(frozen=True)
class Decision:
    """What to do: `action` (MAKE, SKIP, RESUME, REMAKE or REFUSE); for REMAKE and REFUSE the one line that says
    why and what to run (`reason`), for REMAKE also the command alone (`command`)."""

    action: str
    reason: str = ""
    command: str = ""

    def check(self) -> "Decision":
        """Raise the reason of a REFUSE or REMAKE (a stage that makes an artifact again only with --force)."""
        if self.action in (REFUSE, REMAKE):
            raise BoostNerfError(self.reason)
        return self


def decide(found: Found | None, wanted: dict | None, force: bool = False) -> Decision:
    """The one rule of every stage for what it `found` where it writes (`rule`), said at -v."""
    decision = rule(found, wanted, force)
    if found is not None:
        _log.debug(f"{found.name}{' (its checkpoint)' if found.checkpoint else ''}: {decision.action}"
                   + (f": {decision.reason}" if decision.reason else ""))
    return decision


def rule(found: Found | None, wanted: dict | None, force: bool = False) -> Decision:
    """The one rule of every stage for what it `found` where it writes, given the signature it would write
    (`wanted`; None: any, as a reader asks) and --force:

    nothing there                                   MAKE
    a checkpoint of the same signature              RESUME (also with --force: an interrupted --force run goes on)
    a checkpoint of another signature               MAKE with --force (it is dropped), else REFUSE
    a finished artifact, --force                    MAKE
    a finished artifact made from a changed input   REMAKE: what changed, and the command that makes it again
    a finished artifact of another signature        REFUSE: which setting differs
    a finished artifact of the same signature       SKIP
    """
    if found is None:
        return Decision(MAKE)
    change = describe_change(found.signature, wanted) if found.signature is not None and wanted is not None else None
    if found.checkpoint:
        if change is None:
            return Decision(RESUME)
        if force:
            return Decision(MAKE)
        return Decision(REFUSE, f"training checkpoint {found.name} was written with other settings ({change}): rerun "
                                "with the settings it was made with to resume, add --force to restart this model "
                                "with these, or delete it")
    if force:
        return Decision(MAKE)
    if found.stale is not None:
        what, command = found.stale
        return Decision(REMAKE, f"{found.name} is stale: {what}; make it again with {command}", command)
    if change is not None:
        done, redo = DOING.get((found.signature or {}).get("artifact"), ("made", "make it again"))
        return Decision(REFUSE, f"{found.name} was {done} with other settings ({change}): add --force to {redo}, or "
                                f"rerun with the settings it was {done} with")
    return Decision(SKIP)


# --- the scene --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SceneSpec:
    """What identifies the scene a workspace is trained on (the manifest's `data`): its path, as a workspace records
    it (`recorded_path`), and how it is loaded."""

    path: str
    image_size: int | None
    holdout_every: int
    format: str
    bbox: list[float] | None = field(default=None)
    scene: str = "auto"  # data.scene; recorded only when not auto (a workspace made before it records none)

    @staticmethod
    def of(data: Path, rec: DataRecipe, root: Path) -> "SceneSpec":
        return SceneSpec(recorded_path(data, root), rec.image_size, rec.holdout_every, rec.format,
                         None if rec.bbox is None else list(rec.bbox), rec.scene)

    @staticmethod
    def recorded(record: dict) -> "SceneSpec":
        """The spec a manifest's `data` records; a key it lacks (a manifest written before the key was) takes its
        recipe default (`DataRecipe`)."""
        names = {f.name for f in dataclasses.fields(SceneSpec)}
        defaults = {k: v for k, v in dataclasses.asdict(DataRecipe()).items() if k in names}
        return SceneSpec(**{**defaults, **{k: v for k, v in record.items() if k in names}})

    def record(self) -> dict:
        d = dataclasses.asdict(self)
        if d["scene"] == "auto":
            del d["scene"]
        return d

    def id(self) -> str:
        """A short fingerprint of the scene's inputs, stored in every expert so that mixtures can check them."""
        return hashlib.sha256(json.dumps(self.record(), sort_keys=True).encode()).hexdigest()[:16]


def moved(previous: dict | None, now: dict, path_key: str = "path") -> bool:
    """`now` records what `previous` does at another path (a moved workspace, bench folder or scene): every entry
    but `path_key` equal. Whether the content there is the same is the scene digest's to tell (`scene_digest`)."""
    return bool(previous) and previous != now and {**previous, path_key: ""} == {**now, path_key: ""}


@timed("digests")
def scene_digest(scene: Scene) -> str:
    """Fingerprint of what training sees: every split's images, poses and intrinsics (recorded by pretrain)."""
    h = hashlib.blake2b(digest_size=16)
    for name in sorted(scene.splits):
        s = scene.splits[name]
        h.update(name.encode())
        for t in (s.images, s.poses, s.intrinsics):
            h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()
