"""`boostnerf view`: a local web page (viser) that shows a workspace's scene and renders its models live.

The page shows the scene's cameras (train and held-out, as frustums with their images, sized to their spacing), the
models' box, and the density volume's kept cells coloured by the expert the gate picks there (off until ticked); its
first view is a training camera's (`Viewer.first_eye`); it renders what the browser's camera sees
with the chosen model and map (`viewpoint.frame.MODES`): a low resolution while the camera moves, the full one once it
stops. "go to view" snaps the camera to a dataset view and shows its ground truth and PSNR; "save" writes the last
full frame and its camera (WS/renders/views/view-N.png and .json), which `render --camera FILE` renders again.
`--follow` shows the newest model or training checkpoint and reloads it whenever training writes it. The "camera
path" panel (`PathPanel`) draws a path through keyframes taken from the view, plays it, and saves it as
WS/camera_paths/NAME.json (nerfstudio's layout), which `render --camera-path` renders.

What the pages are shown, and when, is `viewpoint.viewer.Viewer` (no browser needed); this module is the page that
shows it: `Controls` (the panel's widgets, by name), `Nodes` (the scene nodes it draws, each held once), `Page`
(a viser server around a `Viewer`), the render loop `serve` and `run`.
"""

from __future__ import annotations

import contextlib
import errno
import io
import logging
import math
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.lineage import Survey
from boostnerf_cli.render.paths import scene_up
from boostnerf_cli.render.renderer import Camera
from boostnerf_cli.viewpoint.camera import camera_for_view, opencv_pose
from boostnerf_cli.viewpoint.frame import MODES, Frame, Look
from boostnerf_cli.viewpoint.geometry import frustums
from boostnerf_cli.viewpoint.viewer import LAYERS, Job, Models, Viewer

log = logging.getLogger(__name__).info  # the stage's messages, on stderr (cli.py says them)

INSTALL = ("boostnerf view needs viser, an optional extra: pip install -e \".[viewer]\" in the clone "
           "(or: pip install viser)")
POLL = 1.0  # seconds between looks at the workspace's model files


def import_viser():
    """The viser module; one line saying how to install it when it is missing."""
    try:
        import viser
    except ImportError:
        raise BoostNerfError(INSTALL) from None
    return viser


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
@dataclass
class Controls:
    """The panel's widgets (viser handles), one field each; every page shares them."""

    model: Any  # dropdown: the models on offer
    mode: Any  # dropdown: `MODES`
    expert: Any  # number: the expert of share and gate
    follow: Any  # checkbox: follow training
    stats: Any  # markdown: the last frame's figures
    split: Any  # dropdown: the dataset view's split
    view: Any  # number: its index
    go: Any  # button: go to view N
    truth: Any  # markdown: the dataset view's PSNR
    truth_image: Any  # image: its ground truth
    save: Any  # button: save the last full frame and its camera
    cameras: Any  # checkboxes: the scene layers (`LAYERS`)
    box: Any
    cells: Any

    def look(self) -> Look:
        return Look(self.mode.value, int(self.expert.value))


@dataclass
class Nodes:
    """The scene nodes the page draws, each held once: the dataset cameras (one frame with every frustum under it),
    the box, the routed cells; a node drawn again replaces the one held (viser replaces a node of the same name), and
    is drawn shown or hidden as the viewer's `layers` say."""

    cameras: Any = None
    box: Any = None
    cells: Any = None
    frustums: list = field(default_factory=list)  # the frustums under `cameras`, in `frustums`' order
    hidden: set = field(default_factory=set)  # those not drawn (`Viewer.hidden_frustums`)

    def replace(self, name: str, handle) -> None:
        old = getattr(self, name)
        if handle is None and old is not None:
            old.remove()
        setattr(self, name, handle)


