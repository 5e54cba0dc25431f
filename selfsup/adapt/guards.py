"""What adaptation refuses: lights in or behind the surfaces, networks that collapse or forget.

A loss that solves the albedo has degenerate minima a loss given the albedo has not: a
light pressed against a wall lights one spot a hundred times brighter than the rest,
and a free albedo per region absorbs what that spot does to the others; a light behind
the visible surface lights nothing the camera sees but what the shadow test lets
through. Both are physically impossible for a lamp the camera's room holds, so the loss
pushes slots out of them (:func:`guard_penalty`), and a checkpoint whose held-back frames
show more of them than the starting network's is refused (:func:`refusals`), as one
that switches more slots on (every slot on explains the most) or forgets the procedural
scenes it was trained on.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from render import GBuffer
from render.geometry import fit_intrinsics

__all__ = ["GuardOptions", "surface_violation", "degenerate_lights", "guard_penalty", "refusals"]


@dataclass(frozen=True)
class GuardOptions:
    """Thresholds of the guards (mirrors ``adapt.guards``).

    ``clearance``: least distance of a light from the nearest seen surface point, as a
    share of the scene size (the generator keeps lights 0.15 m from walls: about 0.025 of
    a room's diagonal); ``behind``: how far past the surface seen at its pixel a light
    may be (share of the scene size) before it counts as behind it;
    ``max_degenerate_rise``: the share of held-back frames with a degenerate counted
    light may rise by this much over the starting network's; ``max_count_rise``: their
    mean count may rise by this many lights; ``forgetting``: the procedural validation's
    median position error may grow by this share.
    """

    clearance: float = 0.02
    behind: float = 0.02
    max_degenerate_rise: float = 0.1
    max_count_rise: float = 0.5
    forgetting: float = 0.1

    def __post_init__(self):
        for name in ("clearance", "behind", "max_degenerate_rise", "max_count_rise", "forgetting"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value >= 0):
                raise ValueError(f"adapt.guards.{name} must be a number >= 0, got {value!r}")


def surface_violation(position: Tensor, gbuffer: GBuffer, size: Tensor, options: GuardOptions,
                      stride: int = 4) -> tuple[Tensor, Tensor]:
    """How far each light is inside its clearance and behind the seen surface, as shares of
    the scene size: ``(too_close (B, K), behind (B, K))``, both >= 0 (0: no violation).
    Differentiable in ``position (B, K, 3)`` (camera frame, metres).

    ``too_close``: ``clearance - d / size`` where the nearest valid point (every
    ``stride``-th pixel) is ``d`` away; ``behind``: ``(z - depth) / size - behind`` where the
    light projects onto a valid pixel whose depth is ``depth`` and the light's ``z`` exceeds it.
    """
    B, K, _ = position.shape
    points = gbuffer.points[:, ::stride, ::stride].reshape(B, -1, 3)
    valid = gbuffer.mask[:, ::stride, ::stride].reshape(B, -1)
    distance = torch.cdist(position, points.to(position.dtype))  # (B, K, N)
    distance = torch.where(valid[:, None], distance, torch.full_like(distance, torch.inf)).amin(-1)
    too_close = (options.clearance - distance / size[:, None]).clamp_min(0)

    intrinsics = gbuffer.intrinsics if gbuffer.intrinsics is not None else fit_intrinsics(gbuffer.points, gbuffer.mask)
    H, W = gbuffer.mask.shape[1:]
    z = position[..., 2]
    projected = position @ intrinsics.to(position.dtype).transpose(1, 2)  # (B, K, 3)
    ahead = z > 1e-6
    u = torch.where(ahead, projected[..., 0] / z.clamp_min(1e-6), torch.full_like(z, -1.0)).detach().floor().long()
    v = torch.where(ahead, projected[..., 1] / z.clamp_min(1e-6), torch.full_like(z, -1.0)).detach().floor().long()
    inside = ahead & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    flat = (v.clamp(0, H - 1) * W + u.clamp(0, W - 1))
    seen = gbuffer.mask.flatten(1).gather(1, flat) & inside
    depth = gbuffer.points[..., 2].flatten(1).gather(1, flat).to(position.dtype)
    behind = torch.where(seen, ((z - depth) / size[:, None] - options.behind).clamp_min(0), torch.zeros_like(z))
    return too_close, behind


def degenerate_lights(position: Tensor, gbuffer: GBuffer, size: Tensor, options: GuardOptions) -> Tensor:
    """``(B, K)`` bool: lights closer to a seen surface than the clearance, or behind the
    surface seen at their pixel (:func:`surface_violation`)."""
    too_close, behind = surface_violation(position, gbuffer, size, options)
    return (too_close > 0) | (behind > 0)


def guard_penalty(position: Tensor, gbuffer: GBuffer, size: Tensor, options: GuardOptions) -> Tensor:
    """``()``: the mean over images of the slots' summed violations (:func:`surface_violation`):
    a hinge that is 0 for every light in the room's free space and pushes others out."""
    too_close, behind = surface_violation(position, gbuffer, size, options)
    return (too_close + behind).sum(1).mean()


def refusals(start: dict, now: dict, options: GuardOptions) -> list[str]:
    """Why a checkpoint with validation ``now`` is refused against the starting network's
    ``start`` (both with ``degenerate_share``, ``mean_count`` on the held-back frames and
    ``procedural_median_error``); empty: accepted."""
    reasons = []
    if now["degenerate_share"] > start["degenerate_share"] + options.max_degenerate_rise:
        reasons.append(f"lights in or behind surfaces in {now['degenerate_share']:.0%} of the held-back frames "
                       f"(the start: {start['degenerate_share']:.0%})")
    if now["mean_count"] > start["mean_count"] + options.max_count_rise:
        reasons.append(f"{now['mean_count']:.2f} lights a held-back frame (the start: {start['mean_count']:.2f}): "
                       "slots switched on to explain more")
    if now["procedural_median_error"] > start["procedural_median_error"] * (1 + options.forgetting):
        reasons.append(f"procedural median position error {now['procedural_median_error']:.4f} against the start's "
                       f"{start['procedural_median_error']:.4f}: forgetting")
    return reasons
