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
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from render import GBuffer, Material
from render.functional import light_transport, light_transport_jacobian
from render.shading import blinn_phong_lobe, light_geometry
from selfsup.estimation.normals import surface_segments
from selfsup.estimation.options import ALBEDO_FREE_RESIDUALS
from selfsup.estimation.problem import FitProblem, centre_and_size, gbuffer_centre_and_size, subsample
from selfsup.estimation.solvers import RUNAWAY_SIZES, grid_candidates, spread_best
from selfsup.estimation.uncertainty import block_sums, field_covariance, position_blocks, tilted_normals

__all__ = ["LogShading", "AlbedoFreeFit", "observe", "pair_differences", "shading_loss", "search", "search_each",
           "split_starts", "refine_positions", "light_shares", "mirror_lobes", "highlight_pixels",
           "position_covariance", "block_scores_of", "group_medians", "albedo_classes", "refine_on_classes"]

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
# The robust segment offsets (:meth:`LogShading.offsets`): reweighted means from the plain
# mean, the Cauchy scale times these factors (wide first, so that a start pulled towards a
# minority of a segment's pixels still finds the majority). Ad hoc, 2026-11-26, on the 24
# two-light Mitsuba captures (direct): the worst light error fell from 0.09-0.25 to
# 0.04-0.07 of the scene in five rooms (and rose 0.11 -> 0.12 in one); a median start instead of the wide steps gave the
# same fits at twice the time.
OFFSET_SCALES = (8.0, 4.0, 2.0, 1.0, 1.0)
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
# Where a search has more starts than its ``starts`` (the second light's: grid, split and
# anchor-pair starts), every start runs this many LM steps at ``start_stride`` and the best
# ``starts`` of them the rest. Ad hoc, 2026-11-27: 0.05-0.1 s a frame less on 2 cores; on 306
# capture frames one borderline frame lost (devset gi 031, 0.040 -> 0.053 of the scene), 5 steps the same.
PRUNE_ITERATIONS = 3
# LM steps of the chosen model on its albedo classes (refine_on_classes): 8 and 15 placed our
# 384 capture frames alike, 245 and 246 successes (ad hoc, 2026-11-27, docs/decisions.md).
CLASS_ITERATIONS = 8


