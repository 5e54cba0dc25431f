"""A dense vote field: each cell's ray towards the light that shades it, and where the rays meet.

The PVNet / VoteNet pattern: a head predicts, at each cell of the working grid and for each
light slot, a unit direction from the cell's point towards that slot's light and a weight.
The slot's light is the weighted least-squares point nearest to all the rays,
``x = (sum w_i A_i)^-1 sum w_i A_i p_i`` with ``A_i = I - d_i d_i^T`` (the projector off ray
``i``), a differentiable 3x3 solve. A ridge of ``RIDGE`` of the weights' sum pulls the point
towards the scene's centre, so that nearly parallel rays (a far light) still give a point.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["VoteHead", "meeting_point", "RIDGE"]

RIDGE = 1e-3


def meeting_point(points: Tensor, direction: Tensor, weight: Tensor) -> Tensor:
    """Weighted least-squares point of the rays ``points + t direction``.

    Args:
        points: ``(B, h, w, 3)`` the rays' origins (scene units).
        direction: ``(B, K, h, w, 3)`` unit directions, one field per slot.
        weight: ``(B, K, h, w)`` >= 0 (0 for cells that do not vote).

    Returns:
        ``(B, K, 3)``: each slot's point (the origin, the scene's centre, where no cell votes).
    """
    eye = torch.eye(3, dtype=points.dtype, device=points.device)
    projector = eye - direction[..., :, None] * direction[..., None, :]  # (B, K, h, w, 3, 3)
    w = weight[..., None, None]
    system = (w * projector).sum((2, 3))  # (B, K, 3, 3)
    rhs = (w * projector @ points[:, None, ..., None]).sum((2, 3))[..., 0]  # (B, K, 3)
    total = weight.sum((2, 3))[..., None, None]
    # The ridge: a point where the rays say nothing (zero weight, parallel rays) stays at 0.
    system = system + (RIDGE * total + 1e-9) * eye
    return torch.linalg.solve(system, rhs[..., None])[..., 0]


class VoteHead(nn.Module):
    """Per cell and slot, a direction to the light and a vote weight, from features.

    ``forward(features (B, C, h, w), mask (B, h, w)) -> (direction (B, K, h, w, 3) unit,
    weight (B, K, h, w) >= 0, 0 off the mask)``.
    """

    def __init__(self, channels: int, slots: int):
        super().__init__()
        self.slots = slots
        self.out = nn.Conv2d(channels, 4 * slots, 1)
        with torch.no_grad():
            self.out.weight.mul_(0.1)
            self.out.bias.zero_()
            # Rays start pointing up (the camera's -y): most rooms are lit from above.
            self.out.bias.view(slots, 4)[:, 1] = -1.0

    def forward(self, features: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
        B, _, h, w = features.shape
        raw = self.out(features).view(B, self.slots, 4, h, w)
        direction = F.normalize(raw[:, :, :3].permute(0, 1, 3, 4, 2), dim=-1, eps=1e-6)
        weight = F.softplus(raw[:, :, 3]) * mask[:, None].to(raw.dtype)
        return direction, weight
