"""Image and geometry features, computed once a frame (RAFT's feature encoder)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from selfsup.network.grid import WorkGrid, grey_log

__all__ = ["Encoder", "encoder_inputs", "ENCODER_CHANNELS"]

ENCODER_CHANNELS = 11


def encoder_inputs(grid: WorkGrid) -> Tensor:
    """``(B, 11, h, w)``: colour over the exposure (clamped to [0, 4]), the log grey level
    (over the exposure, / 4), points in scene units about the centre, normals, and the mask;
    zeros off the mask."""
    g, frame = grid.gbuffer, grid.frame
    mask = g.mask[:, None].to(grid.image.dtype)
    colour = (grid.image / frame.exposure[:, None, None, None]).clamp(0, 4)
    log_grey, _ = grey_log(grid.image, g.mask, frame.exposure)
    points = (g.points - frame.centre[:, None, None]) / frame.size[:, None, None, None]
    maps = torch.cat([colour, log_grey[:, None] / 4, points.permute(0, 3, 1, 2), g.normals.permute(0, 3, 1, 2)], 1)
    return torch.cat([maps * mask, mask], 1)


def _conv(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    groups = 8 if cout % 8 == 0 else 1
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.GroupNorm(groups, cout), nn.SiLU())


class Encoder(nn.Module):
    """A small U-Net: ``forward(grid) -> (features (B, C, h, w), global (B, G))``.

    Args:
        widths: channels at full, half, quarter and eighth resolution.
        global_width: the pooled vector's width.
    """

    def __init__(self, widths: tuple[int, ...] = (32, 48, 64, 96), global_width: int = 128):
        super().__init__()
        if len(widths) < 2 or min(widths) < 1 or global_width < 1:
            raise ValueError(f"widths needs at least two stages of >= 1 channels and global_width >= 1, got "
                             f"{list(widths)} and {global_width}")
        self.widths = tuple(widths)
        self.stem = nn.Sequential(_conv(ENCODER_CHANNELS, widths[0]), _conv(widths[0], widths[0]))
        self.down = nn.ModuleList(nn.Sequential(_conv(a, b, 2), _conv(b, b)) for a, b in zip(widths[:-1], widths[1:]))
        self.up = nn.ModuleList(_conv(b + a, a) for a, b in zip(widths[:-1], widths[1:]))
        self.global_out = nn.Sequential(nn.Linear(widths[-1], global_width), nn.SiLU())
        self.channels = widths[0]
        self.global_width = global_width

    def forward(self, grid: WorkGrid) -> tuple[Tensor, Tensor]:
        x = self.stem(encoder_inputs(grid))
        skips = [x]
        for stage in self.down:
            x = stage(x)
            skips.append(x)
        mask = F.adaptive_max_pool2d(grid.gbuffer.mask[:, None].to(x.dtype), x.shape[-2:])
        pooled = (x * mask).sum((2, 3)) / mask.sum((2, 3)).clamp_min(1)
        for stage, skip in zip(reversed(self.up), reversed(skips[:-1])):
            x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = stage(torch.cat([skip, x], 1))
        return x, self.global_out(pooled)
