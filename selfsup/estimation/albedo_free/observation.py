"""What the albedo-free fit sees: the log shading, its albedo segments and residual view.

:func:`observe` turns a :class:`~selfsup.estimation.problem.FitProblem` into a
:class:`LogShading` (the log of ``image / kd``, the pixels that count, the segments of one
albedo found by :func:`albedo_segments`); :class:`AlbedoFreeFit` is what every fit returns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from render import GBuffer, Material
from selfsup.estimation.normals import surface_segments
from selfsup.estimation.options import ALBEDO_FREE_RESIDUALS, Tuning
from selfsup.estimation.problem import FitProblem

__all__ = ["LogShading", "AlbedoFreeFit", "pair_differences", "albedo_segments", "tuned_segments", "observe",
           "glossy_material", "fit_material", "MIN_SEGMENT_PIXELS"]

# The robust segment offsets (:meth:`LogShading.offsets`): reweighted means from the plain
# mean, the Cauchy scale times these factors (wide first, so that a start pulled towards a
# minority of a segment's pixels still finds the majority). Ad hoc, 2026-11-26, on the 24
# two-light Mitsuba captures (direct): the worst light error fell from 0.09-0.25 to
# 0.04-0.07 of the scene in five rooms (and rose 0.11 -> 0.12 in one); a median start instead of the wide steps gave the
# same fits at twice the time.
OFFSET_SCALES = (8.0, 4.0, 2.0, 1.0, 1.0)


@dataclass
class LogShading:
    """A batch's observed log shading and what its model needs.

    Attributes:
        log_shading: ``(B, H, W)`` log of the channels' mean of ``image / kd``.
        pairs: ``(B, P)`` the residuals that count: valid neighbour pairs
            (:func:`pair_differences` order), or with ``segments`` valid pixels of a
            usable segment (``P = H W``).
        observed: ``(B, P)`` the observation's :meth:`differences`.
        gbuffer, material, falloff: the geometry and renderer settings of the transport
            (with ``material.ks``, each image's specular lobe beside the diffuse light:
            :func:`glossy_material`).
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
        index = self.segments if x.dim() == 2 else self._rows_of_segments(x.shape[1])
        w = weight if x.dim() == 2 else weight[:, None]
        slots = self.segment_count + 1  # the segments and "none": a few hundred sums, not one per pixel
        sums = x.new_zeros(*x.shape[:-1], slots).scatter_add_(-1, index, x * w)
        totals = weight.new_zeros(weight.shape[0], slots).scatter_add_(1, self.segments, weight)
        return (sums / (totals if x.dim() == 2 else totals[:, None]).clamp_min(1e-30)).gather(-1, index)

    def _rows_of_segments(self, rows: int) -> Tensor:
        # The segments for (B, rows, P) values, kept by rows (not a field: the view's fields are
        # its data): a solver asks for the same rows every step.
        kept = self.__dict__.setdefault("_row_index", {})
        if rows not in kept:
            kept[rows] = self.segments[:, None].expand(-1, rows, -1).contiguous()
        return kept[rows]

    def offsets(self, x: Tensor, valid: Tensor | None = None) -> Tensor:
        """Each segment's robust location of ``x (B, P)`` (a log ratio of the
        observation to a model), at each of its pixels ``(B, P)``: means reweighted
        under the Cauchy loss at ``scale`` times :data:`OFFSET_SCALES` in turn, from the
        plain mean; over the pixels ``valid (B, P)`` bool (default: :attr:`pairs`), 0 for
        a segment with none of them. Segments only."""
        valid = (self.pairs if valid is None else valid).to(x.dtype)
        centre = self.segment_means(x, valid)
        for factor in OFFSET_SCALES:
            centre = self.segment_means(x, valid / (1 + ((x - centre) / (factor * self.scale[:, None])) ** 2))
        return centre


