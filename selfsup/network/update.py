"""One update step: read the frame against its re-render, weigh the pixels, take the step.

RAFT's update block, with physics for its correlation: the current lights are re-rendered
on the working grid with cast shadows (:func:`selfsup.network.physics.rerender`); a small
CNN reads the encoder's features, the log residual of the frame against the re-render,
and each slot's shadow mask and share of the shading, and says (1) how much each pair of
neighbouring cells is to be trusted (:data:`selfsup.network.physics.PAIR_OFFSETS`: where an
albedo edge, a highlight or an unmodelled shadow breaks the model, a low weight), (2) by
how much each slot's presence changes (a light added or dropped), (3) the step's damping.
The step itself is the weighted Gauss-Newton step of the pair residuals
(:func:`selfsup.network.physics.gauss_newton_step`), differentiable in the weights.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from selfsup.network.grid import WorkGrid
from selfsup.network.physics import PAIR_OFFSETS, LightState, Rerender, gauss_newton_step, log_residual

__all__ = ["UpdateBlock"]


def _conv(cin: int, cout: int) -> nn.Sequential:
    groups = 8 if cout % 8 == 0 else 1
    return nn.Sequential(nn.Conv2d(cin, cout, 3, 1, 1, bias=False), nn.GroupNorm(groups, cout), nn.SiLU())


class UpdateBlock(nn.Module):
    """``forward(grid, features, global, observed, usable, state, render, logits) -> (state,
    presence logits (B, K), weights (B, 4, h, w), cost (B,))``.

    Args:
        channels: the encoder's feature channels; global_width: its global vector's.
        slots: K; width: this block's channels.
        use_render: False reads no re-render (an ablation: the weights then see the image
            and geometry alone, the same at every step).
    """

    def __init__(self, channels: int, global_width: int, slots: int, width: int = 48, use_render: bool = True):
        super().__init__()
        self.slots = slots
        self.use_render = use_render
        self.body = nn.Sequential(_conv(channels + 2 + 2 * slots, width), _conv(width, width), _conv(width, width))
        self.weights_out = nn.Conv2d(width, len(PAIR_OFFSETS), 1)
        self.slot_out = nn.Sequential(nn.Linear(2 * width + global_width + 2, width), nn.SiLU(), nn.Linear(width, 1))
        self.damping_out = nn.Linear(width + global_width, 1)
        with torch.no_grad():  # start near uniform weights (sigmoid(2) = 0.88), no presence change, damping 0.1
            self.weights_out.weight.mul_(0.1)
            self.weights_out.bias.fill_(2.0)
            self.slot_out[-1].weight.mul_(0.1)
            self.slot_out[-1].bias.zero_()
            self.damping_out.weight.mul_(0.1)
            self.damping_out.bias.fill_(-2.25)

    def forward(self, grid: WorkGrid, features: Tensor, global_features: Tensor, observed: Tensor, usable: Tensor,
                state: LightState, render: Rerender, logits: Tensor):
        mask = grid.gbuffer.mask[:, None].to(features.dtype)
        residual = log_residual(observed, render.shading, usable)[:, None].clamp(-2, 2)
        gain = state.presence * state.log_gain.exp()
        share = (gain[:, :, None, None] * render.transport) / render.shading.clamp_min(1e-12)[:, None]
        maps = torch.cat([residual, residual.abs(), render.visibility * mask, share.clamp(0, 1)], 1)
        if not self.use_render:
            maps = torch.zeros_like(maps)
        x = self.body(torch.cat([features, maps.to(features.dtype)], 1))
        weights = torch.sigmoid(self.weights_out(x)).float()
        total = mask.sum((2, 3)).clamp_min(1)
        pooled = (x * mask).sum((2, 3)) / total  # (B, C)
        slot_weight = share.to(x.dtype) * mask  # (B, K, h, w)
        per_slot = torch.einsum("bchw,bkhw->bkc", x, slot_weight) / slot_weight.sum((2, 3))[..., None].clamp_min(1e-6)
        stats = torch.stack([(residual.abs() * mask).sum((1, 2, 3)) / total[:, 0],
                             (residual * mask).pow(2).sum((1, 2, 3)).div(total[:, 0]).sqrt()], 1).to(x.dtype)
        K = self.slots
        slot_in = torch.cat([pooled[:, None].expand(-1, K, -1), per_slot, global_features[:, None].expand(-1, K, -1),
                             stats[:, None].expand(-1, K, -1)], -1)
        logits = logits + self.slot_out(slot_in)[..., 0].float()
        damping = F.softplus(self.damping_out(torch.cat([pooled, global_features], 1))[:, 0].float()) + 1e-4
        new, cost = gauss_newton_step(state, observed, usable, render, weights, damping)
        presence = torch.sigmoid(logits)
        presence = torch.cat([torch.ones_like(presence[:, :1]), presence[:, 1:]], 1)
        return LightState(new.position, new.log_gain, new.log_ambient, presence, new.vignetting), logits, weights, cost
