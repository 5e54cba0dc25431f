"""Functional form of the shadowed Blinn-Phong renderer.

Image model (``docs/scene-format.md``), per pixel point ``X`` and light ``i``::

    I = kd * L_a + sum_i S_i * I_i * f(d_i) * (kd * max(0, n.l_i) + ks * max(0, n.h_i)^alpha)
        [+ strength * kd * gain * sum_i I_i G_i   with indirect="bounce": render.indirect]

where a material with a clear coat (``Material.coat``) has its diffuse term
multiplied by the rough coat's transmission in and out (:mod:`render.coat`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from render.coat import CoatProfile, coat_profile, coat_transmission, profile_transmission
from render.geometry import dot3, fit_intrinsics, norm3
from render.indirect import INDIRECT_MODES, bounce_image
from render.shading import Falloff, planar_lobe, planar_shading, shading_and_position_gradients
from render.shadows import ShadowMethod, shadow_visibility
from render.types import GBuffer, Material, PointLights, check_ambient

__all__ = ["RenderOutput", "LightTransport", "TransportJacobian", "render", "render_image", "light_transport",
           "light_transport_jacobian"]


@dataclass(frozen=True)
class RenderOutput:
    """The rendered image and its parts.

    Attributes:
        image: ``(B, 3, H, W)``, the sum of the terms below; 0 on invalid pixels.
        ambient: ``(B, 3, H, W)``, ``kd * L_a``.
        diffuse: ``(B, 3, H, W)``, shadowed diffuse light summed over lights.
        specular: ``(B, 3, H, W)`` or None when the specular term was skipped.
        visibility: ``(B, L, H, W)`` per-light shadow term ``S_i`` in [0, 1]: cast
            shadows times the attached shadow ``n . l > 0``; None when shadows are off.
        indirect: ``(B, 3, H, W)`` the lights' light bounced off the visible surfaces
            (``indirect="bounce"``, :mod:`render.indirect`), or None without it.
    """

    image: Tensor
    ambient: Tensor
    diffuse: Tensor
    specular: Tensor | None
    visibility: Tensor | None
    indirect: Tensor | None = None


def _wants_specular(material: Material, specular: bool | str) -> bool:
    if specular == "auto":
        if material.ks is None:
            return False
        if torch.compiler.is_compiling():
            return True
        return bool((material.ks != 0).any())
    if not isinstance(specular, bool):
        raise ValueError(f"specular must be True, False or 'auto', got {specular!r}")
    return specular and material.ks is not None


@dataclass(frozen=True)
class LightTransport:
    """Per-light scalar transport of unit white lights; the image is linear in it::

        image = kd * (L_a + sum_i I_i * diffuse_i) + ks * sum_i I_i * specular_i

    Attributes:
        diffuse: ``(B, L, H, W)``, ``S_i f(d_i) max(0, n.l_i)``, times the coat's
            transmission in and out where ``material.coat`` is set.
        specular: ``(B, L, H, W)`` ``S_i f(d_i) max(0, n.h_i)^alpha``, or None when skipped.
        visibility: ``(B, L, H, W)`` shadow term (attached shadow included), or None
            when shadows are off.
    """

    diffuse: Tensor
    specular: Tensor | None
    visibility: Tensor | None


def _shadow_intrinsics(gbuffer: GBuffer, shadows: ShadowMethod) -> Tensor | None:
    # The epipolar sweep needs K; a G-buffer without one gets it fitted to its points.
    if shadows is ShadowMethod.EPIPOLAR and gbuffer.intrinsics is None:
        return fit_intrinsics(gbuffer.points.detach(), gbuffer.mask)
    return gbuffer.intrinsics


def _shininess(material: Material) -> Tensor:
    # alpha broadcastable to (B, L, H, W): (B|1, 1, H|1, W|1) or a scalar.
    shininess = material.shininess_map()
    return shininess[:, None] if shininess.dim() == 3 else shininess


def _coat(gbuffer: GBuffer, material: Material):
    # The coat as a factor of the diffuse term's cosine c = n.l: g(c) -> (T(c) T_o, T'(c) T_o),
    # c broadcastable to (B, L, H, W), T the coat's transmission in, T_o (B, 1, H, W) out,
    # towards the camera (render.shading.shading_and_position_gradients' cosine_factor). None
    # without a coat.
    if material.coat is None:
        return None
    dtype = gbuffer.points.dtype
    coat = material.coat[..., 0][:, None].to(dtype)
    shininess = _shininess(material)
    profile = _coat_profile(material, coat, shininess, dtype)
    if profile is None:
        def transmit(cosine: Tensor) -> tuple[Tensor, Tensor]:
            return coat_transmission(cosine, coat, shininess, material.coat_f0)
    else:
        def transmit(cosine: Tensor) -> tuple[Tensor, Tensor]:
            return profile_transmission(cosine, profile)
    points = gbuffer.points[:, None]
    n_dot_v = -dot3(gbuffer.normals[:, None], points) / norm3(points).clamp_min(torch.finfo(points.dtype).tiny)
    outward = transmit(n_dot_v)[0]

    def cosine_factor(cosine: Tensor) -> tuple[Tensor, Tensor]:
        inward, slope = transmit(cosine)
        return inward * outward, slope * outward
    return cosine_factor


def _coat_profile(material: Material, coat: Tensor, shininess: Tensor, dtype: torch.dtype) -> CoatProfile | None:
    # The material's CoatProfile, kept on it between calls (a solver renders one material
    # hundreds of times) and found again when coat or shininess changed in place (their
    # version counters) or the dtype or device differ. None (coat_transmission, which
    # differentiates them) where either needs a gradient, under torch.compile, or for a
    # shininess texture with too many distinct values.
    if (torch.is_grad_enabled() and (coat.requires_grad or shininess.requires_grad)) or torch.compiler.is_compiling():
        return None
    key = (dtype, coat.device, material.coat._version, material.shininess._version, material.coat_f0)
    cached = material.__dict__.get("_coat_profile")
    if cached is not None and cached[0] == key:
        return cached[1]
    profile = coat_profile(coat, shininess, material.coat_f0, dtype)
    object.__setattr__(material, "_coat_profile", (key, profile))
    return profile


def _transport(gbuffer, material, light_position, falloff, shadows, shadow_options, with_specular) -> LightTransport:
    geometry = planar_shading(*gbuffer.planes(), light_position, falloff)
    n_dot_l = geometry.n_dot_l
    # Per-light scalar weights (B, L, H, W); RGB enters only where the caller sums lights.
    weight = geometry.falloff
    visibility = None
    if shadows is not ShadowMethod.NONE:
        visibility = shadow_visibility(shadows, gbuffer.points, gbuffer.mask, _shadow_intrinsics(gbuffer, shadows),
                                       light_position, shadow_options)
        # A surface facing away from the light cannot see it (attached shadow):
        # with shadows on, S_i includes that, as an exact shadow ray would. The
        # diffuse term is already 0 there; this gates the specular lobe.
        visibility = visibility * (n_dot_l > 0).to(visibility.dtype)
        weight = weight * visibility
    specular = None
    if with_specular:
        specular = weight * planar_lobe(geometry, _shininess(material))
    diffuse = weight * n_dot_l.clamp_min(0)
    cosine_factor = _coat(gbuffer, material)
    if cosine_factor is not None:
        diffuse = diffuse * cosine_factor(n_dot_l)[0]
    return LightTransport(diffuse=diffuse, specular=specular, visibility=visibility)


def light_transport(
    gbuffer: GBuffer,
    material: Material,
    light_position: Tensor,
    *,
    falloff: Falloff | str = Falloff.INVERSE_SQUARE,
    shadows: ShadowMethod | str = ShadowMethod.EPIPOLAR,
    shadow_options=None,
    specular: bool = True,
) -> LightTransport:
    """Per-light transport maps of lights at ``light_position (B, L, 3)`` with unit intensity.

    The image of any intensities ``I (B, L, 3)`` and ambient follows linearly (see
    :class:`LightTransport`), which is what per-image solvers use to solve the
    intensities in closed form. Only the diffuse map is computed when ``specular``
    is False or ``material.ks`` is None. Inputs are not checked for NaN here.

    Example:
        >>> g = GBuffer.from_depth(torch.full((1, 8, 8), 2.0), torch.tensor([[[8.0, 0, 3.5], [0, 8.0, 3.5], [0, 0, 1]]]))
        >>> t = light_transport(g, Material(kd=torch.full((1, 8, 8, 3), 0.5)), torch.tensor([[[0.0, -1.0, 0.0]]]))
        >>> t.diffuse.shape
        torch.Size([1, 1, 8, 8])
    """
    B = gbuffer.mask.shape[0]
    if light_position.dim() != 3 or light_position.shape[0] != B or light_position.shape[2] != 3:
        raise ValueError(f"light_position must have shape ({B}, L, 3), got {tuple(light_position.shape)}")
    with_specular = bool(specular) and material.ks is not None
    return _transport(gbuffer, material, light_position, Falloff(falloff), ShadowMethod(shadows), shadow_options,
                      with_specular)


@dataclass(frozen=True)
class TransportJacobian:
    """:class:`LightTransport` at some light positions and its derivatives with respect
    to them: ``diffuse``, ``specular``: ``(B, L, H, W, 3)``, ``d transport_i / d p_i``
    (a light's maps depend on its own position only); specular None when skipped."""

    transport: LightTransport
    diffuse: Tensor
    specular: Tensor | None


@torch.no_grad()
def light_transport_jacobian(
    gbuffer: GBuffer,
    material: Material,
    light_position: Tensor,
    fd_step: Tensor | float,
    *,
    falloff: Falloff | str = Falloff.INVERSE_SQUARE,
    shadows: ShadowMethod | str = ShadowMethod.EPIPOLAR,
    shadow_options=None,
    specular: bool = True,
) -> TransportJacobian:
    """The transport maps of :func:`light_transport` and their Jacobian with respect to
    each light's position ``(B, L, 3)``, for Gauss-Newton solvers.

    Shading is differentiated exactly (:func:`render.shading.shading_and_position_gradients`).
    Cast-shadow visibility ``S`` is differentiated by forward differences of step
    ``fd_step`` (metres, a float or ``(B,)``): three more visibility maps per light,
    the finite-difference shadow Jacobian of the paper; the attached shadow
    ``n.l > 0`` counts as constant. Cost: about one transport render with
    ``shadows="none"``, plus three shadow sweeps otherwise. No autograd graph.
    """
    B = gbuffer.mask.shape[0]
    if light_position.dim() != 3 or light_position.shape[0] != B or light_position.shape[2] != 3:
        raise ValueError(f"light_position must have shape ({B}, L, 3), got {tuple(light_position.shape)}")
    falloff, shadows = Falloff(falloff), ShadowMethod(shadows)
    with_specular = bool(specular) and material.ks is not None
    diffuse, spec, d_diffuse, d_specular, n_dot_l = shading_and_position_gradients(
        *gbuffer.planes(), light_position, _shininess(material), falloff, with_specular,
        _coat(gbuffer, material))
    if shadows is ShadowMethod.NONE:
        return TransportJacobian(LightTransport(diffuse, spec, None), d_diffuse, d_specular)

    K = _shadow_intrinsics(gbuffer, shadows)
    cast = shadow_visibility(shadows, gbuffer.points, gbuffer.mask, K, light_position, shadow_options)
    step = torch.as_tensor(fd_step, dtype=light_position.dtype, device=light_position.device).expand(B)
    eye3 = torch.eye(3, dtype=light_position.dtype, device=light_position.device)
    shifted = (light_position[None] + step[None, :, None, None] * eye3[:, None, None, :]).flatten(0, 1)  # (3B, L, 3)
    cast_shifted = shadow_visibility(shadows, gbuffer.points.repeat(3, 1, 1, 1), gbuffer.mask.repeat(3, 1, 1),
                                     None if K is None else K.repeat(3, 1, 1), shifted, shadow_options)
    d_cast = ((cast_shifted.unflatten(0, (3, B)) - cast[None]) / step[None, :, None, None, None]).permute(1, 2, 3, 4, 0)
    attached = (n_dot_l > 0).to(cast.dtype)
    visibility = cast * attached

    def shadowed(value: Tensor, derivative: Tensor) -> Tensor:
        # d(S v)/dp = S dv/dp + v dS/dp, S = cast * attached (attached held constant)
        return visibility[..., None] * derivative + (attached * value)[..., None] * d_cast

    transport = LightTransport(diffuse * visibility, None if spec is None else spec * visibility, visibility)
    return TransportJacobian(transport, shadowed(diffuse, d_diffuse),
                             None if spec is None else shadowed(spec, d_specular))


def _checked_ambient(gbuffer: GBuffer, material: Material, lights: PointLights, ambient: Tensor | None,
                     check_finite: bool, indirect: str) -> Tensor:
    # render's inputs checked (shapes, NaN/inf where asked, the indirect mode); the ambient (B, 3).
    B, H, W = gbuffer.mask.shape
    if material.kd.shape[0] not in (1, B) or material.kd.shape[1:3] != (H, W):
        raise ValueError(
            f"material kd must have shape ({B} or 1, {H}, {W}, 3) to match the G-buffer, "
            f"got {tuple(material.kd.shape)}"
        )
    if lights.position.shape[0] != B:
        raise ValueError(f"lights must have batch size {B}, got {lights.position.shape[0]}")
    la = check_ambient(ambient, B, gbuffer.points)
    if check_finite and not torch.compiler.is_compiling():
        gbuffer.check_finite()
        material.check_finite()
        lights.check_finite()
        if not bool(torch.isfinite(la).all()):
            raise ValueError("ambient holds non-finite values")
    if indirect not in INDIRECT_MODES:
        raise ValueError(f"indirect must be one of {INDIRECT_MODES}, got {indirect!r}")
    if indirect == "bounce" and gbuffer.intrinsics is None:
        raise ValueError("indirect='bounce' needs the G-buffer's intrinsics (a pixel's area): build it with "
                         "GBuffer.from_depth(depth, K)")
    return la


def render(
    gbuffer: GBuffer,
    material: Material,
    lights: PointLights,
    ambient: Tensor | None = None,
    *,
    falloff: Falloff | str = Falloff.INVERSE_SQUARE,
    shadows: ShadowMethod | str = ShadowMethod.EPIPOLAR,
    shadow_options=None,
    diffuse: bool = True,
    specular: bool | str = "auto",
    check_finite: bool = True,
    indirect: str = "none",
    indirect_strength: Tensor | float = 1.0,
) -> RenderOutput:
    """Render the G-buffer under point lights with Blinn-Phong shading and cast shadows.

    Args:
        gbuffer: geometry, ``points/normals (B, H, W, 3)``, ``mask (B, H, W)``.
        material: ``kd (B|1, H, W, 3)``, ``ks (B|1, H, W, 1|3)`` or None, shininess.
        lights: ``position (B, L, 3)``, ``intensity (B, L, 3)``; L may be 0.
        ambient: ambient illumination ``L_a``, ``(B, 3)`` or ``(3,)``; None for none.
        falloff: ``"inverse_square"`` (1/d^2) or ``"none"``.
        shadows: ``"epipolar"`` (default), ``"paper"`` or ``"none"``. Cost:
            ``none`` is free; ``epipolar`` sweeps about 3-12 samples per pixel and
            light; ``paper`` scatters (2r+1)^2 splats per pixel and light, 7 times
            when the light position needs a gradient.
        shadow_options: the method's options dataclass (see :mod:`render.shadows`).
        diffuse: compute the diffuse term (False renders ambient + specular only).
        specular: True, False or ``"auto"`` (default: skip when ``ks`` is None or
            zero everywhere; the check costs one device sync per call).
        check_finite: raise ValueError on NaN/inf in valid inputs (one device sync);
            set False inside hot loops whose inputs are known to be finite.
        indirect: ``"none"`` (default) or ``"bounce"``: the lights' light reflected off the
            visible surfaces (:func:`render.indirect.bounce_image`; needs ``gbuffer.intrinsics``).
        indirect_strength: the bounce's factor, a number or ``(B,)`` (1: as modelled; 0: none).

    Returns:
        :class:`RenderOutput`. Everything is linear in the light intensities and the
        ambient; costs grow linearly with the number of lights.

    Example:
        >>> depth = torch.full((1, 8, 8), 2.0)
        >>> K = torch.tensor([[[8.0, 0, 3.5], [0, 8.0, 3.5], [0, 0, 1]]])
        >>> g = GBuffer.from_depth(depth, K)
        >>> lights = PointLights(position=torch.tensor([[[0.0, -1.0, 0.0]]]), intensity=torch.ones(1, 1, 3))
        >>> out = render(g, Material(kd=torch.full((1, 8, 8, 3), 0.5)), lights)
        >>> out.image.shape
        torch.Size([1, 3, 8, 8])
    """
    B, H, W = gbuffer.mask.shape
    la = _checked_ambient(gbuffer, material, lights, ambient, check_finite, indirect)
    falloff = Falloff(falloff)
    shadows = ShadowMethod(shadows)

    mask = gbuffer.mask[..., None].to(gbuffer.points.dtype)  # (B, H, W, 1)
    kd = material.kd
    ambient_term = kd * la[:, None, None, :] * mask
    with_specular = _wants_specular(material, specular)
    visibility = None
    diffuse_term = torch.zeros_like(ambient_term)
    specular_term = torch.zeros_like(ambient_term) if with_specular else None
    indirect_term = None

    if lights.num_lights > 0 and (diffuse or with_specular or indirect == "bounce"):
        transport = _transport(gbuffer, material, lights.position, falloff, shadows, shadow_options, with_specular)
        visibility = transport.visibility

        def sum_over_lights(per_light: Tensor) -> Tensor:
            # (B, L, H, W) x (B, L, 3) -> (B, H, W, 3)
            return torch.einsum("blhw,blc->bhwc", per_light, lights.intensity)

        if diffuse:
            diffuse_term = kd * sum_over_lights(transport.diffuse) * mask
        if with_specular:
            specular_term = material.ks * sum_over_lights(transport.specular) * mask
        if indirect == "bounce":
            kd_full = kd.expand(B, H, W, 3)
            indirect_term = bounce_image(gbuffer, kd_full, transport.diffuse, lights.intensity,
                                         indirect_strength).permute(0, 2, 3, 1)

    image = ambient_term + diffuse_term
    if specular_term is not None:
        image = image + specular_term
    if indirect_term is not None:
        image = image + indirect_term

    # The one place where channel-last geometry becomes channel-first images.
    def to_chw(t: Tensor | None) -> Tensor | None:
        return None if t is None else t.permute(0, 3, 1, 2)

    return RenderOutput(
        image=to_chw(image),
        ambient=to_chw(ambient_term),
        diffuse=to_chw(diffuse_term),
        specular=to_chw(specular_term),
        visibility=visibility,
        indirect=to_chw(indirect_term),
    )


def render_image(*args, **kwargs) -> Tensor:
    """Like :func:`render`, returning only the image ``(B, 3, H, W)``."""
    return render(*args, **kwargs).image
