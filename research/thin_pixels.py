"""PSNR on a procedural scene's thin structure and on the rest of each held-out view, from rendered PNGs.

A pixel counts as thin structure when more than 20% of its 4 x 4 sub-rays first hit one of the scene's capsules
(rods, cable, wire of `make-scene --content thin`), found by the generator's own exact ray casting (objects.json).
A model that skipping cut thin structure from scores low on those pixels and normally elsewhere. Prints one line
per view: `view I: thin PSNR (pixels) other PSNR (pixels)`. research/recipes/vd-thin.sh uses it.

    python research/thin_pixels.py SCENE RENDERS     # SCENE: a Blender-layout make-scene folder; RENDERS: r_I.png
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import imageio.v3 as iio
import torch

from boostnerf_cli.render.rays import image_rays
from boostnerf_cli.scenes.procedural import intersect


def main(scene: Path, renders: Path) -> None:
    objects = json.loads((scene / "objects.json").read_text())["objects"]
    meta = json.loads((scene / "transforms_test.json").read_text())
    capsule = torch.tensor([o["kind"] == "capsule" for o in objects])
    for i, frame in enumerate(meta["frames"]):
        gt = iio.imread(scene / f"{frame['file_path']}.png").astype(float) / 255
        gt = gt[..., :3] * gt[..., 3:] + (1 - gt[..., 3:])  # on the white background
        s = gt.shape[0]
        f = 0.5 * s / math.tan(0.5 * meta["camera_angle_x"])
        o, d = image_rays(torch.tensor(frame["transform_matrix"]).float(), torch.tensor([4 * f, 4 * f, 2 * s, 2 * s]),
                          4 * s, 4 * s)
        t = torch.stack([intersect(obj, o.double(), d.double())[0] for obj in objects])
        first = capsule[t.argmin(0)] & torch.isfinite(t.min(0).values)
        thin = first.double().reshape(s, 4, s, 4).mean((1, 3)).numpy().reshape(-1) > 0.2
        pred = iio.imread(renders / f"r_{i}.png").astype(float)[..., :3] / 255
        err = ((pred - gt) ** 2).mean(-1).reshape(-1)
        print(f"view {i}: thin {_psnr(err, thin)} other {_psnr(err, ~thin)}")


def _psnr(err, mask) -> str:
    return f"{-10 * math.log10(err[mask].mean()):.2f} ({int(mask.sum())} px)" if mask.any() else "-"


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__.strip().splitlines()[-1].strip())
    main(Path(sys.argv[1]), Path(sys.argv[2]))
