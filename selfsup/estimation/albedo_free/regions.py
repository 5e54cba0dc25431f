"""Regions of one albedo that shading does not cut: segments joined across the edges of shading.

The image's edges (Felzenszwalb's segmentation, :func:`selfsup.estimation.albedo_free.albedo_segments`)
are edges of albedo and of shading alike. On a ball under one lamp the terminator of its
attached shadow, its highlight and the falloff cut it into bands (14-25 segments on the
DiLiGenT photographs, the largest a third of the ball), each band's free level takes the
shading with it, and no light is left to find. What tells the two kinds of edge apart
(:func:`join_shading_cuts`):

- **colour**: white light scales the three channels alike, so shading leaves the
  chromaticity (log R/G, log B/G) as it is; an albedo edge nearly always changes it;
- **continuity**: on a smooth surface the shading is smooth, so the step of the log
  shading across a cut between two of its pixels is what the steps beside it, on either
  side, predict; an albedo edge (and a sharp cast shadow) is a step the neighbours do
  not predict.

Two segments of one smooth surface that meet along a cut where both hold (the median over
the cut's pixel pairs, each pair's allowance widened by its pixels' noise) are one region.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["join_shading_cuts", "group_medians", "EDGE_NOISE_SIGMAS", "MIN_CUT_PAIRS"]

# A cut of fewer pixel pairs says too little to join its two segments.
MIN_CUT_PAIRS = 4
# A pair's step is allowed this many standard deviations of its pixels' noise beside the
# fixed allowance (the log of an 8-bit pixel near black is noise).
EDGE_NOISE_SIGMAS = 3.0


def _find(parent: np.ndarray, i: int) -> int:
    # Union-find root of ``i``, halving the path on the way.
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


def group_medians(values: Tensor, group: Tensor, groups: int, upper: bool = False) -> tuple[Tensor, Tensor]:
    """Each group's median of ``values (N,)`` by ``group (N,)`` (ids in ``[0, groups)``):
    ``(groups,)`` medians (of an even count the lower middle value, with ``upper`` the upper;
    an empty group's value means nothing: mask it by the count) and ``(groups,)`` counts.
    One sort by value, then a stable one by group: each group's values in order, in a row."""
    by_value = values.argsort()
    ordered = values[by_value][group[by_value].argsort(stable=True)]
    counts = torch.bincount(group, minlength=groups)
    middle = counts // 2 if upper else (counts - 1).clamp_min(0) // 2
    index = (counts.cumsum(0) - counts + middle).clamp(0, max(values.numel() - 1, 0))
    return (ordered[index] if values.numel() else values.new_zeros(groups)), counts


def _medians(values: np.ndarray, group: Tensor, groups: int) -> tuple[np.ndarray, np.ndarray]:
    # Each group's median of ``values`` (the upper middle of an even count) and its count:
    # :func:`group_medians` of numpy values.
    medians, counts = group_medians(torch.from_numpy(np.ascontiguousarray(values, dtype=np.float64)), group, groups,
                                    upper=True)
    return medians.numpy(), counts.numpy()


def join_shading_cuts(labels: np.ndarray, log_grey: np.ndarray, chroma: np.ndarray, noise: np.ndarray,
                      surfaces: np.ndarray, max_step: float, max_chroma: float) -> np.ndarray:
    """Segments ``labels (H, W)`` (-1: none) of one image joined where only shading cuts them.

    Args:
        labels: each pixel's segment (``>= 0``), ``-1`` where none.
        log_grey: ``(H, W)`` log of the linear grey image (finite where ``labels >= 0``).
        chroma: ``(H, W, 2)`` log R/G and log B/G.
        noise: ``(H, W)`` standard deviation of ``log_grey``'s noise (the chroma's is
            taken as ``sqrt(2)`` times it).
        surfaces: ``(H, W)`` each pixel's smooth surface: segments of different surfaces
            never join.
        max_step: largest median unexplained step of the log shading across a cut
            (the step less the mean of the steps beside it on either side).
        max_chroma: largest median step of the chromaticity across a cut (Euclidean).

    Returns:
        ``(H, W)`` labels ``0 .. n - 1`` of the joined regions, ``-1`` where ``labels`` is.
    """
    H, W = labels.shape
    keys_all, excess_all, colour_all = [], [], []
    for axis in (0, 1):  # pairs down, then right
        n = labels.shape[axis]
        if n < 2:
            continue
        take = lambda a, lo, hi: a[lo:hi] if axis == 0 else a[:, lo:hi]  # noqa: E731
        a, b = take(labels, 0, n - 1), take(labels, 1, n)
        cut = (a >= 0) & (b >= 0) & (a != b) & (take(surfaces, 0, n - 1) == take(surfaces, 1, n))
        if not cut.any():
            continue
        la, lb = take(log_grey, 0, n - 1), take(log_grey, 1, n)
        step = lb - la
        # The steps beside the cut: into a's pixel from its other side, out of b's pixel onwards,
        # each where that pixel lies in the same segment.
        before = np.full_like(step, np.nan)
        after = np.full_like(step, np.nan)
        if n >= 3:
            # side[j]: the step from pixel j to j + 1 where both lie in one segment; the cut
            # between i and i + 1 has side[i - 1] before it and side[i + 1] after it.
            side = np.where(take(labels, 0, n - 2) == take(labels, 1, n - 1),
                            take(log_grey, 1, n - 1) - take(log_grey, 0, n - 2), np.nan)
            if axis == 0:
                before[1:], after[:-2] = side, side[1:]
            else:
                before[:, 1:], after[:, :-2] = side, side[:, 1:]
        sides = np.stack([before, after])
        counted = np.isfinite(sides).sum(0)
        predicted = np.where(counted > 0, np.nansum(sides, 0) / np.maximum(counted, 1), 0.0)
        sigma = np.sqrt(take(noise, 0, n - 1) ** 2 + take(noise, 1, n) ** 2)
        excess = np.maximum(np.abs(step - predicted) - EDGE_NOISE_SIGMAS * sigma, 0.0)
        colour = np.linalg.norm(take(chroma, 1, n) - take(chroma, 0, n - 1), axis=-1)
        colour = np.maximum(colour - EDGE_NOISE_SIGMAS * np.sqrt(2.0) * sigma, 0.0)
        lo, hi = np.minimum(a, b)[cut], np.maximum(a, b)[cut]
        keys_all.append(lo.astype(np.int64) * (int(labels.max()) + 1) + hi)
        excess_all.append(excess[cut])
        colour_all.append(colour[cut])
    count = int(labels.max()) + 1 if (labels >= 0).any() else 0
    parent = np.arange(count)
    if keys_all:
        unique, rank = np.unique(np.concatenate(keys_all), return_inverse=True)
        rank = torch.from_numpy(rank.reshape(-1))
        excess, pairs = _medians(np.concatenate(excess_all), rank, len(unique))
        colour, _ = _medians(np.concatenate(colour_all), rank, len(unique))
        # Each segment's colour: the median chromaticity of its pixels (the cut's few pixels
        # can agree where the two sides' colours do not); the labels are the groups.
        inside = labels >= 0
        group = torch.from_numpy(np.ascontiguousarray(labels[inside], dtype=np.int64))
        region_hue = np.stack([_medians(chroma[..., c][inside], group, count)[0] for c in range(2)], -1)
        apart = np.linalg.norm(region_hue[unique // count] - region_hue[unique % count], axis=-1)
        joined = unique[(excess <= max_step) & (colour <= max_chroma) & (apart <= max_chroma) & (pairs >= MIN_CUT_PAIRS)]
        for key in joined.tolist():
            i, j = _find(parent, key // count), _find(parent, key % count)
            if i != j:
                parent[max(i, j)] = min(i, j)
    roots = np.array([_find(parent, i) for i in range(count)], dtype=np.int64)
    _, compact = np.unique(roots, return_inverse=True)
    return np.where(labels >= 0, compact.reshape(-1)[np.maximum(labels, 0)], -1)
