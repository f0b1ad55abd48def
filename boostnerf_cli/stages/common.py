"""What several stages share: devices, loading the workspace's scene, and loading any model by name."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
from torch import Tensor, nn

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields import count_params, load_expert
from boostnerf_cli.render.renderer import RenderSettings
from boostnerf_cli.scenes import Scene, load_scene
from boostnerf_cli.workspace import Workspace, read_meta


def resolve_device(name: str) -> str:
    """`auto` -> cuda when available, else cpu; `cuda` without a GPU is an error."""
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise BoostNerfError("--device cuda was asked for but torch sees no CUDA GPU: use --device cpu or auto")
    if name not in ("cpu", "cuda"):
        raise BoostNerfError(f"unknown device {name!r}: use auto, cpu or cuda")
    return name


def workspace_scene(ws: Workspace) -> Scene:
    """Reload the scene a workspace was trained on, exactly as `pretrain` loaded it."""
    m = ws.require_manifest()
    data = m.get("data")
    if not data:
        raise BoostNerfError(f"{ws.manifest_path} records no scene: rerun `boostnerf pretrain --workspace {ws.root}`")
    path = Path(data["path"])
    if not path.exists():
        raise BoostNerfError(f"the workspace's scene {path} is gone: restore it or rerun pretrain in a new workspace")
    scene = load_scene(path, image_size=data.get("image_size"), holdout_every=data.get("holdout_every", 8),
                       format=data.get("format", "auto"))
    if m.get("scene_digest") and scene_digest(scene) != m["scene_digest"]:
        raise BoostNerfError(
            f"the workspace's scene {path} changed since pretrain (its images or cameras differ): restore it, "
            f"or retrain with `boostnerf pretrain --workspace {ws.root} --data {path} --force`"
        )
    return scene


def scene_digest(scene: Scene) -> str:
    """Fingerprint of what training sees: every split's images, poses and intrinsics (recorded by pretrain)."""
    h = hashlib.blake2b(digest_size=16)
    for name in sorted(scene.splits):
        s = scene.splits[name]
        h.update(name.encode())
        for t in (s.images, s.poses, s.intrinsics):
            h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


SKIP_NAMES = ("empty", "terminated")


@dataclass(frozen=True)
class Skips:
    """Which render-time skips are on; each can be turned off to measure what it saves and costs.

    empty:      samples in empty space are not evaluated (a model's occupancy grid; for a mixture also
                the density volume V_D below its threshold T)
    terminated: colour is computed only for samples whose rendering weight exceeds 1e-4 (drops samples
                behind rays that have terminated and in near-empty space)
    All off (`--no-skip`) is dense fixed-step sampling over the model's box, every sample through density
    and colour.
    """

    empty: bool = True
    terminated: bool = True

    @staticmethod
    def from_flags(no_skip: bool = False, off: list[str] | None = None) -> "Skips":
        off = set(off or [])
        unknown = sorted(off - set(SKIP_NAMES))
        if unknown:
            raise BoostNerfError(f"--skip-off {unknown[0]}: unknown skip; the skips are {', '.join(SKIP_NAMES)}")
        if no_skip:
            off = set(SKIP_NAMES)
        return Skips(empty="empty" not in off, terminated="terminated" not in off)

    def describe(self) -> str:
        on = [n for n in SKIP_NAMES if getattr(self, n)]
        return "all on" if len(on) == len(SKIP_NAMES) else "all off" if not on else f"only {', '.join(on)} on"


ALL_SKIPS = Skips()


@dataclass
class LoadedModel:
    """A field ready to render, with what rendering it needs."""

    name: str
    kind: str  # "expert" or "mixture"
    field: nn.Module
    skip: Callable[[Tensor], Tensor] | None
    step: float
    bbox: Tensor
    params: int

    def for_rendering(self, exact_gate: bool = False) -> "LoadedModel":
        """Ready to render: a mixture's gate baked (`Mixture.for_rendering`) unless `exact_gate`."""
        if self.kind == "mixture":
            self.field.for_rendering(exact_gate)
        return self

    def settings(self, scene: Scene, color_threshold: float = 1e-4) -> RenderSettings:
        return RenderSettings(step=self.step, near=scene.near, far=scene.far, bbox=self.bbox,
                              background=scene.background, color_threshold=color_threshold, ndc=scene.ndc)

    def render_setup(self, scene: Scene, skips: Skips) -> tuple[RenderSettings, Callable[[Tensor], Tensor] | None]:
        """The render settings and the empty-space filter for rendering this model with `skips`."""
        return self.settings(scene, 1e-4 if skips.terminated else 0.0), self.skip if skips.empty else None


def load_model(ws: Workspace, name: str, device: str, exact_gate: bool = False) -> LoadedModel:
    """An expert (`dvgo-64`), a mixture (`top1`, `top2`, `ens`) or the finetuned `baseline` of the workspace.

    A mixture is returned ready to render: its gate baked (`Mixture.for_rendering`) unless `exact_gate`.
    """
    path = ws.expert_path(name) if ws.expert_path(name).exists() else ws.model_path(name)
    if not path.exists() or name == "geometry":
        known = ", ".join(all_model_names(ws)) or "none yet"
        raise BoostNerfError(f"no model named {name!r} in {ws.root} (models: {known})")
    if read_meta(path).get("family") == "mixture":
        from boostnerf_cli.moe.mixture import load_mixture

        mix, meta = load_mixture(path, device)
        params = meta.get("stored_params", count_params(mix))  # the trained model's, before baking (pruned: stored)
        return LoadedModel(name, "mixture", mix, mix.skip, meta["step"], mix.bbox, params).for_rendering(exact_gate)
    model, occ, meta = load_expert(path, device)
    return LoadedModel(name, "expert", model, occ.to(device) if occ is not None else None, meta["step"],
                       model.bbox, meta.get("stored_params", count_params(model)))


def all_model_names(ws: Workspace) -> list[str]:
    """Experts smallest first, then mixtures in the paper's order."""
    order = {"baseline": 0, "top1": 1, "top2": 2, "ens": 9}
    mixtures = sorted((n for n in ws.model_names() if n != "init"), key=lambda n: (order.get(n, 5), n))
    return ws.expert_names() + mixtures
