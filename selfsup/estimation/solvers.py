"""Solvers of the light positions: Levenberg-Marquardt, Adam, the paper's gradient descent, and the grid search.

- ``lm``: damped Gauss-Newton on the positions (the step of the variable-projection
  problem, :mod:`selfsup.estimation.problem`). The Jacobian of the image with respect
  to the positions is exact for the shading and a forward difference for cast shadows
  (:func:`render.light_transport_jacobian`); each light's maps depend on its own
  position only, so the shadow differences take 3 sweeps whatever ``L``.
- ``adam`` / ``gd``: first-order steps on the same projected objective, its gradient
  by autograd through the renderer (shadows included); ``gd`` is the paper's (rate
  0.02 in scene-scale units, stop at relative energy change 1e-4).
- :func:`search`: a grid of candidate positions ranked at a coarse stride, the best
  spread apart refined.

Every image of the batch stops on its own. Positions move in units of the scene
size, so nothing assumes an absolute scale.
"""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

from render import light_transport_jacobian
from selfsup.linear import intensity_design
from selfsup.estimation.options import RefineOptions
from selfsup.estimation.problem import (Fit, FitProblem, basis_columns, cauchy_scale, centre_and_size, irls_weights,
                                        robust_loss, solve_at, solve_linear, subsample, transport_maps)

__all__ = ["refine", "search", "grid_candidates", "spread_best", "jacobians", "normal_equations", "RUNAWAY_SIZES"]


RUNAWAY_SIZES = 10.0  # the LM stops an image whose light is this many scene sizes from the centre


def jacobians(problem: FitProblem, position: Tensor, intensity: Tensor, h: Tensor, specular: bool
               ) -> tuple[Tensor, Tensor, Tensor]:
    """The basis images ``(B, 3, L, H, W)`` at ``position (B, L, 3)``, the Jacobian
    ``(B, 3L, 3*H*W)`` of the model image with respect to the positions, at ``intensity``,
    and the lights' diffuse transport ``(B, L, H, W)`` the basis images were made of.

    Shading is differentiated exactly, cast shadows by forward differences of step
    ``h (B, 1, 1)`` (:func:`render.light_transport_jacobian`).
    """
    B, L, _ = position.shape
    jac = light_transport_jacobian(problem.gbuffer, problem.material, position, h.reshape(B), falloff=problem.falloff,
                                   shadows=problem.shadows, shadow_options=problem.shadow_options,
                                   specular=specular)
    t = jac.transport
    cols = basis_columns(problem, t.diffuse, t.specular)
    # d model_c / d p_ij = I_ic (kd_c dD_i/dp_j + ks_c dS_i/dp_j): (B, L, 3 coords, 3 channels, H, W)
    kd = problem.material.kd.permute(0, 3, 1, 2)[:, None, None]  # (B, 1, 1, 3, H, W)
    deriv = kd * jac.diffuse.permute(0, 1, 4, 2, 3)[:, :, :, None]
    if jac.specular is not None:
        ks = problem.material.ks.permute(0, 3, 1, 2)[:, None, None]
        deriv = deriv + ks * jac.specular.permute(0, 1, 4, 2, 3)[:, :, :, None]
    deriv = deriv * intensity[:, :, None, :, None, None]
    return cols, deriv.reshape(B, 3 * L, -1), t.diffuse


