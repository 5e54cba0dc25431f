"""Hard cases: finite images and finite gradients in float32, for every shadow method."""

import pytest
import torch

from render import GBuffer, Material, PointLights, ShadowedBlinnPhong
from tests.conftest import exact_view

H, W = 24, 32


def _scene(scale=1.0):
    view = exact_view((0.2, -1.5, 2.0), H, W, scale=scale)
    depth = view.depth.float()[None]
    return depth, view.K.float()


def _light_cases():
    # (name, light position in a unit-scale scene, depth edit)
    return [
        ("grazing", [-3.0, 0.999, 4.0]),
        ("behind the floor", [0.0, 1.5, 4.0]),
        ("1 mm above the floor", [0.0, 0.999, 3.0]),
        ("on the floor", [0.0, 1.0, 3.0]),
        ("inside the sphere", [-0.4, 0.5, 4.0]),
        ("at the camera", [0.0, 0.0, 0.0]),
        ("behind the camera", [0.5, -0.5, -2.0]),
        ("in the camera plane", [2.0, -1.0, 0.0]),
        ("far away", [1e4, -1e4, 1e4]),
    ]


def _check(layer, gbuffer, material, position, intensity, ambient=None):
    position = position.clone().requires_grad_(True)
    intensity = intensity.clone().requires_grad_(True)
    image = layer(gbuffer, material, PointLights(position=position, intensity=intensity), ambient)
    assert torch.isfinite(image).all()
    image.square().mean().backward()
    assert torch.isfinite(position.grad).all() and torch.isfinite(intensity.grad).all()
    return image


@pytest.mark.parametrize("method", ["epipolar", "paper", "none"])
@pytest.mark.parametrize("name,light", _light_cases(), ids=[c[0] for c in _light_cases()])
def test_hard_light_positions(method, name, light):
    depth, K = _scene()
    g = GBuffer.from_depth(depth, K)
    mat = Material(kd=torch.full((1, H, W, 3), 0.5), ks=torch.full((1, H, W, 1), 0.5), shininess=1000.0)
    _check(ShadowedBlinnPhong(shadows=method), g, mat, torch.tensor([[light]]), torch.full((1, 1, 3), 5.0))


@pytest.mark.parametrize("method", ["epipolar", "paper"])
@pytest.mark.parametrize("shininess", [1.0, 10.0, 1000.0])
def test_shininess_range(method, shininess):
    depth, K = _scene()
    g = GBuffer.from_depth(depth, K)
    mat = Material(kd=torch.full((1, H, W, 3), 0.5), ks=torch.full((1, H, W, 3), 1.0), shininess=shininess)
    _check(ShadowedBlinnPhong(shadows=method), g, mat, torch.tensor([[[0.0, -0.5, 0.5]]]), torch.ones(1, 1, 3))


@pytest.mark.parametrize("method", ["epipolar", "paper"])
def test_holes_zero_normals_and_mixed_batch(method):
    depth, K = _scene()
    depth = depth.expand(3, H, W).clone()
    depth[0, ::3, ::2] = 0  # many holes
    depth[1] = float("nan")  # an image with no valid pixel at all
    normals = torch.zeros(3, H, W, 3)
    normals[..., 2] = -1
    normals[2, 5:10] = 0  # missing normals
    g = GBuffer.from_depth(depth, K, normals=normals)
    assert not g.mask[1].any()
    mat = Material(kd=torch.full((1, H, W, 3), 0.5))
    position = torch.tensor([[[0.3, -1.0, 1.0]]]).expand(3, 1, 3)
    intensity = torch.tensor([[[1.0, 1, 1]], [[1.0, 1, 1]], [[0.0, 0, 0]]])  # zero intensity too
    image = _check(ShadowedBlinnPhong(shadows=method), g, mat, position, intensity, torch.full((3, 3), 0.1))
    assert (image[1] == 0).all()
    assert (image[:, :, ~g.mask[0]][0] == 0).all()


@pytest.mark.parametrize("method", ["epipolar", "paper"])
@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_tiny_and_huge_scenes_render_the_same_picture(method, scale):
    # Scaling the scene, lights and intensities (by scale^2 for 1/d^2) leaves the image unchanged.
    depth, K = _scene()
    mat = Material(kd=torch.full((1, H, W, 3), 0.5))
    layer = ShadowedBlinnPhong(shadows=method)
    ref = _check(layer, GBuffer.from_depth(depth, K), mat, torch.tensor([[[0.2, -1.5, 2.0]]]), torch.full((1, 1, 3), 10.0))
    scaled = _check(layer, GBuffer.from_depth(depth * scale, K), mat, torch.tensor([[[0.2, -1.5, 2.0]]]) * scale,
                    torch.full((1, 1, 3), 10.0 * scale**2))
    assert (scaled - ref).abs().max() < 1e-3 * ref.abs().max()


@pytest.mark.parametrize("name,light,scale", [
    ("grazing", [-3.0, 0.999, 4.0], 1.0), ("1 mm above the floor", [0.0, 0.999, 3.0], 1.0),
    ("inside the sphere", [-0.4, 0.5, 4.0], 1.0), ("above", [0.3, -1.0, 3.0], 1.0),
    ("tiny scene", [0.3, -1.0, 3.0], 1e-3), ("huge scene", [0.3, -1.0, 3.0], 1e3)])
def test_the_default_layers_light_gradient_matches_central_differences(name, light, scale):
    # The whole image's derivative with respect to the light position, float64, with the
    # layer's default shadows (the bounded solid, soft at both ends): autograd against
    # central differences (the huge scene's gradient was NaN through the holes' points).
    view = exact_view((0.2, -1.5, 2.0), H, W, scale=scale)
    g = GBuffer.from_depth(view.depth.double()[None], view.K.double()[None])
    mat = Material(kd=torch.full((1, H, W, 3), 0.5, dtype=torch.float64),
                   ks=torch.full((1, H, W, 1), 0.3, dtype=torch.float64), shininess=20.0)
    layer = ShadowedBlinnPhong(shadows="epipolar")
    weight = torch.rand(1, 3, H, W, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    intensity = torch.full((1, 1, 3), 5.0 * scale**2, dtype=torch.float64)

    def f(p):
        return (layer(g, mat, PointLights(position=p, intensity=intensity)) * weight).sum()

    p = (torch.tensor([[light]], dtype=torch.float64) * scale).requires_grad_(True)
    f(p).backward()
    assert torch.isfinite(p.grad).all()
    h = 1e-6 * scale
    for k in range(3):
        e = torch.zeros(1, 1, 3, dtype=torch.float64)
        e[0, 0, k] = h
        with torch.no_grad():
            numeric = ((f(p.detach() + e) - f(p.detach() - e)) / (2 * h)).item()
        assert p.grad[0, 0, k].item() == pytest.approx(numeric, rel=1e-5, abs=1e-9 * abs(p.grad).max().item())
