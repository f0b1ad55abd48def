"""`boostnerf export`: point clouds, meshes and routing in the frame of the data as the user gave it
(boostnerf_cli/stages/export.py), checked against the procedural scenes' exact geometry and a forward-facing
capture's own files."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import assert_clean_failure, no_temp_files, run_cli

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.lineage import Survey
from boostnerf_cli.models import LoadedModel, load_expert, load_mixture
from boostnerf_cli.render.rays import NDC, image_rays
from boostnerf_cli.scenes.colmap_model import read_model
from boostnerf_cli.scenes.procedural import intersect, rot_z
from boostnerf_cli.stages.export import INSTALL, pixel_normals, routable
from boostnerf_cli.viewpoint.maps import palette
from boostnerf_cli.workspace import Workspace

plyfile = pytest.importorskip("plyfile")  # the test extra installs it


def read_ply(path: Path) -> dict[str, np.ndarray]:
    """A PLY's vertex properties by name, plus `xyz` (N, 3) and, with faces, `faces` (F, 3)."""
    data = plyfile.PlyData.read(str(path))
    v = data["vertex"].data
    out = {name: np.asarray(v[name]) for name in v.dtype.names}
    out["xyz"] = np.stack([out["x"], out["y"], out["z"]], -1).astype(np.float64)
    if "face" in data:
        out["faces"] = np.stack(data["face"].data["vertex_indices"])
    return out


