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
  ``"wrong"`` (scaled by ``wrong_ambient_factor``);
- ``indirect``: the rooms' indirect light added, at a strength drawn in ``[0, indirect]``
  times the first bounce and the later ones (:func:`selfsup.scenes.indirect.with_bounce`;
  needs the render's visibility);
- ``camera``: a camera drawn per scene (:func:`capture_camera`: auto exposure, white
  balance, lens falloff, the sRGB curve, 8 bits, JPEG or PNG, a pixel's misregistration,
  a structured-light depth sensor's steps, bumps and holes, millimetres) captures the
  frame, and the inputs are what the capture reader makes of it: linear colour, metric
  depth, no normals and no ambient; the lights' intensities follow the exposure and the
  white balance's gains.

Ground truth (``light_pos``, ``light_intensity``, ``scene_scale``) is copied as is.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from render import GBuffer
from selfsup.scenes.camera import CameraModel, camera_capture
from selfsup.scenes.capture import srgb_to_linear
from selfsup.scenes.exact import fractal_noise, neighbourhood_max
from selfsup.scenes.indirect import with_bounce
from selfsup.scenes.io import Scene

__all__ = ["Degradations", "degrade", "capture_camera", "REFLECTANCE_MODES", "AMBIENT_MODES"]

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
    indirect: float = 0.0
    camera: bool = False

    def __post_init__(self):
        if self.reflectance not in REFLECTANCE_MODES:
            raise ValueError(f"reflectance must be one of {REFLECTANCE_MODES}, got {self.reflectance!r}")
        if self.ambient not in AMBIENT_MODES:
            raise ValueError(f"ambient must be one of {AMBIENT_MODES}, got {self.ambient!r}")
        for name in ("reflectance_noise", "depth_noise", "depth_quantisation", "edge_hole_jump", "random_holes",
                     "image_noise", "shot_noise", "wrong_ambient_factor", "indirect"):
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


def capture_camera(gen: torch.Generator) -> CameraModel:
    """A consumer camera drawn from ``gen``: mean-metered exposure, white balance (70%),
    a lens losing 0-45% at the corners, PNG or JPEG (quality 70-95), colour and depth a
    pixel apart (30%), a structured-light sensor's disparity steps, bumps and holes."""
    draw = lambda low, high: low + (high - low) * float(torch.rand((), generator=gen, dtype=torch.float64))  # noqa: E731
    return CameraModel(
        key=(0.08, 0.35), white_balance=draw(0, 1) < 0.7, vignetting=draw(0.0, 0.45),
        jpeg_quality=None if draw(0, 1) < 0.5 else int(draw(70, 95)), misregistration_px=float(draw(0, 1) < 0.3),
        disparity_step=draw(0.0005, 0.003), depth_bumps=draw(0.0, 0.002), edge_holes=0.04 if draw(0, 1) < 0.7 else 0.0,
        random_holes=draw(0.0, 0.02))


def _captured(scene: Scene, gen: torch.Generator) -> Scene:
    # The frame through a drawn camera, read back as the capture reader would.
    seed = int(torch.randint(0, 2**31 - 1, (), generator=gen))
    capture = camera_capture(scene.image, scene.depth, scene.K, capture_camera(gen), seed)
    gains = torch.as_tensor(capture.gains * capture.exposure, dtype=scene.image.dtype)
    image = torch.from_numpy(srgb_to_linear(capture.color.astype(np.float64) / 255)).to(scene.image.dtype)
    depth = torch.from_numpy(capture.depth_mm.astype(np.float64) / 1000).to(scene.depth.dtype)
    intensity = None if scene.light_intensity is None else scene.light_intensity * gains
    return dataclasses.replace(scene, image=image, depth=depth, K=torch.from_numpy(capture.K).to(scene.K.dtype),
                               normals=None, ambient=None, light_intensity=intensity)


def degrade(scene: Scene, degradations: Degradations, seed: int, visibility: Tensor | None = None) -> Scene:
    """A copy of ``scene`` with the inputs degraded (reproducible from ``seed``);
    ``visibility (H, W, L)``: the render's, which ``indirect`` needs."""
    d = degradations
    gen = torch.Generator().manual_seed(int(seed))
    out = dataclasses.replace(scene, meta=dict(scene.meta))
    H, W = scene.depth.shape
    valid = (scene.depth > 0)[..., None]
    if d.indirect > 0 and scene.light_pos is not None:
        if visibility is None:
            raise ValueError("degradations.indirect needs the render's visibility (degrade(..., visibility=...))")
        g = GBuffer.from_depth(scene.depth[None], scene.K[None], normals=scene.normals[None] if scene.normals is not None else None)
        strength = d.indirect * float(torch.rand((), generator=gen, dtype=torch.float64))
        lit = with_bounce(scene.image.permute(2, 0, 1)[None], g, scene.kd[None], scene.light_pos[None],
                          scene.light_intensity[None], visibility.permute(2, 0, 1)[None].to(scene.image.dtype), strength,
                          scene.meta.get("falloff", "inverse_square") == "inverse_square")
        out.image = lit[0].permute(1, 2, 0).contiguous()
        out.meta["indirect_strength"] = strength
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
            sigma = (d.image_noise**2 + d.shot_noise**2 * out.image).sqrt()
        else:  # the same value everywhere: one number, as the array would hold it
            sigma = torch.tensor(d.image_noise**2, dtype=scene.image.dtype).sqrt()
        out.image = (out.image + sigma * torch.randn(scene.image.shape, generator=gen, dtype=scene.image.dtype)).clamp_min(0)
    if d.ambient == "unknown":
        out.ambient = None
    elif d.ambient == "wrong" and scene.ambient is not None:
        out.ambient = scene.ambient * d.wrong_ambient_factor
    if d.camera:
        out = _captured(out, gen)
    out.meta["degradations"] = d.describe()
    return out
