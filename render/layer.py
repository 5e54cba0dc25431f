"""The renderer as a torch layer: a thin module around :func:`render.functional.render`."""

from __future__ import annotations

from torch import Tensor, nn

from render.functional import LightTransport, RenderOutput, light_transport, render
from render.indirect import INDIRECT_MODES
from render.shading import Falloff
from render.shadows import ShadowMethod, default_options
from render.types import GBuffer, Material, PointLights

__all__ = ["ShadowedBlinnPhong"]


class ShadowedBlinnPhong(nn.Module):
    """Differentiable Blinn-Phong shading of a G-buffer with cast shadows of point lights.

    Args:
        falloff: ``"inverse_square"`` (default) or ``"none"``.
        shadows: ``"epipolar"`` (default), ``"paper"`` or ``"none"``.
        shadow_options: options dataclass of the method, or a dict of its fields.
        diffuse: compute the diffuse term.
        specular: True, False or ``"auto"`` (skip when ks is None or all zero).
        check_finite: raise on NaN/inf inputs (costs one device sync per call).
        indirect: ``"none"`` (default) or ``"bounce"``: the lights' light reflected off the
            visible surfaces (:mod:`render.indirect`; the G-buffer needs intrinsics).
        indirect_strength: the bounce's factor (a number; ``forward`` takes a per-image
            ``(B,)`` tensor instead, e.g. a network's or a fit's).

    Shapes: see :func:`render.functional.render`; ``forward`` returns the image
    ``(B, 3, H, W)``, :meth:`render_terms` the :class:`RenderOutput` with the
    separate terms and the per-light visibility ``(B, L, H, W)``.

    Example:
        >>> import torch
        >>> layer = ShadowedBlinnPhong(shadows="epipolar")
        >>> K = torch.tensor([[16.0, 0, 7.5], [0, 16.0, 7.5], [0, 0, 1]])
        >>> g = GBuffer.from_depth(torch.full((2, 16, 16), 3.0), K)
        >>> lights = PointLights(position=torch.tensor([[[0.0, -1, 1]]] * 2, requires_grad=True),
        ...                      intensity=torch.ones(2, 1, 3))
        >>> image = layer(g, Material(kd=torch.full((2, 16, 16, 3), 0.7)), lights, torch.full((2, 3), 0.1))
        >>> image.mean().backward(); lights.position.grad.shape
        torch.Size([2, 1, 3])
    """

    def __init__(
        self,
        *,
        falloff: Falloff | str = Falloff.INVERSE_SQUARE,
        shadows: ShadowMethod | str = ShadowMethod.EPIPOLAR,
        shadow_options=None,
        diffuse: bool = True,
        specular: bool | str = "auto",
        check_finite: bool = True,
        indirect: str = "none",
        indirect_strength: float = 1.0,
    ) -> None:
        super().__init__()
        self.falloff = Falloff(falloff)
        self.shadows = ShadowMethod(shadows)
        if isinstance(shadow_options, dict) or shadow_options is None:
            shadow_options = default_options(self.shadows, **(shadow_options or {}))
        self.shadow_options = shadow_options
        if not isinstance(diffuse, bool) or not (isinstance(specular, bool) or specular == "auto"):
            # Named here: the training loss reads the switch itself ("maybe" trained with the specular term on).
            raise ValueError(f"diffuse must be True or False and specular True, False or 'auto', got {diffuse!r} and "
                             f"{specular!r}")
        self.diffuse = diffuse
        self.specular = specular
        self.check_finite = check_finite
        if indirect not in INDIRECT_MODES:
            raise ValueError(f"indirect must be one of {INDIRECT_MODES}, got {indirect!r}")
        if not (isinstance(indirect_strength, (int, float)) and 0 <= indirect_strength < float("inf")):
            raise ValueError(f"indirect_strength must be a finite number >= 0, got {indirect_strength!r}")
        self.indirect = indirect
        self.indirect_strength = float(indirect_strength)

    def render_terms(
        self, gbuffer: GBuffer, material: Material, lights: PointLights, ambient: Tensor | None = None,
        indirect_strength: Tensor | float | None = None,
    ) -> RenderOutput:
        """The image and its terms (:class:`render.functional.RenderOutput`); ``indirect_strength``
        (a number or ``(B,)``) overrides the layer's for this call."""
        return render(
            gbuffer, material, lights, ambient,
            falloff=self.falloff, shadows=self.shadows, shadow_options=self.shadow_options,
            diffuse=self.diffuse, specular=self.specular, check_finite=self.check_finite, indirect=self.indirect,
            indirect_strength=self.indirect_strength if indirect_strength is None else indirect_strength,
        )

    def transport(self, gbuffer: GBuffer, material: Material, light_position: Tensor) -> LightTransport:
        """Per-light transport maps ``(B, L, H, W)`` of unit lights at ``light_position (B, L, 3)``
        with this layer's options (see :func:`render.functional.light_transport`)."""
        return light_transport(
            gbuffer, material, light_position, falloff=self.falloff, shadows=self.shadows,
            shadow_options=self.shadow_options, specular=self.specular is not False,
        )

    def forward(
        self, gbuffer: GBuffer, material: Material, lights: PointLights, ambient: Tensor | None = None,
        indirect_strength: Tensor | float | None = None,
    ) -> Tensor:
        return self.render_terms(gbuffer, material, lights, ambient, indirect_strength).image

    def extra_repr(self) -> str:
        extra = f", indirect={self.indirect}, indirect_strength={self.indirect_strength}" if self.indirect != "none" else ""
        return f"falloff={self.falloff.value}, shadows={self.shadows.value}, specular={self.specular!r}{extra}"
