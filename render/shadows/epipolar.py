"""Watertight, smooth shadows of a depth map by an epipolar sweep.

Model: the depth map is a closed heightfield seen from the camera: everything
behind the visible surface (farther along a camera ray) is solid. The surface
between pixel centres is the bilinear interpolation of the pixel values, so the
occluder is watertight: no splat holes, no light leaking through a surface.

Why a sweep suffices: the shadow ray from a surface point ``X`` to the light
``L`` lies in the plane through the camera centre ``O``, ``L`` and ``X``; it
projects onto the image segment from ``X``'s pixel to the epipole ``e`` (the
image of ``L``), or away from ``e`` when the light is behind the camera. Inside
that plane, let ``gamma(Y)`` be the angle at ``L`` between ``L->O`` and
``L->Y``. The ray is blocked exactly when some surface point ``Y`` between them
on the epipolar line has ``gamma(Y) < gamma(X)``: ``Y`` then lies on the camera's
side of the ray, so the ray passes behind the surface. Visibility is therefore a
comparison of ``gamma(X)`` with the running minimum of ``gamma`` along each
epipolar line, O(samples) per light instead of O(pixels x steps) for ray marching.

Smoothness: with ``margin = (min gamma - gamma(X)) / pixel_angle(X)``, the clearance
of the ray past the occluder in units of the angle one pixel at ``X`` subtends at
the light, visibility is ``smoothstep((margin + bias + width) / width)``: exactly 1
on lit surfaces, exactly 0 deep in shadow, C1 in between. The gradient with
respect to the light (and the points) is the exact derivative of this smoothed,
discretised model: the running minimum picks its occluder sample without a
gradient (a piecewise-constant choice), then the occluder's angle, its position on
the epipolar line and the pixel's lookup are recomputed with autograd. That
recomputation runs only for pixels inside the smooth band: everywhere else the
clamped smoothstep is flat and its derivative is exactly zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["EpipolarShadowOptions", "epipolar_shadow_visibility"]

# gamma lies in [0, pi]; this marks "no occluder seen yet" in the running minimum.
_NO_OCCLUDER = 4.0


@dataclass(frozen=True)
class EpipolarShadowOptions:
    """Settings of the epipolar sweep.

    Attributes:
        width_px: width of the soft transition, in pixel-sized angles at the
            receiver. Larger gives smoother gradients and softer shadow edges.
        bias_px: an occluder must cover the shadow ray by this much before the
            transition starts; absorbs interpolation error on curved surfaces.
        spacing_px: spacing of samples along and across epipolar lines, in pixels.
            Cost is about ``pi * diagonal^2 / spacing^2`` samples per light when the
            light projects inside the image, fewer when outside.
        lookback: how many samples before a pixel's own position its occluders
            must lie (avoids a pixel shadowing itself).
        chunk_samples: the sweep is done in chunks of at most this many samples
            (bounds peak memory, no effect on results).
    """

    width_px: float = 1.0
    bias_px: float = 0.5
    spacing_px: float = 1.0
    lookback: float = 1.0
    chunk_samples: int = 1 << 24

    def __post_init__(self) -> None:
        for name in ("width_px", "spacing_px"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not self.bias_px >= 0:
            raise ValueError(f"bias_px must be >= 0, got {self.bias_px}")
        if not self.lookback >= 0:
            raise ValueError(f"lookback must be >= 0, got {self.lookback}")


@dataclass(frozen=True)
class _Lines:
    """The epipolar sampling pattern of each (image, light), all ``(N,)`` for N = B*L."""

    epipole: Tensor  # (N, 2) pixel coordinates of the light's image
    forward: Tensor  # (N,) bool: light in front of the camera (sweep outwards)
    periodic: Tensor  # (N,) bool: epipole inside the image (lines all around)
    theta0: Tensor  # (N,) angle of line 0
    dtheta: Tensor  # (N,) angle between lines
    r_min: Tensor  # (N,) distance of the nearest image point to the epipole
    r_max: Tensor  # (N,) distance of the farthest image point
    dr: Tensor  # (N,) distance between samples
    num_lines: int
    num_samples: int

    def select(self, key) -> "_Lines":
        """Every field indexed by ``key``: a slice or index tensor of pairs, or
        ``(slice(None), None)`` for ``(N, 1)`` fields that broadcast against pixels."""
        fields = ("epipole", "forward", "periodic", "theta0", "dtheta", "r_min", "r_max", "dr")
        return _Lines(*(getattr(self, f)[key] for f in fields), self.num_lines, self.num_samples)

    def radius(self, k: Tensor) -> Tensor:
        """Distance to the epipole of sample index ``k`` ``(N, ...)``."""
        shape = (-1,) + (1,) * (k.dim() - 1)
        fwd = self.r_min.view(shape) + k * self.dr.view(shape)
        back = self.r_max.view(shape) - k * self.dr.view(shape)
        return torch.where(self.forward.view(shape), fwd, back)


def _make_lines(light_position: Tensor, K: Tensor, height: int, width: int, spacing: float) -> _Lines:
    """Sampling pattern covering the image for each light; ``light_position (N, 3)``, ``K (N, 3, 3)``."""
    dtype = light_position.dtype
    lz = light_position[:, 2]
    # Guard: a light in the camera plane (z = 0) projects to infinity; nudge it
    # to a tiny |z| so the lines become (nearly) parallel instead of undefined.
    eps_z = 1e-4 * light_position.norm(dim=-1) + torch.finfo(dtype).tiny ** 0.5
    forward = lz >= 0
    z_eff = torch.where(lz.abs() < eps_z, torch.where(forward, eps_z, -eps_z), lz)
    projected = torch.einsum("nij,nj->ni", K, light_position)
    epipole = projected[:, :2] / z_eff[:, None]

    corners = torch.tensor(
        [[0.0, 0.0], [width - 1.0, 0.0], [0.0, height - 1.0], [width - 1.0, height - 1.0]],
        dtype=dtype, device=light_position.device,
    )
    to_corner = corners[None] - epipole[:, None]  # (N, 4, 2)
    r_corner = to_corner.norm(dim=-1)
    r_max = r_corner.amax(-1)
    upper = corners[3]
    inside = ((epipole >= 0) & (epipole <= upper)).all(-1)
    nearest = torch.minimum(torch.maximum(epipole, torch.zeros_like(upper)), upper)
    r_min = torch.where(inside, torch.zeros_like(r_max), (epipole - nearest).norm(dim=-1))

    # Angular span of the image seen from an outside epipole: corner angles
    # relative to the direction of the image centre (no wrap-around possible,
    # the rectangle subtends less than pi from outside).
    to_centre = corners.mean(0)[None] - epipole
    theta_c = torch.atan2(to_centre[:, 1], to_centre[:, 0])
    cross = to_centre[:, None, 0] * to_corner[..., 1] - to_centre[:, None, 1] * to_corner[..., 0]
    dot = (to_centre[:, None] * to_corner).sum(-1)
    rel = torch.atan2(cross, dot)
    span = torch.where(inside, torch.full_like(r_max, 2 * math.pi), rel.amax(-1) - rel.amin(-1))
    theta0 = torch.where(inside, torch.full_like(r_max, -math.pi), theta_c + rel.amin(-1))

    with torch.no_grad():
        lines_needed = torch.ceil(span * r_max / spacing).amax()
        samples_needed = torch.ceil((r_max - r_min) / spacing).amax()
        num_lines = max(int(lines_needed) + 1, 2)
        num_samples = max(int(samples_needed) + 1, 2)
    dtheta = torch.where(inside, span / num_lines, span / (num_lines - 1))
    # Guard: an image of one pixel has r_max == r_min; keep the step non-zero.
    dr = ((r_max - r_min) / (num_samples - 1)).clamp_min(torch.finfo(dtype).eps)
    return _Lines(epipole, forward, inside, theta0, dtheta, r_min, r_max, dr, num_lines, num_samples)


def _angle_from_camera_ray(points: Tensor, light_position: Tensor) -> Tensor:
    """``gamma``: angle at the light between ``L->O`` and ``L->X``.

    Args:
        points: ``(N, M, 3)``; light_position: ``(N, 3)``.

    Returns:
        ``(N, M)`` angles in ``[0, pi]``.
    """
    c = -light_position[:, None, :]
    d = points - light_position[:, None, :]
    cx, cy, cz = c.unbind(-1)
    dx, dy, dz = d.unbind(-1)
    sq = (cy * dz - cz * dy).square() + (cz * dx - cx * dz).square() + (cx * dy - cy * dx).square()
    # sqrt guard: |c x d| is 0 for points on the line L-O; the floor keeps sqrt'
    # finite there (atan2 itself is smooth away from (0, 0)).
    sin_part = sq.clamp_min(torch.finfo(points.dtype).tiny).sqrt()
    cos_part = cx * dx + cy * dy + cz * dz
    return torch.atan2(sin_part, cos_part)


def _bilinear(image: Tensor, xy: Tensor, height: int, width: int) -> Tensor:
    """Sample ``image (N, C, H, W)`` at pixel coordinates ``xy (N, M, 2)`` -> ``(N, C, M)``."""
    scale = xy.new_tensor([2.0 / max(width - 1, 1), 2.0 / max(height - 1, 1)])
    grid = (xy * scale - 1).unsqueeze(1)  # (N, 1, M, 2)
    return F.grid_sample(image, grid, mode="bilinear", padding_mode="zeros", align_corners=True).squeeze(2)


def _masked_angle(angle_image: Tensor, xy: Tensor, height: int, width: int) -> tuple[Tensor, Tensor]:
    """Mask-normalised bilinear ``gamma`` at ``xy``; ``angle_image (N, 2, H, W)`` holds
    ``[gamma * mask, mask]``. Returns ``gamma (N, M)`` and validity ``(N, M)``."""
    sampled = _bilinear(angle_image, xy, height, width)
    weight = sampled[:, 1]
    # A sample is surface when most of its bilinear weight falls on valid pixels;
    # the division is guarded for the rest (holes, outside the image).
    valid = weight > 0.5
    angle = sampled[:, 0] / torch.where(valid, weight, 1.0)
    return angle, valid


def epipolar_shadow_visibility(
    points: Tensor,
    mask: Tensor,
    intrinsics: Tensor,
    light_position: Tensor,
    options: EpipolarShadowOptions | None = None,
) -> Tensor:
    """Visibility of every pixel from every light, by the epipolar heightfield sweep.

    Args:
        points: ``(B, H, W, 3)`` camera-frame points of a depth map (the occluders).
        mask: ``(B, H, W)`` bool validity; holes occlude nothing.
        intrinsics: ``(B, 3, 3)`` pinhole matrix of the view.
        light_position: ``(B, L, 3)``.
        options: see :class:`EpipolarShadowOptions`.

    Returns:
        ``(B, L, H, W)`` visibility in [0, 1], differentiable with respect to the
        light positions and the points.

    Example:
        >>> K = torch.tensor([[[2.0, 0, 1.5], [0, 2.0, 1.5], [0, 0, 1]]])
        >>> from render.geometry import unproject_depth
        >>> pts = unproject_depth(torch.ones(1, 4, 4), K)
        >>> mask = torch.ones(1, 4, 4, dtype=torch.bool)
        >>> v = epipolar_shadow_visibility(pts, mask, K, torch.tensor([[[0.0, 0.0, 0.5]]]))
        >>> v.min().item()
        1.0
    """
    options = options or EpipolarShadowOptions()
    B, H, W, _ = points.shape
    L = light_position.shape[1]
    N = B * L
    # (B, L, 3) -> (N, 3); per-image tensors repeated per light: (B, ...) -> (N, ...)
    light = light_position.reshape(N, 3)
    image_index = torch.arange(B, device=points.device).repeat_interleave(L)
    K = intrinsics.to(points.dtype)[image_index]
    pts = points.reshape(B, 1, H * W, 3).expand(B, L, H * W, 3).reshape(N, H * W, 3)
    valid = mask.reshape(B, 1, H * W).expand(B, L, H * W).reshape(N, H * W)
    # Lights that project inside the image need lines all around their epipole,
    # about 2.5x the samples of the others: sweep the two kinds separately so that
    # one such light does not size the pattern of every other (image, light).
    lines = _make_lines(light, K, H, W, options.spacing_px)
    groups = [torch.nonzero(lines.periodic == kind).squeeze(1) for kind in (False, True)]
    groups = [g for g in groups if g.numel()]
    if len(groups) == 1:
        visibility = _sweep(pts, valid, K, light, H, W, options, lines)
    else:
        visibility = torch.empty(N, H * W, dtype=points.dtype, device=points.device)
        for g in groups:
            visibility = visibility.index_copy(0, g, _sweep(pts[g], valid[g], K[g], light[g], H, W, options))
    return visibility.reshape(B, L, H, W)


def _sweep(pts: Tensor, valid: Tensor, K: Tensor, light: Tensor, H: int, W: int,
           options: EpipolarShadowOptions, lines: _Lines | None = None) -> Tensor:
    """Visibility ``(N, H*W)`` of ``pts (N, H*W, 3)`` from ``light (N, 3)``, see above;
    ``lines`` is their pattern when already built (else sized for these N alone)."""
    N = light.shape[0]
    dtype, device = pts.dtype, pts.device
    if lines is None:
        lines = _make_lines(light, K, H, W, options.spacing_px)
    gamma = _angle_from_camera_ray(pts, light)  # (N, H*W)
    weight = valid.to(dtype)
    focal = 0.5 * (K[:, 0, 0] + K[:, 1, 1])
    nl, ns = lines.num_lines, lines.num_samples
    u = torch.arange(W, dtype=dtype, device=device).repeat(H)
    v = torch.arange(H, dtype=dtype, device=device).repeat_interleave(W)

    with torch.no_grad():
        # 1) The sweep: for each line and sample, the smallest gamma at or before
        #    it (running) and which sample holds it (argmin).
        angle_image = torch.stack([gamma * weight, weight], dim=1).reshape(N, 2, H, W)
        running = torch.empty(N, nl, ns, dtype=dtype, device=device)
        argmin = torch.empty(N, nl, ns, dtype=torch.long, device=device)
        rows_per_chunk = max(1, options.chunk_samples // (nl * ns))
        line_index = torch.arange(nl, dtype=dtype, device=device)
        sample_index = torch.arange(ns, dtype=dtype, device=device)
        for start in range(0, N, rows_per_chunk):
            part = slice(start, min(N, start + rows_per_chunk))
            sub = lines.select(part)
            n = part.stop - part.start
            # Directions per line (n, nl, 1, 2) times radii per sample (n, 1, ns, 1).
            theta = sub.theta0[:, None] + line_index[None] * sub.dtheta[:, None]
            direction = torch.stack([torch.cos(theta), torch.sin(theta)], dim=-1)[:, :, None]
            radius = sub.radius(sample_index[None].expand(n, ns))[:, None, :, None]
            xy = sub.epipole[:, None, None] + radius * direction  # (n, nl, ns, 2)
            angle, ok = _masked_angle(angle_image[part], xy.reshape(n, nl * ns, 2), H, W)
            angle = torch.where(ok, angle, _NO_OCCLUDER).reshape(n, nl, ns)
            torch.cummin(angle, dim=-1, out=(running[part], argmin[part]))
        running_flat, argmin_flat = running.reshape(N, nl * ns), argmin.reshape(N, nl * ns)

        # 2) Every pixel, from the running minima of the pattern nodes around it.
        def node_from_sweep(line: Tensor, k: Tensor, has_prior: Tensor, direction: Tensor) -> Tensor:
            value = running_flat.gather(1, line * ns + k)
            return torch.where(has_prior & (value < _NO_OCCLUDER), value, _NO_OCCLUDER)

        running_min = _running_min_at_pixels(lines.select((slice(None), None)), u, v, nl, ns, options.lookback, node_from_sweep)
        distance = (light[:, None] - pts).norm(dim=-1)
        visibility, t = _smooth_visibility(running_min, gamma, pts[..., 2], distance, focal[:, None], options)
        visibility = torch.where(valid, visibility, 1.0)
        band = valid & (t > 0) & (t < 1)

    if not (torch.is_grad_enabled() and (light.requires_grad or pts.requires_grad)):
        return visibility

    # 3) With a gradient, only where it is not zero: inside the smooth band (the
    #    clamped smoothstep is flat, derivative 0, everywhere else). The same
    #    computation as above, but the occluders' angles are recomputed from
    #    their positions on the epipolar lines so that autograd sees how they
    #    move with the light and the points.
    rows, cols = band.nonzero(as_tuple=True)
    if rows.numel() == 0:
        return visibility
    seen = running_flat < _NO_OCCLUDER

    def node_recomputed(line: Tensor, k: Tensor, has_prior: Tensor, direction: Tensor) -> Tensor:
        flat = line * ns + k
        chosen = argmin_flat[rows, flat]
        xy = band_lines.epipole + band_lines.radius(chosen.to(dtype))[..., None] * direction
        angle, ok = _masked_angle_at(gamma, weight, rows, xy, H, W)
        return torch.where(has_prior & seen[rows, flat] & ok, angle, _NO_OCCLUDER)

    band_lines = lines.select(rows)
    band_min = _running_min_at_pixels(band_lines, u[cols], v[cols], nl, ns, options.lookback, node_recomputed)
    band_points = pts[rows, cols]
    band_visibility, _ = _smooth_visibility(
        band_min, gamma[rows, cols], band_points[:, 2], (light[rows] - band_points).norm(dim=-1), focal[rows], options
    )
    return visibility.index_put((rows, cols), band_visibility)


def _running_min_at_pixels(lines: _Lines, u: Tensor, v: Tensor, nl: int, ns: int, lookback: float, node_angle) -> Tensor:
    """Bilinear interpolation, at pixels ``(u, v)``, of the running minimum of gamma
    at the four pattern nodes around each pixel, ``lookback`` samples before it.

    ``lines`` fields broadcast against ``u`` and ``v``; ``node_angle(line, k,
    has_prior, direction)`` gives the running minimum of one node (long indices
    of the pixels' shape).
    """
    dtype = u.dtype
    dx, dy = u - lines.epipole[..., 0], v - lines.epipole[..., 1]
    r_pix = (dx * dx + dy * dy).sqrt()
    # atan2 guard: the pixel at the epipole has no direction; any fixed one will do.
    at_epipole = r_pix < 1e-6
    theta = torch.atan2(torch.where(at_epipole, 1.0, dy), torch.where(at_epipole, 1.0, dx))
    # Angle from line 0, wrapped: lines all around (periodic) span [0, 2 pi); lines
    # from an outside epipole span less than pi, so [-pi/2, 3 pi/2) holds them
    # whole even where they straddle the +-pi seam of atan2.
    shift = torch.where(lines.periodic, 0.0, math.pi / 2)
    rel = torch.remainder(theta - lines.theta0 + shift, 2 * math.pi) - shift
    upper = (nl - 1) + lines.periodic.to(dtype)  # periodic lines wrap to line 0 at index nl
    a = torch.minimum((rel / lines.dtheta).clamp_min(0), upper)
    radial = torch.where(lines.forward, r_pix - lines.r_min, lines.r_max - r_pix)
    s = radial / lines.dr - lookback
    a0, s0 = a.detach().floor(), s.detach().floor()
    fa, fs = a - a0, s - s0
    a0, s0 = a0.long(), s0.long()
    nodes = []
    for da in (0, 1):
        line = a0 + da
        line = torch.where(lines.periodic, torch.remainder(line, nl), line.clamp(0, nl - 1))
        theta_line = lines.theta0 + line.to(dtype) * lines.dtheta
        direction = torch.stack([torch.cos(theta_line), torch.sin(theta_line)], dim=-1)
        for ds in (0, 1):
            k = s0 + ds
            nodes.append(node_angle(line, k.clamp(0, ns - 1), k >= 0, direction))
    m00, m01, m10, m11 = nodes
    return (1 - fa) * ((1 - fs) * m00 + fs * m01) + fa * ((1 - fs) * m10 + fs * m11)


def _smooth_visibility(running_min: Tensor, gamma: Tensor, depth: Tensor, distance: Tensor, focal: Tensor,
                       options: EpipolarShadowOptions) -> tuple[Tensor, Tensor]:
    """Smoothstep of the occlusion margin in pixel-sized angles; returns visibility and its argument t."""
    tiny = torch.finfo(gamma.dtype).tiny ** 0.5
    # Angle one pixel at X subtends at the light (fronto-parallel footprint z/f).
    # Guard: a pixel at the light's position (or of zero depth) has no footprint.
    pixel_angle = (depth.abs() / (focal * distance).clamp_min(tiny)).clamp_min(tiny)
    margin = (running_min - gamma) / pixel_angle
    t = ((margin + options.bias_px + options.width_px) / options.width_px).clamp(0, 1)
    return t * t * (3 - 2 * t), t


def _masked_angle_at(gamma: Tensor, weight: Tensor, rows: Tensor, xy: Tensor, H: int, W: int) -> tuple[Tensor, Tensor]:
    """Like :func:`_masked_angle` (same bilinear weights, zero padding), for points
    ``xy (M, 2)`` of images ``rows (M,)`` of ``gamma/weight (N, H*W)``."""
    x, y = xy[..., 0], xy[..., 1]
    x0, y0 = x.detach().floor(), y.detach().floor()
    wx, wy = x - x0, y - y0
    x0, y0 = x0.long(), y0.long()
    num = torch.zeros_like(x)
    den = torch.zeros_like(x)
    for oy in (0, 1):
        for ox in (0, 1):
            xi, yi = x0 + ox, y0 + oy
            inside = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
            index = yi.clamp(0, H - 1) * W + xi.clamp(0, W - 1)
            w = (wx if ox else 1 - wx) * (wy if oy else 1 - wy)
            m = weight[rows, index] * inside
            num = num + w * m * gamma[rows, index]
            den = den + w * m
    ok = den > 0.5
    return num / torch.where(ok, den, 1.0), ok
