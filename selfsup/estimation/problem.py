"""The fit problem: a batch of images to explain, and the linear part of the fit.

The image model is linear in the light intensities and the ambient once the light
positions are fixed (:class:`render.LightTransport`): every solver re-solves them in
closed form by weighted least squares at each position (variable projection), so
the non-linear search runs over the ``3 L`` position coordinates only. This module
holds the problem (:class:`FitProblem`), the result (:class:`Fit`), that closed-form
solve (:func:`solve_at`) and the robust (Cauchy) weights and loss.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from render import GBuffer, Material, light_transport
from selfsup.scenes.indirect import indirect_columns
from selfsup.estimation.options import RefineOptions
from selfsup.linear import basis_images, intensity_design, solve_design

__all__ = ["FitProblem", "Fit", "subsample", "centre_and_size", "gbuffer_centre_and_size", "solve_linear", "reweighted", "solve_at", "robust_loss",
           "basis_columns", "cauchy_scale", "irls_weights", "design_columns", "transport_maps"]


@dataclass
class FitProblem:
    """One batch of images to explain.

    Attributes:
        gbuffer: ``points/normals (B, H, W, 3)``, ``mask (B, H, W)``, intrinsics ``(B, 3, 3)``.
        material: ``kd (B, H, W, 3)``, ``ks (B, H, W, 1|3)`` or None, shininess.
        image: observed linear RGB ``(B, 3, H, W)``.
        ambient: known ambient ``(B, 3)``, or None to estimate it.
        falloff, shadows: renderer options (see :func:`render.render`).
        indirect: each light's basis images include its indirect light
            (:func:`selfsup.indirect.indirect_columns`). The Jacobians leave its
            derivative out, so fits with it on are approximate; model selection
            only evaluates it (``estimate.indirect``).
        normal_tilt: ``(B, H, W)`` variance (radians^2, per tilt axis) of each normal's
            error where the normals were fitted to noisy depth
            (:func:`selfsup.estimation.normals.plane_fit`), zero where exact; None: every normal
            exact. Only :func:`position_covariance` reads it.
        shadow_options: the shadow method's options (:mod:`render.shadows`), None
            for its defaults.
        cropped: ``(B,)`` bool, the images that are a crop of their frame
            (:func:`selfsup.estimation.prepare.cropped_to_depth`: an object in the dark),
            whose lens's vignetting the albedo-free fit does not look for; None: none is.
        gloss: ``(B, 2)``: the albedo-free fit's specular lobe of each image, the ratio of its
            peak to the diffuse light (``ks / kd``, one for the frame) and its shininess
            (:func:`selfsup.estimation.albedo_free.choose_gloss`); a ratio of 0: diffuse only.
            None: every image diffuse only.
    """

    gbuffer: GBuffer
    material: Material
    image: Tensor
    ambient: Tensor | None = None
    falloff: str = "inverse_square"
    shadows: str = "epipolar"
    indirect: bool = False
    normal_tilt: Tensor | None = None
    shadow_options: object | None = None
    cropped: Tensor | None = None
    gloss: Tensor | None = None
    _median: Tensor | None = field(default=None, init=False, repr=False, compare=False)
    _noise: Tensor | None = field(default=None, init=False, repr=False, compare=False)
    # Median and noise level of each subsample (by stride) already found: the solvers
    # subsample selections and tilings of one batch again and again.
    _coarse: dict[int, tuple[Tensor, Tensor]] = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def batch(self) -> int:
        return self.image.shape[0]

    def median_observed(self) -> Tensor:
        """``(B,)`` median observed value on valid pixels; kept once found (the robust
        loss's scale needs it at every evaluation, 5% of an estimate's time)."""
        if self._median is None:
            mask = self.gbuffer.mask[:, None].expand_as(self.image)
            observed = torch.where(mask, self.image, torch.full_like(self.image, float("nan")))
            self._median = observed.flatten(1).nanmedian(1).values
        return self._median

    def noise_level(self) -> Tensor:
        """``(B,)`` robust standard deviation of the image noise: ``1.4826 median|d| / sqrt(6)``
        of second differences ``d = I(x-1) - 2 I(x) + I(x+1)`` along rows of three valid
        pixels (a linear shading ramp cancels; edges are too few to move the median);
        about the shading's curvature on a clean image. Kept once found."""
        if self._noise is None and self.image.shape[-1] < 3:  # no row of three pixels: no floor
            self._noise = self.image.new_zeros(self.image.shape[0])
        if self._noise is None:
            mask = self.gbuffer.mask
            valid = (mask[..., :-2] & mask[..., 1:-1] & mask[..., 2:])[:, None].expand(-1, self.image.shape[1], -1, -1)
            second = self.image[..., :-2] - 2 * self.image[..., 1:-1] + self.image[..., 2:]
            second = torch.where(valid, second.abs(), torch.full_like(second, float("nan")))
            noise = 1.4826 / math.sqrt(6) * second.flatten(1).nanmedian(1).values
            self._noise = torch.nan_to_num(noise, nan=0.0)  # no three valid pixels in a row: no floor
        return self._noise

    def select(self, index: Tensor) -> "FitProblem":
        """The images ``index`` (a 1-D long tensor), repeats allowed; ``self`` when
        ``index`` is ``0 .. B-1`` in order (the usual case inside a solver loop)."""
        if index.numel() == self.batch and bool((index == torch.arange(self.batch, device=index.device)).all()):
            return self
        g, m = self.gbuffer, self.material
        shin = m.shininess if m.shininess.dim() == 0 else m.shininess[index]
        selected = FitProblem(
            g.select(index),
            Material(kd=m.kd[index], ks=None if m.ks is None else m.ks[index], shininess=shin,
                     coat=None if m.coat is None else m.coat[index], coat_f0=m.coat_f0),
            self.image[index], None if self.ambient is None else self.ambient[index], self.falloff, self.shadows,
            self.indirect, None if self.normal_tilt is None else self.normal_tilt[index], self.shadow_options,
            None if self.cropped is None else self.cropped[index],
            None if self.gloss is None else self.gloss[index],
        )
        # Each image's median is its own: the selection's are these rows (a sort of every
        # image's values each time was 7% of a batched estimate's GPU time).
        selected._median = None if self._median is None else self._median[index]
        selected._noise = None if self._noise is None else self._noise[index]
        selected._coarse = {stride: (median[index], noise[index]) for stride, (median, noise) in self._coarse.items()}
        return selected

    def with_shadows(self, shadows: str, options=None) -> "FitProblem":
        """The same images under another shadow method, with its ``options`` (None: defaults)."""
        return self._changed(shadows=shadows, shadow_options=options)

    def with_material(self, material: Material) -> "FitProblem":
        """The same images with another reflectance (the same observations: medians and noise levels kept)."""
        return self._changed(material=material)

    def with_gloss(self, gloss: Tensor | None) -> "FitProblem":
        """The same images with the albedo-free fit's specular lobe ``gloss (B, 2)`` (ratio,
        shininess; None: diffuse only)."""
        return self._changed(gloss=gloss)

    def with_coat(self, coat: Tensor | None) -> "FitProblem":
        """The same images with their diffuse light through a clear coat of weight ``coat
        (B, H, W, 1)`` (0: none; :mod:`render.coat`), or with none (None)."""
        return self._changed(material=dataclasses.replace(self.material, coat=coat))

    def with_indirect(self, indirect: bool = True) -> "FitProblem":
        """The same images with (or without) each light's indirect light in its basis images."""
        return self._changed(indirect=indirect)

    def _changed(self, **changes) -> "FitProblem":
        # dataclasses.replace, keeping the medians and noise levels found (it would drop them).
        changed = dataclasses.replace(self, **changes)
        changed._median, changed._noise, changed._coarse = self._median, self._noise, self._coarse
        return changed

    @staticmethod
    def cat(problems: list["FitProblem"]) -> "FitProblem":
        """One batch of same-sized problems (the inverse of :meth:`select`); a missing ks
        becomes zero, ks channels and shininess are broadcast per pixel. Falloff, shadows
        (and their options) and whether the ambient is known follow the first problem; a
        missing ``normal_tilt`` becomes zero (exact normals) beside one that is given."""
        def per_pixel(m: Material, value: Tensor | None, channels: int | None = None) -> Tensor:
            B, H, W = m.kd.shape[:3]
            if channels is not None:
                return m.kd.new_zeros(B, H, W, channels) if value is None else value.expand(B, H, W, channels)
            return value.reshape(-1, 1, 1).expand(B, H, W) if value.dim() < 3 else value

        g = [p.gbuffer for p in problems]
        m = [p.material for p in problems]
        first = problems[0]
        return FitProblem(
            GBuffer(torch.cat([x.points for x in g]), torch.cat([x.normals for x in g]), torch.cat([x.mask for x in g]),
                    None if g[0].intrinsics is None else torch.cat([x.intrinsics for x in g])),
            Material(kd=torch.cat([x.kd for x in m]), ks=torch.cat([per_pixel(x, x.ks, 3) for x in m]),
                     shininess=torch.cat([per_pixel(x, x.shininess) for x in m]),
                     coat=None if all(x.coat is None for x in m) else torch.cat([per_pixel(x, x.coat, 1) for x in m]),
                     coat_f0=m[0].coat_f0),
            torch.cat([p.image for p in problems]),
            None if first.ambient is None else torch.cat([p.ambient for p in problems]), first.falloff, first.shadows,
            first.indirect,
            None if all(p.normal_tilt is None for p in problems) else torch.cat(
                [p.image.new_zeros(p.image.shape[0], *p.image.shape[2:]) if p.normal_tilt is None else p.normal_tilt
                 for p in problems]),
            first.shadow_options,
            None if all(p.cropped is None for p in problems) else torch.cat(
                [torch.zeros(p.batch, dtype=torch.bool, device=p.image.device) if p.cropped is None else p.cropped
                 for p in problems]),
            None if all(p.gloss is None for p in problems) else torch.cat(
                [p.image.new_zeros(p.batch, 2) if p.gloss is None else p.gloss for p in problems]),
        )


