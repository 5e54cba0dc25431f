import functools

import pytest
import torch

from render import GBuffer
from selfsup.scenes.analytic import intrinsics_for, objects_on_floor, render_exact_view

# Lights on the camera's side of the objects: where a depth map sees every
# occluder the shadow ray meets (see render/shadows/epipolar.py for the model).
CAMERA_SIDE_LIGHTS = ([0.6, -1.0, 0.5], [-0.8, -0.9, 1.2], [0.2, -1.5, 2.0])


@functools.lru_cache(maxsize=None)
def exact_view(light: tuple, height: int = 120, width: int = 160, ks: float = 0.3, scale: float = 1.0):
    """Exact ray-cast view of the sphere-and-box scene (float64), cached across tests."""
    K = intrinsics_for(height, width)
    lp = torch.tensor([light], dtype=torch.float64) * scale
    return render_exact_view(objects_on_floor(scale), K, height, width, lp, torch.full((1, 3), 10.0 * scale**2), ks=ks)


def gbuffer_of(view, dtype=torch.float64) -> GBuffer:
    return GBuffer(
        points=view.points[None].to(dtype), normals=view.normals[None].to(dtype),
        mask=view.mask[None], intrinsics=view.K[None].to(dtype),
    )


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
