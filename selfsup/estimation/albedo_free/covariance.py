"""How well the albedo-free fit places its lights: the Gauss-Newton covariance of each
light's position (:func:`position_covariance`), with the indirect light and the normals'
noise it cannot see in its residual."""

from __future__ import annotations

import dataclasses

from torch import Tensor

from selfsup.estimation.albedo_free.fit import _cauchy_weights, _jacobian, _log_model, _transport
from selfsup.estimation.albedo_free.observation import AlbedoFreeFit, LogShading
from selfsup.estimation.uncertainty import block_sums, field_covariance, position_blocks, tilted_normals

__all__ = ["position_covariance", "block_scores_of"]


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