def subsample(problem: FitProblem, stride: int) -> FitProblem:
    """Every ``stride``-th pixel of every row and column (no averaging across edges); K follows."""
    if stride == 1:
        return problem
    g, m, s = problem.gbuffer, problem.material, stride
    K = None
    if g.intrinsics is not None:
        # Pixel (i*s, j*s) becomes (i, j): u' = u / s, v' = v / s.
        scale = torch.tensor([1 / s, 1 / s, 1.0], dtype=g.intrinsics.dtype, device=g.intrinsics.device)
        K = g.intrinsics * scale[:, None]
    shin = m.shininess[:, ::s, ::s] if m.shininess.dim() == 3 else m.shininess
    coarse = dataclasses.replace(
        problem,
        gbuffer=GBuffer(g.points[:, ::s, ::s], g.normals[:, ::s, ::s], g.mask[:, ::s, ::s], K),
        material=Material(kd=m.kd[:, ::s, ::s], ks=None if m.ks is None else m.ks[:, ::s, ::s], shininess=shin,
                          coat=None if m.coat is None else m.coat[:, ::s, ::s], coat_f0=m.coat_f0),
        image=problem.image[:, :, ::s, ::s],
        normal_tilt=None if problem.normal_tilt is None else problem.normal_tilt[:, ::s, ::s],
    )
    # Its own median and noise level (kept by the problem it came from): a noise level
    # from every stride-th pixel holds the shading's curvature over stride pixels.
    if stride not in problem._coarse:
        problem._coarse[stride] = (coarse.median_observed(), coarse.noise_level())
    coarse._median, coarse._noise = problem._coarse[stride]
    return coarse