def nearest(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Each point of a (N, 3): its distance to the nearest point of b (M, 3)."""
    tb = torch.from_numpy(b)
    return torch.cat([torch.cdist(torch.from_numpy(a[i : i + 2048]), tb).min(1).values
                      for i in range(0, len(a), 2048)]).numpy()


def surface_distance(objects: list[dict], p: np.ndarray) -> np.ndarray:
    """Each point's distance to the nearest surface of the procedural scene's `objects` (discs, spheres, boxes)."""
    p = torch.from_numpy(p)
    found = []
    for o in objects:
        c = torch.tensor(o["centre"], dtype=torch.float64)
        if o["kind"] == "sphere":
            found.append(((p - c).norm(dim=-1) - o["radius"]).abs())
        elif o["kind"] == "disc":
            rho = (p[:, :2] - c[:2]).norm(dim=-1)
            found.append(torch.sqrt((p[:, 2] - c[2]) ** 2 + (rho - o["radius"]).clamp_min(0) ** 2))
        elif o["kind"] == "box":
            q = ((p - c) @ rot_z(o["angle"])).abs() - torch.tensor(o["half"], dtype=torch.float64)
            found.append((q.clamp_min(0).norm(dim=-1) + q.max(dim=-1).values.clamp_max(0)).abs())
        else:
            raise AssertionError(f"no distance for a {o['kind']}")
    return torch.stack(found).min(0).values.numpy()


def seen_surface(objects: list[dict], split, every: int = 2) -> np.ndarray:
    """The surface the training views see: the first hit of every `every`-th pixel ray of every view."""
    points = []
    for i in range(len(split)):
        o, d = (v.double()[::every] for v in image_rays(split.poses[i], split.intrinsics[i], split.height, split.width))
        t = torch.stack([intersect(obj, o, d)[0] for obj in objects]).min(0).values
        points.append((o + t[:, None] * d)[torch.isfinite(t)])
    return torch.cat(points).numpy()


def expert_cell(ws: Path, name: str) -> float:
    """The mean spacing of expert `name`'s density lattice, world units."""
    model, _, _ = load_expert(Workspace(ws).expert_path(name))
    size = model.bbox[1] - model.bbox[0]
    return float((size / (torch.tensor(model.shape) - 1)).mean())


# --- pure parts -------------------------------------------------------------------------------------------------------
def test_ndc_world_inverts_ndc_points():
    ndc = NDC(sx=2.7, sy=2.1, near=1.0)
    p = torch.randn(500, 3, dtype=torch.float64) * 3
    p[:, 2] = -1.0 - torch.rand(500, dtype=torch.float64) * 50  # in front of the near plane
    assert torch.allclose(ndc.world(ndc.points(p)), p, rtol=1e-9, atol=1e-9)


def test_pixel_normals_face_the_camera_and_take_the_nearer_neighbour_at_a_silhouette():
    """A floor (z = 0) seen from above, with a block standing on its right half: the floor pixels next to the block
    take their across-difference from the floor side, so their normal stays +z."""
    h, w = 6, 8
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    points = torch.stack([u * 0.1, -v * 0.1, torch.zeros_like(u)], -1)
    points[:, 5:, 2] = 0.4  # the block's top, 0.4 above the floor: a silhouette between columns 4 and 5
    valid = torch.ones(h, w, dtype=torch.bool)
    valid[0, 0] = False
    centre = torch.tensor([0.3, -0.3, 5.0], dtype=torch.float64)
    normals, ok = pixel_normals(points, valid, centre)
    assert not ok[0, 0] and ok[1:].all()
    assert torch.allclose(normals[ok], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(int(ok.sum()), 3))
    normals, _ = pixel_normals(points, valid, -centre)  # seen from below: the normals turn to face it
    assert bool((normals[1:, :, 2] < -0.99).all())


def test_routing_refuses_the_ensemble():
    from helpers import toy_mixture

    mix = toy_mixture(3)
    mix.make_ensemble()
    with pytest.raises(BoostNerfError, match="equal weights"):
        routable(LoadedModel("ens", "mixture", mix, mix.skip, 0.05, mix.bbox, 0))


# --- a bounded scene: the exact surface -------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def surface_ws(tmp_path_factory, tiny_scene, tiny_recipe) -> Path:
    """The tiny scene with one 24^3 DVGO expert trained 150 steps (the 30 steps of `trained_ws` leave its geometry a
    cell or more off)."""
    ws = tmp_path_factory.mktemp("export") / "ws"
    run_cli("pretrain", "--data", str(tiny_scene), "--recipe", str(tiny_recipe), "--workspace", str(ws), "--res", "24",
            "--iters", "150", "--device", "cpu", check=True)
    return ws


def test_the_mesh_lies_on_the_scene_surface_within_a_lattice_cell(surface_ws, tiny_scene, tmp_path):
    """Marching cubes on the expert's density, against the procedural scene's exact surfaces. A trilinear density
    lattice ramps over a cell on each side of a surface, so its level set sits within about a cell of it: the median
    distance each way must be under one cell of the expert's lattice (measured: 0.74 and 0.76 of its 0.074), and the
    Chamfer distance (mean mesh -> surface plus mean seen surface -> mesh) under 2.5 cells (measured 1.99: floaters and
    the floor's unseen underside add to the means). Sampled at 64 vertices along the box (a 0.033 spacing)."""
    out = tmp_path / "mesh.ply"
    proc = run_cli("export", "mesh", "--workspace", str(surface_ws), "--model", "dvgo-24", "--out", str(out),
                   "--resolution", "64", "--device", "cpu", check=True)
    assert proc.stdout.strip() == str(out)
    mesh = read_ply(out)
    objects = json.loads((tiny_scene / "objects.json").read_text())["objects"]
    scene = Survey(Workspace(surface_ws)).scene()
    cell = expert_cell(surface_ws, "dvgo-24")
    to_surface = surface_distance(objects, mesh["xyz"])
    to_mesh = nearest(seen_surface(objects, scene.splits["train"]), mesh["xyz"])
    chamfer = to_surface.mean() + to_mesh.mean()
    assert np.median(to_surface) < cell and np.median(to_mesh) < cell, (np.median(to_surface), np.median(to_mesh), cell)
    assert chamfer < 2.5 * cell, (chamfer, cell)
    assert len(mesh["faces"]) > 1000 and mesh["faces"].max() < len(mesh["xyz"])
    # the normals point out of the solids: on the spheres, along the radius
    for sphere in (o for o in objects if o["kind"] == "sphere"):
        radial = mesh["xyz"] - np.array(sphere["centre"])
        near = np.abs(np.linalg.norm(radial, axis=1) - sphere["radius"]) < cell / 2
        normals = np.stack([mesh["nx"], mesh["ny"], mesh["nz"]], -1)[near]
        cosine = (normals * radial[near]).sum(1) / np.linalg.norm(radial[near], axis=1)
        assert near.sum() > 20 and np.median(cosine) > 0.8
    # the OBJ holds the same mesh
    obj = tmp_path / "mesh.obj"
    run_cli("export", "mesh", "--workspace", str(surface_ws), "--model", "dvgo-24", "--out", str(obj), "--resolution",
            "64", "--device", "cpu", check=True)
    lines = obj.read_text().splitlines()
    verts = np.array([[float(x) for x in ln.split()[1:4]] for ln in lines if ln.startswith("v ")])
    faces = np.array([[int(c.split("//")[0]) - 1 for c in ln.split()[1:]] for ln in lines if ln.startswith("f ")])
    assert np.allclose(verts, mesh["xyz"], atol=1e-6) and np.array_equal(faces, mesh["faces"])


def test_the_point_cloud_lies_on_the_seen_surface_with_its_normals(surface_ws, tiny_scene, tmp_path):
    """The depth maps back-projected: --points of them, the median point within a lattice cell of the exact surface,
    and the normals from the depth maps' gradients along the true ones where that surface is the floor or a sphere
    (measured on 32 px views: median cosine 0.74, 96% within 90 degrees)."""
    out = tmp_path / "points.ply"
    run_cli("export", "pointcloud", "--workspace", str(surface_ws), "--model", "dvgo-24", "--out", str(out),
            "--points", "2000", "--device", "cpu", check=True)
    cloud = read_ply(out)
    objects = json.loads((tiny_scene / "objects.json").read_text())["objects"]
    cell = expert_cell(surface_ws, "dvgo-24")
    xyz = cloud["xyz"]
    assert len(xyz) == 2000
    each = np.stack([surface_distance([o], xyz) for o in objects])
    assert np.median(each.min(0)) < cell
    true = np.full_like(xyz, np.nan)  # the normal of the nearest surface, where it is the floor or a sphere
    for k, o in enumerate(objects):
        mine = (each.argmin(0) == k) & (each.min(0) < cell)
        if o["kind"] == "disc":
            true[mine] = [0.0, 0.0, 1.0]
        elif o["kind"] == "sphere":
            radial = xyz[mine] - np.array(o["centre"])
            true[mine] = radial / np.linalg.norm(radial, axis=1, keepdims=True)
    normals = np.stack([cloud["nx"], cloud["ny"], cloud["nz"]], -1)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-4)
    known = ~np.isnan(true[:, 0])
    cosine = (normals[known] * true[known]).sum(1)
    assert known.sum() > 200 and np.median(cosine) > 0.5 and np.mean(cosine > 0) > 0.85, (known.sum(), cosine)


