"""The albedo-free fit's lights in the image's units (:func:`intensities_of`), the loss of
its model without lights (:func:`ambient_only_loss`) and the evidence for its lights
(:func:`evidence`): what the fit's ratios become in a record, and how much its lights explain."""

from __future__ import annotations

import math
from dataclasses import replace

import torch
from torch import Tensor

from selfsup.estimation import albedo_free
from selfsup.estimation.criterion import bic
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.problem import Fit, FitProblem, cauchy_scale, irls_weights
from selfsup.estimation.solvers import refine

__all__ = ["intensities_of", "ambient_only_loss", "ambient_criterion", "evidence"]


# An ambient log weight this far above the first light's: its shading is the ambient's alone.
AMBIENT_ONLY_LOG_WEIGHT = 60.0


def ambient_only_loss(obs: albedo_free.LogShading, fit: albedo_free.AlbedoFreeFit) -> Tensor:
    """``(B,)`` loss of the model without lights (the ambient alone: the log shading one
    constant, each segment's offset free) on the residuals of ``obs``: the fit's positions
    held, its ambient's weight so far above theirs that they add nothing."""
    log_weight = fit.log_weight.clone()
    log_weight[:, 0] = AMBIENT_ONLY_LOG_WEIGHT
    return albedo_free.refine_positions(obs, fit.position, log_weight, 0).loss


def ambient_criterion(obs: albedo_free.LogShading, fit: albedo_free.AlbedoFreeFit, block: int) -> list[float]:
    """Each image's :func:`bic` of the model without lights (no parameter; :func:`ambient_only_loss`)
    on the residuals of ``obs``, ``block`` pixels a side an independent sample: a model
    explains the shading only where its own criterion is below."""
    return [bic(loss, pairs, 0, block) for loss, pairs in zip(ambient_only_loss(obs, fit).tolist(), fit.pairs.tolist())]


def evidence(obs: albedo_free.LogShading, fit: albedo_free.AlbedoFreeFit, n_params: list[int], block: int,
             spread: float) -> list[float]:
    """Each image's evidence for ``fit``'s lights (``n_params`` parameters each): the criterion
    of the model without lights less the fit's, both under one Cauchy scale fitted to the
    frame: ``spread`` x the fit's residual spread (:func:`albedo_free.residual_spread`), at
    least the observation's own (0: the observation's).

    The observation's scale is the sensor's noise (at least 2%): where the model misses by
    more than that (normals integrated across parts that hide each other, a paint's sheen),
    every residual costs about its logarithm, so that a light explaining most of the
    shading gained no more than the ambient alone loses, and the frame said "no light"
    (our analogue of DiLiGenT's gold-painted figure: a light with all the light, evidence -3).
    At the frame's own misfit the two models are judged as least squares judge them, on how
    much of the shading's variation each leaves. At the observation's scale (``spread`` 0) the
    fit's own loss is taken (``fit.loss``, on ``obs``)."""
    judged, loss = obs, fit.loss
    if spread > 0:
        judged = replace(obs, scale=torch.maximum(obs.scale, spread * albedo_free.residual_spread(obs, fit)))
        loss = albedo_free.refine_positions(judged, fit.position, fit.log_weight, 0, log_bounce=fit.log_bounce).loss
    return [unlit - bic(value, pairs, k, block)
            for unlit, value, pairs, k in zip(ambient_criterion(judged, fit, block), loss.tolist(), fit.pairs.tolist(),
                                                n_params)]


def intensities_of(problem: FitProblem, fit: albedo_free.AlbedoFreeFit, options: EstimateOptions,
                   observed: albedo_free.LogShading | None = None) -> tuple[Fit, Tensor]:
    """The albedo-free fit's lights and ambient as intensities in the image's units: the
    fit's own ratios (its log weights, which its covariance and shares rest on) times one
    scale per channel, the Cauchy-reweighted least-squares factor of the model shading
    (no cast shadows, as the fit; its specular lobe where the fit has one; with the fit's bounce, :func:`albedo_free.bounce_maps`
    of ``observed``, its log shading) times kd against each channel of the image; and each
    image's share ``(B,)`` of the model's light that is the bounce (0 without it).

    With the albedo unknown, a light's colour is the surfaces' colour too: a channel solved
    on its own makes colour a free knob (a red wall took a red-only light, a blue ambient
    painted shadows blue). ``tuning.light_colour``: ``neutral`` (the default): every light
    and the ambient the image's white, equal channels, as a camera's white balance makes
    the light it sees; ``shared``: one colour for all, each channel's own factor (the
    image's mean colour, surfaces and light together); ``free``: each light and the
    ambient solved per channel at the positions, as before
    (:func:`selfsup.estimation.solvers.refine` without steps).

    Returns: a :class:`Fit` (``intensity (B, L, 3)``, ``ambient (B, 3)``, ``model (B, 3, H, W)``)
    and the bounce's share ``(B,)``.
    """
    solve = replace(options.tuning.refine, specular=False, max_iters=(0,), strides=(1,))
    weight = fit.log_weight.exp()  # (B, L + 1): the ambient's, then each light's, relative
    material = albedo_free.fit_material(problem)  # with the fit's lobe and coat, if any
    diffuse = albedo_free.model_transport(problem.gbuffer, material, problem.falloff, fit.position)  # (B, L, H, W)
    direct = (weight[:, 1:, None, None] * diffuse).sum(1)  # (B, H, W)
    bounce = torch.zeros_like(direct)
    if fit.log_bounce is not None and observed is not None and bool(fit.bounced().any()):
        maps = albedo_free.bounce_maps(observed, diffuse, fit.log_weight)
        strength = torch.where(fit.bounced(), fit.log_bounce, torch.full_like(fit.log_bounce, -math.inf)).exp()
        bounce = strength[:, None, None] * (weight[:, 1:, None, None] * maps).sum(1)
    shading = weight[:, :1, None] + direct + bounce  # (B, H, W)
    mask = problem.gbuffer.mask[:, None].to(problem.image.dtype)  # (B, 1, H, W)
    share = (bounce * mask[:, 0]).flatten(1).sum(1) / (shading * mask[:, 0]).flatten(1).sum(1).clamp_min(1e-30)
    if options.tuning.light_colour == "free":
        return refine(problem, fit.position, solve), share
    unit = problem.material.kd.permute(0, 3, 1, 2) * shading[:, None] * mask  # (B, 3, H, W) at scale 1
    image = problem.image * mask
    scale = cauchy_scale(problem, solve)
    weights = irls_weights(problem, None, solve)
    for _ in range(solve.irls_passes + 1):
        # (B, 3): each channel's factor; guarded where a channel has no model light.
        product, square = (weights * image * unit).flatten(2).sum(2), (weights * unit * unit).flatten(2).sum(2)
        if options.tuning.light_colour == "neutral":  # one factor for the three channels
            product, square = product.sum(1, keepdim=True), square.sum(1, keepdim=True)
        factor = (product / square.clamp_min(1e-30)).expand(-1, 3)
        model = factor[..., None, None] * unit
        weights = irls_weights(problem, model - problem.image, solve, scale)
    residual = (model - image) * mask
    cost = (weights * residual**2).flatten(1).sum(1)
    return Fit(fit.position, weight[:, 1:, None] * factor[:, None], weight[:, :1] * factor, cost, model,
               torch.zeros_like(cost), residual.pow(2).flatten(1).sum(1), mask.expand_as(image).flatten(1).sum(1)), share
