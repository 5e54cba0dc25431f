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
    off their plane (zero where there is no normal). :func:`planes_that_hold` adds
    ``radius (B, H, W)``, the half-size in pixels of the window whose plane each pixel
    took (None from :func:`plane_fit`)."""

    normals: Tensor
    has_normal: Tensor
    tilt_variance: Tensor
    radius: Tensor | None = None


class _Planes(NamedTuple):
    # Each pixel's own window's plane: normal, has_normal, tilt variance, the scatter of its
    # points off the plane (variance, m^2) and the window's centroid.
    normals: Tensor
    has_normal: Tensor
    tilt: Tensor
    scatter: Tensor
    centres: Tensor


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
    both planes and may take either; and on a curved surface every window is off its
    plane alike, so a pixel may take a window beside it, whose plane is tilted by the
    curvature over the shift (:func:`planes_that_hold` takes a shift only where the
    pixel's own plane does not hold).

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
    if not all(0 < f < math.inf for f in shifts):
        raise ValueError(f"plane_fit's shifts must be fractions of the radius > 0, got {shifts}")
    own = _own_planes(points, mask, radius, max_relative_step, step)
    if not shifts:
        return PlaneFit(own.normals, own.has_normal, own.tilt)
    n, tilt, _ = _nearby_planes(points, own, sorted({max(1, round(f * radius)) for f in shifts}))
    return PlaneFit(n, own.has_normal, tilt)


def _own_planes(points: Tensor, mask: Tensor, radius: int, max_relative_step: float, step: int) -> _Planes:
    # plane_fit's planes of each pixel's own window (see there).
    if radius < 1 or not 1 <= step <= radius:
        raise ValueError(f"plane_fit needs radius >= 1 and 1 <= step <= radius, got radius {radius}, step {step}")
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
    scatter = torch.where(has_normal, scatter, torch.zeros_like(scatter))
    return _Planes(n, has_normal, tilt, scatter, points + mean.permute(0, 2, 3, 1))


def _nearby_planes(points: Tensor, own: _Planes, distances: list[int], allowed: Tensor | None = None,
                   holds: Tensor | None = None, noise: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    # plane_fit's shifts: each pixel's normal and tilt variance taken from the window (its
    # own, or one ``distances`` pixels away in the eight directions) whose plane has the
    # least scatter plus squared distance to the pixel; and whether a window beside it was
    # taken ``(B, H, W)``. planes_that_hold's gate: only pixels where ``allowed`` look
    # beside them, at windows where ``holds`` (their plane holds), whose plane the pixel lies
    # on within ``noise`` (a squared distance per pixel); the own window does not compete.
    H, W = points.shape[1:3]
    reach = max(distances)
    # One channel-first stack, padded once: normal (3), centroid (3), scatter, tilt, has_normal.
    usable = own.has_normal if holds is None else own.has_normal & holds
    fields = torch.cat([own.normals, own.centres, own.scatter[..., None], own.tilt[..., None],
                        usable[..., None].to(points.dtype)], -1).permute(0, 3, 1, 2)
    padded = torch.nn.functional.pad(fields, (reach,) * 4)
    if allowed is None:
        best = torch.where(own.has_normal, own.scatter + ((points - own.centres) * own.normals).sum(-1) ** 2,
                           torch.full_like(own.scatter, math.inf))
        looks = own.has_normal
    else:
        best = torch.full_like(own.scatter, math.inf)
        looks = allowed & own.has_normal
    chosen_normals, chosen_tilt = own.normals, own.tilt
    beside = torch.zeros_like(own.has_normal)
    for d in distances:
        for di, dj in ((-d, -d), (-d, 0), (-d, d), (0, -d), (0, d), (d, -d), (d, 0), (d, d)):
            there = padded[:, :, reach + di : reach + di + H, reach + dj : reach + dj + W].permute(0, 2, 3, 1)
            normal, centre = there[..., 0:3], there[..., 3:6]
            distance = ((points - centre) * normal).sum(-1) ** 2
            score = there[..., 6] + distance
            better = looks & (there[..., 8] > 0) & (score < best)
            if noise is not None:  # the pixel on that plane within the noise
                better &= distance <= noise
            best = torch.where(better, score, best)
            chosen_normals = torch.where(better[..., None], normal, chosen_normals)
            chosen_tilt = torch.where(better, there[..., 7], chosen_tilt)
            beside |= better
    return chosen_normals, chosen_tilt, beside


# planes_that_hold: a window's plane holds where its points scatter off it (variance) at most
# this many times the depth's noise, the median over the window of its second differences'
# (:func:`_second_difference_noise`): noise scatters alike at every size, a curved surface's sag
# grows as the window's size squared, a crease's distance from either plane as the size.
# Against the clean files' normals, share more than 10 degrees off: `python -m benchmarks.noisy_normals
# data/mitsuba --every 4` 4.2% (12 Mitsuba sensor-noise files), `... data/procedural --every 4`
# 6.5%. Ad hoc on the same files (the trial script not kept; its mask a little narrower): growth
# 2: 4.6% and 6.8%, 1.5: 13% (Mitsuba), 8: 8.6% (procedural), against 4.0% and 6.2% for 3 and
# 6.1% and 7.4% for plane_fit with shifts, as before. Two references were tried and left
# out: the next smaller window's scatter (beside a crease both windows straddle it: 61 degrees
# off there), and the mean scatter of the 3x3 windows (a plane through 9 points tilts to fit
# noise as large as the pixel spacing, so that reference fell below the noise and a quarter of
# the procedural sensor's pixels took 3x3 planes 52 degrees off).
PLANE_GROWTH = 3.0
# ... windows this wide or wider may be taken beside a pixel (a narrower one rounds a crease
# off over a few pixels only, and on a curved surface its plane beside leans as much).
MIN_SHIFTED_RADIUS = 4
# ... and a pixel lies on its window's plane within this many of the window's standard deviations.
ON_PLANE_SIGMAS = 3.0


def _second_difference_noise(z: Tensor, mask: Tensor) -> Tensor:
    # The depth's noise variance (B, H, W) seen in second differences along rows and columns
    # (a plane's nearly cancel; white noise of variance s^2 gives 6 s^2 each), where the three
    # pixels are valid; NaN where neither direction has them. Unlike a small window's plane,
    # which tilts to fit noise as large as the pixel spacing, it does not absorb the noise.
    nan = torch.full_like(z, float("nan"))
    total, count = torch.zeros_like(z), torch.zeros_like(z)
    for axis in (1, 2):
        n = z.shape[axis]
        if n < 3:
            continue
        lo, mid, hi = (z.narrow(axis, i, n - 2) for i in range(3))
        ok = mask.narrow(axis, 0, n - 2) & mask.narrow(axis, 1, n - 2) & mask.narrow(axis, 2, n - 2)
        value = torch.where(ok, (lo - 2 * mid + hi) ** 2 / 6, torch.zeros_like(mid))
        pad = [0, 0, 0, 0]
        pad[(2 - axis) * 2], pad[(2 - axis) * 2 + 1] = 1, 1
        total += torch.nn.functional.pad(value, pad)
        count += torch.nn.functional.pad(ok.to(z.dtype), pad)
    return torch.where(count > 0, total / count.clamp_min(1), nan)


def _local_median(value: Tensor, mask: Tensor, radius: int, step: int) -> Tensor:
    # The median of ``value (B, H, W)`` (NaN: none) over each pixel's window, sampled every
    # ``step`` pixels of its (2 radius + 1)^2 (5x5 samples at step radius / 2).
    B, H, W = value.shape
    padded = torch.nn.functional.pad(torch.where(mask, value, torch.full_like(value, float("nan"))), (radius,) * 4,
                                     value=float("nan"))
    samples = torch.stack([padded[:, di : di + H, dj : dj + W] for di in range(0, 2 * radius + 1, step)
                           for dj in range(0, 2 * radius + 1, step)])
    return torch.nan_to_num(samples.nanmedian(0).values, nan=0.0)


def window_radii(radius: int) -> list[int]:
    """The window half-sizes :func:`planes_that_hold` tries, largest first: ``radius``,
    halved (rounded down) down to 1."""
    radii = [radius]
    while radii[-1] > 1:
        radii.append(max(1, radii[-1] // 2))
    return radii


def planes_that_hold(points: Tensor, mask: Tensor, *, radius: int = 8, max_relative_step: float = 0.1,
                     shifts: tuple[float, ...] = (), growth: float = PLANE_GROWTH) -> PlaneFit:
    """Each pixel's normal from the largest window on which the depth is a plane.

    :func:`plane_fit`'s wide window averages a sensor's noise away where the surface is a
    plane over it, but rounds a curved surface off: on a ball 50 cm across, 21 m from a
    narrow-angle camera (the DiLiGenT photographs), planes through 21x21 windows put the
    normals 5 degrees off at the median (with ``shifts`` 22), where the depth's own
    differences were 0.6 off. Here the windows of :func:`window_radii` of ``radius`` are
    tried in turn, largest first (the largest sampled every ``radius / 4`` pixels, rounded, as
    :func:`plane_fit`'s ``step``, the others every ``radius / 2``). A window's plane holds at a pixel where its points scatter
    off it (variance) at most ``growth`` (:data:`PLANE_GROWTH`) times the depth's noise (the
    median over the window of what its second differences along rows and columns say), and
    the pixel lies on it within :data:`ON_PLANE_SIGMAS` standard deviations of the noise:
    noise scatters alike at every size, while a surface that curves or creases inside the
    window scatters far more. A
    pixel whose own plane does not hold at a size may take, with ``shifts``, the plane of a
    window of that size beside it (as :func:`plane_fit`'s shifts; windows of
    :data:`MIN_SHIFTED_RADIUS` or wider) that holds and that the pixel lies on; else it tries
    the next size. The smallest window is taken where no larger one holds.

    Returns:
        :class:`PlaneFit` with ``radius (B, H, W)`` long: the half-size of the window
        each pixel's plane came from (0 where there is no normal).
    """
    if radius < 1:
        raise ValueError(f"planes_that_hold needs radius >= 1, got {radius}")
    if not all(0 < f < math.inf for f in shifts) or not growth >= 1:
        raise ValueError(f"planes_that_hold needs shifts > 0 and growth >= 1, got {shifts}, {growth}")
    radii = window_radii(radius)
    depth_noise = _second_difference_noise(points[..., 2], mask)
    # The widest window sampled as plane_fit samples it (every radius / 4 pixels); the narrower
    # ones, which only the pixels the wider ones leave undecided take, every radius / 2.
    steps = [max(1, round(r / 4)) if k == 0 else max(1, r // 2) for k, r in enumerate(radii)]
    fits = [_own_planes(points, mask, r, max_relative_step, step) for r, step in zip(radii, steps)]
    smallest, largest = fits[-1], fits[0]
    # Where the smallest window has too few points for a plane, the largest's is the fallback.
    normals = torch.where(smallest.has_normal[..., None], smallest.normals, largest.normals)
    tilt = torch.where(smallest.has_normal, smallest.tilt, largest.tilt)
    has_normal = smallest.has_normal | largest.has_normal
    chosen = torch.where(smallest.has_normal, radii[-1], torch.where(largest.has_normal, radii[0], 0))
    undecided = smallest.has_normal.clone()
    for k in range(len(radii) - 1):
        fit = fits[k]
        tiny = torch.finfo(points.dtype).tiny
        # The plane holds over the window, and the pixel itself lies on it (beside a crease a
        # window's plane can be the other side's, which most of its points lie on).
        distance = ((points - fit.centres) * fit.normals).sum(-1) ** 2
        noise = _local_median(depth_noise, mask, radii[k], max(1, radii[k] // 2)).clamp_min(tiny)
        holds = (fit.has_normal & (fit.scatter <= growth * noise) & (distance <= ON_PLANE_SIGMAS**2 * noise))
        take = undecided & holds
        normals = torch.where(take[..., None], fit.normals, normals)
        tilt = torch.where(take, fit.tilt, tilt)
        chosen = torch.where(take, radii[k], chosen)
        undecided &= ~take
        if shifts and radii[k] >= MIN_SHIFTED_RADIUS and bool(undecided.any()):
            beside_n, beside_tilt, beside = _nearby_planes(points, fit, sorted({max(1, round(f * radii[k])) for f in shifts}),
                                                           allowed=undecided, holds=fit.scatter <= growth * noise,
                                                           noise=ON_PLANE_SIGMAS**2 * noise)
            normals = torch.where(beside[..., None], beside_n, normals)
            tilt = torch.where(beside, beside_tilt, tilt)
            chosen = torch.where(beside, radii[k], chosen)
            undecided &= ~beside
    return PlaneFit(normals, has_normal, tilt, chosen)


# The half-size of smooth_normals' window as the estimator uses it (prepare).
SMOOTHING_RADIUS = 3


def smooth_normals(
    points: Tensor, normals: Tensor, mask: Tensor, *, radius: int = SMOOTHING_RADIUS, passes: int = 2,
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


# normal_noise's percentile: a sensor whose depth comes in steps (a Kinect's disparity, a
# depth map binned by its median) leaves most neighbours on one step, so the median angle
# of the real frames of ../shared/real_captures was 0.05-0.46 degrees where a quarter of
# the pixels were 2-3 degrees off; the 75th percentile tells them from clean depth.
NOISE_QUANTILE = 0.75


def normal_noise(points: Tensor, normals: Tensor, mask: Tensor, quantile: float = NOISE_QUANTILE) -> Tensor:
    """The ``quantile`` (75th percentile) of the angle (degrees) ``(B,)`` between each
    valid normal and its :func:`smooth_normals` version with a one-pixel window: about
    zero for normals of clean geometry, a degree for depth in millimetre steps, a few
    degrees for normals of a consumer depth sensor."""
    smoothed = smooth_normals(points, normals, mask, radius=1, passes=1)
    cos = (smoothed * normals).sum(-1).clamp(-1, 1)
    angle = torch.rad2deg(torch.acos(cos))
    angle = torch.where(mask, angle, torch.full_like(angle, float("nan")))
    return torch.nanquantile(angle.flatten(1), quantile, dim=1)


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
