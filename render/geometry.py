"""Camera geometry: depth to points, robust normals, intrinsics.

Conventions (OpenCV camera frame, see ``render/__init__.py``): x right, y down,
z forward; pixel ``(row i, col j)`` has image coordinates ``u = j, v = i``.
"""

from __future__ import annotations

import torch
from kornia.geometry.depth import depth_to_3d_v2
from torch import Tensor

__all__ = ["unproject_depth", "normals_from_points", "smallest_eigenvector", "fit_intrinsics", "pixel_grid", "dot3",
           "norm3", "broadcast_shape"]


def broadcast_shape(*shapes: torch.Size | tuple[int, ...]) -> tuple[int, ...]:
    """The broadcast of ``shapes``, as ``torch.broadcast_shapes``; ValueError where they do
    not broadcast. Not that function: its first call imports sympy (half a second in every
    fresh process or DataLoader worker), and each call costs more."""
    if all(shape == shapes[0] for shape in shapes[1:]):  # the ray caster's usual case, per operation
        return tuple(shapes[0])
    width = max(len(shape) for shape in shapes)
    out = [1] * width
    for shape in shapes:
        for axis, size in enumerate((1,) * (width - len(shape)) + tuple(shape)):
            if size == 1:
                continue
            if out[axis] not in (1, size):
                raise ValueError(f"shapes {[tuple(s) for s in shapes]} do not broadcast")
            out[axis] = size
    return tuple(out)


def dot3(a: Tensor, b: Tensor, axis: int = -1) -> Tensor:
    """``a . b`` over an axis of length 3 (the last by default), broadcasting:
    ``(..., 3) x (..., 3) -> (...)``.

    On the CPU as three strided products and two sums: 2-3x faster there than a
    reduction over so short an axis (measured 2026-11-23, 300k vectors); elsewhere one
    fused kernel (``torch.linalg.vecdot``).
    """
    if a.device.type != "cpu":
        return torch.linalg.vecdot(a, b, dim=axis)
    ax, ay, az = a.unbind(axis)
    bx, by, bz = b.unbind(axis)
    return ax * bx + ay * by + az * bz


def positive(x: Tensor) -> Tensor:
    """1 where ``x > 0``, 0 elsewhere, in ``x``'s dtype (NaN stays NaN): a mask to multiply
    by. On the CPU ``torch.where`` and bool masks cost 5-30x a float product (torch 2.13, one
    core, 38,400 floats: where 178 us, ``x > 0`` 30 us, this 12 us, a product 5 us;
    ``benchmarks/results/planar_shading_cpu2_2026-12-07.md``); a masked value
    ``v * positive(x)`` must be finite where ``x <= 0``."""
    return x.sign().clamp_min(0)


def norm3(v: Tensor, axis: int = -1) -> Tensor:
    """Euclidean length over an axis of length 3 (the last by default): ``(..., 3) -> (...)``
    (see :func:`dot3`).

    With a gradient, always ``torch.linalg.vector_norm``: its derivative at a zero
    vector is 0, where that of a square root is infinite.
    """
    if v.device.type != "cpu" or (v.requires_grad and torch.is_grad_enabled()):
        return torch.linalg.vector_norm(v, dim=axis)
    return dot3(v, v, axis).sqrt()


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


def smallest_eigenvector(moments: Tensor) -> tuple[Tensor, Tensor]:
    """Eigenvalues ``(..., 3)`` (ascending) of symmetric 3x3 matrices given by their six
    distinct entries ``moments (..., 6)`` (xx yy zz xy xz yz), and the unit eigenvector
    ``(..., 3)`` of the smallest, in closed form: the eigenvalues by the trigonometric
    solution of the characteristic cubic, the eigenvector as the longest cross product
    of two rows of ``A - l0 I``. Elementwise passes only, where a batched
    ``torch.linalg.eigh`` of one 160x120 image's matrices took half of
    :func:`selfsup.estimation.normals.plane_fit` (18 of 37 ms against 1.8 ms, 2 threads). The vector is non-finite where every eigenvalue is equal (no direction is the
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


