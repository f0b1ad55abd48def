"""Trilinear grids against grid_sample in float64; rays, projection and box clipping."""

import math
from dataclasses import replace

import pytest
import torch
import torch.nn.functional as F

from boostnerf_cli.fields import grid as G
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.render.rays import image_rays, intersect_box, pixel_directions, project_points
from boostnerf_cli.render.renderer import sample_rays
from boostnerf_cli.scenes import load_scene

BOX = torch.tensor([[-1.0, -0.5, -2.0], [1.0, 1.5, 0.0]], dtype=torch.float64)


def _grid_sample_ref(table, shape, xyz, bbox):
    """Reference: grid_sample(align_corners=True) on the same lattice, float64."""
    vol = table.T.reshape(1, -1, *shape)  # (1, C, X, Y, Z) -> grid_sample wants (N, C, D, H, W) = (z?..)
    vol = vol.permute(0, 1, 4, 3, 2)  # (1, C, Z, Y, X): W <-> x, H <-> y, D <-> z
    rel = (xyz - bbox[0]) / (bbox[1] - bbox[0]) * 2 - 1
    out = F.grid_sample(vol, rel.view(1, 1, 1, -1, 3), mode="bilinear", align_corners=True)
    return out.view(table.shape[1], -1).T


@pytest.mark.parametrize("channels,shape,n", [(3, (5, 7, 4), 200), (1, (5, 7, 4), 200), (12, (23, 19, 17), 40)])
def test_lookup_matches_grid_sample_forward_and_backward(channels, shape, n):
    """One channel (the density grid's path) and several (the compact path; the (23, 19, 17) grid with
    40 points leaves most rows untouched, whose gradient must be exactly 0)."""
    g = torch.Generator().manual_seed(0)
    table = torch.randn(math.prod(shape), channels, dtype=torch.float64, generator=g, requires_grad=True)
    xyz = BOX[0] + torch.rand(n, 3, dtype=torch.float64, generator=g) * (BOX[1] - BOX[0])
    idx, w = G.corners(xyz, BOX, shape)
    ours = G._Lookup.apply(table, idx, w)
    ref = _grid_sample_ref(table, shape, xyz, BOX)
    assert torch.allclose(ours, ref, atol=1e-12)
    up = torch.randn_like(ours)
    (ga,) = torch.autograd.grad((ours * up).sum(), table)
    (gb,) = torch.autograd.grad((ref * up).sum(), table)
    assert torch.allclose(ga, gb, atol=1e-12)


def test_weights_are_a_partition_of_unity_and_vertices_are_exact():
    shape = (4, 4, 4)
    table = torch.arange(64, dtype=torch.float64)[:, None]
    verts = torch.stack(torch.meshgrid(*[torch.linspace(float(BOX[0, a]), float(BOX[1, a]), 4, dtype=torch.float64)
                                         for a in range(3)], indexing="ij"), -1).reshape(-1, 3)
    idx, w = G.corners(verts, BOX, shape)
    assert torch.allclose(w.sum(-1), torch.ones(64, dtype=torch.float64))
    assert torch.allclose(G.lookup(table, idx, w)[:, 0], table[:, 0])


def test_points_outside_are_clamped_to_the_border():
    shape = (3, 3, 3)
    table = torch.randn(27, 2, dtype=torch.float64)
    far = torch.tensor([[5.0, 5.0, 5.0], [-9.0, -9.0, -9.0]], dtype=torch.float64)
    idx, w = G.corners(far, BOX, shape)
    out = G.lookup(table, idx, w)
    assert torch.allclose(out[0], table[26]) and torch.allclose(out[1], table[0])


def test_resample_reproduces_a_linear_function():
    shape, new_shape = (4, 5, 6), (7, 3, 9)
    verts = lambda s, b: torch.stack(torch.meshgrid(*[torch.linspace(float(b[0, a]), float(b[1, a]), s[a],  # noqa: E731
                                                       dtype=torch.float64) for a in range(3)], indexing="ij"),
                                     -1).reshape(-1, 3)
    f = lambda p: (p @ torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64))[:, None] + 0.3  # noqa: E731
    inner = torch.tensor([[-0.5, 0.0, -1.5], [0.5, 1.0, -0.5]], dtype=torch.float64)
    out = G.resample(f(verts(shape, BOX)), shape, BOX, new_shape, inner)
    assert torch.allclose(out, f(verts(new_shape, inner)), atol=1e-10)


def test_lattice_shape_has_about_n_voxels_and_isotropic_spacing():
    box = torch.tensor([[0.0, 0.0, 0.0], [2.0, 1.0, 1.0]])
    shape = G.lattice_shape(box, 16000)
    assert abs(shape[0] * shape[1] * shape[2] - 16000) / 16000 < 0.1
    assert abs(shape[0] / shape[1] - 2.0) < 0.1


