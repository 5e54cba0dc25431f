"""The albedo-free model and its fit: unit transport, log model, Cauchy loss, Jacobian and
Levenberg-Marquardt (:func:`refine_positions`), and what a fitted model says about its
lights (:func:`light_shares`, :func:`mirror_lobes`, :func:`highlight_pixels`)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from render import GBuffer, Material
from render.functional import light_transport, light_transport_jacobian
from render.indirect import PATCHES_ACROSS, one_bounce
from render.shading import blinn_phong_lobe, light_geometry
from selfsup.estimation.albedo_free.observation import AlbedoFreeFit, LogShading, fit_material
from selfsup.estimation.problem import FitProblem, gbuffer_centre_and_size
from selfsup.estimation.solvers import RUNAWAY_SIZES

__all__ = ["shading_loss", "refine_positions", "bounce_maps", "light_shares", "model_transport", "mirror_lobes", "highlight_pixels",
           "LM_TOLERANCE", "FINAL_TOLERANCE"]

# Levenberg-Marquardt stops an image once a step lowers its loss by less than this share
# (:func:`refine_positions`' default): where starts are compared, a slow slide (an ambient
# weight sinking towards nil) must go on, or the starts' ranking changes (a test frame lost its
# second light at 1e-4 everywhere).
LM_TOLERANCE = 1e-6
# The same for the last, full-resolution steps from a start already chosen (the searches' ends,
# a network's lights refined, the lens's chosen strength): 1e-4 against 1e-6 took 0.89 of the
# time on 258 capture frames with every count the same and one success more (ad hoc, 2026-12-06,
# the two alternated frame by frame in one process:
# benchmarks/results/lm_tolerance_cpu2_2026-12-06.md); 1e-3 (everywhere) lost three successes.
# At 1e-4 a criterion of ~280 effective samples moves by 0.03 a step, far below the penalty of a
# light's four parameters (~22).
FINAL_TOLERANCE = 1e-4


def _transport(obs: LogShading, position: Tensor) -> Tensor:
    # Unit transport (B, L, H, W), shading alone: model_transport of the observation's material.
    return model_transport(obs.gbuffer, obs.material, obs.falloff, position)


def model_transport(gbuffer: GBuffer, material: Material, falloff: str, position: Tensor) -> Tensor:
    """The albedo-free model's unit transport ``(B, L, H, W)`` of lights at ``position
    (B, L, 3)``, shading alone (no cast shadows): diffuse, plus the lobe of ``material``
    where it has one (:func:`.observation.glossy_material`: ``ks`` the lobe's ratio to the
    diffuse light), on the lit side only."""
    t = light_transport(gbuffer, material, position, falloff=falloff, shadows="none", specular=material.ks is not None)
    if t.specular is None:
        return t.diffuse
    return t.diffuse + _gloss_ratio(material)[..., None] * torch.where(t.diffuse > 0, t.specular, 0.0)


def _gloss_ratio(material: Material) -> Tensor:
    # Each image's lobe ratio, (B, 1, 1) (broadcast against (B, L, H, W) with one more axis).
    return material.ks[:, :1, :1, 0]


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


def bounce_maps(obs: LogShading, diffuse: Tensor, log_weight: Tensor) -> Tensor:
    """Each light's first bounce off the visible surfaces ``(B, L, H, W)``, in the units of its
    unit transport ``diffuse (B, L, H, W)``, the surfaces' albedo that of the model without the
    bounce (each segment's robust offset, relative to its median: the fit's bounce strength
    takes the albedo's unknown scale and the later bounces; :func:`render.indirect.one_bounce`,
    patches every twentieth of the width). The segments' own pixels reflect; others not."""
    log_model, _ = _log_model(diffuse, log_weight)
    ratio = (obs.log_shading - log_model).flatten(1)
    if obs.segments is None:
        offsets = torch.zeros_like(ratio)
    else:
        offsets = obs.offsets(ratio)
    level = torch.where(obs.pairs, offsets, torch.full_like(offsets, float("nan"))).nanmedian(1).values
    level = torch.nan_to_num(level, nan=0.0)
    albedo = torch.where(obs.pairs, (offsets - level[:, None]).clamp(-5, 5).exp(), torch.zeros_like(offsets))
    B, H, W = obs.log_shading.shape
    step = max(1, round(W / PATCHES_ACROSS))
    kd = albedo.view(B, H, W, 1).expand(B, H, W, 3)
    return one_bounce(obs.gbuffer, kd, diffuse, step, step)[:, 0]


