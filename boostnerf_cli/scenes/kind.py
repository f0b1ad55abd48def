"""The scene's kind, chosen once when it is loaded (recipe key `data.scene`): how its space is sampled.

- forward: a forward-facing capture (LLFF), sampled in normalized device coordinates (`Scene.ndc`);
- bounded: the subject inside one box (`Scene.bbox`): images with alpha, a layout that gives the box (Blender, NSVF,
  Tanks and Temples), a box given with data.bbox, or views that show a plain background around the subject;
- unbounded: an opaque capture whose views show scenery at their edges (walls, a table, trees, sky): space is
  contracted into one ball (render/contraction.py, `Scene.contraction`), whose box the grids cover, so every family,
  the coarse geometry, the occupancy grid, V_D, the gate and the dispatch see contracted points through the renderer
  and nothing else.

`auto`, in one sentence: an LLFF capture is forward; a scene whose end is marked (a layout's box or alpha, data.bbox,
alpha in its images, or a plain background at its views' edges) is bounded; any other scene of two cameras or more is
unbounded, whether its cameras stand all around their subject or on one side of it (a phone's half or quarter orbit),
since something opaque lies past every box its cameras give, and a box draws it on its faces.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import torch
from torch import Tensor

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.render.contraction import contraction_around, sphere_from_cameras, sphere_from_points
from boostnerf_cli.render.paths import focus_point, scene_up
from boostnerf_cli.scenes.llff import choose_folder
from boostnerf_cli.scenes.scene import Scene

KINDS = ("auto", "bounded", "unbounded", "forward")
LAYOUT_BOX = ("blender", "nsvf", "tanks")  # layouts that give the box (bbox.txt) or mark the background (alpha)
PLAIN_EDGE = 0.2  # views whose edge pixels show the background colour this often: a subject on a plain background
AROUND = 0.5  # cameras surround their subject when their mean horizontal direction from it is shorter than this
FACING = 0.5  # ... and most of them face it (the median cosine between axis and way to it at least this)


def edge_background_share(scene: Scene, tol: float = 0.03) -> float:
    """The share of the training views' edge pixels (one pixel wide) that show the scene's background colour."""
    images = scene.splits["train"].images
    edges = torch.cat([images[:, 0], images[:, -1], images[:, :, 0], images[:, :, -1]], dim=1)  # (N, 2W + 2H, 3)
    bg = torch.tensor(scene.background, dtype=images.dtype)
    return float(((edges - bg).abs().amax(-1) <= tol).double().mean())


def surround(poses: Tensor) -> tuple[bool, str]:
    """Whether cameras (N, 4, 4) stand all around one point that they face, -> (yes, why)."""
    if len(poses) < 3:
        return False, f"{len(poses)} training camera(s) cannot surround a subject"
    try:
        focus = focus_point(poses).double()
        up = scene_up(poses).double()
    except BoostNerfError:
        return False, "the cameras' viewing axes meet nowhere"
    p = poses.double()
    way = p[:, :3, 3] - focus
    flat = way - (way @ up)[:, None] * up
    flat = flat / flat.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    spread = float(flat.mean(0).norm())
    facing = float(((-way / way.norm(dim=-1, keepdim=True).clamp_min(1e-12)) * -p[:, :3, 2]).sum(-1).median())
    if facing < FACING:
        return False, "the cameras do not face a common point"
    if spread >= AROUND:
        return False, f"the cameras stand on one side of the point they face (mean direction {spread:.2f})"
    return True, f"cameras all around the point they face (mean direction {spread:.2f})"


def marks_background(scene: Scene) -> bool:
    """Some training image has alpha that marks background pixels."""
    alpha = scene.splits["train"].alpha
    return alpha is not None and bool((alpha < 0.5).any())


def auto_kind(scene: Scene, bbox_given: bool) -> tuple[str, str]:
    """(kind, why) for `data.scene: auto` (module docstring)."""
    if scene.ndc is not None:
        what = "an LLFF capture" if scene.format == "llff" else f"a {scene.format} capture whose cameras face one way"
        return "forward", f"{what}: forward-facing, sampled in normalized device coordinates"
    if scene.format in LAYOUT_BOX:
        return "bounded", f"the {scene.format} layout gives the box or marks the background"
    if bbox_given:
        return "bounded", "data.bbox gives the box"
    if marks_background(scene):
        return "bounded", "the images' alpha marks their background"
    share = edge_background_share(scene)
    if share >= PLAIN_EDGE:
        return "bounded", f"{100 * share:.0f}% of the views' edge pixels show the plain background colour"
    poses = scene.splits["train"].poses
    if len(poses) < 2:
        return "bounded", "one training camera: no sphere around the cameras can be chosen"
    return "unbounded", f"opaque views with scenery at their edges, {surround(poses)[1]}"


def opaque_all_round(scene: Scene) -> bool:
    """The views are opaque and show scenery at their edges (no alpha, no plain background there): what lies past a
    bounded scene's box is more scenery, not a cut subject."""
    return scene.ndc is None and not marks_background(scene) and edge_background_share(scene) < PLAIN_EDGE


