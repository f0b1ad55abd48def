"""`boostnerf export KIND`: a model as a point cloud, a mesh or its routing, in the frame of the data as the user gave
it (a capture's COLMAP world, a transforms.json's own), so that it lines up with the user's files.

- `pointcloud` (PLY): every training view rendered; each pixel whose accumulated opacity reaches `min_opacity` is
  back-projected along its camera ray (the renderer's rays, lens included: `render.rays.image_rays`) to its expected
  depth. Colour: the rendered colour without the background. Normal: from the depth map's gradients, i.e. the cross
  product of the back-projected points' differences to the neighbouring pixels across and down (of the two neighbours
  on an axis the nearer one, so that a silhouette does not bend it), turned to face the camera; a pixel without an
  opaque neighbour on each axis has none and is left out. `points` of them, drawn uniformly from every kept pixel of
  every view (seeded: the same file each time).
- `mesh` (PLY or OBJ, by the suffix): marching cubes (scikit-image) on the density the renderer sees (the field's,
  zero where its empty-space filter skips: the occupancy grid, a mixture's V_D) on a lattice of `resolution`
  vertices along the region's longest side, at the level where the opacity over one of the model's render steps is
  `threshold`. The region: a bounded scene's model box within the scene box; an unbounded scene's box around the
  sphere the contraction keeps linear (the shell beyond, out to infinity, is not meshed); a forward-facing scene's NDC
  box (the space the renderer samples), up to the capture's farthest depth bound, each vertex then mapped back to the
  world (the NDC map is projective: a triangle stays a triangle). Vertex colour: the model's colour seen looking
  along the negative normal; normals: area-weighted face normals, facing out of the density.
- `routing` (PLY, mixtures): one point at the centre of each cell of V_D's lattice that the renderer keeps (the
  occupancy grid, and V_D's opacity over one step above T; in an unbounded scene, inside the contracted ball, where
  the samples are), coloured by the expert the gate ranks first there (the
  colours of `render --per-expert` and the viewer: `viewpoint.maps.palette`), with the properties `expert` (its
  index, smallest expert 0) and `probability` (the gate's).

The renderer's points go out through `to_data`: NDC -> world (`NDC.world`), contracted -> world
(`Contraction.uncontract`), world -> the data's frame (`cameras.DataFrame.points_to_data`). The file is written
through `workspace.atomic_path`: a failed or interrupted export leaves no file at `out`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from boostnerf_cli.cameras import DataFrame
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.grid import lattice_points
from boostnerf_cli.images import to_uint8
from boostnerf_cli.lineage import Survey
from boostnerf_cli.models import ALL_SKIPS, LoadedModel, load_model, n_views
from boostnerf_cli.render.contraction import SHELL
from boostnerf_cli.render.occupancy import cell_points
from boostnerf_cli.render.packing import packer_for
from boostnerf_cli.render.rays import image_rays
from boostnerf_cli.render.renderer import Camera, render_image
from boostnerf_cli.scenes import Scene
from boostnerf_cli.viewpoint.maps import palette
from boostnerf_cli.workspace import atomic_path

log = logging.getLogger(__name__).info  # the stage's messages, on stderr (cli.py says them)

KINDS = {"pointcloud": (".ply",), "mesh": (".ply", ".obj"), "routing": (".ply",)}  # what each writes, by suffix
INSTALL = ("boostnerf export writes PLY files with plyfile, an optional extra: pip install -e \".[export]\" "
           "in the clone (or: pip install plyfile)")
POINTS = 100_000  # pointcloud: points written at most
MIN_OPACITY = 0.5  # pointcloud: a pixel's accumulated opacity from which it is a point (the depth pictures' cut)
RESOLUTION = 128  # mesh: lattice vertices along the region's longest side
# mesh: the surface, where the opacity over one render step crosses this. On the procedural scene (48 px, 24 views,
# a 32^3 DVGO expert trained 300 steps; lattice cell 0.053) the mean distances mesh -> surface + surface -> mesh
# were 0.217 at 0.01, 0.117 at 0.1, 0.094 at 0.2, 0.090 at 0.3 and 0.195 at 0.5 (holes): 0.2 keeps clear of them
MESH_THRESHOLD = 0.2
CHUNK = 1 << 16  # points per field query
NDC_FAR = 1 - 1e-6  # an NDC depth at or past this is infinitely far: no point


@dataclass(frozen=True)
class ExportOptions:
    """pointcloud: `points` at most, from pixels of opacity `min_opacity` or more of the first `views` training views
    (None: all); mesh: `resolution` lattice vertices along the longest side, the surface at opacity `threshold` over
    one render step."""

    points: int = POINTS
    min_opacity: float = MIN_OPACITY
    views: int | None = None
    resolution: int = RESOLUTION
    threshold: float = MESH_THRESHOLD


def check_request(kind: str, out: Path, options: ExportOptions) -> None:
    """Refuse, in one line and before anything is read, an unknown kind, a suffix it does not write, a folder as the
    file to write, options out of range, or PLY without plyfile (how to install it)."""
    if kind not in KINDS:
        raise BoostNerfError(f"unknown export {kind!r}: use pointcloud, mesh or routing")
    suffix = out.suffix.lower()
    if suffix not in KINDS[kind]:
        raise BoostNerfError(f"export {kind} writes {' or '.join(s[1:].upper() for s in KINDS[kind])}: give --out a "
                             f"file ending in {' or '.join(KINDS[kind])} (got {out.name!r})")
    if out.is_dir():
        raise BoostNerfError(f"--out {out} is a folder: give the file to write, e.g. {out / ('model' + suffix)}")
    if not 0 < options.min_opacity <= 1:
        raise BoostNerfError(f"--min-opacity {options.min_opacity:g}: give an opacity in (0, 1]")
    if not 0 < options.threshold < 1:
        raise BoostNerfError(f"--threshold {options.threshold:g}: give an opacity over one render step in (0, 1)")
    if suffix == ".ply":
        plyfile()


def plyfile():
    """The plyfile module; one line saying how to install it when it is missing."""
    try:
        import plyfile as module
    except ImportError:
        raise BoostNerfError(INSTALL) from None
    return module


def run(survey: Survey, kind: str, name: str, out: Path, options: ExportOptions, device: str) -> dict:
    """Export model `name` of the workspace as `kind` (`KINDS`) to `out`. -> what was written (`count`, and per kind
    `faces`, `views`, `kept_pixels`, `cells`, `experts`)."""
    check_request(kind, out, options)
    name = survey.current([name])[0]
    model = load_model(survey.ws, name, device)
    if kind == "routing":
        routable(model)
    scene = survey.scene()
    with torch.no_grad():
        if kind == "pointcloud":
            return pointcloud(model, scene, out, options, device)
        if kind == "mesh":
            return mesh(model, scene, out, options, device)
        return routing(model, scene, out, device)


# --- frames ----------------------------------------------------------------------------------------------------------
def to_world(scene: Scene, xyz: Tensor) -> Tensor:
    """Points (N, 3) of the space the renderer samples (NDC for a forward-facing scene, the contracted ball for an
    unbounded one) -> the scene's world."""
    if scene.ndc is not None:
        return scene.ndc.world(xyz)
    if scene.contraction is not None:
        return scene.contraction.uncontract(xyz)
    return xyz