class Page:
    """A viser server showing `viewer`: the panel, the scene, one background frame per browser page."""

    def __init__(self, viewer: Viewer, server) -> None:
        self.viewer, self.server = viewer, server
        self.nodes = Nodes()
        self.hiding = threading.Lock()  # the pages' camera reports come on several threads
        self.controls = self.add_controls()
        self.path_panel = PathPanel(self)
        self.draw_cameras()
        self.draw_model_parts()
        server.on_client_connect(self.connect)
        server.on_client_disconnect(self.disconnect)

    # --- the panel ---------------------------------------------------------------------------------------------------
    def add_controls(self) -> Controls:
        """The panel: model, map, expert, go to view, save, the scene layers, and the last frame's figures."""
        gui, viewer = self.server.gui, self.viewer
        offered = viewer.labels or ["(none yet)"]
        model = gui.add_dropdown("model", offered, initial_value=viewer.label or offered[0])
        mode = gui.add_dropdown("show", MODES, initial_value=viewer.look.mode)
        expert = gui.add_number("expert (share, gate)", 0, min=0, step=1)
        follow = gui.add_checkbox("follow training", viewer.following)
        stats = gui.add_markdown("no frame yet")
        with gui.add_folder("dataset view"):
            split = gui.add_dropdown("split", [s for s in ("train", "test") if s in viewer.scene.splits
                                               or (s == "test" and viewer.scene.held_out() is not None)])
            view = gui.add_number("view N", 0, min=0, step=1)
            go = gui.add_button("go to view N")
            truth = gui.add_markdown("")
            truth_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="ground truth", visible=False)
        save = gui.add_button("save (PNG + camera JSON)")
        layers = {name: gui.add_checkbox({"cells": "routed cells"}.get(name, name), viewer.layers[name])
                  for name in LAYERS}
        c = Controls(model, mode, expert, follow, stats, split, view, go, truth, truth_image, save, **layers)

        @c.model.on_update
        def _(event) -> None:
            if c.model.value != viewer.label and c.model.value in viewer.labels:
                c.follow.value = False  # a model picked by hand stays
                viewer.follow(False)
                viewer.choose(c.model.value)

        c.follow.on_update(lambda event: viewer.follow(c.follow.value))
        c.mode.on_update(lambda event: viewer.show(c.look()))
        c.expert.on_update(lambda event: viewer.show(c.look()))
        for name in LAYERS:
            getattr(c, name).on_update(lambda event, name=name: self.set_layer(name, getattr(c, name).value))
        c.go.on_click(lambda event: self.go_to(event.client))
        c.save.on_click(lambda event: self.save(event.client))
        return c

    def sync(self, model_changed: bool) -> None:
        """After `Viewer.poll`: offer the models found, show the one shown, and draw its box and cells anew when it
        changed."""
        viewer, c = self.viewer, self.controls
        if viewer.labels and list(c.model.options) != viewer.labels:
            c.model.options = viewer.labels
        if viewer.label is not None and c.model.value != viewer.label:
            c.model.value = viewer.label
        if model_changed:
            self.draw_model_parts()

    # --- the scene ---------------------------------------------------------------------------------------------------
    def draw_cameras(self) -> None:
        """The dataset's cameras as frustums with their images (train blue, held-out orange), under /cameras, as
        deep as `Viewer.frustum_size` says (a fraction of the cameras' spacing)."""
        import viser.transforms as vtf

        scene, viewer = self.server.scene, self.viewer
        self.nodes.replace("cameras", scene.add_frame("/cameras", show_axes=False, visible=viewer.layers["cameras"]))
        self.nodes.frustums = [scene.add_camera_frustum(
            f"/cameras/{f.split}/{k:04d}", fov=f.fov, aspect=f.aspect, scale=viser_frustum_scale(
                viewer.frustum_size, f.fov, f.aspect), image=f.thumbnail,
            color=(40, 90, 230) if f.split == "train" else (230, 120, 30),
            wxyz=vtf.SO3.from_matrix(f.pose[:3, :3]).wxyz, position=f.pose[:3, 3])
            for k, f in enumerate(frustums(viewer.scene))]
        self.nodes.hidden = set()

    def hide_frustums(self) -> None:
        """Draw every frustum but those at or beside a page's camera (`Viewer.hidden_frustums`: the camera a page
        stands at would fill its view with its own image)."""
        with self.hiding:
            hidden = self.viewer.hidden_frustums()
            for k in hidden ^ self.nodes.hidden:
                self.nodes.frustums[k].visible = k not in hidden
            self.nodes.hidden = hidden

    def draw_model_parts(self) -> None:
        """The box, and the density volume's kept cells coloured by the gate's pick (when the workspace has a
        mixture), shown or hidden as the viewer's layers say."""
        scene, viewer = self.server.scene, self.viewer
        edges, cells = viewer.model_parts()
        self.nodes.replace("box", scene.add_line_segments(
            "/box", edges.astype(np.float32), (250, 160, 40), thickness=2.0, thickness_units="screen",
            visible=viewer.layers["box"]))
        if cells is None:
            self.nodes.replace("cells", None)
            return
        # viser draws a point 2 * point_size wide (its shader: point_size / tan(fov / 2) * height / depth pixels)
        self.nodes.replace("cells", scene.add_point_cloud(
            "/cells", cells.points, cells.colours, point_size=cells.width / 2, precision="float32",
            visible=viewer.layers["cells"]))

    def set_layer(self, name: str, on: bool) -> None:
        """Show or hide scene layer `name` on every page."""
        self.viewer.set_layer(name, on)
        node = getattr(self.nodes, name)
        if node is not None:
            node.visible = self.viewer.layers[name]

    # --- the pages ---------------------------------------------------------------------------------------------------
    def connect(self, client) -> None:
        """A new page: its camera is followed (each move renders again)."""
        viewer, c = self.viewer, self.controls
        viewer.connect(client.client_id)

        @client.camera.on_update
        def _(handle) -> None:
            if viewer.moved(client.client_id, camera_of(handle, viewer.size)) and c.truth_image.visible:
                c.truth_image.visible = False
                c.truth.content = ""
            self.hide_frustums()

    def disconnect(self, client) -> None:
        self.viewer.disconnect(client.client_id)
        self.hide_frustums()

    def go_to(self, client) -> None:
        """Snap `client`'s camera to the chosen dataset view; show its render at the view's size, its ground truth
        and the PSNR (of a colour render)."""
        c = self.controls
        split, i = c.split.value, int(c.view.value)
        try:
            snap = self.viewer.go_to(split, i, client.client_id)
        except BoostNerfError as e:
            client.add_notification("go to view", str(e), auto_close_seconds=5.0)
            return
        eye = self.viewer.eye(split, i)
        with client.atomic():
            client.camera.position, client.camera.look_at = _vector(eye.position), _vector(eye.look_at)
            client.camera.up_direction, client.camera.fov = _vector(eye.up), eye.fov
        self.hide_frustums()
        c.truth_image.image = (snap.truth * 255 + 0.5).clip(0, 255).astype(np.uint8)
        c.truth_image.visible = True
        c.truth.content = f"**{split} view {i}**: " + (f"PSNR {snap.psnr:.2f} dB" if snap.psnr is not None else
                                                       "PSNR: show colour to score it")
        if snap.shot is not None:
            self.present(client, snap.camera, snap.shot, full=True)

    def save(self, client) -> None:
        """Write the page's last full-size frame and its camera."""
        view = self.viewer.clients.get(client.client_id)
        if view is None or view.last is None:
            client.add_notification("save", "no full-size frame yet: hold the camera still a moment",
                                    auto_close_seconds=5.0)
            return
        path = self.viewer.save(*view.last)
        client.add_notification("saved", f"{path} and its camera {path.with_suffix('.json').name}",
                                auto_close_seconds=8.0)

    def present(self, client, camera: Camera, shot: Frame, full: bool) -> None:
        """Show `shot` as the page's background, and its figures."""
        client.scene.set_background_image(shot.image, format="png" if full else "jpeg")
        viewer = self.viewer
        figures = (f"**{viewer.label}**, {viewer.look.mode}: {shot.seconds * 1000:.0f} ms, "
                   f"{camera.width}x{camera.height} px")
        self.controls.stats.content = figures + (f", {shot.gflops:.3f} GFLOPs" if shot.gflops is not None else "")

    def render_next(self) -> bool:
        """Render one frame, for the page that has waited longest for one (`Viewer.next_job`). -> whether one was
        rendered."""
        clients = self.server.get_clients()
        job: Job | None = self.viewer.next_job(clients)
        if job is None:
            return False
        shot = self.viewer.draw(job.camera, count=job.full)
        if shot is None:
            return False
        client = clients.get(job.client)
        if client is not None:
            self.present(client, job.camera, shot, job.full)
        self.viewer.drawn(job, shot)
        return True


