"""The renderer's indirect light (render.indirect): a bounce between the surfaces a G-buffer sees."""

import math

import pytest
import torch

from render import GBuffer, Material, PointLights, ShadowedBlinnPhong, render
from render.indirect import bounce_gain, bounce_image, one_bounce


def _two_patches(dtype=torch.float64):
    # A 1x2 G-buffer: pixel 0 on a floor (normal up, -y), pixel 1 on a wall facing it and the
    # camera, 1 m apart; both seen from 2 m.
    K = torch.tensor([[[10.0, 0, 0.5], [0, 10.0, 0.0], [0, 0, 1]]], dtype=dtype)
    points = torch.tensor([[[[-0.1, 0.0, 2.0], [0.1, 0.0, 2.0]]]], dtype=dtype)
    normals = torch.tensor([[[[0.0, -1.0, 0.0], [-0.6, 0.0, -0.8]]]], dtype=dtype)
    return GBuffer(points=points, normals=normals, mask=torch.ones(1, 1, 2, dtype=torch.bool), intrinsics=K)


def test_the_bounce_of_two_patches_is_the_form_factor_written_out():
    g = _two_patches()
    kd = torch.tensor([[[[0.5, 0.4, 0.3], [0.2, 0.6, 0.9]]]], dtype=torch.float64)
    diffuse = torch.tensor([[[[0.7, 0.0]]]], dtype=torch.float64)  # the light reaches the floor alone
    got = one_bounce(g, kd, diffuse, patch_px=1, target_px=1)[0, :, 0, 0]  # (3, 2)
    p, x = g.points[0, 0, 0], g.points[0, 0, 1]
    n_p, n_x = g.normals[0, 0, 0], g.normals[0, 0, 1]
    d = p - x  # from the wall's pixel to the floor's patch
    r = float(d.norm())
    cos_view = max(float(n_p @ -p) / float(p.norm()), 0.2)
    area = (2.0 / 10.0) ** 2 / cos_view  # (z / f)^2 over the view angle's cosine
    form = max(float(n_x @ d) / r, 0) * max(float(n_p @ -d) / r, 0) * area / (math.pi * r**2)
    torch.testing.assert_close(got[:, 1], kd[0, 0, 0] * 0.7 * form, rtol=1e-10, atol=0)
    assert float(got[:, 0].abs().max()) == 0.0  # the unlit wall returns nothing to the floor


def test_the_layer_adds_the_bounce_and_its_strength_scales_it():
    K = torch.tensor([[20.0, 0, 11.5], [0, 20.0, 7.5], [0, 0, 1]])
    depth = torch.full((2, 16, 24), 3.0)  # a back wall 3 m away
    depth[:, 9:, :] = 0.3 * 20.0 / (torch.arange(9, 16).float() - 7.5)[:, None]  # a floor 0.3 m below the camera
    floor = depth < 3.0
    normals = torch.where(floor[..., None], torch.tensor([0.0, -1.0, 0.0]), torch.tensor([0.0, 0.0, -1.0]))
    g = GBuffer.from_depth(depth.clamp_max(3.0), K, normals=normals)
    material = Material(kd=torch.full((2, 16, 24, 3), 0.6))
    lights = PointLights(position=torch.tensor([[[0.0, -0.5, 1.5]]] * 2), intensity=torch.ones(2, 1, 3))
    plain = ShadowedBlinnPhong()(g, material, lights)
    bounced = ShadowedBlinnPhong(indirect="bounce")
    terms = bounced.render_terms(g, material, lights)
    assert terms.indirect is not None and float(terms.indirect.min()) >= 0 and float(terms.indirect.max()) > 0
    torch.testing.assert_close(terms.image, plain + terms.indirect)
    # The generator's bounce and the estimator's are this one (selfsup.scenes.indirect.with_bounce).
    from selfsup.scenes.indirect import with_bounce

    visibility = bounced.transport(g, material, lights.position).visibility
    torch.testing.assert_close(with_bounce(plain, g, material.kd, lights.position, lights.intensity, visibility, 1.0),
                               terms.image)
    half = bounced(g, material, lights, indirect_strength=torch.tensor([0.5, 0.0]))  # per image
    torch.testing.assert_close(half[0], plain[0] + 0.5 * terms.indirect[0])
    torch.testing.assert_close(half[1], plain[1])
    assert "indirect=bounce" in repr(bounced)


def test_the_bounce_is_differentiable_in_float64():
    g = GBuffer.from_depth(torch.tensor([[[2.0, 2.0, 2.0], [2.0, 1.6, 1.6], [1.2, 1.2, 1.6]]], dtype=torch.float64),
                           torch.tensor([[4.0, 0, 1.0], [0, 4.0, 1.0], [0, 0, 1]], dtype=torch.float64))
    kd = torch.rand(1, 3, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 0.8 + 0.1

    def image(position, intensity, strength):
        out = render(g, Material(kd=kd), PointLights(position=position, intensity=intensity), shadows="none",
                     indirect="bounce", indirect_strength=strength, check_finite=False)
        return out.indirect

    position = torch.tensor([[[0.3, -0.8, 0.9]]], dtype=torch.float64, requires_grad=True)
    intensity = torch.tensor([[[1.0, 0.8, 0.6]]], dtype=torch.float64, requires_grad=True)
    strength = torch.tensor([0.7], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(image, (position, intensity, strength))
    assert float(bounce_gain(kd, g.mask).min()) > 1


def test_bad_indirect_settings_are_named():
    K = torch.tensor([[8.0, 0, 3.5], [0, 8.0, 3.5], [0, 0, 1]])
    g = GBuffer.from_depth(torch.full((1, 8, 8), 2.0), K)
    lights = PointLights(position=torch.tensor([[[0.0, -1.0, 0.5]]]), intensity=torch.ones(1, 1, 3))
    material = Material(kd=torch.full((1, 8, 8, 3), 0.5))
    without = GBuffer(points=g.points, normals=g.normals, mask=g.mask, intrinsics=None)
    with pytest.raises(ValueError, match="intrinsics"):
        render(without, material, lights, indirect="bounce")
    with pytest.raises(ValueError, match="indirect must be one of"):
        render(g, material, lights, indirect="path_traced")
    with pytest.raises(ValueError, match="indirect must be one of"):
        ShadowedBlinnPhong(indirect="yes")
    with pytest.raises(ValueError, match="indirect_strength"):
        ShadowedBlinnPhong(indirect="bounce", indirect_strength=-1.0)
    with pytest.raises(ValueError, match="strength must be a number or"):
        render(g, material, lights, indirect="bounce", indirect_strength=torch.ones(3))
    with pytest.raises(ValueError, match="finite and >= 0"):
        bounce_image(g, material.kd, torch.ones(1, 1, 8, 8), torch.ones(1, 1, 3), float("nan"))