def to_data(scene: Scene, world: Tensor) -> np.ndarray:
    """Points (N, 3) of the scene's world -> the data's frame, float64 (N, 3)."""
    return DataFrame.of(scene.extra).points_to_data(world.double().cpu().numpy())


def _queried(field_call, xyz: Tensor, *more: Tensor) -> Tensor:
    """`field_call` over (N, 3) points (and `more` per-point tensors) in chunks of `CHUNK`, concatenated."""
    if xyz.shape[0] == 0:
        return field_call(xyz, *more)
    return torch.cat([field_call(xyz[i : i + CHUNK], *(m[i : i + CHUNK] for m in more))
                      for i in range(0, xyz.shape[0], CHUNK)])


# --- pointcloud ------------------------------------------------------------------------------------------------------
def pixel_normals(points: Tensor, valid: Tensor, centre: Tensor) -> tuple[Tensor, Tensor]:
    """Normals of a back-projected depth map: points (H, W, 3), valid (H, W) bool, the camera centre (3,) in the same
    frame -> unit normals (H, W, 3) facing the camera, and (H, W) bool where there is one: a valid pixel with a valid
    neighbour on each image axis (of two, the nearer one)."""

    def difference(axis: int) -> tuple[Tensor, Tensor]:
        ahead = torch.roll(points, -1, axis) - points
        behind = points - torch.roll(points, 1, axis)
        n = points.shape[axis]
        index = torch.arange(n).reshape((-1, 1) if axis == 0 else (1, -1))
        ok_ahead = valid & torch.roll(valid, -1, axis) & (index < n - 1)
        ok_behind = valid & torch.roll(valid, 1, axis) & (index > 0)
        take_ahead = ok_ahead & (~ok_behind | (ahead.norm(dim=-1) <= behind.norm(dim=-1)))
        return torch.where(take_ahead[..., None], ahead, behind), ok_ahead | ok_behind

    du, ok_u = difference(1)
    dv, ok_v = difference(0)
    normal = torch.linalg.cross(du, dv)
    length = normal.norm(dim=-1)
    ok = ok_u & ok_v & (length > 0)
    normal = normal / length.clamp_min(1e-30)[..., None]
    facing = ((centre - points) * normal).sum(-1) >= 0
    return torch.where(facing[..., None], normal, -normal), ok


