"""Camera geometry: depth to points, robust normals, intrinsics.

Conventions (OpenCV camera frame, see ``render/__init__.py``): x right, y down,
z forward; pixel ``(row i, col j)`` has image coordinates ``u = j, v = i``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from kornia.geometry.depth import depth_to_3d_v2
from torch import Tensor

__all__ = ["unproject_depth", "normals_from_points", "plane_normals", "plane_fit", "PlaneFit", "smooth_normals",
           "normal_noise", "smallest_eigenvector", "fit_intrinsics", "pixel_grid", "dot3", "norm3", "surface_segments"]


def dot3(a: Tensor, b: Tensor) -> Tensor:
    """``a . b`` over a last axis of length 3, broadcasting: ``(..., 3) x (..., 3) -> (...)``.

    On the CPU as three strided products and two sums: 2-3x faster there than a
    reduction over so short an axis (measured 2026-11-23, 300k vectors); elsewhere one
    fused kernel (``torch.linalg.vecdot``).
    """
    if a.device.type != "cpu":
        return torch.linalg.vecdot(a, b)
    ax, ay, az = a.unbind(-1)
    bx, by, bz = b.unbind(-1)
    return ax * bx + ay * by + az * bz


def norm3(v: Tensor) -> Tensor:
    """Euclidean length over a last axis of length 3: ``(..., 3) -> (...)`` (see :func:`dot3`).

    With a gradient, always ``torch.linalg.vector_norm``: its derivative at a zero
    vector is 0, where that of a square root is infinite.
    """
    if v.device.type != "cpu" or (v.requires_grad and torch.is_grad_enabled()):
        return torch.linalg.vector_norm(v, dim=-1)
    return dot3(v, v).sqrt()


def pixel_grid(height: int, width: int, like: Tensor) -> tuple[Tensor, Tensor]:
    """Pixel-centre coordinates ``(u, v)``, each ``(H, W)``, dtype/device of ``like``."""
    v, u = torch.meshgrid(
        torch.arange(height, dtype=like.dtype, device=like.device),
        torch.arange(width, dtype=like.dtype, device=like.device),
        indexing="ij",
    )
    return u, v


def unproject_depth(depth: Tensor, K: Tensor) -> Tensor:
    """Camera-frame points of a z-depth map: ``X = depth * inv(K) @ [u, v, 1]``.

    Args:
        depth: ``(B, H, W)`` z-depth (not ray length).
        K: ``(B, 3, 3)`` pinhole intrinsics without skew.

    Returns:
        ``(B, H, W, 3)`` points.

    Example:
        >>> K = torch.tensor([[[2.0, 0, 1], [0, 2.0, 1], [0, 0, 1]]])
        >>> unproject_depth(torch.ones(1, 3, 3), K)[0, 1, 1]
        tensor([0., 0., 1.])
    """
    last_row = (K[:, 2] - K.new_tensor([0.0, 0.0, 1.0])).abs().le(1e-6).all(-1)
    pinhole = (K[:, 0, 0] > 0) & (K[:, 1, 1] > 0) & (K[:, 1, 0] == 0) & last_row
    if not bool(pinhole.all()):
        # A zero or negative focal length unprojected every pixel to nothing (all masked, silently).
        raise ValueError(f"K must be pinhole intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0; "
                         f"image {int((~pinhole).nonzero()[0])} of the batch is not: {K[~pinhole][0].tolist()}")
    if bool((K[:, 0, 1] != 0).any()):
        # kornia's unprojection ignores skew; refuse rather than silently misplace points.
        raise ValueError("intrinsics with non-zero skew K[0, 1] are not supported")
    return depth_to_3d_v2(depth, K)


def normals_from_points(
    points: Tensor, mask: Tensor, *, max_relative_step: float = 0.1
) -> tuple[Tensor, Tensor]:
    """Unit normals of an image-layout point cloud that never cross depth edges.

    For each pixel the horizontal and vertical tangents are taken from the
    neighbour pair (central, forward or backward difference) whose depth step is
    smallest among those below ``max_relative_step * depth``: a pixel on a
    silhouette uses the side on its own surface. Pixels with no usable pair on an
    axis get no normal. Normals are flipped to face the camera.

    Args:
        points: ``(B, H, W, 3)`` camera-frame points.
        mask: ``(B, H, W)`` bool validity.
        max_relative_step: largest accepted depth step between neighbours, relative
            to the pixel's depth.

    Returns:
        ``normals (B, H, W, 3)`` (zero where missing) and ``has_normal (B, H, W)`` bool.
    """
    z = points[..., 2]

    def tangent(axis: int) -> tuple[Tensor, Tensor]:
        # Neighbours along `axis` (1 = rows/v, 2 = cols/u); out-of-image counts as invalid.
        def shifted(t: Tensor, step: int, fill) -> Tensor:
            out = torch.roll(t, shifts=-step, dims=axis)
            index = torch.arange(t.shape[axis], device=t.device)
            edge = (index + step < 0) | (index + step >= t.shape[axis])
            shape = [1] * t.dim()
            shape[axis] = -1
            return torch.where(edge.view(shape), torch.as_tensor(fill, dtype=t.dtype, device=t.device), out)

        p_next, p_prev = shifted(points, 1, 0.0), shifted(points, -1, 0.0)
        m_next, m_prev = shifted(mask, 1, False), shifted(mask, -1, False)
        limit = max_relative_step * z.abs()
        step_next = (p_next[..., 2] - z).abs()
        step_prev = (z - p_prev[..., 2]).abs()
        ok_next = m_next & mask & (step_next <= limit)
        ok_prev = m_prev & mask & (step_prev <= limit)
        # Central difference when both sides are on the surface and agree in slope
        # (within a factor 2), else the one-sided difference with the smaller step.
        similar = (step_next <= 2 * step_prev + 1e-12 * z.abs()) & (step_prev <= 2 * step_next + 1e-12 * z.abs())
        use_central = ok_next & ok_prev & similar
        use_next = ok_next & ~use_central & (~ok_prev | (step_next <= step_prev))
        use_prev = ok_prev & ~use_central & ~use_next
        central = p_next - p_prev
        forward = p_next - points
        backward = points - p_prev
        t = torch.where(use_central[..., None], central, torch.where(use_next[..., None], forward, backward))
        return t, use_central | use_next | use_prev

    t_u, ok_u = tangent(2)
    t_v, ok_v = tangent(1)
    n = torch.cross(t_u, t_v, dim=-1)
    length = n.norm(dim=-1)
    has_normal = ok_u & ok_v & mask & (length > 0)
    # Guard the normalisation: invalid pixels have zero-length normals.
    n = n / torch.where(has_normal, length, torch.ones_like(length))[..., None]
    # Face the camera: dot(n, -X) > 0.
    facing = (n * points).sum(-1) > 0
    n = torch.where(facing[..., None], -n, n)
    n = torch.where(has_normal[..., None], n, torch.zeros_like(n))
    return n, has_normal


def _window(padded: list[Tensor], radius: int, height: int, width: int):
    """For each offset of a ``(2 radius + 1)^2`` window, the views of the ``padded``
    ``(B, H + 2 radius, W + 2 radius, ...)`` tensors shifted by it, each ``(B, H, W, ...)``."""
    for di in range(2 * radius + 1):
        for dj in range(2 * radius + 1):
            yield [t[:, di : di + height, dj : dj + width] for t in padded]


class PlaneFit(NamedTuple):
    """:func:`plane_fit`'s answer: ``normals (B, H, W, 3)`` (zero where missing),
    ``has_normal (B, H, W)`` and ``tilt_variance (B, H, W)``, the variance (radians^2,
    per tilt axis) of each normal's error from the scatter of the window's points
    off their plane (zero where there is no normal)."""

    normals: Tensor
    has_normal: Tensor
    tilt_variance: Tensor


def plane_normals(points: Tensor, mask: Tensor, *, radius: int = 3, max_relative_step: float = 0.1, step: int = 1
                  ) -> tuple[Tensor, Tensor]:
    """Unit normals ``(B, H, W, 3)`` and ``has_normal (B, H, W)`` of least-squares planes
    fitted to each pixel's window, for noisy depth: :func:`plane_fit` without the tilt
    variance."""
    fit = plane_fit(points, mask, radius=radius, max_relative_step=max_relative_step, step=step)
    return fit.normals, fit.has_normal


def plane_fit(points: Tensor, mask: Tensor, *, radius: int = 3, max_relative_step: float = 0.1, step: int = 1,
              shifts: tuple[float, ...] = ()) -> PlaneFit:
    """Unit normals of least-squares planes fitted to each pixel's window, for noisy depth.

    Differences of neighbouring pixels turn sensor noise of a few centimetres into
    normals tens of degrees off; a plane through the ``(2 radius + 1)^2`` window
    averages it away. Neighbours whose depth differs from the centre's by more
    than ``max_relative_step * z`` are left out, so planes do not reach across
    depth edges (they do round creases off within the window). The normal is the
    eigenvector of the smallest eigenvalue of the window's point covariance,
    turned to face the camera. ``step`` > 1 samples the window every ``step``
    pixels: a wide window's leverage (the tilt error falls with the window's
    extent) at the cost of a narrow one, ``((2 radius) / step + 1)^2`` offsets.
    Memory ``O(B H W)``.

    ``shifts`` (fractions of ``radius``; none by default) lets each pixel take the plane
    of a nearby window instead of its own: among its own and the windows centred
    ``round(f radius)`` pixels away in the eight directions, for each ``f``, the one
    with the least ``s^2 + d^2``, ``s^2`` the window's scatter off its plane (below) and
    ``d`` the pixel's distance from that plane. A window centred beside a crease (a
    floor meeting a wall, an object standing on the floor) fits neither plane and
    rounds the crease off over its whole width; a window further in, on the pixel's
    own side, fits the pixel's plane. On the Mitsuba sensor-noise files (160x120,
    ``radius`` 8, ``step`` 2) the share of normals more than 10 degrees off fell from
    17% to 6% with ``(1, 0.5, 0.25)`` (README, "Normals of noisy depth beside
    creases"). What it cannot tell apart: a pixel on the crease line itself lies on
    both planes and may take either.

    Args:
        points: ``(B, H, W, 3)`` camera-frame points.
        mask: ``(B, H, W)`` bool validity.
        radius: window half-size in pixels (>= 1).
        max_relative_step: largest accepted depth difference to the centre, relative
            to its depth.
        step: pixel spacing of the window's samples (>= 1, at most ``radius``).

    Returns:
        :class:`PlaneFit`: ``normals (B, H, W, 3)`` (zero where missing), ``has_normal
        (B, H, W)`` (at least 3 neighbours and a well-defined plane) and ``tilt_variance
        (B, H, W)``. The tilt is a regression slope: with ``N`` samples, ``l0 <= l1 <= l2``
        the eigenvalues of their covariance, the points scatter off the plane with variance
        ``s^2 = l0 N / (N - 3)`` and the tilt towards in-plane axis ``k`` has variance
        ``s^2 / (N l_k)``; ``tilt_variance`` is the mean over the two axes (independent
        noise between samples assumed; a curved surface's scatter counts as noise).
    """
    if radius < 1 or not 1 <= step <= radius:
        raise ValueError(f"plane_fit needs radius >= 1 and 1 <= step <= radius, got radius {radius}, step {step}")
    if not all(0 < f < math.inf for f in shifts):
        raise ValueError(f"plane_fit's shifts must be fractions of the radius > 0, got {shifts}")
    B, H, W, _ = points.shape
    # Channel-first, with the 6 distinct second moments: a (..., 3) last axis and a 3x3
    # outer product per offset cost a third more time (ad hoc, 160x120).
    p = points.permute(0, 3, 1, 2)
    padded_points = torch.nn.functional.pad(p, (radius,) * 4)
    padded_mask = torch.nn.functional.pad(mask, (radius,) * 4)
    limit = max_relative_step * p[:, 2].abs()
    count = torch.zeros_like(p[:, 0])
    first = torch.zeros_like(p)  # sums of offsets from the centre (better conditioned than raw points)
    rows, cols = (0, 1, 2, 0, 0, 1), (0, 1, 2, 1, 2, 2)  # xx yy zz xy xz yz
    second = p.new_zeros(B, 6, H, W)
    for di in range(0, 2 * radius + 1, step):
        for dj in range(0, 2 * radius + 1, step):
            offset = padded_points[:, :, di : di + H, dj : dj + W] - p
            use = padded_mask[:, di : di + H, dj : dj + W] & mask & (offset[:, 2].abs() <= limit)
            offset = offset * use[:, None]
            count += use
            first += offset
            second += offset[:, rows] * offset[:, cols]
    samples = count.clamp_min(1)[:, None]
    mean = first / samples
    moments = (second / samples - mean[:, rows] * mean[:, cols]).permute(0, 2, 3, 1)  # (B, H, W, 6)
    eigenvalues, n = smallest_eigenvector(moments)
    # A plane needs spread in two directions: the middle eigenvalue well above zero.
    spread = eigenvalues[..., 1] > 1e-6 * eigenvalues[..., 2].clamp_min(torch.finfo(points.dtype).tiny)
    has_normal = mask & (count >= 3) & spread & torch.isfinite(n).all(-1)
    facing = (n * points).sum(-1) > 0
    n = torch.where(facing[..., None], -n, n)
    used = count.clamp_min(4)
    scatter = eigenvalues[..., 0].clamp_min(0) * used / (used - 3)
    tiny = torch.finfo(points.dtype).tiny
    tilt = 0.5 * scatter / used * (1 / eigenvalues[..., 1].clamp_min(tiny) + 1 / eigenvalues[..., 2].clamp_min(tiny))
    tilt = torch.where(has_normal & torch.isfinite(tilt), tilt, torch.zeros_like(tilt))
    n = torch.where(has_normal[..., None], n, torch.zeros_like(n))
    if shifts:
        n, tilt = _nearby_planes(points, n, has_normal, tilt, points + mean.permute(0, 2, 3, 1), scatter,
                                 sorted({max(1, round(f * radius)) for f in shifts}))
    return PlaneFit(n, has_normal, tilt)


def _nearby_planes(points: Tensor, normals: Tensor, has_normal: Tensor, tilt: Tensor, centres: Tensor,
                   scatter: Tensor, distances: list[int]) -> tuple[Tensor, Tensor]:
    # plane_fit's shifts: each pixel's normal and tilt variance taken from the window (its
    # own, or one ``distances`` pixels away in the eight directions) whose plane has the
    # least scatter plus squared distance to the pixel. ``centres (B, H, W, 3)``: each
    # window's centroid; ``scatter (B, H, W)``: its points' variance off its plane.
    H, W = points.shape[1:3]
    reach = max(distances)
    # One channel-first stack, padded once: normal (3), centroid (3), scatter, tilt, has_normal.
    fields = torch.cat([normals, centres, scatter[..., None], tilt[..., None],
                        has_normal[..., None].to(points.dtype)], -1).permute(0, 3, 1, 2)
    padded = torch.nn.functional.pad(fields, (reach,) * 4)
    best = torch.where(has_normal, scatter + ((points - centres) * normals).sum(-1) ** 2,
                       torch.full_like(scatter, math.inf))
    chosen_normals, chosen_tilt = normals, tilt
    for d in distances:
        for di, dj in ((-d, -d), (-d, 0), (-d, d), (0, -d), (0, d), (d, -d), (d, 0), (d, d)):
            there = padded[:, :, reach + di : reach + di + H, reach + dj : reach + dj + W].permute(0, 2, 3, 1)
            normal, centre = there[..., 0:3], there[..., 3:6]
            score = there[..., 6] + ((points - centre) * normal).sum(-1) ** 2
            better = has_normal & (there[..., 8] > 0) & (score < best)
            best = torch.where(better, score, best)
            chosen_normals = torch.where(better[..., None], normal, chosen_normals)
            chosen_tilt = torch.where(better, there[..., 7], chosen_tilt)
    return chosen_normals, chosen_tilt


def smallest_eigenvector(moments: Tensor) -> tuple[Tensor, Tensor]:
    """Eigenvalues ``(..., 3)`` (ascending) of symmetric 3x3 matrices given by their six
    distinct entries ``moments (..., 6)`` (xx yy zz xy xz yz), and the unit eigenvector
    ``(..., 3)`` of the smallest, in closed form: the eigenvalues by the trigonometric
    solution of the characteristic cubic, the eigenvector as the longest cross product
    of two rows of ``A - l0 I``. Elementwise passes only, where a batched
    ``torch.linalg.eigh`` of one 160x120 image's matrices took half of
    :func:`plane_fit` (18 of 37 ms against 1.8 ms, 2 threads). The vector is non-finite where every eigenvalue is equal (no direction is the
    smallest); its sign is arbitrary."""
    xx, yy, zz, xy, xz, yz = moments.unbind(-1)
    q = (xx + yy + zz) / 3
    off = xy * xy + xz * xz + yz * yz
    p = torch.sqrt((((xx - q) ** 2 + (yy - q) ** 2 + (zz - q) ** 2 + 2 * off) / 6).clamp_min(0))
    safe = torch.where(p > 0, p, torch.ones_like(p))
    bxx, byy, bzz = (xx - q) / safe, (yy - q) / safe, (zz - q) / safe
    bxy, bxz, byz = xy / safe, xz / safe, yz / safe
    half_det = 0.5 * (bxx * (byy * bzz - byz * byz) - bxy * (bxy * bzz - byz * bxz) + bxz * (bxy * byz - byy * bxz))
    angle = torch.acos(half_det.clamp(-1, 1)) / 3
    largest = q + 2 * p * torch.cos(angle)
    smallest = q + 2 * p * torch.cos(angle + 2 * torch.pi / 3)
    eigenvalues = torch.stack([smallest, 3 * q - largest - smallest, largest], -1)
    rows = torch.stack([torch.stack([xx - smallest, xy, xz], -1), torch.stack([xy, yy - smallest, yz], -1),
                        torch.stack([xz, yz, zz - smallest], -1)], -2)  # (..., 3, 3)
    crosses = torch.stack([torch.linalg.cross(rows[..., 0, :], rows[..., 1, :]),
                           torch.linalg.cross(rows[..., 0, :], rows[..., 2, :]),
                           torch.linalg.cross(rows[..., 1, :], rows[..., 2, :])], -2)
    lengths = crosses.norm(dim=-1)
    best = crosses.gather(-2, lengths.argmax(-1)[..., None, None].expand(*lengths.shape[:-1], 1, 3))[..., 0, :]
    return eigenvalues, best / lengths.amax(-1, keepdim=True)


def smooth_normals(
    points: Tensor, normals: Tensor, mask: Tensor, *, radius: int = 3, passes: int = 2,
    normal_sigma: float = 0.3, plane_sigma: float = 0.02,
) -> Tensor:
    """Edge-preserving (bilateral) smoothing of a normal map, for noisy depth sensors.

    Each valid normal becomes the normalised weighted mean of the valid normals in
    its ``(2 radius + 1)^2`` window, weighted by ``exp(-|n_j - n_i|^2 / normal_sigma^2)``
    (creases keep their sides apart) times ``exp(-(d_j / (plane_sigma z_i))^2)``
    where ``d_j`` is the neighbour's distance from the centre's tangent plane (a
    depth edge keeps its sides apart; the scale grows with depth as sensor noise
    does). A piecewise-smooth clean map barely changes; sensor noise (several
    degrees per pixel) drops by about half per the devset's noisy scenes. Memory
    ``O(B H W)``: the window is visited offset by offset.

    Args:
        points, normals: ``(B, H, W, 3)``; normals unit length where valid.
        mask: ``(B, H, W)`` bool validity.
        radius, passes: window half-size (pixels) and number of passes.
        normal_sigma, plane_sigma: the two weights' scales (unit-vector distance;
            fraction of the pixel's depth).

    Returns:
        ``(B, H, W, 3)`` unit normals (zeros where ``mask`` is false).
    """
    if radius < 1 or passes < 1 or normal_sigma <= 0 or plane_sigma <= 0:
        raise ValueError(f"smooth_normals needs radius, passes >= 1 and positive sigmas, got "
                         f"{radius}, {passes}, {normal_sigma}, {plane_sigma}")
    B, H, W, _ = points.shape
    pad = (0, 0, radius, radius, radius, radius)  # (C, W, H) of a channel-last tensor
    valid = mask[..., None].to(points.dtype)
    padded_points = torch.nn.functional.pad(points, pad)
    padded_valid = torch.nn.functional.pad(valid, pad)
    plane_scale = (plane_sigma * points[..., 2:].abs()).clamp_min(torch.finfo(points.dtype).tiny)
    current = torch.where(mask[..., None], normals, torch.zeros_like(normals))
    for _ in range(passes):
        padded_normals = torch.nn.functional.pad(current, pad)
        total = torch.zeros_like(current)
        for n_j, neighbour, neighbour_valid in _window([padded_normals, padded_points, padded_valid], radius, H, W):
            plane = ((neighbour - points) * current).sum(-1, keepdim=True) / plane_scale
            similarity = ((n_j - current) ** 2).sum(-1, keepdim=True) / normal_sigma**2
            total = total + neighbour_valid * torch.exp(-similarity - plane**2) * n_j
        length = total.norm(dim=-1, keepdim=True)
        current = torch.where(mask[..., None] & (length > 0), total / length.clamp_min(1e-30), current)
    return current


def normal_noise(points: Tensor, normals: Tensor, mask: Tensor) -> Tensor:
    """Median angle (degrees) ``(B,)`` between each valid normal and its
    :func:`smooth_normals` version with a one-pixel window: about zero for normals
    of clean geometry, a few degrees for normals of a consumer depth sensor."""
    smoothed = smooth_normals(points, normals, mask, radius=1, passes=1)
    cos = (smoothed * normals).sum(-1).clamp(-1, 1)
    angle = torch.rad2deg(torch.acos(cos))
    angle = torch.where(mask, angle, torch.full_like(angle, float("nan")))
    return angle.flatten(1).nanmedian(1).values


def fit_intrinsics(points: Tensor, mask: Tensor) -> Tensor:
    """Least-squares pinhole ``K`` (no skew) that projects each point onto its pixel.

    Used when a G-buffer was built from a point cloud without intrinsics.

    Args:
        points: ``(B, H, W, 3)`` camera-frame points with ``z > 0`` where valid.
        mask: ``(B, H, W)`` validity; needs at least 3 valid pixels per image.

    Returns:
        ``(B, 3, 3)`` intrinsics.
    """
    B, H, W, _ = points.shape
    u, v = pixel_grid(H, W, points)
    z = points[..., 2]
    ok = mask & (z > 0)
    if bool((ok.flatten(1).sum(1) < 3).any()):
        raise ValueError("cannot fit intrinsics: an image has fewer than 3 valid points with z > 0")
    # u = fx * x/z + cx and v = fy * y/z + cy, solved per image in closed form.
    safe_z = torch.where(ok, z, torch.ones_like(z))
    xn, yn = points[..., 0] / safe_z, points[..., 1] / safe_z
    w = ok.to(points.dtype)

    def line_fit(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
        n = w.sum((1, 2))
        ma = (w * a).sum((1, 2)) / n
        mb = (w * b).sum((1, 2)) / n
        var = (w * (a - ma[:, None, None]) ** 2).sum((1, 2))
        cov = (w * (a - ma[:, None, None]) * (b - mb[:, None, None])).sum((1, 2))
        slope = cov / var.clamp_min(torch.finfo(points.dtype).tiny)
        return slope, mb - slope * ma

    fx, cx = line_fit(xn, u.expand(B, H, W))
    fy, cy = line_fit(yn, v.expand(B, H, W))
    K = torch.zeros(B, 3, 3, dtype=points.dtype, device=points.device)
    K[:, 0, 0], K[:, 0, 2], K[:, 1, 1], K[:, 1, 2], K[:, 2, 2] = fx, cx, fy, cy, 1.0
    return K


def surface_segments(points: Tensor, normals: Tensor, mask: Tensor, *, max_relative_step: float = 0.03,
                     max_angle_deg: float = 20.0, max_rounds: int = 10_000) -> Tensor:
    """Connected smooth surfaces of a G-buffer: labels ``(B, H, W)`` long, -1 outside ``mask``.

    Two 4-neighbours belong together when both are valid, their depths differ by less
    than ``max_relative_step`` of the depth and their normals by less than
    ``max_angle_deg``: a room's walls and floor, and the objects on them, come out as
    separate segments. A segment's label is its smallest flat pixel index (minimum
    label propagation with pointer jumping: about log-many rounds on compact shapes,
    at most ``max_rounds``).

    Args:
        points, normals: ``(B, H, W, 3)``; mask: ``(B, H, W)`` bool.
    """
    if points.shape[:-1] != mask.shape or normals.shape != points.shape:
        raise ValueError(f"points {tuple(points.shape)}, normals {tuple(normals.shape)} and mask {tuple(mask.shape)} "
                         "must be (B, H, W, 3), (B, H, W, 3), (B, H, W)")
    B, H, W = mask.shape
    none = H * W  # the label of invalid pixels while propagating: larger than any pixel index
    label = torch.arange(H * W, device=mask.device).expand(B, -1).reshape(B, H, W)
    label = torch.where(mask, label, torch.full_like(label, none))
    z = points[..., 2]
    cos_min = torch.cos(torch.deg2rad(torch.tensor(max_angle_deg, dtype=torch.float64))).item()
    links = []
    for axis in (1, 2):  # down and right neighbours; each link serves both directions
        n = mask.shape[axis] - 1
        here, there = (slice(None),) * axis + (slice(0, n),), (slice(None),) * axis + (slice(1, None),)
        joined = (mask[here] & mask[there] & ((z[here] - z[there]).abs() < max_relative_step * z[here].abs())
                  & (dot3(normals[here], normals[there]) > cos_min))
        links.append((here, there, joined))
    flat_none = torch.full((B, 1), none, device=mask.device, dtype=label.dtype)
    for _ in range(max_rounds):
        new = label.clone()
        for here, there, joined in links:
            new[here] = torch.minimum(new[here], torch.where(joined, label[there], none))
            new[there] = torch.minimum(new[there], torch.where(joined, label[here], none))
        # Pointer jumping: a pixel takes the label its label's pixel already has.
        flat = new.reshape(B, -1)
        lookup = torch.cat([flat, flat_none], 1)
        new = torch.minimum(flat, lookup.gather(1, flat)).reshape(B, H, W)
        if torch.equal(new, label):
            break
        label = new
    return torch.where(mask, label, torch.full_like(label, -1))