def normal_equations(problem: FitProblem, j_pos: Tensor, cols: Tensor, weights: Tensor,
                      residual: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
    """Gauss-Newton normal matrix ``J^T W J (B, P + 3k, P + 3k)`` and, given ``residual``
    ``(B, 3, H, W)``, gradient ``J^T W r (B, P + 3k)`` of the model image over every
    parameter: the positions (``j_pos (B, P = 3L, 3*H*W)`` from :func:`jacobians`) first,
    then the linear ones channel by channel, each light's intensity and, when unknown,
    the ambient (``k = L [+ 1]``; the image is linear in them: their columns are the basis
    images ``cols (B, 3, L, H, W)`` and ``kd``). ``weights (B, 3, H, W)``.

    A linear parameter of channel ``c`` touches channel ``c``'s pixels alone, so the
    blocks are products over one channel each: the dense Jacobian over all parameters
    would be two thirds zeros, and forming and multiplying it took 2.6x as long at
    160x120 (2 lights, 6 images, one CPU thread; measured 2026-11-23). The tests build
    that dense Jacobian and compare.
    """
    B, P, _ = j_pos.shape
    design = intensity_design(cols, problem.material.kd, problem.ambient)  # (B, 3, k, N)
    k, N = design.shape[2], design.shape[3]
    by_channel = j_pos.view(B, P, 3, N)
    j_w = (by_channel * weights.reshape(B, 1, 3, N)).view(B, P, 3 * N)
    a_w = design * weights.reshape(B, 3, 1, N)
    # Channel by channel as (B, P, N) x (B, N, k) products of strided views: a product over
    # the channels as a batch axis would copy the positions' Jacobian first.
    cross = torch.stack([by_channel[:, :, c] @ a_w[:, c].transpose(1, 2) for c in range(3)], 2).view(B, P, 3 * k)
    eye = torch.eye(3, dtype=j_pos.dtype, device=j_pos.device)
    linear = ((a_w @ design.transpose(-1, -2))[:, :, :, None, :] * eye[:, None, :, None]).reshape(B, 3 * k, 3 * k)
    normal = torch.cat([torch.cat([j_w @ j_pos.transpose(1, 2), cross], 2), torch.cat([cross.transpose(1, 2), linear], 2)], 1)
    if residual is None:
        return normal, None
    # As rows times matrices: BLAS runs that faster than matrices times columns.
    gradient = torch.cat([(residual.reshape(B, 1, 3 * N) @ j_w.transpose(1, 2)).view(B, P),
                          (residual.reshape(B, 3, 1, N) @ a_w.transpose(-1, -2)).view(B, 3 * k)], 1)
    return normal, gradient


def _lm(problem: FitProblem, position: Tensor, options: RefineOptions, max_iters: int) -> tuple[Tensor, Tensor]:
    # Damped Gauss-Newton over positions, intensities and (unknown) ambient together,
    # of which only the position step is kept (the linear ones are re-solved exactly at
    # the trial): the step of the variable-projection problem. A step over positions
    # alone, intensities held, ignores that the re-solve absorbs what a move does to
    # brightness (inverse-square distance against intensity) and crept in tiny steps.
    B, L, _ = position.shape
    centre, size = centre_and_size(problem)
    h = (options.fd_step * size)[:, None, None]  # (B, 1, 1)
    damping = torch.full((B,), 1e-3, dtype=position.dtype, device=position.device)
    active = torch.ones(B, dtype=torch.bool, device=position.device)
    iterations = torch.zeros(B, dtype=torch.long, device=position.device)
    sub, selected = problem, B  # the active images' problem
    scale = cauchy_scale(problem, options)
    # One reweighting pass only: weights converged at a wrong start would silence the
    # very residuals that say where the light should move.
    cost, intensity, ambient, model, weights, _, _ = solve_at(problem, position, options, passes=1)
    # Each parameter's kind in the normal equations' order: positions (0), then channel by
    # channel each light's intensity (1) and the unknown ambient (2).
    k = L + (problem.ambient is None)
    linear_kind = torch.tensor([1] * L + [2] * (k - L), device=position.device).repeat(3)
    kinds = torch.cat([torch.zeros(3 * L, dtype=torch.long, device=position.device), linear_kind])
    for _ in range(max_iters):
        idx = active.nonzero(as_tuple=True)[0]
        if idx.numel() == 0:
            break
        n = idx.numel()
        if n != selected:  # the active set only shrinks: select again only when it did
            sub, selected = problem.select(idx), n
        pos, w = position[idx], weights[idx]
        cols_base, j_pos, _ = jacobians(sub, pos, intensity[idx], h[idx], options.specular)
        jtj, jtr = normal_equations(sub, j_pos, cols_base, w, model[idx] - sub.image)
        diag = jtj.diagonal(dim1=-2, dim2=-1)
        # A light that lights nothing has zero columns: a floor of 1e-6 of the largest
        # curvature of its kind keeps the damped system positive definite (it then stays
        # put). Of its kind: positions, intensities and the ambient have curvatures in
        # units of their own (an intensity's goes as distance^-4), and one floor for all
        # lifted the intensities' in a file in millimetres, which moved its answer.
        peak = torch.stack([(diag * (kinds == kind)).amax(-1) for kind in range(3)], -1)[:, kinds]
        diag = torch.where(peak > 0, diag.clamp_min(1e-6 * peak), torch.ones_like(diag))
        damped = torch.zeros_like(diag)
        damped[:, : 3 * L] = diag[:, : 3 * L]  # damp the position block only: the linear block is exact
        system = jtj + damping[idx, None, None] * torch.diag_embed(damped) + torch.diag_embed(1e-9 * diag)
        # solve_ex never raises: a singular or non-finite system gives a step that is rejected below.
        step = -torch.linalg.solve_ex(system, jtr[..., None])[0].squeeze(-1)
        # A failed solve (non-finite step) counts as a rejected step: more damping next time.
        finite = torch.isfinite(step).all(-1)
        step = torch.where(finite[:, None], step, torch.zeros_like(step))[:, : 3 * L]
        trial = pos + step.reshape(n, L, 3)
        t_cost, t_int, t_amb, t_model, _, _, _ = solve_at(sub, trial, options, weights=w)
        better = (t_cost < cost[idx]) & finite
        rel = (cost[idx] - t_cost) / cost[idx].clamp_min(1e-30)
        # Accepted steps replace the state, rejected ones leave it: selects, not boolean
        # indexing, so nothing here waits for the device.
        pick = better[:, None, None]
        position[idx] = torch.where(pick, trial, pos)
        intensity[idx] = torch.where(pick, t_int, intensity[idx])
        ambient[idx] = torch.where(better[:, None], t_amb, ambient[idx])
        model[idx] = torch.where(pick[..., None], t_model, model[idx])
        cost[idx] = torch.where(better, t_cost, cost[idx])
        damping[idx] = torch.where(better, damping[idx] * 0.3, damping[idx] * 10).clamp(1e-9, 1e9)
        iterations[idx] += 1
        moved = step.reshape(n, L, 3).norm(dim=-1).amax(-1) / size[idx]
        # A light that ran off beyond RUNAWAY_SIZES scene sizes is fitting a direction, not
        # a point: its cost creeps down for ever; it stops there (and loses to the others).
        away = (position[idx] - centre[idx, None]).norm(dim=-1).amax(-1) / size[idx] > RUNAWAY_SIZES
        done = (better & ((rel < options.tol) | (moved < options.step_tol) | away)) | (damping[idx] >= 1e9)
        active[idx] = active[idx] & ~done
        # Re-weight (IRLS) the images that moved.
        if options.robust:
            residual = model[idx] - sub.image
            new_w = irls_weights(sub, residual, options, scale[idx])
            weights[idx] = torch.where(pick[..., None], new_w, w)
            cost[idx] = torch.where(better, (new_w * residual**2).flatten(1).sum(1), cost[idx])
    return position, iterations


def _first_order(problem: FitProblem, position: Tensor, options: RefineOptions, max_iters: int) -> tuple[Tensor, Tensor]:
    B = position.shape[0]
    centre, size = centre_and_size(problem)
    unit = ((position - centre[:, None]) / size[:, None, None]).detach().requires_grad_(True)
    tol = 1e-4 if options.method == "gd" else options.tol
    optimiser = (torch.optim.SGD([unit], lr=options.learning_rate) if options.method == "gd"
                 else torch.optim.Adam([unit], lr=options.learning_rate))
    _, _, _, _, weights, _, _ = solve_at(problem, position.detach(), options, passes=1)  # as in _lm
    norm = (weights * problem.image**2).flatten(1).sum(1).clamp_min(1e-30)
    previous = torch.full((B,), float("inf"), dtype=position.dtype, device=position.device)
    active = torch.ones(B, dtype=torch.bool, device=position.device)
    iterations = torch.zeros(B, dtype=torch.long, device=position.device)
    for _ in range(max_iters):
        if not active.any():
            break
        optimiser.zero_grad()
        diffuse, specular = transport_maps(problem, centre[:, None] + unit * size[:, None, None], options.specular)
        _, _, model = solve_linear(problem, diffuse, specular, weights)
        energy = (weights * (model - problem.image) ** 2).flatten(1).sum(1) / norm
        (energy * active).sum().backward()
        unit.grad[~active] = 0
        before = unit.detach().clone()
        optimiser.step()
        iterations += active
        with torch.no_grad():
            # A non-finite gradient or step stops that image where it was, never at NaN.
            broken = ~torch.isfinite(unit).all(-1).all(-1) | ~torch.isfinite(energy)
            unit[broken] = before[broken]
            change = (previous - energy).abs() / energy.clamp_min(1e-30)
            active &= ~(change < tol) & ~broken
            previous = energy.detach()
    return (centre[:, None] + unit.detach() * size[:, None, None]), iterations


def refine(problem: FitProblem, position: Tensor, options: RefineOptions | None = None) -> Fit:
    """Refine lights starting at ``position (B, L, 3)``; coarse to fine over ``options.strides``.

    Example:
        >>> # fit = refine(FitProblem(gbuffer, material, image), init_positions)  # doctest: +SKIP
    """
    options = options or RefineOptions()
    if position.dim() != 3 or position.shape[0] != problem.batch or position.shape[2] != 3:
        raise ValueError(f"position must have shape ({problem.batch}, L, 3), got {tuple(position.shape)}")
    if not bool(torch.isfinite(position).all()):
        raise ValueError("initial light positions hold non-finite values")
    position = position.detach().clone()
    total = torch.zeros(problem.batch, dtype=torch.long, device=position.device)
    for stride, iters in zip(options.strides, options.max_iters):
        if iters == 0:
            continue  # nothing to descend: the final evaluation below is all there is
        level = subsample(problem, stride)
        if options.method == "lm":
            position, iterations = _lm(level, position, options, iters)
        else:
            with torch.enable_grad():
                position, iterations = _first_order(level, position, options, iters)
        total += iterations
    with torch.no_grad():
        cost, intensity, ambient, model, weights, _, _ = solve_at(problem, position, options)
        rss = ((model - problem.image) ** 2 * problem.gbuffer.mask[:, None]).flatten(1).sum(1)
        n = problem.gbuffer.mask.flatten(1).sum(1) * 3
    return Fit(position, intensity, ambient, cost, model, total, rss, n)


def grid_candidates(problem: FitProblem, per_axis: tuple[int, int, int] = (5, 5, 5)) -> Tensor:
    """Candidate light positions ``(B, G, 3)`` on a grid over the valid points' box,
    grown by half its size sideways and upwards (lights hang above what a camera
    sees), and reaching towards the camera (never behind it)."""
    _, lo, hi = problem.gbuffer.extent()
    span = hi - lo
    lo = torch.stack([lo[:, 0] - 0.5 * span[:, 0], lo[:, 1] - 0.5 * span[:, 1], 0.1 * lo[:, 2]], 1)
    hi = torch.stack([hi[:, 0] + 0.5 * span[:, 0], hi[:, 1], hi[:, 2]], 1)
    axes = [torch.linspace(0, 1, n, dtype=lo.dtype, device=lo.device) for n in per_axis]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)  # (G, 3)
    return lo[:, None] + grid[None] * (hi - lo)[:, None]