def test_a_box_flatter_than_its_lattice_keeps_about_n_voxels():
    """A flat data.bbox ([3, 3, 1e-6]) with the 8^3 geometry grid gave 2.7 M vertices (466 MB, like a hang), and a
    camera box stretched by a wild cx one of 1e9 x 3 x 3: the sides held at 2 now leave the budget to the others."""
    flat = G.lattice_shape(torch.tensor([[-1.5, -1.5, 0.0], [1.5, 1.5, 1e-6]]), 512)
    assert flat == (16, 16, 2)
    assert G.lattice_shape(torch.tensor([[0.0, 0.0, 0.0], [1e9, 3.0, 3.0]]), 512) == (128, 2, 2)
    for box in ([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], [[-1.3, -1.2, -0.4], [1.2, 1.3, 1.1]]):  # unchanged
        size = torch.tensor(box, dtype=torch.float64).diff(dim=0)[0]
        plain = (size / (size.prod() / 160**3) ** (1 / 3)).round().long().tolist()
        assert list(G.lattice_shape(torch.tensor(box), 160**3)) == plain


def test_a_budget_of_a_few_voxels_gives_every_side_two_vertices():
    """`--res 2` or `--res 3` (growth starts such an expert at 4 or 3 voxels) and `--res 1` on an elongated box ended
    in a ZeroDivisionError: once the sides left free came out thin too, every side was held and none was left to
    share the budget."""
    for box in ([[-1.096, -1.048, -1.049], [1.056, 1.07, 0.328]], [[0.0, 0.0, 0.0], [4.0, 1.0, 0.5]],
                [[0.0, 0.0, 0.0], [10.0, 1.0, 1.0]], [[0.0, 0.0, 0.0], [3.0, 3.0, 0.3]]):
        for n in (1, 2, 3, 4, 8):
            assert G.lattice_shape(torch.tensor(box), n) == (2, 2, 2), (box, n)
    assert G.lattice_shape(torch.tensor([[-1.096, -1.048, -1.049], [1.056, 1.07, 0.328]]), 27) == (3, 3, 2)


def test_rays_and_projection_are_inverse():
    pose = torch.eye(4)
    pose[:3, 3] = torch.tensor([0.3, -0.2, 4.0])
    intr = torch.tensor([50.0, 55.0, 16.0, 12.0])
    o, d = image_rays(pose, intr, 24, 32)
    assert o.shape == (24 * 32, 3) and torch.allclose(d.norm(dim=-1), torch.ones(24 * 32))
    pts = o + 3.0 * d
    uv, depth = project_points(pts, pose, intr)
    v, u = torch.meshgrid(torch.arange(24) + 0.5, torch.arange(32) + 0.5, indexing="ij")
    assert torch.allclose(uv, torch.stack([u.reshape(-1), v.reshape(-1)], -1), atol=1e-3)
    assert (depth > 0).all()
    centre = pixel_directions(24, 32, intr)[12, 16]
    assert torch.allclose(centre, torch.tensor([0.5 / 50.0, -0.5 / 55.0, -1.0]))


