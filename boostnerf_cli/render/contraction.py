"""Unbounded scenes: mip-NeRF 360's contraction of all of space into one ball, and the samples placed along it.

Around a centre c with radius r, a world point x, with y = (x - c) / r, maps to

    contract(x) = c + r * y                          |y| <= 1  (the sphere around the subject: kept as it is)
    contract(x) = c + r * (2 - 1 / |y|) * y / |y|    |y| >  1  (the rest of the world, out to infinity: a shell)

so the whole world lands in the ball of radius 2 r around c, and one bounded box, `Contraction.box()` (c +- 2 r),
holds it. Every field (each expert family, the coarse geometry, the occupancy grid, the density volume V_D, the
gate and the mixture's dispatch) is given contracted points by the renderer and nothing else: none of them knows
about it.

Samples (`Contraction.sample`): a fixed step in world units (= contracted units, inside the sphere) from `near` to
where the ray leaves the sphere, then `n_out` samples evenly spaced in disparity (1 / t) from there to `far`, which
in contracted space is about the same step through the shell. Each sample's interval for compositing is its
length in contracted space (`deltas`), so a density means the same per contracted unit inside and out, and a
voxel of the background is opaque at the same density as a voxel of the subject.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

SHELL = 2.0  # the contracted world's radius, in sphere radii


@dataclass(frozen=True)
class Contraction:
    """The sphere kept linear (centre, radius, world units) and the far bound the samples reach."""

    centre: tuple[float, float, float]
    radius: float
    far: float
    # the longest stretch a ray samples linearly, from near to where it leaves the sphere (cameras outside the sphere
    # cross it from farther off than its diameter); 0: the diameter
    reach: float = 0.0

    def __post_init__(self) -> None:
        if not (self.radius > 0 and math.isfinite(self.radius)):
            raise ValueError(f"contraction radius must be positive and finite, got {self.radius}")
        if not self.far > self.radius:
            raise ValueError(f"contraction far bound {self.far} must exceed its radius {self.radius}")

    def _c(self, like: Tensor) -> Tensor:
        return torch.tensor(self.centre, dtype=like.dtype, device=like.device)

    def box(self) -> Tensor:
        """(2, 3) the box that holds the whole contracted world: centre +- 2 r."""
        c = torch.tensor(self.centre, dtype=torch.float32)
        return torch.stack([c - SHELL * self.radius, c + SHELL * self.radius])

    def contract(self, xyz: Tensor) -> Tensor:
        """World points (..., 3) -> contracted points (..., 3), inside the ball of radius 2 r."""
        c = self._c(xyz)
        y = (xyz - c) / self.radius
        n = y.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        out = torch.where(n <= 1, y, (SHELL - 1 / n) * y / n)
        return c + self.radius * out

    def uncontract(self, xyz: Tensor) -> Tensor:
        """Contracted points (..., 3) (radius below 2 r) -> world points: the inverse of `contract`."""
        c = self._c(xyz)
        z = (xyz - c) / self.radius
        n = z.norm(dim=-1, keepdim=True).clamp(1e-12, SHELL - 1e-7)
        out = torch.where(n <= 1, z, z / (n * (SHELL - n)))
        return c + self.radius * out

    def slots(self, step: float) -> tuple[int, int]:
        """(samples inside, samples outside) per ray at `step`: the linear stretch (`reach`, at least the sphere's
        diameter), and the shell's depth r (a ray leaving the sphere crosses about r of contracted space)."""
        return math.ceil(max(2 * self.radius, self.reach) / step) + 1, math.ceil(self.radius / step) + 1

    def sample(self, origins: Tensor, dirs: Tensor, near: float, step: float,
               jitter: bool) -> tuple[Tensor, Tensor, Tensor]:
        """Samples along rays (R, 3), (R, 3) (unit directions): -> t (R, S) world distances, valid (R, S) bool,
        contracted points (R, S, 3). The first `slots(step)[0]` are `step` apart from `near` to where the ray leaves
        the sphere (where it passes nearest the centre, for a ray that misses it), the rest evenly in disparity from
        there to `far`; with `jitter`, one uniform offset per ray, as the bounded sampler."""
        n_in, n_out = self.slots(step)
        oc = origins - self._c(origins)
        b = (oc * dirs).sum(-1)
        disc = b * b - (oc * oc).sum(-1) + self.radius ** 2
        leave = torch.where(disc > 0, -b + disc.clamp_min(0).sqrt(), -b)
        leave = leave.clamp(min=max(near, 1e-3 * self.radius), max=0.5 * self.far)
        u = torch.rand_like(b)[:, None] if jitter else torch.full_like(b, 0.5)[:, None]
        j = torch.arange(n_in, device=origins.device, dtype=origins.dtype)
        t_in = near + (j[None, :] + u) * step
        valid_in = t_in < leave[:, None]
        t_in = torch.minimum(t_in, leave[:, None])  # the unused slots sit where the ray leaves the sphere
        k = torch.arange(n_out, device=origins.device, dtype=origins.dtype)
        s = (k[None, :] + u) / n_out
        t_out = 1.0 / ((1 - s) / leave[:, None] + s / self.far)
        t = torch.cat([t_in, t_out], dim=1)
        valid = torch.cat([valid_in, torch.ones_like(t_out, dtype=torch.bool)], dim=1)
        xyz = self.contract(origins[:, None, :] + t[..., None] * dirs[:, None, :])
        return t, valid, xyz

    @staticmethod
    def deltas(xyz: Tensor) -> Tensor:
        """(R, S) each sample's interval for compositing: the contracted distance to the next sample (the last
        sample repeats the one before it)."""
        gaps = (xyz[:, 1:] - xyz[:, :-1]).norm(dim=-1)
        if gaps.shape[1] == 0:
            return torch.zeros(xyz.shape[:2], dtype=xyz.dtype, device=xyz.device)
        return torch.cat([gaps, gaps[:, -1:]], dim=1)

    def to_dict(self) -> dict:
        return {"centre": list(self.centre), "radius": self.radius, "far": self.far, "reach": self.reach}

    @staticmethod
    def from_dict(d: dict) -> "Contraction":
        return Contraction(tuple(float(v) for v in d["centre"]), float(d["radius"]), float(d["far"]),
                           float(d.get("reach", 0.0)))