def pointcloud(model: LoadedModel, scene: Scene, out: Path, options: ExportOptions, device: str) -> dict:
    split = scene.split("train")
    n = n_views(split, options.views)
    settings, skip = model.render_setup(scene, ALL_SKIPS)
    packer = packer_for(device)
    background = torch.tensor(scene.background, dtype=torch.float64)
    frame = DataFrame.of(scene.extra)
    generator = torch.Generator().manual_seed(0)
    keys = torch.zeros(0, dtype=torch.float64)
    xyz, normals, rgb = torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, 3), torch.zeros(0, 3)
    kept = 0
    h, w = split.height, split.width
    for i in range(n):
        pose = split.poses[i]
        r = render_image(model.field, Camera(pose, split.intrinsics[i], h, w), settings, skip, device, packer)
        o, d = image_rays(pose, split.intrinsics[i], h, w, scene.ndc)  # the rays render_image cast
        acc = r["acc"].reshape(-1).double()
        p = o.double() + (r["depth"].reshape(-1).double() / acc.clamp_min(1e-12))[:, None] * d.double()
        good = acc >= options.min_opacity
        if scene.ndc is not None:
            good &= p[:, 2] < NDC_FAR
            p = scene.ndc.world(torch.where(good[:, None], p, torch.zeros_like(p)))
        points = torch.from_numpy(frame.points_to_data(p.numpy()))
        centre = torch.from_numpy(frame.points_to_data(pose[:3, 3].double().numpy()))
        n_map, has = pixel_normals(points.reshape(h, w, 3), good.reshape(h, w), centre)
        good &= has.reshape(-1)
        colour = (r["rgb"].reshape(-1, 3).double() - (1 - acc)[:, None] * background) / acc.clamp_min(1e-12)[:, None]
        rows = good.nonzero().squeeze(-1)
        kept += len(rows)
        # bottom-k sampling: every kept pixel draws a key, the `points` smallest keys of all views are kept
        keys = torch.cat([keys, torch.rand(len(rows), generator=generator, dtype=torch.float64)])
        xyz = torch.cat([xyz, points[rows]])
        normals = torch.cat([normals, n_map.reshape(-1, 3)[rows].float()])
        rgb = torch.cat([rgb, colour[rows].clamp(0, 1).float()])
        if len(keys) > options.points:
            order = keys.topk(options.points, largest=False).indices
            keys, xyz, normals, rgb = keys[order], xyz[order], normals[order], rgb[order]
    if not kept:
        raise BoostNerfError(f"no pixel of {model.name}'s render of {n} training view{'s' if n != 1 else ''} reaches "
                             f"opacity {options.min_opacity:g}: lower --min-opacity, or train the model longer")
    order = keys.argsort()
    xyz, normals, rgb = xyz[order].numpy(), normals[order].numpy(), rgb[order].numpy()
    write_ply(out, xyz, rgb, normals)
    log(f"{model.name}: wrote {len(xyz):,} points (of {kept:,} pixels with opacity >= {options.min_opacity:g} in "
        f"{n} training view{'s' if n != 1 else ''}; normals from the depth maps' gradients) to {out}, in the data's "
        "frame")
    return {"count": len(xyz), "kept_pixels": kept, "views": n}


