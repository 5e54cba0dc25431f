"""The network's working grid: a frame pooled to a few thousand cells, with its camera.

Everything :class:`selfsup.network.lightnet.IterativeLightNet` computes (features, votes,
re-renders) lives on one grid per frame: the image and G-buffer averaged over blocks
(valid pixels only) to about ``long_side`` cells along the longer side, the aspect kept,
and the intrinsics scaled with them, so that the renderer's screen-space shadows see a
pinhole camera. A frame already that small is used as it is.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from render import GBuffer
from selfsup.model import SceneFrame, scene_frame

__all__ = ["WorkGrid", "work_grid", "grid_size", "grey_log"]

# A cell counts as geometry where at least this share of its pixels is valid.
MIN_COVERAGE = 0.5


@dataclass
class WorkGrid:
    """A batch of frames on the working grid.

    Attributes:
        image: ``(B, 3, h, w)`` linear colour, the mean of each cell's valid pixels.
        gbuffer: ``(B, h, w)`` points (cell means), unit normals, mask, intrinsics ``(B, 3, 3)``.
        coverage: ``(B, h, w)`` share of each cell's pixels that are valid.
        frame: the full-resolution frame's normalisation (centre, size, exposure).
    """

    image: Tensor
    gbuffer: GBuffer
    coverage: Tensor
    frame: SceneFrame

    def normalised(self, position: Tensor) -> Tensor:
        """Metres ``(B, K, 3)`` -> scene units about the centre."""
        return (position - self.frame.centre[:, None]) / self.frame.size[:, None, None]

    def metres(self, normalised: Tensor) -> Tensor:
        """Scene units ``(B, K, 3)`` -> metres."""
        return self.frame.centre[:, None] + self.frame.size[:, None, None] * normalised


def grid_size(height: int, width: int, long_side: int) -> tuple[int, int]:
    """``(h, w)``: ``height x width`` scaled so that the longer side is at most ``long_side``."""
    scale = min(1.0, long_side / max(height, width))
    return max(1, round(height * scale)), max(1, round(width * scale))


def _pool(x: Tensor, size: tuple[int, int]) -> Tensor:
    return x if x.shape[-2:] == size else F.adaptive_avg_pool2d(x, size)


def work_grid(image: Tensor, gbuffer: GBuffer, long_side: int = 64) -> WorkGrid:
    """``image (B, 3, H, W)`` and its G-buffer (with intrinsics) on the working grid.

    Raises:
        ValueError: no intrinsics (the grid's camera and the shadows need them), an image
            whose shape is not the G-buffer's, or an image without a valid pixel.
    """
    if image.dim() != 4 or image.shape[1] != 3 or image.shape[-2:] != gbuffer.mask.shape[-2:]:
        raise ValueError(f"image must be (B, 3, H, W) with the G-buffer's (H, W) {tuple(gbuffer.mask.shape[-2:])}, "
                         f"got {tuple(image.shape)}")
    if gbuffer.intrinsics is None:
        raise ValueError("the G-buffer needs intrinsics (GBuffer.from_depth gives them): the working grid's camera "
                         "and its shadows are made from them")
    frame = scene_frame(image, gbuffer)
    H, W = image.shape[-2:]
    size = grid_size(H, W, long_side)
    mask = gbuffer.mask[:, None].to(image.dtype)
    if size == (H, W):
        return WorkGrid(image, gbuffer, mask[:, 0], frame)
    # (B, 3 + 3 + 3, H, W): colour, points and normals of the valid pixels; the invalid hold zeros.
    maps = torch.cat([image * mask, gbuffer.points.permute(0, 3, 1, 2), gbuffer.normals.permute(0, 3, 1, 2)], 1)
    coverage = _pool(mask, size)
    means = _pool(maps, size) / coverage.clamp_min(1e-6)
    normals = means[:, 6:9]
    length = normals.norm(dim=1, keepdim=True)
    # Cells of few valid pixels, or whose normals cancel (a crease), are left out.
    valid = (coverage[:, 0] >= MIN_COVERAGE) & (length[:, 0] > 0.5)
    h, w = size
    K = gbuffer.intrinsics.clone()
    sx, sy = w / W, h / H
    # Pixel centres: u' + 0.5 = (u + 0.5) * sx.
    K[:, 0, 0], K[:, 0, 2] = K[:, 0, 0] * sx, (K[:, 0, 2] + 0.5) * sx - 0.5
    K[:, 1, 1], K[:, 1, 2] = K[:, 1, 1] * sy, (K[:, 1, 2] + 0.5) * sy - 0.5
    grid = GBuffer(means[:, 3:6].permute(0, 2, 3, 1), (normals / length.clamp_min(1e-6)).permute(0, 2, 3, 1), valid, K)
    return WorkGrid(means[:, :3] * valid[:, None], grid, coverage[:, 0] * valid, frame)


def grey_log(image: Tensor, mask: Tensor, exposure: Tensor) -> tuple[Tensor, Tensor]:
    """The log of the channels' mean of ``image (B, 3, h, w)`` over ``exposure (B,)``, and
    where it is usable ``(B, h, w)`` bool: valid and above 1e-4 of the exposure (darker
    pixels hold no shading a camera resolves; their log is held at that floor)."""
    grey = image.mean(1) / exposure[:, None, None]
    usable = mask & (grey > 1e-4)
    return torch.log(grey.clamp_min(1e-4)), usable
