"""The viewer's state, without a browser: which model and map it shows, which scene layers, and for each page (a
client) its camera and what it has been shown, as explicit phases. `stages/view.py` is the page that shows it (viser);
a test drives this module as a page would, with no browser.

- `Models`: the workspace's models as the viewer offers them, each read when asked for and again when its file
  changed (with `Models.follow`, the models in training too, from their checkpoints: `checkpoint_model`).
- `ClientView`: one page's camera and its `Phase`: WAITING (no camera reported yet) -> MOVED (a frame is due) ->
  PREVIEWED (its low-resolution frame is shown; the full one once the camera is `STILL`) -> SHOWN (its full frame is
  shown); any change (the camera, the model, the map) makes it MOVED again. A page snapped to a dataset view is
  `ClientView.pinned`: the camera it reports while it moves there is not a move.
- `Viewer`: the shown model and `Look`, the layers drawn (`LAYERS`), the pages; `Viewer.next_job` says which page to
  draw next (the one that has waited longest: a page whose camera keeps moving does not starve the others),
  `Viewer.draw` renders, `Viewer.drawn` records it; and the camera path the pages draw (the viewer's path, a
  `viewpoint.camera_path.CameraPath`: `Viewer.add_keyframe`, `Viewer.save_path`, `Viewer.load_path`).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np
import torch

from boostnerf_cli.cameras import DataFrame
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.registry import count_params
from boostnerf_cli.metrics.image import psnr
from boostnerf_cli.models import LoadedModel, load_mixture, load_model, new_expert
from boostnerf_cli.recipe import TrainRecipe
from boostnerf_cli.render.renderer import Camera
from boostnerf_cli.scenes import Scene
from boostnerf_cli.tasks import load_field_state
from boostnerf_cli.viewpoint.camera import dataset_camera, scaled
from boostnerf_cli.viewpoint.camera_path import (
    CameraPath,
    Keyframe,
    camera_path_file,
    read_camera_path,
    saved_paths,
    write_camera_path,
)
from boostnerf_cli.viewpoint.frame import MIXTURE_MODES, Frame, Look, frame
from boostnerf_cli.viewpoint.geometry import (
    Cells,
    Eye,
    box_edges,
    camera_positions,
    eye_at,
    first_view,
    frustum_size,
    hidden_frustums,
    routed_cells,
    subject,
    world_box,
)
from boostnerf_cli.viewpoint.saved import save_view
from boostnerf_cli.workspace import Workspace

STILL = 0.25  # seconds without a camera change after which the full-resolution frame is rendered
SNAP = 1.0  # seconds a page takes to move to a dataset view it was snapped to (what it reports meanwhile is no move)
PREVIEW = 4  # a moving camera's frame is this many times smaller a side (16 pixels high at least)
TRAINING = " (training)"  # the label of a model read from its training checkpoint
LAYERS = ("cameras", "box", "cells")  # what the scene shows besides the frame: dataset cameras, box, routed cells
HIDDEN_FIRST = ("cells",)  # layers off until ticked: a scene's kept cells fill its subject, in front of the render

log = logging.getLogger(__name__).info  # said on stderr by the command (cli.py), as a stage's messages


# --- the workspace's models -----------------------------------------------------------------------------------------
def checkpoint_model(ws: Workspace, name: str, device: str) -> LoadedModel:
    """Model `name` as its training checkpoint holds it now (an expert, the baseline or a mixture in training): an
    expert through `models.new_expert` and `tasks.load_field_state` (what `FieldTask.load_state` does on resuming),
    its render step the checkpoint's `step_ratio` (the recipe's default when it records none)."""
    state = torch.load(ws.checkpoint_path(name), map_location="cpu", weights_only=True)
    task, sig = state["task"], state.get("signature") or {}
    if "meta" in task:  # an expert's (pretrain) or the baseline's (FieldTask.state)
        model = new_expert(task["meta"], task["model"]["bbox"], str(ws.checkpoint_path(name)))
        skip = load_field_state(model, task)
        model = model.to(device).eval()
        skip = None if skip is None else skip.to(device)
        step = float(sig.get("train", {}).get("step_ratio", TrainRecipe.step_ratio)) * model.unit
        return LoadedModel(name + TRAINING, "expert", model, skip, step, model.bbox, count_params(model))
    mix, meta = load_mixture(ws.model_path("init"), device)  # a mixture's: moe/init's layout, the state trained
    if name == "ens":
        mix.make_ensemble()
    mix.configure(**sig.get("routing", {}))
    mix.load_state_dict(task["model"])
    mix.eval()
    return LoadedModel(name + TRAINING, "mixture", mix, mix.skip, meta["step"], mix.bbox,
                       count_params(mix)).for_rendering()


@dataclass
class Models:
    """The workspace's models as the page offers them: each finished model, and with `follow` each model in training
    (its checkpoint, labelled `TRAINING`). A model is loaded when asked for and again when its file changed; a file
    that cannot be read (being written by another process, damaged) is said once, and the last good model kept."""

    ws: Workspace
    device: str
    follow: bool = False
    loaded: dict[str, tuple[tuple, LoadedModel]] = field(default_factory=dict)
    failed: dict[str, tuple] = field(default_factory=dict)
    reads: int = 0  # model files read

    def path(self, label: str) -> Path:
        if label.endswith(TRAINING):
            return self.ws.checkpoint_path(label[: -len(TRAINING)])
        return self.ws.model_file(label)

    def labels(self) -> list[str]:
        """The models on offer, experts smallest first, then mixtures; then those in training (with `follow`)."""
        names = self.ws.all_model_names()
        if self.follow and self.ws.checkpoints_dir.exists():
            names += [p.stem + TRAINING for p in sorted(self.ws.checkpoints_dir.glob("*.pt"))
                      if not p.stem.startswith("geometry") and p.stem not in names]
        return names

    def newest(self) -> str | None:
        """The model whose file was written last."""
        stamps = {label: _stamp(self.path(label)) for label in self.labels()}
        stamps = {k: v for k, v in stamps.items() if v is not None}
        return max(stamps, key=lambda k: stamps[k][0]) if stamps else None

    def get(self, label: str) -> LoadedModel | None:
        """Model `label`, read again when its file changed since; None when it cannot be read (said once per
        version of the file) and none was read before."""
        stamp = _stamp(self.path(label))
        held = self.loaded.get(label)
        if held is not None and (stamp is None or held[0] == stamp or self.failed.get(label) == stamp):
            return held[1]
        if stamp is None or self.failed.get(label) == stamp:
            return held[1] if held else None
        try:
            if label.endswith(TRAINING):
                model = checkpoint_model(self.ws, label[: -len(TRAINING)], self.device)
            else:
                model = load_model(self.ws, label, self.device)
        except Exception as e:  # noqa: BLE001  a file half written by another process fails in many ways
            self.failed[label] = stamp
            what = f"{e}" if isinstance(e, BoostNerfError) else f"{type(e).__name__}: {str(e)[:120]}"
            keep = "keeping the one read before" if held else "it is shown once it reads"
            log(f"cannot read {self.path(label)} ({what}); another process may be writing it: {keep}")
            return held[1] if held else None
        self.failed.pop(label, None)
        self.loaded[label] = (stamp, model)
        self.reads += 1
        return model

    def changed(self, label: str) -> bool:
        """Whether model `label`'s file changed since it was read (or last failed to read)."""
        stamp = _stamp(self.path(label))
        held = self.loaded.get(label)
        return stamp is not None and (held is None or held[0] != stamp) and self.failed.get(label) != stamp


