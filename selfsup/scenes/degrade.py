"""Degradations of what the estimator is given, never of the ground truth.

Each is a switch of :class:`Degradations` (mirrored by ``configs/data/*.yaml``):

- reflectance: ``"true"``; ``"half"`` (kd = ks = 0.5, the paper's "m = 0.0" row);
  ``"noise"`` (fractal noise of magnitude ``reflectance_noise`` added to kd, the
  paper's m = 0.1 .. 0.3 rows);
- depth like a consumer RGB-D sensor: noise with standard deviation
  ``depth_noise * z^2``, quantisation in steps of ``depth_quantisation * z^2``,
  holes where the depth jumps by more than ``edge_hole_jump`` (relative) and at a
  share ``random_holes`` of random pixels; degraded depth also drops the stored
  normals (a sensor gives none);
- image noise: Gaussian read noise ``image_noise`` plus shot noise
  ``shot_noise * sqrt(I)``, clamped at 0;
- ambient: ``"true"``, ``"unknown"`` (dropped from the file, to be estimated) or
  ``"wrong"`` (scaled by ``wrong_ambient_factor``).

Ground truth (``light_pos``, ``light_intensity``, ``scene_scale``) is copied as is.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from selfsup.scenes.exact import fractal_noise, neighbourhood_max
from selfsup.scenes.io import Scene

__all__ = ["Degradations", "degrade", "REFLECTANCE_MODES", "AMBIENT_MODES"]

REFLECTANCE_MODES = ("true", "half", "noise")
AMBIENT_MODES = ("true", "unknown", "wrong")


@dataclass
class Degradations:
    """Switches; the defaults change nothing."""

    reflectance: str = "true"
    reflectance_noise: float = 0.0
    depth_noise: float = 0.0
    depth_quantisation: float = 0.0
    edge_hole_jump: float = 0.0
    random_holes: float = 0.0
    image_noise: float = 0.0
    shot_noise: float = 0.0
    ambient: str = "true"
    wrong_ambient_factor: float = 2.0

    def __post_init__(self):
        if self.reflectance not in REFLECTANCE_MODES:
            raise ValueError(f"reflectance must be one of {REFLECTANCE_MODES}, got {self.reflectance!r}")
        if self.ambient not in AMBIENT_MODES:
            raise ValueError(f"ambient must be one of {AMBIENT_MODES}, got {self.ambient!r}")
        for name in ("reflectance_noise", "depth_noise", "depth_quantisation", "edge_hole_jump", "random_holes",
                     "image_noise", "shot_noise", "wrong_ambient_factor"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.random_holes >= 1:
            raise ValueError(f"random_holes must be < 1 (a share of pixels), got {self.random_holes}")

    @property
    def touches_depth(self) -> bool:
        return any(v > 0 for v in (self.depth_noise, self.depth_quantisation, self.edge_hole_jump, self.random_holes))

    def describe(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if getattr(self, f.name) != f.default}


def _degrade_depth(depth: Tensor, d: Degradations, gen: torch.Generator) -> Tensor:
    valid = depth > 0
    z = depth
    squared = depth**2
    if d.depth_noise > 0:
        z = z + d.depth_noise * squared * torch.randn(z.shape, generator=gen, dtype=z.dtype)
    if d.depth_quantisation > 0:
        step = d.depth_quantisation * squared
        z = torch.round(z / step.clamp_min(1e-9)) * step  # step > 0 where depth is valid
    keep = valid & (z > 0)
    if d.edge_hole_jump > 0:
        # Relative depth range over each 3x3 neighbourhood of the clean depth: its maximum and
        # the maximum of its negation, found together.
        extremes = neighbourhood_max(torch.stack([depth, -depth]))
        keep &= extremes[0] + extremes[1] <= d.edge_hole_jump * depth
    if d.random_holes > 0:
        keep &= torch.rand(z.shape, generator=gen, dtype=z.dtype) >= d.random_holes
    return torch.where(keep, z, 0.0)


def degrade(scene: Scene, degradations: Degradations, seed: int) -> Scene:
    """A copy of ``scene`` with the inputs degraded (reproducible from ``seed``)."""
    d = degradations
    gen = torch.Generator().manual_seed(int(seed))
    out = dataclasses.replace(scene, meta=dict(scene.meta))
    H, W = scene.depth.shape
    valid = (scene.depth > 0)[..., None]
    if d.reflectance == "half":
        out.kd = torch.full_like(scene.kd, 0.5) * valid
        out.ks = torch.full((H, W, 1), 0.5, dtype=scene.kd.dtype) * valid
    elif d.reflectance == "noise" and d.reflectance_noise > 0:
        # Fractal noise on the scene's surfaces (camera-frame points), one pattern per channel.
        v, u = torch.meshgrid(torch.arange(H, dtype=scene.K.dtype), torch.arange(W, dtype=scene.K.dtype), indexing="ij")
        pixels = torch.stack([u, v, torch.ones_like(u)], -1)
        points = scene.depth[..., None] * (pixels @ torch.linalg.inv(scene.K).T)
        offset = torch.rand(3, 3, generator=gen, dtype=points.dtype) * 100
        size = torch.full((H * W,), 0.4, dtype=points.dtype) * float(scene.depth[scene.depth > 0].median())
        pattern = torch.stack([fractal_noise((points.reshape(-1, 3) + offset[c]).T, size) for c in range(3)], -1)
        out.kd = ((scene.kd + d.reflectance_noise * (2 * pattern.reshape(H, W, 3) - 1)).clamp(0, 1)) * valid
    if d.touches_depth:
        out.depth = _degrade_depth(scene.depth, d, gen)
        out.normals = None
    if d.image_noise > 0 or d.shot_noise > 0:
        if d.shot_noise > 0:
            sigma = (d.image_noise**2 + d.shot_noise**2 * scene.image).sqrt()
        else:  # the same value everywhere: one number, as the array would hold it
            sigma = torch.tensor(d.image_noise**2, dtype=scene.image.dtype).sqrt()
        out.image = (scene.image + sigma * torch.randn(scene.image.shape, generator=gen, dtype=scene.image.dtype)).clamp_min(0)
    if d.ambient == "unknown":
        out.ambient = None
    elif d.ambient == "wrong" and scene.ambient is not None:
        out.ambient = scene.ambient * d.wrong_ambient_factor
    out.meta["degradations"] = d.describe()
    return out
