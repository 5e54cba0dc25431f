"""Per-image refinement of point lights: Levenberg-Marquardt, Adam, the paper's gradient descent.

The image model is linear in the light intensities and the ambient once the light
positions are fixed (:class:`render.LightTransport`). All three optimisers use
that: the intensities and (unknown) ambient are re-solved in closed form by
weighted least squares at every position (variable projection), so the
non-linear search runs over the ``3 L`` position coordinates only.

- ``lm``: damped Gauss-Newton on the positions (the step of the variable-projection
  problem). The Jacobian of the image with respect to the positions is exact for
  the shading and a forward difference for cast shadows
  (:func:`render.light_transport_jacobian`); each light's maps depend on its own
  position only, so the shadow differences take 3 sweeps whatever ``L``.
- ``adam`` / ``gd``: first-order steps on the same projected objective, its
  gradient by autograd through the renderer (shadows included); ``gd`` is the
  paper's (rate 0.02 in scene-scale units, stop at relative energy change 1e-4).

Every image of the batch stops on its own. The robust option reweights
residuals (Cauchy, IRLS) so highlights and albedo errors the model lacks do not
pull the lights. Positions move in units of the scene size, so nothing assumes
an absolute scale.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from render import GBuffer, Material, light_transport, light_transport_jacobian
from selfsup.indirect import indirect_columns
from selfsup.linear import basis_images, intensity_design, solve_design

__all__ = ["FitProblem", "RefineOptions", "Fit", "refine", "search", "solve_linear", "reweighted", "evaluate", "grid_candidates",
           "robust_loss", "position_covariance", "subsample", "spread_best", "scene_frame", "position_blocks",
           "albedo_scores", "normal_tilt_scores", "tilt_axes"]


RUNAWAY_SIZES = 10.0  # the LM stops an image whose light is this many scene sizes from the centre


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
            (:func:`render.geometry.plane_fit`), zero where exact; None: every normal
            exact. Only :func:`position_covariance` reads it.
        shadow_options: the shadow method's options (:mod:`render.shadows`), None
            for its defaults.
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
class RefineOptions:
    """Optimiser settings (mirrors ``configs/refine/*.yaml``).

    ``method``: ``lm`` | ``adam`` | ``gd``. ``max_iters`` per pyramid level,
    ``strides``: coarse-to-fine pixel strides. ``tol``: stop when the relative cost
    decrease of an accepted step falls below it (``gd`` uses the paper's 1e-4);
    ``step_tol`` (``lm``): or when it moves every light less than this, in scene sizes.
    ``robust``: Cauchy IRLS with scale ``robust_scale`` x median observed value, at
    least ``robust_noise_floor`` x the image's noise level (:meth:`FitProblem.noise_level`:
    a scale below the noise would treat good pixels as outliers);
    ``irls_passes``: reweighting passes that solve the intensities and ambient of
    a robust fit at fixed positions (one pass leaves the outliers' pull in the
    closed-form solve, which skews every loss compared between candidates).
    ``fd_step``: forward-difference step of the shadow Jacobian, in scene sizes. ``learning_rate``: adam/gd.
    """

    method: str = "lm"
    max_iters: tuple[int, ...] = (30, 10)
    strides: tuple[int, ...] = (4, 1)
    tol: float = 1e-4
    step_tol: float = 1e-4
    robust: bool = True
    robust_scale: float = 0.2
    robust_noise_floor: float = 1.0
    irls_passes: int = 4
    fd_step: float = 1e-3
    learning_rate: float = 0.02
    specular: bool = True

    def __post_init__(self):
        if self.method not in ("lm", "adam", "gd"):
            raise ValueError(f"method must be lm, adam or gd, got {self.method!r}")
        if len(self.max_iters) != len(self.strides):
            raise ValueError(f"max_iters {self.max_iters} and strides {self.strides} must have the same length")
        if not self.strides or any(s < 1 for s in self.strides) or any(i < 0 for i in self.max_iters):
            raise ValueError(f"strides need one level or more, each >= 1, and max_iters >= 0, got strides "
                             f"{self.strides} and max_iters {self.max_iters}")
        if not (self.fd_step > 0 and self.learning_rate > 0):  # 0: no shadow derivative, no first-order step
            raise ValueError(f"fd_step and learning_rate must be > 0, got {self.fd_step}, {self.learning_rate}")
        if not (self.tol >= 0 and self.step_tol >= 0):
            raise ValueError(f"tol and step_tol must be >= 0, got {self.tol}, {self.step_tol}")
        if self.irls_passes < 1:
            raise ValueError(f"irls_passes must be >= 1, got {self.irls_passes}")
        if not (self.robust_scale > 0 and self.robust_noise_floor >= 0):
            raise ValueError(f"robust_scale must be > 0 and robust_noise_floor >= 0, got {self.robust_scale}, "
                             f"{self.robust_noise_floor}")


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


def scene_frame(problem: FitProblem) -> tuple[Tensor, Tensor]:
    """Centroid ``(B, 3)`` and size ``(B,)`` (bounding-box diagonal, at least 1e-6) of the valid points."""
    centre, lo, hi = problem.gbuffer.extent()
    return centre, (hi - lo).norm(dim=-1).clamp_min(1e-6)


def _columns(problem: FitProblem, diffuse: Tensor, specular: Tensor | None) -> Tensor:
    # Per-channel basis images (B, 3, L, H, W) of unit lights: kd_c D_i + ks_c S_i, plus
    # the diffuse light's indirect light where the problem models it.
    columns = basis_images(problem.material.kd, problem.material.ks, diffuse, specular)
    if problem.indirect:
        columns = columns + indirect_columns(problem.gbuffer, problem.material.kd, diffuse)
    return columns


def _cauchy_scale(problem: FitProblem, options: RefineOptions) -> Tensor:
    # The robust loss's scale (B,): robust_scale x the median observed value on valid
    # pixels, at least robust_noise_floor x the noise level.
    scale = options.robust_scale * problem.median_observed().clamp_min(1e-6)
    if options.robust_noise_floor > 0:
        scale = torch.maximum(scale, options.robust_noise_floor * problem.noise_level())
    return scale


def _weights(problem: FitProblem, residual: Tensor | None, options: RefineOptions, scale: Tensor | None = None
             ) -> Tensor:
    # IRLS weights (B, 3, H, W): the valid mask, times Cauchy weights of the residual;
    # ``scale`` (B,): the problem's _cauchy_scale, if the caller already has it.
    mask = problem.gbuffer.mask[:, None].to(problem.image.dtype).expand_as(problem.image)
    if residual is None or not options.robust:
        return mask
    scale = _cauchy_scale(problem, options) if scale is None else scale
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
    a = _design(problem, diffuse, specular) if design is None else design
    intensity, ambient, model = solve_design(a, problem.material.kd, problem.image, weights, problem.ambient)
    return intensity, ambient, model * problem.gbuffer.mask[:, None]


def _design(problem: FitProblem, diffuse: Tensor, specular: Tensor | None) -> Tensor:
    # The least-squares columns (B, 3, k, H*W) of transport maps (B, L, H, W).
    return intensity_design(_columns(problem, diffuse, specular), problem.material.kd, problem.ambient)


def _transport(problem: FitProblem, position: Tensor, specular: bool):
    t = light_transport(problem.gbuffer, problem.material, position, falloff=problem.falloff,
                        shadows=problem.shadows, shadow_options=problem.shadow_options, specular=specular)
    return t.diffuse, t.specular


def reweighted(problem: FitProblem, diffuse: Tensor, specular: Tensor | None, options: RefineOptions,
               passes: int | None = None, design: Tensor | None = None) -> Tensor:
    """IRLS weights ``(B, 3, H, W)`` of the robust fit of fixed transport maps ``(B, L, H, W)``:
    ``passes`` (``options.irls_passes`` by default) reweightings from the plain
    least-squares solve; the valid mask alone when ``options.robust`` is off. The
    solves share one least-squares design (``design``, if the caller has it)."""
    weights = _weights(problem, None, options)
    scale = _cauchy_scale(problem, options) if options.robust else None
    passes = (passes or options.irls_passes) if options.robust else 0
    if passes and design is None:
        design = _design(problem, diffuse, specular)
    for _ in range(passes):
        _, _, model = solve_linear(problem, diffuse, specular, weights, design)
        weights = _weights(problem, model - problem.image, options, scale)
    return weights


def evaluate(problem: FitProblem, position: Tensor, options: RefineOptions, weights: Tensor | None = None,
             passes: int | None = None):
    """Solve intensities/ambient at ``position (B, L, 3)``; returns
    ``(cost (B,), intensity, ambient, model, weights, diffuse, specular)``.

    Given no ``weights``, the robust fit reweights ``passes`` times
    (``options.irls_passes`` by default) from the plain least-squares solve.
    """
    diffuse, specular = _transport(problem, position, options.specular)
    design = _design(problem, diffuse, specular)
    if weights is None:
        weights = reweighted(problem, diffuse, specular, options, passes, design)
    intensity, ambient, model = solve_linear(problem, diffuse, specular, weights, design)
    cost = (weights * (model - problem.image) ** 2).flatten(1).sum(1)
    return cost, intensity, ambient, model, weights, diffuse, specular


def _jacobians(problem: FitProblem, position: Tensor, intensity: Tensor, h: Tensor, specular: bool
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
    cols = _columns(problem, t.diffuse, t.specular)
    # d model_c / d p_ij = I_ic (kd_c dD_i/dp_j + ks_c dS_i/dp_j): (B, L, 3 coords, 3 channels, H, W)
    kd = problem.material.kd.permute(0, 3, 1, 2)[:, None, None]  # (B, 1, 1, 3, H, W)
    deriv = kd * jac.diffuse.permute(0, 1, 4, 2, 3)[:, :, :, None]
    if jac.specular is not None:
        ks = problem.material.ks.permute(0, 3, 1, 2)[:, None, None]
        deriv = deriv + ks * jac.specular.permute(0, 1, 4, 2, 3)[:, :, :, None]
    deriv = deriv * intensity[:, :, None, :, None, None]
    return cols, deriv.reshape(B, 3 * L, -1), t.diffuse


def _normal_equations(problem: FitProblem, j_pos: Tensor, cols: Tensor, weights: Tensor,
                      residual: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
    """Gauss-Newton normal matrix ``J^T W J (B, P + 3k, P + 3k)`` and, given ``residual``
    ``(B, 3, H, W)``, gradient ``J^T W r (B, P + 3k)`` of the model image over every
    parameter: the positions (``j_pos (B, P = 3L, 3*H*W)`` from :func:`_jacobians`) first,
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
    centre, size = scene_frame(problem)
    h = (options.fd_step * size)[:, None, None]  # (B, 1, 1)
    damping = torch.full((B,), 1e-3, dtype=position.dtype, device=position.device)
    active = torch.ones(B, dtype=torch.bool, device=position.device)
    iterations = torch.zeros(B, dtype=torch.long, device=position.device)
    sub, selected = problem, B  # the active images' problem
    scale = _cauchy_scale(problem, options)
    # One reweighting pass only: weights converged at a wrong start would silence the
    # very residuals that say where the light should move.
    cost, intensity, ambient, model, weights, _, _ = evaluate(problem, position, options, passes=1)
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
        cols_base, j_pos, _ = _jacobians(sub, pos, intensity[idx], h[idx], options.specular)
        jtj, jtr = _normal_equations(sub, j_pos, cols_base, w, model[idx] - sub.image)
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
        t_cost, t_int, t_amb, t_model, _, _, _ = evaluate(sub, trial, options, weights=w)
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
            new_w = _weights(sub, residual, options, scale[idx])
            weights[idx] = torch.where(pick[..., None], new_w, w)
            cost[idx] = torch.where(better, (new_w * residual**2).flatten(1).sum(1), cost[idx])
    return position, iterations


def _first_order(problem: FitProblem, position: Tensor, options: RefineOptions, max_iters: int) -> tuple[Tensor, Tensor]:
    B = position.shape[0]
    centre, size = scene_frame(problem)
    unit = ((position - centre[:, None]) / size[:, None, None]).detach().requires_grad_(True)
    tol = 1e-4 if options.method == "gd" else options.tol
    optimiser = (torch.optim.SGD([unit], lr=options.learning_rate) if options.method == "gd"
                 else torch.optim.Adam([unit], lr=options.learning_rate))
    _, _, _, _, weights, _, _ = evaluate(problem, position.detach(), options, passes=1)  # as in _lm
    norm = (weights * problem.image**2).flatten(1).sum(1).clamp_min(1e-30)
    previous = torch.full((B,), float("inf"), dtype=position.dtype, device=position.device)
    active = torch.ones(B, dtype=torch.bool, device=position.device)
    iterations = torch.zeros(B, dtype=torch.long, device=position.device)
    for _ in range(max_iters):
        if not active.any():
            break
        optimiser.zero_grad()
        diffuse, specular = _transport(problem, centre[:, None] + unit * size[:, None, None], options.specular)
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
        cost, intensity, ambient, model, weights, _, _ = evaluate(problem, position, options)
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


def robust_loss(problem: FitProblem, model: Tensor, options: RefineOptions) -> Tensor:
    """Cauchy loss ``(B,)`` of the residual, ``sum c^2 log(1 + (r/c)^2)`` over valid values
    (plain SSE when ``options.robust`` is off); comparable across candidate fits."""
    mask = problem.gbuffer.mask[:, None].expand_as(problem.image)
    residual = (model - problem.image) * mask
    if not options.robust:
        return residual.pow(2).flatten(1).sum(1)
    c = _cauchy_scale(problem, options)
    return (c[:, None] ** 2 * torch.log1p((residual.flatten(1) / c[:, None]) ** 2)).sum(1)


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
    size = scene_frame(coarse)[1]  # (B,)
    with torch.no_grad():
        positions = torch.cat([base[:, None].expand(B, G, -1, -1), cands[:, :, None]], 2)  # (B, G, L, 3)
        tiled = _tiled(ranked, G)
        _, _, _, model, _, _, _ = evaluate(tiled, positions.flatten(0, 1), options, passes=1)  # a coarse ranking
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


def position_covariance(problem: FitProblem, fit: Fit, options: RefineOptions, correlation_px: float = 1.0,
                        albedo_error: float = 0.0, albedo_block_px: int = 1, indirect_variation: float = 0.0,
                        indirect_length: float = 0.15, normal_error: bool = False) -> Tensor:
    """Gauss-Newton covariance ``(B, L, 3, 3)`` of each light's position.

    The Jacobian covers every parameter (positions, intensities, unknown ambient),
    so their trade-offs widen the positions' uncertainty; the noise variance is the
    residual's. ``correlation_px`` (pixels per independent residual) inflates it for
    spatially correlated residuals.

    ``albedo_error`` (0: the file's kd is exact) adds what an error of the given kd
    moves the lights by: an error of standard deviation ``albedo_error`` (albedo units),
    the same over each square block of ``albedo_block_px`` pixels, independent between
    blocks and channels (:func:`albedo_scores`). The fit takes up an albedo error
    partly in its parameters, where its residual cannot show it, so the residual's
    variance alone misses it (README, "Uncertainty under reflectance errors").

    ``indirect_variation`` (0: off; only where the ambient is unknown, ``problem.ambient``
    None) adds what light the model lacks moves the lights by, taking the fitted constant
    ambient for the mean of a smooth field: the light a surface point receives besides
    the point lights is ``ambient (1 + e(x))``, ``e`` a Gaussian random field over the 3D
    points of standard deviation ``indirect_variation`` and correlation length
    ``indirect_length`` (of the scene size), one value per block of ``albedo_block_px``
    pixels (:func:`indirect_field_scores`; README, "Uncertainty under indirect light").

    ``normal_error`` adds what the normals' error moves the lights by, where
    ``problem.normal_tilt`` gives its variance (normals fitted to noisy depth): every
    block of ``albedo_block_px`` pixels tilted as one, independently between blocks and
    the two tilt axes (:func:`normal_tilt_scores`; README, "Uncertainty under noisy
    depth").
    """
    if not (indirect_variation >= 0 and math.isfinite(indirect_variation) and 0 < indirect_length < math.inf):
        raise ValueError(f"indirect_variation must be a finite value >= 0 and indirect_length > 0, got "
                         f"{indirect_variation} and {indirect_length}")
    if albedo_error < 0 or not math.isfinite(albedo_error):
        raise ValueError(f"albedo_error must be a finite value >= 0, got {albedo_error}")
    B, L, _ = fit.position.shape
    _, size = scene_frame(problem)
    h = (options.fd_step * size)[:, None, None]
    cols, j_pos, diffuse = _jacobians(problem, fit.position, fit.intensity, h, options.specular)
    mask = problem.gbuffer.mask[:, None].expand_as(problem.image).to(j_pos.dtype)
    info, _ = _normal_equations(problem, j_pos, cols, mask)
    sigma2 = fit.rss / (fit.n - info.shape[1]).clamp_min(1) * correlation_px
    extras = []  # score covariances of the further error sources
    if albedo_error > 0:
        scores = albedo_scores(problem, fit, j_pos, cols, diffuse, mask, albedo_block_px)  # (B, P + 3k, 3 * blocks)
        extras.append(albedo_error**2 * scores @ scores.transpose(1, 2))
    if indirect_variation > 0 and problem.ambient is None:
        extras.append(indirect_field_scores(problem, fit, j_pos, cols, mask, albedo_block_px, indirect_variation,
                                            indirect_length))
    if normal_error and problem.normal_tilt is not None:
        scores = normal_tilt_scores(problem, fit, j_pos, cols, mask, albedo_block_px, options.specular)
        extras.append(scores @ scores.transpose(1, 2))
    return position_blocks(info, sigma2, L, sum(extras) if extras else None)


def normal_tilt_scores(problem: FitProblem, fit: Fit, j_pos: Tensor, cols: Tensor, weights: Tensor, block_px: int,
                       specular: bool, step: float = 1e-3) -> Tensor:
    """Scores ``(B, P + 3k, 2 * blocks)`` (axis-major) of an error of the normals: every
    normal of a square block of ``block_px`` pixels tilted by one angle about each of the
    two :func:`tilt_axes`, independent between blocks and axes, of standard deviation
    ``sqrt(problem.normal_tilt)`` at each pixel (at most 1 radian). Each is the block's
    :func:`block_scores` (every channel alike) of the model's change under a unit-variance
    tilt, a forward difference of ``step`` radians through the renderer (diffuse and, with
    ``specular``, specular; shadows do not move); such a tilt ``e`` of one block moves the
    fit by ``-info^-1 scores e`` (to first order), and the score covariance is
    ``scores scores^T``."""
    g = problem.gbuffer
    n = g.normals
    size = problem.normal_tilt.clamp(0, 1).sqrt()[:, None] * weights  # (B, 3, H, W)
    intensity = fit.intensity.transpose(1, 2)[..., None, None]  # (B, 3, L, 1, 1)
    model = (cols * intensity).sum(2)
    per_axis = []
    for axis in tilt_axes(n):
        tilted = dataclasses.replace(g, normals=torch.nn.functional.normalize(n + step * axis, dim=-1))
        t = light_transport(tilted, problem.material, fit.position, falloff=problem.falloff, shadows=problem.shadows,
                            shadow_options=problem.shadow_options, specular=specular)
        changed = (_columns(dataclasses.replace(problem, gbuffer=tilted), t.diffuse, t.specular) * intensity).sum(2)
        per_axis.append(block_scores(problem, j_pos, cols, (changed - model) / step * size, block_px,
                                     shared_channels=True))  # (B, n, blocks): one tilt for the channels
    return torch.cat(per_axis, 2)


def indirect_field_scores(problem: FitProblem, fit: Fit, j_pos: Tensor, cols: Tensor, weights: Tensor,
                          block_px: int, variation: float, length: float) -> Tensor:
    """Score covariance ``(B, P + 3k, P + 3k)`` of a relative variation ``e`` of the fitted
    ambient light over the scene: ``S K S^T``, ``S`` the blocks' scores for a change of
    the ambient by its own value in one block (every channel alike, :func:`block_scores`),
    ``K`` the field's covariance between the blocks' 3D centres,
    ``variation^2 exp(-|x - x'|^2 / (2 (length x scene size)^2))``."""
    g = problem.gbuffer
    derivative = problem.material.kd.permute(0, 3, 1, 2) * fit.ambient[:, :, None, None] * weights
    scores = block_scores(problem, j_pos, cols, derivative, block_px, shared_channels=True)  # (B, n, blocks)
    valid = g.mask.to(g.points.dtype)[:, None]  # (B, 1, H, W)
    points = torch.where(g.mask[..., None], g.points, torch.zeros_like(g.points)).permute(0, 3, 1, 2)
    sums = block_sums(torch.cat([points, valid], 1), block_px)  # (B, 4, blocks)
    centre = (sums[:, :3] / sums[:, 3:].clamp_min(1)).transpose(1, 2)  # (B, blocks, 3); empty blocks score 0
    _, size = scene_frame(problem)
    distance2 = torch.cdist(centre, centre).square() / (length * size)[:, None, None].square()
    kernel = variation**2 * torch.exp(-0.5 * distance2)
    return scores @ kernel.to(scores.dtype) @ scores.transpose(1, 2)


def tilt_axes(normals: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit axes ``(B, H, W, 3)`` across each normal ``(B, H, W, 3)``, orthogonal to
    it and to each other, turning smoothly over a surface: ``n x a`` with ``a`` the x
    axis (the y axis where ``n`` is within 26 degrees of x), then ``n x`` that one."""
    helper = torch.where(normals[..., :1].abs() < 0.9, normals.new_tensor([1.0, 0.0, 0.0]),
                         normals.new_tensor([0.0, 1.0, 0.0]))
    first = torch.nn.functional.normalize(torch.linalg.cross(normals, helper.expand_as(normals)), dim=-1)
    return first, torch.linalg.cross(normals, first)


def albedo_scores(problem: FitProblem, fit: Fit, j_pos: Tensor, cols: Tensor, diffuse: Tensor, weights: Tensor,
                  block_px: int) -> Tensor:
    """``J^T W dM/dkd`` summed over each square block of ``block_px`` pixels and channel:
    ``(B, P + 3k, 3 * blocks)`` (channel-major), the parameters (``P = 3 L`` positions, then
    ``k = L [+ 1]`` linear ones per channel) ordered as :func:`_normal_equations` orders
    them, from its ``j_pos``, ``cols`` and ``weights (B, 3, H, W)`` and the lights' diffuse
    transport ``diffuse (B, L, H, W)`` (all three as :func:`_jacobians` gives them). A kd error ``e`` that is
    constant over blocks moves the fit by ``-info^-1 scores e`` (to first order).

    ``dM_c/dkd_c`` is the ambient plus the lights' diffuse light (the specular term does
    not scale with kd; the indirect light's own dependence on kd is left out)."""
    ambient = problem.ambient if problem.ambient is not None else fit.ambient
    per_kd = ambient[:, :, None, None] + torch.einsum("blhw,blc->bchw", diffuse, fit.intensity)
    return block_scores(problem, j_pos, cols, per_kd * weights, block_px)


def block_scores(problem: FitProblem, j_pos: Tensor, cols: Tensor, derivative: Tensor, block_px: int,
                 shared_channels: bool = False) -> Tensor:
    """``J^T derivative`` summed over each square block of ``block_px`` pixels and channel:
    ``(B, P + 3k, 3 * blocks)`` (channel-major), for an error source that is one value per
    block and channel and changes model channel ``c`` by ``derivative (B, 3, H, W)`` (weights
    included) per unit; the parameters ordered as :func:`_normal_equations` orders them.
    ``shared_channels``: one value per block for every channel alike, ``(B, P + 3k, blocks)``."""
    B, P, _ = j_pos.shape
    H, W = problem.image.shape[-2:]
    per_kd = derivative.reshape(B, 1, 3, H, W)
    design = intensity_design(cols, problem.material.kd, problem.ambient)  # (B, 3, k, N)
    k = design.shape[2]
    position_part = j_pos.view(B, P, 3, H, W) * per_kd  # (B, P, 3, H, W)
    linear_part = design.view(B, 3, k, H, W).transpose(1, 2) * per_kd  # (B, k, 3, H, W): channel c's own parameters

    def pooled(x: Tensor) -> Tensor:  # (B, n, 3, H, W) -> (B, n, 3, blocks)
        return block_sums(x.reshape(B, -1, H, W), block_px).view(B, x.shape[1], 3, -1)

    positions, linear = pooled(position_part), pooled(linear_part)  # (B, P, 3, n_b), (B, k, 3, n_b)
    n_b = positions.shape[-1]
    # Channel c's kd error touches channel c's linear parameters alone: rows P + c k .. P + c k + k - 1.
    linear_rows = linear.new_zeros(B, 3, k, 3, n_b)
    for c in range(3):
        linear_rows[:, c, :, c] = linear[:, :, c]
    scores = torch.cat([positions, linear_rows.view(B, 3 * k, 3, n_b)], 1)  # (B, P + 3k, 3, n_b)
    return scores.sum(2) if shared_channels else scores.reshape(B, P + 3 * k, 3 * n_b)


def block_sums(x: Tensor, block_px: int) -> Tensor:
    """Sums ``(B, C, blocks)`` of ``x (B, C, H, W)`` over square blocks of ``block_px`` pixels,
    row-major; the blocks cut by the image's right and bottom borders hold what is left
    of them (summed as they are, not their mean times ``block_px^2``)."""
    b = max(1, int(block_px))
    return torch.nn.functional.avg_pool2d(x, b, b, ceil_mode=True, divisor_override=1).flatten(2)


def position_blocks(info: Tensor, sigma2: Tensor, n_lights: int, extra: Tensor | None = None) -> Tensor:
    """Each light's ``(B, L, 3, 3)`` block of the covariance ``sigma2 (B,) x info^-1`` of a
    Gauss-Newton information matrix ``info (B, k, k)`` whose first ``3 L`` parameters
    are the lights' positions, plus ``info^-1 extra info^-1`` for a further error source
    of score covariance ``extra (B, k, k)``; in ``info``'s dtype.

    The parameters' curvatures differ by many orders of magnitude (positions in the
    file's units, intensities that grow with the distance squared, the ambient), so
    ``info`` is inverted in float64 after scaling it to a unit diagonal, which makes
    the answer independent of the units. A pseudo-inverse of the raw matrix cut off
    every direction below float32's relative precision of the largest curvature: a
    distant light's position got almost no variance, and the same scene given in
    millimetres a position_std a hundred times too small. A direction the data do not
    constrain (a scaled eigenvalue under 1e-12) gets the variance of one that small,
    enormous rather than zero: unknown is not certain. It stays finite (at most the
    dtype's largest value), also where nothing has any curvature (a light that lights
    no pixel, its ambient given): a record must hold numbers, and inf beside 0 made NaN.
    """
    B, k, _ = info.shape
    matrix = info.double()
    diagonal = matrix.diagonal(dim1=-2, dim2=-1)
    # A parameter with no curvature at all is scaled by 1: its row is zero either way.
    scale = torch.where(diagonal > 0, diagonal, torch.ones_like(diagonal)).rsqrt()  # (B, k)
    eigenvalues, vectors = torch.linalg.eigh(matrix * scale[:, :, None] * scale[:, None, :])
    # With any curvature the unit diagonal makes the largest eigenvalue at least 1; with
    # none (a zero matrix) 1 stands in for it.
    floor = 1e-12 * eigenvalues.amax(-1, keepdim=True).clamp_min(1.0)
    scaled_inverse = (vectors / eigenvalues.clamp_min(floor)[:, None, :]) @ vectors.transpose(-1, -2)
    inverse = scaled_inverse * scale[:, :, None] * scale[:, None, :]
    cov = inverse * sigma2.double()[:, None, None]
    if extra is not None:
        cov = cov + inverse @ extra.double() @ inverse
    largest = torch.finfo(info.dtype).max
    cov = cov.clamp(-largest, largest).to(info.dtype)
    pos_cov = cov[:, : 3 * n_lights, : 3 * n_lights].reshape(B, n_lights, 3, n_lights, 3)
    return torch.stack([pos_cov[:, i, :, i, :] for i in range(n_lights)], 1)