@dataclass
class LogShading:
    """A batch's observed log shading and what its model needs.

    Attributes:
        log_shading: ``(B, H, W)`` log of the channels' mean of ``image / kd``.
        pairs: ``(B, P)`` the residuals that count: valid neighbour pairs
            (:func:`pair_differences` order), or with ``segments`` valid pixels of a
            usable segment (``P = H W``).
        observed: ``(B, P)`` the observation's :meth:`differences`.
        gbuffer, material, falloff: the geometry and renderer settings of the transport.
        scale: ``(B,)`` Cauchy scale of the residuals (log units).
        segments: ``(B, H W)`` each pixel's albedo segment (``segment_count``: none), or None for pairs.
        segment_count: how many segment ids there are (one more than the largest label; the
            id of "none"): the segment sums' length, whatever the image's size.
    """

    log_shading: Tensor
    pairs: Tensor
    observed: Tensor
    gbuffer: GBuffer
    material: Material
    falloff: str
    scale: Tensor
    segments: Tensor | None = None
    segment_count: int = 0

    def differences(self, x: Tensor) -> Tensor:
        """The albedo-free view of log images ``x (B, [k,] H, W)`` -> ``(B, [k,] P)``: pair
        differences of neighbours, or each pixel minus its segment's mean."""
        if self.segments is None:
            return pair_differences(x)
        flat = x.flatten(-2)
        valid = self.pairs.to(flat.dtype)
        return (flat - self.segment_means(flat, valid)) * (valid if flat.dim() == 2 else valid[:, None])

    def segment_means(self, x: Tensor, weight: Tensor) -> Tensor:
        """Each pixel's segment's ``weight (B, P)``-weighted mean of ``x (B, [k,] P)``, at
        every pixel (the shape of ``x``; 0 where a segment weighs nothing). Segments only."""
        if self.segments is None:
            raise ValueError("segment means are a segment view's; pairs have none")
        # An expanded index is read with stride 0, which scatter_add_ takes 1.6x as long over
        # as over a copy of it (the copy's cost included; ad hoc, 2026-11-27, 2-core CPU, (16, 8, 4800) sums).
        index = self.segments if x.dim() == 2 else self.segments[:, None].expand_as(x).contiguous()
        w = weight if x.dim() == 2 else weight[:, None]
        slots = self.segment_count + 1  # the segments and "none": a few hundred sums, not one per pixel
        sums = x.new_zeros(*x.shape[:-1], slots).scatter_add_(-1, index, x * w)
        totals = weight.new_zeros(weight.shape[0], slots).scatter_add_(1, self.segments, weight)
        return (sums / (totals if x.dim() == 2 else totals[:, None]).clamp_min(1e-30)).gather(-1, index)

    def offsets(self, x: Tensor) -> Tensor:
        """Each segment's robust location of ``x (B, P)`` (a log ratio of the
        observation to a model), at each of its pixels ``(B, P)``: means reweighted
        under the Cauchy loss at ``scale`` times :data:`OFFSET_SCALES` in turn, from the
        plain mean. Segments only."""
        valid = self.pairs.to(x.dtype)
        centre = self.segment_means(x, valid)
        for factor in OFFSET_SCALES:
            centre = self.segment_means(x, valid / (1 + ((x - centre) / (factor * self.scale[:, None])) ** 2))
        return centre


@dataclass
class AlbedoFreeFit:
    """Result of a batch: ``position (B, L, 3)``, ``log_weight (B, L + 1)`` (the ambient's,
    then each light's, log intensity relative to the first light's, which is 0),
    ``loss (B,)`` (Cauchy loss of the residuals), ``pairs (B,)`` (residuals that count:
    :attr:`LogShading.pairs`)."""

    position: Tensor
    log_weight: Tensor
    loss: Tensor
    pairs: Tensor

    @staticmethod
    def rows(picked: list[tuple["AlbedoFreeFit", int]]) -> "AlbedoFreeFit":
        """Row ``r`` of each ``(fit, r)`` (fits of one light count), stacked into one batch."""
        return AlbedoFreeFit(*(torch.stack([getattr(fit, f.name)[r] for fit, r in picked])
                               for f in dataclasses.fields(AlbedoFreeFit)))

    def without(self, light: int) -> "AlbedoFreeFit":
        """The fit with light ``light`` left out, its weights relative to the new first
        light (the loss and pairs kept as they were)."""
        L = self.position.shape[1]
        if not 0 <= light < L or L < 2:
            raise ValueError(f"cannot leave light {light} out of a fit of {L} lights")
        keep = [i for i in range(L) if i != light]
        # Every log weight relative to the new first light's (which becomes 0).
        u = self.log_weight[:, [0] + [1 + i for i in keep]] - self.log_weight[:, 1 + keep[0] : 2 + keep[0]]
        return AlbedoFreeFit(self.position[:, keep], u, self.loss, self.pairs)

    def better(self, other: "AlbedoFreeFit") -> "AlbedoFreeFit":
        """Each image's row of whichever fit (of one light count) has the lower loss."""
        take = other.loss < self.loss
        pick = lambda a, b: torch.where(take.view(-1, *[1] * (a.dim() - 1)), b, a)  # noqa: E731
        return AlbedoFreeFit(*(pick(getattr(self, f.name), getattr(other, f.name)) for f in dataclasses.fields(self)))


