"""Closed-form light intensities and ambient for fixed light positions.

The image model is linear in the intensities and the ambient term, so for given
light transport maps the best of them is a small weighted least-squares problem
per image and channel (``L + 1`` unknowns). Both the training loss and the
per-image refinement solve it, so that the light positions are all that is
searched for (variable projection).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["basis_images", "solve_intensities"]


def basis_images(kd: Tensor, ks: Tensor | None, diffuse: Tensor, specular: Tensor | None) -> Tensor:
    """Per-channel images ``(B, 3, L, H, W)`` of unit-intensity lights: ``kd_c D_i + ks_c S_i``.

    Args:
        kd: ``(B, H, W, 3)``; ks: ``(B, H, W, 1|3)`` or None.
        diffuse, specular: ``(B, L, H, W)`` transport maps (specular may be None).
    """
    cols = kd.permute(0, 3, 1, 2)[:, :, None] * diffuse[:, None]
    if specular is not None and ks is not None:
        cols = cols + ks.permute(0, 3, 1, 2)[:, :, None] * specular[:, None]
    return cols


def solve_intensities(cols: Tensor, kd: Tensor, image: Tensor, weights: Tensor, ambient: Tensor | None = None,
                      ridge: float = 1e-9) -> tuple[Tensor, Tensor, Tensor]:
    """Weighted least-squares intensities (and ambient) for basis images ``cols``.

    Args:
        cols: ``(B, 3, L, H, W)`` from :func:`basis_images`; an all-zero column (a
            light switched off) gets intensity 0.
        kd: ``(B, H, W, 3)`` albedo (the ambient term's image is ``kd * L_a``).
        image: observed ``(B, 3, H, W)``.
        weights: ``(B, 3, H, W)`` per-value weights (0 on invalid pixels).
        ambient: known ambient ``(B, 3)``, or None to solve for it.
        ridge: Tikhonov term relative to the trace of the normal matrix.

    Returns:
        intensity ``(B, L, 3)`` (>= 0), ambient ``(B, 3)`` (the known one if given,
        else solved, >= 0) and the model image ``(B, 3, H, W)`` (not masked).
    """
    L = cols.shape[2]
    kd_image = kd.permute(0, 3, 1, 2)
    target = image
    if ambient is not None:
        target = target - kd_image * ambient[:, :, None, None]
    else:
        cols = torch.cat([cols, kd_image[:, :, None]], 2)
    k = cols.shape[2]
    a = cols.flatten(3)  # (B, 3, k, N)
    w = weights.flatten(2)[:, :, None]  # (B, 3, 1, N)
    normal = (a * w) @ a.transpose(-1, -2)  # (B, 3, k, k)
    rhs = ((a * w) @ target.flatten(2)[..., None]).squeeze(-1)  # (B, 3, k)
    # The ridge keeps a light that lights nothing solvable (intensity -> 0).
    scale = ridge * normal.diagonal(dim1=-2, dim2=-1).sum(-1).clamp_min(1e-30)
    eye = torch.eye(k, dtype=a.dtype, device=a.device)
    x, info = torch.linalg.solve_ex(normal + scale[..., None, None] * eye, rhs[..., None])
    # A singular system (no lit pixel at all) gives no light rather than an exception.
    x = torch.where((info == 0)[..., None, None] & torch.isfinite(x), x, torch.zeros_like(x)).squeeze(-1).clamp_min(0)
    model = (x[..., None, None] * cols).sum(2)
    if ambient is not None:
        model = model + kd_image * ambient[:, :, None, None]
    else:
        ambient = x[:, :, L]
    return x[:, :, :L].transpose(1, 2), ambient, model
