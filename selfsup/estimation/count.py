"""One light more, or not: the albedo-free fit's count.

:func:`judged` decides, per image, whether a fit of one light more replaces the fit before
it: its criterion lower (without the highlights of the lights before, on albedo classes, or
either, as the tuning says) and each light carrying its share, or the capture's black pixels
asking for it. The driver (:mod:`selfsup.estimation.reflectance`) searches the lights; this
module compares fits.
"""

from __future__ import annotations

import torch
from torch import Tensor

from selfsup.estimation import albedo_free, unlit
from selfsup.estimation.criterion import criterion_light
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.problem import FitProblem

__all__ = ["MIN_RESIDUALS", "CLASS_COUNT_PENALTY", "residual_options", "judged", "or_black_pixels_need",
           "judged_on_classes", "highlight_free_labels", "without_highlights"]

MIN_RESIDUALS = 100  # the fewest residuals an albedo-free fit or count decision rests on
# How many times a light's parameters count when one light more is judged on albedo classes
# (estimate.tuning.albedo_free_count=classes): each model's classes are merged under its own
# lights, a choice the criterion does not count. Measured (2026-12-06, results file
# count_classes_cpu2_2026-12-06.md): counted once, one-light Mitsuba rooms took a second light in 2
# of 48 frames and the DiLiGenT bear in 5 of 24 (1 on segments); twice, none and 1, the
# two-light counts still 4 rooms up over eight capture sets; three times, the bear none.
CLASS_COUNT_PENALTY = 2


def residual_options(options: EstimateOptions) -> dict:
    # The albedo-free fit's residuals, as the tuning says.
    return dict(residuals=options.tuning.albedo_free_residuals, segment_scale=options.tuning.albedo_segment_scale)


def judged(sub: FitProblem, before: albedo_free.AlbedoFreeFit, more: albedo_free.AlbedoFreeFit,
           fewer_value: list[float], labels: Tensor | None, options: EstimateOptions, criterion,
           geometry: Tensor | None = None) -> tuple[list[bool], list[bool], list[float], list[float]]:
    # Whether each image takes the fit of one light more: its criterion lower (judged without the
    # highlights where enough residuals are left; on albedo classes with albedo_free_count=classes;
    # on either with either) and each light carrying min_light_share, or the black pixels asking
    # for it; whether the black pixels alone took it; and the two criteria compared.
    shares = albedo_free.light_shares(sub, more).amin(1).tolist()
    more_value = criterion(more)
    count, lobe_deg = options.tuning.albedo_free_count, options.tuning.albedo_free_lobe_deg
    if labels is not None and lobe_deg > 0:
        labels = highlight_free_labels(sub, before, labels, options)  # found once for both comparisons
    on_classes = None
    if labels is not None and count != "segments":
        on_classes = judged_on_classes(sub, before, more, labels, geometry, options, criterion, fewer_value,
                                       more_value)
    if labels is not None and count != "classes" and lobe_deg > 0:
        fewer_there, more_there = without_highlights(sub, before, more, labels, options)
        kept = (more_there.pairs >= MIN_RESIDUALS).tolist()
        fewer_value = [c if ok else v for c, ok, v in zip(criterion(fewer_there), kept, fewer_value)]
        more_value = [c if ok else v for c, ok, v in zip(criterion(more_there), kept, more_value)]
    if on_classes is not None:
        # classes: the classes' values. either: the values of whichever comparison the light wins
        # (the classes' where both or neither do).
        wins_on_segments = [m < f for f, m in zip(fewer_value, more_value)]
        keep_segments = [count == "either" and on_segments and not c < f
                         for on_segments, f, c in zip(wins_on_segments, *on_classes)]
        fewer_value = [b if k else a for k, a, b in zip(keep_segments, on_classes[0], fewer_value)]
        more_value = [b if k else a for k, a, b in zip(keep_segments, on_classes[1], more_value)]
    by_criterion = [c < f and share >= options.tuning.min_light_share
                    for c, f, share in zip(more_value, fewer_value, shares)]
    taken = by_criterion
    if options.tuning.unlit_evidence:
        taken = or_black_pixels_need(sub, options, before, more, by_criterion,
                                     [share >= options.tuning.weak_light_min_share for share in shares])
    return taken, [t and not c for t, c in zip(taken, by_criterion)], fewer_value, more_value


def or_black_pixels_need(problem: FitProblem, options: EstimateOptions, fewer: albedo_free.AlbedoFreeFit,
                         more: albedo_free.AlbedoFreeFit, taken: list[bool], lighting: list[bool] | None = None
                         ) -> list[bool]:
    """``taken`` (one light more, per image of ``problem``) or, where the criterion did not
    take it, the capture's black pixels need it (:func:`selfsup.estimation.unlit.needs_another_light`
    under the criterion's cast shadows). Only the images not taken already are rendered, and
    only those of a diffuse model: where the fit has a specular lobe (metal, gloss), a black
    pixel may be one the lobe does not reach as well as a shadow. ``lighting``: per image, whether
    every light of ``more`` gives some light (``tuning.weak_light_min_share`` of it; None: all do);
    where one does not, the black pixels cannot ask for it: a light 66 m behind the camera giving
    0.12% of a procedural room's light took its count by lighting, as a faint fill above the model's
    unlit level and below the capture's black one, the first light's shadows that the depth predicts wrongly."""
    diffuse_only = albedo_free.diffuse_images(problem).tolist()
    lighting = [True] * len(taken) if lighting is None else lighting
    rest = [j for j, t in enumerate(taken) if not t and diffuse_only[j] and lighting[j]]
    if not rest:
        return taken
    rows = torch.tensor(rest, dtype=torch.long, device=problem.image.device)
    needed = unlit.needs_another_light(criterion_light(problem.select(rows), options),
                                       (fewer.position[rows], fewer.log_weight[rows, 1:].exp()),
                                       (more.position[rows], more.log_weight[rows, 1:].exp())).tolist()
    out = list(taken)
    for j, need in zip(rest, needed):
        out[j] = need
    return out