def _stamp(path: Path) -> tuple | None:
    """A file's (modification time, size, inode): another one when it is written again; None when it is missing."""
    try:
        st = path.stat()
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size, st.st_ino)


def preferred(labels: list[str]) -> str | None:
    """The model shown first: top2, else top1, else the last (the largest expert, or the last mixture)."""
    for name in ("top2", "top1"):
        if name in labels:
            return name
    return labels[-1] if labels else None


# --- one page -------------------------------------------------------------------------------------------------------
class Phase(Enum):
    """What a page has been shown of its current camera, model and map."""

    WAITING = "no camera yet"
    MOVED = "a frame is due"
    PREVIEWED = "its low-resolution frame is shown"
    SHOWN = "its full frame is shown"


@dataclass
class ClientView:
    """One page: its camera (`size` pixels high), when it last moved, its `Phase`, the change count (`version`: a
    frame rendered for an older one is shown but leaves the page MOVED), since when a frame has been due (`due_since`),
    the dataset view it was snapped to (`pinned`), and its last full frame with its camera (what "save" writes)."""

    camera: Camera | None = None
    changed_at: float = 0.0
    version: int = 0
    phase: Phase = Phase.WAITING
    due_since: float = 0.0
    pinned: tuple[str, int] | None = None
    last: tuple[Camera, Frame] | None = None

    def change(self, now: float) -> None:
        """Something it shows changed: a frame is due (none while it has no camera)."""
        self.version += 1
        if self.camera is None:
            return
        if self.phase is not Phase.MOVED:  # its last frame was drawn: this one waits from now
            self.due_since = now
        self.phase = Phase.MOVED

    def wants(self, now: float) -> bool | None:
        """The frame due now: None (none), False (low resolution: the camera moves), True (full size)."""
        if self.camera is None or self.phase is Phase.SHOWN:
            return None
        full = now - self.changed_at >= STILL or self.pinned is not None
        if self.phase is Phase.PREVIEWED and not full:
            return None  # its low-resolution frame is shown: wait until the camera stops
        return full

    def drawn(self, version: int, full: bool, camera: Camera, shot: Frame) -> None:
        """A frame rendered for change `version` is shown."""
        if full:
            self.last = (camera, shot)
        if version == self.version:
            self.phase = Phase.SHOWN if full else Phase.PREVIEWED


