"""A depth map integrated from a normal map, as photometric-stereo data sets make theirs.

DiLiGenT (the real objects of ``../shared/real_captures/objects``) has true normals and no depth;
the depth a user's capture folder gets from it is the surface whose normals they are, found by
least squares and rounded to millimetres. On a smooth object that surface is the object (the
shared bear and cat: their depth's normals 1.5-1.6 degrees off the true ones). Where one part
hides another the true depth jumps, and nothing in a normal map says by how much: the least
squares spread the missing jumps over both parts as a slow tilt (our generator's box half in
front of a sphere: the depth's normals 4.2 degrees off at the median, 19 at the 90th percentile;
2026-12-07). :func:`integrated_depth` makes that depth for our generator's renders
(:func:`selfsup.scenes.studio.photograph`), so that the estimator meets what such a capture holds.

The relation (a perspective camera, OpenCV axes): a pixel ``(u, v)`` sees the point
``z r`` with ``r = ((u - cx) / fx, (v - cy) / fy, 1)``; the surface through it with normal
``n`` has ``d ln z / du = -n_x / (fx n.r)`` and ``d ln z / dv = -n_y / (fy n.r)``.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["integrated_depth"]

# The conjugate gradients stop at this relative residual of the normal equations, or after
# this many steps (a 160x120 region converges in a few hundred).
INTEGRATION_TOLERANCE = 1e-10
INTEGRATION_STEPS = 5000


def integrated_depth(normals: Tensor, depth: Tensor, K: Tensor) -> Tensor:
    """``(H, W)`` the depth whose log's steps between 4-neighbours best match, in least squares,
    the steps the unit ``normals (H, W, 3)`` give (each step the mean of its two pixels'), over
    each 4-connected region of pixels with ``depth (H, W) > 0`` whose normal faces the camera;
    each region scaled to ``depth``'s geometric mean over it (a normal map says nothing of a
    region's distance). 0 where ``depth`` is, or where the normal faces away from its ray.
    ``K (3, 3)``: the intrinsics. Computed in float64; returned in ``depth``'s dtype."""
    from skimage.measure import label

    if normals.ndim != 3 or normals.shape[-1] != 3 or depth.shape != normals.shape[:2] or K.shape != (3, 3):
        raise ValueError(f"integrated_depth needs normals (H, W, 3), depth (H, W) and K (3, 3), got "
                         f"{tuple(normals.shape)}, {tuple(depth.shape)}, {tuple(K.shape)}")
    n, z, K = normals.detach().double().cpu(), depth.detach().double().cpu(), K.detach().double().cpu()
    if not (bool(torch.isfinite(n).all()) and bool(torch.isfinite(K).all())):
        raise ValueError("integrated_depth needs finite normals and intrinsics")
    H, W = z.shape
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    ray = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    facing = (n * ray).sum(-1)
    valid = torch.isfinite(z) & (z > 0) & (facing < -1e-6)
    if not bool(valid.any()):
        return torch.zeros_like(depth)
    safe = torch.where(valid, facing, -torch.ones_like(facing))
    slope = (-n[..., 0] / (K[0, 0] * safe), -n[..., 1] / (K[1, 1] * safe))  # d ln z / du, d ln z / dv
    index = torch.full((H, W), -1, dtype=torch.long)
    index[valid] = torch.arange(int(valid.sum()))
    first, second, step = [], [], []
    for axis, g in ((1, slope[0]), (0, slope[1])):  # pairs right, then down
        a = [slice(None), slice(None)]
        b = [slice(None), slice(None)]
        a[axis], b[axis] = slice(0, -1), slice(1, None)
        both = valid[tuple(a)] & valid[tuple(b)]
        first.append(index[tuple(a)][both])
        second.append(index[tuple(b)][both])
        step.append(0.5 * (g[tuple(a)][both] + g[tuple(b)][both]))
    i0, i1, g = torch.cat(first), torch.cat(second), torch.cat(step)
    log_z = _least_squares_steps(i0, i1, g, int(valid.sum()))
    # Each region's own constant: its geometric mean the given depth's.
    regions = torch.from_numpy(label(valid.numpy(), connectivity=1).astype(np.int64))[valid] - 1
    count = int(regions.max()) + 1
    pixels = torch.zeros(count, dtype=torch.float64).index_add_(0, regions, torch.ones_like(log_z))
    shift = (torch.zeros(count, dtype=torch.float64).index_add_(0, regions, torch.log(z[valid]) - log_z) / pixels)
    out = torch.zeros(H, W, dtype=torch.float64)
    out[valid] = torch.exp(log_z + shift[regions])
    return out.to(depth)


def _least_squares_steps(i0: Tensor, i1: Tensor, step: Tensor, count: int) -> Tensor:
    # ``(count,)`` x minimising sum (x[i1] - x[i0] - step)^2: conjugate gradients on the normal
    # equations (a graph Laplacian, singular by one constant a region, its right side orthogonal
    # to them, so the iterates stay in its range). Each region's constant is left to the caller.
    def laplacian(x: Tensor) -> Tensor:
        d = x[i1] - x[i0]
        return torch.zeros_like(x).index_add_(0, i1, d).index_add_(0, i0, -d)

    b = torch.zeros(count, dtype=torch.float64).index_add_(0, i1, step).index_add_(0, i0, -step)
    x = torch.zeros_like(b)
    r = b.clone()
    p = r.clone()
    rr = float(r @ r)
    stop = INTEGRATION_TOLERANCE ** 2 * max(rr, 1e-300)
    for _ in range(INTEGRATION_STEPS):
        if rr <= stop:
            break
        Ap = laplacian(p)
        alpha = rr / max(float(p @ Ap), 1e-300)
        x += alpha * p
        r -= alpha * Ap
        rr, rr_before = float(r @ r), rr
        p = r + (rr / rr_before) * p
    return x
