"""Cameras' and rooms' realities in synthetic captures (selfsup/scenes/camera.py)."""

import io

import numpy as np
import pytest
import torch
from PIL import Image

from selfsup.scenes.camera import CameraModel, camera_capture, with_area_lights
from selfsup.scenes.capture import linear_to_srgb
from selfsup.scenes.sampler import SamplerConfig, sample_scene

SMALL = SamplerConfig(height=48, width=64, specular_prob=0.0, n_lights_probs=(1.0,))
OFF = CameraModel(key=None, white_balance=False, vignetting=0.0, jpeg_quality=None, misregistration_px=0.0,
                  disparity_step=0.0, depth_bumps=0.0, edge_holes=0.0, random_holes=0.0)


def _frame(height=48, width=64, colour=(0.3, 0.3, 0.3)):
    image = torch.ones(height, width, 3, dtype=torch.float64) * torch.tensor(colour, dtype=torch.float64)
    depth = torch.full((height, width), 2.0, dtype=torch.float64)
    K = torch.tensor([[50.0, 0, (width - 1) / 2], [0, 50.0, (height - 1) / 2], [0, 0, 1]], dtype=torch.float64)
    return image, depth, K


@pytest.mark.parametrize("kind", ["panel", "window"])
def test_an_area_light_shares_its_intensity_over_a_square_around_its_centre(kind):
    spec = sample_scene(3, SMALL)
    area, centres = with_area_lights(spec, kind, size=0.6, points=3)
    assert area.light_position.shape == (9, 3) and centres.shape == (1, 3)
    assert torch.allclose(area.light_position.mean(0), centres[0], atol=1e-5)
    assert torch.allclose(area.light_relative_intensity.sum(0), spec.light_relative_intensity[0], rtol=1e-5)
    spread = (area.light_position - centres[0]).norm(dim=-1).max()
    assert spread == pytest.approx(0.6 / 3 * np.sqrt(2), rel=1e-4)  # the corner cells' centres
    floor_point, up = spec.prims.planes[0, :3], spec.prims.planes[0, 3:6]
    heights = (area.light_position - floor_point) @ up
    if kind == "panel":  # horizontal, under the room's top
        assert torch.allclose(heights, torch.full_like(heights, spec.meta["room_size_m"][2] - 0.05), atol=1e-4)
    else:  # vertical: its points at every height of the square, in front of the back wall
        wall_point, facing = spec.prims.planes[1, :3], spec.prims.planes[1, 3:6]
        assert torch.allclose((area.light_position - wall_point) @ facing, torch.full_like(heights, 0.15), atol=1e-4)
    with pytest.raises(ValueError, match="kind must be one of"):
        with_area_lights(spec, "bulb")


def test_a_camera_with_every_switch_off_writes_the_recipe():
    image, depth, K = _frame()
    shot = camera_capture(image, depth, K, OFF, seed=0, exposure=2.0)
    expected = np.round(linear_to_srgb(np.clip(image.numpy() * 2.0, 0, 1)) * 255).astype(np.uint8)
    assert np.array_equal(shot.color, expected) and shot.suffix == ".png"
    assert np.array_equal(shot.depth_mm, np.full((48, 64), 2000, dtype=np.uint16))
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(shot.encoded))), expected)
    with pytest.raises(ValueError, match="exposure is needed"):
        camera_capture(image, depth, K, OFF, seed=0)


def test_white_balance_auto_exposure_and_vignetting_act_as_a_camera_does():
    image, depth, K = _frame(colour=(0.4, 0.2, 0.1))
    model = CameraModel(key=(0.2, 0.2), jpeg_quality=None, misregistration_px=0.0, vignetting=0.3,
                        disparity_step=0.0, depth_bumps=0.0, edge_holes=0.0, random_holes=0.0)
    shot = camera_capture(image, depth, K, model, seed=1)
    centre, corner = shot.color[24, 32].astype(int), shot.color[0, 0].astype(int)
    assert max(centre) - min(centre) <= 1  # grey-world gains: the tinted grey surface is grey
    assert corner[0] < centre[0]  # vignetting darkens the corners
    linear_centre = (shot.color[24, 32] / 255.0) ** 2.2
    assert 0.15 < float(linear_centre.mean()) < 0.3  # the mean metered to about the key


def test_phone_sizes_and_a_depth_sensor_follow_the_model():
    image, depth, K = _frame(height=48, width=64)
    depth[:, 32:] = 3.0  # a depth jump: holes beside it
    model = CameraModel(key=None, color_size=(160, 120), depth_size=(32, 24), misregistration_px=2.0)
    shot = camera_capture(image, depth, K, model, seed=2, exposure=1.0)
    assert shot.color.shape == (120, 160, 3) and shot.suffix == ".jpg" and shot.depth_mm.shape == (24, 32)
    assert shot.K[0, 0] == pytest.approx(25.0) and shot.K[0, 2] == pytest.approx((31.5 - 0.5) / 2)
    assert (shot.depth_mm == 0).any() and set(np.unique(shot.depth_mm[shot.depth_mm > 0]) // 100) <= {19, 20, 21, 29, 30, 31}
    with pytest.raises(ValueError, match="must divide the render"):
        camera_capture(image, depth, K, CameraModel(key=None, depth_size=(30, 24)), seed=0, exposure=1.0)
    with pytest.raises(ValueError, match="vignetting"):
        CameraModel(vignetting=1.0)
