"""`boostnerf view`: a local web page (viser) that shows a workspace's scene and renders its models live.

The page shows the scene's cameras (train and held-out, as frustums with their images), the models' box, and the
density volume's kept cells coloured by the expert the gate picks there; it renders what the browser's camera sees
with the chosen model and map (`viewpoint.MODES`): a low resolution while the camera moves, the full one once it
stops. "go to view" snaps the camera to a dataset view and shows its ground truth and PSNR; "save" writes the last
full frame and its camera (WS/renders/views/view-N.png and .json), which `render --camera FILE` renders again.
`--follow` shows the newest model or training checkpoint and reloads it whenever training writes it.

What renders lives in `viewpoint` (no browser needed); this module is the page around it: `Models` (the workspace's
models, reloaded when their file changes), `Viewer` (the state, the scene and the controls) and `run`.
"""

from __future__ import annotations

import contextlib
import errno
import io
import logging
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.registry import FAMILIES, count_params
from boostnerf_cli.lineage import Survey
from boostnerf_cli.models import LoadedModel, load_mixture, load_model
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.render.paths import scene_up
from boostnerf_cli.render.renderer import Camera
from boostnerf_cli.scenes import Scene
from boostnerf_cli.viewpoint import (
    MIXTURE_MODES,
    MODES,
    Frame,
    Look,
    box_edges,
    camera_for_view,
    dataset_camera,
    fov_of,
    frame,
    frustums,
    opencv_pose,
    psnr,
    routed_cells,
    save_view,
    scaled,
)
from boostnerf_cli.workspace import Workspace

log = logging.getLogger(__name__).info  # the stage's messages, on stderr (cli.py says them)

INSTALL = "boostnerf view needs viser, an optional extra: pip install 'boostnerf[viewer]' (or: pip install viser)"
STILL = 0.25  # seconds without a camera change after which the full-resolution frame is rendered
POLL = 1.0  # seconds between looks at the workspace's model files
SNAP = 1.0  # seconds a page takes to move to a dataset view it was snapped to (what it reports meanwhile is no move)
TRAINING = " (training)"  # the label of a model read from its training checkpoint


def import_viser():
    """The viser module; one line saying how to install it when it is missing."""
    try:
        import viser
    except ImportError:
        raise BoostNerfError(INSTALL) from None
    return viser


# --- the workspace's models -----------------------------------------------------------------------------------------
def checkpoint_model(ws: Workspace, name: str, device: str) -> LoadedModel:
    """Model `name` as its training checkpoint holds it now (an expert, the baseline or a mixture in training)."""
    state = torch.load(ws.checkpoint_path(name), map_location="cpu", weights_only=True)
    task, sig = state["task"], state.get("signature") or {}
    if "meta" in task:  # an expert's (pretrain) or the baseline's (FieldTask.state)
        meta, tensors = task["meta"], task["model"]
        model = FAMILIES[meta["family"]].from_config(meta, tensors["bbox"])
        model.resize_to(tuple(meta["shape"]))
        model.load_state_dict(tensors)
        model = model.to(device).eval()
        skip = None if task["skip"] is None else OccupancyGrid(task["skip"], task["skip_bbox"]).to(device)
        step = float(sig.get("train", {}).get("step_ratio", 0.5)) * model.unit
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


# --- the page --------------------------------------------------------------------------------------------------------
@dataclass
class ClientView:
    """What one browser shows: its camera, when it last changed, what the page shows now (`shown`: the change count
    and whether the frame was full size), and the dataset view it was snapped to (`pinned`)."""

    camera: Camera | None = None
    changed_at: float = 0.0
    version: int = 0
    shown: tuple[int, bool] = (-1, False)
    pinned: tuple[str, int] | None = None
    last: tuple[Camera, Frame] | None = None  # the last full-size frame and its camera (what "save" writes)