def spread_best(points: Tensor, score: Tensor, size: Tensor, count: int, min_gap: float) -> tuple[Tensor, Tensor]:
    """The ``count`` best-scored of ``points (B, G, D)`` per image, each more than
    ``min_gap * size (B,)`` from those chosen before it (greedy, best first).

    Returns indices ``(B, count)`` into ``G``, the last distinct one repeated when
    fewer are that far apart, and the number of distinct ones ``(B,)``.
    """
    B, G, D = points.shape
    order = torch.nan_to_num(score, nan=math.inf).argsort(dim=1, stable=True)
    ranks = torch.arange(G, device=points.device).expand(B, G)
    rank = torch.empty_like(order).scatter_(1, order, ranks)  # each point's place in the order
    available = torch.ones(B, G, dtype=torch.bool, device=points.device)
    distinct = torch.zeros(B, dtype=torch.long, device=points.device)
    chosen: list[Tensor] = []
    for _ in range(count):
        masked = torch.where(available, rank, G)
        index = masked.argmin(1)
        found = masked.gather(1, index[:, None])[:, 0] < G
        if chosen:
            index = torch.where(found, index, chosen[-1])
        distinct += found
        chosen.append(index)
        gap = (points - points.gather(1, index[:, None, None].expand(B, 1, D))).norm(dim=-1)
        available &= gap > min_gap * size[:, None]
    return torch.stack(chosen, 1), distinct


