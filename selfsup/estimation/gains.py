"""Per-surface albedo gains: each smooth surface's albedo rescaled by what a fit says it is
(``tuning.reflectance_gains``, used by :mod:`selfsup.estimation.stages`)."""

from __future__ import annotations

import torch
from torch import Tensor

from selfsup.estimation import albedo_free

__all__ = ["segment_gains"]


def segment_gains(image: Tensor, model: Tensor, segments: Tensor, min_pixels: int = 30, lit_share: float = 0.2,
                  limits: tuple[float, float] = (0.2, 5.0)) -> Tensor:
    """Per-surface albedo factors ``(B, H, W, 3)``: on each segment and channel, the
    median of ``image / model`` over its pixels lit to at least ``lit_share`` of the
    segment's brightest model value (shadows and dark sides say little), clamped to
    ``limits``; 1 on segments with fewer than ``min_pixels`` such pixels and outside.

    Args:
        image, model: ``(B, 3, H, W)``; segments: ``(B, H, W)`` labels (-1: none),
        e.g. :func:`selfsup.estimation.normals.surface_segments`.
    """
    B, C, H, W = image.shape
    label = segments.reshape(B, 1, H * W).expand(B, C, H * W)
    inside = label >= 0
    # One group per (image, segment, channel): segment labels are flat pixel indices.
    group = ((torch.arange(B, device=image.device)[:, None, None] * (H * W) + label.clamp_min(0)) * C
             + torch.arange(C, device=image.device)[None, :, None]).reshape(-1)
    model = model.reshape(B, C, H * W)
    groups = B * H * W * C
    # Outside pixels share group 0's index (label clamped): their model values must not count there.
    brightest = model.new_zeros(groups).scatter_reduce_(0, group, (model * inside).reshape(-1), "amax")
    ratio = (image.reshape(B, C, H * W) / model.clamp_min(1e-12)).reshape(-1)
    use = (inside & (model > lit_share * brightest[group].view_as(model))).reshape(-1) & torch.isfinite(ratio)
    values, owner = ratio[use], group[use]
    if not values.numel():
        return torch.ones_like(image).permute(0, 2, 3, 1)
    median, counts = albedo_free.group_medians(values, owner, groups)
    factor = torch.where(counts >= min_pixels, median.clamp(*limits), torch.ones_like(median))
    factor = torch.where(inside.reshape(-1), factor[group], torch.ones_like(ratio))
    return factor.view(B, C, H, W).permute(0, 2, 3, 1)
