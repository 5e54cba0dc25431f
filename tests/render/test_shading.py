import math

import pytest
import torch

from render import GBuffer, Material, PointLights, ShadowedBlinnPhong, render
from render.coat import internal_reflectance, rough_transmittance
from render.shading import blinn_phong_lobe, falloff_factor

K = torch.tensor([[20.0, 0, 7.5], [0, 20.0, 7.5], [0, 0, 1]], dtype=torch.float64)


def flat_wall(batch=1, size=16, z=2.0, dtype=torch.float64):
    return GBuffer.from_depth(torch.full((batch, size, size), z, dtype=dtype), K.to(dtype))


def test_diffuse_exact_angles():
    # Wall z = 2 facing the camera, kd = 1, falloff none: the pixel value is n . l.
    g = flat_wall()
    mat = Material(kd=torch.ones(1, 16, 16, 3, dtype=torch.float64))
    X = g.points[0, 5, 9]
    cases = {"45 degrees": (X + torch.tensor([0.0, -1.0, -1.0], dtype=torch.float64), 1 / math.sqrt(2)),
             "behind the surface": (X + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), 0.0)}
    for name, (light, expected) in cases.items():
        lights = PointLights(position=light.view(1, 1, 3), intensity=torch.ones(1, 1, 3, dtype=torch.float64))
        value = render(g, mat, lights, falloff="none", shadows="none").image[0, 0, 5, 9].item()
        assert value == pytest.approx(expected, abs=1e-12), name


def test_coat_lets_through_the_rough_transmittance_in_and_out():
    # A light at 45 degrees on a wall pixel seen at angle c_o, shininess 20 (Beckmann
    # roughness sqrt(2 / 22)): the diffuse value times T(1/sqrt 2) T(c_o) / (eta^2 (1 - R_int)),
    # T and R_int by quadrature here, read off the table there.
    g = flat_wall()
    kd = torch.ones(1, 16, 16, 3, dtype=torch.float64)
    X = g.points[0, 5, 9]
    lights = PointLights(position=(X + torch.tensor([0.0, -1.0, -1.0], dtype=torch.float64)).view(1, 1, 3),
                         intensity=torch.ones(1, 1, 3, dtype=torch.float64))
    c_in, c_out = 1 / math.sqrt(2), float(-(g.normals[0, 5, 9] @ X) / X.norm())
    alpha, eta = torch.tensor([math.sqrt(2 / 22)], dtype=torch.float64), 1.5
    T_in, T_out = rough_transmittance(torch.tensor([c_in, c_out], dtype=torch.float64), alpha, eta)[0].tolist()
    scale = float(1 / (eta**2 * (1 - internal_reflectance(alpha, eta))))

    def coated(weight):
        return Material(kd=kd, shininess=20.0, coat=torch.full_like(kd[..., :1], weight))

    full = render(g, coated(1.0), lights, falloff="none", shadows="none").image[0, 0, 5, 9].item()
    assert full == pytest.approx(c_in * T_in * T_out * scale, abs=2e-3)
    assert full < c_in  # less light than bare at these angles
    none = render(g, coated(0.0), lights, falloff="none", shadows="none").image[0, 0, 5, 9].item()
    assert none == pytest.approx(c_in, abs=1e-12)
    # Half a coat: each side half-way between bare and coated; the specular term is untouched.
    ks = torch.full_like(kd[..., :1], 0.5)
    half = render(g, Material(kd=kd, ks=ks, shininess=20.0, coat=torch.full_like(ks, 0.5)), lights, falloff="none",
                  shadows="none")
    bare = render(g, Material(kd=kd, ks=ks, shininess=20.0), lights, falloff="none", shadows="none")
    root = math.sqrt(scale)
    assert half.diffuse[0, 0, 5, 9].item() == pytest.approx(
        c_in * (0.5 + 0.5 * T_in * root) * (0.5 + 0.5 * T_out * root), abs=2e-3)
    torch.testing.assert_close(half.specular, bare.specular, rtol=0, atol=0)


@pytest.mark.parametrize("coat,match", [(torch.full((1, 4, 4, 3), 0.5), "coat must have shape"),
                                        (torch.full((1, 4, 4, 1), 1.5), "coat must be in"),
                                        (torch.full((1, 4, 4, 1), math.nan), "coat holds")])
def test_bad_coat_is_named(coat, match):
    with pytest.raises(ValueError, match=match):
        Material(kd=torch.ones(1, 4, 4, 3), coat=coat).check_finite()


def test_specular_peak_and_falloff():
    n = torch.tensor([0.0, 0.0, -1.0])
    assert blinn_phong_lobe(n, n, n, torch.tensor(500.0)).item() == pytest.approx(1.0)
    l = torch.tensor([0.0, math.sin(0.2), -math.cos(0.2)])
    # h is halfway: angle 0.1 from n.
    assert blinn_phong_lobe(n, l, n, torch.tensor(10.0)).item() == pytest.approx(math.cos(0.1) ** 10)
    assert falloff_factor(torch.tensor(2.0), "inverse_square").item() == 0.25
    assert falloff_factor(torch.tensor(2.0), "none").item() == 1.0