def pair_differences(x: Tensor) -> Tensor:
    """``x (..., H, W)`` -> ``(..., P)``: each pixel minus its left neighbour, then minus
    its upper one, flattened (``P = H (W - 1) + (H - 1) W``)."""
    return torch.cat([(x[..., :, 1:] - x[..., :, :-1]).flatten(-2), (x[..., 1:, :] - x[..., :-1, :]).flatten(-2)], -1)


def _pair_mask(mask: Tensor) -> Tensor:
    # (B, H, W) -> (B, P): both pixels of the pair valid.
    return torch.cat([(mask[..., :, 1:] & mask[..., :, :-1]).flatten(-2),
                      (mask[..., 1:, :] & mask[..., :-1, :]).flatten(-2)], -1)


# Felzenszwalb's graph segmentation of the sRGB-encoded image (skimage): its scale (larger:
# fewer, larger segments), smoothing and smallest segment; a segment of fewer valid pixels
# than MIN_SEGMENT_PIXELS is left out (its mean would be most of its pixels' values).
SEGMENT_SIGMA = 0.5
SEGMENT_MIN_SIZE = 15
MIN_SEGMENT_PIXELS = 8


def albedo_segments(problem: FitProblem, scale: float = 50.0, geometry: Tensor | None = None) -> Tensor:
    """Regions of one albedo ``(B, H, W)`` long (-1: none): the smooth surfaces of the
    geometry (:func:`selfsup.estimation.normals.surface_segments`) cut by the image's edges
    (Felzenszwalb's segmentation of the sRGB-encoded image at ``scale``), so that both an
    object's outline and a texture's edges bound them. Found once per image: a subsample's
    are every stride-th label (:func:`search`). ``geometry``: the surfaces ``(B, H, W)``
    when already found (a still camera's frames share them)."""
    import numpy as np
    from skimage.segmentation import felzenszwalb

    from selfsup.scenes.capture import linear_to_srgb

    g = problem.gbuffer
    B, H, W = g.mask.shape
    if geometry is None:
        geometry = surface_segments(g.points, g.normals, g.mask)
    geometry = geometry.flatten(1).cpu().numpy()
    image = problem.image.detach().double().cpu().numpy()
    keep = g.mask.flatten(1).cpu().numpy()
    out = np.full((B, H * W), -1, dtype=np.int64)
    for b in range(B):
        level = np.percentile(image[b][:, keep[b].reshape(H, W)], 99) if keep[b].any() else 1.0
        encoded = linear_to_srgb(image[b].transpose(1, 2, 0) / max(level, 1e-30))  # edges as an eye (and a camera) sees them
        colour = felzenszwalb(encoded, scale=scale, sigma=SEGMENT_SIGMA, min_size=SEGMENT_MIN_SIZE).ravel()
        key = np.where(keep[b], geometry[b] * (int(colour.max()) + 1) + colour, -1)
        _, label = np.unique(key, return_inverse=True)
        out[b] = np.where(keep[b], label.reshape(-1) - int((~keep[b]).any()), -1)  # the invalid key (-1) sorts first
    return torch.from_numpy(out).to(g.mask.device).view(B, H, W)


def _usable(labels: Tensor, valid: Tensor) -> tuple[Tensor, int]:
    # (B, H, W) labels -> (B, H*W) segment of each valid pixel of a segment of at least
    # MIN_SEGMENT_PIXELS valid ones, ``count`` (none) elsewhere, and ``count``: one more than
    # the largest label (a subsample's labels are its full image's).
    count = int(labels.max()) + 1 if labels.numel() else 0
    flat = torch.where(valid & (labels >= 0), labels, count).flatten(1)
    sizes = torch.zeros(valid.shape[0], count + 1, dtype=torch.long, device=flat.device)
    sizes.scatter_add_(1, flat, torch.ones_like(flat))
    return torch.where((flat < count) & (sizes.gather(1, flat) >= MIN_SEGMENT_PIXELS), flat, count), count