# --- routing ----------------------------------------------------------------------------------------------------------
def kept_cells(ws: Path, name: str) -> tuple[torch.Tensor, int]:
    """The centres of the V_D cells a mixture keeps, worked out here from its file (V_D's opacity over one step above
    T, in an occupied cell), in the mixture's own space, and its number of experts."""
    mix, _ = load_mixture(Workspace(ws).model_path(name))
    vd = mix.vd
    axes = [torch.linspace(float(vd.bbox[0, a]), float(vd.bbox[1, a]), vd.shape[a]) for a in range(3)]
    mids = [(ax[:-1] + ax[1:]) / 2 for ax in axes]  # halfway between neighbouring vertices
    centres = torch.stack(torch.meshgrid(*mids, indexing="ij"), dim=-1).reshape(-1, 3)
    with torch.no_grad():
        keep = -torch.expm1(-vd.density(centres) * mix.cfg.step) > mix.cfg.density_threshold
    if mix.occupancy is not None:
        keep &= mix.occupancy(centres)
    return centres[keep].double(), mix.m


def test_routing_is_one_point_per_kept_cell_coloured_by_its_expert(mixture_ws, tmp_path):
    out = tmp_path / "routing.ply"
    run_cli("export", "routing", "--workspace", str(mixture_ws), "--model", "top2", "--out", str(out), "--device",
            "cpu", check=True)
    points = read_ply(out)
    cells, m = kept_cells(mixture_ws, "top2")
    assert len(points["xyz"]) == len(cells) > 0
    assert nearest(points["xyz"], cells.numpy()).max() < 1e-6  # a blender scene: the world is the data's frame
    expert = points["expert"].astype(int)
    assert expert.min() >= 0 and expert.max() < m
    colours = np.stack([points["red"], points["green"], points["blue"]], -1)
    assert np.array_equal(colours, np.round(palette(m)[expert] * 255).astype(np.uint8))
    assert ((points["probability"] >= 1 / m - 1e-6) & (points["probability"] <= 1)).all()