@dataclass
class AlbedoFreeFit:
    """Result of a batch: ``position (B, L, 3)``, ``log_weight (B, L + 1)`` (the ambient's,
    then each light's, log intensity relative to the first light's, which is 0),
    ``loss (B,)`` (Cauchy loss of the residuals), ``pairs (B,)`` (residuals that count:
    :attr:`LogShading.pairs`), ``log_bounce (B,)`` or None: the log strength of the lights'
    light bounced off the surfaces (:func:`selfsup.estimation.albedo_free.fit.bounce_maps`;
    ``-inf`` for an image without it, None for a batch without it)."""

    position: Tensor
    log_weight: Tensor
    loss: Tensor
    pairs: Tensor
    log_bounce: Tensor | None = None

    _ALWAYS = ("position", "log_weight", "loss", "pairs")  # the fields every fit has

    def log_bounces(self) -> Tensor:
        """``log_bounce (B,)``, ``-inf`` where the fit has no bounce."""
        if self.log_bounce is not None:
            return self.log_bounce
        return torch.full_like(self.loss, -math.inf)

    def bounced(self) -> Tensor:
        """``(B,)`` bool: the images whose model has the bounce."""
        return torch.isfinite(self.log_bounces())

    @staticmethod
    def rows(picked: list[tuple["AlbedoFreeFit", int]]) -> "AlbedoFreeFit":
        """Row ``r`` of each ``(fit, r)`` (fits of one light count), stacked into one batch."""
        bounce = None
        if any(fit.log_bounce is not None for fit, _ in picked):
            bounce = torch.stack([fit.log_bounces()[r] for fit, r in picked])
        return AlbedoFreeFit(*(torch.stack([getattr(fit, name)[r] for fit, r in picked])
                               for name in AlbedoFreeFit._ALWAYS), bounce)

    def without(self, light: int) -> "AlbedoFreeFit":
        """The fit with light ``light`` left out, its weights relative to the new first
        light (the loss and pairs kept as they were)."""
        L = self.position.shape[1]
        if not 0 <= light < L or L < 2:
            raise ValueError(f"cannot leave light {light} out of a fit of {L} lights")
        return self._in_order([i for i in range(L) if i != light])

    def only(self, light: int) -> "AlbedoFreeFit":
        """Light ``light`` alone, its weights relative to it (the loss and pairs kept as they were)."""
        L = self.position.shape[1]
        if not 0 <= light < L:
            raise ValueError(f"there is no light {light} in a fit of {L} lights")
        return self._in_order([light])

    def with_last_at(self, light: int) -> "AlbedoFreeFit":
        """The fit with its last light moved to index ``light`` (the others keep their order),
        its weights relative to the new first light (the loss and pairs kept): a light searched
        again beside :meth:`without` ``(light)`` put back in its place."""
        L = self.position.shape[1]
        if not 0 <= light < L:
            raise ValueError(f"cannot move the last light to index {light} of a fit of {L} lights")
        return self._in_order(list(range(light)) + [L - 1] + list(range(light, L - 1)))

    def _in_order(self, order: list[int]) -> "AlbedoFreeFit":
        # The lights ``order`` (indices, in that order), every log weight relative to the new
        # first light's (which becomes 0); the ambient's, loss, pairs and bounce kept.
        u = self.log_weight[:, [0] + [1 + i for i in order]] - self.log_weight[:, 1 + order[0] : 2 + order[0]]
        return AlbedoFreeFit(self.position[:, order], u, self.loss, self.pairs, self.log_bounce)

    def better(self, other: "AlbedoFreeFit") -> "AlbedoFreeFit":
        """Each image's row of whichever fit (of one light count) has the lower loss."""
        return self.chosen(other.loss < self.loss, other)

    def chosen(self, take: Tensor, other: "AlbedoFreeFit") -> "AlbedoFreeFit":
        """Each image's row of ``other`` where ``take (B,)``, of this fit elsewhere."""
        pick = lambda a, b: torch.where(take.view(-1, *[1] * (a.dim() - 1)), b, a)  # noqa: E731
        bounce = None
        if self.log_bounce is not None or other.log_bounce is not None:
            bounce = pick(self.log_bounces(), other.log_bounces())
        return AlbedoFreeFit(*(pick(getattr(self, name), getattr(other, name)) for name in self._ALWAYS), bounce)


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
# The clear coat of glossy_material without a lobe: the Blinn-Phong exponent that sets its
# roughness (Beckmann a = sqrt(2 / (s + 2)), 0.1: a smooth varnish or plastic).
COAT_SHININESS = 200.0