def observe(problem: FitProblem, robust_scale: float = 0.02, noise_floor: float = 1.0, residuals: str = "segments",
            segment_scale: float = 50.0, labels: Tensor | None = None) -> LogShading:
    """The observed log shading of ``problem``; pixels with kd or the image at zero left out.

    ``residuals``: ``segments`` (each pixel's log shading minus its albedo segment's mean,
    :func:`albedo_segments` at ``segment_scale``, or ``labels (B, H, W)`` when found
    already) or ``pairs`` (differences of neighbours). The Cauchy scale is ``robust_scale`` (a relative change), at least
    ``noise_floor`` x the image's noise level relative to its median.
    """
    if residuals not in ALBEDO_FREE_RESIDUALS:
        raise ValueError(f"residuals must be one of {ALBEDO_FREE_RESIDUALS}, got {residuals!r}")
    kd = problem.material.kd.permute(0, 3, 1, 2)  # (B, 3, H, W)
    lit = (kd > 0).all(1) & problem.gbuffer.mask
    grey = torch.where(lit[:, None], problem.image / kd.clamp_min(1e-12), torch.zeros_like(problem.image)).mean(1)
    median = torch.where(lit, grey, torch.full_like(grey, float("nan"))).flatten(1).nanmedian(1).values
    median = torch.nan_to_num(median, nan=1.0).clamp_min(1e-30)
    valid = lit & (grey > 1e-6 * median[:, None, None])
    log_shading = torch.log(torch.where(valid, grey, median[:, None, None]))
    relative_noise = problem.noise_level() / problem.median_observed().clamp_min(1e-30)
    scale = torch.clamp_min(noise_floor * relative_noise, robust_scale)
    segments, count = None, 0
    if residuals == "segments":
        segments, count = _usable(albedo_segments(problem, segment_scale) if labels is None else labels, valid)
        pairs = segments < count
    else:
        pairs = _pair_mask(valid)
    obs = LogShading(log_shading, pairs, log_shading, problem.gbuffer, Material(kd=problem.material.kd),
                     problem.falloff, scale.to(grey.dtype), segments, count)
    obs.observed = obs.differences(log_shading)  # the same view of the data as of every model
    return obs


def _tiled(obs: LogShading, count: int) -> LogShading:
    # Every image ``count`` times in a row.
    rep = lambda x: None if x is None else x.repeat_interleave(count, 0)  # noqa: E731
    rows = torch.arange(obs.gbuffer.batch_size, device=obs.gbuffer.points.device).repeat_interleave(count)
    return LogShading(rep(obs.log_shading), rep(obs.pairs), rep(obs.observed), obs.gbuffer.select(rows),
                      Material(kd=rep(obs.material.kd)), obs.falloff, rep(obs.scale), rep(obs.segments),
                      obs.segment_count)


def _transport(obs: LogShading, position: Tensor) -> Tensor:
    # Unit diffuse transport (B, L, H, W), shading alone.
    return light_transport(obs.gbuffer, obs.material, position, falloff=obs.falloff, shadows="none",
                           specular=False).diffuse


def _log_model(diffuse: Tensor, log_weight: Tensor) -> tuple[Tensor, Tensor]:
    # The model's shading S (B, H, W) and its log, of unit transport (B, L, H, W) and
    # log weights (B, L + 1); S floored as _floored_log.
    w = log_weight.exp()
    return _floored_log(w[:, :1, None] + (w[:, 1:, None, None] * diffuse).sum(1))


def _floored_log(shading: Tensor) -> tuple[Tensor, Tensor]:
    # The log of shadings (..., H, W) and the shadings, each floored at 1e-12 of its peak
    # (dark sides, no ambient).
    shading = shading.clamp_min(1e-12 * shading.flatten(-2).amax(-1).clamp_min(1e-30)[..., None, None])
    return shading.log(), shading


