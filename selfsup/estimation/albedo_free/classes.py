"""Albedo classes: the segments of each smooth surface that share one albedo merged
(:func:`albedo_classes`), and the chosen lights refined on them (:func:`refine_on_classes`)."""

from __future__ import annotations

import torch
from torch import Tensor

from selfsup.estimation.albedo_free.fit import _log_model, _transport, refine_positions
from selfsup.estimation.albedo_free.observation import MIN_SEGMENT_PIXELS, AlbedoFreeFit, LogShading, observe
from selfsup.estimation.albedo_free.regions import group_medians
from selfsup.estimation.normals import surface_segments
from selfsup.estimation.problem import FitProblem

__all__ = ["albedo_classes", "refine_on_classes"]

# LM steps of the chosen model on its albedo classes (refine_on_classes): 8 and 15 placed our
# 384 capture frames alike, 245 and 246 successes (ad hoc, 2026-11-27, docs/decisions.md).
CLASS_ITERATIONS = 8


def albedo_classes(problem: FitProblem, labels: Tensor, position: Tensor, log_weight: Tensor,
                   level_tolerance: float = 0.1, chroma_tolerance: float = 0.06,
                   geometry: Tensor | None = None) -> Tensor:
    """The albedo segments ``labels (B, H, W)`` of each smooth surface merged into classes of
    one albedo ``(B, H, W)`` (-1: none), however far apart their segments lie.

    A segment is a patch of one albedo, but a surface holds many patches of the same one
    (a checker's cells, a floor cut by a shadow or an object's outline), and each patch's
    free offset throws away how bright it is beside the others: the falloff across the
    room, which is what places a light under indirect light (one patch alone sees its
    shading flattened by the bounce and puts the light too far). Segments of one surface
    (:func:`selfsup.estimation.normals.surface_segments`) join a class when their colour
    (the median log R/G and B/G of their pixels: the albedo's hue, which shading by white
    light does not change) lies within ``chroma_tolerance`` of the class's first (largest)
    segment and their level under the model of lights ``position (B, L, 3)`` and log weights
    ``log_weight (B, L + 1)`` (as :class:`AlbedoFreeFit`'s; the median log ratio of the observed
    shading to the model's: the albedo, up to the model's error) within ``level_tolerance``. Clipped
    pixels and pixels without light are not read. Segments with fewer than
    :data:`MIN_SEGMENT_PIXELS` readable pixels stay as they are."""
    g = problem.gbuffer
    B, H, W = g.mask.shape
    if geometry is None:
        geometry = surface_segments(g.points, g.normals, g.mask)
    obs = observe(problem, labels=labels)
    log_model, _ = _log_model(_transport(obs, position), log_weight)
    image = problem.image.detach().double().flatten(2)  # (B, 3, H W)
    peak = image.amax((1, 2), keepdim=True)
    readable = (obs.pairs & (image > 0).all(1) & (image < 0.98 * peak).all(1)).cpu()
    tiny = torch.finfo(image.dtype).tiny
    # Per pixel (B, 3, H W): the level under the model, then the hue (log R/G, log B/G).
    values = torch.cat([(obs.log_shading - log_model).flatten(1).detach().double()[:, None],
                        (image[:, [0, 2]].clamp_min(tiny) / image[:, 1:2].clamp_min(tiny)).log()], 1).cpu()
    geometry, cells = geometry.flatten(1).cpu(), labels.flatten(1).cpu()
    out = torch.full((B, H * W), -1, dtype=torch.long)
    for b in range(B):
        cell = cells[b]
        if not bool((cell >= 0).any()):
            continue  # no segment: nothing to merge (-1 everywhere)
        at = (readable[b] & (cell >= 0)).nonzero()[:, 0]
        count = int(cell.max()) + 1
        stats, sizes = zip(*(group_medians(v[at], cell[at], count, upper=True) for v in values[b]))
        first = torch.full((count,), H * W, dtype=torch.long).scatter_reduce_(0, cell[at], at, "amin")
        ids = (sizes[0] > 0).nonzero()[:, 0]  # the segments with readable pixels, in id order
        surface = geometry[b, first[ids]]  # a segment lies on one surface (the segmentation cuts at them)
        rows = zip(sizes[0][ids].tolist(), ids.tolist(), surface.tolist(), *(x[ids].tolist() for x in stats))
        segments = sorted((r for r in rows if r[0] >= MIN_SEGMENT_PIXELS), key=lambda r: -r[0])  # largest first
        classes, class_of = [], torch.arange(count) + len(segments)
        for _, i, on, lv, c0, c1 in segments:
            for k, (s2, l2, d0, d1) in enumerate(classes):
                if (s2 == on and abs(l2 - lv) < level_tolerance and abs(d0 - c0) < chroma_tolerance
                        and abs(d1 - c1) < chroma_tolerance):
                    class_of[i] = k
                    break
            else:
                class_of[i] = len(classes)
                classes.append((on, lv, c0, c1))
        merged = torch.where(cell >= 0, class_of[cell.clamp_min(0)], -1)
        _, compact = torch.unique(merged, return_inverse=True)
        out[b] = torch.where(merged >= 0, compact - int(bool((merged < 0).any())), -1)
    return out.to(labels.device).view(B, H, W)


def refine_on_classes(problem: FitProblem, labels: Tensor, fit: AlbedoFreeFit, robust_scale: float = 0.02,
                      rounds: int = 1, iterations: int = CLASS_ITERATIONS, level_tolerance: float = 0.1,
                      chroma_tolerance: float = 0.06, geometry: Tensor | None = None
                      ) -> tuple[AlbedoFreeFit, LogShading]:
    """``fit``'s lights refined (``iterations`` LM steps) on its segments ``labels (B, H, W)``
    merged into :func:`albedo_classes`, ``rounds`` (>= 1) times (the classes found again
    under the refined model each time); ``geometry``: the smooth surfaces when found
    already. Returns the fit and the observation on the last classes."""
    if rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    if geometry is None:
        g = problem.gbuffer
        geometry = surface_segments(g.points, g.normals, g.mask)
    for _ in range(rounds):
        classes = albedo_classes(problem, labels, fit.position, fit.log_weight, level_tolerance, chroma_tolerance,
                                 geometry)
        observed = observe(problem, robust_scale, labels=classes)
        fit = refine_positions(observed, fit.position, fit.log_weight, iterations, log_bounce=fit.log_bounce)
    return fit, observed
