"""Issue 17 experiment: would dropping coarse cells that no training view sees make the box agree across layouts?

Writes the thin procedural scene (`make-scene --content thin`, 80 px, 28 train views) in the Blender, nerfstudio
and NSVF layouts, trains the shared coarse geometry (32^3, 300 steps, as tests/test_thin_structures.py) and prints,
per layout, the box `pretrain` draws around the occupied cells, and the box around the occupied cells whose largest
rendering weight over every training ray is at least tau (cells only hidden space or barely visible floaters
occupy would go). docs/results.md, issue 17, records the output.

    python research/visible_box.py OUT
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from boostnerf_cli.recipe import GeometryRecipe
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.render.rays import image_rays
from boostnerf_cli.render.renderer import render_rays
from boostnerf_cli.scenes import load_scene, make_scene
from boostnerf_cli.stages.pretrain import Site, ensure_geometry
from boostnerf_cli.workspace import Workspace


@torch.no_grad()
def max_weight_per_cell(model, occ: OccupancyGrid, scene) -> torch.Tensor:
    """The largest rendering weight any training ray gives a sample in each cell of `occ` (flat, x-major)."""
    settings = scene.render_settings(0.5 * model.voxel_size, occ.bbox, 0.0)
    seen = torch.zeros(occ.occupied.numel())
    tr = scene.splits["train"]
    for i in range(len(tr)):
        o, d = image_rays(tr.poses[i], tr.intrinsics[i], tr.height, tr.width, scene.ndc)
        b = render_rays(model, o, d, settings, occ)
        w, t = b.extras["weights"], b.extras["t"]
        r, s = t.shape
        ray = torch.arange(r)[:, None].expand(r, s).reshape(-1)
        idx = occ.cell_index(o[ray] + t.reshape(-1, 1) * d[ray])
        ok = idx >= 0
        seen.scatter_reduce_(0, idx[ok], w.reshape(-1)[ok].float(), "amax")
    return seen


def main(out: Path) -> None:
    torch.set_num_threads(1)
    for layout in ("blender", "nerfstudio", "nsvf"):
        if not (out / layout).exists():
            make_scene(out / layout, size=80, n_train=28, n_test=4, content="thin", layout=layout)
        scene = load_scene(out / layout, image_size=80)
        ws = Workspace(out / f"ws-{layout}")
        ws.experts_dir.mkdir(parents=True, exist_ok=True)
        geometry = ensure_geometry(Site(ws, scene, "", "cpu"), GeometryRecipe(res=32, iters=300, batch_rays=1024), 0)
        box, occ, model = geometry.box, geometry.occupancy, geometry.model
        seen = max_weight_per_cell(model, occ, scene).reshape(occ.occupied.shape)
        print(f"{layout}: box {[round(v, 2) for v in box.flatten().tolist()]}, occupied {occ.fraction():.3f}")
        for tau in (1e-3, 1e-2):
            vis = OccupancyGrid(occ.occupied & (seen >= tau), occ.bbox)
            vis_box = [round(v, 2) for v in vis.occupied_bbox(1).flatten().tolist()]
            print(f"  seen with weight >= {tau:g}: box {vis_box}, occupied {vis.fraction():.3f}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(Path(sys.argv[1]))
