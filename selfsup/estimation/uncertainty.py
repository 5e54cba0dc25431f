"""Position covariances of the chosen lights (Gauss-Newton), with the error sources the residual cannot show.

:func:`position_covariance` starts from the residual's variance and adds, where the
settings say, what an albedo error, unmodelled (indirect) light and the normals'
error move the lights by, each as a covariance of scores over the criterion's
blocks (``docs/estimation.md``, "Uncertainty").
"""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

from render import GBuffer, light_transport
from selfsup.estimation.options import RefineOptions
from selfsup.estimation.problem import Fit, FitProblem, basis_columns, centre_and_size, gbuffer_centre_and_size
from selfsup.estimation.solvers import jacobians, normal_equations
from selfsup.linear import intensity_design

__all__ = ["position_covariance", "position_blocks", "albedo_scores", "normal_tilt_scores", "indirect_field_scores",
           "field_covariance", "tilted_normals", "tilt_axes", "block_scores", "block_sums"]


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
    variance alone misses it (benchmarks/results/estimation_measurements.md, "Uncertainty under reflectance errors").

    ``indirect_variation`` (0: off; only where the ambient is unknown, ``problem.ambient``
    None) adds what light the model lacks moves the lights by, taking the fitted constant
    ambient for the mean of a smooth field: the light a surface point receives besides
    the point lights is ``ambient (1 + e(x))``, ``e`` a Gaussian random field over the 3D
    points of standard deviation ``indirect_variation`` and correlation length
    ``indirect_length`` (of the scene size), one value per block of ``albedo_block_px``
    pixels (:func:`indirect_field_scores`; benchmarks/results/estimation_measurements.md, "Uncertainty under indirect light").

    ``normal_error`` adds what the normals' error moves the lights by, where
    ``problem.normal_tilt`` gives its variance (normals fitted to noisy depth): every
    block of ``albedo_block_px`` pixels tilted as one, independently between blocks and
    the two tilt axes (:func:`normal_tilt_scores`; benchmarks/results/estimation_measurements.md, "Uncertainty under noisy
    depth").
    """
    if not (indirect_variation >= 0 and math.isfinite(indirect_variation) and 0 < indirect_length < math.inf):
        raise ValueError(f"indirect_variation must be a finite value >= 0 and indirect_length > 0, got "
                         f"{indirect_variation} and {indirect_length}")
    if albedo_error < 0 or not math.isfinite(albedo_error):
        raise ValueError(f"albedo_error must be a finite value >= 0, got {albedo_error}")
    B, L, _ = fit.position.shape
    _, size = centre_and_size(problem)
    h = (options.fd_step * size)[:, None, None]
    cols, j_pos, diffuse = jacobians(problem, fit.position, fit.intensity, h, options.specular)
    mask = problem.gbuffer.mask[:, None].expand_as(problem.image).to(j_pos.dtype)
    info, _ = normal_equations(problem, j_pos, cols, mask)
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
    size = problem.normal_tilt.clamp(0, 1).sqrt()[:, None] * weights  # (B, 3, H, W)
    intensity = fit.intensity.transpose(1, 2)[..., None, None]  # (B, 3, L, 1, 1)
    model = (cols * intensity).sum(2)
    per_axis = []
    for tilted in tilted_normals(problem.gbuffer, step):
        t = light_transport(tilted, problem.material, fit.position, falloff=problem.falloff, shadows=problem.shadows,
                            shadow_options=problem.shadow_options, specular=specular)
        changed = (basis_columns(dataclasses.replace(problem, gbuffer=tilted), t.diffuse, t.specular) * intensity).sum(2)
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
    derivative = problem.material.kd.permute(0, 3, 1, 2) * fit.ambient[:, :, None, None] * weights
    scores = block_scores(problem, j_pos, cols, derivative, block_px, shared_channels=True)  # (B, n, blocks)
    kernel = field_covariance(problem.gbuffer, block_px, variation, length)
    return scores @ kernel.to(scores.dtype) @ scores.transpose(1, 2)


def field_covariance(gbuffer: GBuffer, block_px: int, variation: float, length: float) -> Tensor:
    """Covariance ``(B, blocks, blocks)`` between the square blocks of ``block_px`` pixels
    (row-major, :func:`block_sums`) of a Gaussian random field over the 3D points:
    ``variation^2 exp(-|x - x'|^2 / (2 (length x scene size)^2))`` at the blocks' centres
    (the mean of their valid points; the scene size the valid points' bounding-box
    diagonal); in the points' dtype."""
    g = gbuffer
    valid = g.mask.to(g.points.dtype)[:, None]  # (B, 1, H, W)
    points = torch.where(g.mask[..., None], g.points, torch.zeros_like(g.points)).permute(0, 3, 1, 2)
    sums = block_sums(torch.cat([points, valid], 1), block_px)  # (B, 4, blocks)
    centre = (sums[:, :3] / sums[:, 3:].clamp_min(1)).transpose(1, 2)  # (B, blocks, 3); empty blocks score 0
    _, size = gbuffer_centre_and_size(g)
    distance2 = torch.cdist(centre, centre).square() / (length * size)[:, None, None].square()
    return variation**2 * torch.exp(-0.5 * distance2)


def tilted_normals(gbuffer: GBuffer, step: float) -> list[GBuffer]:
    """``gbuffer`` with every normal tilted by ``step`` radians about each of its two
    :func:`tilt_axes` in turn (two G-buffers): the forward differences of a normal error."""
    n = gbuffer.normals
    return [dataclasses.replace(gbuffer, normals=torch.nn.functional.normalize(n + step * axis, dim=-1))
            for axis in tilt_axes(n)]


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
    ``k = L [+ 1]`` linear ones per channel) ordered as :func:`normal_equations` orders
    them, from its ``j_pos``, ``cols`` and ``weights (B, 3, H, W)`` and the lights' diffuse
    transport ``diffuse (B, L, H, W)`` (all three as :func:`jacobians` gives them). A kd error ``e`` that is
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
    included) per unit; the parameters ordered as :func:`normal_equations` orders them.
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