# --- mesh ------------------------------------------------------------------------------------------------------------
def mesh_region(model: LoadedModel, scene: Scene) -> tuple[Tensor, str]:
    """The box (2, 3) of the renderer's space that `mesh` samples (module docstring), and its name for the log."""
    box = torch.stack([torch.maximum(model.bbox[0].cpu(), scene.bbox[0]), torch.minimum(model.bbox[1].cpu(),
                                                                                        scene.bbox[1])])
    if scene.contraction is not None:
        c = torch.tensor(scene.contraction.centre, dtype=torch.float32)
        r = scene.contraction.radius
        return torch.stack([c - r, c + r]), f"the box around the sphere kept linear (radius {r:.3g})"
    if scene.ndc is not None:
        bounds = scene.extra.get("bounds")
        far = float(np.max(bounds)) if bounds else scene.ndc.depth(NDC_FAR)
        box[1, 2] = min(float(box[1, 2]), scene.ndc.z(far))
        return box, f"the NDC box up to depth {far:.3g} (the capture's farthest bound)"
    if not bool((box[1] > box[0]).all()):
        raise BoostNerfError(f"{model.name}'s box does not overlap the scene box: nothing to mesh")
    return box, "the model's box within the scene box"


def lattice(box: Tensor, resolution: int) -> tuple[tuple[int, int, int], np.ndarray]:
    """The lattice over `box` with `resolution` vertices along its longest side, the others as near the same spacing
    as fits the box exactly -> (shape, spacing (3,))."""
    size = (box[1] - box[0]).double()
    step = float(size.max()) / (resolution - 1)
    shape = tuple(max(2, round(float(s) / step) + 1) for s in size)
    return shape, (size / (torch.tensor(shape, dtype=torch.float64) - 1)).numpy()


