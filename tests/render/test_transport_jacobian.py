"""light_transport_jacobian: exact shading derivatives, finite-difference shadow ones."""

import pytest
import torch

from render import Material, light_transport, light_transport_jacobian
from tests.conftest import CAMERA_SIDE_LIGHTS, exact_view, gbuffer_of

# torch's forward-mode jacobian goes through a deprecated torch.jit.script inside torch itself.
pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")


def _scene(dtype=torch.float64, shininess=20.0, coat=False):
    view = exact_view(tuple(CAMERA_SIDE_LIGHTS[0]), 30, 40)
    g = gbuffer_of(view, dtype)
    kd = torch.rand(1, 30, 40, 3, dtype=dtype) * 0.8 + 0.1
    # A coat on part of the image, weights from 0 to 1.
    weight = (torch.rand_like(kd[..., :1]) - 0.3).clamp(0, 1) if coat else None
    material = Material(kd=kd, ks=torch.full_like(kd[..., :1], 0.4), shininess=torch.tensor(shininess, dtype=dtype),
                        coat=weight)
    lights = torch.tensor([[[0.6, -1.0, 0.5], [-0.5, -0.8, 1.6]]], dtype=dtype)
    return g, material, lights


def _autograd_jacobian(g, material, lights, falloff, term):
    # d(term map)/d(position) by autograd, (B, L, H, W, 3): light i's map depends on p_i only.
    def maps(position):
        t = light_transport(g, material, position, falloff=falloff, shadows="none")
        return getattr(t, term)
    full = torch.autograd.functional.jacobian(maps, lights, vectorize=True, strategy="forward-mode")  # (B, L, H, W, B, L, 3)
    L = lights.shape[1]
    return torch.stack([full[0, i, :, :, 0, i] for i in range(L)])[None]


@pytest.mark.parametrize("falloff", ["inverse_square", "none"])
@pytest.mark.parametrize("shininess,coat", [(1.0, False), (20.0, False), (500.0, False), (20.0, True)])
def test_shading_derivatives_equal_autograd(falloff, shininess, coat):
    g, material, lights = _scene(shininess=shininess, coat=coat)
    jac = light_transport_jacobian(g, material, lights, 1e-4, falloff=falloff, shadows="none")
    plain = light_transport(g, material, lights, falloff=falloff, shadows="none")
    assert torch.equal(jac.transport.diffuse, plain.diffuse) and torch.equal(jac.transport.specular, plain.specular)
    for term in ("diffuse", "specular"):
        expected = _autograd_jacobian(g, material, lights, falloff, term)
        got = getattr(jac, term)
        assert got.abs().amax() > 0
        torch.testing.assert_close(got, expected, rtol=1e-9, atol=1e-9 * expected.abs().amax())


def test_shadowed_jacobian_matches_differences_of_the_whole_transport():
    # Epipolar shadows: shading exact, visibility by forward differences. Away from
    # shadow edges it equals central differences of the shadowed transport; at the
    # edges (visibility moving) it equals forward differences of the whole transport,
    # which the shading derivative alone does not.
    g, material, lights = _scene()
    h = 1e-4
    jac = light_transport_jacobian(g, material, lights, h, shadows="epipolar")
    plain = light_transport(g, material, lights, shadows="epipolar")
    torch.testing.assert_close(jac.transport.diffuse, plain.diffuse)
    torch.testing.assert_close(jac.transport.visibility, plain.visibility)
    unshadowed = light_transport_jacobian(g, material, lights, h, shadows="none")
    for j in range(3):
        step = torch.zeros_like(lights)
        step[..., j] = h
        ahead = light_transport(g, material, lights + step, shadows="epipolar")
        behind = light_transport(g, material, lights - step, shadows="epipolar")
        steady = ((ahead.visibility - behind.visibility).abs() < 1e-12) & (plain.visibility > 0.5)
        central = (ahead.diffuse - behind.diffuse) / (2 * h)
        assert steady.float().mean() > 0.5
        torch.testing.assert_close(jac.diffuse[..., j][steady], central[steady], rtol=1e-4, atol=1e-6)

        forward = (ahead.diffuse - plain.diffuse) / h
        shading_only = plain.visibility * unshadowed.diffuse[..., j]
        edge = (ahead.visibility - plain.visibility).abs() > 1e-6
        assert edge.any()
        scale = forward[edge].abs().amax()
        assert (shading_only[edge] - forward[edge]).abs().amax() > 0.1 * scale  # the shadow term matters there
        torch.testing.assert_close(jac.diffuse[..., j][edge], forward[edge], rtol=0, atol=0.01 * scale)
    assert torch.isfinite(jac.diffuse).all() and torch.isfinite(jac.specular).all()


def test_wrong_light_shape_is_named():
    g, material, _ = _scene()
    with pytest.raises(ValueError, match="light_position"):
        light_transport_jacobian(g, material, torch.zeros(1, 3), 1e-3)