def judged_on_classes(sub: FitProblem, fewer: albedo_free.AlbedoFreeFit, more: albedo_free.AlbedoFreeFit,
                      labels: Tensor, geometry: Tensor | None, options: EstimateOptions, criterion,
                      fewer_value: list[float], more_value: list[float]) -> tuple[list[float], list[float]]:
    """The criteria of ``fewer`` and ``more`` (fits of n - 1 and n lights), each refined on its
    own segments ``labels`` merged into albedo classes (:func:`albedo_free.refine_on_classes`),
    the classes counted as parameters (each one level) and each light's
    :data:`CLASS_COUNT_PENALTY` times, on the pixels of ``labels`` (the highlights already left
    out: :func:`highlight_free_labels`); an image left with fewer than :data:`MIN_RESIDUALS` keeps
    ``fewer_value`` and ``more_value`` (as found). A segment's free level absorbs what a second
    light does to it; how bright the segments of one paint are beside each other is part of what
    the light explains, and a model that explains it joins more segments into fewer classes.
    Measured over eight capture sets: 4 more two-light rooms counted, 2 one-light rooms' stray
    pairs gone, but a capture sequence's second light lost in 8 frames (the pair's margin 6.6 on
    segments, -4.2 here); the true pair as found from the truth still pays in only 6-20 of 24
    two-light rooms a set (7-20 on segments: benchmarks/results/count_classes_cpu2_2026-12-06.md)."""
    tuning = options.tuning
    values = []
    for fit in (fewer, more):
        refined, observed = albedo_free.refine_on_classes(
            sub, labels, fit, tuning.albedo_free_scale, 1, level_tolerance=tuning.albedo_class_level,
            chroma_tolerance=tuning.albedo_class_chroma, geometry=geometry)
        classes = [int(torch.unique(c[p]).numel()) for c, p in zip(observed.segments, observed.pairs)]
        own = [k + 4 * fit.position.shape[1] * (CLASS_COUNT_PENALTY - 1) for k in classes]  # one level a class
        values.append(criterion(refined, own))
    kept = (refined.pairs >= MIN_RESIDUALS).tolist()  # both fits count the same pixels
    return ([v if ok else f for v, ok, f in zip(values[0], kept, fewer_value)],
            [v if ok else m for v, ok, m in zip(values[1], kept, more_value)])


def highlight_free_labels(problem: FitProblem, fewer: albedo_free.AlbedoFreeFit, labels: Tensor,
                          options: EstimateOptions) -> Tensor:
    """The segments ``labels (B, H, W)`` less the pixels of ``fewer``'s mirror lobes that are
    brighter than its model (:func:`albedo_free.highlight_pixels`; -1 there), in the images
    whose model has no specular lobe (where it has one, the highlight is the model's)."""
    every_pixel = albedo_free.observe(problem, options.tuning.albedo_free_scale, labels=labels, **residual_options(options))
    held_out = albedo_free.highlight_pixels(every_pixel, fewer, options.tuning.albedo_free_lobe_deg)
    held_out &= albedo_free.diffuse_images(problem)[:, None, None]
    return torch.where(held_out, torch.full_like(labels, -1), labels)


def without_highlights(problem: FitProblem, fewer: albedo_free.AlbedoFreeFit, more: albedo_free.AlbedoFreeFit,
                       outside_labels: Tensor, options: EstimateOptions
                       ) -> tuple[albedo_free.AlbedoFreeFit, albedo_free.AlbedoFreeFit]:
    """``fewer`` and ``more`` (fits of n - 1 and n lights, as found on every pixel) with
    their losses on the segments' pixels less those of ``fewer``'s brighter mirror lobes
    (``outside_labels``: :func:`highlight_free_labels`). A glossy surface
    beside a light shows a highlight the diffuse-only fit cannot explain; a second light
    next to the first widens the modelled peak towards it and lowers the loss (one-light
    capture sequences with a glossy wall 0.05 of the scene from the light took such a pair
    on almost every frame). Without the highlight the pair has nothing to explain."""
    outside = albedo_free.observe(problem, options.tuning.albedo_free_scale, labels=outside_labels,
                                  **residual_options(options))
    # No iterations: the loss of each fit at its positions and log weights, on these pixels.
    return (albedo_free.refine_positions(outside, fewer.position, fewer.log_weight, 0, log_bounce=fewer.log_bounce),
            albedo_free.refine_positions(outside, more.position, more.log_weight, 0, log_bounce=more.log_bounce))