def _per_image(value: Tensor, like: Tensor) -> Tensor:
    # A per-image value (B,) or (B, P) viewed to broadcast against ``like`` (B, [G,] P): a
    # model per image, or G candidate models of each image side by side.
    return value.view(value.shape[0], *[1] * (like.dim() - value.dim()), *value.shape[1:])


def shading_loss(obs: LogShading, residual: Tensor) -> Tensor:
    """Cauchy loss ``(B,)`` of pair residuals ``(B, P)`` (or ``(B, G)`` of ``G`` models'
    ``(B, G, P)``): ``sum c^2 log(1 + (r / c)^2)``."""
    c = _per_image(obs.scale, residual)
    return (c**2 * torch.log1p((residual / c) ** 2) * _per_image(obs.pairs, residual)).sum(-1)


def _cauchy_weights(obs: LogShading, residual: Tensor) -> Tensor:
    # IRLS weights (B, P) of pair residuals: 0 off the valid pairs.
    return obs.pairs / (1 + (residual / obs.scale[:, None]) ** 2)


def _residual(obs: LogShading, log_model: Tensor, robust: bool = True) -> Tensor:
    # (B, P): pairs' differences, or each pixel's log ratio to the model less its segment's
    # offset (robust: :meth:`LogShading.offsets`; else the mean, :meth:`LogShading.differences`).
    # Not robust, log models (B, G, H, W) give (B, G, P).
    if obs.segments is None or not robust:
        model = obs.differences(log_model)
        return torch.where(_per_image(obs.pairs, model), _per_image(obs.observed, model) - model,
                           torch.zeros((), dtype=model.dtype, device=model.device))
    ratio = (obs.log_shading - log_model).flatten(1)
    return torch.where(obs.pairs, ratio - obs.offsets(ratio), torch.zeros_like(ratio))


def _evaluate(obs: LogShading, position: Tensor, log_weight: Tensor) -> tuple[Tensor, Tensor]:
    # The loss (B,) and the residual (B, P) it sums.
    log_model, _ = _log_model(_transport(obs, position), log_weight)
    residual = _residual(obs, log_model)
    return shading_loss(obs, residual), residual


