"""Blinn-Phong lighting math as plain functions, channel-last, batched over lights.

Shapes use B batch, L lights, H, W image. Every function broadcasts its inputs
with torch rules; the shapes below are the ones the renderer passes.
"""

from __future__ import annotations

from enum import Enum
from typing import NamedTuple

import torch
from torch import Tensor

from render.geometry import dot3, norm3

__all__ = ["Falloff", "LightGeometry", "light_geometry", "falloff_factor", "blinn_phong_lobe",
           "shading_and_position_gradients"]


class Falloff(str, Enum):
    """Distance attenuation ``f(d)`` of a point light (``meta.falloff`` of scene files)."""

    INVERSE_SQUARE = "inverse_square"  # f = 1/d^2, physical; the default
    NONE = "none"  # f = 1, as written in the Blinn-Phong light-estimation paper


class LightGeometry(NamedTuple):
    """See :func:`light_geometry`."""

    to_light: Tensor  # (B, L, H, W, 3) unit, surface to light
    distance: Tensor  # (B, L, H, W)
    to_viewer: Tensor  # (B, 1, H, W, 3) unit, surface to camera centre


def _safe_normalize(v: Tensor, length: Tensor, eps: Tensor) -> Tensor:
    # Guard: a zero vector (light on the point, point at the camera) would give
    # 0/0; dividing by max(length, eps) keeps values and gradients finite.
    return v / torch.maximum(length, eps)[..., None]


def light_geometry(points: Tensor, light_position: Tensor) -> LightGeometry:
    """Unit vectors and distances between surface points, lights and the camera.

    Args:
        points: ``(B, 1, H, W, 3)`` camera-frame points.
        light_position: ``(B, L, 1, 1, 3)``.

    Returns:
        ``to_light`` ``(B, L, H, W, 3)`` unit vector from surface to light,
        ``distance`` ``(B, L, H, W)``, ``to_viewer`` ``(B, 1, H, W, 3)`` unit vector
        from surface to camera centre.

    Example:
        >>> g = light_geometry(torch.tensor([[[[[0.0, 0, 1]]]]]), torch.tensor([[[[[0.0, 0, 3]]]]]))
        >>> g.to_light[0, 0, 0, 0], g.distance[0, 0, 0, 0]
        (tensor([0., 0., 1.]), tensor(2.))
    """
    offset, distance, depth, eps = light_offset(points, light_position)
    to_light = offset / distance[..., None]
    to_viewer = _safe_normalize(-points, depth, eps)
    return LightGeometry(to_light, distance, to_viewer)


