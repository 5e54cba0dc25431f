"""Normals for the estimator from noisy depth: plane fits, edge-preserving smoothing, noise, surface segments.

Only the estimator uses these (``render/`` keeps the geometry every renderer user
needs: unprojection, normals from points, intrinsics). Conventions as in
:mod:`render.geometry`: OpenCV camera frame, channel-last ``(B, H, W, 3)``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from render.geometry import dot3, smallest_eigenvector

__all__ = ["plane_normals", "plane_fit", "PlaneFit", "smooth_normals", "normal_noise", "surface_segments"]


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
    17% to 6% with ``(1, 0.5, 0.25)`` (benchmarks/results/estimation_measurements.md, "Normals of noisy depth beside
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
            plane = dot3(neighbour - points, current)[..., None] / plane_scale
            change = n_j - current
            similarity = dot3(change, change)[..., None] / normal_sigma**2
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
