"""Exact ray casting against analytic primitives, batched over rays, in torch.

The ground truth the project measures itself against: it shares no code with
``render/``; shadows come from exact shadow rays against the primitives.

Primitives of one scene, camera frame (x right, y down, z forward), metres:

- planes ``(P, 6)``: a point and a unit normal (infinite; flipped towards the ray when shaded);
- spheres ``(S, 4)``: centre, radius;
- boxes ``(X, 15)``: centre, half extents, rotation ``R`` (box-to-camera) row-major;
- cylinders ``(C, 8)``: centre, unit axis, radius, half height (capped).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import torch
from torch import Tensor

from render.geometry import broadcast_shape

__all__ = ["Primitives", "PrimitiveBatch", "Bundles", "Hit", "bundle_rays", "cast_bundles", "blocked_bundles", "hit_normals",
           "cast_rays", "any_hit", "camera_rays", "exact_visibility", "blinn_phong", "shade_exact"]


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


# Layout. Inside this module rays are stored by component, directions ``d (3, ...)``.
# Rays that share an origin are cast in bundles of ``_CHUNK``, ``d (3, N, S)`` with
# one origin per bundle; a bundle is tested against a primitive only if a cone
# around its rays meets a sphere around the primitive (:func:`_pairs`), and then
# exactly, ray by ray, as a ``(M, S)`` block for ``M`` (bundle, primitive) pairs,
# the primitive's parameters broadcast as ``(M, 1)`` columns. Rays with origins
# of their own (``o (3, R)``) meet every primitive: ``t (P, R)``, columns ``(P, 1)``.
# Bundles of several scenes are cast together: each bundle and each primitive
# belongs to one scene, and only pairs of the same scene are formed.
#
# Speed, measured on the 2-core CPU with torch 2.13: arithmetic costs about 0.3 ns
# per element, but ``torch.where``, ``masked_fill``, comparisons into bool, ``min``
# with indices and ``sqrt`` of a negative number 3 to 50 times more; and every
# call costs 4-10 microseconds, so a scene's few thousand calls dominate unless
# scenes are cast together. Masks are float 0/1 (comparisons written into a float
# tensor), "and" is a product, a choice is ``_select``, and a miss is the finite
# ``_FAR`` until the end (a product with an infinity could make a NaN).

_FAR = 1e30


def _mask(compare, a: Tensor, b: Tensor | float, dtype: torch.dtype | None = None) -> Tensor:
    """``compare(a, b)`` (``torch.gt``, ``ge``, ``le``...) as float 0/1, broadcast, in
    ``dtype`` (default ``a``'s: give one where ``a`` holds integers)."""
    shape = broadcast_shape(a.shape, b.shape) if isinstance(b, Tensor) else a.shape
    return compare(a, b, out=torch.empty(shape, dtype=dtype or a.dtype, device=a.device))


def _select(mask: Tensor, a: Tensor | float, b: Tensor | float) -> Tensor:
    """``a`` where the float ``mask`` is 1, else ``b``; exact for finite values."""
    return a * mask + b * (1 - mask)


def _offsets(o: Tensor, centre: Tensor) -> list[Tensor]:
    # o - c per component: (P, 1) for a shared origin, else (P, R).
    return [o[i] - centre[:, i : i + 1] for i in range(3)]


def _along(vector: Tensor, d: Tensor) -> Tensor:
    # v . d for a vector (P, 3) per primitive and ray directions (3, ...): (P, ...).
    return d[0] * vector[:, 0:1] + d[1] * vector[:, 1:2] + d[2] * vector[:, 2:3]


def _none_within(x: Tensor, limit: float) -> bool:
    """Whether no element of ``x`` has ``|x| <= limit`` (NaN is not within): two passes, where
    the guards against such elements cost four (a guard then adds zeros, exactly)."""
    return not x.numel() or not bool(x.abs().amin() <= limit)


def _planes(pl: Tensor, o: Tensor, d: Tensor, t_min: float) -> Tensor:
    normal = pl[:, 3:6]
    oc = _offsets(o, pl[:, :3])
    denom = _along(normal, d)
    numer = -(oc[0] * normal[:, 0:1] + oc[1] * normal[:, 1:2] + oc[2] * normal[:, 2:3])
    if _none_within(denom, 1e-12):  # no ray runs along its plane
        t = (numer / denom).clamp(-_FAR, _FAR)
        return _select(_mask(torch.gt, t, t_min), t, _FAR)
    parallel = _mask(torch.le, denom.abs(), 1e-12)
    t = (numer / (denom + parallel)).clamp(-_FAR, _FAR)
    return _select((1 - parallel) * _mask(torch.gt, t, t_min), t, _FAR)


def _spheres(sp: Tensor, o: Tensor, d: Tensor, t_min: float) -> Tensor:
    oc = _offsets(o, sp[:, :3])
    a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    b = oc[0] * d[0] + oc[1] * d[1] + oc[2] * d[2]
    c = oc[0] * oc[0] + oc[1] * oc[1] + oc[2] * oc[2] - sp[:, 3:4] ** 2
    disc = b * b - a * c
    root = disc.clamp_min(0).sqrt()
    near, far = (-b - root) / a, (-b + root) / a
    t = _select(_mask(torch.gt, near, t_min), near, far)
    return _select(_mask(torch.ge, disc, 0.0) * _mask(torch.gt, t, t_min), t, _FAR)


def _boxes(bx: Tensor, o: Tensor, d: Tensor, t_min: float) -> Tensor:
    # Slabs in each box's frame, x_box = R^T (x - c); the columns of R are the box axes.
    oc = _offsets(o, bx[:, :3])
    rot = bx[:, 6:15].unflatten(-1, (3, 3))
    enter = leave = None
    for j in range(3):
        axis = rot[:, :, j]
        d_local = _along(axis, d)
        o_local = oc[0] * axis[:, 0:1] + oc[1] * axis[:, 1:2] + oc[2] * axis[:, 2:3]
        # Axis-parallel rays: a tiny stand-in direction keeps 1/d finite with the right slab answer.
        if _none_within(d_local, 1e-30):  # no ray runs along the slab
            inv = 1.0 / d_local
        else:
            inv = 1.0 / (d_local + 1e-30 * _mask(torch.le, d_local.abs(), 1e-30))
        half = bx[:, 3 + j : 4 + j]
        ta, tb = (-half - o_local) * inv, (half - o_local) * inv
        low, high = torch.minimum(ta, tb), torch.maximum(ta, tb)
        enter = low if enter is None else torch.maximum(enter, low)
        leave = high if leave is None else torch.minimum(leave, high)
    enter, leave = enter.clamp(-_FAR, _FAR), leave.clamp(-_FAR, _FAR)
    t = _select(_mask(torch.gt, enter, t_min), enter, leave)  # from inside: where it leaves
    return _select(_mask(torch.ge, leave, enter) * _mask(torch.gt, t, t_min), t, _FAR)


def _cylinders(cy: Tensor, o: Tensor, d: Tensor, t_min: float) -> Tensor:
    # The interval inside the infinite cylinder, cut by the slab between the caps.
    axis, radius, half_h = cy[:, 3:6], cy[:, 6:7], cy[:, 7:8]
    oc = _offsets(o, cy[:, :3])
    d_ax = _along(axis, d)
    o_ax = oc[0] * axis[:, 0:1] + oc[1] * axis[:, 1:2] + oc[2] * axis[:, 2:3]
    d_perp = [d[i] - d_ax * axis[:, i : i + 1] for i in range(3)]
    o_perp = [oc[i] - o_ax * axis[:, i : i + 1] for i in range(3)]
    a = d_perp[0] * d_perp[0] + d_perp[1] * d_perp[1] + d_perp[2] * d_perp[2]
    b = o_perp[0] * d_perp[0] + o_perp[1] * d_perp[1] + o_perp[2] * d_perp[2]
    c = o_perp[0] * o_perp[0] + o_perp[1] * o_perp[1] + o_perp[2] * o_perp[2] - radius**2
    disc = b * b - a * c
    root = disc.clamp_min(0).sqrt()
    if bool(a.amin() > 1e-20) and bool(d_ax.abs().amin() > 1e-20):  # no ray needs the guards below (NaN would)
        side_low, side_high = ((-b - root) / a).clamp(-_FAR, _FAR), ((-b + root) / a).clamp(-_FAR, _FAR)
        ta = ((-half_h - o_ax) / d_ax).clamp(-_FAR, _FAR)
        tb = ((half_h - o_ax) / d_ax).clamp(-_FAR, _FAR)
        slab_low, slab_high = torch.minimum(ta, tb), torch.maximum(ta, tb)
        inside = _mask(torch.ge, disc, 0.0)
    else:
        crosses = _mask(torch.gt, a, 1e-20)  # else the ray runs along the axis: inside for all t, or never
        safe_a = a + (1 - crosses)
        side_low = _select(crosses, ((-b - root) / safe_a).clamp(-_FAR, _FAR), -_FAR)
        side_high = _select(crosses, ((-b + root) / safe_a).clamp(-_FAR, _FAR), _FAR)
        side = crosses * _mask(torch.ge, disc, 0.0) + (1 - crosses) * _mask(torch.le, c, 0.0)
        tilted = _mask(torch.gt, d_ax.abs(), 1e-20)  # else the ray runs between the caps' planes, or outside
        safe_d = d_ax + (1 - tilted)
        ta = ((-half_h - o_ax) / safe_d).clamp(-_FAR, _FAR)
        tb = ((half_h - o_ax) / safe_d).clamp(-_FAR, _FAR)
        slab_low = _select(tilted, torch.minimum(ta, tb), -_FAR)
        slab_high = _select(tilted, torch.maximum(ta, tb), _FAR)
        inside = side * (tilted + (1 - tilted) * _mask(torch.le, o_ax.abs(), half_h))
    enter, leave = torch.maximum(side_low, slab_low), torch.minimum(side_high, slab_high)
    t = _select(_mask(torch.gt, enter, t_min), enter, leave)
    return _select(inside * _mask(torch.ge, leave, enter) * _mask(torch.gt, t, t_min), t, _FAR)


_KINDS = (("planes", _planes), ("spheres", _spheres), ("boxes", _boxes), ("cylinders", _cylinders))
_CHUNK = 64  # rays per bundle: 8 x 8 pixels of an image in tile order


@dataclass(frozen=True)
class PrimitiveBatch:
    """The primitives of ``B`` scenes in one table per kind, kind by kind and, within a
    kind, scene by scene: so the *global index* (planes of every scene, then spheres,
    boxes, cylinders) lists any one scene's primitives in its own order.

    ``start``, ``count (B, 4)``: each scene's first row and number of rows in each
    kind's table; ``scene``, ``local (P,)``: a global index's scene and its index there."""

    prims: Primitives
    start: Tensor
    count: Tensor
    scene: Tensor
    local: Tensor

    @staticmethod
    def of(scenes: list[Primitives]) -> "PrimitiveBatch":
        tables = [torch.cat([getattr(p, kind) for p in scenes]) for kind, _ in _KINDS]
        count = torch.tensor([[getattr(p, kind).shape[0] for kind, _ in _KINDS] for p in scenes], dtype=torch.long)
        start = count.cumsum(0) - count  # each scene's first row in each kind's table
        before = count.cumsum(1) - count  # within a scene, a kind's rows follow its earlier kinds'
        scene = torch.cat([torch.arange(len(scenes)).repeat_interleave(count[:, k]) for k in range(len(_KINDS))])
        # Row r of kind k belongs to scene b = scene[r]: its local index is before[b, k] + (r - start[b, k]).
        local = torch.cat([torch.arange(int(count[:, k].sum())) + (before[:, k] - start[:, k]).repeat_interleave(count[:, k])
                           for k in range(len(_KINDS))])
        return PrimitiveBatch(Primitives(*tables), start, count, scene, local)

    @property
    def first(self) -> list[int]:
        """Global index of each kind's first row."""
        sizes = [getattr(self.prims, kind).shape[0] for kind, _ in _KINDS]
        return [sum(sizes[:k]) for k in range(len(sizes))]


@dataclass(frozen=True)
class Bundles:
    """Rays from one origin per bundle: ``d (3, N, S)``, ``origin (N, 3)``, ``scene (N,)``
    and ``t_max (N, S)`` (or None: unbounded); with the cone around each bundle, unit
    ``axis (N, 3)`` and half-angle ``spread (N,)``, and the least and greatest distance
    from the origin, ``near`` and ``far (N,)``, that the rays' segments reach (float64)."""

    d: Tensor
    origin: Tensor
    scene: Tensor
    t_max: Tensor | None
    axis: Tensor
    spread: Tensor
    near: Tensor
    far: Tensor

    @staticmethod
    def of(d: Tensor, origin: Tensor, scene: Tensor, t_min: float, t_max: Tensor | None = None) -> "Bundles":
        """Bundles from directions ``d (3, N, S)``. The cone is found in the rays' dtype:
        its float32 rounding (below 5e-4 radians) is covered by :func:`_pairs`' margin."""
        length = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
        inv = 1 / length
        unit = [d[i] * inv for i in range(3)]
        axis = torch.stack([u.sum(-1) for u in unit], -1).double()
        axis_norm = axis.norm(dim=-1)
        axis = axis / axis_norm.clamp_min(1e-300)[:, None]
        low = axis.to(d.dtype)
        cos = unit[0] * low[:, 0:1] + unit[1] * low[:, 1:2] + unit[2] * low[:, 2:3]
        spread = torch.acos(cos.amin(-1).double().clamp(-1, 1))
        # Rays of a bundle pointing every way, or one without a direction (zero or not
        # finite, which makes the cone NaN): the cone is the whole sphere, reaching from 0 to inf.
        whole = ~((axis_norm > 1e-3 * d.shape[-1]) & torch.isfinite(spread))
        spread = torch.where(whole, torch.full_like(spread, math.pi), spread)
        axis = torch.where(whole[:, None], torch.tensor([1.0, 0.0, 0.0], dtype=axis.dtype), axis)
        near = (length.amin(-1) * t_min).double().nan_to_num(0.0)
        far = torch.full_like(near, math.inf) if t_max is None else (length * t_max).amax(-1).double()
        far = torch.where(whole | far.isnan(), torch.full_like(far, math.inf), far)
        near = torch.where(whole, torch.zeros_like(near), near)
        return Bundles(d, origin, scene, t_max, axis, spread, near, far)


def bundle_rays(rays: Tensor) -> Tensor:
    """Rays ``(R, ...)`` in bundles ``(N, S, ...)``, the last one filled up with copies of the last ray."""
    pad = -rays.shape[0] % _CHUNK
    if pad:
        rays = torch.cat([rays, rays[-1:].expand(pad, *rays.shape[1:])])
    return rays.unflatten(0, (-1, _CHUNK))


def _bounds(kind: str, table: Tensor) -> Tensor:
    # Bounding spheres (P, 4) of one kind of object.
    if kind == "spheres":
        return table
    if kind == "boxes":
        return torch.cat([table[:, :3], table[:, 3:6].norm(dim=-1, keepdim=True)], 1)
    return torch.cat([table[:, :3], torch.hypot(table[:, 6], table[:, 7])[:, None]], 1)


def _pairs(batch: PrimitiveBatch, bundles: Bundles, k: int) -> tuple[Tensor, Tensor]:
    """The (bundle, row of kind ``k``) pairs of one scene that may meet: ``bundle, row (M,)``.

    A plane meets a bundle only if the bundle's cone reaches into the half-space of
    directions heading towards it, and the plane lies within the rays' reach. An
    object is bounded by a sphere; a ray meets the sphere only if its direction is
    within the sphere's angular radius of the centre's and the sphere lies within
    the ray's segment: so the bundle's cone and the sphere must be within the sum of
    their angles. Conservative: float64, the sphere padded by 1e-3 of its radius and
    the angles by 1e-3 radians, well beyond float32 rounding.
    """
    counts = batch.count[bundles.scene, k]
    bundle = torch.repeat_interleave(torch.arange(counts.shape[0]), counts)
    if not bundle.numel():
        return bundle, bundle
    row = torch.arange(bundle.shape[0]) - torch.repeat_interleave(counts.cumsum(0) - counts, counts)
    row = row + batch.start[bundles.scene, k].index_select(0, bundle)
    kind = _KINDS[k][0]
    # One gather of a per-bundle and of a per-primitive table, then per pair by component
    # (columns of the gathered rows): no (M, 3) arrays, no reductions over a last axis of 3.
    origin, axis = bundles.origin.double(), bundles.axis
    b = torch.cat([origin, axis, torch.stack([bundles.spread, bundles.near, bundles.far,
                                              (origin * origin).sum(-1).sqrt()], 1)], 1).index_select(0, bundle)
    o, a, spread, near, far, origin_norm = b[:, 0:3].T, b[:, 3:6].T, b[:, 6], b[:, 7], b[:, 8], b[:, 9]
    if kind == "planes":
        plane = batch.prims.planes.double().index_select(0, row).T  # point, normal
        # Signed distance from the origin; the rays must head that way, and reach that far.
        gap = (plane[0] - o[0]) * plane[3] + (plane[1] - o[1]) * plane[4] + (plane[2] - o[2]) * plane[5]
        toward = torch.acos(((a[0] * plane[3] + a[1] * plane[4] + a[2] * plane[5]) * torch.sign(gap)).clamp(-1, 1))
        ok = (toward <= math.pi / 2 + spread + 1e-3) | (gap == 0)
        ok &= gap.abs() * (1 - 1e-3) < far
    else:
        bound = _bounds(kind, getattr(batch.prims, kind)).double().index_select(0, row).T  # centre, radius
        offset = [bound[i] - o[i] for i in range(3)]
        dist = (offset[0] * offset[0] + offset[1] * offset[1] + offset[2] * offset[2]).sqrt().clamp_min(1e-300)
        radius = bound[3] * (1 + 1e-3) + 1e-6 * (dist + origin_norm)
        toward = torch.acos(((a[0] * offset[0] + a[1] * offset[1] + a[2] * offset[2]) / dist).clamp(-1, 1))
        reach = torch.where(radius < dist, torch.asin((radius / dist).clamp_max(1)), torch.full_like(dist, math.pi))
        ok = toward <= spread + reach + 1e-3
        ok &= dist + radius > near
        ok &= dist - radius < far
    keep = ok.nonzero(as_tuple=True)[0]
    return bundle.index_select(0, keep), row.index_select(0, keep)


# (bundle, primitive) pairs tested at once: a block's (pairs, 64) float32 arrays of 1 MB
# stay in the 2 MB L2 cache of the 2-core CPU, where an elementwise pass costs about half
# of what it costs on arrays of 8 MB (a plane test, ad hoc: 2.6 against 4.8 ns per pair and ray).
_PAIRS_PER_BLOCK = 4096


def _pair_blocks(batch: PrimitiveBatch, bundles: Bundles, t_min: float, kinds: range):
    """Blocks of the (bundle, primitive) pairs of ``kinds`` that may meet, each as
    ``t (m, S)`` (``_FAR`` where the pair does not meet), ``bundle (m,)`` and the
    primitive's global index ``(m,)``, with ``m <= _PAIRS_PER_BLOCK``."""
    first = batch.first
    for k in kinds:
        kind, fn = _KINDS[k]
        table = getattr(batch.prims, kind)
        if not table.shape[0]:
            continue
        bundle, row = _pairs(batch, bundles, k)
        for start in range(0, bundle.shape[0], _PAIRS_PER_BLOCK):
            which, rows = bundle[start : start + _PAIRS_PER_BLOCK], row[start : start + _PAIRS_PER_BLOCK]
            origin = bundles.origin.index_select(0, which).T[:, :, None]  # (3, m, 1)
            yield fn(table.index_select(0, rows), origin, bundles.d.index_select(1, which), t_min), which, rows + first[k]


def _reduce_into(out: Tensor, bundle: Tensor, values: Tensor, reduce: str) -> None:
    # Reduce pair rows values (m, S) into their bundles' rays, out (N, S): "amin" or "amax" with out's own values.
    with warnings.catch_warnings():  # index_reduce_ is "beta"; 2-3x faster than scatter_reduce_ here
        warnings.filterwarnings("ignore", message="index_reduce", category=UserWarning)
        out.index_reduce_(0, bundle, values, reduce)


def cast_bundles(batch: PrimitiveBatch, bundles: Bundles, t_min: float = 0.0) -> tuple[Tensor, Tensor]:
    """Nearest hit of each bundled ray: ``t (N*S,)`` (``inf`` where none) and the global
    index ``(N*S,)`` of the primitive (-1 where none; the first listed on a tie)."""
    N, S = bundles.d.shape[1:]
    blocks = list(_pair_blocks(batch, bundles, t_min, range(len(_KINDS))))
    t = bundles.d.new_full((N, S), _FAR)
    for t_pair, bundle, _ in blocks:
        _reduce_into(t, bundle, t_pair, "amin")
    # The first primitive at the nearest t: global index g weighs n - g among the equal ones.
    n = batch.local.shape[0]
    weight = bundles.d.new_zeros(N, S)
    for t_pair, bundle, index in blocks:
        at_nearest = _mask(torch.eq, t_pair, t.index_select(0, bundle)) * _mask(torch.lt, t_pair, _FAR)
        _reduce_into(weight, bundle, at_nearest * (n - index[:, None]).to(t.dtype), "amax")
    t, weight = t.reshape(-1), weight.reshape(-1)
    miss = _mask(torch.ge, t, _FAR)
    return t / (1 - miss), _select(miss, -1.0, n - weight).long()


def blocked_bundles(batch: PrimitiveBatch, bundles: Bundles, t_min: float = 0.0, objects_only: bool = False) -> Tensor:
    """Whether each bundled ray hits a primitive with ``t_min < t < t_max``: ``(N*S,)`` bool.
    ``objects_only`` leaves the planes out."""
    N, S = bundles.d.shape[1:]
    t_max = bundles.t_max if bundles.t_max is not None else bundles.d.new_full((N, S), _FAR)
    hit = bundles.d.new_zeros(N, S)
    for t_pair, bundle, _ in _pair_blocks(batch, bundles, t_min, range(int(objects_only), len(_KINDS))):
        _reduce_into(hit, bundle, _mask(torch.lt, t_pair, t_max.index_select(0, bundle)), "amax")
    return hit.reshape(-1) > 0


def _dense_t(prims: Primitives, o: Tensor, d: Tensor, t_min: float) -> Tensor:
    """``t (P, R)`` of every primitive (global order) on rays of their own ``o, d (3, R)``."""
    ts = [fn(getattr(prims, kind), o, d, t_min) for kind, fn in _KINDS if getattr(prims, kind).shape[0]]
    return torch.cat(ts) if ts else d.new_full((0, d.shape[1]), _FAR)


def _shared_origin(origins: Tensor) -> bool:
    return bool(origins.shape[0]) and (origins.stride(0) == 0 or torch.equal(origins, origins[:1].expand_as(origins)))


def hit_normals(prims: Primitives, points: Tensor, index: Tensor) -> Tensor:
    """Outward unit normals ``(3, R)`` at ``points (3, R)`` (by component) on primitives
    ``index (R,)`` (global; -1, none, gets zeros), found from the point on the primitive's surface."""
    # Planes first in the global order: their normals are a gather; the other kinds are solved on their rays.
    planes = prims.planes.shape[0]
    unit = prims.planes[:, 3:6] / prims.planes[:, 3:6].norm(dim=-1, keepdim=True).clamp_min(1e-30)
    others = sum(getattr(prims, kind).shape[0] for kind, _ in _KINDS[1:])
    # (3, P + 2) by index + 1: none (-1) first, the planes' normals, zeros for the other kinds and for any
    # index out of range (a NaN ray's), clamped to the last.
    normal_of = torch.cat([unit.new_zeros(1, 3), unit, unit.new_zeros(others + 1, 3)]).T.to(points.dtype).contiguous()
    normal = normal_of.index_select(1, (index + 1).clamp_(0, planes + others + 1))
    curved = (index >= planes).nonzero(as_tuple=True)[0]
    if not curved.numel():
        return normal
    index_of_curved = index.index_select(0, curved)
    first = planes
    for kind, _ in _KINDS[1:]:
        table = getattr(prims, kind)
        last = first + table.shape[0]
        pick = (_mask(torch.ge, index_of_curved, first) * _mask(torch.lt, index_of_curved, last)).nonzero(as_tuple=True)[0]
        if pick.numel():
            rows = curved.index_select(0, pick)
            row = table.T.contiguous().index_select(1, index_of_curved.index_select(0, pick) - first)  # (width, M)
            v = points.index_select(1, rows) - row[:3]  # from the centre
            if kind == "spheres":
                n = v
            elif kind == "boxes":
                # Box frame coordinates local_j = sum_i R_ij v_i; the face is the axis where the
                # point is farthest out relative to the half extent.
                rot = row[6:15]  # R_ij at 3 i + j
                local = [v[0] * rot[j] + v[1] * rot[3 + j] + v[2] * rot[6 + j] for j in range(3)]
                out = [local[j].abs() / row[3 + j] for j in range(3)]
                # One-hot of the first largest (an argmax over a leading axis of 3 is slow).
                first_axis = _mask(torch.ge, out[0], out[1]) * _mask(torch.ge, out[0], out[2])
                second_axis = (1 - first_axis) * _mask(torch.ge, out[1], out[2])
                chosen = (first_axis, second_axis, 1 - first_axis - second_axis)
                n = sum(rot[[j, 3 + j, 6 + j]] * (chosen[j] * torch.sign(local[j])) for j in range(3))
            else:
                axis = row[3:6]
                h = v[0] * axis[0] + v[1] * axis[1] + v[2] * axis[2]
                perp = v - h * axis
                perp_norm = (perp[0] * perp[0] + perp[1] * perp[1] + perp[2] * perp[2]).sqrt()
                on_cap = _mask(torch.ge, h.abs() / row[7], perp_norm / row[6])
                n = _select(on_cap, torch.sign(h) * axis, perp)
            length = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt().clamp_min(1e-30)
            normal.index_copy_(1, rows, n / length)
        first = last
    return normal


def _one_scene(prims: Primitives, origins: Tensor, directions: Tensor, t_min: float, t_max: Tensor | None):
    batch = PrimitiveBatch.of([prims])
    d = bundle_rays(directions).permute(2, 0, 1)
    tm = None if t_max is None else bundle_rays(t_max)
    N = d.shape[1]
    bundles = Bundles.of(d, origins[:1].expand(N, 3), torch.zeros(N, dtype=torch.long), t_min, tm)
    return batch, bundles


def cast_rays(prims: Primitives, origins: Tensor, directions: Tensor, t_min: float = 0.0) -> Hit:
    """Nearest hit of each ray ``origins/directions (R, 3)`` (directions need not be unit).

    Where two primitives are hit at the same ``t``, the one listed first wins. Rays
    from one origin are cast in bundles of consecutive rays: list them so that
    neighbours point alike (8 x 8 pixel tiles, say) for speed."""
    R = origins.shape[0]
    if _shared_origin(origins):
        t, index = cast_bundles(*_one_scene(prims, origins, directions, t_min, None), t_min)
        t, index = t[:R], index[:R]
    else:
        # Every ray against every primitive; primitive p weighs P - p among those at the nearest t.
        t_all = _dense_t(prims, origins.T.contiguous(), directions.T.contiguous(), t_min)
        P = t_all.shape[0]
        t = t_all.amin(0) if P else directions.new_full((R,), _FAR)
        weight = torch.arange(P, 0, -1, dtype=t.dtype)[:, None]
        first = P - (_mask(torch.eq, t_all, t) * weight).amax(0) if P else t
        miss = _mask(torch.ge, t, _FAR)
        t, index = t / (1 - miss), _select(miss, -1.0, first).long()
    points = origins + directions * torch.where(index >= 0, t, torch.zeros_like(t))[:, None]
    return Hit(t, hit_normals(prims, points.T.contiguous(), index).T, index)


def any_hit(prims: Primitives, origins: Tensor, directions: Tensor, t_min: float, t_max: Tensor) -> Tensor:
    """Whether each ray hits anything with ``t_min < t < t_max (R,)``: ``(R,)`` bool.

    Rays from one origin are cast in bundles, as in :func:`cast_rays`."""
    R = origins.shape[0]
    t_max = t_max.to(directions.dtype)
    if _shared_origin(origins):
        return blocked_bundles(*_one_scene(prims, origins, directions, t_min, t_max), t_min)[:R]
    t_all = _dense_t(prims, origins.T.contiguous(), directions.T.contiguous(), t_min)
    if t_all.shape[0] == 0:
        return torch.zeros(R, dtype=torch.bool, device=origins.device)
    return _mask(torch.lt, t_all, t_max).amax(0) > 0


def camera_rays(K: Tensor, height: int, width: int) -> Tensor:
    """Directions ``(H*W, 3)`` through pixel centres with ``z = 1`` (so ``t`` is z-depth)."""
    v, u = torch.meshgrid(torch.arange(height, dtype=K.dtype), torch.arange(width, dtype=K.dtype), indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], -1).reshape(-1, 3)
    return pix @ torch.linalg.inv(K).T