class Viewer:
    """The page's state and its controls; `draw` renders a camera with the chosen model and look (the server's render
    loop calls it, and so can a test, without a browser)."""

    def __init__(self, ws: Workspace, scene: Scene, models: Models, size: int | None = None,
                 model: str | None = None):
        self.ws, self.scene, self.models = ws, scene, models
        train = scene.split("train")
        self.size = size or min(max(train.height, 128), 256)
        self.lock = threading.RLock()
        self.packers: dict = {}
        self.look = Look()
        self.label: str | None = None
        self.model: LoadedModel | None = None
        self.clients: dict[int, ClientView] = {}
        self.server = None
        self.gui: dict = {}
        self.following = models.follow  # show the newest model (the page's "follow training" box)
        self.frames = 0  # frames rendered
        labels = models.labels()
        if model is not None and model not in labels:
            raise BoostNerfError(f"no model named {model!r} in {ws.root} (models: {', '.join(labels) or 'none yet'})")
        first = model or (models.newest() if models.follow else None) or _preferred(labels)
        if first is None:
            log(f"{ws.root} has no models yet: the page shows the scene's cameras until one is written "
                f"(`boostnerf pretrain --workspace {ws.root}` trains them; view --follow shows them as they train)")
        else:
            self.choose(first)

    # --- state -------------------------------------------------------------------------------------------------------
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
            self.touch()
            return model

    def show(self, look: Look) -> None:
        """Show `look` with the current model (one line and no change when the model has no such map)."""
        with self.lock:
            if self.model is not None:
                try:
                    look.check(self.model)
                except BoostNerfError as e:
                    log(str(e))
                    return
            self.look = look
            self.touch()

    def touch(self) -> None:
        """Something every page shows changed: each renders again."""
        for view in self.clients.values():
            view.version += 1

    def touch_done(self) -> None:
        """Take what every page shows as rendered (after a frame that failed: not tried again until a change)."""
        for view in self.clients.values():
            view.shown = (view.version, True)

    def draw(self, camera: Camera, count: bool = False) -> Frame | None:
        """`camera` rendered with the current model and look (None when no model is loaded yet)."""
        with self.lock:
            if self.model is None:
                return None
            self.frames += 1
            return frame(self.model, self.scene, camera, self.look, self.models.device, self.packers, count)

    def go_to(self, split: str, i: int) -> tuple[Camera, Frame | None, np.ndarray, float | None]:
        """Dataset view `i` of `split` at its own size -> (its camera, the frame, its ground truth, the PSNR of the
        colour render against it, None for another look)."""
        views = self.scene.split(split)
        if not 0 <= i < len(views):
            raise BoostNerfError(f"the {split} split has views 0 to {len(views) - 1}, not {i}")
        camera = dataset_camera(views, i)
        shot = self.draw(camera, count=True)
        gt = views.images[i].numpy()
        return camera, shot, gt, (psnr(shot.rgb, gt) if shot is not None and shot.rgb is not None else None)

    def save(self, camera: Camera, shot: Frame) -> Path:
        """Write `shot` and its camera as the next WS/renders/views/view-N.png and .json -> the PNG."""
        name = (self.label or "").removesuffix(TRAINING)
        with self.lock:
            path = save_view(self.ws.root / "renders" / "views", shot.image, camera, name, self.look)
        if self.label != name:
            log(f"note: this frame shows {name} as its training checkpoint held it; `render --camera` renders the "
                "model as it is when run (the finished one once training ends)")
        log(f"saved {path} and {path.with_suffix('.json').name}: `boostnerf render --workspace {self.ws.root} "
            f"--camera {path.with_suffix('.json')}` renders it again")
        return path

    def poll(self) -> bool:
        """Look at the model files: offer new ones, follow the newest (with `follow`), read the shown one again when
        its file changed. -> whether the shown model changed."""
        labels = self.models.labels()
        if "model" in self.gui and list(self.gui["model"].options) != labels and labels:
            self.gui["model"].options = labels
        target = self.label
        if self.following:
            target = self.models.newest() or target
        elif target is None and labels:
            target = _preferred(labels)
        if target is None or (target == self.label and not self.models.changed(target)):
            return False
        before = self.model
        self.choose(target)
        if "model" in self.gui and self.label is not None and self.gui["model"].value != self.label:
            self.gui["model"].value = self.label
        return self.model is not before

    def extent(self) -> float:
        """The diagonal of the box the page draws (the model's, else the scene's)."""
        box = self.model.bbox if self.model is not None else self.scene.bbox
        return float((box[1] - box[0]).norm().cpu())

    def model_parts(self) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """The box's edges (the model's, else the scene's), and the routed cells (points, colours) of the shown
        mixture, else of the workspace's top2 or top1; None without one."""
        mixture = self.model if self.model is not None and self.model.kind == "mixture" else None
        for label in ("top2", "top1"):
            if mixture is None and label in self.models.labels():
                mixture = self.models.get(label)
        box = self.model.bbox if self.model is not None else self.scene.bbox
        routed = mixture is not None and mixture.field.gate.cfg.gate_type != "uniform"  # the ensemble routes nowhere
        cells = routed_cells(mixture.field) if routed else None
        return box_edges(box.cpu()), cells