def test_intersect_box_handles_misses_parallel_rays_and_near_far():
    box = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    o = torch.tensor([[0.0, 0.0, 5.0], [3.0, 3.0, 5.0], [0.5, 0.0, 5.0], [0.0, 0.0, 0.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    t0, t1, hit = intersect_box(o, d, box, near=0.0, far=100.0)
    assert hit.tolist() == [True, False, True, True]
    assert torch.allclose(t0[0], torch.tensor(4.0)) and torch.allclose(t1[0], torch.tensor(6.0))
    assert torch.allclose(t0[3], torch.tensor(0.0)) and torch.allclose(t1[3], torch.tensor(1.0))
    assert torch.isfinite(t0[hit]).all() and torch.isfinite(t1[hit]).all()
    _, _, hit = intersect_box(o, d, box, near=0.0, far=3.0)
    assert not hit[0]


def test_occupancy_lookup_matches_a_per_point_reference_on_faces_edges_and_outside():
    """Cells by floor((x - lo) / size * res); the box includes its faces (max face -> last cell)."""
    g = torch.Generator().manual_seed(3)
    shape = (5, 3, 7)
    occ = torch.rand(shape, generator=g) > 0.5
    box = torch.tensor([[-1.0, -1.2, -0.9], [1.1, 1.3, 0.8]])
    grid = OccupancyGrid(occ, box)
    pts = box[0] + (torch.rand(4000, 3, generator=g) * 1.4 - 0.2) * (box[1] - box[0])
    for a in range(3):  # points exactly on each min and max face, and just outside them
        pts[a * 200 : a * 200 + 50, a] = box[0, a]
        pts[a * 200 + 50 : a * 200 + 100, a] = box[1, a]
        pts[a * 200 + 100 : a * 200 + 150, a] = box[1, a] + 1e-4
        pts[a * 200 + 150 : a * 200 + 200, a] = box[0, a] - 1e-4

    def reference(p):
        rel = [(float(p[a]) - float(box[0, a])) / (float(box[1, a]) - float(box[0, a])) for a in range(3)]
        if not all(0.0 <= r <= 1.0 for r in rel):
            return False
        return bool(occ[tuple(min(int(math.floor(r * n)), n - 1) for r, n in zip(rel, shape))])

    got = grid(pts)
    want = torch.tensor([reference(p) for p in pts])
    assert torch.equal(got, want)
    assert grid(torch.zeros(0, 3)).shape == (0,)


@pytest.mark.parametrize("at_once", [False, True])
def test_a_grid_of_more_than_2_to_the_24_cells_looks_up_the_right_cell(at_once, monkeypatch):
    """A grid whose padded rows pass 2^24 (a paper-sized mixture's skip table: 255^3 and up) numbers them in float64:
    float32 sums of its strides round to a neighbouring row. Checked against the exact row, by both lookups, axis by
    axis and over (N, 3) at once, with the occupancy read per point."""
    from boostnerf_cli.fields import grid as G

    if at_once:
        monkeypatch.setattr(G, "by_axis", lambda t: False)
    g = torch.Generator().manual_seed(9)
    shape = (300, 260, 230)  # 302 * 262 * 232 padded rows: 18.4M > 2^24
    occ = torch.rand(shape, generator=g) > 0.5
    box = torch.tensor([[-1.0, -0.5, 0.0], [2.0, 1.5, 1.0]])
    grid = OccupancyGrid(occ, box)
    pts = box[0] + torch.rand(100000, 3, generator=g) * (box[1] - box[0])
    cell = ((pts - box[0]) / (box[1] - box[0]) * torch.tensor(shape)).floor().long()
    cell = torch.minimum(cell, torch.tensor(shape) - 1)
    padded = [n + 2 for n in shape]
    want = (cell[:, 0] + 1) * padded[1] * padded[2] + (cell[:, 1] + 1) * padded[2] + cell[:, 2] + 1
    assert torch.equal(grid.padded_rows(pts), want) and torch.equal(grid.padded_rows_within(pts), want)
    occupied = occ[cell[:, 0], cell[:, 1], cell[:, 2]]
    assert torch.equal(grid(pts), occupied) and torch.equal(grid.within(pts), occupied)


def test_occupancy_grid_lookup_and_bbox():
    occ = torch.zeros(4, 4, 4, dtype=torch.bool)
    occ[1, 2, 3] = True
    grid = OccupancyGrid(occ, torch.tensor([[0.0, 0.0, 0.0], [4.0, 4.0, 4.0]]))
    pts = torch.tensor([[1.5, 2.5, 3.5], [0.5, 0.5, 0.5], [9.0, 2.5, 3.5]])
    assert grid(pts).tolist() == [True, False, False]
    assert torch.allclose(grid.occupied_bbox(margin_cells=0), torch.tensor([[1.0, 2.0, 3.0], [2.0, 3.0, 4.0]]))


def test_cell_index_names_the_cell_the_occupancy_lookup_reads():
    """OccupancyGrid.cell_index and the lookup share one arithmetic: the same cell for points inside, on the
    faces (the max face in the last cell) and -1 outside (the lookup's empty border)."""
    from boostnerf_cli.render.occupancy import OccupancyGrid

    g = torch.Generator().manual_seed(3)
    bbox = torch.tensor([[-1.0, -0.5, 0.0], [1.0, 0.7, 2.0]])
    grid = OccupancyGrid(torch.rand(5, 4, 6, generator=g) > 0.5, bbox)
    pts = bbox[0] + (torch.rand(4000, 3, generator=g) * 1.4 - 0.2) * (bbox[1] - bbox[0])
    faces = bbox[0] + torch.randint(0, 2, (300, 3), generator=g) * (bbox[1] - bbox[0])
    pts = torch.cat([pts, faces, bbox])
    idx = grid.cell_index(pts)
    full = OccupancyGrid(torch.ones(5, 4, 6, dtype=torch.bool), bbox)
    assert torch.equal(idx >= 0, full(pts))  # inside exactly where the lookup finds a cell
    assert bool((idx[:4000] >= 0).any()) and bool((idx[:4000] < 0).any()) and bool((idx[4000:] >= 0).all())
    assert torch.equal(grid(pts), (idx >= 0) & grid.occupied.reshape(-1)[idx.clamp_min(0)])
    centres = grid.cell_centers()
    assert torch.equal(grid.cell_index(centres), torch.arange(5 * 4 * 6))  # [x, y, z] order


def test_a_model_samples_at_its_own_step_however_many_steps_its_box_holds(tiny_scene):
    """A paper-size expert (384^3 at step ratio 0.5) needs ~1,330 samples across its box's diagonal. The renderer
    lengthened the step of every ray of a batch (a whole chunk of an image) to fit 1,024 samples, silently, by up to
    1.3x; a scene's settings now take as many samples as the model's box holds at its step, as DVGO does."""
    scene = load_scene(tiny_scene)
    bbox = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    step = 0.5 * 2.0 / 384  # half a voxel of a 384^3 grid over the box
    settings = scene.render_settings(step, bbox)
    corner = torch.tensor([[-1.5, -1.5, -1.5]])  # one ray along the box's diagonal, from outside it
    direction = torch.nn.functional.normalize(torch.ones(1, 3), dim=-1)
    t, valid, _, used = sample_rays(corner, direction, replace(settings, near=0.0, far=10.0), jitter=False)
    assert used == step
    assert abs(int(valid.sum()) - 2 * math.sqrt(3) / step) <= 1 and int(valid.sum()) > 1024


@pytest.mark.parametrize("static", [False, True], ids=["dynamic", "static"])
def test_the_cpu_renderer_samples_and_tests_only_what_its_rays_reach(static):
    """A dynamic packer (the CPU's) gives a batch the sample slots its longest ray needs, not the box diagonal's, and
    tests the occupancy of the samples inside the box only: rendering lego on the CPU took 1.5-1.8x as long while
    every slot was evaluated. A static packer (a GPU's) keeps the diagonal's slots and tests every slot, so nothing
    waits for the device. The samples themselves, and so the image, are the same."""
    from boostnerf_cli.render.packing import DYNAMIC, Budgets
    from boostnerf_cli.render.renderer import RenderSettings, render_rays

    box = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    settings = RenderSettings(step=0.02, near=0.0, far=10.0, bbox=box, color_threshold=0.0)
    slots, step = settings.sampling
    origins = torch.tensor([[0.0, 0.0, 3.0], [0.5, 0.2, 3.0]])  # straight down through the box: 2 units of it each
    dirs = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    tested = []

    def occupancy(xyz):
        tested.append(xyz.shape[0])
        return xyz[:, 0] < 0.25  # the second ray's samples are all skipped

    class Field:
        def density(self, xyz):
            return torch.full(xyz.shape[:1], 5.0)

        def color(self, xyz, dirs):
            return torch.full((xyz.shape[0], 3), 0.5)

    bundle = render_rays(Field(), origins, dirs, settings, occupancy, packer=Budgets() if static else DYNAMIC)
    inside = math.ceil(2.0 / step)  # each ray's samples in the box
    s = bundle.extras["t"].shape[1]
    assert s == (slots if static else inside) and slots > 1.5 * inside
    assert tested == [2 * s] if static else tested == [2 * inside]
    assert bundle.acc[0] > 0.99 and bundle.acc[1] == 0.0


@pytest.mark.parametrize("kind", ["expert", "mixture", "unbounded"])
def test_packed_compositing_renders_what_padded_compositing_does(kind):
    """Rendering on the CPU composites over the kept samples only (`render_rays_packed`): the colour, depth and
    opacity of padded compositing over every slot (`render_rays`), to float32 rounding, and the same sample counts,
    for an expert with its occupancy grid, a Top-2 mixture with its filter, and a contracted (unbounded) scene."""
    from helpers import TOY_BOX, toy_experts, toy_mixture

    from boostnerf_cli.render.contraction import Contraction
    from boostnerf_cli.render.renderer import RenderSettings, render_rays, render_rays_packed

    g = torch.Generator().manual_seed(0)
    origins = torch.tensor([0.0, 0.0, 2.5]) + 0.3 * torch.randn(300, 3, generator=g)
    dirs = F.normalize(torch.tensor([0.0, 0.0, -1.0]) + 0.4 * torch.randn(300, 3, generator=g), dim=-1)
    if kind == "mixture":
        field = toy_mixture(k=2, seed=1).for_rendering()
        skip = field.skip
        settings = RenderSettings(step=0.05, near=0.5, far=5.0, bbox=TOY_BOX)
    else:
        field = toy_experts(1, seed=2)[0]
        with torch.no_grad():
            field.density_table.normal_(0.0, 3.0)
        skip = OccupancyGrid.from_density(field.density, TOY_BOX, (8, 8, 8), 0.05, 1e-3)
        settings = RenderSettings(step=0.05, near=0.5, far=5.0, bbox=TOY_BOX)
        if kind == "unbounded":
            c = Contraction((0.0, 0.0, 0.0), 0.5, 50.0)
            settings = RenderSettings(step=0.05, near=0.01, far=c.far, bbox=c.box(), contraction=c)
            skip = None
    with torch.no_grad():
        padded = render_rays(field, origins, dirs, settings, skip)
        packed = render_rays_packed(field, origins, dirs, settings, skip)
    assert int(packed.n_samples) == int(padded.n_samples) > 0 and int(packed.n_color) == int(padded.n_color) > 0
    for a, b in ((packed.color, padded.color), (packed.depth, padded.depth), (packed.acc, padded.acc)):
        assert torch.allclose(a, b, atol=2e-5, rtol=1e-5), float((a - b).abs().max())
    assert float(padded.acc.max()) > 0.2  # rays that meet something


@pytest.mark.parametrize("case", ["outside", "inside", "near", "ndc", "chords"])
def test_samples_made_as_lists_are_the_valid_slots_of_the_grid_bit_for_bit(case):
    """`sample_list` (what rendering on the CPU samples a bounded scene with) gives exactly the samples inside the box
    that `sample_rays` marks valid: the same rays, distances and points to the last bit, in the same order, for rays
    that miss the box, graze it, start inside it or are cut by the near plane, and for one camera's shared origin."""
    from helpers import TOY_BOX

    from boostnerf_cli.render.renderer import RenderSettings, sample_list, sample_rays

    g = torch.Generator().manual_seed(5)
    n = 400
    if case == "inside":  # origins inside the box: every ray leaves through a face
        origins = 0.5 * torch.randn(n, 3, generator=g).clamp(-1, 1)
    elif case == "ndc":  # rays as NDC makes them: from the near plane z = -1, unnormalised, towards +z
        origins = torch.cat([2 * torch.rand(n, 2, generator=g) - 1, -torch.ones(n, 1)], -1)
    else:  # one camera: a shared origin, expanded as image_rays makes it
        origins = torch.tensor([0.3, -0.2, 2.5]).expand(n, 3)
    dirs = F.normalize(torch.tensor([0.0, 0.0, -1.0]) + 0.6 * torch.randn(n, 3, generator=g), dim=-1)
    dirs[:4] = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])  # axis-parallel
    near = 2.2 if case == "near" else 0.1
    settings = RenderSettings(step=0.037, near=near, far=6.0, bbox=TOY_BOX)
    if case == "chords":  # chords near a whole number and a half of steps: where the count's estimate is off by one
        origins = torch.cat([1.8 * torch.rand(n, 2, generator=g) - 0.9, 1 + 3 * torch.rand(n, 1, generator=g)], -1)
        dirs = torch.tensor([0.0, 0.0, -1.0]).expand(n, 3)
        settings = RenderSettings(step=2 / 7.5, near=0.0, far=6.0, bbox=torch.tensor([[-1.0] * 3, [1.0] * 3]))
    if case == "ndc":
        dirs = torch.cat([0.3 * torch.randn(n, 2, generator=g), 2 * torch.ones(n, 1)], -1)
        box = torch.tensor([[-1.5, -1.5, -1.0], [1.5, 1.5, 1.0]])
        settings = RenderSettings(step=0.004, near=0.0, far=1.0, bbox=box)
    t, valid, xyz, step = sample_rays(origins, dirs, settings, jitter=False, fit=True)
    ray, tl, xl, step_l = sample_list(origins, dirs, settings)
    rows = valid.reshape(-1).nonzero().squeeze(-1)
    assert step_l == step and len(rows) > 1000 and (~valid).any()
    if case == "chords":  # the first estimate of some ray's count is wrong, and corrected
        t0, t1, hit = intersect_box(origins, dirs, settings.bbox, settings.near, settings.far)
        guess = torch.ceil(torch.where(hit, t1 - t0, torch.zeros_like(t0)) / step - 0.5).clamp(0, t.shape[1])
        assert (guess.long() != valid.sum(1)).any()
    assert torch.equal(ray, rows // t.shape[1])
    assert torch.equal(tl, t.reshape(-1)[rows]) and torch.equal(xl, xyz.reshape(-1, 3)[rows])


def test_a_grown_grid_sets_every_cell_within_its_reach_of_an_occupied_one():
    """`OccupancyGrid.grown(reach)` sets exactly the cells within ceil(reach / cell) + 1 cells of an occupied one along
    every axis (a box window: a max-pool over it), for reaches shorter and longer than the grid, on uneven cells."""
    g = torch.Generator().manual_seed(2)
    box = torch.tensor([[-1.0, -0.5, 0.0], [1.0, 0.5, 3.0]])
    shape = (13, 7, 30)
    occupied = torch.rand(shape, generator=g) < 0.01
    grid = OccupancyGrid(occupied, box)
    cell = (box[1] - box[0]) / torch.tensor(shape)
    for reach in (0.0, 0.05, 0.3, 1.1, 5.0):
        k = [min(n, math.ceil(reach / float(c)) + 1) for n, c in zip(shape, cell)]
        want = F.max_pool3d(occupied[None, None].float(), tuple(2 * a + 1 for a in k), 1, tuple(k))[0, 0] > 0
        grown = grid.grown(reach)
        assert torch.equal(grown.occupied, want), reach
        assert grid.grown(reach) is grown and torch.equal(grown.bbox, grid.bbox)
    assert not grid.grown(0.3).occupied.all() and grid.grown(5.0).occupied.all()


@pytest.mark.parametrize("case", ["camera", "inside", "ndc", "thin", "small", "empty"])
def test_samples_made_in_runs_are_every_sample_the_skip_may_keep_bit_for_bit(case, monkeypatch):
    """`sample_list` given the cells a skip may keep makes its slots in runs and leaves out the runs that reach no such
    cell (grown by half a run, `OccupancyGrid.grown`): what it makes is a subsequence of the plain samples, the same
    rays, distances and points to the bit, that holds every sample the skip keeps, and leaves most of the empty space
    out; for a sparse grid of scattered cells, a single thin wall one cell thick (runs cross it between their middles),
    rays from inside the box, NDC's unnormalised directions, a grid over a smaller box than the render box (a run's
    middle outside it is looked up clamped into it) and a grid with no occupied cell (no sample at all)."""
    from helpers import TOY_BOX

    from boostnerf_cli.render import renderer as R

    g = torch.Generator().manual_seed(11)
    n = 2000
    box = TOY_BOX
    if case == "inside":
        origins = 0.5 * torch.randn(n, 3, generator=g).clamp(-1, 1)
    elif case == "ndc":
        origins = torch.cat([2 * torch.rand(n, 2, generator=g) - 1, -torch.ones(n, 1)], -1)
        box = torch.tensor([[-1.5, -1.5, -1.0], [1.5, 1.5, 1.0]])
    else:
        origins = torch.tensor([0.3, -0.2, 2.5]).expand(n, 3)
    dirs = F.normalize(torch.tensor([0.0, 0.0, -1.0]) + 0.6 * torch.randn(n, 3, generator=g), dim=-1)
    step = 0.021
    if case == "ndc":
        dirs = torch.cat([0.3 * torch.randn(n, 2, generator=g), 2 * torch.ones(n, 1)], -1)
        step = 0.004
    settings = R.RenderSettings(step=step, near=0.1, far=6.0, bbox=box)
    shape = (40, 40, 40)
    grid_box = box
    if case == "thin":  # one wall of cells across the rays: a run's middle lies at most half a run from it
        occupied = torch.zeros(shape, dtype=torch.bool)
        occupied[:, :, 17] = True
    elif case == "small":  # the grid covers the middle of the render box; its cells at the faces are occupied
        grid_box = 0.4 * box
        occupied = torch.rand(shape, generator=g) < 0.002
        occupied[0], occupied[-1], occupied[:, :, 0] = True, True, True
    else:
        occupied = torch.rand(shape, generator=g) < (0.0 if case == "empty" else 0.0015)
    grid = OccupancyGrid(occupied, grid_box)
    monkeypatch.setattr(R, "SPARSE", 1.0)  # in runs whatever share of the box the grown cells fill
    ray, t, xyz, _ = R.sample_list(origins, dirs, settings)
    ray_r, t_r, xyz_r, _ = R.sample_list(origins, dirs, settings, grid)
    key = ray * 10**6 + torch.round((t - t.min()) / settings.sampling[1]).long()  # a sample's (ray, slot)
    key_r = ray_r * 10**6 + torch.round((t_r - t.min()) / settings.sampling[1]).long()
    at = torch.searchsorted(key, key_r)  # runs keep the plain order: each made sample is found among the plain ones
    assert torch.equal(key[at], key_r) and bool((at[1:] > at[:-1]).all())
    assert torch.equal(ray[at], ray_r) and torch.equal(t[at], t_r) and torch.equal(xyz[at], xyz_r)
    if case == "empty":
        assert len(ray_r) == len(t_r) == len(xyz_r) == 0 and len(ray) > 1000
        return
    kept = grid(xyz).nonzero().squeeze(-1)  # outside the grid's box: not kept
    assert len(kept) > 30  # the rays meet the cells
    assert bool(torch.isin(key[kept], key_r).all())  # every sample the grid keeps is made
    # and most of the empty space is not (but around a smaller grid whose faces are occupied: a run's middle outside it
    # counts in the cell at the face)
    assert len(ray_r) < (1.0 if case == "small" else 0.5) * len(ray)


def test_a_one_channel_blend_without_gradient_matches_the_corner_lookup():
    """`grid.blend` (a one-channel table without gradients: rendering's densities, V_D) gives what blending the 8
    listed corners gives, to float32 rounding, inside the box, on its faces and vertices and clamped outside it; with a
    gradient, or several channels, it is the corner lookup itself, bit for bit."""
    from boostnerf_cli.fields import grid as G

    g = torch.Generator().manual_seed(3)
    shape, bbox = (7, 5, 9), torch.tensor([[-1.0, -0.5, 0.0], [2.0, 0.5, 1.5]])
    table = torch.randn(7 * 5 * 9, 1, generator=g) * 4
    inner = bbox[0] + torch.rand(500, 3, generator=g) * (bbox[1] - bbox[0])
    outer = bbox[0] - 0.5 + torch.rand(200, 3, generator=g) * (bbox[1] - bbox[0] + 1.0)  # many outside the box
    vertices = G.lattice_points(bbox, shape)
    xyz = torch.cat([inner, outer, vertices, bbox])
    want = G.lookup(table, *G.corners(xyz, bbox, shape))
    sampled, grid_sample = [], F.grid_sample
    with pytest.MonkeyPatch.context() as m:  # the blend without gradients goes through grid_sample
        m.setattr(G.F, "grid_sample", lambda *a, **k: sampled.append(1) or grid_sample(*a, **k))
        got = G.blend(table, xyz, bbox, shape)
    assert sampled == [1]
    assert got.shape == want.shape and torch.allclose(got, want, atol=1e-5, rtol=1e-5), float((got - want).abs().max())
    assert torch.allclose(G.blend(table, vertices, bbox, shape), table, atol=1e-5)  # exact at the vertices
    three = torch.randn(7 * 5 * 9, 3, generator=g)
    assert torch.equal(G.blend(three, xyz, bbox, shape), G.lookup(three, *G.corners(xyz, bbox, shape)))
    trained = table.clone().requires_grad_()
    assert torch.equal(G.blend(trained, xyz, bbox, shape).detach(), want)


@pytest.mark.parametrize("n", [1, 1023, 1024, 2049, 5003])
def test_a_blend_shared_among_threads_is_the_one_threads_bit_for_bit(n):
    """On the CPU `grid.blend` hands grid_sample one part of the points per thread (grid_sample shares out its batch,
    not its points), padded to equal parts: the same values, to the bit, as on one thread, however many points."""
    from boostnerf_cli.fields import grid as G

    g = torch.Generator().manual_seed(4)
    shape, bbox = (9, 6, 8), torch.tensor([[-1.0, -0.5, 0.0], [2.0, 0.5, 1.5]])
    table = torch.randn(9 * 6 * 8, 1, generator=g)
    xyz = bbox[0] - 0.2 + torch.rand(n, 3, generator=g) * (bbox[1] - bbox[0] + 0.4)
    threads = torch.get_num_threads()
    batches, grid_sample = [], F.grid_sample
    try:
        torch.set_num_threads(1)
        one = G.blend(table, xyz, bbox, shape)
        torch.set_num_threads(3)
        with pytest.MonkeyPatch.context() as m:
            m.setattr(G.F, "grid_sample", lambda v, q, **k: batches.append(q.shape[0]) or grid_sample(v, q, **k))
            three = G.blend(table, xyz, bbox, shape)
    finally:
        torch.set_num_threads(threads)
    assert batches == [min(3, max(1, n // 1024))]
    assert three.shape == (n, 1) and torch.equal(three, one)


@pytest.mark.parametrize("dtype,box_dtype", [(torch.float32, torch.float32), (torch.float64, torch.float64),
                                             (torch.float32, torch.float64), (torch.float16, torch.float32)])
def test_coordinates_axis_by_axis_are_the_broadcast_arithmetic_bit_for_bit(dtype, box_dtype, monkeypatch):
    """Point arithmetic goes axis by axis on the CPU (`grid.by_axis`: a third of the time there) and over (N, 3) at
    once on a GPU: the corners and weights, the blend, the box test, the gate cells' index and the occupancy grid's
    rows and cells come out the same, to the bit, either way, on faces, vertices and outside too, and in the same
    precision where the box's is wider than the points'."""
    from boostnerf_cli.fields import grid as G
    from boostnerf_cli.moe import cells as C
    from boostnerf_cli.render.occupancy import OccupancyGrid

    g = torch.Generator().manual_seed(6)
    bbox = torch.tensor([[-1.3, -0.2, 0.7], [0.9, 2.1, 1.1]], dtype=box_dtype)
    shape = (7, 11, 5)
    xyz = bbox[0] - 0.5 + torch.rand(1200, 3, generator=g, dtype=box_dtype) * (bbox[1] - bbox[0] + 1.0)
    xyz[:100, 1] = bbox[1, 1] + torch.linspace(-1e-3, 1e-3, 100, dtype=box_dtype)  # on and about a face
    xyz = torch.cat([xyz, G.lattice_points(bbox, shape)]).to(dtype)
    inside = ((xyz >= bbox[0]) & (xyz <= bbox[1])).all(-1)
    table = torch.randn(7 * 11 * 5, 1, generator=g, dtype=box_dtype)
    grid = OccupancyGrid(torch.rand(6, 4, 9, generator=g) > 0.5, bbox)
    scale = torch.tensor([7.0, 11.0, 5.0], dtype=dtype)

    def all_of():
        return [*G.axis_coords(xyz, bbox, scale), *G.axis_coords(xyz, bbox, 2.0), G.inside_box(xyz, bbox),
                *G.corners(xyz, bbox, shape), G.blend(table, xyz, bbox, shape), C.cell_index(xyz, bbox, shape),
                grid.padded_rows(xyz), grid.padded_rows_within(xyz[inside]), grid.cell_index(xyz[None]), grid(xyz)]

    assert G.by_axis(xyz)  # the CPU's way
    by_axis = all_of()
    monkeypatch.setattr(G, "by_axis", lambda t: False)  # a GPU's way, on the CPU
    at_once = all_of()
    for a, b in zip(by_axis, at_once, strict=True):
        assert a.shape == b.shape and a.dtype == b.dtype and torch.equal(a, b)
    assert torch.equal(torch.stack(by_axis[:3], -1), (xyz - bbox[0]) / (bbox[1] - bbox[0]) * scale)
    assert torch.equal(by_axis[6], inside)


def test_the_lookup_for_points_inside_the_box_agrees_with_the_general_one():
    """`OccupancyGrid.within` (and `SkipCells.within`), the renderer's lookup for its samples inside the box, gives
    `__call__`'s answer for every point inside the box, its faces and corners included (a point on the max face in the
    last cell), and counts a point just past a face in the cell at that face, where `__call__` calls it empty."""
    from boostnerf_cli.moe.cells import MIXED, SkipCells

    g = torch.Generator().manual_seed(2)
    bbox = torch.tensor([[-0.7, -1.2, -0.5], [0.6, 1.1, 1.0]])
    grid = OccupancyGrid(torch.rand(5, 9, 4, generator=g) > 0.4, bbox)
    inside = bbox[0] + torch.rand(3000, 3, generator=g) * (bbox[1] - bbox[0])
    corners = torch.stack(torch.meshgrid(*bbox.T, indexing="ij"), -1).reshape(-1, 3)  # the box's 8 corners
    faces = inside.clone()
    faces[:, 0] = torch.where(torch.rand(3000, generator=g) < 0.5, bbox[0, 0], bbox[1, 0])
    xyz = torch.cat([inside, corners, faces])
    assert torch.equal(grid.within(xyz), grid(xyz)) and grid(xyz).any() and not grid(xyz).all()
    past = torch.tensor([[float(bbox[1, 0]) + 1e-6, 0.0, 0.2]])  # just past the max x face: rounding's kind of miss
    one = torch.zeros(5, 9, 4, dtype=torch.bool)
    one[4, 4, 1] = True  # the face cell it lies against: x the last, y (0 + 1.2) / 2.3 * 9, z (0.2 + 0.5) / 1.5 * 4
    grid = OccupancyGrid(one, bbox)
    assert grid(torch.tensor([[0.59, 0.0, 0.2]]))[0]  # that cell, from inside
    assert not grid(past)[0] and grid.within(past)[0]
    state = torch.randint(0, 3, (5, 9, 4), generator=g, dtype=torch.uint8)
    state[0], state[-1], state[:, 0], state[:, -1], state[:, :, 0], state[:, :, -1] = (MIXED,) * 6
    cells = SkipCells(state, bbox)
    assert torch.equal(cells.within(xyz), cells(xyz))
    assert cells.within(past)[0] == MIXED and cells(past)[0] == 0  # the face cell: tested, never passed unseen


def test_the_renderer_tests_samples_outside_a_grid_smaller_than_its_box_as_empty():
    """`renderer.passing` looks samples up by `within` only where the grid's box holds the render box: a grid over a
    smaller box calls a sample between the two boxes empty, as `__call__` does, not the face cell beside it."""
    from boostnerf_cli.render.renderer import passing

    full = torch.ones(4, 4, 4, dtype=torch.bool)
    small = OccupancyGrid(full, torch.tensor([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]]))
    box = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.8, 0.0, 0.0], [-0.9, 0.2, 0.1]])  # inside; two past the grid's faces
    assert passing(small, pts, box).tolist() == [True, False, False] == small(pts).tolist()
    assert small.within(pts).tolist() == [True, True, True]  # what `within` would have said
    assert passing(small, pts[:1], small.bbox).tolist() == [True]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16])
