"""What the network compares: its lights re-rendered on the working grid, and the
Gauss-Newton step that a set of pixel weights makes of the difference.

The model of a frame's shading (no albedo needed): each pixel's grey level is its albedo
times ``S = exp(v) + sum_k g_k exp(u_k) D_k``, where ``D_k = V_k max(0, n.l_k) / d_k^2`` is
slot ``k``'s unit diffuse transport (``V_k`` its cast-shadow visibility, through
:func:`render.light_transport`), ``u_k`` its log intensity relative to slot 0's (``u_0 =
0``), ``g_k`` its presence and ``v`` the log ambient. Distances are in scene units (the
frame's size), so nothing depends on the scene's scale. The albedo cancels in the
difference of two neighbouring pixels' logs where both share it: the residuals are such
differences, along rows and columns at one and three cells (:data:`PAIR_OFFSETS`), and
a weight per pair says where they share it (not across an albedo edge, a highlight or a
shadow edge the depth does not predict). Those weights are what the network learns; the
step they make is physics: the damped Gauss-Newton step of the weighted pair residuals
in the slots' positions, relative intensities and the ambient.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from render.shading import Falloff, shading_and_position_gradients
from render.shadows import ShadowMethod, shadow_visibility
from selfsup.network.grid import WorkGrid

__all__ = ["LightState", "Rerender", "PAIR_OFFSETS", "rerender", "pair_differences", "pair_usable",
           "gauss_newton_step", "log_residual", "lens_log_factor", "radius_squared", "MAX_MOVE", "LOG_GAIN_RANGE"]

# (rows, columns) of each pair's second pixel from its first.
PAIR_OFFSETS = ((0, 1), (1, 0), (0, 3), (3, 0))
# A step moves a light at most this far (scene units) and a log intensity at most by
# LOG_STEP; log gains stay within LOG_GAIN_RANGE (a second light down to e^-7 of the first).
MAX_MOVE = 0.3
LOG_STEP = 2.0
LOG_GAIN_RANGE = (-7.0, 4.0)
# The IRLS prior on every pair: Cauchy weights at this scale (log units), so that even
# before the network has learned anything a few outliers do not carry the step.
CAUCHY_SCALE = 0.15
MAX_VIGNETTING = 2.0


@dataclass
class LightState:
    """The network's lights in scene units.

    Attributes:
        position: ``(B, K, 3)`` scene units about the frame's centre.
        log_gain: ``(B, K)`` log intensity relative to slot 0's (column 0 is 0).
        log_ambient: ``(B,)`` log ambient relative to slot 0's unit intensity.
        presence: ``(B, K)`` in [0, 1]; slot 0's is 1.
        vignetting: ``(B,)`` >= 0: the lens's ``a`` of :func:`lens_log_factor`.
    """

    position: Tensor
    log_gain: Tensor
    log_ambient: Tensor
    presence: Tensor
    vignetting: Tensor

    def detach(self) -> "LightState":
        return LightState(self.position.detach(), self.log_gain.detach(), self.log_ambient.detach(),
                          self.presence.detach(), self.vignetting.detach())


def radius_squared(grid: WorkGrid) -> Tensor:
    """``(B, h, w)``: each cell's squared distance from the principal point in focal lengths."""
    K = grid.gbuffer.intrinsics
    h, w = grid.gbuffer.mask.shape[1:]
    v, u = torch.meshgrid(torch.arange(h, dtype=K.dtype, device=K.device), torch.arange(w, dtype=K.dtype, device=K.device),
                          indexing="ij")
    return ((u - K[:, 0, 2, None, None]) / K[:, 0, 0, None, None]) ** 2 + ((v - K[:, 1, 2, None, None]) / K[:, 1, 1, None, None]) ** 2


def lens_log_factor(vignetting: Tensor, r2: Tensor) -> Tensor:
    """``(B, h, w)``: the log of a lens's radial factor ``(1 + a r^2)^-2`` (the camera model's,
    :func:`selfsup.scenes.camera.lens_falloff`), ``a = vignetting (B,)``."""
    return -2 * torch.log1p(vignetting[:, None, None] * r2)