def _preferred(labels: list[str]) -> str | None:
    """The model shown first: top2, else top1, else the last (the largest expert, or the last mixture)."""
    for name in ("top2", "top1"):
        if name in labels:
            return name
    return labels[-1] if labels else None


def free_port(host: str, port: int) -> int:
    """`port` if it can be bound on `host`, else the next one that can (one line says so); one line for a host that
    cannot be bound at all."""
    for candidate in range(port, port + 100):
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
            try:
                s.bind((host, candidate))
            except OSError as e:
                if e.errno != errno.EADDRINUSE:
                    raise BoostNerfError(f"cannot serve on {host}:{candidate} ({e.strerror}): give --host an address "
                                         "of this machine, e.g. 127.0.0.1") from None
                continue
        if candidate != port:
            log(f"port {port} is in use (another viewer?): serving on {candidate} instead; --port N chooses one")
        return candidate
    raise BoostNerfError(f"ports {port} to {port + 99} are all in use on {host}: give a free one with --port")


# --- the browser side (viser) ---------------------------------------------------------------------------------------
def start_server(viewer: Viewer, host: str, port: int):
    """Serve `viewer` on `host`:`port` (the next free port when it is taken) -> the viser server."""
    viser = import_viser()
    with contextlib.redirect_stdout(io.StringIO()):  # viser's own banner: `run` says the address in one line
        server = viser.ViserServer(host=host, port=free_port(host, port), verbose=False)
    viewer.server = server
    up = scene_up(viewer.scene.split("train").poses).numpy()
    server.scene.set_up_direction(tuple(float(v) for v in up))
    first = opencv_pose(viewer.scene.split("train").poses[0])[:3, 3]
    box = viewer.scene.bbox if viewer.model is None else viewer.model.bbox
    centre = box.mean(0).double().cpu().numpy()
    server.initial_camera.position = tuple(float(v) for v in centre + 1.2 * (first - centre))  # behind the first camera
    server.initial_camera.look_at = tuple(float(v) for v in centre)
    server.initial_camera.up = tuple(float(v) for v in up)
    add_controls(viewer, server)
    draw_cameras(viewer, server)
    draw_model_parts(viewer, server)
    server.on_client_connect(lambda client: connect(viewer, client))
    server.on_client_disconnect(lambda client: viewer.clients.pop(client.client_id, None))
    return server


def draw_cameras(viewer: Viewer, server) -> None:
    """The dataset's cameras as frustums with their images (train blue, held-out orange), under /cameras."""
    import viser.transforms as vtf

    server.scene.add_frame("/cameras", show_axes=False, visible=viewer.gui["cameras"].value)
    size = viewer.extent()
    for k, f in enumerate(frustums(viewer.scene)):
        server.scene.add_camera_frustum(
            f"/cameras/{f.split}/{k:04d}", fov=f.fov, aspect=f.aspect, scale=0.1 * size, image=f.thumbnail,
            color=(40, 90, 230) if f.split == "train" else (230, 120, 30),
            wxyz=vtf.SO3.from_matrix(f.pose[:3, :3]).wxyz, position=f.pose[:3, 3])


def draw_model_parts(viewer: Viewer, server) -> None:
    """The box, and the density volume's kept cells coloured by the gate's pick (when the workspace has a mixture)."""
    edges, cells = viewer.model_parts()
    server.scene.add_line_segments("/box", edges.astype(np.float32), (250, 160, 40), thickness=2.0,
                                   thickness_units="screen", visible=viewer.gui["box"].value)
    if cells is not None:
        points, colours = cells
        server.scene.add_point_cloud("/cells", points, colours, point_size=0.006 * viewer.extent(),
                                     visible=viewer.gui["cells"].value)