@dataclass
class Fit:
    """Result for a batch: ``position (B, L, 3)``, ``intensity (B, L, 3)``,
    ``ambient (B, 3)``, ``cost (B,)`` (robust weighted SSE at full resolution),
    ``model (B, 3, H, W)``, ``iterations (B,)``, ``rss (B,)`` (plain SSE), ``n (B,)``
    (valid values used)."""

    position: Tensor
    intensity: Tensor
    ambient: Tensor
    cost: Tensor
    model: Tensor
    iterations: Tensor
    rss: Tensor
    n: Tensor


def centre_and_size(problem: FitProblem) -> tuple[Tensor, Tensor]:
    """Centroid ``(B, 3)`` and size ``(B,)`` (bounding-box diagonal, at least 1e-6) of the valid points."""
    return gbuffer_centre_and_size(problem.gbuffer)


def gbuffer_centre_and_size(gbuffer: GBuffer) -> tuple[Tensor, Tensor]:
    """:func:`centre_and_size` of a G-buffer's valid points."""
    centre, lo, hi = gbuffer.extent()
    return centre, (hi - lo).norm(dim=-1).clamp_min(1e-6)


def basis_columns(problem: FitProblem, diffuse: Tensor, specular: Tensor | None) -> Tensor:
    # Per-channel basis images (B, 3, L, H, W) of unit lights: kd_c D_i + ks_c S_i, plus
    # the diffuse light's indirect light where the problem models it.
    columns = basis_images(problem.material.kd, problem.material.ks, diffuse, specular)
    if problem.indirect:
        columns = columns + indirect_columns(problem.gbuffer, problem.material.kd, diffuse)
    return columns


def cauchy_scale(problem: FitProblem, options: RefineOptions) -> Tensor:
    # The robust loss's scale (B,): robust_scale x the median observed value on valid
    # pixels, at least robust_noise_floor x the noise level.
    scale = options.robust_scale * problem.median_observed().clamp_min(1e-6)
    if options.robust_noise_floor > 0:
        scale = torch.maximum(scale, options.robust_noise_floor * problem.noise_level())
    return scale


