import pytest
import torch

from render import CubeShadowOptions, EpipolarShadowOptions, GBuffer, Material, PointLights, render
from render.shadows import epipolar_shadow_visibility
from selfsup.scenes.analytic import compare_to_exact
from tests.conftest import CAMERA_SIDE_LIGHTS, exact_view, gbuffer_of


def _render_like_exact(view, light, method, dtype=torch.float64, **kw):
    H, W = view.mask.shape
    mat = Material(kd=torch.full((1, H, W, 3), 0.6, dtype=dtype), ks=torch.full((1, H, W, 1), 0.3, dtype=dtype), shininess=20.0)
    lights = PointLights(position=torch.tensor([[light]], dtype=dtype), intensity=torch.full((1, 1, 3), 10.0, dtype=dtype))
    return render(gbuffer_of(view, dtype), mat, lights, torch.full((1, 3), 0.05, dtype=dtype), shadows=method, **kw)


@pytest.mark.parametrize("light", CAMERA_SIDE_LIGHTS)
def test_epipolar_shadows_match_exact_ray_casting(light):
    view = exact_view(tuple(light))
    out = _render_like_exact(view, light, "epipolar")
    exact = view.visibility[..., 0]
    assert (exact[view.mask] < 0.5).double().mean() > 0.01  # the scene really has shadows
    score = compare_to_exact(view, out.visibility[0, 0], out.image[0].permute(1, 2, 0))
    assert score.agree >= 0.99
    assert score.lit_within_1e4 >= 0.99


def test_paper_shadows_match_exact_ray_casting():
    light = CAMERA_SIDE_LIGHTS[1]
    view = exact_view(tuple(light))
    out = _render_like_exact(view, light, "paper")
    score = compare_to_exact(view, out.visibility[0, 0], out.image[0].permute(1, 2, 0))
    assert score.agree >= 0.99


def test_paper_jacobian_matches_central_differences_of_image():
    light = [-0.8, -0.9, 1.2]
    view = exact_view(tuple(light), 60, 80)
    H, W = view.mask.shape
    opts = CubeShadowOptions(resolution=128)
    weight = torch.rand(1, 3, H, W, dtype=torch.float64)
    mat = Material(kd=torch.full((1, H, W, 3), 0.6, dtype=torch.float64))
    g = gbuffer_of(view)

    def loss(p):
        lights = PointLights(position=p, intensity=torch.full((1, 1, 3), 10.0, dtype=torch.float64))
        return (render(g, mat, lights, shadows="paper", shadow_options=opts).image * weight).sum()

    p = torch.tensor([[light]], dtype=torch.float64, requires_grad=True)
    loss(p).backward()
    step = opts.fd_step * (g.points[0][g.mask[0]] - p.detach()[0, 0]).norm(dim=-1).mean()
    numeric = torch.zeros(3, dtype=torch.float64)
    for k in range(3):
        e = torch.zeros(1, 1, 3, dtype=torch.float64)
        e[0, 0, k] = step
        numeric[k] = (loss(p.detach() + e) - loss(p.detach() - e)) / (2 * step)
    shadow_part = (numeric - p.grad[0, 0]).norm() / numeric.norm()
    assert shadow_part < 0.05, (p.grad, numeric)


def test_epipolar_gradient_is_exact_for_the_smoothed_model():
    # float64 finite differences of the whole visibility map against autograd.
    light = [0.2, -1.5, 2.0]
    view = exact_view(tuple(light), 30, 40)
    g = gbuffer_of(view)
    opts = EpipolarShadowOptions(width_px=3.0)
    weight = torch.rand(1, 1, 30, 40, dtype=torch.float64)

    def f(p):
        return (epipolar_shadow_visibility(g.points, g.mask, g.intrinsics, p, opts) * weight).sum()

    p = torch.tensor([[light]], dtype=torch.float64, requires_grad=True)
    f(p).backward()
    assert p.grad.abs().sum() > 0
    h = 1e-6
    for k in range(3):
        e = torch.zeros(1, 1, 3, dtype=torch.float64)
        e[0, 0, k] = h
        numeric = (f(p.detach() + e) - f(p.detach() - e)) / (2 * h)
        assert numeric.item() == pytest.approx(p.grad[0, 0, k].item(), rel=1e-3, abs=1e-6)


def test_gradcheck_smooth_parts_float64():
    K = torch.tensor([[8.0, 0, 3.5], [0, 8.0, 2.5], [0, 0, 1]], dtype=torch.float64)
    depth = 2.0 + 0.3 * torch.rand(1, 6, 8, dtype=torch.float64)
    g = GBuffer.from_depth(depth, K)
    kd = torch.rand(1, 6, 8, 3, dtype=torch.float64)
    ks = torch.rand(1, 6, 8, 1, dtype=torch.float64)

    def f(position, intensity, ambient, shininess):
        mat = Material(kd=kd, ks=ks, shininess=shininess)
        return render(g, mat, PointLights(position=position, intensity=intensity), ambient, shadows="none").image

    inputs = (
        torch.tensor([[[0.3, -0.6, 0.4], [-0.2, 0.1, 0.8]]], dtype=torch.float64, requires_grad=True),
        torch.rand(1, 2, 3, dtype=torch.float64, requires_grad=True),
        torch.rand(1, 3, dtype=torch.float64, requires_grad=True),
        torch.tensor(12.0, dtype=torch.float64, requires_grad=True),
    )
    assert torch.autograd.gradcheck(f, inputs)
