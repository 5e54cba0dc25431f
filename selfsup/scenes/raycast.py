"""Exact ray casting against analytic primitives, batched over rays, in torch.

This is the ground truth the project measures itself against: it shares no
code with ``render/`` (no shadow maps, no depth-map heightfields): shadows come
from exact shadow rays against the primitives.

Primitives of one scene, camera frame (x right, y down, z forward), metres:

- planes ``(P, 6)``: a point and a unit normal (infinite, one-sided normals are
  flipped towards the ray at shading time);
- spheres ``(S, 4)``: centre, radius;
- boxes ``(X, 15)``: centre, half extents, rotation ``R`` (box-to-camera) row-major;
- cylinders ``(C, 8)``: centre, unit axis, radius, half height (capped).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

__all__ = ["Primitives", "Hit", "cast_rays", "any_hit", "camera_rays", "exact_visibility", "shade_exact"]


def _empty(width: int) -> Tensor:
    return torch.zeros(0, width, dtype=torch.float64)


@dataclass
class Primitives:
    """The analytic shapes of one scene (see module docstring for the layouts)."""

    planes: Tensor = field(default_factory=lambda: _empty(6))
    spheres: Tensor = field(default_factory=lambda: _empty(4))
    boxes: Tensor = field(default_factory=lambda: _empty(15))
    cylinders: Tensor = field(default_factory=lambda: _empty(8))

    def to(self, dtype: torch.dtype, device: torch.device | str | None = None) -> "Primitives":
        return Primitives(*(t.to(dtype=dtype, device=device) for t in (self.planes, self.spheres, self.boxes, self.cylinders)))


@dataclass(frozen=True)
class Hit:
    """Nearest hits of ``R`` rays: ``t (R,)`` (inf where none), ``normal (R, 3)``
    (outward, unit), ``primitive (R,)`` (global index, -1 where none)."""

    t: Tensor
    normal: Tensor
    primitive: Tensor


def _dot(a: Tensor, b: Tensor) -> Tensor:
    # Written out: a reduction over a last axis of 3 is several times slower on CPU.
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _rows_times(rot: Tensor, v: Tensor) -> Tensor:
    # R^T v for rot (..., 3, 3), v (..., 3), written out like _dot.
    return rot[..., 0, :] * v[..., 0:1] + rot[..., 1, :] * v[..., 1:2] + rot[..., 2, :] * v[..., 2:3]


def _cols_times(rot: Tensor, v: Tensor) -> Tensor:
    # R v for rot (..., 3, 3), v (..., 3).
    return rot[..., :, 0] * v[..., 0:1] + rot[..., :, 1] * v[..., 1:2] + rot[..., :, 2] * v[..., 2:3]


# The intersection functions broadcast: rays ``o, d (..., 3)`` against primitives
# ``(..., k)``; dense calls pass ``(R, 1, 3)`` against ``(1, P, k)``, culled calls
# pass one row per candidate (ray, primitive) pair. They return ``t (...)`` (inf
# where none) and the outward unit normal ``(..., 3)``.


def _planes(p: Tensor, o: Tensor, d: Tensor, t_min: float) -> tuple[Tensor, Tensor]:
    n = p[..., 3:6]
    denom = _dot(d, n)
    parallel = denom.abs() <= 1e-12
    # Safe denominator in both branches: the parallel case is discarded below.
    t = _dot(p[..., :3] - o, n) / torch.where(parallel, torch.ones_like(denom), denom)
    t = torch.where(parallel | (t <= t_min), torch.full_like(t, float("inf")), t)
    return t, n.expand(*t.shape, 3)


def _spheres(s: Tensor, o: Tensor, d: Tensor, t_min: float) -> tuple[Tensor, Tensor]:
    oc = o - s[..., :3]
    a = _dot(d, d)
    b = _dot(oc, d)
    c = _dot(oc, oc) - s[..., 3] ** 2
    disc = b * b - a * c
    root = disc.clamp_min(0).sqrt()
    t0, t1 = (-b - root) / a, (-b + root) / a
    t = torch.where(t0 > t_min, t0, t1)
    t = torch.where((disc >= 0) & (t > t_min), t, torch.full_like(t, float("inf")))
    normal = (oc + t[..., None] * d) / s[..., 3:4]
    return t, normal


def _boxes(bx: Tensor, o: Tensor, d: Tensor, t_min: float) -> tuple[Tensor, Tensor]:
    centre, half = bx[..., :3], bx[..., 3:6]
    rot = bx[..., 6:15].unflatten(-1, (3, 3))
    # Into each box's frame: x_box = R^T (x - c).
    ol = _rows_times(rot, o - centre)
    dl = _rows_times(rot, d)
    # Axis-parallel rays: a tiny stand-in direction keeps 1/d finite with the right slab answer.
    tiny = 1e-30
    inv = 1.0 / torch.where(dl.abs() > tiny, dl, torch.full_like(dl, tiny))
    t1 = (-half - ol) * inv
    t2 = (half - ol) * inv
    enter, enter_axis = torch.minimum(t1, t2).max(-1)
    leave, leave_axis = torch.maximum(t1, t2).min(-1)
    outside = enter > t_min
    t = torch.where(outside, enter, leave)
    axis = torch.where(outside, enter_axis, leave_axis)
    t = torch.where((leave >= enter) & (t > t_min), t, torch.full_like(t, float("inf")))
    # The normal opposes the ray where it enters, follows it where it leaves (ray inside).
    d_axis = torch.sign(dl.gather(-1, axis[..., None]))
    sign = torch.where(outside[..., None], -d_axis, d_axis)
    local_n = torch.zeros_like(ol).scatter(-1, axis[..., None], sign)
    normal = _cols_times(rot, local_n)
    return t, normal


def _cylinders(cy: Tensor, o: Tensor, d: Tensor, t_min: float) -> tuple[Tensor, Tensor]:
    centre, axis, radius, half_h = cy[..., :3], cy[..., 3:6], cy[..., 6], cy[..., 7]
    oc = o - centre
    d_ax = _dot(d, axis)
    o_ax = _dot(oc, axis)
    d_perp = d - d_ax[..., None] * axis
    o_perp = oc - o_ax[..., None] * axis
    a = _dot(d_perp, d_perp)
    b = _dot(o_perp, d_perp)
    c = _dot(o_perp, o_perp) - radius**2
    disc = b * b - a * c
    safe_a = torch.where(a > 1e-20, a, torch.ones_like(a))  # rays along the axis meet the caps only
    root = disc.clamp_min(0).sqrt()
    inf = torch.full_like(a, float("inf"))
    candidates, normals = [], []
    for sign in (-1.0, 1.0):
        t = (-b + sign * root) / safe_a
        h = o_ax + t * d_ax
        ok = (a > 1e-20) & (disc >= 0) & (t > t_min) & (h.abs() <= half_h)
        candidates.append(torch.where(ok, t, inf))
        normals.append((o_perp + t[..., None] * d_perp) / radius[..., None])
    safe_d = torch.where(d_ax.abs() > 1e-20, d_ax, torch.ones_like(d_ax))  # rays across the axis miss the caps
    for sign in (-1.0, 1.0):
        t = (sign * half_h - o_ax) / safe_d
        p = o_perp + t[..., None] * d_perp
        ok = (d_ax.abs() > 1e-20) & (t > t_min) & (_dot(p, p) <= radius**2)
        candidates.append(torch.where(ok, t, inf))
        normals.append((sign * axis).expand_as(p))
    t, which = torch.stack(candidates, -1).min(-1)
    normal = torch.stack(normals, -2).gather(-2, which[..., None, None].expand(*which.shape, 1, 3)).squeeze(-2)
    return t, normal


def _bounds(kind: str, prims: Tensor) -> Tensor:
    # Bounding spheres (P, 4) of one kind of primitive.
    if kind == "boxes":
        return torch.cat([prims[:, :3], prims[:, 3:6].norm(dim=-1, keepdim=True)], 1)
    return torch.cat([prims[:, :3], torch.hypot(prims[:, 6], prims[:, 7])[:, None]], 1)


def _may_hit(bound: Tensor, o: Tensor, d: Tensor, t_min: float, t_max: Tensor | None) -> Tensor:
    # (R, P) bool: the ray's segment (t_min, t_max) meets the bounding sphere.
    oc = bound[None, :, :3] - o[:, None]
    dd = _dot(d, d)[:, None]
    s = _dot(oc, d[:, None]) / dd
    miss2 = _dot(oc, oc) - s * s * dd
    r2 = bound[None, :, 3] ** 2
    half = ((r2 - miss2).clamp_min(0) / dd).sqrt()
    ok = (miss2 <= r2) & (s + half > t_min)
    if t_max is not None:
        ok &= s - half < t_max[:, None]
    return ok


_KINDS = (("spheres", _spheres), ("boxes", _boxes), ("cylinders", _cylinders))


def _all_hits(prims: Primitives, o: Tensor, d: Tensor, t_min: float, t_max: Tensor | None = None,
              normals: bool = True) -> tuple[Tensor, Tensor | None]:
    """``t (R, P)`` of every ray against every primitive (global order) and, if asked,
    the normals ``(R, P, 3)``. Boxes and cylinders are first culled by bounding spheres
    and intersected exactly only for the (ray, primitive) pairs that may hit."""
    R = o.shape[0]
    ts, ns = [], []
    if prims.planes.shape[0]:
        t, n = _planes(prims.planes[None], o[:, None], d[:, None], t_min)
        ts.append(t)
        ns.append(n)
    for kind, fn in _KINDS:
        table = getattr(prims, kind)
        if not table.shape[0]:
            continue
        if kind == "spheres":  # as cheap as its own bounding test
            t, n = fn(table[None], o[:, None], d[:, None], t_min)
        else:
            ray, prim = _may_hit(_bounds(kind, table), o, d, t_min, t_max).nonzero(as_tuple=True)
            t_pair, n_pair = fn(table[prim], o[ray], d[ray], t_min)
            t = torch.full((R, table.shape[0]), float("inf"), dtype=o.dtype)
            t[ray, prim] = t_pair
            n = None
            if normals:
                n = torch.zeros(R, table.shape[0], 3, dtype=o.dtype)
                n[ray, prim] = n_pair
        ts.append(t)
        ns.append(n)
    if not ts:
        return torch.full((R, 0), float("inf"), dtype=o.dtype), torch.zeros(R, 0, 3, dtype=o.dtype)
    return torch.cat(ts, 1), (torch.cat(ns, 1) if normals else None)


def cast_rays(prims: Primitives, origins: Tensor, directions: Tensor, t_min: float = 0.0) -> Hit:
    """Nearest hit of each ray ``origins/directions (R, 3)`` (directions need not be unit)."""
    t_all, n_all = _all_hits(prims, origins, directions, t_min)
    if t_all.shape[1] == 0:
        inf = torch.full(origins.shape[:1], float("inf"), dtype=origins.dtype)
        return Hit(inf, torch.zeros_like(origins), torch.full_like(inf, -1, dtype=torch.long))
    t, index = t_all.min(1)
    normal = n_all.gather(1, index[:, None, None].expand(-1, 1, 3)).squeeze(1)
    index = torch.where(torch.isfinite(t), index, torch.full_like(index, -1))
    return Hit(t, normal, index)


def any_hit(prims: Primitives, origins: Tensor, directions: Tensor, t_min: float, t_max: Tensor) -> Tensor:
    """Whether each ray hits anything with ``t_min < t < t_max (R,)``: ``(R,)`` bool."""
    t_all, _ = _all_hits(prims, origins, directions, t_min, t_max, normals=False)
    if t_all.shape[1] == 0:
        return torch.zeros(origins.shape[0], dtype=torch.bool)
    return (t_all < t_max[:, None]).any(1)


def camera_rays(K: Tensor, height: int, width: int) -> Tensor:
    """Directions ``(H*W, 3)`` through pixel centres with ``z = 1`` (so ``t`` is z-depth)."""
    v, u = torch.meshgrid(torch.arange(height, dtype=K.dtype), torch.arange(width, dtype=K.dtype), indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], -1).reshape(-1, 3)
    return pix @ torch.linalg.inv(K).T


def exact_visibility(prims: Primitives, points: Tensor, normals: Tensor, light_position: Tensor) -> Tensor:
    """Exact shadow-ray visibility ``(R, L)`` of points ``(R, 3)`` from lights ``(L, 3)``.

    ``normals`` must face the camera. The ray leaves from the point nudged along
    that normal by 1e-6 of its distance, so a lit surface never shadows itself
    through rounding, and a light behind the surface is blocked by the surface.
    """
    scale = points.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    out = []
    for light in light_position:
        origin = points + 1e-6 * scale * normals
        blocked = any_hit(prims, origin, light[None] - origin, 1e-9, torch.ones(points.shape[0], dtype=points.dtype))
        out.append(~blocked)
    return torch.stack(out, -1).to(points.dtype)


def shade_exact(
    points: Tensor,
    normals: Tensor,
    visibility: Tensor,
    kd: Tensor,
    ks: Tensor,
    shininess: Tensor,
    light_position: Tensor,
    light_intensity: Tensor,
    ambient: Tensor,
    falloff: str = "inverse_square",
) -> Tensor:
    """The scene-format image model, written out independently of ``render/``.

    Args:
        points, normals: ``(R, 3)``; visibility: ``(R, L)``; kd: ``(R, 3)``;
        ks: ``(R, 1|3)``; shininess: ``(R,)``; light_position, light_intensity:
        ``(L, 3)``; ambient: ``(3,)``.

    Returns:
        ``(R, 3)`` radiance.
    """
    v = -points / points.norm(dim=-1, keepdim=True)
    color = kd * ambient[None]
    for i in range(light_position.shape[0]):
        offset = light_position[i][None] - points
        d = offset.norm(dim=-1, keepdim=True)
        l = offset / d
        h = l + v
        h = h / h.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        f = 1.0 / d**2 if falloff == "inverse_square" else torch.ones_like(d)
        diffuse = kd * (normals * l).sum(-1, keepdim=True).clamp_min(0)
        spec = ks * (normals * h).sum(-1, keepdim=True).clamp_min(0) ** shininess[:, None]
        color = color + visibility[:, i : i + 1] * light_intensity[i][None] * f * (diffuse + spec)
    return color
