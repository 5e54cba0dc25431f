"""Where the albedo-free lights start: grid searches of one light more than a fit
(:func:`search`), pairs found together (:func:`anchor_pairs`), a light split in two
(:func:`split_starts`) and each light searched again with the others held
(:func:`search_each`)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from selfsup.estimation.albedo_free.fit import (FINAL_TOLERANCE, _floored_log, _residual, _transport, refine_positions,
                                                shading_loss)
from selfsup.estimation.albedo_free.observation import AlbedoFreeFit, LogShading, _tiled, albedo_segments, observe
from selfsup.estimation.problem import FitProblem, centre_and_size, subsample
from selfsup.estimation.solvers import grid_candidates, spread_best

__all__ = ["search", "search_each", "split_starts", "anchor_pairs", "refine_from"]

# Contrasts tried in the grid search: the ambient at exp(g) x the median unit-light shading.
AMBIENT_STEPS = (-4.0, -2.0, -1.0, 0.0, 1.0)
# A second light's intensity tried at these ratios to the first's.
RATIO_STEPS = (0.1, 0.3, 1.0, 3.0)
# Split starts: a light of the fit before is replaced by two, this share of the scene size
# either side of it along each axis, each with half its intensity. Where two lights lie a
# scene's third apart, the one-light fit lands between them and a grid search with it held
# there finds no second light that lowers the loss much; split, they move apart
# (ad hoc, docs/decisions.md 2026-11-26; the whole effect: `python -m benchmarks.captures run`).
SPLIT_STEP = 0.15
# Each light searched again with the others held (:func:`search_each`): fewer starts and
# LM steps than the first search (the others are right by then). Ad hoc, 2026-11-26, with
# the segments' means: on the 18 devset captures it reached the losses of four starts of 15
# steps within 1%, at 0.15 s a frame against 0.22 (8 Mitsuba captures, 2-core CPU).
EACH_STARTS = 2
EACH_ITERATIONS = (10, 10)
# The second light's search also starts from pairs found together (:func:`anchor_pairs`):
# each anchor of this grid held as one light, each candidate of PAIR_GRID tried as the
# other at these intensity ratios, ANCHOR_STARTS best pairs kept. Ad hoc (docs/decisions.md,
# 2026-11-27), 306 capture frames: devset direct 031 finds its two lights 0.42 of the
# scene apart, which a one-light fit 0.33-0.37 from both hid, and two procedural frames
# theirs; a 7x7x7 pair grid with four ratios gave the same at twice the cost, one ratio
# or two starts lost frames.
ANCHOR_GRID = (3, 3, 3)
PAIR_GRID = (5, 5, 5)
PAIR_RATIOS = (0.3, 1.0, 3.0)
ANCHOR_STARTS = 4
PAIR_PIXELS = 1200  # the pairs are ranked on about this many pixels (a 160x120 image's every 4th)
# One light more searched beside a network's settled lights (``cnn+refine``'s sure images): the
# network's pair and the split starts are its best starts, so a coarser grid, two starts, fewer LM
# steps and no anchor pairs. Ad hoc, 2026-12-07, 234 capture frames (Mitsuba and procedural, one
# thread): beside the same first light as the full search, the same one-light successes (113),
# two-light rooms placed 45 against 43 and counted 57 against 58, at 0.64-0.98 s a frame against
# 0.93-1.23 (docs/decisions.md; benchmarks/results/cnn_start_settled_cpu2_2026-12-07.md).
LEAN_SEARCH = dict(per_axis=(5, 5, 5), starts=2, iterations=(10, 5), anchors=False)
# Where a search has more starts than its ``starts`` (the second light's: grid, split and
# anchor-pair starts), every start runs this many LM steps at ``start_stride`` and the best
# ``starts`` of them the rest. Ad hoc, 2026-11-27: 0.05-0.1 s a frame less on 2 cores; on 306
# capture frames one borderline frame lost (devset gi 031, 0.040 -> 0.053 of the scene), 5 steps the same.
PRUNE_ITERATIONS = 3


def _grid_losses(obs: LogShading, fixed: AlbedoFreeFit | None, cands: Tensor) -> tuple[Tensor, Tensor]:
    """Loss ``(B, G)`` of each grid candidate ``(B, G, 3)`` as the searched light, at its
    best contrast step, and that step's log weights ``(B, G, L + 1)``. The candidates are
    one image's lights side by side (no image repeated per candidate), the held lights'
    shading summed once for all of them."""
    B, G, _ = cands.shape
    diffuse = _transport(obs, cands)  # (B, G, H, W)

    def loss_of(shading: Tensor) -> Tensor:
        # (B, G, H, W) shadings -> (B, G) losses, with the segments' means (ranking only).
        return shading_loss(obs, _residual(obs, _floored_log(shading)[0], robust=False))

    if fixed is None:
        unit = torch.where(obs.gbuffer.mask[:, None], diffuse, torch.full_like(diffuse, float("nan")))
        base = torch.nan_to_num(unit.flatten(2).nanmedian(2).values, nan=1.0).clamp_min(1e-30).log()  # (B, G)
        steps = [torch.stack([base + g, torch.zeros_like(base)], -1) for g in AMBIENT_STEPS]
        losses = [loss_of(u[..., :1, None].exp() + u[..., 1:, None].exp() * diffuse) for u in steps]
    else:
        w = fixed.log_weight.exp()
        held = (w[:, 1:, None, None] * _transport(obs, fixed.position)).sum(1)  # (B, H, W)
        steps, losses = [], []
        for r in RATIO_STEPS:
            u = torch.cat([fixed.log_weight, torch.full_like(fixed.log_weight[:, :1], math.log(r))], 1)
            steps.append(u[:, None].expand(B, G, -1))
            losses.append(loss_of(w[:, :1, None, None] + (held[:, None] + u[:, -1:, None, None].exp() * diffuse)))
    losses, weights = torch.stack(losses, -1), torch.stack(steps, -2)  # (B, G, K), (B, G, K, L + 1)
    best = losses.argmin(-1, keepdim=True)
    return losses.gather(-1, best)[..., 0], weights.gather(-2, best[..., None].expand(B, G, 1, weights.shape[-1]))[..., 0, :]


def search(problem: FitProblem, n_lights: int = 1, fixed: AlbedoFreeFit | None = None, robust_scale: float = 0.02,
           per_axis: tuple[int, int, int] = (7, 7, 7), starts: int = 4, rank_stride: int = 4, start_stride: int = 2,
           iterations: tuple[int, int] = (15, 15), residuals: str = "segments",
           segment_scale: float = 50.0, labels: Tensor | None = None, split: bool = True, anchors: bool = True,
           extra_starts: Tensor | None = None) -> AlbedoFreeFit:
    """Fit ``n_lights`` lights to the log shading of ``problem``, every image at once.

    The last light is searched, the others (``fixed``, the fit of ``n_lights - 1``)
    start where they are: every grid candidate (:func:`selfsup.estimation.solvers.grid_candidates`)
    with a few contrast steps is scored at every ``rank_stride``-th pixel, the
    ``starts`` best well-spread ones (with ``split``, also :func:`split_starts` of
    ``fixed``) run ``iterations[0]`` LM steps at
    ``start_stride``, and the best of those ``iterations[1]`` at full resolution (with
    ``split`` and ``anchors``, the second light's search of segments also starts from
    :func:`anchor_pairs`, both lights moved; with more starts than ``starts``, each runs
    :data:`PRUNE_ITERATIONS` steps first and the best ``starts`` go on);
    ``residuals``, ``segment_scale``, ``labels``: as :func:`observe` (the segments are
    found once, at full resolution). ``extra_starts (B, E, n_lights, 3)``: starts in place of
    the grid's last ``E`` (a network's lights), each at the grid's contrast of its first light
    (the held lights' weights and a third for the last, with ``fixed``).
    """
    B = problem.batch
    if (fixed is None) != (n_lights == 1) or (fixed is not None and fixed.position.shape[1] != n_lights - 1):
        raise ValueError(f"searching light {n_lights} needs the fit of the {n_lights - 1} before it")
    if residuals == "segments" and labels is None:
        labels = albedo_segments(problem, segment_scale)
    at = (lambda s: None) if labels is None else (lambda s: labels[:, ::s, ::s])  # noqa: E731  a subsample's labels
    coarsest = subsample(problem, rank_stride)
    ranked = observe(coarsest, robust_scale, residuals=residuals, labels=at(rank_stride))
    cands = grid_candidates(coarsest, per_axis)
    with torch.no_grad():
        losses, weights = _grid_losses(ranked, fixed, cands)
    size = centre_and_size(problem)[1]
    # A network's starts take the places of the grid's last ones: the search costs what it did.
    grid_starts = max(1, starts - (0 if extra_starts is None else extra_starts.shape[1]))
    index, _ = spread_best(cands, losses, size, grid_starts, 0.15)  # (B, S)
    rows = torch.arange(B, device=index.device)[:, None]
    base = cands.new_zeros(B, 0, 3) if fixed is None else fixed.position
    position = torch.cat([base[:, None].expand(B, index.shape[1], -1, -1), cands[rows, index][:, :, None]], 2)
    log_weight = weights[rows, index]
    if fixed is not None and split:
        more_position, more_weight = split_starts(fixed, size)
        position, log_weight = torch.cat([position, more_position], 1), torch.cat([log_weight, more_weight], 1)
    if fixed is not None and split and anchors and fixed.position.shape[1] == 1 and residuals == "segments":
        # Ranked on about PAIR_PIXELS pixels, whatever the image's size.
        stride = rank_stride * max(1, round(math.sqrt(ranked.pairs.shape[1] / PAIR_PIXELS)))
        paired, seen = coarsest, ranked
        if stride != rank_stride:
            paired = subsample(problem, stride)
            seen = observe(paired, robust_scale, residuals=residuals, labels=at(stride))
        with torch.no_grad():
            pair_position, pair_weight = anchor_pairs(seen, paired, size, ANCHOR_STARTS)
        position, log_weight = torch.cat([position, pair_position], 1), torch.cat([log_weight, pair_weight], 1)
    if extra_starts is not None:
        if extra_starts.shape[0] != B or extra_starts.shape[2] != n_lights:
            raise ValueError(f"extra_starts must be (B={B}, E, {n_lights}, 3), got {tuple(extra_starts.shape)}")
        E = extra_starts.shape[1]
        if fixed is None:
            with torch.no_grad():
                _, extra_weight = _grid_losses(ranked, None, extra_starts[:, :, 0].to(cands))
        else:
            extra_weight = torch.cat([fixed.log_weight, torch.full_like(fixed.log_weight[:, :1], math.log(1 / 3))], 1)
            extra_weight = extra_weight[:, None].expand(B, E, -1)
        position = torch.cat([position, extra_starts.to(position)], 1)
        log_weight = torch.cat([log_weight, extra_weight.to(log_weight)], 1)
    S = position.shape[1]
    started = observe(subsample(problem, start_stride), robust_scale, residuals=residuals, labels=at(start_stride))
    if S > starts and iterations[0] > PRUNE_ITERATIONS:
        # Every start a few steps, then the best ``starts`` of them the rest of the way.
        fit = refine_positions(_tiled(started, S), position.flatten(0, 1), log_weight.flatten(0, 1), PRUNE_ITERATIONS)
        keep = fit.loss.reshape(B, S).topk(starts, dim=1, largest=False).indices  # (B, starts)
        rows = (torch.arange(B, device=keep.device)[:, None] * S + keep).flatten()
        position, log_weight = fit.position[rows].view(B, starts, -1, 3), fit.log_weight[rows].view(B, starts, -1)
        S, remaining = starts, iterations[0] - PRUNE_ITERATIONS
    else:
        remaining = iterations[0]
    fit = refine_positions(_tiled(started, S), position.flatten(0, 1), log_weight.flatten(0, 1), remaining)
    best = fit.loss.reshape(B, S).argmin(1)
    pick = torch.arange(B, device=best.device) * S + best
    full = observe(problem, robust_scale, residuals=residuals, labels=at(1))
    return refine_positions(full, fit.position[pick], fit.log_weight[pick], iterations[1], FINAL_TOLERANCE)


def anchor_pairs(ranked: LogShading, coarse: FitProblem, size: Tensor, count: int) -> tuple[Tensor, Tensor]:
    """Starts for two lights found together: every anchor of :data:`ANCHOR_GRID` held as
    the first light (at its ambient contrast alone), every candidate of :data:`PAIR_GRID`
    tried as the second at each of :data:`PAIR_RATIOS`, all ranked like :func:`_grid_losses`
    (the segments' mean view); the ``count`` best pairs, well spread. Where neither light
    lies near where one light alone fits best, holding that one fit finds no second light
    (devset capture direct 031: lights 0.42 of the scene apart, the one-light fit 0.33-0.37
    from both). Returns positions ``(B, count, 2, 3)`` and log weights ``(B, count, 3)``."""
    anchors = grid_candidates(coarse, ANCHOR_GRID)  # (B, K, 3)
    cands = grid_candidates(coarse, PAIR_GRID)  # (B, G, 3)
    (B, K, _), G = anchors.shape, cands.shape[1]
    _, alone = _grid_losses(ranked, None, anchors)  # (B, K, 2): each anchor's ambient contrast alone
    anchor_shading = alone[..., :1].exp() + _transport(ranked, anchors).flatten(2)  # (B, K, P)
    candidate = _transport(ranked, cands).flatten(2)  # (B, G, P)
    ratios = torch.tensor(PAIR_RATIOS, dtype=candidate.dtype, device=candidate.device)
    H, W = ranked.log_shading.shape[-2:]
    c2 = (ranked.scale**2)[:, None, None]
    losses = []
    for k in range(K):  # the view _residual(robust=False) takes, every candidate and ratio at once
        log_model = torch.log(anchor_shading[:, k, None, None] + ratios[:, None] * candidate[:, :, None])  # (B, G, R, P)
        residual = ranked.observed[:, None] - ranked.differences(log_model.view(B, -1, H, W))  # (B, G R, P)
        losses.append((c2 * torch.log1p(residual.square_() / c2)).sum(-1))  # (B, G R)
    losses = torch.stack(losses, 1).view(B, K, G, len(PAIR_RATIOS))
    loss, step = losses.min(-1)  # (B, K, G)
    pairs = torch.cat([anchors[:, :, None].expand(B, K, G, 3), cands[:, None].expand(B, K, G, 3)], -1)
    index, _ = spread_best(pairs.reshape(B, K * G, 6), loss.reshape(B, K * G), size, count, 0.15)
    rows = torch.arange(B, device=index.device)[:, None]
    step = step.reshape(B, K * G)[rows, index]
    log_weight = torch.stack([alone[..., 0][rows, index // G], torch.zeros_like(ratios[step]), ratios.log()[step]], -1)
    return pairs.reshape(B, K * G, 2, 3)[rows, index], log_weight


def split_starts(fixed: AlbedoFreeFit, size: Tensor, step: float = SPLIT_STEP) -> tuple[Tensor, Tensor]:
    """Starts for one light more than ``fixed`` (``L - 1`` lights): each of its lights
    split in two, ``step x size (B,)`` either side of where it was along each axis, each
    half as bright (a split along ``-x`` is the one along ``x``, its halves swapped).
    Returns positions ``(B, 3 (L - 1), L, 3)`` (the new light last) and log weights
    ``(B, 3 (L - 1), L + 1)``."""
    B, M, _ = fixed.position.shape
    offsets = torch.eye(3, dtype=fixed.position.dtype, device=fixed.position.device)[None] * (step * size)[:, None, None]
    positions, weights = [], []
    for j in range(M):
        moved = fixed.position[:, None].repeat(1, 3, 1, 1)  # (B, 3, M, 3)
        moved[:, :, j] += offsets
        other = fixed.position[:, None, j] - offsets  # (B, 3, 3)
        positions.append(torch.cat([moved, other[:, :, None]], 2))
        u = fixed.log_weight.clone()  # (B, M + 1): ambient, then each light; the first light's is 0
        if j == 0:  # halving the gauge light: everything else doubles relative to it
            u[:, [0] + list(range(2, M + 1))] += math.log(2.0)
            new = torch.zeros_like(u[:, :1])
        else:
            u[:, j + 1] -= math.log(2.0)
            new = u[:, j + 1 : j + 2]
        weights.append(torch.cat([u, new], 1)[:, None].expand(B, 3, M + 2))
    return torch.cat(positions, 1), torch.cat(weights, 1)


def search_each(problem: FitProblem, fit: AlbedoFreeFit, robust_scale: float = 0.02, residuals: str = "segments",
                segment_scale: float = 50.0, labels: Tensor | None = None, per_axis: tuple[int, int, int] = (7, 7, 7),
                starts: int = EACH_STARTS, iterations: tuple[int, int] = EACH_ITERATIONS) -> AlbedoFreeFit:
    """Each light of ``fit`` (two or more) but its last searched again with the others held
    where they are (:func:`search`), one after the other, each image keeping whichever fit
    has the lower loss (the light in its place). A light searched while a wrong one was held
    (the first of two, fitted alone, between the two) can then be searched again once the
    other is right. The last light (the newest) was searched with the others held already:
    searching it again (in the pairs of 258 capture frames) changed no count or success and
    moved no light by more than 0.001 of the scene, at 0.11 of a frame's time (ad hoc, 2026-12-06:
    benchmarks/results/lm_tolerance_cpu2_2026-12-06.md).
    ``per_axis``, ``starts``, ``iterations``: as :func:`search`, the others as :func:`observe`."""
    if residuals == "segments" and labels is None:
        labels = albedo_segments(problem, segment_scale)
    for light in range(fit.position.shape[1] - 1):
        again = search(problem, fit.position.shape[1], fixed=fit.without(light), robust_scale=robust_scale,
                       residuals=residuals, segment_scale=segment_scale, labels=labels, split=False, per_axis=per_axis,
                       starts=starts, iterations=iterations)
        fit = fit.better(again.with_last_at(light))
    return fit


def refine_from(problem: FitProblem, position: Tensor, robust_scale: float = 0.02, residuals: str = "segments",
                segment_scale: float = 50.0, labels: Tensor | None = None, iterations: tuple[int, int] = (15, 15),
                start_stride: int = 2) -> AlbedoFreeFit:
    """The lights at ``position (B, n, 3)`` (a network's) refined as :func:`search` refines its
    best start, with no grid: ``iterations[0]`` LM steps at ``start_stride``, then
    ``iterations[1]`` at full resolution; the first light's contrast the grid's best ambient
    step for it, each other light at a third of the first's intensity."""
    if residuals == "segments" and labels is None:
        labels = albedo_segments(problem, segment_scale)
    at = (lambda s: None) if labels is None else (lambda s: labels[:, ::s, ::s])  # noqa: E731  a subsample's labels
    started = observe(subsample(problem, start_stride), robust_scale, residuals=residuals, labels=at(start_stride))
    with torch.no_grad():
        _, first = _grid_losses(started, None, position[:, :1])  # (B, 1, 2): the ambient's and the light's
    others = torch.full_like(position[:, 1:, 0], math.log(1 / 3))
    log_weight = torch.cat([first[:, 0], others], 1)
    fit = refine_positions(started, position, log_weight, iterations[0])
    full = observe(problem, robust_scale, residuals=residuals, labels=at(1))
    return refine_positions(full, fit.position, fit.log_weight, iterations[1], FINAL_TOLERANCE)