def _jacobian(obs: LogShading, position: Tensor, log_weight: Tensor, robust: bool = True,
              residual: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Residual ``(B, P)`` and its Jacobian ``(B, k, P)`` with respect to the free
    parameters: each light's position (3L), the ambient's log weight, and the log
    weights of lights 2.. (the first light's is the gauge). With ``robust`` segment
    offsets the Jacobian is the reweighting's (each offset a weighted mean whose weights
    are held): exact where the residuals lie well inside the Cauchy scale. ``residual``:
    the one at these parameters when known (:func:`_evaluate`'s)."""
    B, L, _ = position.shape
    jac = light_transport_jacobian(obs.gbuffer, obs.material, position, 1.0, falloff=obs.falloff, shadows="none",
                                   specular=False)
    diffuse = jac.transport.diffuse  # (B, L, H, W)
    log_model, shading = _log_model(diffuse, log_weight)
    w = log_weight.exp()
    H, W = diffuse.shape[-2:]
    # d log S / d p_i = w_i dD_i/dp_i / S; d log S / d u_0 = w_0 / S; d log S / d u_i = w_i D_i / S,
    # each block written into one (B, k, H, W) array and divided by S there (no copies between).
    d_log = diffuse.new_empty(B, 4 * L, H, W)
    torch.mul(w[:, 1:, None, None, None], jac.diffuse.permute(0, 1, 4, 2, 3),
              out=d_log[:, : 3 * L].view(B, L, 3, H, W))
    d_log[:, 3 * L] = w[:, :1, None]
    torch.mul(w[:, 2:, None, None], diffuse[:, 1:], out=d_log[:, 3 * L + 1 :])
    d_log /= shading[:, None]
    residual = _residual(obs, log_model, robust) if residual is None else residual
    if obs.segments is None or not robust:
        return residual, -obs.differences(d_log) * obs.pairs[:, None]
    # The offsets move with the model: each is a weighted mean (the Cauchy weights of its
    # pixels' residuals), so a residual's derivative is the model's less that mean of it
    # (mean - d, which is -(d - mean) exactly).
    d_log = d_log.flatten(2)  # (B, k, P)
    mean = obs.segment_means(d_log, _cauchy_weights(obs, residual))
    return residual, mean.sub_(d_log).mul_(obs.pairs[:, None])


def _unpack(step: Tensor, L: int) -> tuple[Tensor, Tensor]:
    # A free-parameter step (B, 4L) -> position step (B, L, 3), log-weight step (B, L + 1).
    B = step.shape[0]
    d_pos = step[:, : 3 * L].reshape(B, L, 3)
    d_u = torch.cat([step[:, 3 * L : 3 * L + 1], step.new_zeros(B, 1), step[:, 3 * L + 1 :]], 1)
    return d_pos, d_u


def refine_positions(obs: LogShading, position: Tensor, log_weight: Tensor, iterations: int = 20,
                     tol: float = 1e-6) -> AlbedoFreeFit:
    """Damped Gauss-Newton (Levenberg-Marquardt) with Cauchy IRLS weights from
    ``position (B, L, 3)`` and ``log_weight (B, L + 1)``; each image stops on its own
    (relative loss decrease below ``tol``, or damping run out)."""
    position, log_weight = position.detach().clone(), log_weight.detach().clone()
    B, L, _ = position.shape
    centre, size = gbuffer_centre_and_size(obs.gbuffer)
    reach = RUNAWAY_SIZES * size  # (B,)
    loss, residual = _evaluate(obs, position, log_weight)
    damping = torch.full((B,), 1e-3, dtype=position.dtype, device=position.device)
    active = torch.ones(B, dtype=torch.bool, device=position.device)
    for _ in range(iterations):
        if not bool(active.any()):
            break
        residual, jac = _jacobian(obs, position, log_weight, residual=residual)
        weights = _cauchy_weights(obs, residual)
        weighted = jac * weights[:, None]
        jtj = (weighted @ jac.transpose(1, 2)).double()
        jtr = (weighted @ residual[..., None]).double()
        diag = jtj.diagonal(dim1=-2, dim2=-1)
        peak = diag.amax(-1, keepdim=True)
        diag = torch.where(peak > 0, diag.clamp_min(1e-9 * peak), torch.ones_like(diag))
        system = jtj + damping.double()[:, None, None] * torch.diag_embed(diag)
        # residual r = observed - model, J = d r / d theta: the step solves (J W J^T) d = -J W r.
        step = -torch.linalg.solve_ex(system, jtr)[0].squeeze(-1).to(position.dtype)
        finite = torch.isfinite(step).all(-1) & active
        step = torch.where(finite[:, None], step, torch.zeros_like(step))
        d_pos, d_u = _unpack(step, L)
        trial_pos, trial_u = position + d_pos, log_weight + d_u
        trial, trial_residual = _evaluate(obs, trial_pos, trial_u)
        # A step that takes a light beyond RUNAWAY_SIZES scene sizes fits a direction, not a
        # point (the log shading of a far light flattens towards it): it is not taken.
        inside = (trial_pos - centre[:, None]).norm(dim=-1).amax(-1) <= reach
        better = finite & inside & (trial < loss)
        rel = (loss - trial) / loss.clamp_min(1e-30)
        position = torch.where(better[:, None, None], trial_pos, position)
        log_weight = torch.where(better[:, None], trial_u, log_weight)
        loss = torch.where(better, trial, loss)
        residual = torch.where(better[:, None], trial_residual, residual)
        damping = torch.where(better, damping * 0.3, damping * 10).clamp(1e-9, 1e9)
        active &= ~((better & (rel < tol)) | (damping >= 1e9))
    return AlbedoFreeFit(position, log_weight, loss, obs.pairs.sum(1))


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
    return refine_positions(full, fit.position[pick], fit.log_weight[pick], iterations[1])


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
    """Each light of ``fit`` (two or more) searched again with the others held where they
    are (:func:`search`), one after the other, each image keeping whichever fit has the
    lower loss. A light searched while a wrong one was held (the first of two, fitted
    alone, between the two) can then be searched again once the other is right.
    ``per_axis``, ``starts``, ``iterations``: as :func:`search`, the others as :func:`observe`."""
    if residuals == "segments" and labels is None:
        labels = albedo_segments(problem, segment_scale)
    for light in range(fit.position.shape[1]):
        again = search(problem, fit.position.shape[1], fixed=fit.without(light), robust_scale=robust_scale,
                       residuals=residuals, segment_scale=segment_scale, labels=labels, split=False, per_axis=per_axis,
                       starts=starts, iterations=iterations)
        fit = fit.better(again)
    return fit


def light_shares(problem: FitProblem, fit: AlbedoFreeFit) -> Tensor:
    """Each light's share ``(B, L)`` of the fitted direct shading over the valid pixels."""
    diffuse = light_transport(problem.gbuffer, Material(kd=problem.material.kd), fit.position,
                              falloff=problem.falloff, shadows="none", specular=False).diffuse
    direct = (fit.log_weight[:, 1:].exp()[..., None, None] * diffuse * problem.gbuffer.mask[:, None]).flatten(2).sum(2)
    return direct / direct.sum(1, keepdim=True).clamp_min(1e-30)


def mirror_lobes(gbuffer: GBuffer, position: Tensor, max_angle_deg: float) -> Tensor:
    """``(B, H, W)`` bool: valid pixels whose normal lies within ``max_angle_deg`` of the
    half vector between the view and the direction to any light at ``position (B, L, 3)``:
    where a glossy surface shows that light's highlight (a Blinn-Phong lobe of shininess
    30 keeps 0.15 of its peak 20 degrees out)."""
    geometry = light_geometry(gbuffer.points[:, None], position[:, :, None, None])
    cosine = blinn_phong_lobe(gbuffer.normals[:, None], geometry.to_light, geometry.to_viewer, 1.0)  # n.h (B, L, H, W)
    return (cosine > math.cos(math.radians(max_angle_deg))).any(1) & gbuffer.mask


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
        fit = refine_positions(observed, fit.position, fit.log_weight, iterations)
    return fit, observed


def highlight_pixels(obs: LogShading, fit: AlbedoFreeFit, max_angle_deg: float) -> Tensor:
    """``(B, H, W)`` bool: the pixels of ``fit``'s lights' :func:`mirror_lobes` that are
    brighter than its model (a positive residual against their segment's offset): where
    a glossy surface may show a highlight the diffuse-only fit does not explain.
    Segment residuals only."""
    if obs.segments is None:
        raise ValueError("highlight pixels are found on segment residuals; pairs have no pixel of their own")
    _, residual = _evaluate(obs, fit.position, fit.log_weight)
    lobes = mirror_lobes(obs.gbuffer, fit.position, max_angle_deg)
    return lobes & (residual.view_as(lobes) > 0)


def position_covariance(obs: LogShading, fit: AlbedoFreeFit, block_px: int = 1, indirect_variation: float = 0.0,
                        indirect_length: float = 0.15, normal_tilt: Tensor | None = None) -> Tensor:
    """Gauss-Newton covariance ``(B, L, 3, 3)`` of each light's position under the pair
    residuals' Cauchy weights (the albedo edges' pairs weigh nothing); the noise
    variance is the weighted residual's, inflated by the ``block_px^2`` pixels of one
    independent residual (the criterion's block).

    Two error sources the residual cannot show are added as the given-albedo covariance
    adds them (``uncertainty.position_covariance``), one value per block:

    - ``indirect_variation > 0``: a smooth relative variation of the ambient over the
      scene (the indirect light a constant ambient leaves out), a Gaussian field of that
      standard deviation and correlation length ``indirect_length`` (of the scene size);
    - ``normal_tilt (B, H, W)``: the variance (radians^2 per tilt axis) of normals fitted
      to noisy depth, every block tilted as one, independently between blocks and axes.
    """
    residual, jac = _jacobian(obs, fit.position, fit.log_weight)
    weights = _cauchy_weights(obs, residual)
    sigma2 = (weights * residual**2).sum(1) / (weights.sum(1) - jac.shape[1]).clamp_min(1) * float(block_px**2)
    info = ((jac * weights[:, None]) @ jac.transpose(1, 2)).double()
    weighted = jac * weights[:, None]
    extras = []
    if indirect_variation > 0 or normal_tilt is not None:
        log_model, shading = _log_model(_transport(obs, fit.position), fit.log_weight)
    if indirect_variation > 0:
        # The ambient times (1 + e): d log S = ambient / S per unit e, e a field over the blocks.
        scores = block_scores_of(obs, weighted, fit.log_weight[:, :1, None].exp() / shading, block_px)
        kernel = field_covariance(obs.gbuffer, block_px, indirect_variation, indirect_length).double()
        extras.append(scores @ kernel @ scores.transpose(1, 2))
    if normal_tilt is not None:
        for change in _tilt_changes(obs, fit, log_model, normal_tilt):
            scores = block_scores_of(obs, weighted, change, block_px)
            extras.append(scores @ scores.transpose(1, 2))
    return position_blocks(info, sigma2.double(), fit.position.shape[1],
                           sum(extras) if extras else None).to(fit.position.dtype)


def _tilt_changes(obs: LogShading, fit: AlbedoFreeFit, log_model: Tensor, normal_tilt: Tensor,
                  step: float = 1e-3) -> list[Tensor]:
    # The log shading's change (B, H, W) from ``log_model`` under a tilt of one standard
    # deviation (sqrt(normal_tilt), at most 1 radian) of every normal about each of its two
    # tilt axes: forward differences of ``step`` radians through the shading.
    size = normal_tilt.to(log_model.dtype).clamp(0, 1).sqrt()
    changes = []
    for tilted in tilted_normals(obs.gbuffer, step):
        moved, _ = _log_model(_transport(dataclasses.replace(obs, gbuffer=tilted), fit.position), fit.log_weight)
        changes.append((moved - log_model) / step * size)
    return changes


def block_scores_of(obs: LogShading, weighted_jac: Tensor, change: Tensor, block_px: int) -> Tensor:
    """``J^T W`` times the observation's log shading changed by ``change (B, H, W)`` over one
    square block of ``block_px`` pixels, for each block: ``(B, k, blocks)`` float64,
    row-major blocks; ``weighted_jac (B, k, P)`` is the Jacobian of :func:`_jacobian`
    times the Cauchy weights. To first order such a change, times ``e``, moves the fit by
    ``-info^-1 scores e``. The segment offsets absorb their mean of the change, which the
    Jacobian's rows (their own offsets' means taken out, under the same weights) do not
    see; the pairs view is mapped back to its pixels by the differences' adjoint."""
    B, k = weighted_jac.shape[:2]
    H, W = obs.log_shading.shape[-2:]
    if obs.segments is None:
        across, down = weighted_jac.split([H * (W - 1), (H - 1) * W], -1)
        across, down = across.reshape(B, k, H, W - 1), down.reshape(B, k, H - 1, W)
        per_pixel = weighted_jac.new_zeros(B, k, H, W)
        per_pixel[..., :, 1:] += across
        per_pixel[..., :, :-1] -= across
        per_pixel[..., 1:, :] += down
        per_pixel[..., :-1, :] -= down
    else:
        per_pixel = weighted_jac.reshape(B, k, H, W)
    return block_sums((per_pixel * change[:, None]).double(), block_px)