@dataclass
class Rerender:
    """The state's re-render on the grid: ``transport (B, K, h, w)`` (unit, shadowed),
    ``visibility (B, K, h, w)``, ``shading (B, h, w)`` (``S``, the lens's factor
    included), and, with a Jacobian, ``jacobian (B, h, w, n)``: ``d log S / d`` the ``n =
    4K + 1`` parameters (each slot's position, then the relative log gains of slots 1..,
    the log ambient, the lens's ``a``)."""

    transport: Tensor
    visibility: Tensor
    shading: Tensor
    jacobian: Tensor | None = None


def rerender(grid: WorkGrid, state: LightState, shadows: ShadowMethod | str = ShadowMethod.EPIPOLAR,
             shadow_options=None, jacobian: bool = True) -> Rerender:
    """Re-render ``state``'s lights on ``grid`` (no gradient: the step's inputs).

    Visibility is rendered in metres by :func:`render.shadows.shadow_visibility` (the
    layer's screen-space shadows on the grid's camera); the shading and its derivatives
    are in scene units (:func:`render.shading.shading_and_position_gradients`), the
    visibility held fixed in them.
    """
    with torch.no_grad():
        g = grid.gbuffer
        point_planes, normal_planes = g.planes()
        centre, size = grid.frame.centre[:, :, None, None], grid.frame.size[:, None, None, None]
        points = (point_planes - centre) / size  # (B, 3, h, w) scene units
        position = state.position.detach()
        diffuse, _, d_diffuse, _, _ = shading_and_position_gradients(points, normal_planes, position, 1.0,
                                                                     Falloff.INVERSE_SQUARE, with_specular=False)
        method = ShadowMethod(shadows)
        if method is ShadowMethod.NONE:
            visibility = torch.ones_like(diffuse)
        else:
            visibility = shadow_visibility(method, g.points, g.mask, g.intrinsics, grid.metres(position), shadow_options)
        mask = g.mask[:, None].to(diffuse.dtype)
        transport = diffuse * visibility * mask
        gain = state.presence.detach() * state.log_gain.detach().exp()  # (B, K)
        ambient = state.log_ambient.detach().exp()
        lights = ambient[:, None, None] + (gain[:, :, None, None] * transport).sum(1)
        r2 = radius_squared(grid)
        lens = lens_log_factor(state.vignetting.detach(), r2).exp()
        shading = lights * lens
        if not jacobian:
            return Rerender(transport, visibility, shading)
        per_slot = gain[:, :, None, None, None] * (d_diffuse * (visibility * mask)[..., None])  # (B, K, h, w, 3)
        K = position.shape[1]
        columns = [per_slot[:, k] for k in range(K)]
        columns += [(gain[:, k, None, None] * transport[:, k])[..., None] for k in range(1, K)]
        columns.append(ambient[:, None, None, None].expand(-1, *shading.shape[1:], 1))
        jac = torch.cat(columns, -1) / lights[..., None]
        d_lens = -2 * r2 / (1 + state.vignetting.detach()[:, None, None] * r2)
        jac = torch.cat([jac, d_lens[..., None]], -1)
        return Rerender(transport, visibility, shading, jac)


def pair_differences(x: Tensor, offset: tuple[int, int]) -> Tensor:
    """``x[..., i + dy, j + dx, ...] - x[..., i, j, ...]`` over the pairs inside the grid.

    Args:
        x: ``(B, h, w, ...)``; offset ``(dy, dx)``.
    Returns:
        ``(B, h - dy, w - dx, ...)``.
    """
    dy, dx = offset
    h, w = x.shape[1:3]
    return x[:, dy:, dx:] - x[:, : h - dy, : w - dx]


def pair_usable(usable: Tensor, offset: tuple[int, int]) -> Tensor:
    """``(B, h - dy, w - dx)``: both pixels of each pair usable (``usable (B, h, w)`` bool)."""
    dy, dx = offset
    h, w = usable.shape[1:3]
    return usable[:, dy:, dx:] & usable[:, : h - dy, : w - dx]


def pair_weight_maps(weights: Tensor, offset_index: int) -> Tensor:
    """The pair weights of offset ``offset_index`` from the network's ``(B, 4, h, w)``
    maps: each pair takes the mean of its two pixels' values (symmetric in the pair)."""
    dy, dx = PAIR_OFFSETS[offset_index]
    w = weights[:, offset_index]
    h, wd = w.shape[1:3]
    return 0.5 * (w[:, dy:, dx:] + w[:, : h - dy, : wd - dx])


