"""A specular lobe in the albedo-free model, chosen per image: metal and glossy paint.

The albedo-free fit explains the log shading with diffuse light. A glossy object shows its
lamp twice: the diffuse shading, and the lobe around the mirror direction. A sharp highlight
is a few pixels, and :func:`.fit.highlight_pixels` leaves them out; a rough metal (whose
diffuse light is nil) or a broad paint gloss spreads the lobe over much of the object, and the
diffuse-only fit then moves its light towards the lobe, or takes a second light beside the
first to widen the peak. Independent renders of rough gold and aluminium (Mitsuba's GGX
conductors, path traced, through a camera) took two lights in every frame, the first
up to 24.6 degrees off (``benchmarks/results/gloss_cpu2_2026-12-06.md``). A lobe and a light
beside the first explain the same peak, so by default (``tuning.albedo_free_gloss=instead``)
the lobe is tried only where the diffuse fit takes more lights, with one light, and kept where
its criterion is below theirs (not where the black pixels took the second light: a lobe casts
no shadow). That light starts at the one-light fit and at each of the more lights alone: beside
other objects a metal's one diffuse light lands between its lamp and the lobe's peak, where
one of the pair's lights is near the lamp. Rough gold and aluminium then take one light in 10 of 16
frames (``benchmarks/results/gloss_instead_cpu2_2026-12-06.md``; 14 of 16 with the lobe's shape
refined, ``benchmarks/results/gloss_beside_cpu2_2026-12-06.md``), and a frame one light
explains never takes a lobe (tried beside every first light, ``auto``, the matte DiLiGenT
bear's faint sheen took one in 24 of 24 frames and lost 0.6 degrees). Where one light and its
lobe lose, the lobe is tried beside the lights the diffuse fit took (two lamps on a glossy
object); where they win, one light more is searched beside them (a glossy room may have two
lamps), kept only where it is farther from the first than the lobe's width
(``selfsup/estimation/reflectance.py``).

With one paint over the frame (a photographed object) the lobe is one more term of the
shading, its ratio to the diffuse light (``ks / kd``) and its shininess one pair for the
frame: ``S = a + sum_i L_i (D_i + r P_i)``, ``P_i`` the Blinn-Phong lobe of light ``i``
(:func:`render.light_transport`'s specular map) on the side the light reaches. Each
segment's free albedo still divides out, since the lobe is scaled with it (a dielectric's
white lobe over a coloured paint is this to the extent that one paint's level fixes ``r``).
:func:`choose_gloss` tries a grid of both at the first light's position and keeps the lobe
where the criterion prefers it (two parameters more); every later fit of the image (with
``auto``: its second light, the verdict; its intensities) then sees it through the problem's
``gloss``.
"""

from __future__ import annotations

import itertools
import math

import torch
from torch import Tensor

from selfsup.estimation.albedo_free.fit import FINAL_TOLERANCE, refine_positions
from selfsup.estimation.albedo_free.observation import AlbedoFreeFit, observe
from selfsup.estimation.problem import FitProblem, centre_and_size, subsample

__all__ = ["choose_gloss", "fit_lobes", "keep_lobes", "GLOSS_RATIOS", "GLOSS_SHININESS", "GLOSS_PARAMETERS"]

# The grid of lobes tried (ratio of the lobe's peak to the diffuse light, Blinn-Phong
# shininess): from a paint's broad sheen to a metal whose diffuse light is nil, and from a
# rough lobe (GGX alpha 0.45) to a fairly sharp one (alpha 0.16; a sharper highlight is a few
# pixels, left out as such). Ad hoc, 2026-12-06, on the Mitsuba studio objects: rough gold
# (alpha 0.25, Blinn-Phong 30) chose (10, 10) in 8 of 8 frames on a 6 x 5 grid.
GLOSS_RATIOS = (0.3, 1.0, 3.0, 10.0, 30.0)
GLOSS_SHININESS = (4.0, 12.0, 40.0, 120.0)
GLOSS_STRIDE = 4  # the grid is tried at every fourth pixel (every second: the same lobes chosen on
# 24 Mitsuba metal frames, one frame fewer of sharp gold taking one, at 2.2 times the time)
GLOSS_ITERATIONS = (8, 12)  # LM steps of every lobe of the grid, then of the best at full resolution
GLOSS_PARAMETERS = 2  # the ratio and the shininess, counted by the criterion
# Each start's best lobe of the grid is then refined on the 8 lobes about it, each round at half
# the last step (in log; the grid's is a factor of about 3.2 in both): the grid alone is too
# coarse for a lobe between its shininesses (our renderer's rough gold-like paint, Blinn-Phong 8
# beside a box and a cylinder: two lights, 9.8 degrees off, on the grid; one and its lobe, 1.0,
# refined twice; Mitsuba's aluminium one light in 7 of 8 frames, 4 on the grid). Refined, the lobe
# also takes a pair's place in the tracking benchmark's glossy room lit by two lamps, whose dim
# second lamp does not pay beside it even started from the truth (benchmarks/results/
# gloss_beside_cpu2_2026-12-06.md).
GLOSS_REFINE_ROUNDS = 2
# A start within this share of the scene size of an earlier one is the same start (a two-light
# fit's brighter light is often where the one-light fit was): left out of the grid.
SAME_START = 0.05


