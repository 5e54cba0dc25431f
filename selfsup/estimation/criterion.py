"""Model selection: which light count and terms explain an image best.

Every candidate model (1 .. ``max_lights`` lights, with or without the specular
term and the clear coat) is judged by :func:`bic` of its robust loss on the
criterion's problem (:func:`judged_problem`: a subsample, cast shadows, each light's
indirect light where the file leaves light unaccounted for), counting one
independent sample per block of :func:`block_px` pixels. Weak lights need more
evidence (:func:`shadow_gain`, :func:`light_shares`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from render import light_transport
from render.shadows import EpipolarShadowOptions
from selfsup.estimation.options import EstimateOptions, RefineOptions
from selfsup.estimation.problem import Fit, FitProblem, reweighted, robust_loss, solve_at, solve_linear, subsample

__all__ = ["Candidate", "bic", "effective_samples", "block_px", "judged_problem", "criterion_light", "candidates",
           "shadow_gain", "light_shares", "specular_images", "fit_row", "stacked_fits", "by_model"]


@dataclass
class Candidate:
    """One fitted model: its fit, light count, specular switch and criterion value."""

    fit: Fit
    n_lights: int
    specular: bool
    criterion: float
    covariance: Tensor | None = None  # (L, 3, 3) when the fit found its own (the albedo-free one's)
    reflectance: str = "given"  # which data the fit explained: "given" (the image) | "albedo_free"
    samples: float | None = None  # the independent samples the criterion counted (effective_samples)
    coat: bool = False  # whether the specular pixels' diffuse light went through a clear coat (render.Material.coat)
    evidence: float | None = None  # the ambient-only model's criterion less this one's (albedo-free fits)
    # ... judged at the sensor's noise (the fit's own scale), not the frame's misfit: a sure network's
    # lights must explain the shading as a lamp's would, or the frame is searched (estimate_albedo_free)
    noise_evidence: float | None = None
    vignetting: float | None = None  # the corner light loss of the lens the fit took out (albedo-free fits)
    highlight_pixels: int | None = None  # pixels left out of the placement as a highlight (albedo-free fits)
    bounce_share: float | None = None  # the modelled light's share bounced off the surfaces (albedo-free fits with it)
    gloss: tuple[float, float] | None = None  # the albedo-free fit's specular lobe (ratio to the diffuse, shininess), if any


def block_px(options: EstimateOptions, width: int, albedo_free: bool = False) -> int:
    """Side in pixels of the criterion's independent-sample block for an image ``width``
    pixels wide: ``options.tuning.block_width x width`` (``albedo_free_block_width`` for the
    albedo-free fit), rounded, at least 1 (a procedural sensor-noise scene rendered at
    320x240 got a spurious second light with 8-pixel blocks and the right one with 16,
    as at 160x120 with 8)."""
    share = options.tuning.albedo_free_block_width if albedo_free else options.tuning.block_width
    return max(1, round(share * width))


def bic(loss: float, n_values: int, n_params: int, block_px: int) -> float:
    """Bayesian information criterion on ``n_values / block_px^2`` independent samples.

    ``loss`` is the (robust) sum of squared residuals over ``n_values`` values.
    """
    n_eff = effective_samples(n_values, n_params, block_px)
    return n_eff * math.log(max(loss, 1e-30) / n_values) + n_params * math.log(n_eff)


def effective_samples(n_values: int, n_params: int, block_px: int) -> float:
    """The independent samples :func:`bic` counts: one per ``block_px^2`` values, at
    least ``n_params + 2``."""
    return max(n_values / block_px**2, n_params + 2.0)


def shadow_gain(problem: FitProblem, position: Tensor, light: Tensor, specular: bool, options: RefineOptions
                ) -> Tensor:
    """Relative robust-loss decrease ``(B,)`` when light ``light (B,)`` of ``position (B, L, 3)``
    casts its shadows (epipolar; every other light casts its own in both fits),
    intensities and ambient solved with converged reweighting each time.

    Evidence that a weak light is a light: its shadows are in the image. A light that
    stands in for what the model lacks (indirect light, albedo errors, sensor noise)
    predicts shadows that are not there, and the loss rises. On the devset and two
    procedural sets (2026-11-23) the weak stand-ins gave -0.001 to -0.73, true second
    lights of 5-7% of the light +0.03 and +0.09 (two others +0.002 and -0.004).
    """
    shadowed = light_transport(problem.gbuffer, problem.material, position, falloff=problem.falloff,
                               shadows="epipolar", specular=specular,
                               shadow_options=EpipolarShadowOptions(scene_thickness=None))  # as it was measured
    bare = light_transport(problem.gbuffer, problem.material, position, falloff=problem.falloff, shadows="none",
                           specular=specular)
    pick = torch.nn.functional.one_hot(light, position.shape[1]).to(position.dtype)[..., None, None]  # (B, L, 1, 1)
    losses = []
    for diffuse, spec in ((pick * bare.diffuse + (1 - pick) * shadowed.diffuse,
                           None if shadowed.specular is None else pick * bare.specular + (1 - pick) * shadowed.specular),
                          (shadowed.diffuse, shadowed.specular)):
        _, _, model = solve_linear(problem, diffuse, spec, reweighted(problem, diffuse, spec, options))
        losses.append(robust_loss(problem, model, options))
    without, with_shadows = losses
    return (without - with_shadows) / without.clamp_min(1e-30)


def light_shares(problem: FitProblem, fit: Fit, specular: bool) -> Tensor:
    """Each light's share ``(B, L)`` of the direct light the fit renders (summed over pixels)."""
    t = light_transport(problem.gbuffer, problem.material, fit.position, falloff=problem.falloff,
                        shadows=problem.shadows,
                        shadow_options=problem.shadow_options, specular=specular)
    kd = problem.material.kd.permute(0, 3, 1, 2)[:, :, None]  # (B, 3, 1, H, W)
    per_light = kd * t.diffuse[:, None]
    if t.specular is not None:
        per_light = per_light + problem.material.ks.permute(0, 3, 1, 2)[:, :, None] * t.specular[:, None]
    energy = (per_light.sum((-1, -2)) * fit.intensity.transpose(1, 2)).sum(1)  # (B, L)
    return energy / energy.sum(-1, keepdim=True).clamp_min(1e-30)