class PathPanel:
    """The camera path panel: keyframes from the page's view, reordered, deleted, each with its field of view; the
    path's duration, frames per second, smoothness, loop and frame size; a preview that plays it on the page; save to
    and load from WS/camera_paths (`Viewer.save_path`, `Viewer.load_path`). The path and its logic are the viewer's
    `path` (`viewpoint.camera_path.CameraPath`); the scene shows its keyframes (red frustums) and the path (a red
    line)."""

    def __init__(self, page: Page) -> None:
        self.page, self.viewer = page, page.viewer
        self.lock = threading.RLock()  # the path, between callbacks (a value set here calls its callback at once)
        self.playing: threading.Event | None = None
        self.nodes: list = []
        gui, path = page.server.gui, page.viewer.path
        with gui.add_folder("camera path", expand_by_default=False):
            self.listing = gui.add_markdown(path.summary())
            self.add = gui.add_button("add keyframe (this view)")
            self.index = gui.add_number("keyframe N", 0, min=0, step=1)
            self.up, self.down = gui.add_button("move N earlier"), gui.add_button("move N later")
            self.delete = gui.add_button("delete N")
            self.fov = gui.add_number("N's field of view (deg)", 50.0, min=1.0, max=179.0, step=0.5)
            self.seconds = gui.add_number("duration (s)", path.seconds, min=0.1, step=0.1)
            self.fps = gui.add_number("frames per second", path.fps, min=1.0, max=120.0, step=1.0)
            self.smoothness = gui.add_slider("smoothness", 0.0, 1.0, 0.05, path.smoothness)
            self.cycle = gui.add_checkbox("loop", path.cycle)
            self.size = gui.add_vector2("frame size (w, h)", (path.width, path.height), min=(16, 16), step=1)
            self.preview = gui.add_button("preview (play on this page)")
            self.name = gui.add_text("name", "path")
            self.save = gui.add_button("save to WS/camera_paths")
            self.saved = gui.add_dropdown("saved paths", self.viewer.saved_paths() or [NONE])
            self.load = gui.add_button("load the saved path")
        self.connect()

    def connect(self) -> None:
        """Each widget's callback: an edit of the path (`edit`), after which the panel and the scene show it anew."""
        viewer = self.viewer
        self.add.on_click(lambda e: self.edit(e, lambda: self.select(viewer.add_keyframe(e.client_id))))
        self.up.on_click(lambda e: self.edit(e, lambda: self.select(viewer.path.move(self.selected(), -1))))
        self.down.on_click(lambda e: self.edit(e, lambda: self.select(viewer.path.move(self.selected(), 1))))
        self.delete.on_click(lambda e: self.edit(e, lambda: viewer.path.delete(self.selected())))
        self.fov.on_update(lambda e: self.edit(e, self.set_fov))
        self.index.on_update(lambda e: self.edit(e, lambda: None))
        for widget in (self.seconds, self.fps, self.smoothness, self.cycle, self.size):
            widget.on_update(lambda e: self.edit(e, self.configure))
        self.preview.on_click(lambda e: self.play(e.client))
        self.save.on_click(lambda e: self.edit(e, lambda: self.say(e.client, "saved", viewer.save_path(
            self.name.value))))
        self.load.on_click(lambda e: self.edit(e, self.load_chosen))

    def selected(self) -> int:
        return self.viewer.path.check(int(self.index.value))

    def select(self, i: int) -> None:
        self.index.value = i

    def set_fov(self) -> None:
        if self.viewer.path.keyframes:
            self.viewer.path.set_fov(self.selected(), float(self.fov.value))

    def configure(self) -> None:
        width, height = self.size.value
        self.viewer.path.configure(self.seconds.value, self.fps.value, self.smoothness.value, self.cycle.value, width,
                                   height)

    def load_chosen(self) -> None:
        """Load the path chosen in the dropdown; its settings fill the panel (each widget set writes them back)."""
        if self.saved.value == NONE:
            raise BoostNerfError("WS/camera_paths holds no camera path yet: save one first")
        path = self.viewer.load_path(self.saved.value)
        self.name.value = self.saved.value
        self.seconds.value, self.fps.value, self.smoothness.value = path.seconds, path.fps, path.smoothness
        self.cycle.value, self.size.value = path.cycle, (path.width, path.height)
        self.select(0)

    def say(self, client, title: str, what) -> None:
        if client is not None:
            client.add_notification(title, str(what), auto_close_seconds=6.0)

    def edit(self, event, change) -> None:
        """Apply `change` to the path (a refusal is one line on the page), then show the path anew."""
        with self.lock:
            try:
                change()
            except BoostNerfError as e:
                self.say(getattr(event, "client", None), "camera path", e)
            self.show()

    def show(self) -> None:
        """The panel's listing, N's field of view, the saved paths offered, and the keyframes and line drawn."""
        path = self.viewer.path
        self.listing.content = path.summary()
        i = int(self.index.value)
        if 0 <= i < len(path.keyframes):
            self.fov.value = round(path.keyframes[i].fov, 2)
        names = self.viewer.saved_paths() or [NONE]
        if list(self.saved.options) != names:
            self.saved.options = names
        self.draw()

    def draw(self) -> None:
        import viser.transforms as vtf

        scene, path = self.page.server.scene, self.viewer.path
        for node in self.nodes:
            node.remove()
        self.nodes = []
        for i, k in enumerate(path.keyframes):
            pose = opencv_pose(torch.from_numpy(k.pose))
            self.nodes.append(scene.add_camera_frustum(
                f"/camera_path/keyframe{i}", fov=float(np.radians(k.fov)), aspect=path.width / path.height,
                scale=viser_frustum_scale(self.viewer.frustum_size, float(np.radians(k.fov)), path.width / path.height),
                color=(220, 30, 40), wxyz=vtf.SO3.from_matrix(pose[:3, :3]).wxyz,
                position=pose[:3, 3]))
        if len(path.keyframes) > 1:
            points = np.stack([path.at(float(t)).pose[:3, 3] for t in np.linspace(0.0, path.seconds, 100)])
            self.nodes.append(scene.add_line_segments("/camera_path/line", np.stack([points[:-1], points[1:]], 1),
                                                      (220, 30, 40), thickness=2.0, thickness_units="screen"))

    def play(self, client) -> None:
        """Play the path's frames on `client`'s page at its frames per second (pressing again stops it)."""
        if self.playing is not None:
            self.playing.set()
            return
        if not self.viewer.path.keyframes:
            self.say(client, "camera path", "no keyframes yet: add one from this view")
            return
        stop = self.playing = threading.Event()
        frames, fps = self.viewer.path.frames(), self.viewer.path.fps

        def run() -> None:
            try:
                for f in frames:
                    if stop.is_set():
                        break
                    show_camera(client, f.pose, float(np.radians(f.fov)))
                    stop.wait(1.0 / fps)
            finally:
                self.playing = None

        threading.Thread(target=run, daemon=True).start()