FAR_RADII = 1000.0  # the far bound, in sphere radii: its contracted radius is 2 - 1/1000 of the shell's 2


def contraction_around(centre: Tensor, radius: float, origins: Tensor | None = None) -> Contraction:
    """The contraction of a sphere (centre (3,), radius): far bound `FAR_RADII` radii away; its linear stretch
    reaches through the sphere from the farthest of the camera centres `origins` (N, 3)."""
    c = centre.double()
    reach = 0.0 if origins is None else float((origins.double() - c).norm(dim=-1).max()) + float(radius)
    return Contraction(tuple(float(v) for v in c), float(radius), FAR_RADII * float(radius), reach)


SPHERE_SHARE = 0.5  # the sphere kept linear reaches this share of the cameras' median distance to their subject


def sphere_from_cameras(origins: Tensor, focus: Tensor) -> tuple[Tensor, float]:
    """The sphere kept linear for cameras around a subject: centred on `focus` (the point nearest their optical
    axes), of `SPHERE_SHARE` times the cameras' (N, 3) median distance to it. mip-NeRF 360 holds every camera in it
    (an MLP has no cells to spare); a grid gives the sphere half its side, so a sphere twice as large would give the
    subject half the voxels. -> (centre (3,), radius)."""
    radius = SPHERE_SHARE * float((origins.double() - focus.double()).norm(dim=-1).median())
    return focus.double(), radius


def sphere_from_points(points: Tensor, share: float = 0.9) -> tuple[Tensor, float]:
    """The sphere kept linear for a capture with sparse points (N, 3): centred on their median, holding `share`
    of them (a few far points, the background, stay outside). -> (centre (3,), radius)."""
    p = points.double()
    centre = p.median(dim=0).values
    radius = float(torch.quantile((p - centre).norm(dim=-1), share))
    return centre, radius