def past_the_box_remedy(scene: Scene) -> str:
    """What to do when many foreground rays of a bounded scene end on its box's faces or miss it (one clause, the
    likelier remedy first): contract the world for views with scenery all round, else a box that holds the subject."""
    unbounded = ("set recipe key data.scene: unbounded, which contracts the world around the cameras "
                 "(docs/datasets.md, \"Scene kinds\")")
    bbox = "give recipe key data.bbox a box that holds the subject (docs/datasets.md, \"The scene box\")"
    if scene.ndc is not None:  # neither key applies to a forward-facing capture (`refusal`)
        folder = Path(scene.source)
        try:  # its largest photos, as the LLFF loader picks them (fern: images_8/)
            images = choose_folder(folder, None)[0]
        except (BoostNerfError, OSError):  # a layout without images_<N>/ folders (COLMAP's images/), or none readable
            images = folder / "images"
        return ("a forward-facing capture is sampled in normalized device coordinates, which hold only what lies in "
                "front of its cameras: if they look all around the subject, make a scene of its photos that can be "
                f"sampled all around, `boostnerf capture --images {images} --out NEW`, and train on that")
    if opaque_all_round(scene) and not scene.extra.get("bbox"):
        return f"the views show scenery past the box: {unbounded}; if only the subject is cut, {bbox}"
    return f"if that is the subject, {bbox}; if it is scenery (a room, a landscape), {unbounded}"


def refusal(kind: str, scene: Scene, folder, bbox_given: bool) -> str:
    """"" or why `kind`, asked for, cannot work on `scene` (one line)."""
    if kind == "forward" and scene.ndc is None:
        return (f"data.scene: forward needs a forward-facing LLFF capture (poses_bounds.npy); {folder} is "
                f"{scene.format}: use auto, bounded or unbounded")
    if kind in ("bounded", "unbounded") and scene.ndc is not None:
        return (f"data.scene: {kind} does not apply to {folder}: an LLFF capture's poses_bounds.npy describes a "
                "forward-facing view, sampled in normalized device coordinates; use auto or forward")
    if kind == "unbounded" and bbox_given:
        return ("data.scene: unbounded takes no data.bbox (its space is the whole world, contracted around the "
                "cameras): remove data.bbox, or use data.scene: bounded")
    if kind == "unbounded" and len(scene.splits["train"]) < 2:
        return (f"data.scene: unbounded needs cameras at two places at least, to choose the sphere kept linear; "
                f"{folder} has {len(scene.splits['train'])} training view: use bounded")
    return ""


def contracted(scene: Scene) -> Scene:
    """`scene` with its space contracted (render/contraction.py): the sphere kept linear from its sparse points
    (a capture that has them: `scene.points`, as a COLMAP model gives them) or else its training cameras
    (`sphere_from_cameras`); the box that of the contracted world, far the contraction's far bound; the linear
    stretch reaches through the sphere from every camera, test views too."""
    poses = scene.splits["train"].poses
    if scene.points is not None and len(scene.points.xyz) >= 8:
        centre, radius = sphere_from_points(scene.points.xyz)
    else:
        try:
            focus = focus_point(poses)
        except BoostNerfError:
            focus = poses[:, :3, 3].mean(0)
        centre, radius = sphere_from_cameras(poses[:, :3, 3], focus)
    if not radius > 0 or not math.isfinite(radius):
        raise BoostNerfError(f"scene {scene.name!r}: its training cameras share one spot, so no sphere around them "
                             "can be chosen for data.scene: unbounded; use bounded")
    c = contraction_around(centre, radius, torch.cat([split.poses[:, :3, 3] for split in scene.splits.values()]))
    return dataclasses.replace(scene, bbox=c.box(), near=min(scene.near, 0.1 * radius), far=c.far, contraction=c)


def with_kind(scene: Scene, asked: str, folder, bbox_given: bool) -> Scene:
    """`scene` as the kind `asked` (auto: `auto_kind`), refused in one line where that kind cannot work; the kind and
    why it was chosen in `scene.extra["kind"]`."""
    if asked not in KINDS:
        raise BoostNerfError(f"data.scene: {asked!r} is not a scene kind: use one of {', '.join(KINDS)}")
    if asked == "auto":
        kind, why = auto_kind(scene, bbox_given)
        why = f"auto: {why}"
    else:
        kind, why = asked, "data.scene"
        if problem := refusal(kind, scene, folder, bbox_given):
            raise BoostNerfError(problem)
    if kind == "unbounded":
        scene = contracted(scene)
    return dataclasses.replace(scene, extra={**scene.extra, "kind": {"kind": kind, "why": why}})
