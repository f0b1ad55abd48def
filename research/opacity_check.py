"""Where a model's opacity disagrees with the views: background learned as surface, surface learned as empty space.

Renders the held-out views of a workspace's model and compares each pixel's rendered opacity (acc) with the
scene's alpha. A transparent pixel (alpha < 0.01) rendered with acc > 0.5 is background made opaque (what a
random training background that ignores a Blender scene's alpha teaches); an opaque pixel (alpha > 0.99, every
pixel of a scene without alpha: LLFF photographs) rendered with acc < 0.5 is a hole, whose colour may still be
right against the background but whose depth reads empty (fern's white ceiling). Prints one JSON line: the
held-out PSNR and both percentages, averaged over the views. docs/datasets.md, "Forward-facing scenes", records
what it measured.

    python research/opacity_check.py WORKSPACE MODEL [--views N] [--device cpu]
"""

from __future__ import annotations

import argparse
import json
import sys

import torch

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.lineage import Survey
from boostnerf_cli.metrics import psnr
from boostnerf_cli.models import ALL_SKIPS, load_model, render_split
from boostnerf_cli.workspace import Workspace

TRANSPARENT, OPAQUE, HALF = 0.01, 0.99, 0.5


def opacity_errors(acc: torch.Tensor, alpha: torch.Tensor | None) -> dict[str, float | None]:
    """Percentages of one view's pixels (acc and alpha flat, alpha None: every pixel opaque): transparent pixels
    rendered opaque (None when the view has none), opaque pixels rendered mostly empty (None when none)."""
    alpha = torch.ones_like(acc) if alpha is None else alpha
    clear, solid = alpha < TRANSPARENT, alpha > OPAQUE
    pct = lambda hit, of: 100.0 * float((hit & of).sum()) / int(of.sum()) if bool(of.any()) else None  # noqa: E731
    return {"background_opaque_pct": pct(acc > HALF, clear), "holes_pct": pct(acc < HALF, solid)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace")
    parser.add_argument("model")
    parser.add_argument("--views", type=int, default=None, help="only the first N held-out views")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    if args.views is not None and args.views < 1:
        print(f"error: --views must be at least 1, got {args.views}", file=sys.stderr)
        return 2
    try:
        ws = Workspace(args.workspace)
        scene = Survey(ws).scene()
        split = scene.split("test")
        model = load_model(ws, args.model, args.device)
        rows = []
        for i, r in enumerate(render_split(model, scene, split, args.device, ALL_SKIPS, args.views)):
            alpha = None if split.alpha is None else split.alpha[i].reshape(-1)
            rows.append({"psnr": psnr(r["rgb"].cpu(), split.images[i]),
                         **opacity_errors(r["acc"].cpu().reshape(-1), alpha)})
    except BoostNerfError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    out: dict[str, object] = {"workspace": args.workspace, "model": args.model, "views": len(rows),
                              "alpha": split.alpha is not None}
    for key in rows[0]:
        values = [row[key] for row in rows if row[key] is not None]
        out[key] = round(sum(values) / len(values), 3) if values else None
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
