"""One bounce of indirect light between the surfaces a G-buffer sees.

Indoors, light reflected by the walls and the floor adds to what the lights give
directly: 12-38% of the image on the devset's path-traced files. The image model has no such term: where a file does not
give its ambient, a constant ambient takes what it can, and a second point light
can take the rest (a light "found" in a scene with one). This module predicts the
first bounce from the geometry and albedo alone: every patch of the visible
surfaces, lit by a light's direct transport, reflects diffusely onto every other
point,

    G_i(x) = sum_p kd_p D_i(p) A_p cos(theta_x) cos(theta_p) / (pi r^2),

``A_p`` the patch's area, ``theta`` the angles of the line between them to each
normal, without visibility between the two. Surfaces the camera does not see
(behind it, above the frame) and the later bounces are missing: on three
path-traced Mitsuba scenes the first bounce was 0.53-0.70 of the indirect light
(correlation 0.72-0.93 with it over the pixels). :func:`bounce_gain` adds the
later bounces as a geometric series of the scene's mean albedo.

Model selection uses it (:mod:`selfsup.estimation`, ``estimate.indirect``): a light
explains the image with its bounce, so a stand-in light for the bounce no longer
pays for itself. The generator adds it to training scenes (:func:`with_bounce`,
``degradations.indirect``): a network that has never seen a bounce takes it for a
second light.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from render import GBuffer, Material, light_transport
from render.shading import Falloff

__all__ = ["one_bounce", "bounce_gain", "indirect_columns", "with_bounce"]

MIN_COS_VIEW = 0.2  # a patch seen at a grazing angle covers more surface; counted up to 5 pixels' worth
MAX_MEAN_ALBEDO = 0.8  # bounce_gain at most 5
PATCHES_ACROSS = 20  # indirect_columns: patches (and targets) along the image width


def one_bounce(gbuffer: GBuffer, kd: Tensor, diffuse: Tensor, patch_px: int = 8, target_px: int = 8) -> Tensor:
    """First-bounce indirect light ``(B, 3, L, H, W)``: irradiance at each pixel (in the
    units of the diffuse transport, so that ``kd * I_i * (D_i + G_i)`` is the pixel lit
    by light ``i`` of intensity ``I_i``) from the visible surfaces lit by each light.

    Args:
        gbuffer: points, normals ``(B, H, W, 3)``, mask, and ``intrinsics`` (required:
            a pixel's area in metres is ``(z / f)^2`` over its view angle's cosine).
        kd: ``(B, H, W, 3)`` albedo of the reflecting patches.
        diffuse: ``(B, L, H, W)`` direct diffuse transport of each light.
        patch_px: the reflecting patches: one pixel every ``patch_px`` along rows and columns.
        target_px: the bounce is found every ``target_px`` pixels and interpolated
            bilinearly between (it is smooth; 300 x 300 pairs at 160x120, 3 ms on the
            2-core CPU; every 4 pixels cost 4x more and chose the same models on the
            48 path-traced Mitsuba scenes).
    """
    if gbuffer.intrinsics is None:
        raise ValueError("one_bounce needs the G-buffer's intrinsics (a pixel's area)")
    B, H, W, _ = gbuffer.points.shape
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


def indirect_columns(gbuffer: GBuffer, kd: Tensor, diffuse: Tensor, patches_across: int = PATCHES_ACROSS) -> Tensor:
    """Indirect light ``(B, 3, L, H, W)`` of unit-intensity lights, per channel:
    ``kd * bounce_gain * G_i`` (:func:`one_bounce`, :func:`bounce_gain`), to be added to
    their direct basis images (:func:`selfsup.linear.basis_images`). Patches and targets
    are ``patches_across`` to the image width at any resolution (every 8 pixels at 160)."""
    step = max(1, round(kd.shape[2] / patches_across))
    gain = bounce_gain(kd, gbuffer.mask)[:, :, None, None, None]
    return gain * kd.permute(0, 3, 1, 2)[:, :, None] * one_bounce(gbuffer, kd, diffuse, step, step)


def with_bounce(image: Tensor, gbuffer: GBuffer, kd: Tensor, light_position: Tensor, light_intensity: Tensor,
                visibility: Tensor, strength: Tensor | float, inverse_square: bool = True) -> Tensor:
    """``image (B, 3, H, W)`` plus ``strength`` times the indirect light of its lights:
    ``kd * bounce_gain * sum_i I_i G_i`` (:func:`indirect_columns`), each light's bounce
    from its shadowed direct diffuse transport.

    Args:
        gbuffer: with intrinsics; kd ``(B, H, W, 3)``.
        light_position, light_intensity: ``(B, L, 3)`` (an unused slot has intensity 0).
        visibility: ``(B, L, H, W)`` in [0, 1] (1 lit).
        strength: a number or ``(B,)``: 1 is the first bounce and the later ones of
            :func:`bounce_gain`.
    """
    direct = light_transport(gbuffer, Material(kd=kd), light_position, shadows="none", specular=False,
                             falloff=Falloff.INVERSE_SQUARE if inverse_square else Falloff.NONE).diffuse
    columns = indirect_columns(gbuffer, kd, direct * visibility)  # (B, 3, L, H, W)
    bounce = (columns * light_intensity.transpose(1, 2)[..., None, None]).sum(2)
    strength = torch.as_tensor(strength, dtype=image.dtype, device=image.device).reshape(-1, 1, 1, 1)
    return image + strength * bounce