def test_direction_encoding_on_the_cpu_is_the_broadcast_product_bit_for_bit(dtype, monkeypatch):
    """The encoding of directions and features multiplies them by each power of two on its own on the CPU (a product
    broadcast along the short last axis runs element by element there) and as one broadcast product on a GPU: the
    same numbers to the bit, signed zeros and infinities included, for 3 channels and for many."""
    from boostnerf_cli.fields import grid as G
    from boostnerf_cli.fields.dvgo import direction_encoding

    g = torch.Generator().manual_seed(9)
    for channels in (3, 27):
        x = (3 * torch.randn(500, channels, generator=g)).to(dtype)
        x[::7] = -0.0
        x[3, 0], x[4, 1] = float("inf"), float("-inf")
        assert G.by_axis(x)  # the CPU's way
        cpu = direction_encoding(x, 4)
        with monkeypatch.context() as m:
            m.setattr(G, "by_axis", lambda t: False)  # a GPU's way, on the CPU
            gpu = direction_encoding(x, 4)
        assert cpu.shape == (500, 9 * channels) and cpu.dtype == dtype
        assert torch.equal(cpu.nan_to_num(5.0), gpu.nan_to_num(5.0))
        assert torch.equal(torch.signbit(cpu), torch.signbit(gpu))


@pytest.mark.parametrize("n_freq", [2, 4])
def test_direction_encoding_gradients_are_the_broadcast_products_bit_for_bit(n_freq, monkeypatch):
    """An encoded input that needs a gradient (TensoRF's appearance features in training) gets the gradient of the
    one broadcast product on the CPU too: summed over the frequencies in its order, not frequency by frequency."""
    from boostnerf_cli.fields import grid as G
    from boostnerf_cli.fields.dvgo import direction_encoding

    g = torch.Generator().manual_seed(4)
    x = torch.randn(4000, 3, generator=g)
    up = torch.randn(4000, 9 * 3 if n_freq == 4 else 15, generator=g)

    def grad():
        leaf = x.clone().requires_grad_()
        return torch.autograd.grad((direction_encoding(leaf, n_freq) * up).sum(), leaf)[0]

    cpu = grad()
    with monkeypatch.context() as m:
        m.setattr(G, "by_axis", lambda t: False)
        gpu = grad()
    assert torch.equal(cpu, gpu)