def add_controls(viewer: Viewer, server) -> None:
    """The panel: model, map, expert, go to view, save, what the scene shows, and the last frame's figures."""
    gui, g = server.gui, viewer.gui
    labels = viewer.models.labels()
    offered = labels or ["(none yet)"]
    g["model"] = gui.add_dropdown("model", offered, initial_value=viewer.label or offered[0])
    g["mode"] = gui.add_dropdown("show", MODES, initial_value=viewer.look.mode)
    g["expert"] = gui.add_number("expert (share, gate)", 0, min=0, step=1)
    g["follow"] = gui.add_checkbox("follow training", viewer.models.follow)
    g["stats"] = gui.add_markdown("no frame yet")
    with gui.add_folder("dataset view"):
        g["split"] = gui.add_dropdown("split", [s for s in ("train", "test") if s in viewer.scene.splits
                                                or (s == "test" and viewer.scene.held_out() is not None)])
        g["view"] = gui.add_number("view N", 0, min=0, step=1)
        g["go"] = gui.add_button("go to view N")
        g["truth"] = gui.add_markdown("")
        g["gt"] = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="ground truth", visible=False)
    g["save"] = gui.add_button("save (PNG + camera JSON)")
    g["cameras"] = gui.add_checkbox("cameras", True)
    g["box"] = gui.add_checkbox("box", True)
    g["cells"] = gui.add_checkbox("routed cells", True)

    @g["model"].on_update
    def _(event) -> None:
        if g["model"].value != viewer.label and g["model"].value in viewer.models.labels():
            g["follow"].value = viewer.following = False  # a model picked by hand stays
            viewer.choose(g["model"].value)

    @g["follow"].on_update
    def _(event) -> None:
        viewer.following = bool(g["follow"].value)

    @g["mode"].on_update
    def _(event) -> None:
        viewer.show(Look(g["mode"].value, int(g["expert"].value)))

    @g["expert"].on_update
    def _(event) -> None:
        viewer.show(Look(g["mode"].value, int(g["expert"].value)))

    for key, name in (("cameras", "/cameras"), ("box", "/box"), ("cells", "/cells")):
        g[key].on_update(lambda event, key=key, name=name: _visible(server, name, g[key].value))
    g["go"].on_click(lambda event: go_to(viewer, event.client))
    g["save"].on_click(lambda event: save(viewer, event.client))


def _visible(server, name: str, on: bool) -> None:
    handle = server.scene.get_handle_by_name(name)
    if handle is not None:
        handle.visible = on


def connect(viewer: Viewer, client) -> None:
    """A new page: its camera is followed (each move renders again)."""
    view = viewer.clients.setdefault(client.client_id, ClientView())

    @client.camera.on_update
    def _(camera) -> None:
        moved = camera_of(viewer, camera)
        if view.pinned is not None and view.camera is not None and (
                _close(moved, view.camera) or time.monotonic() - view.changed_at < SNAP):
            return  # the page moving to the dataset view it was snapped to, and reporting it
        with viewer.lock:
            view.camera, view.changed_at, view.pinned = moved, time.monotonic(), None
            view.version += 1
        if viewer.gui["gt"].visible:
            viewer.gui["gt"].visible = False
            viewer.gui["truth"].content = ""


def camera_of(viewer: Viewer, handle) -> Camera:
    """The camera a page shows (viser's handle), `viewer.size` pixels high."""
    import viser.transforms as vtf

    rotation = vtf.SO3(np.asarray(handle.wxyz)).as_matrix()
    return camera_for_view(rotation, np.asarray(handle.position), float(handle.fov), float(handle.aspect), viewer.size)


def _close(a: Camera, b: Camera) -> bool:
    """Whether two cameras look from about the same place the same way (the page rounds what it reports)."""
    size = 1e-2 * max(1.0, float(a.pose[:3, 3].norm()))
    return bool((a.pose[:3, 3] - b.pose[:3, 3]).norm() < size and (a.pose[:3, :3] - b.pose[:3, :3]).abs().max() < 1e-2)


def go_to(viewer: Viewer, client) -> None:
    """Snap `client`'s camera to the chosen dataset view; show its render at the view's size, its ground truth and
    the PSNR (of a colour render)."""
    g = viewer.gui
    split, i = g["split"].value, int(g["view"].value)
    try:
        camera, shot, gt, score = viewer.go_to(split, i)
    except BoostNerfError as e:
        client.add_notification("go to view", str(e), auto_close_seconds=5.0)
        return
    view = viewer.clients.setdefault(client.client_id, ClientView())
    pose = opencv_pose(camera.pose)
    with viewer.lock:
        view.camera, view.pinned, view.changed_at = camera, (split, i), time.monotonic()
        view.shown = (view.version, True)
    with client.atomic():
        client.camera.position = tuple(pose[:3, 3])
        client.camera.look_at = tuple(pose[:3, 3] + pose[:3, 2] * float(viewer.scene.near + viewer.scene.far) / 4)
        client.camera.up_direction = tuple(-pose[:3, 1])
        client.camera.fov = fov_of(camera)
    g["gt"].image = (gt * 255 + 0.5).clip(0, 255).astype(np.uint8)
    g["gt"].visible = True
    g["truth"].content = f"**{split} view {i}**: " + (f"PSNR {score:.2f} dB" if score is not None else
                                                     "PSNR: show colour to score it")
    if shot is not None:
        present(viewer, client, view, camera, shot, full=True)


