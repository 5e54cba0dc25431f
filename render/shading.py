"""Blinn-Phong lighting math as plain functions, batched over lights.

Shapes use B batch, L lights, H, W image. Every function broadcasts its inputs
with torch rules; the shapes below are the ones the renderer passes. The helpers take
channel-last ``(..., 3)`` vectors; the renderer's transport and its Jacobian are written on
planes, ``(..., 3, H, W)`` (:func:`planar_shading`).
"""

from __future__ import annotations

from enum import Enum
from typing import Callable, NamedTuple

import torch
from torch import Tensor

from render.geometry import dot3, norm3, positive

__all__ = ["Falloff", "LightGeometry", "light_geometry", "falloff_factor", "blinn_phong_lobe",
           "shading_and_position_gradients", "ShadingGradients",
           "PlanarShading", "planar_shading", "planar_lobe"]


class Falloff(str, Enum):
    """Distance attenuation ``f(d)`` of a point light (``meta.falloff`` of scene files)."""

    INVERSE_SQUARE = "inverse_square"  # f = 1/d^2, physical; the default
    NONE = "none"  # f = 1, as written in the Blinn-Phong light-estimation paper


class LightGeometry(NamedTuple):
    """See :func:`light_geometry`."""

    to_light: Tensor  # (B, L, H, W, 3) unit, surface to light
    distance: Tensor  # (B, L, H, W)
    to_viewer: Tensor  # (B, 1, H, W, 3) unit, surface to camera centre


def _safe_normalize(v: Tensor, length: Tensor, eps: Tensor, axis: int = -1) -> Tensor:
    # Guard: a zero vector (light on the point, point at the camera) would give
    # 0/0; dividing by max(length, eps) keeps values and gradients finite.
    return v / torch.maximum(length, eps).unsqueeze(axis)


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


