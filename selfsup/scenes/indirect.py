"""Indirect light for the generator and the estimator: :mod:`render.indirect`'s bounce, in their terms.

The first bounce between the surfaces a G-buffer sees, and the later ones as a geometric
series, live in the renderer (:mod:`render.indirect`: ``render(..., indirect="bounce")``,
:class:`render.ShadowedBlinnPhong`); this module is its one implementation under the names
the generator and the estimator use:

- model selection (:mod:`selfsup.estimation`, ``estimate.indirect``): each light's basis
  images carry its bounce (:func:`indirect_columns`), so a stand-in light for the bounce no
  longer pays for itself;
- the generator adds it to training scenes (:func:`with_bounce`, ``degradations.indirect``):
  a network that has never seen a bounce takes it for a second light.
"""

from __future__ import annotations

from torch import Tensor

from render import GBuffer, Material, light_transport
from render.indirect import PATCHES_ACROSS, bounce_gain, bounce_image, bounce_transport, one_bounce
from render.shading import Falloff

__all__ = ["one_bounce", "bounce_gain", "indirect_columns", "with_bounce"]


def indirect_columns(gbuffer: GBuffer, kd: Tensor, diffuse: Tensor, patches_across: int = PATCHES_ACROSS) -> Tensor:
    """Indirect light ``(B, 3, L, H, W)`` of unit-intensity lights, per channel, to be added to
    their direct basis images (:func:`selfsup.linear.basis_images`): the renderer's
    :func:`render.indirect.bounce_transport`."""
    return bounce_transport(gbuffer, kd, diffuse, patches_across)


def with_bounce(image: Tensor, gbuffer: GBuffer, kd: Tensor, light_position: Tensor, light_intensity: Tensor,
                visibility: Tensor, strength: Tensor | float, inverse_square: bool = True) -> Tensor:
    """``image (B, 3, H, W)`` plus ``strength`` times the indirect light of its lights:
    ``kd * bounce_gain * sum_i I_i G_i`` (:func:`indirect_columns`), each light's bounce
    from its shadowed direct diffuse transport.

    Args:
        gbuffer: with intrinsics; kd ``(B, H, W, 3)``.
        light_position, light_intensity: ``(B, L, 3)`` (an unused slot has intensity 0).
        visibility: ``(B, L, H, W)`` in [0, 1] (1 lit).
        strength: a number or ``(B,)``: 1 is the first bounce and the later ones of
            :func:`bounce_gain`.
    """
    direct = light_transport(gbuffer, Material(kd=kd), light_position, shadows="none", specular=False,
                             falloff=Falloff.INVERSE_SQUARE if inverse_square else Falloff.NONE).diffuse
    return image + bounce_image(gbuffer, kd, direct * visibility, light_intensity, strength).to(image.dtype)