def log_residual(observed: Tensor, shading: Tensor, usable: Tensor) -> Tensor:
    """``(B, h, w)``: ``observed - log S`` less its median over the usable pixels (the
    albedo's and the intensity's common scale), 0 elsewhere."""
    difference = observed - shading.clamp_min(1e-12).log()
    centre = torch.where(usable, difference, torch.full_like(difference, float("nan"))).flatten(1).nanmedian(1).values
    centre = torch.nan_to_num(centre, nan=0.0)
    return torch.where(usable, difference - centre[:, None, None], torch.zeros_like(difference))


def gauss_newton_step(state: LightState, observed: Tensor, usable: Tensor, render: Rerender, weights: Tensor,
                      damping: Tensor) -> tuple[LightState, Tensor]:
    """One damped Gauss-Newton step of the weighted pair residuals.

    Args:
        state: the lights the re-render was made of (taken as constants).
        observed: ``(B, h, w)`` the frame's log grey level (:func:`selfsup.network.grid.grey_log`).
        usable: ``(B, h, w)`` bool.
        render: :func:`rerender` of ``state`` with its Jacobian.
        weights: ``(B, 4, h, w)`` in [0, 1] per pixel and pair offset (:data:`PAIR_OFFSETS`);
            differentiable: the step is a smooth function of them.
        damping: ``(B,)`` > 0, Levenberg-Marquardt's ``lambda`` (relative to the diagonal).

    Returns:
        The new state (its positions, gains and ambient depend on ``weights`` and
        ``damping``; its presence is ``state``'s) and the weighted cost before the step
        ``(B,)`` (the mean weighted squared pair residual).
    """
    model = render.shading.clamp_min(1e-12).log()
    J = render.jacobian
    n = J.shape[-1]
    B = observed.shape[0]
    normal = observed.new_zeros(B, n, n)
    rhs = observed.new_zeros(B, n)
    cost = observed.new_zeros(B)
    total = observed.new_zeros(B)
    for index, offset in enumerate(PAIR_OFFSETS):
        r = pair_differences(observed - model, offset)  # (B, h', w')
        Jr = -pair_differences(J, offset)  # (B, h', w', n): d r / d params
        valid = pair_usable(usable, offset).to(r.dtype)
        prior = valid / (1 + (r / CAUCHY_SCALE) ** 2)
        w = pair_weight_maps(weights, index) * prior  # (B, h', w')
        Jw = (Jr * w[..., None]).flatten(1, 2)  # (B, P, n)
        flat = Jr.flatten(1, 2)
        normal = normal + Jw.transpose(1, 2) @ flat
        rhs = rhs + (Jw * r.flatten(1)[..., None]).sum(1)
        cost = cost + (w * r * r).flatten(1).sum(1)
        total = total + w.flatten(1).sum(1)
    diagonal = normal.diagonal(dim1=-2, dim2=-1)
    # LM: lambda times the diagonal, plus a floor of 1e-6 of its mean so that a parameter
    # nothing constrains (an absent slot) stays where it is instead of making the system singular.
    floor = 1e-6 * diagonal.mean(-1, keepdim=True).clamp_min(1e-12)
    system = normal + torch.diag_embed(damping[:, None] * diagonal + floor)
    delta = -torch.linalg.solve(system, rhs[..., None])[..., 0]  # (B, n)
    K = state.position.shape[1]
    move = delta[:, : 3 * K].view(B, K, 3)
    # A step longer than MAX_MOVE is shortened along its direction (its direction still learns).
    length = move.norm(dim=-1, keepdim=True)
    move = move * (MAX_MOVE / length.clamp_min(MAX_MOVE))
    gains = delta[:, 3 * K : 4 * K - 1].clamp(-LOG_STEP, LOG_STEP)
    log_gain = torch.cat([state.log_gain[:, :1], (state.log_gain[:, 1:] + gains).clamp(*LOG_GAIN_RANGE)], 1)
    log_ambient = state.log_ambient + delta[:, -2].clamp(-LOG_STEP, LOG_STEP)
    # The lens: a in [0, MAX_VIGNETTING] (a corner at r^2 = 0.5 then loses up to 3/4 of the light).
    vignetting = (state.vignetting + delta[:, -1]).clamp(0.0, MAX_VIGNETTING)
    new = LightState(state.position + move, log_gain, log_ambient.clamp(-12.0, 4.0), state.presence, vignetting)
    return new, cost / total.clamp_min(1e-12)
