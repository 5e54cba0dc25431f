"""Indirect light: the first bounce between the surfaces a G-buffer sees, and the later ones.

Indoors, light reflected by the walls and the floor adds to what the lights give directly:
12-38% of the image on the devset's path-traced files. :func:`one_bounce` predicts the first
bounce from the geometry and albedo alone: every patch of the visible surfaces, lit by a
light's direct transport, reflects diffusely onto every other point,

    G_i(x) = sum_p kd_p D_i(p) A_p cos(theta_x) cos(theta_p) / (pi r^2),

``A_p`` the patch's area, ``theta`` the angles of the line between them to each normal,
without visibility between the two. Surfaces the camera does not see (behind it, above the
frame) and the later bounces are missing: on three path-traced Mitsuba scenes the first
bounce was 0.53-0.70 of the indirect light (correlation 0.72-0.93 with it over the pixels).
:func:`bounce_gain` adds the later bounces as a geometric series of the scene's mean albedo,
and :func:`bounce_transport` is the pixel's light of it per unit light; the renderer adds
``strength`` times it (``render(..., indirect="bounce")``, :class:`render.ShadowedBlinnPhong`).

Shapes as in :mod:`render`: geometry ``(B, H, W, 3)``, per-light maps ``(B, L, H, W)``,
images ``(B, 3, H, W)``. Differentiable in everything (positions through the transport),
dtype and device of the inputs.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from render.types import GBuffer

__all__ = ["one_bounce", "bounce_gain", "bounce_transport", "bounce_image", "INDIRECT_MODES", "MIN_COS_VIEW",
           "MAX_MEAN_ALBEDO", "PATCHES_ACROSS"]

INDIRECT_MODES = ("none", "bounce")
MIN_COS_VIEW = 0.2  # a patch seen at a grazing angle covers more surface; counted up to 5 pixels' worth
MAX_MEAN_ALBEDO = 0.8  # bounce_gain at most 5
PATCHES_ACROSS = 20  # bounce_transport: patches (and targets) along the image width


def _need_intrinsics(gbuffer: GBuffer, what: str) -> None:
    if gbuffer.intrinsics is None:
        raise ValueError(f"{what} needs the G-buffer's intrinsics (a pixel's area in metres is (z / f)^2): "
                         "build it with GBuffer.from_depth(depth, K) or give intrinsics")


def one_bounce(gbuffer: GBuffer, kd: Tensor, diffuse: Tensor, patch_px: int = 8, target_px: int = 8) -> Tensor:
    """First-bounce indirect light ``(B, 3, L, H, W)``: irradiance at each pixel (in the
    units of the diffuse transport, so that ``kd * I_i * (D_i + G_i)`` is the pixel lit
    by light ``i`` of intensity ``I_i``) from the visible surfaces lit by each light.

    Args:
        gbuffer: points, normals ``(B, H, W, 3)``, mask, and ``intrinsics`` (required:
            a pixel's area in metres is ``(z / f)^2`` over its view angle's cosine).
        kd: ``(B, H, W, 3)`` albedo of the reflecting patches.
        diffuse: ``(B, L, H, W)`` direct diffuse transport of each light (shadowed, for
            a light's cast shadows to darken its bounce).
        patch_px: the reflecting patches: one pixel every ``patch_px`` along rows and columns.
        target_px: the bounce is found every ``target_px`` pixels and interpolated
            bilinearly between (it is smooth; 300 x 300 pairs at 160x120, 3 ms on the
            2-core CPU; every 4 pixels cost 4x more and chose the same models on the
            48 path-traced Mitsuba scenes).
    """
    _need_intrinsics(gbuffer, "one_bounce")
    B, H, W, _ = gbuffer.points.shape
    if kd.shape != (B, H, W, 3) or diffuse.dim() != 4 or diffuse.shape[0] != B or diffuse.shape[2:] != (H, W):
        raise ValueError(f"one_bounce needs kd ({B}, {H}, {W}, 3) and diffuse ({B}, L, {H}, {W}), got "
                         f"{tuple(kd.shape)} and {tuple(diffuse.shape)}")
    if patch_px < 1 or target_px < 1:
        raise ValueError(f"patch_px and target_px must be >= 1, got {patch_px} and {target_px}")
    L = diffuse.shape[1]
    dtype, device = gbuffer.points.dtype, gbuffer.points.device

    def grid(step: int) -> Tensor:  # flat indices of every step-th pixel from step // 2
        rows = torch.arange(step // 2, H, step, device=device)
        cols = torch.arange(step // 2, W, step, device=device)
        return (rows[:, None] * W + cols[None]).flatten()

    valid = gbuffer.mask.flatten(1)[..., None]
    # Invalid pixels may hold anything (non-finite points of missing depth): zeros, then masked out.
    points = torch.where(valid, gbuffer.points.flatten(1, 2), torch.zeros((), dtype=dtype, device=device))
    normals = torch.where(valid, gbuffer.normals.flatten(1, 2), torch.zeros((), dtype=dtype, device=device))
    mask = valid[..., 0].to(dtype)
    source, target = grid(patch_px), grid(target_px)
    p, n_p = points[:, source], normals[:, source]  # (B, M, 3)
    x, n_x = points[:, target], normals[:, target]  # (B, N, 3)

    focal = gbuffer.intrinsics[:, 0, 0].to(dtype)[:, None]
    cos_view = (n_p * -p).sum(-1) / p.norm(dim=-1).clamp_min(1e-12)
    area = (p[..., 2] / focal) ** 2 / cos_view.clamp_min(MIN_COS_VIEW) * patch_px**2 * mask[:, source]  # (B, M)
    area = torch.where(mask[:, source] > 0, area, torch.zeros_like(area))

    # Pair terms from matrix products, no (B, N, M, 3) tensor: |p - x|^2, n_x.(p - x), n_p.(x - p).
    squared = ((x * x).sum(-1)[:, :, None] + (p * p).sum(-1)[:, None] - 2 * x @ p.transpose(1, 2)).clamp_min(0)
    toward_patch = n_x @ p.transpose(1, 2) - (n_x * x).sum(-1)[:, :, None]  # (B, N, M), times r
    toward_point = (x @ n_p.transpose(1, 2)) - (n_p * p).sum(-1)[:, None]  # (B, N, M), times r
    # cos_x cos_p / r^2 = (n_x.d)(n_p.(-d)) / r^4; r^2 at least the patch's area (no singularity at the patch itself).
    r2 = torch.maximum(squared, area[:, None])
    factors = toward_patch.clamp_min(0) * toward_point.clamp_min(0) / (r2 * r2) * area[:, None] / math.pi
    factors = torch.where(mask[:, target, None] > 0, factors, torch.zeros_like(factors))  # (B, N, M)

    radiance = torch.nan_to_num(kd.flatten(1, 2)[:, source].transpose(1, 2)[:, :, None] * diffuse.flatten(2)[:, None, :, source])  # (B, 3, L, M)
    at_targets = (radiance.flatten(1, 2) @ factors.transpose(1, 2)).view(B, 3 * L, -1)  # (B, 3L, N)
    h, w = len(range(target_px // 2, H, target_px)), len(range(target_px // 2, W, target_px))
    coarse = at_targets.view(B, 3 * L, h, w)
    if target_px == 1:
        full = coarse
    else:
        # Coarse sample j lies at pixel target_px // 2 + j * target_px; the interpolation puts it
        # at (target_px - 1) / 2 + j * target_px: half a pixel off for even steps, on a smooth term.
        full = F.interpolate(coarse, scale_factor=target_px, mode="bilinear", align_corners=False)
        full = F.pad(full, (0, max(W - full.shape[-1], 0), 0, max(H - full.shape[-2], 0)), mode="replicate")
    return full[..., :H, :W].reshape(B, 3, L, H, W) * gbuffer.mask[:, None, None]


def bounce_gain(kd: Tensor, mask: Tensor, max_albedo: float = MAX_MEAN_ALBEDO) -> Tensor:
    """``(B, 3)``: ``1 / (1 - a)``, ``a`` the mean albedo over valid pixels per channel
    (at most ``max_albedo``): the first bounce and all later ones, each reflected as by
    the scene's mean albedo (a geometric series), relative to the first.

    Args:
        kd: ``(B, H, W, 3)``; mask: ``(B, H, W)``.
    """
    weight = mask[..., None].to(kd.dtype)
    mean = (torch.nan_to_num(kd) * weight).sum((1, 2)) / weight.sum((1, 2)).clamp_min(1)
    return 1 / (1 - mean.clamp(0, max_albedo))


def bounce_transport(gbuffer: GBuffer, kd: Tensor, diffuse: Tensor, patches_across: int = PATCHES_ACROSS) -> Tensor:
    """Indirect light ``(B, 3, L, H, W)`` of unit-intensity lights at each pixel, per channel,
    as the camera sees it: ``kd * bounce_gain * G_i`` (:func:`one_bounce`, :func:`bounce_gain`),
    to be added to each light's direct diffuse light ``kd * D_i``. Patches and targets are
    ``patches_across`` to the image width at any resolution (every 8 pixels at 160)."""
    step = max(1, round(kd.shape[2] / patches_across))
    gain = bounce_gain(kd, gbuffer.mask)[:, :, None, None, None]
    return gain * kd.permute(0, 3, 1, 2)[:, :, None] * one_bounce(gbuffer, kd, diffuse, step, step)


def bounce_image(gbuffer: GBuffer, kd: Tensor, diffuse: Tensor, intensity: Tensor, strength: Tensor | float = 1.0,
                 patches_across: int = PATCHES_ACROSS) -> Tensor:
    """The indirect light ``(B, 3, H, W)`` of lights of ``intensity (B, L, 3)`` whose direct
    diffuse transport is ``diffuse (B, L, H, W)``: ``strength`` (a number or ``(B,)``; 1: the
    first bounce and the later ones of :func:`bounce_gain`) times the sum over the lights of
    :func:`bounce_transport` times their intensities."""
    B = gbuffer.mask.shape[0]
    if intensity.shape != (B, diffuse.shape[1], 3):
        raise ValueError(f"intensity must be ({B}, {diffuse.shape[1]}, 3) for the transport's lights, got "
                         f"{tuple(intensity.shape)}")
    columns = bounce_transport(gbuffer, kd, diffuse, patches_across)  # (B, 3, L, H, W)
    bounce = (columns * intensity.transpose(1, 2)[..., None, None]).sum(2)
    strength = torch.as_tensor(strength, dtype=bounce.dtype, device=bounce.device)
    if strength.dim() > 1 or (strength.dim() == 1 and strength.shape[0] not in (1, B)):
        raise ValueError(f"indirect strength must be a number or ({B},), got shape {tuple(strength.shape)}")
    if not bool(torch.isfinite(strength).all()) or bool((strength < 0).any()):
        raise ValueError("indirect strength must be finite and >= 0")
    return strength.reshape(-1, 1, 1, 1) * bounce