def specular_images(problem: FitProblem) -> Tensor:
    """Whether each image's material has a specular term: ``(B,)`` bool."""
    ks = problem.material.ks
    if ks is None:
        return torch.zeros(problem.batch, dtype=torch.bool, device=problem.image.device)
    return (ks > 0).flatten(1).any(1)


def fit_row(fit: Fit, i: int) -> Fit:
    return Fit(*(getattr(fit, f.name)[i : i + 1] for f in dataclasses.fields(Fit)))


def stacked_fits(fits: list[Fit]) -> Fit:
    return Fit(*(torch.cat([getattr(f, name.name) for f in fits]) for name in dataclasses.fields(Fit)))


def candidates(problem: FitProblem, fit: Fit, n_lights: int, specular: list[bool], options: EstimateOptions
                ) -> list[Candidate]:
    # Each image's fitted model and its criterion: robust loss, 6 parameters per light,
    # the unknown ambient (3) and the specular switch, on the problem the criterion judges.
    judged = judged_problem(problem, options)
    if judged is problem:
        model = fit.model
    else:
        model = solve_at(judged, fit.position, replace(options.tuning.refine, specular=any(specular)))[3]
    loss = robust_loss(judged, model, options.tuning.refine).tolist()
    n_values = (judged.gbuffer.mask.flatten(1).sum(1) * 3).tolist()
    ambient = 3 if problem.ambient is None else 0
    block = block_px(options, judged.image.shape[-1])
    out = []
    for i, spec in enumerate(specular):
        n_params = 6 * n_lights + ambient + int(spec)
        out.append(Candidate(fit_row(fit, i), n_lights, spec, bic(loss[i], int(n_values[i]), n_params, block),
                             samples=effective_samples(int(n_values[i]), n_params, block)))
    return out


def judged_problem(problem: FitProblem, options: EstimateOptions) -> FitProblem:
    """The problem on which model selection judges a fit of ``problem``: every
    ``options.tuning.criterion_stride``-th pixel (:func:`selfsup.estimation.solvers.subsample`), cast
    shadows by ``options.tuning.criterion_shadows``, and each light's indirect light where
    ``options.tuning.indirect`` says the file leaves light unaccounted for (no ambient
    given). ``problem`` itself where all three leave it as it is. Every pixel where the
    stride would leave an image none of its valid ones (a mask of scattered pixels)."""
    judged = subsample(problem, options.tuning.criterion_stride)
    if not bool(judged.gbuffer.mask.flatten(1).any(1).all()):
        judged = problem
    return criterion_light(judged, options)


def criterion_light(problem: FitProblem, options: EstimateOptions) -> FitProblem:
    # The problem's light transport as the criterion models it: its cast shadows and, where
    # the file leaves light unaccounted for, each light's indirect light.
    if options.tuning.criterion_shadows == "epipolar":  # criterion_thickness None: the unbounded solid
        problem = problem.with_shadows("epipolar", EpipolarShadowOptions(scene_thickness=options.tuning.criterion_thickness))
    elif options.tuning.criterion_shadows != problem.shadows:
        problem = problem.with_shadows(options.tuning.criterion_shadows)
    if options.tuning.indirect == "auto" and problem.ambient is None and problem.gbuffer.intrinsics is not None:
        problem = problem.with_indirect()
    return problem


def by_model(best: list[Candidate]) -> dict[tuple[int, bool], list[int]]:
    # The images of each (light count, specular switch): one batched call each.
    groups: dict[tuple[int, bool], list[int]] = {}
    for i, candidate in enumerate(best):
        groups.setdefault((candidate.n_lights, candidate.specular), []).append(i)
    return groups