def _stride_for(problem: FitProblem, pixels: int) -> int:
    # The subsampling stride that leaves about ``pixels`` pixels of the image (at least 1).
    H, W = problem.image.shape[-2:]
    return max(1, int(math.sqrt(H * W / pixels)))


def _tiled(problem: FitProblem, count: int) -> FitProblem:
    # Every image ``count`` times in a row: image b fills rows b*count .. (b+1)*count - 1.
    return problem.select(torch.arange(problem.batch, device=problem.image.device).repeat_interleave(count))


def _pick(positions: Tensor, index: Tensor) -> Tensor:
    # positions (B, S, L, 3) at index (B, K): (B, K, L, 3).
    return positions.gather(1, index[..., None, None].expand(-1, -1, *positions.shape[2:]))


def search(problem: FitProblem, n_lights: int, options: RefineOptions | None = None, fixed: Tensor | None = None,
           per_axis: tuple[int, int, int] = (7, 6, 7), starts: int = 8, finalists: int = 2,
           unshadowed_first: bool = True, extra_starts: Tensor | None = None, rank_pixels: int = 300,
           start_pixels: int = 1200) -> Fit:
    """Fit ``n_lights`` lights with no initial guess, every image of the batch at once.

    The last light is searched (the others, ``fixed (B, n_lights - 1, 3)``, start
    where given): every grid candidate is scored on about ``rank_pixels`` pixels by
    the robust loss with intensities solved; the ``starts`` best well-spread ones
    run a short LM on about ``start_pixels`` pixels, from where they are and
    (``unshadowed_first``) from where a shadow-free LM, whose landscape is
    smoother, took them; the ``finalists`` best of those that ended at least 2% of
    the scene size apart run ``options``' coarse-to-fine refinement; the lowest
    robust loss wins. ``extra_starts (B, S, 3)`` (e.g. a network's
    guesses for the searched light) join the grid's best as starts.

    The batch runs as one: ``B x candidates`` images per step, each stopping on its
    own, so a GPU fills up; an image's answer is the one it gets alone.
    """
    options = options or RefineOptions()
    B = problem.batch
    if fixed is None and n_lights != 1:
        raise ValueError("without fixed lights only one light is searched")
    base = problem.image.new_zeros(B, 0, 3) if fixed is None else fixed
    if base.shape != (B, n_lights - 1, 3):
        raise ValueError(f"fixed must have shape ({B}, {n_lights - 1}, 3), got {tuple(base.shape)}")
    coarse = subsample(problem, _stride_for(problem, start_pixels))
    ranked = subsample(problem, _stride_for(problem, rank_pixels))
    cands = grid_candidates(coarse, per_axis)  # (B, G, 3)
    G = cands.shape[1]
    size = centre_and_size(coarse)[1]  # (B,)
    with torch.no_grad():
        positions = torch.cat([base[:, None].expand(B, G, -1, -1), cands[:, :, None]], 2)  # (B, G, L, 3)
        tiled = _tiled(ranked, G)
        _, _, _, model, _, _, _ = solve_at(tiled, positions.flatten(0, 1), options, passes=1)  # a coarse ranking
        score = robust_loss(tiled, model, options).reshape(B, G)
    starts_at = _pick(positions, spread_best(cands, score, size, starts, 0.15)[0])  # (B, S, L, 3)
    if extra_starts is not None:
        guesses = torch.cat([base[:, None].expand(B, extra_starts.shape[1], -1, -1), extra_starts[:, :, None]], 2)
        starts_at = torch.cat([guesses, starts_at], 1)
    # The starts need their basin, not its bottom: millimetre steps end them.
    quick = dataclasses.replace(options, strides=(1,), max_iters=(12,), step_tol=max(options.step_tol, 1e-3))
    if unshadowed_first and problem.shadows != "none":
        # Shading alone gives a smoother landscape: also start from where a shadow-free descent went.
        S = starts_at.shape[1]
        smooth = refine(_tiled(coarse, S).with_shadows("none"), starts_at.flatten(0, 1), quick)
        starts_at = torch.cat([starts_at, smooth.position.reshape(B, S, n_lights, 3)], 1)
    S = starts_at.shape[1]
    tiled = _tiled(coarse, S)
    short = refine(tiled, starts_at.flatten(0, 1), quick)
    score = robust_loss(tiled, short.model, options).reshape(B, S)
    ends = short.position.reshape(B, S, n_lights, 3)
    # Starts that the short LM took to one place are one finalist, not several.
    index, distinct = spread_best(ends.flatten(2), score, size, finalists, 0.02)
    F = int(distinct.max())
    tiled = _tiled(problem, F)
    full = refine(tiled, _pick(ends, index[:, :F]).flatten(0, 1), options)
    best = robust_loss(tiled, full.model, options).reshape(B, F).argmin(1)
    rows = torch.arange(B, device=best.device) * F + best
    return Fit(*(getattr(full, f.name)[rows] for f in dataclasses.fields(Fit)))
