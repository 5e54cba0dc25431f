"""Cast shadows of point lights, one module per method, one entry point.

Methods (see :class:`ShadowMethod`):

- ``epipolar`` (default): the depth map as a watertight heightfield, swept along
  epipolar lines; smooth visibility with an exact gradient for that smoothed model.
- ``paper``: cube shadow maps of point splats, binary, with the finite-difference
  Jacobian of Nieto et al. (six more maps per light when a gradient is needed).
- ``none``: every pixel sees every light.
"""

from __future__ import annotations

from enum import Enum

from torch import Tensor

from render.shadows.cubemap import CubeShadowOptions, cube_shadow_visibility
from render.shadows.epipolar import EpipolarShadowOptions, epipolar_shadow_visibility

__all__ = [
    "ShadowMethod",
    "CubeShadowOptions",
    "EpipolarShadowOptions",
    "cube_shadow_visibility",
    "epipolar_shadow_visibility",
    "shadow_visibility",
    "default_options",
]


class ShadowMethod(str, Enum):
    NONE = "none"
    PAPER = "paper"
    EPIPOLAR = "epipolar"


_OPTIONS = {ShadowMethod.PAPER: CubeShadowOptions, ShadowMethod.EPIPOLAR: EpipolarShadowOptions}


def default_options(method: ShadowMethod | str, **overrides):
    """The options dataclass of ``method`` with ``overrides`` applied (None for ``none``)."""
    method = ShadowMethod(method)
    if method is ShadowMethod.NONE:
        if overrides:
            raise ValueError(f"shadow method 'none' takes no options, got {sorted(overrides)}")
        return None
    return _OPTIONS[method](**overrides)


def shadow_visibility(
    method: ShadowMethod | str,
    points: Tensor,
    mask: Tensor,
    intrinsics: Tensor | None,
    light_position: Tensor,
    options=None,
) -> Tensor | None:
    """Visibility ``(B, L, H, W)`` of each pixel from each light, or None for ``none``.

    Args:
        method: which method (:class:`ShadowMethod` or its name).
        points: ``(B, H, W, 3)``; mask: ``(B, H, W)`` bool; intrinsics: ``(B, 3, 3)``
            (needed by ``epipolar``); light_position: ``(B, L, 3)``.
        options: the method's options dataclass, or None for its defaults.
    """
    method = ShadowMethod(method)
    if method is ShadowMethod.NONE:
        return None
    if options is not None and not isinstance(options, _OPTIONS[method]):
        raise TypeError(f"shadow method {method.value!r} needs {_OPTIONS[method].__name__}, got {type(options).__name__}")
    if points.shape[0] == 0 or light_position.shape[1] == 0:  # no image or no light: nothing to cast
        return points.new_ones(points.shape[0], light_position.shape[1], *points.shape[1:3])
    if method is ShadowMethod.PAPER:
        return cube_shadow_visibility(points, mask, light_position, options)
    if intrinsics is None:
        raise ValueError("the epipolar shadow method needs the view's intrinsics")
    return epipolar_shadow_visibility(points, mask, intrinsics, light_position, options)
