"""One frame: what a camera sees of a model as a `Look` (one of `MODES`), rendered (`picture`) and timed, with its
GFLOPs when counted (`frame`)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from boostnerf_cli.costs import gflops_of
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.images import to_uint8
from boostnerf_cli.models import ALL_SKIPS, LoadedModel, Skips
from boostnerf_cli.render.packing import DYNAMIC, Packer, packer_for
from boostnerf_cli.render.renderer import Camera, render_image
from boostnerf_cli.scenes import Scene
from boostnerf_cli.viewpoint.maps import depth_picture, expert_share, gate_probability, grey, routing_colours

# what a frame shows: the render's colour, its depth, the routing colours (every expert's gate probability), one
# expert's share of the mixture, the gate's probability for one expert
MODES = ("colour", "depth", "routing", "share", "gate")
MIXTURE_MODES = ("routing", "share", "gate")  # only a mixture has them


@dataclass(frozen=True)
class Look:
    """What a frame shows: one of `MODES`, and for share and gate the expert (its index, smallest first)."""

    mode: str = "colour"
    expert: int = 0

    def check(self, model: LoadedModel) -> "Look":
        """This look, checked against `model`: one line for an unknown mode, a mixture's mode on an expert, or an
        expert index the mixture has not."""
        if self.mode not in MODES:
            raise BoostNerfError(f"unknown view mode {self.mode!r}: use one of {', '.join(MODES)}")
        if self.mode in MIXTURE_MODES and model.kind != "mixture":
            raise BoostNerfError(f"{model.name} is an expert, not a mixture: it has no {self.mode} map (the modes of "
                                 "an expert are colour and depth)")
        if self.mode in ("share", "gate") and not 0 <= self.expert < model.field.m:
            raise BoostNerfError(f"{model.name} has experts 0 to {model.field.m - 1}, not {self.expert}")
        return self


@dataclass
class Frame:
    """One rendered frame: the picture (uint8 (H, W, 3)), the colour render when the look is colour (for a PSNR),
    the seconds it took, and its GFLOPs (None when not counted)."""

    image: np.ndarray
    rgb: np.ndarray | None
    seconds: float
    gflops: float | None = None


def picture(model: LoadedModel, scene: Scene, camera: Camera, look: Look, device: str,
            packers: dict[str, Packer] | None = None, skips: Skips = ALL_SKIPS) -> tuple[np.ndarray, np.ndarray | None]:
    """What `camera` sees of `model` as `look` -> (uint8 (H, W, 3), the colour (H, W, 3) in [0, 1] or None).
    `packers`: one per picture kind, kept from frame to frame (their budgets carry over); `EXACT`: exact lists of the
    kept samples (no budget's pads), for counting."""
    look.check(model)
    packers = {} if packers is None else packers
    settings, skip = model.render_setup(scene, skips)

    def packer(key: str) -> Packer:
        return DYNAMIC if packers is EXACT else packers.setdefault(key, packer_for(device))

    if look.mode in ("colour", "depth"):
        r = render_image(model.field, camera, settings, skip, device, packer("mixture"))
        rgb = r["rgb"].numpy()
        return (to_uint8(rgb), rgb) if look.mode == "colour" else (depth_picture(r, scene), None)
    mix = model.field
    if look.mode == "share":
        return expert_share(mix, look.expert, camera, settings, skip, device, packer(f"expert{look.expert}")), None
    if look.mode == "gate":
        prob = gate_probability(mix, look.expert, camera, settings, skip, device, packer(f"gate{look.expert}"))
        return grey(prob), None
    probs = np.stack([gate_probability(mix, e, camera, settings, skip, device, packer(f"gate{e}"))
                      for e in range(mix.m)], -1)
    return routing_colours(probs), None


EXACT: dict[str, Packer] = {}  # `picture`'s packers that list exactly the kept samples


def frame(model: LoadedModel, scene: Scene, camera: Camera, look: Look, device: str,
          packers: dict[str, Packer] | None = None, count: bool = False) -> Frame:
    """`picture`, timed; with `count` its GFLOPs too (`costs.gflops_of`: counting slows the frame, so the time is
    then that of a second, uncounted render)."""
    t0 = time.perf_counter()
    image, rgb = picture(model, scene, camera, look, device, packers)
    seconds = time.perf_counter() - t0
    gflops = gflops_of(lambda: picture(model, scene, camera, look, device, EXACT))[1] if count else None
    return Frame(image, rgb, seconds, gflops)