def light_offset(points: Tensor, light_position: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The unnormalised half of :func:`light_geometry`: ``offset`` (surface to light,
    shapes as there), guarded ``distance``, and the points' ``depth`` and ``eps``
    (the guard's floor)."""
    offset = light_position - points
    # Square-root guard: sqrt'(0) is infinite; the clamp keeps the gradient finite
    # for a light exactly on the surface. The scale-aware floor (1e-6 of the
    # point's distance to the camera) works for millimetre and kilometre scenes.
    depth = norm3(points)
    eps = 1e-6 * depth.clamp_min(torch.finfo(points.dtype).tiny ** 0.25)
    distance = dot3(offset, offset).clamp_min(torch.finfo(points.dtype).tiny).sqrt()
    return offset, torch.maximum(distance, eps), depth, eps


def falloff_factor(distance: Tensor, falloff: Falloff | str) -> Tensor:
    """``f(d)``: ``1/d^2`` (inverse_square) or 1 (none); same shape as ``distance``."""
    falloff = Falloff(falloff)
    if falloff is Falloff.NONE:
        return torch.ones_like(distance)
    return 1.0 / (distance * distance)


def blinn_phong_lobe(normals: Tensor, to_light: Tensor, to_viewer: Tensor, shininess: Tensor) -> Tensor:
    """``max(0, n . h)^alpha`` with ``h = normalize(l + v)``, ``(B, L, H, W)``.

    Args:
        normals: ``(B, 1, H, W, 3)``.
        to_light: ``(B, L, H, W, 3)`` unit vectors.
        to_viewer: ``(B, 1, H, W, 3)`` unit vectors.
        shininess: alpha, broadcastable to ``(B, L, H, W)`` (e.g. ``(B, 1, H, W)``).

    Example:
        >>> n = torch.tensor([0.0, 0, -1])
        >>> blinn_phong_lobe(n, n, n, torch.tensor(1000.0)).item()
        1.0
    """
    _, _, safe, lit = _half_vector(normals, to_light, to_viewer)
    return torch.where(lit, safe.pow(shininess), torch.zeros_like(safe))


def _half_vector(normals: Tensor, to_light: Tensor, to_viewer: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    # h, |l + v| (1 where undefined), n.h (1 where unlit) and where the lobe is lit.
    half = to_light + to_viewer
    length = norm3(half)
    # Guard: h is undefined when the light is exactly opposite the viewer (l = -v);
    # the lobe is then taken as 0 (n.h has no preferred value) with a zero gradient.
    ok = length > 1e-6
    length = torch.where(ok, length, torch.ones_like(length))
    half = half / length[..., None]
    n_dot_h = dot3(normals, half)
    lit = ok & (n_dot_h > 1e-12)
    # Pow guard: for alpha < 1 the derivative of x^alpha is infinite at 0; the
    # masked branch gets a safe base of 1 so its (discarded) gradient stays finite.
    return half, length, torch.where(lit, n_dot_h, torch.ones_like(n_dot_h)), lit


def shading_and_position_gradients(normals: Tensor, geometry: LightGeometry, shininess: Tensor,
                                   falloff: Falloff | str, with_specular: bool = True
                                   ) -> tuple[Tensor, Tensor | None, Tensor, Tensor | None]:
    """The unshadowed transport ``diffuse = f(d) max(0, n.l)`` and ``specular = f(d)
    max(0, n.h)^alpha`` ``(B, L, H, W)`` and their exact derivatives with respect to each light's position
    ``(B, L, H, W, 3)``, sharing every intermediate (a Gauss-Newton step needs all four;
    computed apart, n.l, the falloff and the half vector are computed twice). Specular
    terms are None without ``with_specular``.

    With ``o = p - X``, ``d = |o|``, ``l = o / d`` and ``h = (l + v) / |l + v|``:
    ``dl/dp = (I - l l^T) / d``, ``dh/dp = (I - h h^T) / |l + v| dl/dp`` and
    ``df/dp = f'(d) l``. Where a term is clamped to 0 its derivative is 0.

    Args:
        normals: ``(B, 1, H, W, 3)``; geometry: :func:`light_geometry` of the lights.
        shininess: alpha, broadcastable to ``(B, L, H, W)``.
        with_specular: False skips the specular terms (returned as None).

    Returns:
        ``diffuse``, ``specular`` ``(B, L, H, W)`` and ``d diffuse_i / d p_i``,
        ``d specular_i / d p_i`` ``(B, L, H, W, 3)``.
    """
    to_light, distance, to_viewer = geometry
    f = falloff_factor(distance, falloff)
    # f'(d) / f: -2/d for 1/d^2, 0 for no falloff.
    log_slope = -2.0 / distance if Falloff(falloff) is Falloff.INVERSE_SQUARE else torch.zeros_like(distance)
    n_dot_l = dot3(normals, to_light)
    lit = n_dot_l > 0
    diffuse = f * n_dot_l.clamp_min(0)
    d_n_dot_l = (normals - n_dot_l[..., None] * to_light) / distance[..., None]
    d_diffuse = f[..., None] * (d_n_dot_l + (n_dot_l * log_slope)[..., None] * to_light)
    d_diffuse = torch.where(lit[..., None], d_diffuse, torch.zeros_like(d_diffuse))
    if not with_specular:
        return diffuse, None, d_diffuse, None
    half, length, safe, lobe_lit = _half_vector(normals, to_light, to_viewer)
    lobe = torch.where(lobe_lit, safe.pow(shininess), torch.zeros_like(safe))
    # d(n.h)/dp = (I - l l^T)(n - (n.h) h) / (d |l + v|); 0 where unlit (lobe = 0)
    tangent = normals - safe[..., None] * half
    d_n_dot_h = (tangent - dot3(tangent, to_light)[..., None] * to_light) / (distance * length)[..., None]
    d_lobe = (shininess * lobe / safe)[..., None] * d_n_dot_h
    d_specular = f[..., None] * (d_lobe + (lobe * log_slope)[..., None] * to_light)
    return diffuse, f * lobe, d_diffuse, d_specular