def choose_gloss(problem: FitProblem, found: AlbedoFreeFit, labels: Tensor | None, robust_scale: float,
                 criterion, residuals: str = "segments", against: list[float] | None = None,
                 starts: list[AlbedoFreeFit] = (), shapes: Tensor | None = None) -> tuple[FitProblem, AlbedoFreeFit]:
    """Each image's specular lobe, or none: the best of :func:`fit_lobes` kept where its
    ``criterion(fit, extra)`` (a list per image; lower is better; :data:`GLOSS_PARAMETERS`
    more) is below the diffuse fit's (``found``'s), and below ``against`` (a criterion per
    image, e.g. of the diffuse fit with more lights) where given (:func:`keep_lobes`).
    Returns the problem with its ``gloss (B, 2)`` (a ratio of 0 where none was kept; None
    where no image kept one) and each image's fit, with or without it. The other arguments:
    as :func:`fit_lobes`."""
    gloss, fitted, values = fit_lobes(problem, found, labels, robust_scale, criterion, residuals, starts, shapes)
    return keep_lobes(problem, found, gloss, fitted, values, criterion, against)


def fit_lobes(problem: FitProblem, found: AlbedoFreeFit, labels: Tensor | None, robust_scale: float,
              criterion, residuals: str = "segments", starts: list[AlbedoFreeFit] = (),
              shapes: Tensor | None = None) -> tuple[Tensor, AlbedoFreeFit, list[float]]:
    """Each image's best specular lobe: every lobe of :data:`GLOSS_RATIOS` x
    :data:`GLOSS_SHININESS` (and of ``shapes (B, K, 2)``, ratios and shininesses of each
    image's own) refined from ``found`` (a fit of ``problem``, its lights held in number; and
    from each fit of as many lights in ``starts``, other places they may start, unless
    :data:`SAME_START` of the scene size from an earlier one in every image) at
    :data:`GLOSS_STRIDE`; each start's best lobe refined about it (:data:`GLOSS_REFINE_ROUNDS`)
    and at full resolution, and the one of lowest ``criterion(fit, extra)`` kept. Returns its
    ``gloss (B, 2)``, its fit and its criterion (a list per image). ``labels``,
    ``robust_scale``, ``residuals``: as :func:`observe`."""
    B = problem.batch
    grid = torch.tensor(list(itertools.product(GLOSS_RATIOS, GLOSS_SHININESS)), dtype=problem.image.dtype,
                        device=problem.image.device)[None].expand(B, -1, -1)  # (B, G, 2)
    shapes = grid if shapes is None else torch.cat([grid, shapes.to(grid)], 1)
    fits = [found]
    _, size = centre_and_size(problem)
    for start in starts:  # each start unless every image has it already
        apart = torch.stack([(start.position - f.position).norm(dim=-1).amax(1) for f in fits]).amin(0)
        if bool((apart > SAME_START * size).any()):
            fits.append(start)
    G = shapes.shape[1]
    S = len(fits)
    tries = S * G  # each image's grid: every lobe from every start
    rows = torch.arange(B, device=problem.image.device).repeat_interleave(tries)
    L = found.position.shape[1]
    position = torch.stack([f.position for f in fits], 1)[:, :, None].expand(-1, -1, G, -1, -1).reshape(B * tries, L, 3)
    log_weight = torch.stack([f.log_weight for f in fits], 1)[:, :, None].expand(-1, -1, G, -1).reshape(B * tries, -1)
    combos = shapes[:, None].expand(-1, S, -1, -1).reshape(B * S, G, 2)  # each start's lobes
    tiled = subsample(problem.select(rows).with_gloss(combos.reshape(-1, 2)), GLOSS_STRIDE)
    coarse_labels = None if labels is None else labels[rows][:, ::GLOSS_STRIDE, ::GLOSS_STRIDE]
    seen = observe(tiled, robust_scale, residuals=residuals, labels=coarse_labels)
    tried = refine_positions(seen, position, log_weight, GLOSS_ITERATIONS[0])
    # Each start's best lobe of the grid, refined about it and at full resolution; each image
    # keeps the start whose lobe has the lowest criterion.
    best = tried.loss.view(B * S, G).argmin(1)  # (B S,)
    pick = torch.arange(B * S, device=best.device) * G + best
    gloss = combos[torch.arange(B * S, device=best.device), best]  # (B S, 2)
    coarse = AlbedoFreeFit.rows([(tried, int(r)) for r in pick])  # the grid's best fits
    each = torch.arange(B, device=best.device).repeat_interleave(S)
    images, each_labels = problem.select(each), None if labels is None else labels[each]
    gloss, coarse = _refined_lobes(images, gloss, coarse, each_labels, robust_scale, residuals)
    full = observe(images.with_gloss(gloss), robust_scale, residuals=residuals, labels=each_labels)
    fitted = refine_positions(full, coarse.position, coarse.log_weight, GLOSS_ITERATIONS[1], FINAL_TOLERANCE)
    values = criterion(fitted, [GLOSS_PARAMETERS] * (B * S))
    kept = [b * S + min(range(S), key=lambda k: values[b * S + k]) for b in range(B)]
    return gloss[kept], AlbedoFreeFit.rows([(fitted, r) for r in kept]), [values[r] for r in kept]