def grid_density(model: LoadedModel, scene: Scene, box: Tensor, shape: tuple[int, int, int], device: str) -> np.ndarray:
    """The density the renderer sees at every lattice vertex -> (X, Y, Z) float32: the field's, zero where the model's
    empty-space filter skips."""
    x = torch.linspace(float(box[0, 0]), float(box[1, 0]), shape[0], dtype=torch.float64)
    slab = box.clone()
    sigma = np.zeros(shape, dtype=np.float32)
    rows = max(1, CHUNK * 4 // (shape[1] * shape[2]))  # x planes per batch
    for i in range(0, shape[0], rows):
        part = x[i : i + rows]
        slab[0, 0], slab[1, 0] = float(part[0]), float(part[-1])
        xyz = lattice_points(slab.to(device), (len(part), shape[1], shape[2]))
        if scene.contraction is not None:
            xyz = scene.contraction.contract(xyz)
        values = _queried(model.field.density, xyz)
        if model.skip is not None:
            values = values * _queried(model.skip, xyz)
        sigma[i : i + len(part)] = values.float().reshape(len(part), shape[1], shape[2]).cpu().numpy()
    return sigma


def face_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (V, 3) of a triangle mesh (right-hand winding), unit length (0 for a vertex of
    degenerate faces only)."""
    a, b, c = (verts[faces[:, k]] for k in range(3))
    cross = np.cross(b - a, c - a)
    normals = np.zeros_like(verts)
    for k in range(3):
        np.add.at(normals, faces[:, k], cross)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.maximum(length, 1e-300)


def mesh(model: LoadedModel, scene: Scene, out: Path, options: ExportOptions, device: str) -> dict:
    from skimage.measure import marching_cubes

    box, region = mesh_region(model, scene)
    shape, spacing = lattice(box, options.resolution)
    sigma = grid_density(model, scene, box, shape, device)
    level = -math.log1p(-options.threshold) / model.step  # density with that opacity over one render step
    peak = float(sigma.max())
    if peak <= level:
        raise BoostNerfError(f"{model.name} has no density above --threshold {options.threshold:g} (opacity over one "
                             f"render step, density {level:.3g}; its largest is {peak:.3g}) in {region}: lower "
                             "--threshold, or train the model longer")
    if float(sigma.min()) >= level:
        raise BoostNerfError(f"{model.name}'s density is above --threshold {options.threshold:g} everywhere in "
                             f"{region}: no surface to mesh; raise --threshold")
    verts, faces, mc_normals, _ = marching_cubes(sigma, level, spacing=tuple(float(s) for s in spacing))
    verts = torch.from_numpy(verts.astype(np.float64)) + box[0].double()
    outward = torch.from_numpy(mc_normals.astype(np.float64))  # towards less density
    where = verts.float().to(device)
    if scene.contraction is not None:
        where = scene.contraction.contract(where)
    rgb = _queried(model.field.color, where, -outward.float().to(device)).float().clamp(0, 1).cpu().numpy()
    points = to_data(scene, to_world(scene, verts))
    faces = faces.astype(np.int64)
    normals = face_normals(points, faces)
    # the winding must make the normals point out of the density in the data's frame too (the NDC map can mirror)
    eps = 1e-3 * float(spacing.min())
    ahead = to_data(scene, to_world(scene, verts + eps * outward)) - points
    if float((normals * ahead).sum()) < 0:
        faces, normals = faces[:, ::-1].copy(), -normals
    if out.suffix.lower() == ".obj":
        write_obj(out, points, rgb, normals, faces)
    else:
        write_ply(out, points, rgb, normals, faces)
    log(f"{model.name}: wrote a mesh of {len(points):,} vertices and {len(faces):,} faces (marching cubes on a "
        f"{'x'.join(map(str, shape))} lattice over {region}, at opacity {options.threshold:g} over one render step) "
        f"to {out}, in the data's frame")
    return {"count": len(points), "faces": len(faces), "shape": list(shape)}


# --- routing ---------------------------------------------------------------------------------------------------------
def routable(model: LoadedModel) -> None:
    """Refuse a model without a gate's choice to export: a single expert, the ensemble."""
    if model.kind != "mixture":
        raise BoostNerfError(f"{model.name} is a single expert: export routing shows a mixture's gate; give a mixture "
                             "(top1, top2, ...: boostnerf build-moe, then finetune --topk K)")
    if model.field.gate.cfg.gate_type == "uniform":
        raise BoostNerfError(f"{model.name} sends every sample to every expert with equal weights (no gate picks "
                             "one): export routing of a top-k mixture (top1, top2, ...)")


def routing(model: LoadedModel, scene: Scene, out: Path, device: str) -> dict:
    mix = model.field
    vd = mix.vd
    # the centres of the cells between V_D's vertices, in `moe.cells.cell_index`'s order
    centres = cell_points(vd.bbox, tuple(n - 1 for n in vd.shape), torch.full((3,), 0.5, device=vd.bbox.device))
    kept = centres[_queried(mix.skip, centres)]
    if scene.contraction is not None:  # the box's corners past the contracted ball: no sample ever lies there
        c = scene.contraction
        kept = kept[(kept - torch.tensor(c.centre).to(kept)).norm(dim=-1) < SHELL * c.radius]
    if kept.shape[0] == 0:
        raise BoostNerfError(f"{model.name}'s density volume keeps no cell (every cell's opacity over one step is at "
                             f"most T = {mix.cfg.density_threshold:g}): nothing to export; check the model with "
                             "boostnerf render")
    probs = _queried(mix.gate.probs, kept).float()
    best, expert = probs.max(dim=-1)
    expert = expert.cpu().numpy()
    points = to_data(scene, to_world(scene, kept.cpu().double()))
    colours = palette(mix.m)[expert]
    extra = {"expert": expert.astype(np.uint8), "probability": best.cpu().numpy().astype(np.float32)}
    write_ply(out, points, colours, extra=extra)
    names = list(mix.cfg.expert_names) or [f"expert {e}" for e in range(mix.m)]
    counts = np.bincount(expert, minlength=mix.m)
    log(f"{model.name}: wrote {len(points):,} points, one per cell V_D keeps (of {centres.shape[0]:,}), to {out}, in "
        "the data's frame; cells per expert: " + ", ".join(f"{n} {c:,}" for n, c in zip(names, counts)))
    return {"count": len(points), "cells": int(centres.shape[0]), "experts": counts.tolist()}


# --- files -----------------------------------------------------------------------------------------------------------
def write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray, normals: np.ndarray | None = None,
              faces: np.ndarray | None = None, extra: dict[str, np.ndarray] | None = None) -> None:
    """A binary PLY: vertices x y z (float64: a capture's frame may sit far from its origin), nx ny nz (float32) when
    `normals`, red green blue (uchar) from `rgb` in [0, 1], then the `extra` per-vertex properties; faces as
    `vertex_indices` lists when `faces` (F, 3)."""
    module = plyfile()
    fields = [("x", "f8"), ("y", "f8"), ("z", "f8")]
    if normals is not None:
        fields += [("nx", "f4"), ("ny", "f4"), ("nz", "f4")]
    fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    fields += [(k, v.dtype.str) for k, v in (extra or {}).items()]
    vertex = np.empty(len(xyz), dtype=fields)
    for a, k in enumerate("xyz"):
        vertex[k] = xyz[:, a]
    if normals is not None:
        for a, k in enumerate(("nx", "ny", "nz")):
            vertex[k] = normals[:, a]
    for k, v in zip(("red", "green", "blue"), to_uint8(rgb).T):
        vertex[k] = v
    for k, v in (extra or {}).items():
        vertex[k] = v
    elements = [module.PlyElement.describe(vertex, "vertex")]
    if faces is not None:
        face = np.empty(len(faces), dtype=[("vertex_indices", "i4", (3,))])
        face["vertex_indices"] = faces
        elements.append(module.PlyElement.describe(face, "face"))
    with atomic_path(path, keep_suffix=True) as tmp:
        module.PlyData(elements).write(str(tmp))


def write_obj(path: Path, xyz: np.ndarray, rgb: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> None:
    """A Wavefront OBJ: `v x y z r g b` (the common extension: colours in [0, 1]), `vn`, faces `f a//a b//b c//c`."""
    lines = ["# boostnerf export mesh"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g} {r:.4f} {g:.4f} {b:.4f}" for (x, y, z), (r, g, b) in zip(xyz, rgb)]
    lines += [f"vn {x:.6f} {y:.6f} {z:.6f}" for x, y, z in normals]
    lines += [f"f {a}//{a} {b}//{b} {c}//{c}" for a, b, c in (faces + 1).tolist()]
    with atomic_path(path, keep_suffix=True) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