@dataclass(frozen=True)
class Job:
    """A frame to draw: for which page, from which camera (the page's, smaller while it moves), full size or not, and
    for which of its changes."""

    client: int
    camera: Camera
    full: bool
    version: int


@dataclass(frozen=True)
class Snap:
    """A dataset view shown: its camera, the frame (None without a model), its ground truth and the PSNR of a colour
    frame against it (None for another look)."""

    camera: Camera
    shot: Frame | None
    truth: np.ndarray
    psnr: float | None


def _close(a: Camera, b: Camera) -> bool:
    """Whether two cameras look from about the same place the same way (a page rounds what it reports)."""
    size = 1e-2 * max(1.0, float(a.pose[:3, 3].norm()))
    return bool((a.pose[:3, 3] - b.pose[:3, 3]).norm() < size and (a.pose[:3, :3] - b.pose[:3, :3]).abs().max() < 1e-2)


# --- the viewer -----------------------------------------------------------------------------------------------------
class Viewer:
    """What the pages show: the model and look, the scene layers drawn, each page's `ClientView`. Rendering (`draw`,
    under `lock`) and the pages' reports (`moved`, under `clients_lock`) do not wait for each other."""

    def __init__(self, ws: Workspace, scene: Scene, models: Models, size: int | None = None,
                 model: str | None = None):
        self.ws, self.scene, self.models = ws, scene, models
        train = scene.split("train")
        self.size = size or min(max(train.height, 128), 256)
        self.lock = threading.RLock()  # the model, the look and the packers: held while a frame renders
        self.clients_lock = threading.Lock()
        self.packers: dict = {}
        self.look = Look()
        self.label: str | None = None
        self.model: LoadedModel | None = None
        self.clients: dict[int, ClientView] = {}
        self.following = models.follow  # show the newest model (the page's "follow training" box)
        self.layers = {name: name not in HIDDEN_FIRST for name in LAYERS}  # the scene layers drawn
        self.subject = subject(scene)  # the point the training cameras look at
        self.cameras = camera_positions(scene)  # the frustums' apexes
        self.frustum_size = frustum_size(self.cameras, self.subject)
        self.frames = 0  # frames rendered
        self.labels = models.labels()  # the models on offer, as last looked at
        self.path = CameraPath(width=train.width, height=train.height)  # the camera path drawn (its frames' size: the
        # training views')
        if model is not None and model not in self.labels:
            raise BoostNerfError(f"no model named {model!r} in {ws.root} (models: "
                                 f"{', '.join(self.labels) or 'none yet'})")
        first = model or (models.newest() if models.follow else None) or preferred(self.labels)
        if first is None:
            log(f"{ws.root} has no models yet: the page shows the scene's cameras until one is written "
                f"(`boostnerf pretrain --workspace {ws.root}` trains them; view --follow shows them as they train)")
        else:
            self.choose(first)

    # --- the model and the look ---------------------------------------------------------------------------------
    def choose(self, label: str) -> LoadedModel | None:
        """Show model `label` (the look falls back to colour when it is a mixture's map and the model is an expert)."""
        with self.lock:
            model = self.models.get(label)
            if model is None:
                return None
            if model is not self.model:
                self.packers = {}
            self.label, self.model = label, model
            if model.kind != "mixture" and self.look.mode in MIXTURE_MODES:
                self.look = Look("colour")
            elif model.kind == "mixture" and self.look.expert >= model.field.m:
                self.look = Look(self.look.mode, 0)
        self.changed()
        return model

    def show(self, look: Look) -> bool:
        """Show `look` with the current model -> whether it is shown (one line and no change when the model has no
        such map)."""
        with self.lock:
            if self.model is not None:
                try:
                    look.check(self.model)
                except BoostNerfError as e:
                    log(str(e))
                    return False
            self.look = look
        self.changed()
        return True

    def follow(self, on: bool) -> None:
        """Show the newest model whenever one is written (on), or keep the one shown."""
        self.following = bool(on)

    def poll(self) -> bool:
        """Look at the model files: offer new ones (`labels`), follow the newest (while `following`), read the shown
        one again when its file changed. -> whether the shown model changed."""
        self.labels = self.models.labels()
        target = self.label
        if self.following:
            target = self.models.newest() or target
        elif target is None and self.labels:
            target = preferred(self.labels)
        if target is None or (target == self.label and not self.models.changed(target)):
            return False
        before = self.model
        self.choose(target)
        return self.model is not before

    # --- the pages ---------------------------------------------------------------------------------------------------
    def connect(self, client: int) -> ClientView:
        with self.clients_lock:
            return self.clients.setdefault(client, ClientView())

    def disconnect(self, client: int) -> None:
        with self.clients_lock:
            self.clients.pop(client, None)

    def moved(self, client: int, camera: Camera, now: float | None = None) -> bool:
        """Page `client` reports `camera` -> whether it is a move (a pinned page reporting the dataset view it was
        snapped to, or moving there, is not)."""
        now = time.monotonic() if now is None else now
        with self.clients_lock:
            view = self.clients.setdefault(client, ClientView())
            if view.pinned is not None and view.camera is not None and (
                    _close(camera, view.camera) or now - view.changed_at < SNAP):
                return False
            view.camera, view.changed_at, view.pinned = camera, now, None
            view.change(now)
            return True

    def changed(self) -> None:
        """Something every page shows changed (the model, the look): each is drawn again."""
        now = time.monotonic()
        with self.clients_lock:
            for view in self.clients.values():
                view.change(now)

    def settle(self) -> None:
        """Take what every page shows as drawn (after a frame that failed: not tried again until a change)."""
        with self.clients_lock:
            for view in self.clients.values():
                if view.camera is not None:
                    view.phase = Phase.SHOWN

    def next_job(self, connected=None, now: float | None = None) -> Job | None:
        """The next frame to draw: of the pages (those in `connected`, when given) with a frame due, the one whose
        frame has been due longest; low resolution while its camera moves, full size once still. None: none due."""
        now = time.monotonic() if now is None else now
        if self.model is None:
            return None
        with self.clients_lock:
            due = [(view.due_since, cid, view, full) for cid, view in self.clients.items()
                   if (connected is None or cid in connected) and (full := view.wants(now)) is not None]
            if not due:
                return None
            _, cid, view, full = min(due, key=lambda d: d[0])
            camera = view.camera if full else scaled(view.camera, max(16, view.camera.height // PREVIEW))
            return Job(cid, camera, full, view.version)

    def drawn(self, job: Job, shot: Frame) -> None:
        with self.clients_lock:
            view = self.clients.get(job.client)
            if view is not None:
                view.drawn(job.version, job.full, job.camera, shot)

    def draw(self, camera: Camera, count: bool = False) -> Frame | None:
        """`camera` rendered with the current model and look (None when no model is loaded yet)."""
        with self.lock:
            if self.model is None:
                return None
            self.frames += 1
            return frame(self.model, self.scene, camera, self.look, self.models.device, self.packers, count)

    def go_to(self, split: str, i: int, client: int | None = None) -> Snap:
        """Dataset view `i` of `split` at its own size, drawn with its GFLOPs; with `client`, that page is pinned to
        it and shown it."""
        views = self.scene.split(split)
        if not 0 <= i < len(views):
            raise BoostNerfError(f"the {split} split has views 0 to {len(views) - 1}, not {i}")
        camera = dataset_camera(views, i)
        shot = self.draw(camera, count=True)
        truth = views.images[i].numpy()
        if client is not None:
            with self.clients_lock:
                view = self.clients.setdefault(client, ClientView())
                view.camera, view.pinned, view.changed_at = camera, (split, i), time.monotonic()
                view.version += 1
                view.phase = Phase.MOVED if shot is None else Phase.SHOWN
                if shot is not None:
                    view.last = (camera, shot)
        score = psnr(shot.rgb, truth) if shot is not None and shot.rgb is not None else None
        return Snap(camera, shot, truth, score)

    def save(self, camera: Camera, shot: Frame) -> Path:
        """Write `shot` and its camera as the next WS/renders/views/view-N.png and .json -> the PNG."""
        name = (self.label or "").removesuffix(TRAINING)
        with self.lock:
            path = save_view(self.ws.root / "renders" / "views", shot.image, camera, name, self.look)
        if self.label != name:
            log(f"note: this frame shows {name} as its training checkpoint held it; `render --camera` renders "
                "the model as it is when run (the finished one once training ends)")
        log(f"saved {path} and {path.with_suffix('.json').name}: `boostnerf render --workspace {self.ws.root} "
            f"--camera {path.with_suffix('.json')}` renders it again")
        return path

    # --- the camera path ----------------------------------------------------------------------------------------------
    def add_keyframe(self, client: int, at: int | None = None) -> int:
        """Page `client`'s camera as a keyframe of the path, before keyframe `at` (default: last) -> its index."""
        with self.clients_lock:
            view = self.clients.get(client)
            camera = view.camera if view is not None else None
        if camera is None:
            raise BoostNerfError("this page has reported no camera yet: move the view a little, then add the keyframe")
        return self.path.add(Keyframe.of_camera(camera), at)

    def save_path(self, name: str) -> Path:
        """Write the camera path as WS/camera_paths/NAME.json (nerfstudio's layout, in the data's frame) -> the file."""
        file = camera_path_file(self.ws.camera_paths_dir, name)
        write_camera_path(file, self.path, DataFrame.of(self.scene.extra))
        log(f"saved {file} ({len(self.path.keyframes)} keyframes, {len(self.path.frame_times())} frames): `boostnerf "
            f"render --workspace {self.ws.root} --model {(self.label or 'NAME').removesuffix(TRAINING)} "
            f"--camera-path {file}` renders it")
        return file

    def load_path(self, name: str) -> CameraPath:
        """Make WS/camera_paths/NAME.json (any tool's, nerfstudio's layout) the camera path drawn -> it; one line for
        a file that has frames but no keyframes to edit."""
        file = camera_path_file(self.ws.camera_paths_dir, name)
        read = read_camera_path(file, DataFrame.of(self.scene.extra))
        if not read.path.keyframes:
            raise BoostNerfError(f"camera path {file} has frames but no keyframes to edit: `boostnerf render "
                                 "--camera-path` renders it as it is")
        self.path = read.path
        return read.path

    def saved_paths(self) -> list[str]:
        """The names of the camera paths in WS/camera_paths."""
        return saved_paths(self.ws.camera_paths_dir)

    # --- the scene around the frame ----------------------------------------------------------------------------------
    def first_eye(self) -> Eye:
        """Where a page's camera stands first: at the training camera `first_view` picks, with its field of view,
        looking at the subject."""
        train = self.scene.split("train")
        return eye_at(dataset_camera(train, first_view(train.poses)), self.subject)

    def eye(self, split: str, i: int) -> Eye:
        """The page's camera at dataset view `i` of `split` (go to view N)."""
        return eye_at(dataset_camera(self.scene.split(split), i), self.subject)

    def hidden_frustums(self) -> set[int]:
        """The frustums (in `geometry.frustums`' order) not drawn: those at or beside a page's camera."""
        with self.clients_lock:
            eyes = [v.camera.pose[:3, 3].double().numpy() for v in self.clients.values() if v.camera is not None]
        return hidden_frustums(self.cameras, eyes, self.frustum_size)

    def model_parts(self) -> tuple[np.ndarray, Cells | None]:
        """The box's edges (the model's, else the scene's; in the world: `geometry.world_box`), and the routed
        cells of the shown mixture, else of the workspace's top2 or top1; None without one."""
        mixture = self.model if self.model is not None and self.model.kind == "mixture" else None
        for label in ("top2", "top1"):
            if mixture is None and label in self.labels:
                mixture = self.models.get(label)
        box = self.model.bbox if self.model is not None else self.scene.bbox
        routed = mixture is not None and mixture.field.gate.cfg.gate_type != "uniform"  # the ensemble routes nowhere
        cells = routed_cells(mixture.field, self.scene.contraction) if routed else None
        return box_edges(world_box(box.cpu(), self.scene.contraction)), cells

    def set_layer(self, name: str, on: bool) -> None:
        """Draw scene layer `name` (`LAYERS`) or not."""
        if name not in self.layers:
            raise BoostNerfError(f"unknown layer {name!r}: the layers are {', '.join(LAYERS)}")
        self.layers[name] = bool(on)