def albedo_segments(problem: FitProblem, scale: float = 50.0, geometry: Tensor | None = None,
                    edge_step: float | None = Tuning.albedo_edge_step,
                    edge_chroma: float = Tuning.albedo_edge_chroma) -> Tensor:
    """Regions of one albedo ``(B, H, W)`` long (-1: none): the smooth surfaces of the
    geometry (:func:`selfsup.estimation.normals.surface_segments`) cut by the image's edges
    (Felzenszwalb's segmentation of the sRGB-encoded image at ``scale``), so that both an
    object's outline and a texture's edges bound them; then the segments of one surface
    joined again where only shading cuts them (:func:`.regions.join_shading_cuts`: the
    chromaticity within ``edge_chroma`` across the cut, and the log shading's step no more
    than ``edge_step`` beyond what the steps beside the cut predict; ``edge_step`` None:
    not joined). Found once per image: a subsample's are every stride-th label
    (:func:`search`). ``geometry``: the surfaces ``(B, H, W)`` when already found (a
    still camera's frames share them)."""
    from skimage.segmentation import felzenszwalb

    from selfsup.estimation.albedo_free.regions import join_shading_cuts
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
        label = np.where(keep[b], label.reshape(-1) - int((~keep[b]).any()), -1)  # the invalid key (-1) sorts first
        if edge_step is not None and keep[b].any():
            rgb = np.maximum(image[b], 1e-12 * max(level, 1e-30))  # (3, H, W)
            grey = rgb.mean(0)
            chroma = np.stack([np.log(rgb[0] / rgb[1]), np.log(rgb[2] / rgb[1])], -1)
            noise = code_noise(grey / max(level, 1e-30))
            label = join_shading_cuts(label.reshape(H, W), np.log(grey), chroma, noise, geometry[b].reshape(H, W),
                                      edge_step, edge_chroma).reshape(-1)
        out[b] = label
    return torch.from_numpy(out).to(g.mask.device).view(B, H, W)


def code_noise(relative: np.ndarray) -> np.ndarray:
    """The standard deviation of the log of a linear value ``relative`` (of the image's white)
    that 8-bit sRGB codes leave: a third of a code times ``d ln I / d code = 2.4 / (code + 14)``
    on the curve (5% of the value at black, 0.3% at white)."""
    from selfsup.scenes.capture import linear_to_srgb

    code = 255 * linear_to_srgb(np.clip(relative, 0.0, 1.0))
    return 0.3 * 2.4 / (code + 14.0)


def tuned_segments(problem: FitProblem, tuning: Tuning, geometry: Tensor | None = None) -> Tensor:
    """:func:`albedo_segments` ``(B, H, W)`` with the segmentation's constants of ``tuning``."""
    return albedo_segments(problem, tuning.albedo_segment_scale, geometry, tuning.albedo_edge_step,
                           tuning.albedo_edge_chroma)


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
    obs = LogShading(log_shading, pairs, log_shading, problem.gbuffer, fit_material(problem),
                     problem.falloff, scale.to(grey.dtype), segments, count)
    obs.observed = obs.differences(log_shading)  # the same view of the data as of every model
    return obs


def _tiled(obs: LogShading, count: int) -> LogShading:
    # Every image ``count`` times in a row.
    rep = lambda x: None if x is None else x.repeat_interleave(count, 0)  # noqa: E731
    rows = torch.arange(obs.gbuffer.batch_size, device=obs.gbuffer.points.device).repeat_interleave(count)
    m = obs.material
    material = Material(kd=rep(m.kd), ks=rep(m.ks), shininess=m.shininess if m.shininess.dim() == 0 else rep(m.shininess))
    return LogShading(rep(obs.log_shading), rep(obs.pairs), rep(obs.observed), obs.gbuffer.select(rows), material,
                      obs.falloff, rep(obs.scale), rep(obs.segments), obs.segment_count)


def glossy_material(kd: Tensor, gloss: Tensor | None, coat: Tensor | None = None) -> Material:
    """The albedo-free fit's reflectance: ``kd (B, H, W, 3)`` and, with ``gloss (B, 2)``
    (:attr:`~selfsup.estimation.problem.FitProblem.gloss`), a specular lobe of each image's
    ratio to the diffuse light (``ks (B, H, W, 1)``, one value an image, an expanded view) and
    shininess ``(B,)``; diffuse only where ``gloss`` is None. ``coat (B, H, W, 1)``: the diffuse
    light through a clear coat of that weight (:mod:`render.coat`), as rough as the lobe, or as
    :data:`COAT_SHININESS` without one."""
    B, H, W, _ = kd.shape
    if gloss is None:
        if coat is None:
            return Material(kd=kd)
        return Material(kd=kd, shininess=kd.new_full((B,), COAT_SHININESS), coat=coat.to(kd))
    gloss = gloss.to(kd)
    return Material(kd=kd, ks=gloss[:, 0].view(B, 1, 1, 1).expand(B, H, W, 1), shininess=gloss[:, 1].clamp_min(1e-3),
                    coat=None if coat is None else coat.to(kd))


def fit_material(problem: FitProblem) -> Material:
    """The albedo-free fit's reflectance of ``problem``: :func:`glossy_material` of its kd, its
    lobe (:attr:`~selfsup.estimation.problem.FitProblem.gloss`) and its coat (``material.coat``)."""
    return glossy_material(problem.material.kd, problem.gloss, problem.material.coat)
