"""How far one set of camera poses is from another, up to the similarity that structure from motion leaves free
(scale, rotation, translation): for a capture's poses against known ones."""

from __future__ import annotations

import numpy as np

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.scenes.scene import Scene


def scene_poses(scene: Scene) -> dict[str, np.ndarray]:
    """Every view's camera-to-world pose (4, 4) float64 by name, over all splits."""
    return {name: pose.double().numpy() for split in scene.splits.values()
            for name, pose in zip(split.names, split.poses)}


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama's least-squares similarity dst ~ s R src + t for points (N, 3) -> (s, R (3, 3), t (3,))."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    scale = float(np.trace(np.diag(sig) @ d) / (a ** 2).sum(1).mean())
    return scale, rot, mu_d - scale * rot @ mu_s


def pose_errors(estimated: dict[str, np.ndarray], reference: dict[str, np.ndarray]) -> dict:
    """Align `estimated` camera centres onto `reference` (same names) by a similarity, then per camera the rotation
    error (degrees) and the centre error as a fraction of the reference cameras' spread (their largest distance from
    their mean): -> median and largest of each, and how many cameras were compared."""
    names = sorted(set(estimated) & set(reference))
    if len(names) < 3:
        raise BoostNerfError(f"only {len(names)} cameras in common: at least 3 are needed to compare poses")
    est = np.stack([estimated[n] for n in names])
    ref = np.stack([reference[n] for n in names])
    scale, rot, t = similarity(est[:, :3, 3], ref[:, :3, 3])
    centres = scale * est[:, :3, 3] @ rot.T + t
    spread = float(np.linalg.norm(ref[:, :3, 3] - ref[:, :3, 3].mean(0), axis=1).max())
    centre_err = np.linalg.norm(centres - ref[:, :3, 3], axis=1) / spread
    rel = np.einsum("nji,njk->nik", rot @ est[:, :3, :3], ref[:, :3, :3])  # (R est)^T ref per camera
    angle = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return {"cameras": len(names), "median_rotation_deg": float(np.median(angle)),
            "max_rotation_deg": float(angle.max()), "median_centre_error": float(np.median(centre_err)),
            "max_centre_error": float(centre_err.max())}


def compare_scenes(estimated: Scene, reference: Scene) -> dict:
    """`pose_errors` of two scenes' views, matched by name."""
    return pose_errors(scene_poses(estimated), scene_poses(reference))


__all__ = ["compare_scenes", "pose_errors", "scene_poses", "similarity"]