def _effective(obs: LogShading, diffuse: Tensor, log_weight: Tensor, log_bounce: Tensor | None
               ) -> tuple[Tensor, Tensor | None]:
    # Each light's transport with its bounce (B, L, H, W), and the bounce maps (None without).
    if log_bounce is None:
        return diffuse, None
    bounce = bounce_maps(obs, diffuse, log_weight)
    return diffuse + log_bounce.exp()[:, None, None, None] * bounce, bounce


def _evaluate(obs: LogShading, position: Tensor, log_weight: Tensor,
              log_bounce: Tensor | None = None) -> tuple[Tensor, Tensor]:
    # The loss (B,) and the residual (B, P) it sums.
    transport, _ = _effective(obs, _transport(obs, position), log_weight, log_bounce)
    log_model, _ = _log_model(transport, log_weight)
    residual = _residual(obs, log_model)
    return shading_loss(obs, residual), residual


def _jacobian(obs: LogShading, position: Tensor, log_weight: Tensor, robust: bool = True,
              residual: Tensor | None = None, log_bounce: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Residual ``(B, P)`` and its Jacobian ``(B, k, P)`` with respect to the free
    parameters: each light's position (3L), the ambient's log weight, and the log
    weights of lights 2.. (the first light's is the gauge), and with ``log_bounce (B,)``
    the bounce's log strength (last; the bounce maps held, so the positions' rows leave
    the bounce's own dependence on them out). With ``robust`` segment
    offsets the Jacobian is the reweighting's (each offset a weighted mean whose weights
    are held): exact where the residuals lie well inside the Cauchy scale. ``residual``:
    the one at these parameters when known (:func:`_evaluate`'s)."""
    B, L, _ = position.shape
    jac = light_transport_jacobian(obs.gbuffer, obs.material, position, 1.0, falloff=obs.falloff, shadows="none",
                                   specular=obs.material.ks is not None)
    unit, d_unit = jac.transport.diffuse, jac.diffuse
    if jac.specular is not None:  # the lobe at its ratio, on the lit side only (as _transport)
        lit = unit > 0
        ratio = _gloss_ratio(obs.material)[..., None]
        unit = unit + ratio * torch.where(lit, jac.transport.specular, 0.0)
        d_unit = d_unit + ratio[..., None] * torch.where(lit[..., None], jac.specular, 0.0)
    diffuse, bounce = _effective(obs, unit, log_weight, log_bounce)  # (B, L, H, W)
    log_model, shading = _log_model(diffuse, log_weight)
    w = log_weight.exp()
    H, W = diffuse.shape[-2:]
    # d log S / d p_i = w_i dD_i/dp_i / S; d log S / d u_0 = w_0 / S; d log S / d u_i = w_i D_i / S,
    # (d / d log b = b sum_i w_i G_i / S), each block written into one (B, k, H, W) array and
    # divided by S there (no copies between).
    d_log = diffuse.new_empty(B, 4 * L + int(bounce is not None), H, W)
    torch.mul(w[:, 1:, None, None, None], d_unit.permute(0, 1, 4, 2, 3),
              out=d_log[:, : 3 * L].view(B, L, 3, H, W))
    d_log[:, 3 * L] = w[:, :1, None]
    torch.mul(w[:, 2:, None, None], diffuse[:, 1:], out=d_log[:, 3 * L + 1 : 4 * L])
    if bounce is not None:
        d_log[:, 4 * L] = log_bounce.exp()[:, None, None] * (w[:, 1:, None, None] * bounce).sum(1)
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
    d_u = torch.cat([step[:, 3 * L : 3 * L + 1], step.new_zeros(B, 1), step[:, 3 * L + 1 : 4 * L]], 1)
    return d_pos, d_u


def refine_positions(obs: LogShading, position: Tensor, log_weight: Tensor, iterations: int = 20,
                     tol: float = LM_TOLERANCE, log_bounce: Tensor | None = None) -> AlbedoFreeFit:
    """Damped Gauss-Newton (Levenberg-Marquardt) with Cauchy IRLS weights from
    ``position (B, L, 3)`` and ``log_weight (B, L + 1)`` (and the bounce's log strength
    ``log_bounce (B,)``, refined too where finite; :func:`bounce_maps`); each image stops on
    its own (relative loss decrease below ``tol``, or damping run out)."""
    position, log_weight = position.detach().clone(), log_weight.detach().clone()
    if log_bounce is not None:
        log_bounce = log_bounce.detach().clone()
    B, L, _ = position.shape
    centre, size = gbuffer_centre_and_size(obs.gbuffer)
    reach = RUNAWAY_SIZES * size  # (B,)
    loss, residual = _evaluate(obs, position, log_weight, log_bounce)
    damping = torch.full((B,), 1e-3, dtype=position.dtype, device=position.device)
    active = torch.ones(B, dtype=torch.bool, device=position.device)
    normal = None  # the weighted normal equations at the current parameters, kept while no image takes a step
    for _ in range(iterations):
        if normal is None:
            residual, jac = _jacobian(obs, position, log_weight, residual=residual, log_bounce=log_bounce)
            weights = _cauchy_weights(obs, residual)
            weighted = jac * weights[:, None]
            jtj = (weighted @ jac.transpose(1, 2)).double()
            jtr = (weighted @ residual[..., None]).double()
            diag = jtj.diagonal(dim1=-2, dim2=-1)
            peak = diag.amax(-1, keepdim=True)
            normal = jtj, jtr, torch.where(peak > 0, diag.clamp_min(1e-9 * peak), torch.ones_like(diag))
        jtj, jtr, diag = normal
        system = jtj + damping.double()[:, None, None] * torch.diag_embed(diag)
        # residual r = observed - model, J = d r / d theta: the step solves (J W J^T) d = -J W r.
        step = -torch.linalg.solve_ex(system, jtr)[0].squeeze(-1).to(position.dtype)
        finite = torch.isfinite(step).all(-1) & active
        step = torch.where(finite[:, None], step, torch.zeros_like(step))
        d_pos, d_u = _unpack(step, L)
        trial_pos, trial_u = position + d_pos, log_weight + d_u
        trial_bounce = None
        if log_bounce is not None:  # an image without the bounce (-inf) keeps none
            trial_bounce = torch.where(torch.isfinite(log_bounce), (log_bounce + step[:, 4 * L]).clamp(-12, 6), log_bounce)
        trial, trial_residual = _evaluate(obs, trial_pos, trial_u, trial_bounce)
        # A step that takes a light beyond RUNAWAY_SIZES scene sizes fits a direction, not a
        # point (the log shading of a far light flattens towards it): it is not taken.
        inside = (trial_pos - centre[:, None]).norm(dim=-1).amax(-1) <= reach
        better = finite & inside & (trial < loss)
        rel = (loss - trial) / loss.clamp_min(1e-30)
        position = torch.where(better[:, None, None], trial_pos, position)
        log_weight = torch.where(better[:, None], trial_u, log_weight)
        if log_bounce is not None:
            log_bounce = torch.where(better, trial_bounce, log_bounce)
        loss = torch.where(better, trial, loss)
        residual = torch.where(better[:, None], trial_residual, residual)
        damping = torch.where(better, damping * 0.3, damping * 10).clamp(1e-9, 1e9)
        active &= ~((better & (rel < tol)) | (damping >= 1e9))
        moved, going = torch.stack([better.any(), active.any()]).tolist()  # one wait for the device
        if not going:
            break
        if moved:  # where no image moved only the damping changed: the same equations
            normal = None
    return AlbedoFreeFit(position, log_weight, loss, obs.pairs.sum(1), log_bounce)


def residual_spread(obs: LogShading, fit: AlbedoFreeFit) -> Tensor:
    """``(B,)`` robust spread of ``fit``'s residuals on ``obs``: 1.4826 x their median absolute
    value over the residuals that count (a Gaussian's standard deviation; 0 where none count)."""
    _, residual = _evaluate(obs, fit.position, fit.log_weight, fit.log_bounce)
    counted = torch.where(obs.pairs, residual.abs(), torch.full_like(residual, float("nan")))
    return 1.4826 * torch.nan_to_num(counted.nanmedian(1).values, nan=0.0)


def light_shares(problem: FitProblem, fit: AlbedoFreeFit) -> Tensor:
    """Each light's share ``(B, L)`` of the fitted direct shading over the valid pixels (its
    lobe's with it where ``problem`` has one, :attr:`FitProblem.gloss`)."""
    transport = model_transport(problem.gbuffer, fit_material(problem), problem.falloff, fit.position)
    direct = (fit.log_weight[:, 1:].exp()[..., None, None] * transport * problem.gbuffer.mask[:, None]).flatten(2).sum(2)
    return direct / direct.sum(1, keepdim=True).clamp_min(1e-30)


def mirror_lobes(gbuffer: GBuffer, position: Tensor, max_angle_deg: float) -> Tensor:
    """``(B, H, W)`` bool: valid pixels whose normal lies within ``max_angle_deg`` of the
    half vector between the view and the direction to any light at ``position (B, L, 3)``:
    where a glossy surface shows that light's highlight (a Blinn-Phong lobe of shininess
    30 keeps 0.15 of its peak 20 degrees out)."""
    geometry = light_geometry(gbuffer.points[:, None], position[:, :, None, None])
    cosine = blinn_phong_lobe(gbuffer.normals[:, None], geometry.to_light, geometry.to_viewer, 1.0)  # n.h (B, L, H, W)
    return (cosine > math.cos(math.radians(max_angle_deg))).any(1) & gbuffer.mask


def highlight_pixels(obs: LogShading, fit: AlbedoFreeFit, max_angle_deg: float, min_excess: float = 0.0) -> Tensor:
    """``(B, H, W)`` bool: the pixels of ``fit``'s lights' :func:`mirror_lobes` that are
    brighter than its model (a residual above ``min_excess`` times the fit's Cauchy scale):
    where a glossy surface may show a highlight the diffuse-only fit does not explain. Each
    residual is taken against its segment's offset over the segment's pixels outside the
    lobes (over all of them where it lies inside): a highlight that covers much of its
    segment lifts even a robust offset, and its dimmer rim then reads as darker than the
    model and stays in (a glossy wall beside a lamp, half of its segment in the lobe).
    Segment residuals only."""
    if obs.segments is None:
        raise ValueError("highlight pixels are found on segment residuals; pairs have no pixel of their own")
    transport, _ = _effective(obs, _transport(obs, fit.position), fit.log_weight, fit.log_bounce)
    log_model, _ = _log_model(transport, fit.log_weight)
    ratio = (obs.log_shading - log_model).flatten(1)
    lobes = mirror_lobes(obs.gbuffer, fit.position, max_angle_deg)
    outside = obs.pairs & ~lobes.flatten(1)
    has_outside = obs.segment_means(outside.to(ratio.dtype), obs.pairs.to(ratio.dtype)) > 0
    residual = torch.where(obs.pairs, ratio - obs.offsets(ratio, torch.where(has_outside, outside, obs.pairs)),
                           torch.zeros_like(ratio))
    return lobes & (residual.view_as(lobes) > min_excess * obs.scale.view(-1, 1, 1))
