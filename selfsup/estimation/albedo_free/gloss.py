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
the lobe is tried only where the diffuse fit takes more lights, with the first light alone,
and kept where its criterion is below theirs (not where the black pixels took the second
light: a lobe casts no shadow). Rough gold and aluminium then take one light in 10 of 16
frames (``benchmarks/results/gloss_instead_cpu2_2026-12-06.md``), and a frame one light
explains never takes a lobe (tried beside every first light, ``auto``, the matte DiLiGenT
bear's faint sheen took one in 24 of 24 frames and lost 0.6 degrees).

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

import torch
from torch import Tensor

from selfsup.estimation.albedo_free.fit import FINAL_TOLERANCE, refine_positions
from selfsup.estimation.albedo_free.observation import AlbedoFreeFit, observe
from selfsup.estimation.problem import FitProblem, subsample

__all__ = ["choose_gloss", "GLOSS_RATIOS", "GLOSS_SHININESS", "GLOSS_PARAMETERS"]

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


def choose_gloss(problem: FitProblem, found: AlbedoFreeFit, labels: Tensor | None, robust_scale: float,
                 criterion, residuals: str = "segments", against: list[float] | None = None
                 ) -> tuple[FitProblem, AlbedoFreeFit]:
    """Each image's specular lobe, or none: every lobe of :data:`GLOSS_RATIOS` x
    :data:`GLOSS_SHININESS` refined from ``found`` (the first light's fit of ``problem``)
    at :data:`GLOSS_STRIDE`, the best one at full resolution, kept where ``criterion(fit,
    extra)`` (a list per image; lower is better) with :data:`GLOSS_PARAMETERS` more is below
    the diffuse fit's, and below ``against`` (a criterion per image, e.g. of the diffuse
    fit with more lights) where given. Returns the problem with its ``gloss (B, 2)`` (a
    ratio of 0 where none was kept; None where no image kept one) and each image's fit, with
    or without it. ``labels``, ``robust_scale``, ``residuals``: as :func:`observe`."""
    B = problem.batch
    combos = torch.tensor(list(itertools.product(GLOSS_RATIOS, GLOSS_SHININESS)), dtype=problem.image.dtype,
                          device=problem.image.device)  # (G, 2)
    G = combos.shape[0]
    rows = torch.arange(B, device=problem.image.device).repeat_interleave(G)
    tiled = subsample(problem.select(rows).with_gloss(combos.repeat(B, 1)), GLOSS_STRIDE)
    coarse_labels = None if labels is None else labels[rows][:, ::GLOSS_STRIDE, ::GLOSS_STRIDE]
    seen = observe(tiled, robust_scale, residuals=residuals, labels=coarse_labels)
    tried = refine_positions(seen, found.position[rows], found.log_weight[rows], GLOSS_ITERATIONS[0])
    best = tried.loss.view(B, G).argmin(1)  # (B,)
    pick = torch.arange(B, device=best.device) * G + best
    gloss = combos[best]  # (B, 2)
    glossy = problem.with_gloss(gloss)
    full = observe(glossy, robust_scale, residuals=residuals, labels=labels)
    fitted = refine_positions(full, tried.position[pick], tried.log_weight[pick], GLOSS_ITERATIONS[1], FINAL_TOLERANCE)
    plain, lobed = criterion(found), criterion(fitted, [GLOSS_PARAMETERS] * B)
    if against is not None:
        plain = [min(p, a) for p, a in zip(plain, against)]
    take = torch.tensor([c < p for p, c in zip(plain, lobed)], device=problem.image.device)
    if not bool(take.any()):
        return problem, found
    gloss = torch.where(take[:, None], gloss, torch.zeros_like(gloss))
    return problem.with_gloss(gloss), found.chosen(take, fitted)