# --- bad input ------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("args, out_name, needles", [
    (["mesh", "--model", "dvgo-16", "--threshold", "0.999999"], "mesh.ply", ["no density above --threshold"]),
    (["cube", "--model", "dvgo-16"], "x.ply", ["unknown export 'cube'", "pointcloud, mesh or routing"]),
    (["mesh", "--model", "dvgo-99"], "mesh.ply", ["no model named 'dvgo-99'", "dvgo-12, dvgo-16"]),
    (["routing", "--model", "dvgo-12"], "routing.ply", ["dvgo-12 is a single expert"]),
    (["mesh", "--model", "dvgo-16"], "mesh.stl", ["ending in .ply or .obj"]),
    (["pointcloud", "--model", "dvgo-16"], "points.obj", ["ending in .ply"]),
])
def test_bad_exports_are_one_line_and_write_nothing(mixture_ws, tmp_path, args, out_name, needles):
    out = tmp_path / "out" / out_name
    out.parent.mkdir()
    proc = run_cli("export", *args, "--workspace", str(mixture_ws), "--out", str(out), "--device", "cpu")
    assert_clean_failure(proc, *needles)
    assert not out.exists() and not any(out.parent.iterdir()) and no_temp_files(out.parent)


def test_without_plyfile_a_ply_is_refused_with_how_to_install_it(trained_ws, tmp_path):
    stub = tmp_path / "stub"
    stub.mkdir()
    (stub / "plyfile.py").write_text("raise ImportError('No module named plyfile')\n")
    out = tmp_path / "points.ply"
    path = os.pathsep.join(p for p in (str(stub), os.environ.get("PYTHONPATH", "")) if p)
    proc = run_cli("export", "pointcloud", "--workspace", str(trained_ws), "--model", "dvgo-16", "--out", str(out),
                   env_extra={"PYTHONPATH": path})
    assert_clean_failure(proc, INSTALL)
    assert not out.exists()


# --- a forward-facing capture: the data's frame is not boostnerf's world ----------------------------------------------
@pytest.fixture(scope="module")
def forward_ws(tmp_path_factory, tiny_recipe) -> tuple[Path, Path]:
    """A forward-facing capture in the COLMAP layout (its sparse points and cameras in the data's frame; boostnerf
    rescales and recentres it, world_from_data, and samples it in NDC), two experts, and a 5-step Top-1 mixture."""
    root = tmp_path_factory.mktemp("forward")
    scene, ws = root / "scene", root / "ws"
    run_cli("make-scene", str(scene), "--size", "32", "--train-views", "12", "--test-views", "2", "--format", "colmap",
            "--rig", "forward", check=True)
    run_cli("pretrain", "--data", str(scene), "--recipe", str(tiny_recipe), "--workspace", str(ws), "--res", "12,24",
            "--iters", "300", "--set", "pretrain.geometry.iters=300", "--device", "cpu", check=True)
    run_cli("build-moe", "--workspace", str(ws), "--device", "cpu", check=True)
    run_cli("finetune", "--workspace", str(ws), "--topk", "1", "--iters", "5", "--device", "cpu", check=True)
    return scene, ws


