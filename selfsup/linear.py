"""Closed-form light intensities and ambient for fixed light positions.

The image model is linear in the intensities and the ambient term, so for given
light transport maps the best of them is a small weighted least-squares problem
per image and channel (``L + 1`` unknowns). Both the training loss and the
per-image refinement solve it, so that the light positions are all that is
searched for (variable projection).
"""

from __future__ import annotations

import torch
from torch import Tensor

from render.shading import Falloff

__all__ = ["basis_images", "solve_intensities", "intensity_design", "solve_design", "single_light_costs", "pseudo_huber",
           "segment_albedo"]


def basis_images(kd: Tensor, ks: Tensor | None, diffuse: Tensor, specular: Tensor | None) -> Tensor:
    """Per-channel images ``(B, 3, L, H, W)`` of unit-intensity lights: ``kd_c D_i + ks_c S_i``.

    Args:
        kd: ``(B, H, W, 3)``; ks: ``(B, H, W, 1|3)`` or None.
        diffuse, specular: ``(B, L, H, W)`` transport maps (specular may be None).
    """
    cols = kd.permute(0, 3, 1, 2)[:, :, None] * diffuse[:, None]
    if specular is not None and ks is not None:
        cols = cols + ks.permute(0, 3, 1, 2)[:, :, None] * specular[:, None]
    return cols


def solve_intensities(cols: Tensor, kd: Tensor, image: Tensor, weights: Tensor, ambient: Tensor | None = None,
                      ridge: float = 1e-9) -> tuple[Tensor, Tensor, Tensor]:
    """Weighted least-squares intensities (and ambient) for basis images ``cols``.

    Args:
        cols: ``(B, 3, L, H, W)`` from :func:`basis_images`; an all-zero column (a
            light switched off) gets intensity 0.
        kd: ``(B, H, W, 3)`` albedo (the ambient term's image is ``kd * L_a``).
        image: observed ``(B, 3, H, W)``.
        weights: ``(B, 3, H, W)`` per-value weights (0 on invalid pixels).
        ambient: known ambient ``(B, 3)``, or None to solve for it.
        ridge: Tikhonov term relative to the trace of the normal matrix.

    Returns:
        intensity ``(B, L, 3)`` (>= 0), ambient ``(B, 3)`` (the known one if given,
        else solved, >= 0) and the model image ``(B, 3, H, W)`` (not masked).
    """
    return solve_design(intensity_design(cols, kd, ambient), kd, image, weights, ambient, ridge)


def intensity_design(cols: Tensor, kd: Tensor, ambient: Tensor | None) -> Tensor:
    """The columns ``(B, 3, k, H*W)`` of :func:`solve_intensities`' least-squares problem:
    the basis images ``cols (B, 3, L, H, W)`` and, when the ``ambient`` is unknown (None),
    ``kd (B, H, W, 3)``'s image as its column (``k = L + 1``). Several solves with other
    weights (reweighting) share one: :func:`solve_design`."""
    if ambient is None:
        cols = torch.cat([cols, kd.permute(0, 3, 1, 2)[:, :, None]], 2)
    return cols.flatten(3)


