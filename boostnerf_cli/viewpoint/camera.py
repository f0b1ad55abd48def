"""The cameras a frame is rendered from: a dataset view's, a browser viewer's (OpenCV axes, a vertical field of view),
and the same camera at another size. Poses are the scenes' OpenGL camera-to-world matrices; the conventions, the
field of view and the scaling are `boostnerf_cli.cameras`'s."""

from __future__ import annotations

import numpy as np
import torch

from boostnerf_cli.cameras import Intrinsics, flip_axes
from boostnerf_cli.render.renderer import Camera
from boostnerf_cli.scenes import Split


def dataset_camera(split: Split, i: int) -> Camera:
    """View `i` of `split` as a camera."""
    return Camera(split.poses[i], split.intrinsics[i], split.height, split.width)  # the split's row (float32)


def opencv_pose(pose: torch.Tensor) -> np.ndarray:
    """A camera-to-world pose (4, 4), OpenGL (looks down -z) -> OpenCV (looks down +z, y down), float64."""
    return flip_axes(pose.double()).numpy()


def camera_for_view(rotation: np.ndarray, position: np.ndarray, fov: float, aspect: float, height: int) -> Camera:
    """The camera a browser viewer shows: its rotation (3, 3) and position (3,) in the OpenCV convention, its vertical
    field of view (radians) and aspect (width / height), rendered `height` pixels high."""
    height = max(1, int(height))
    width = max(1, int(round(height * aspect)))
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, position
    intrinsics = torch.tensor(Intrinsics.from_fov(fov, height, width).row(), dtype=torch.float32)
    return Camera(flip_axes(torch.from_numpy(pose).float()), intrinsics, height, width)


def fov_of(camera: Camera) -> float:
    """A camera's vertical field of view in radians."""
    return Intrinsics.of(camera.intrinsics).fov_y(camera.height)


def scaled(camera: Camera, height: int) -> Camera:
    """The same camera rendering `height` pixels high (the width and the intrinsics scaled alike; a lens is the same
    at any size)."""
    s = height / camera.height
    width = max(1, int(round(camera.width * s)))
    intrinsics = Intrinsics.of(camera.intrinsics).resized(camera.height, camera.width, height, width)
    return Camera(camera.pose, torch.tensor(intrinsics.row(), dtype=torch.float32), height, width)