def test_single_pixel_matches_formula_by_hand():
    g = flat_wall()
    kd, ks, alpha, la, intensity = 0.4, 0.3, 7.0, 0.1, 3.0
    mat = Material(kd=torch.full((1, 16, 16, 3), kd, dtype=torch.float64),
                   ks=torch.full((1, 16, 16, 1), ks, dtype=torch.float64), shininess=alpha)
    lp = torch.tensor([[[0.3, -0.4, 0.5]]], dtype=torch.float64)
    lights = PointLights(position=lp, intensity=torch.full((1, 1, 3), intensity, dtype=torch.float64))
    img = render(g, mat, lights, torch.full((1, 3), la, dtype=torch.float64), shadows="none").image
    X = g.points[0, 5, 9]
    n = torch.tensor([0.0, 0, -1], dtype=torch.float64)
    d = (lp[0, 0] - X).norm()
    l = (lp[0, 0] - X) / d
    v = -X / X.norm()
    h = (l + v) / (l + v).norm()
    expected = kd * la + intensity / d**2 * (kd * (n @ l).clamp_min(0) + ks * (n @ h).clamp_min(0) ** alpha)
    torch.testing.assert_close(img[0, :, 5, 9], expected.expand(3))


def test_terms_add_up_and_module_equals_function():
    g = flat_wall(batch=2)
    mat = Material(kd=torch.rand(2, 16, 16, 3, dtype=torch.float64), ks=torch.rand(2, 16, 16, 3, dtype=torch.float64),
                   shininess=torch.tensor([5.0, 50.0], dtype=torch.float64))
    lights = PointLights(position=torch.randn(2, 3, 3, dtype=torch.float64) * 0.3 + torch.tensor([0, -0.5, 1.0], dtype=torch.float64),
                         intensity=torch.rand(2, 3, 3, dtype=torch.float64))
    ambient = torch.rand(2, 3, dtype=torch.float64)
    layer = ShadowedBlinnPhong()
    out = layer.render_terms(g, mat, lights, ambient)
    torch.testing.assert_close(out.image, out.ambient + out.diffuse + out.specular)
    torch.testing.assert_close(layer(g, mat, lights, ambient), render(g, mat, lights, ambient).image)
    assert out.visibility.shape == (2, 3, 16, 16)


def test_image_is_linear_in_lights():
    g = flat_wall()
    mat = Material(kd=torch.full((1, 16, 16, 3), 0.5, dtype=torch.float64))
    p = torch.tensor([[[0.2, -0.3, 0.8], [-0.5, 0.1, 1.0]]], dtype=torch.float64)
    both = render(g, mat, PointLights(position=p, intensity=torch.ones(1, 2, 3, dtype=torch.float64))).image
    one = [render(g, mat, PointLights(position=p[:, i:i + 1], intensity=torch.ones(1, 1, 3, dtype=torch.float64))).image
           for i in range(2)]
    torch.testing.assert_close(both, one[0] + one[1])


def test_specular_auto_skips_zero_ks_and_none():
    g = flat_wall()
    lights = PointLights(position=torch.tensor([[[0.0, -0.5, 1.0]]], dtype=torch.float64), intensity=torch.ones(1, 1, 3, dtype=torch.float64))
    kd = torch.full((1, 16, 16, 3), 0.5, dtype=torch.float64)
    assert render(g, Material(kd=kd), lights).specular is None
    assert render(g, Material(kd=kd, ks=torch.zeros(1, 16, 16, 1, dtype=torch.float64)), lights).specular is None
    assert render(g, Material(kd=kd, ks=torch.zeros(1, 16, 16, 1, dtype=torch.float64)), lights, specular=True).specular is not None


def test_shadows_none_and_no_lights():
    g = flat_wall()
    mat = Material(kd=torch.full((1, 16, 16, 3), 0.5, dtype=torch.float64))
    out = render(g, mat, PointLights(position=torch.zeros(1, 0, 3, dtype=torch.float64), intensity=torch.zeros(1, 0, 3, dtype=torch.float64)),
                 torch.full((3,), 0.2, dtype=torch.float64))
    torch.testing.assert_close(out.image, torch.full_like(out.image, 0.1))
    lights = PointLights(position=torch.tensor([[[0.0, 0, 1.0]]], dtype=torch.float64), intensity=torch.ones(1, 1, 3, dtype=torch.float64))
    assert render(g, mat, lights, shadows="none").visibility is None