def to_boostnerf_world(points: np.ndarray, ws: Path) -> np.ndarray:
    """Points of the data's frame as they would be left in boostnerf's world: the inverse normalisation dropped."""
    t = np.asarray(Survey(Workspace(ws)).scene().extra["world_from_data"])
    return points @ t[:3, :3].T + t[:3, 3]


@pytest.mark.slow
def test_forward_facing_exports_line_up_with_the_captures_own_points(forward_ws, tmp_path):
    """The point cloud and the mesh of a forward-facing capture lie on its sparse points (COLMAP's points3D, the data's
    frame): the median distance to the nearest one is under a tenth (the mesh: 0.15) of their extent, and left in
    boostnerf's world (world_from_data not inverted) it would be over a quarter of it and 3 times as far (measured:
    0.058 and 0.35 of the extent for the points, 0.093 and 0.39 for the mesh). The point cloud's normals face the
    cameras."""
    scene, ws = forward_ws
    model = read_model(scene / "sparse" / "0")
    sparse = np.asarray(model.xyz, dtype=np.float64)
    extent = float(np.linalg.norm(sparse.max(0) - sparse.min(0)))
    assert not np.allclose(Survey(Workspace(ws)).scene().extra["world_from_data"], np.eye(4))
    for kind, out, near in (("pointcloud", tmp_path / "points.ply", 0.1), ("mesh", tmp_path / "mesh.ply", 0.15)):
        run_cli("export", kind, "--workspace", str(ws), "--model", "dvgo-24", "--out", str(out), "--device", "cpu",
                check=True)
        xyz = read_ply(out)["xyz"]
        assert np.isfinite(xyz).all()
        here, dropped = np.median(nearest(xyz, sparse)), np.median(nearest(to_boostnerf_world(xyz, ws), sparse))
        assert here < near * extent and dropped > max(0.25 * extent, 3 * here), (kind, here, dropped, extent)
    cloud = read_ply(tmp_path / "points.ply")
    normals = np.stack([cloud["nx"], cloud["ny"], cloud["nz"]], -1)
    cameras = np.stack([image.world_from_camera()[:3, 3] for image in model.images.values()])
    towards = cameras.mean(0) - cloud["xyz"]
    assert np.mean((normals * towards).sum(1) > 0) > 0.9


@pytest.mark.slow
def test_forward_facing_routing_is_v_d_cells_through_ndc_and_the_data_frame(forward_ws, tmp_path):
    """The routing points are the kept V_D cells' centres taken from NDC to the world (depth 2 near / (1 - z), worked
    out here) and then to the data's frame (world_from_data inverted)."""
    _, ws = forward_ws
    out = tmp_path / "routing.ply"
    run_cli("export", "routing", "--workspace", str(ws), "--model", "top1", "--out", str(out), "--device", "cpu",
            check=True)
    points = read_ply(out)
    cells, m = kept_cells(ws, "top1")
    scene = Survey(Workspace(ws)).scene()
    ndc = scene.ndc
    depth = 2 * ndc.near / (1 - cells[:, 2])
    world = torch.stack([cells[:, 0] * depth / ndc.sx, cells[:, 1] * depth / ndc.sy, -depth], -1).numpy()
    data = (world - np.asarray(scene.extra["world_from_data"])[:3, 3]) @ np.linalg.inv(
        np.asarray(scene.extra["world_from_data"])[:3, :3]).T
    assert len(points["xyz"]) == len(data) > 0 and points["expert"].max() < m
    scale = float(np.linalg.norm(data.max(0) - data.min(0)))
    assert nearest(points["xyz"], data).max() < 1e-6 * max(1.0, scale)
    assert math.isfinite(scale)
