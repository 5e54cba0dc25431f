"""The per-frame search as the network's teacher: its lights are where the albedo-free photometric error is least.

The network places a slot by choosing one of its position hypotheses (a classification)
and refining it; only the last, small step follows a loss's gradient. On real-looking
frames the photometric error's gradient at the network's answer points to a local minimum
of textures, highlights and indirect light, not to the lamp (measured on Mitsuba frames: on
a grid of +-0.1 of the scene size about the true light the re-render error is least at the
light in 25-28 of 64 frames, benchmarks/results/adapt_loss_landscape_cpu2_2026-11-29.md).
The estimator's per-frame search
(:func:`selfsup.adapt.frames.teach`) minimises the albedo-free error globally (grid, robust
fit, model selection), which finds the lamp on most frames; what it finds is the target of
each slot's hypothesis scores, its position and the count. No ground truth enters: the
teacher is the photometric objective's own minimiser.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from selfsup.linear import pseudo_huber
from selfsup.model import LightPrediction

__all__ = ["TeacherOptions", "teacher_loss"]


@dataclass(frozen=True)
class TeacherOptions:
    """Weights of the teacher's terms (mirrors ``adapt.teacher``): ``position`` (pseudo-Huber of
    the slot-to-light distance over the scene size, width ``scale``), ``anchors`` (cross
    entropy of the hypothesis scores against a Gaussian of width ``anchor_width`` of the scene
    size about the light), ``count`` (cross entropy of the count head against the lights found;
    0 by default: at 0.5 the adapted network stopped counting second lights, 25% -> 3% of the
    two-light test rooms, benchmarks/results/adapt_teacher_count_cpu2_2026-11-29.md). All 0:
    the photometric loss alone."""

    position: float = 1.0
    anchors: float = 0.1
    count: float = 0.0
    scale: float = 0.02
    anchor_width: float = 0.05

    def __post_init__(self):
        for name in ("position", "anchors", "count"):
            if getattr(self, name) < 0:
                raise ValueError(f"adapt.teacher.{name} must be >= 0, got {getattr(self, name)}")
        if self.scale <= 0 or self.anchor_width <= 0:
            raise ValueError("adapt.teacher.scale and adapt.teacher.anchor_width must be > 0")


def _assignment(position: Tensor, teacher: Tensor, mask: Tensor) -> Tensor:
    """``(B, K)`` long: the slot each teacher row goes to (a permutation of the slots, the one
    of least summed distance over the rows that are lights)."""
    B, K, _ = position.shape
    distance = torch.cdist(teacher, position.detach())  # (B, K rows, K slots)
    orders = torch.tensor(list(itertools.permutations(range(K))), device=position.device)  # (P, K)
    cost = (distance[:, torch.arange(K, device=position.device)[None], orders] * mask[:, None]).sum(-1)  # (B, P)
    return orders[cost.argmin(1)]


def teacher_loss(prediction: LightPrediction, teacher: Tensor, mask: Tensor, size: Tensor,
                 options: TeacherOptions) -> tuple[Tensor, dict[str, float]]:
    """``()`` loss of ``prediction`` against the teacher's lights ``teacher (B, K, 3)`` (rows of
    ``mask (B, K)``; an image without any is left out) and its parts; ``size (B,)`` the scenes' sizes."""
    zero = prediction.position.new_zeros(())
    has = mask.any(1)
    if not bool(has.any()):
        return zero, {}
    position, anchors, logits = prediction.position[has], prediction.anchor_position[has], prediction.anchor_logits[has]
    teacher, mask, size = teacher[has].to(position), mask[has], size[has].to(position)
    slot = _assignment(position, teacher, mask)  # (b, K)
    rows = torch.arange(len(slot), device=slot.device)[:, None]
    placed = position[rows, slot]  # (b, K, 3): the slot of each teacher row
    distance = (placed - teacher).norm(dim=-1) / size[:, None]
    weight = mask.to(position.dtype)
    position_term = (pseudo_huber(distance, options.scale) * weight).sum() / weight.sum()
    # Each assigned slot's hypotheses: a Gaussian about the teacher's light.
    spread = (anchors[rows, slot] - teacher[:, :, None]).norm(dim=-1) / size[:, None, None]  # (b, K, M)
    target = torch.softmax(-0.5 * (spread / options.anchor_width) ** 2, -1)
    anchor_term = -((target * torch.log_softmax(logits[rows, slot], -1)).sum(-1) * weight).sum() / weight.sum()
    count_term = F.cross_entropy(prediction.count_logits[has], mask.sum(1) - 1)
    total = options.position * position_term + options.anchors * anchor_term + options.count * count_term
    return total, {"teacher_position": float(position_term.detach()), "teacher_anchors": float(anchor_term.detach()),
                   "teacher_count": float(count_term.detach())}