def test_bad_render_arguments():
    g = flat_wall()
    mat = Material(kd=torch.full((1, 8, 8, 3), 0.5, dtype=torch.float64))
    lights = PointLights(position=torch.zeros(1, 1, 3, dtype=torch.float64), intensity=torch.ones(1, 1, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="material kd must have shape"):
        render(g, mat, lights)
    mat = Material(kd=torch.full((1, 16, 16, 3), 0.5, dtype=torch.float64))
    with pytest.raises(ValueError, match="'sometimes' is not a valid ShadowMethod"):
        render(g, mat, lights, shadows="sometimes")
    with pytest.raises(ValueError, match="light position holds 1 non-finite"):
        bad = PointLights(position=torch.tensor([[[0.0, float("nan"), 1]]], dtype=torch.float64), intensity=torch.ones(1, 1, 3, dtype=torch.float64))
        render(g, mat, bad)
    with pytest.raises(ValueError, match="ambient must have shape"):
        render(g, mat, lights, torch.ones(2, 2))
    # The layer names a bad switch when built: the training loss reads it without rendering.
    for switches in (dict(specular="maybe"), dict(specular=1), dict(diffuse="yes")):
        with pytest.raises(ValueError, match="specular True, False or 'auto'"):
            ShadowedBlinnPhong(**switches)
    with pytest.raises(TypeError, match="needs EpipolarShadowOptions"):
        from render import CubeShadowOptions
        render(g, mat, lights, shadow_options=CubeShadowOptions())
    with pytest.raises(ValueError, match="spacing_px must be > 0"):
        ShadowedBlinnPhong(shadow_options={"spacing_px": 0})


def test_dtype_and_device_follow_inputs():
    g = flat_wall(dtype=torch.float32)
    mat = Material(kd=torch.full((1, 16, 16, 3), 0.5))
    lights = PointLights(position=torch.tensor([[[0.0, -0.5, 1.0]]]), intensity=torch.ones(1, 1, 3))
    for method in ("epipolar", "paper", "none"):
        assert render(g, mat, lights, shadows=method).image.dtype == torch.float32


def test_dot3_and_norm3_match_the_reductions_and_norm3_has_a_zero_gradient_at_zero():
    from render.geometry import dot3, norm3

    a, b = torch.randn(2, 5, 1, 3, dtype=torch.float64), torch.randn(2, 1, 4, 3, dtype=torch.float64)
    torch.testing.assert_close(dot3(a, b), (a * b).sum(-1))
    torch.testing.assert_close(norm3(a), a.norm(dim=-1))
    v = torch.zeros(3, 3, dtype=torch.float64).index_fill_(0, torch.tensor([1]), 1.0).requires_grad_(True)
    norm3(v).sum().backward()
    assert torch.isfinite(v.grad).all() and v.grad[0].abs().sum() == 0


def test_the_planar_transport_equals_the_channel_last_helpers_guards_included():
    # The renderer's transport is written on planes (render.shading.planar_shading); the public
    # channel-last helpers must give the same maps, also where a guard holds: a light on the
    # surface (distance floored) and a light on the camera ray behind the point (l = -v).
    from render import light_transport
    from render.shading import light_geometry

    depth = 2.0 + 0.3 * torch.rand(1, 16, 16, dtype=torch.float64)
    g = GBuffer.from_depth(depth, K)
    X = g.points[0, 5, 9]
    lights = torch.stack([X, 2.0 * X, torch.tensor([0.4, -0.7, 0.9], dtype=torch.float64)])[None]  # (1, 3, 3)
    material = Material(kd=torch.full((1, 16, 16, 3), 0.5, dtype=torch.float64),
                        ks=torch.full((1, 16, 16, 1), 0.3, dtype=torch.float64), shininess=0.7)
    for falloff in ("inverse_square", "none"):
        t = light_transport(g, material, lights, falloff=falloff, shadows="none")
        geometry = light_geometry(g.points[:, None], lights[:, :, None, None])
        n_dot_l = (g.normals[:, None] * geometry.to_light).sum(-1)
        f = falloff_factor(geometry.distance, falloff)
        torch.testing.assert_close(t.diffuse, f * n_dot_l.clamp_min(0))
        lobe = blinn_phong_lobe(g.normals[:, None], geometry.to_light, geometry.to_viewer, torch.tensor(0.7))
        torch.testing.assert_close(t.specular, f * lobe)
        assert torch.isfinite(t.diffuse).all() and torch.isfinite(t.specular).all()


def test_planar_shading_names_channel_last_geometry_and_bad_lights():
    from render.shading import planar_shading, shading_and_position_gradients

    g = flat_wall()
    points, normals = g.planes()
    light = torch.tensor([[[0.3, -0.4, 0.5]]], dtype=torch.float64)
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\) planes"):
        planar_shading(g.points, g.normals, light, "inverse_square")  # channel-last, not planes
    with pytest.raises(ValueError, match="light_position must have shape"):
        shading_and_position_gradients(points, normals, light[0], 1.0, "none")
    assert planar_shading(points, normals, light, "none").n_dot_l.shape == (1, 1, 16, 16)