def solve_design(a: Tensor, kd: Tensor, image: Tensor, weights: Tensor, ambient: Tensor | None = None,
                 ridge: float = 1e-9) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`solve_intensities` on its :func:`intensity_design` ``a (B, 3, k, H*W)`` (the same
    ``ambient``: ``k - 1`` lights when it is unknown, else ``k``)."""
    L = a.shape[2] - (ambient is None)
    kd_image = kd.permute(0, 3, 1, 2)
    target = image
    if ambient is not None:
        target = target - kd_image * ambient[:, :, None, None]
    w = weights.flatten(2)[:, :, None]  # (B, 3, 1, N)
    weighted = a * w
    normal = weighted @ a.transpose(-1, -2)  # (B, 3, k, k)
    # As a row times a matrix: BLAS runs that 3-6x faster than the matrix times a column.
    rhs = (target.flatten(2)[:, :, None] @ weighted.transpose(-1, -2)).squeeze(-2)  # (B, 3, k)
    # The ridge keeps a nearly dark light solvable (intensity -> 0); it is relative to
    # each column's own diagonal, so it does not depend on units: the lights' columns
    # (1/d^2) and the ambient's (kd) differ by d^2, and a ridge relative to the trace
    # silenced the lights of a scene given in centimetres. A light that lights nothing
    # (a column under 1e-12 of the brightest light's) gets a unit-scale diagonal
    # instead: its intensity is then exactly 0 and, unlike a 1e-9 ridge in float32,
    # the solve's backward stays finite (a gradient step may carry a light behind a
    # wall). With a known ambient and every light dark the whole system is zero: scale
    # 1 then.
    diagonal = normal.diagonal(dim1=-2, dim2=-1)
    trace = diagonal.sum(-1)
    trace = torch.where(trace > 0, trace, torch.ones_like(trace))
    brightest = diagonal[..., :L].amax(-1, keepdim=True) if L else diagonal.new_zeros(diagonal.shape[:-1] + (1,))
    dead = torch.cat([diagonal[..., :L] <= 1e-12 * brightest, diagonal[..., L:] <= 0], -1).to(a.dtype)
    x, info = torch.linalg.solve_ex(normal + torch.diag_embed(ridge * diagonal + dead * trace[..., None]),
                                    rhs[..., None])
    # A singular system (no lit pixel at all) gives no light rather than an exception.
    x = torch.where((info == 0)[..., None, None] & torch.isfinite(x), x, torch.zeros_like(x)).squeeze(-1).clamp_min(0)
    model = (x[:, :, None] @ a).view_as(image)  # sum_j x_j cols_j, as a product: 2-4x faster than the sum over j
    if ambient is not None:
        model = model + kd_image * ambient[:, :, None, None]
    else:
        ambient = x[:, :, L]
    return x[:, :, :L].transpose(1, 2), ambient, model


def _segment_sums(values: Tensor, segments: Tensor, slots: int) -> Tensor:
    # (B, 3, P) values summed per segment: (B, 3, slots).
    index = segments[:, None].expand_as(values).contiguous()
    return values.new_zeros(*values.shape[:2], slots).scatter_add_(-1, index, values)


@torch.no_grad()
def segment_albedo(diffuse: Tensor, image: Tensor, weights: Tensor, segments: Tensor, count: int,
                   iterations: int = 3, mean_albedo: float = 0.5, ridge: float = 1e-6) -> Tensor:
    """The albedo ``(B, H, W, 3)`` that is one colour over each segment and, with the lights'
    intensities and the ambient, best explains ``image`` under the unit-intensity
    diffuse transport ``diffuse (B, L, H, W)`` (shadows included where they are).

    The model ``I_c = rho_{s,c} (a_c + sum_i L_{i,c} D_i)`` is bilinear: alternating least
    squares solves the intensities and ambient for the albedo (:func:`solve_intensities`),
    then each segment's albedo for the shading in closed form
    (``rho_{s,c} = sum w I S / sum w S^2`` over its pixels), ``iterations`` times, from each
    segment's mean colour (the shading taken as even). Albedo and light trade one scale in
    each channel (a white wall under a warm lamp looks as a warm wall under a white one):
    each channel's ``weights``-weighted mean albedo is set to ``mean_albedo`` (grey on
    average, a capture's convention, :data:`selfsup.scenes.capture.ASSUMED_ALBEDO`). Not
    differentiated: a loss solves the intensities again at this albedo with gradients
    (at the solution, the albedo's own derivative adds nothing to the cost's).

    Args:
        diffuse: ``(B, L, H, W)``; image ``(B, 3, H, W)``; weights ``(B, 3, H, W)`` (0 where
            a pixel does not count); segments ``(B, H W)`` long, each pixel's segment in
            ``0 .. count - 1`` or ``count`` (none: its albedo is ``mean_albedo``).
    """
    B, _, H, W = image.shape
    if segments.shape != (B, H * W):
        raise ValueError(f"segments must have shape {(B, H * W)}, got {tuple(segments.shape)}")
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    slots = count + 1
    w = weights.flatten(2) * (segments < count)[:, None].to(weights.dtype)  # (B, 3, P)
    observed = image.flatten(2)

    def normalised(rho: Tensor) -> Tensor:  # (B, 3, slots) -> the albedo image (B, H, W, 3)
        rho = rho.clamp_min(0)
        rho[..., count] = 0
        pixels = rho.gather(-1, segments[:, None].expand(-1, 3, -1))
        mean = (pixels * w).sum(2) / w.sum(2).clamp_min(1e-30)  # (B, 3)
        pixels = pixels * (mean_albedo / mean.clamp_min(1e-30))[..., None]
        pixels = torch.where(segments[:, None] < count, pixels, torch.full_like(pixels, mean_albedo))
        return pixels.view(B, 3, H, W).permute(0, 2, 3, 1)

    kd = normalised(_segment_sums(w * observed, segments, slots) / _segment_sums(w, segments, slots).clamp_min(1e-30))
    for _ in range(iterations):
        intensity, ambient, _ = solve_intensities(basis_images(kd, None, diffuse, None), kd, image, weights, ridge=ridge)
        shading = torch.einsum("blc,blhw->bchw", intensity, diffuse).flatten(2) + ambient[..., None]  # (B, 3, P)
        kd = normalised(_segment_sums(w * observed * shading, segments, slots)
                        / _segment_sums(w * shading * shading, segments, slots).clamp_min(1e-30))
    return kd


def pseudo_huber(residual: Tensor, scale: float) -> Tensor:
    """``sqrt(r^2 + c^2) - c`` elementwise: quadratic below ``c = scale``, linear above."""
    return torch.sqrt(residual * residual + scale * scale) - scale


# Hypotheses x pixels per call of _single_light_costs. On the CPU images are taken a
# few at a time so that its (B, M, P) temporaries stay near the cache (on the 2-core
# CPU, 4 images of 216 x 676 ran twice as fast as 16 at once; answers are identical).
# An accelerator wants the opposite, few large calls: there the bound only caps memory
# (each temporary 256 MiB in float32).
_COST_ELEMENTS_CPU = 640_000
_COST_ELEMENTS_ACCELERATOR = 1 << 26


def single_light_costs(position: Tensor, points: Tensor, normals: Tensor, mask: Tensor, kd: Tensor, image: Tensor,
                       exposure: Tensor, falloff, robust_scale: float | None = None) -> Tensor:
    """Error ``(B, M)`` of each light position ``(B, M, 3)`` as the only light, unshadowed
    and diffuse, with its intensity and the ambient term the non-negative
    least-squares fit (per channel).

    Args:
        points, normals: ``(B, H, W, 3)``; mask ``(B, H, W)``; kd ``(B, H, W, 3)``;
        image ``(B, 3, H, W)``; exposure ``(B,)`` divides the residual.

    ``robust_scale`` None: the mean squared exposure-normalised error, from
    per-hypothesis sums over pixels alone (``|y|^2 - x^T b``, three matrix products).
    Otherwise the mean pseudo-Huber cost of the same fit's residual (what the
    photometric loss measures: shadows and highlights the hypothesis cannot
    explain pull with bounded force).
    """
    B, M = points.shape[0], position.shape[1]
    budget = _COST_ELEMENTS_CPU if points.device.type == "cpu" else _COST_ELEMENTS_ACCELERATOR
    per_call = max(1, budget // max(1, M * points.shape[1] * points.shape[2]))
    per_image = (position.expand(B, -1, -1), points, normals, mask, kd, image, exposure)
    return torch.cat([_single_light_costs(*(x[i : i + per_call] for x in per_image), falloff, robust_scale)
                      for i in range(0, B, per_call)])


def _sums_over_pixels(per_hypothesis: Tensor, per_pixel: Tensor) -> Tensor:
    """``per_hypothesis (B, M, P) @ per_pixel (B, P, C)`` as the transposed product, which
    BLAS runs faster for a few columns C on the 2-core CPU (and bitwise the same there)."""
    return (per_pixel.transpose(1, 2) @ per_hypothesis.transpose(1, 2)).transpose(1, 2)


def _single_light_costs(position: Tensor, points: Tensor, normals: Tensor, mask: Tensor, kd: Tensor, image: Tensor,
                        exposure: Tensor, falloff, robust_scale: float | None) -> Tensor:
    points = points.flatten(1, 2)  # (B, P, 3)
    normals = normals.flatten(1, 2)
    weight = mask.flatten(1).to(image.dtype)[..., None]  # (B, P, 1)
    kd = kd.flatten(1, 2)  # (B, P, 3)
    observed = image.flatten(2).transpose(1, 2)  # (B, P, 3)

    # Distances and n.(l - p) from matrix products: no (B, M, P, 3) tensor is formed,
    # and each (B, M, P) array is made in as few passes as possible (they dominate).
    offsets = (position * position).sum(-1)[:, :, None] + (points * points).sum(-1)[:, None]
    squared = torch.baddbmm(offsets, position, points.transpose(1, 2), alpha=-2)  # (B, M, P)
    floor = 1e-6 * points.norm(dim=-1).amax(1)[:, None, None]
    inverse = squared.clamp_min(floor * floor).rsqrt()  # 1 / max(distance, floor)
    facing = torch.baddbmm(-(normals * points).sum(-1)[:, None], position, normals.transpose(1, 2))
    diffuse = facing.clamp_min(0) * inverse  # max(0, n . l)
    if Falloff(falloff) is Falloff.INVERSE_SQUARE:
        diffuse = diffuse * inverse.square()

    albedo_weight = weight * kd * kd  # (B, P, 3)
    target_weight = weight * kd * observed
    # The sums are formed in the input dtype, the 2x2 solves in float64: a far light
    # is nearly constant over the scene, so its column is close to the ambient one.
    wide = torch.float64 if image.device.type != "mps" else image.dtype
    s_11 = albedo_weight.sum(1)[:, None].to(wide)  # (B, 1, 3): ambient column against itself
    # Both sums against diffuse from one product, 6 columns wide: 2.7x faster than two of 3.
    s_d1, b_d = _sums_over_pixels(diffuse, torch.cat([albedo_weight, target_weight], -1)).to(wide).split(3, -1)
    s_dd = _sums_over_pixels(diffuse * diffuse, albedo_weight).to(wide)  # (B, M, 3)
    b_1 = target_weight.sum(1)[:, None].to(wide)
    y_y = (weight * observed * observed).sum(1)[:, None].to(wide)
    s_dd, s_11 = s_dd * (1 + 1e-9) + 1e-30, s_11 * (1 + 1e-9) + 1e-30  # ridge: an unlit hypothesis stays solvable
    det = s_dd * s_11 - s_d1 * s_d1
    light = (b_d * s_11 - b_1 * s_d1) / det
    ambient = (s_dd * b_1 - s_d1 * b_d) / det
    both = y_y - light * b_d - ambient * b_1
    light_only = y_y - b_d.clamp_min(0) ** 2 / s_dd
    ambient_only = y_y - b_1.clamp_min(0) ** 2 / s_11
    feasible = (light >= 0) & (ambient >= 0)
    error = torch.where(feasible, both, torch.minimum(light_only, ambient_only))
    count = 3 * weight.sum((1, 2)).clamp_min(1)
    if robust_scale is None:
        return error.clamp_min(0).sum(-1).to(image.dtype) / (count * exposure**2)[:, None]
    only_light = ~feasible & (light_only <= ambient_only)
    light = torch.where(feasible, light, torch.where(only_light, b_d.clamp_min(0) / s_dd, torch.zeros_like(light)))
    ambient = torch.where(feasible, ambient, torch.where(only_light, torch.zeros_like(ambient), b_1.clamp_min(0) / s_11))
    light, ambient = light.to(image.dtype), ambient.to(image.dtype)  # (B, M, 3)
    model = kd[:, None] * (light[:, :, None] * diffuse[..., None] + ambient[:, :, None])  # (B, M, P, 3)
    residual = (model - observed[:, None]) / exposure[:, None, None, None]
    return (pseudo_huber(residual, robust_scale) * weight[:, None]).sum((2, 3)) / count[:, None]