def save(viewer: Viewer, client) -> None:
    """Write the page's last full-size frame and its camera."""
    view = viewer.clients.get(client.client_id)
    if view is None or view.last is None:
        client.add_notification("save", "no full-size frame yet: hold the camera still a moment",
                                auto_close_seconds=5.0)
        return
    path = viewer.save(*view.last)
    client.add_notification("saved", f"{path} and its camera {path.with_suffix('.json').name}", auto_close_seconds=8.0)


def present(viewer: Viewer, client, view: ClientView, camera: Camera, shot: Frame, full: bool) -> None:
    """Show `shot` as the page's background and its figures."""
    client.scene.set_background_image(shot.image, format="png" if full else "jpeg")
    figures = f"**{viewer.label}**, {viewer.look.mode}: {shot.seconds * 1000:.0f} ms, {camera.width}x{camera.height} px"
    viewer.gui["stats"].content = figures + (f", {shot.gflops:.3f} GFLOPs" if shot.gflops is not None else "")
    if full:
        view.last = (camera, shot)


def render_pending(viewer: Viewer) -> bool:
    """Render one frame for one page that needs one: low resolution while its camera moves, full size once still
    (then with its GFLOPs). -> whether a frame was rendered."""
    if viewer.server is None or viewer.model is None:
        return False
    clients = viewer.server.get_clients()
    now = time.monotonic()
    for cid, view in list(viewer.clients.items()):
        if view.camera is None or cid not in clients or view.shown == (view.version, True):
            continue
        full = now - view.changed_at >= STILL or view.pinned is not None
        if view.shown == (view.version, False) and not full:
            continue  # this camera's low-resolution frame is shown: wait until it stops
        version = view.version
        camera = view.camera if full else scaled(view.camera, max(16, view.camera.height // 4))
        shot = viewer.draw(camera, count=full)
        if shot is None:
            return False
        present(viewer, clients[cid], view, camera, shot, full)
        view.shown = (version, full)
        return True
    return False


def serve(viewer: Viewer, stop: threading.Event) -> None:
    """The render loop: frames as pages need them, the model files looked at every `POLL` seconds, until `stop`. A
    frame or a look that fails is said in one line, and the page stays up."""
    checked = 0.0
    while not stop.is_set():
        try:
            if time.monotonic() - checked >= POLL:
                checked = time.monotonic()
                if viewer.poll() and viewer.server is not None:
                    draw_model_parts(viewer, viewer.server)
            if not render_pending(viewer):
                stop.wait(0.02)
        except Exception as e:  # noqa: BLE001  the page stays up; the next change tries again
            why = str(e) if isinstance(e, BoostNerfError) else f"{type(e).__name__}: {e}"
            log(f"could not render {viewer.label}: {why}")
            viewer.touch_done()
            stop.wait(POLL)


def run(survey: Survey, device: str, host: str = "127.0.0.1", port: int = 8080, model: str | None = None,
        follow: bool = False, size: int | None = None) -> None:
    """Serve the page until interrupted (Ctrl-C). Following training, it renders on one thread: the training keeps
    the other cores."""
    import_viser()
    if follow:
        torch.set_num_threads(1)
    ws, scene = survey.ws, survey.scene()
    viewer = Viewer(ws, scene, Models(ws, device, follow), size, model)
    server = start_server(viewer, host, port)
    shown = "localhost" if host in ("127.0.0.1", "::1") else host
    log(f"viewer at http://{shown}:{server.get_port()}/ (Ctrl-C stops it)")
    stop = threading.Event()
    try:
        serve(viewer, stop)
    finally:
        stop.set()
        with contextlib.redirect_stdout(io.StringIO()):  # "(viser) Server stopped"
            server.stop()
        log(f"the viewer rendered {viewer.frames} frame{'s' if viewer.frames != 1 else ''} and read "
            f"{viewer.models.reads} model file{'s' if viewer.models.reads != 1 else ''}")