NONE = "(none)"  # the saved paths offered when there are none


def show_camera(client, pose: np.ndarray, fov: float) -> None:
    """Move `client`'s camera to `pose` (OpenGL camera-to-world, the scene's world) with vertical field of view `fov`
    (radians), in one message."""
    import viser.transforms as vtf

    cv = opencv_pose(torch.from_numpy(np.asarray(pose, dtype=np.float64)))
    with client.atomic():
        client.camera.wxyz = vtf.SO3.from_matrix(cv[:3, :3]).wxyz
        client.camera.position = tuple(cv[:3, 3])
        client.camera.fov = fov


def start_server(viewer: Viewer, host: str, port: int) -> Page:
    """Serve `viewer` on `host`:`port` (the next free port when it is taken) -> the page."""
    viser = import_viser()
    with contextlib.redirect_stdout(io.StringIO()):  # viser's own banner: `run` says the address in one line
        server = viser.ViserServer(host=host, port=free_port(host, port), verbose=False)
    server.scene.set_up_direction(_vector(scene_up(viewer.scene.split("train").poses).numpy()))
    server.gui.main_panel.dock_right()  # the panel beside the 3D view, not over it: the first view shows it all
    eye = viewer.first_eye()  # a training camera's view of the subject, its field of view
    camera = server.initial_camera
    camera.position, camera.look_at, camera.up, camera.fov = (_vector(eye.position), _vector(eye.look_at),
                                                              _vector(eye.up), eye.fov)
    return Page(viewer, server)