def exact_visibility(prims: Primitives, points: Tensor, normals: Tensor, light_position: Tensor) -> Tensor:
    """Exact shadow-ray visibility ``(R, L)`` of points ``(R, 3)`` from lights ``(L, 3)``.

    ``normals`` must face the camera. The ray's end is the point nudged along that
    normal by 1e-6 of its distance, so a lit surface never shadows itself through
    rounding, and a light behind the surface is blocked by the surface. Rays are
    cast from the light (one shared origin) and blocked by a hit before their end.
    """
    scale = points.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    target = points + 1e-6 * scale * normals
    end = torch.full(points.shape[:1], 1 - 1e-9, dtype=points.dtype, device=points.device)
    out = [~any_hit(prims, light.expand_as(target), target - light, 0.0, end) for light in light_position]
    return torch.stack(out, -1).to(points.dtype)


def blinn_phong(points: Tensor, normals: Tensor, visibility: Tensor, shininess: Tensor | None, light_position: Tensor,
                light_intensity: Tensor, falloff: str = "inverse_square", diffuse: bool = True,
                specular: bool = True) -> tuple[Tensor | None, Tensor | None]:
    """The scene-format image model's light terms, by component: radiance is
    ``kd * diffuse + ks * specular`` plus the ambient term (the core of :func:`shade_exact`;
    a reduction over a last axis of 3 is several times slower on CPU).

    Args:
        points, normals: ``(3, R)``; visibility: ``(L, R)``; shininess: ``(R,)`` (unused
        without ``specular``); light_position, light_intensity: ``(L, 3, 1)`` shared, or
        ``(L, 3, R)`` for lights of each ray's own; diffuse, specular: which terms to
        compute (the other is returned as None).

    Returns:
        ``diffuse, specular (3, R)``: the lights' unshadowed share times ``n.l`` and
        times ``(n.h)^shininess``, summed over the lights.
    """
    p, n = points, normals
    v = -p * (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).rsqrt() if specular else None
    diffuse_sum = specular_sum = None  # the first light's term itself (a zero array to add it to costs two passes)
    for i in range(light_position.shape[0]):
        offset = light_position[i] - p
        d2 = offset[0] * offset[0] + offset[1] * offset[1] + offset[2] * offset[2]
        l = offset * d2.rsqrt()
        arriving = light_intensity[i] * (visibility[i] / d2 if falloff == "inverse_square" else visibility[i])
        if diffuse:
            term = arriving * (n[0] * l[0] + n[1] * l[1] + n[2] * l[2]).clamp_min(0)
            diffuse_sum = term if diffuse_sum is None else diffuse_sum + term
        if specular:
            h = l + v
            h = h * (h[0] * h[0] + h[1] * h[1] + h[2] * h[2]).clamp_min(1e-24).rsqrt()
            # (n.h)^s as exp(s log n.h), 3x faster than a tensor power; n.h = 0 gives exp(-69 s), zero in float32 for s >= 2.
            cosine = (n[0] * h[0] + n[1] * h[1] + n[2] * h[2]).clamp_min(1e-30)
            term = arriving * torch.exp(shininess * torch.log(cosine))
            specular_sum = term if specular_sum is None else specular_sum + term
    if diffuse and diffuse_sum is None:  # no lights
        diffuse_sum = torch.zeros_like(p)
    if specular and specular_sum is None:
        specular_sum = torch.zeros_like(p)
    return diffuse_sum, specular_sum


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
        ``(L, 3)``, or ``(R, L, 3)`` for lights of each ray's own; ambient: ``(3,)``.

    Returns:
        ``(R, 3)`` radiance.
    """
    if light_position.dim() == 2:
        lights = light_position[:, :, None], light_intensity[:, :, None]
    else:
        lights = light_position.permute(1, 2, 0), light_intensity.permute(1, 2, 0)
    diffuse, specular = blinn_phong(points.T.contiguous(), normals.T.contiguous(), visibility.T.contiguous(),
                                    shininess, *lights, falloff)
    return (kd.T * (diffuse + ambient[:, None]) + ks.T * specular).T
