"""Small analytic test scenes with exact ground truth: objects on a floor.

Used by the renderer's correctness tests and the shadow-accuracy benchmark.
Everything is computed by exact ray casting (:mod:`selfsup.scenes.raycast`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from selfsup.scenes.raycast import Primitives, camera_rays, cast_rays, exact_visibility, shade_exact

__all__ = ["ExactView", "ShadowAgreement", "objects_on_floor", "render_exact_view", "intrinsics_for", "compare_to_exact",
           "shadow_edge_band"]


@dataclass(frozen=True)
class ExactView:
    """Exact G-buffer and image of one view; all ``(H, W, ...)`` float64.

    ``depth (H, W)`` (0 where no hit), ``points/normals (H, W, 3)``,
    ``mask (H, W)``, ``visibility (H, W, L)``, ``image (H, W, 3)``, ``K (3, 3)``.
    """

    depth: Tensor
    points: Tensor
    normals: Tensor
    mask: Tensor
    visibility: Tensor
    image: Tensor
    K: Tensor


def intrinsics_for(height: int, width: int, fov_x_deg: float = 60.0, dtype=torch.float64) -> Tensor:
    """Pinhole ``K (3, 3)`` with square pixels, principal point at the image centre."""
    f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    return torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], dtype=dtype)


def objects_on_floor(scale: float = 1.0) -> Primitives:
    """A sphere and a rotated box resting on a floor, with a back wall; camera at the origin."""
    c, s = math.cos(0.5), math.sin(0.5)
    rot_y = [c, 0, s, 0, 1, 0, -s, 0, c]
    prims = Primitives(
        planes=torch.tensor([[0, 1.0, 0, 0, -1, 0], [0, 0, 7.0, 0, 0, -1]], dtype=torch.float64),
        spheres=torch.tensor([[-0.4, 0.5, 4.0, 0.5]], dtype=torch.float64),
        boxes=torch.tensor([[0.9, 0.65, 4.6, 0.35, 0.35, 0.35, *rot_y]], dtype=torch.float64),
    )
    prims.planes[:, :3] *= scale
    prims.spheres[:, :4] *= scale
    prims.boxes[:, :6] *= scale
    return prims


def render_exact_view(
    prims: Primitives,
    K: Tensor,
    height: int,
    width: int,
    light_position: Tensor,
    light_intensity: Tensor,
    *,
    kd: float = 0.6,
    ks: float = 0.0,
    shininess: float = 20.0,
    ambient: float = 0.05,
    falloff: str = "inverse_square",
) -> ExactView:
    """Ray cast the primitives from the origin through pixel centres and shade exactly.

    Normals are flipped to face the camera; light_position/intensity are ``(L, 3)``.
    """
    dirs = camera_rays(K, height, width)
    hit = cast_rays(prims, torch.zeros_like(dirs), dirs)
    mask = torch.isfinite(hit.t)
    t = torch.where(mask, hit.t, torch.zeros_like(hit.t))
    points = dirs * t[:, None]
    normals = hit.normal * torch.where((hit.normal * dirs).sum(-1, keepdim=True) > 0, -1.0, 1.0)
    normals = torch.where(mask[:, None], normals, torch.zeros_like(normals))
    vis = exact_visibility(prims, points, normals, light_position)
    R = points.shape[0]
    image = shade_exact(
        points, normals, vis,
        torch.full((R, 3), kd, dtype=points.dtype), torch.full((R, 1), ks, dtype=points.dtype),
        torch.full((R,), shininess, dtype=points.dtype), light_position, light_intensity,
        torch.full((3,), ambient, dtype=points.dtype), falloff,
    )
    image = torch.where(mask[:, None], image, torch.zeros_like(image))
    return ExactView(
        depth=t.reshape(height, width), points=points.reshape(height, width, 3),
        normals=normals.reshape(height, width, 3), mask=mask.reshape(height, width),
        visibility=vis.reshape(height, width, -1) * mask.reshape(height, width, 1),
        image=image.reshape(height, width, 3), K=K,
    )


@dataclass(frozen=True)
class ShadowAgreement:
    """How a render matches an exact view, on valid pixels away from the 1-pixel
    band around exact shadow edges: ``agree``, the share whose lit/shadowed class
    (visibility > 0.5) matches the exact shadow rays; ``lit_within_1e-4``, the share
    of exactly lit pixels whose value is within 1e-4 relative."""

    agree: float
    lit_within_1e4: float


def shadow_edge_band(visibility: Tensor, pixels: int = 1) -> Tensor:
    """Pixels ``(..., H, W)`` bool whose neighbourhood of ``pixels`` either side holds both
    classes of the exact ``visibility (..., H, W)`` (0 or 1): the band at shadow edges
    (one pixel by default) where a pixel-sized disagreement is a matter of sampling,
    left out of the comparisons."""
    e = visibility.reshape(-1, 1, *visibility.shape[-2:])
    size = 2 * pixels + 1
    band = F.max_pool2d(e, size, 1, pixels) != -F.max_pool2d(-e, size, 1, pixels)
    return band.reshape(visibility.shape)


def compare_to_exact(view: ExactView, visibility: Tensor, image: Tensor) -> ShadowAgreement:
    """Compare a render's ``visibility (H, W)`` and ``image (H, W, 3)`` with ``view`` (one light)."""
    exact = view.visibility[..., 0]
    keep = view.mask & ~shadow_edge_band(exact)
    agree = ((visibility > 0.5) == (exact > 0.5))[keep].double().mean().item()
    lit = keep & (exact > 0.5)
    rel = ((image.to(view.image.dtype) - view.image).abs() / view.image).amax(-1)[lit]
    return ShadowAgreement(agree, (rel <= 1e-4).double().mean().item())