def light_offset(points: Tensor, light_position: Tensor, axis: int = -1) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The unnormalised half of :func:`light_geometry`: ``offset`` (surface to light,
    shapes as there), guarded ``distance``, and the points' ``depth`` and ``eps``
    (the guard's floor); vectors along ``axis`` (``-3`` for planes, :func:`planar_shading`)."""
    offset = light_position - points
    # Square-root guard: sqrt'(0) is infinite; the clamp keeps the gradient finite
    # for a light exactly on the surface. The scale-aware floor (1e-6 of the
    # point's distance to the camera) works for millimetre and kilometre scenes.
    depth = norm3(points, axis)
    eps = 1e-6 * depth.clamp_min(torch.finfo(points.dtype).tiny ** 0.25)
    distance = dot3(offset, offset, axis).clamp_min(torch.finfo(points.dtype).tiny).sqrt()
    return offset, torch.maximum(distance, eps), depth, eps


def falloff_factor(distance: Tensor, falloff: Falloff | str) -> Tensor:
    """``f(d)``: ``1/d^2`` (inverse_square) or 1 (none); same shape as ``distance``."""
    falloff = Falloff(falloff)
    if falloff is Falloff.NONE:
        return torch.ones_like(distance)
    inverse = 1.0 / distance
    return inverse * inverse


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
    return safe.pow(shininess) * lit


def _half_vector(normals: Tensor, to_light: Tensor, to_viewer: Tensor, axis: int = -1
                 ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    # h, |l + v| (1 where undefined), n.h (1 where unlit) and where the lobe is lit (1, else
    # 0; float masks: geometry.positive); vectors along ``axis``.
    half = to_light + to_viewer
    length = norm3(half, axis)
    # Guard: h is undefined when the light is exactly opposite the viewer (l = -v);
    # the lobe is then taken as 0 (n.h has no preferred value) with a zero gradient.
    ok = positive(length - 1e-6)
    length = length * ok + (1 - ok)
    half = half / length.unsqueeze(axis)
    n_dot_h = dot3(normals, half, axis)
    lit = ok * positive(n_dot_h - 1e-12)
    # Pow guard: for alpha < 1 the derivative of x^alpha is infinite at 0; the
    # masked branch gets a safe base of 1 so its (discarded) gradient stays finite.
    return half, length, n_dot_h * lit + (1 - lit), lit


class PlanarShading(NamedTuple):
    """See :func:`planar_shading`: ``(B, [1|L], 3, H, W)`` vectors, one contiguous plane a component."""

    points: Tensor  # (B, 1, 3, H, W) camera-frame points
    normals: Tensor  # (B, 1, 3, H, W)
    offset: Tensor  # (B, L, 3, H, W) surface to light
    depth: Tensor  # (B, 1, H, W) the points' distance to the camera
    eps: Tensor  # (B, 1, H, W) the distances' guard (:func:`light_offset`)
    distance: Tensor  # (B, L, H, W) guarded
    inverse: Tensor  # (B, L, H, W) 1 / distance
    n_dot_l: Tensor  # (B, L, H, W)
    falloff: Tensor  # (B, L, H, W) f(d)
    inverse_square: bool  # which falloff f is

    def to_light(self) -> Tensor:
        """``(B, L, 3, H, W)`` unit vectors from the surface to each light."""
        return self.offset * self.inverse[:, :, None]

    def half_vector(self, to_light: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """:func:`blinn_phong_lobe`'s ``h`` ``(B, L, 3, H, W)``, ``|l + v|``, ``n.h`` (1 where
        unlit) and where the lobe is lit (1, else 0), ``(B, L, H, W)``."""
        to_viewer = _safe_normalize(-self.points, self.depth, self.eps, -3)
        return _half_vector(self.normals, self.to_light() if to_light is None else to_light, to_viewer, -3)


def planar_shading(points: Tensor, normals: Tensor, light_position: Tensor, falloff: Falloff | str) -> PlanarShading:
    """The shading's geometry of lights at ``light_position (B, L, 3)`` over a G-buffer's
    ``points`` and ``normals`` as ``(B, 3, H, W)`` planes (:meth:`render.GBuffer.planes`),
    each vector component a contiguous ``(H, W)`` array. The renderer's transport and its
    Jacobian are written on these: on the CPU, with masks as float products
    (:func:`render.geometry.positive`), the Jacobian takes 0.3-0.6x and the transport 0.55-0.7x
    the time they took on interleaved ``(..., 3)`` vectors, whose components are read with
    stride 3 (one core, ``(B, L) = (1..21, 1..2)`` at 40x30-160x120:
    ``benchmarks/results/planar_shading_cpu2_2026-12-07.md``). The guards are
    :func:`light_geometry`'s."""
    if points.dim() != 4 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"points and normals must be (B, 3, H, W) planes of one shape (GBuffer.planes()), got "
                         f"{tuple(points.shape)} and {tuple(normals.shape)}")
    if light_position.dim() != 3 or light_position.shape[0] != points.shape[0] or light_position.shape[2] != 3:
        raise ValueError(f"light_position must have shape ({points.shape[0]}, L, 3), got {tuple(light_position.shape)}")
    point_planes, normal_planes = points[:, None], normals[:, None]
    offset, distance, depth, eps = light_offset(point_planes, light_position[..., None, None], -3)
    inverse = 1.0 / distance
    n_dot_l = dot3(normal_planes, offset, -3) * inverse
    return PlanarShading(point_planes, normal_planes, offset, depth, eps, distance, inverse, n_dot_l,
                         falloff_factor(distance, falloff), Falloff(falloff) is Falloff.INVERSE_SQUARE)


def planar_lobe(shading: PlanarShading, shininess: Tensor | float) -> Tensor:
    """``max(0, n.h)^alpha`` ``(B, L, H, W)`` on :func:`planar_shading`'s geometry (as
    :func:`blinn_phong_lobe`); ``shininess`` broadcastable to ``(B, L, H, W)``."""
    _, _, safe, lit = shading.half_vector()
    return safe.pow(shininess) * lit


class ShadingGradients(NamedTuple):
    """See :func:`shading_and_position_gradients`."""

    diffuse: Tensor  # (B, L, H, W)
    specular: Tensor | None  # (B, L, H, W)
    d_diffuse: Tensor  # (B, L, H, W, 3)
    d_specular: Tensor | None  # (B, L, H, W, 3)
    n_dot_l: Tensor  # (B, L, H, W)


def shading_and_position_gradients(points: Tensor, normals: Tensor, light_position: Tensor, shininess: Tensor | float,
                                   falloff: Falloff | str, with_specular: bool = True,
                                   cosine_factor: Callable[[Tensor], tuple[Tensor, Tensor]] | None = None
                                   ) -> ShadingGradients:
    """The unshadowed transport ``diffuse = f(d) max(0, n.l)`` and ``specular = f(d)
    max(0, n.h)^alpha`` ``(B, L, H, W)`` and their exact derivatives with respect to each light's position
    ``(B, L, H, W, 3)``, sharing every intermediate (a Gauss-Newton step needs all four).
    Specular terms are None without ``with_specular``. No autograd graph is meant: a solver's.

    With ``o = p - X``, ``d = |o|``, ``l = o / d`` and ``h = (l + v) / |l + v|``:
    ``dl/dp = (I - l l^T) / d``, ``dh/dp = (I - h h^T) / |l + v| dl/dp`` and
    ``df/dp = f'(d) l``; so ``d diffuse/dp = f/d (n - (1 + k) (n.l) l)`` with ``k = 2`` under
    the inverse square and 0 without falloff. Where a term is clamped to 0 its derivative is 0.
    The guards are :func:`light_geometry`'s and :func:`blinn_phong_lobe`'s.

    Computed on :func:`planar_shading`'s planes; the derivatives are returned as
    ``(B, L, H, W, 3)`` views of ``(B, L, 3, H, W)`` planes (``.permute(0, 1, 4, 2, 3)``
    gives the planes back without a copy).

    Args:
        points: ``(B, 3, H, W)`` camera-frame points; normals: ``(B, 3, H, W)`` unit (planes,
            :meth:`render.GBuffer.planes`).
        light_position: ``(B, L, 3)``.
        shininess: alpha, broadcastable to ``(B, L, H, W)``.
        with_specular: False skips the specular terms (returned as None).
        cosine_factor: None, or ``g(c) -> (g(c), g'(c))`` of the cosine ``c = n.l``
            ``(B, L, H, W)``, a factor of the diffuse term (a clear coat's transmission,
            :mod:`render.coat`): ``diffuse = f c g(c)``, differentiated with it.

    Returns:
        :class:`ShadingGradients`: ``diffuse``, ``specular`` ``(B, L, H, W)``, ``d diffuse_i / d p_i``,
        ``d specular_i / d p_i`` ``(B, L, H, W, 3)`` and the cosine ``n_dot_l (B, L, H, W)``.
    """
    geometry = planar_shading(points, normals, light_position, falloff)
    normal_planes, offset, distance, inverse, n_dot_l, f = (geometry.normals, geometry.offset, geometry.distance,
                                                            geometry.inverse, geometry.n_dot_l, geometry.falloff)
    lit = positive(n_dot_l)
    diffuse = f * n_dot_l.clamp_min(0)
    # d diffuse/dp = along_n n - along_o o (lit only); a cosine factor g adds f c g' dc/dp,
    # dc/dp = (n - c l) / d.
    along_n = f * inverse
    along_o = (3.0 if geometry.inverse_square else 1.0) * n_dot_l * inverse * along_n
    if cosine_factor is not None:
        g, slope = cosine_factor(n_dot_l)
        extra = diffuse * slope * inverse
        along_n, along_o = g * along_n + extra, g * along_o + extra * n_dot_l * inverse
        diffuse = diffuse * g
    along_n, along_o = along_n * lit, along_o * lit
    d_diffuse = along_n[:, :, None] * normal_planes - along_o[:, :, None] * offset
    if not with_specular:
        return ShadingGradients(diffuse, None, d_diffuse.permute(0, 1, 3, 4, 2), None, n_dot_l)
    to_light = geometry.to_light()
    half, length, safe, lobe_lit = geometry.half_vector(to_light)
    lobe = safe.pow(shininess) * lobe_lit
    # d(n.h)/dp = (I - l l^T)(n - (n.h) h) / (d |l + v|); 0 where unlit (lobe = 0)
    tangent = normal_planes - safe[:, :, None] * half
    d_n_dot_h = (tangent - dot3(tangent, to_light, -3)[:, :, None] * to_light) / (distance * length)[:, :, None]
    d_lobe = (shininess * lobe / safe)[:, :, None] * d_n_dot_h
    if geometry.inverse_square:  # f'(d) / f = -2 / d
        d_lobe = d_lobe - (2.0 * lobe * inverse)[:, :, None] * to_light
    d_specular = f[:, :, None] * d_lobe
    return ShadingGradients(diffuse, f * lobe, d_diffuse.permute(0, 1, 3, 4, 2), d_specular.permute(0, 1, 3, 4, 2),
                            n_dot_l)