@pytest.mark.filterwarnings("ignore:Converting a tensor with requires_grad")  # sample_rays' fit reads the chords
def test_samples_made_as_lists_carry_the_gradient_of_their_rays():
    """`sample_list` on rays that need a gradient makes points that carry it, the gradient `sample_rays`' valid points
    give."""
    from helpers import TOY_BOX

    from boostnerf_cli.render.renderer import RenderSettings, sample_list, sample_rays

    g = torch.Generator().manual_seed(2)
    origins = (torch.tensor([0.3, -0.2, 2.5]) + 0.1 * torch.randn(50, 3, generator=g)).requires_grad_()
    dirs = F.normalize(torch.tensor([0.0, 0.0, -1.0]) + 0.3 * torch.randn(50, 3, generator=g), dim=-1)
    settings = RenderSettings(step=0.05, near=0.1, far=6.0, bbox=TOY_BOX)
    ray, t, xyz, _ = sample_list(origins, dirs, settings)
    _, valid, ref, _ = sample_rays(origins, dirs, settings, jitter=False, fit=True)
    assert len(ray) > 100 and xyz.requires_grad and torch.equal(xyz, ref[valid])
    up = torch.randn(xyz.shape, generator=g)
    (grad,) = torch.autograd.grad((xyz * up).sum(), origins)
    (want,) = torch.autograd.grad((ref[valid] * up).sum(), origins)
    assert torch.allclose(grad, want, rtol=1e-5, atol=1e-5)