def keep_lobes(problem: FitProblem, found: AlbedoFreeFit, gloss: Tensor, fitted: AlbedoFreeFit, values: list[float],
               criterion, against: list[float] | None = None) -> tuple[FitProblem, AlbedoFreeFit]:
    """Each image's lobe ``gloss (B, 2)`` and its fit (criterion ``values``, from
    :func:`fit_lobes`) kept where below ``found``'s criterion and ``against`` (where given):
    as :func:`choose_gloss` returns them."""
    plain = criterion(found)
    if against is not None:
        plain = [min(p, a) for p, a in zip(plain, against)]
    take = torch.tensor([c < p for p, c in zip(plain, values)], device=problem.image.device)
    if not bool(take.any()):
        return problem, found
    gloss = torch.where(take[:, None], gloss, torch.zeros_like(gloss))
    return problem.with_gloss(gloss), found.chosen(take, fitted)


def _refined_lobes(problem: FitProblem, gloss: Tensor, fit: AlbedoFreeFit, labels: Tensor | None, robust_scale: float,
                   residuals: str) -> tuple[Tensor, AlbedoFreeFit]:
    # Each image's lobe ``gloss (B, 2)`` and its fit at GLOSS_STRIDE, refined for
    # GLOSS_REFINE_ROUNDS rounds: the 8 lobes about it at the round's step (in log) refined as
    # the grid's were, the lowest loss kept (the lobe itself where none is lower).
    if GLOSS_REFINE_ROUNDS == 0:  # off: no 8-fold copies of the labels for nothing
        return gloss, fit
    B = problem.batch
    step = torch.tensor([math.log(GLOSS_RATIOS[-1] / GLOSS_RATIOS[0]) / (len(GLOSS_RATIOS) - 1),
                         math.log(GLOSS_SHININESS[-1] / GLOSS_SHININESS[0]) / (len(GLOSS_SHININESS) - 1)],
                        dtype=gloss.dtype, device=gloss.device)
    around = torch.tensor([(a, b) for a in (-1.0, 0.0, 1.0) for b in (-1.0, 0.0, 1.0) if (a, b) != (0.0, 0.0)],
                          dtype=gloss.dtype, device=gloss.device)  # (8, 2)
    rows = torch.arange(B, device=gloss.device).repeat_interleave(len(around))
    coarse_labels = None if labels is None else labels[rows][:, ::GLOSS_STRIDE, ::GLOSS_STRIDE]
    for _ in range(GLOSS_REFINE_ROUNDS):
        step = step / 2
        lobes = gloss[:, None] * (around * step).exp()  # (B, 8, 2)
        seen = observe(subsample(problem.select(rows).with_gloss(lobes.reshape(-1, 2)), GLOSS_STRIDE), robust_scale,
                       residuals=residuals, labels=coarse_labels)
        tried = refine_positions(seen, fit.position[rows], fit.log_weight[rows], GLOSS_ITERATIONS[0])
        loss, best = tried.loss.view(B, len(around)).min(1)
        better = loss < fit.loss
        pick = torch.arange(B, device=best.device) * len(around) + best
        gloss = torch.where(better[:, None], lobes[torch.arange(B, device=best.device), best], gloss)
        fit = fit.chosen(better, AlbedoFreeFit.rows([(tried, int(r)) for r in pick]))
    return gloss, fit
