"""Differentiable, shadow-casting Blinn-Phong rendering of RGB-D views.

Conventions, stated once for the whole package:

- Camera frame, OpenCV: x right, y down, z forward, camera centre at the origin;
  metres. Pixel ``(row i, col j)`` has image coordinates ``u = j, v = i`` and
  3D point ``depth[i, j] * inv(K) @ [j, i, 1]`` (z-depth, not ray length).
- Axis letters: B batch, L lights, H, W image, C channels. Geometry is
  channel-last ``(B, H, W, 3)``; images are ``(B, 3, H, W)``.
- ``to_light``: unit vector from surface to light; ``to_viewer``: from surface to
  the camera centre; ``half = normalize(to_light + to_viewer)``.
- Normals face the camera (``dot(n, -X) > 0``); invalid pixels are masked and hold
  zeros.
- Image model, for light i at distance d_i with visibility S_i in [0, 1]::

      I = kd * L_a + sum_i S_i * I_i * f(d_i) * (kd * max(0, n.l_i) + ks * max(0, n.h_i)^alpha)

  with ``f = 1/d^2`` (``falloff="inverse_square"``, default) or ``f = 1`` (``"none"``).
- dtype and device follow the inputs; nothing here reads files or configs.
"""

from render.functional import (LightTransport, RenderOutput, TransportJacobian, light_transport, light_transport_jacobian,
                               render, render_image)
from render.layer import ShadowedBlinnPhong
from render.shading import Falloff
from render.shadows import CubeShadowOptions, EpipolarShadowOptions, ShadowMethod
from render.types import GBuffer, Material, PointLights

__all__ = [
    "GBuffer",
    "Material",
    "PointLights",
    "ShadowedBlinnPhong",
    "RenderOutput",
    "render",
    "render_image",
    "light_transport",
    "LightTransport",
    "light_transport_jacobian",
    "TransportJacobian",
    "Falloff",
    "ShadowMethod",
    "EpipolarShadowOptions",
    "CubeShadowOptions",
]