def _vector(v) -> tuple[float, ...]:
    return tuple(float(x) for x in v)


def viser_frustum_scale(depth: float, fov: float, aspect: float) -> float:
    """viser's `scale` of a camera frustum `depth` deep (apex to image): viser sizes a frustum by its volume, its
    depth scale / cbrt(tan(fov / 2)^2 * aspect / 3)."""
    return depth * (math.tan(fov / 2) ** 2 * aspect / 3) ** (1 / 3)


def camera_of(handle, size: int) -> Camera:
    """The camera a page shows (viser's camera handle), `size` pixels high."""
    import viser.transforms as vtf

    rotation = vtf.SO3(np.asarray(handle.wxyz)).as_matrix()
    return camera_for_view(rotation, np.asarray(handle.position), float(handle.fov), float(handle.aspect), size)


def serve(page: Page, stop: threading.Event) -> None:
    """The render loop: frames as pages need them, the model files looked at every `POLL` seconds, until `stop`. A
    frame or a look that fails is said in one line, and the page stays up."""
    viewer = page.viewer
    checked = 0.0
    while not stop.is_set():
        try:
            if time.monotonic() - checked >= POLL:
                checked = time.monotonic()
                page.sync(viewer.poll())
            if not page.render_next():
                stop.wait(0.02)
        except Exception as e:  # noqa: BLE001  the page stays up; the next change tries again
            why = str(e) if isinstance(e, BoostNerfError) else f"{type(e).__name__}: {e}"
            log(f"could not render {viewer.label}: {why}")
            viewer.settle()
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
    page = start_server(viewer, host, port)
    server = page.server
    shown = "localhost" if host in ("127.0.0.1", "::1") else host
    log(f"viewer at http://{shown}:{server.get_port()}/ (Ctrl-C stops it)")
    stop = threading.Event()
    try:
        serve(page, stop)
    finally:
        stop.set()
        with contextlib.redirect_stdout(io.StringIO()):  # "(viser) Server stopped"
            server.stop()
        log(f"the viewer rendered {viewer.frames} frame{'s' if viewer.frames != 1 else ''} and read "
            f"{viewer.models.reads} model file{'s' if viewer.models.reads != 1 else ''}")