def irls_weights(problem: FitProblem, residual: Tensor | None, options: RefineOptions, scale: Tensor | None = None
             ) -> Tensor:
    # IRLS weights (B, 3, H, W): the valid mask, times Cauchy weights of the residual;
    # ``scale`` (B,): the problem's cauchy_scale, if the caller already has it.
    mask = problem.gbuffer.mask[:, None].to(problem.image.dtype).expand_as(problem.image)
    if residual is None or not options.robust:
        return mask
    scale = cauchy_scale(problem, options) if scale is None else scale
    return mask / (1 + (residual / scale[:, None, None, None]) ** 2)


def solve_linear(problem: FitProblem, diffuse: Tensor, specular: Tensor | None, weights: Tensor,
                 design: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Closed-form intensities and ambient for fixed light transport.

    Args:
        diffuse, specular: ``(B, L, H, W)`` transport maps (specular may be None).
        weights: ``(B, 3, H, W)`` per-value weights (0 on invalid pixels).
        design: these maps' least-squares columns (:func:`selfsup.linear.intensity_design`
            of their basis images), if the caller has them: solves that differ in
            their weights alone share them.

    Returns:
        intensity ``(B, L, 3)`` (>= 0), ambient ``(B, 3)`` (the known one if given,
        else solved, >= 0) and the model image ``(B, 3, H, W)``.
    """
    a = design_columns(problem, diffuse, specular) if design is None else design
    intensity, ambient, model = solve_design(a, problem.material.kd, problem.image, weights, problem.ambient)
    return intensity, ambient, model * problem.gbuffer.mask[:, None]


def design_columns(problem: FitProblem, diffuse: Tensor, specular: Tensor | None) -> Tensor:
    # The least-squares columns (B, 3, k, H*W) of transport maps (B, L, H, W).
    return intensity_design(basis_columns(problem, diffuse, specular), problem.material.kd, problem.ambient)


def transport_maps(problem: FitProblem, position: Tensor, specular: bool):
    t = light_transport(problem.gbuffer, problem.material, position, falloff=problem.falloff,
                        shadows=problem.shadows, shadow_options=problem.shadow_options, specular=specular)
    return t.diffuse, t.specular


def reweighted(problem: FitProblem, diffuse: Tensor, specular: Tensor | None, options: RefineOptions,
               passes: int | None = None, design: Tensor | None = None) -> Tensor:
    """IRLS weights ``(B, 3, H, W)`` of the robust fit of fixed transport maps ``(B, L, H, W)``:
    ``passes`` (``options.irls_passes`` by default) reweightings from the plain
    least-squares solve; the valid mask alone when ``options.robust`` is off. The
    solves share one least-squares design (``design``, if the caller has it)."""
    weights = irls_weights(problem, None, options)
    scale = cauchy_scale(problem, options) if options.robust else None
    passes = (passes or options.irls_passes) if options.robust else 0
    if passes and design is None:
        design = design_columns(problem, diffuse, specular)
    for _ in range(passes):
        _, _, model = solve_linear(problem, diffuse, specular, weights, design)
        weights = irls_weights(problem, model - problem.image, options, scale)
    return weights


def solve_at(problem: FitProblem, position: Tensor, options: RefineOptions, weights: Tensor | None = None,
             passes: int | None = None):
    """Solve intensities/ambient at ``position (B, L, 3)``; returns
    ``(cost (B,), intensity, ambient, model, weights, diffuse, specular)``.

    Given no ``weights``, the robust fit reweights ``passes`` times
    (``options.irls_passes`` by default) from the plain least-squares solve.
    """
    diffuse, specular = transport_maps(problem, position, options.specular)
    design = design_columns(problem, diffuse, specular)
    if weights is None:
        weights = reweighted(problem, diffuse, specular, options, passes, design)
    intensity, ambient, model = solve_linear(problem, diffuse, specular, weights, design)
    cost = (weights * (model - problem.image) ** 2).flatten(1).sum(1)
    return cost, intensity, ambient, model, weights, diffuse, specular


def robust_loss(problem: FitProblem, model: Tensor, options: RefineOptions) -> Tensor:
    """Cauchy loss ``(B,)`` of the residual, ``sum c^2 log(1 + (r/c)^2)`` over valid values
    (plain SSE when ``options.robust`` is off); comparable across candidate fits."""
    mask = problem.gbuffer.mask[:, None].expand_as(problem.image)
    residual = (model - problem.image) * mask
    if not options.robust:
        return residual.pow(2).flatten(1).sum(1)
    c = cauchy_scale(problem, options)
    return (c[:, None] ** 2 * torch.log1p((residual.flatten(1) / c[:, None]) ** 2)).sum(1)
