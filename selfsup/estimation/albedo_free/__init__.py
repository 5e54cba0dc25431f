"""Light positions from the log shading with the albedo taken out: a fit no piecewise-constant albedo error moves.

Where the file's ``kd`` is not the surfaces' albedo (a capture's 0.5 everywhere; the
paper's protocol row "m = 0" gives kd = ks = 0.5 over a textured scene), ``image / kd``
is the shading times the albedo's error. Over a region of one albedo that error is one
constant, which drops out of the logarithm's deviation from its mean over the region::

    log(I_p / kd_p) - mean_s log(I / kd) = log S_p - mean_s log S,   S = a + sum_i L_i D_i

with ``D_i`` the unit-intensity diffuse transport of light ``i`` (shading alone, no cast
shadows) and ``a`` the ambient. The fit takes each segment's offset not as the mean but
as a robust (Cauchy) location of ``log(I / kd) - log S`` over it (:meth:`LogShading.offsets`):
a segment that holds a second albedo in a few of its pixels, or a shadow its model lacks,
keeps the offset of the rest, where a mean would shift every residual in it. The grid
search ranks its candidates with the mean (the cheaper view). The regions
(``residuals="segments"``, the default) are the geometry's smooth surfaces cut by the
image's edges (:func:`albedo_segments`);
``residuals="pairs"`` takes neighbouring pixels instead (differences to the right and
below). Either is fitted under a Cauchy loss, whose outliers are what the regions miss:
weak texture edges inside a segment, pairs across an albedo edge, cast shadows. The fit
sees the lights' positions and the intensities' ratios (to the first light, and the
ambient's), not their overall scale. The observation is the mean over the channels of
``image / kd`` (the grey shading, exact for white lights).

Measured (benchmarks/results/estimation_measurements.md, "Camera captures"): on 48 Mitsuba captures a set, one-light
success 100% direct, 83% path traced, 100% sensor-noisy with segments and their robust
offsets (96/83/100% with their means; 100/88/100% with the count decided without the
lights' highlights, :func:`highlight_pixels`), against 71/71/50% with pairs, whose
differences are small beside 8-bit quantisation and millimetre depth. This loss alone
takes a second light in a third of the two-light captures of our Mitsuba rooms at most
(:func:`search_each`, :func:`split_starts` and :func:`anchor_pairs` find the fits; its
criterion rarely takes them); with the black pixels of the direct-light and sensor-noisy
captures (:mod:`selfsup.estimation.unlit`) 46-79% of them are counted right, and every
two-light devset capture.
The chosen model's lights are then placed on the segments of each surface merged into
classes of one albedo (:func:`albedo_classes`, :func:`refine_on_classes`), which gives back
part of what each segment's free level throws away: how bright it is beside the others.
It is no substitute where kd is right: the image fit of a file with its albedo uses
every pixel's brightness, which this fit throws away.

The package, by what its parts do: :mod:`.observation` (the log shading, its segments
and residual view), :mod:`.fit` (the model, its loss and Levenberg-Marquardt),
:mod:`.light_search` (where the lights start), :mod:`.classes` (albedo classes) and
:mod:`.covariance` (how well each light is placed), :mod:`.regions` (segments joined across shading).
"""

from selfsup.estimation.albedo_free.classes import CLASS_ITERATIONS, albedo_classes, refine_on_classes
from selfsup.estimation.albedo_free.regions import group_medians
from selfsup.estimation.albedo_free.covariance import block_scores_of, position_covariance
from selfsup.estimation.albedo_free.fit import (FINAL_TOLERANCE, LM_TOLERANCE, bounce_maps, highlight_pixels,
                                                light_shares, mirror_lobes, model_transport, refine_positions,
                                                residual_spread, shading_loss)
from selfsup.estimation.albedo_free.observation import (MIN_SEGMENT_PIXELS, AlbedoFreeFit, LogShading, albedo_segments,
                                                        fit_material, glossy_material, observe, pair_differences,
                                                        tuned_segments)
from selfsup.estimation.albedo_free.gloss import (GLOSS_PARAMETERS, choose_coat, choose_gloss, choose_lone_lobe,
                                                  coated_images, diffuse_images, fit_lobes, gloss_parameters,
                                                  keep_lobes, lobe_of, mirror_start)
from selfsup.estimation.albedo_free.light_search import (AMBIENT_STEPS, LEAN_SEARCH, RATIO_STEPS, anchor_pairs,
                                                         refine_from, search, search_each, split_starts)

__all__ = ["LogShading", "AlbedoFreeFit", "observe", "pair_differences", "albedo_segments", "tuned_segments", "shading_loss", "search",
           "search_each", "split_starts", "anchor_pairs", "refine_positions", "bounce_maps", "light_shares", "model_transport",
           "glossy_material", "fit_material", "mirror_lobes", "residual_spread",
           "highlight_pixels", "position_covariance", "block_scores_of", "group_medians", "albedo_classes",
           "refine_on_classes", "refine_from", "choose_gloss", "choose_coat", "choose_lone_lobe", "fit_lobes", "keep_lobes", "mirror_start",
           "diffuse_images", "gloss_parameters", "lobe_of", "coated_images",
           "GLOSS_PARAMETERS", "AMBIENT_STEPS", "LEAN_SEARCH", "RATIO_STEPS", "CLASS_ITERATIONS", "MIN_SEGMENT_PIXELS",
           "LM_TOLERANCE", "FINAL_TOLERANCE"]
