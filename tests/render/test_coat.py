import math

import pytest
import torch

from render import GBuffer, Material, light_transport
from render.coat import (beckmann_g1, coat_profile, coat_tables, coat_transmission, fresnel_dielectric,
                         internal_reflectance, profile_transmission, rough_transmittance)
from render.coat import _half_vector_quadrature

ETA = 1.5
F64 = torch.float64


def test_fresnel_at_normal_incidence_brewster_and_total_internal_reflection():
    assert float(fresnel_dielectric(torch.tensor(1.0, dtype=F64), ETA)) == pytest.approx(((ETA - 1) / (ETA + 1)) ** 2)
    # At Brewster's angle the p-polarised part vanishes: F = r_s^2 / 2, r_s = cos(2 theta_B).
    brewster = math.atan(ETA)
    expected = 0.5 * math.cos(2 * brewster) ** 2
    assert float(fresnel_dielectric(torch.tensor(math.cos(brewster), dtype=F64), ETA)) == pytest.approx(expected)
    # From inside, beyond the critical angle (sin > 1 / ETA), everything is reflected.
    assert float(fresnel_dielectric(torch.tensor(0.5, dtype=F64), 1 / ETA)) == 1.0


def test_smooth_coat_lets_through_one_minus_fresnel():
    mu = torch.linspace(0.3, 1.0, 8, dtype=F64)
    smooth = rough_transmittance(mu, torch.tensor([0.02], dtype=F64), ETA)[0]
    torch.testing.assert_close(smooth, 1 - fresnel_dielectric(mu, ETA), rtol=0, atol=3e-3)


def test_internal_reflectance_of_a_smooth_coat_is_the_diffuse_fresnel_reflectance():
    # 2 int_0^1 F(mu, 1/eta) mu dmu by a fine rule on the Fresnel equations alone.
    mu = (torch.arange(20000, dtype=F64) + 0.5) / 20000
    expected = float(2 * (fresnel_dielectric(mu, 1 / ETA) * mu).mean())
    assert 0.55 < expected < 0.65
    assert float(internal_reflectance(torch.tensor([0.02], dtype=F64), ETA)[0]) == pytest.approx(expected, abs=3e-3)


def test_reflected_share_by_half_vectors_equals_the_brdf_integrated_over_directions():
    # The half-vector quadrature against the microfacet BRDF F D G / (4 mu_i mu_o) times
    # mu_o integrated over outgoing directions on a fine grid: the change of variables.
    alpha, mu_i = 0.3, 0.6
    n = 600
    mu_o = ((torch.arange(n, dtype=F64) + 0.5) / n)[:, None]
    phi = ((torch.arange(n, dtype=F64) + 0.5) / n * 2 * math.pi)[None]
    i = torch.tensor([math.sqrt(1 - mu_i**2), 0.0, mu_i], dtype=F64)
    s_o = (1 - mu_o**2).sqrt()
    o = torch.stack([s_o * phi.cos(), s_o * phi.sin(), mu_o + 0 * phi], -1)
    h = o + i
    h = h / h.norm(dim=-1, keepdim=True)
    cos_h = h[..., 2]
    D = torch.exp(-(1 - cos_h**2) / cos_h**2 / alpha**2) / (math.pi * alpha**2 * cos_h**4)
    G = beckmann_g1(torch.tensor(mu_i, dtype=F64), alpha) * beckmann_g1(mu_o + 0 * phi, alpha)
    F = fresnel_dielectric((h * i).sum(-1), ETA)
    brdf_cos = F * D * G / (4 * mu_i)
    by_directions = float(brdf_cos.sum() * (1 / n) * (2 * math.pi / n))
    by_half_vectors = float(_half_vector_quadrature(torch.tensor([mu_i], dtype=F64), torch.tensor([alpha], dtype=F64),
                                                    ETA, transmitted=False)[0, 0])
    assert by_half_vectors == pytest.approx(by_directions, rel=5e-3)


@pytest.mark.parametrize("alpha,lost", [(0.05, 0.005), (0.3, 0.005), (0.8, 0.03)])
def test_energy_is_conserved(alpha, lost):
    mu = torch.linspace(0.05, 1.0, 12, dtype=F64)
    a = torch.tensor([alpha], dtype=F64)
    total = rough_transmittance(mu, a, ETA)[0] + _half_vector_quadrature(mu, a, ETA, transmitted=False)[0]
    assert bool((total <= 1 + 2e-3).all())
    assert float(total[-1]) >= 1 - lost  # at normal incidence little is masked


def test_transmission_reads_the_table_and_its_slope_is_its_derivative():
    table, scale = coat_tables(ETA, F64, "cpu")
    assert table.shape[1] == 65 and bool((table >= 0).all() and (table <= 1).all())
    cosine = torch.linspace(0.05, 0.95, 19, dtype=F64, requires_grad=True)
    shininess = torch.tensor(20.0, dtype=F64)
    value, slope = coat_transmission(cosine, torch.tensor(1.0, dtype=F64), shininess, 0.04)
    (grad,) = torch.autograd.grad(value.sum(), cosine)
    torch.testing.assert_close(slope, grad)
    direct = rough_transmittance(cosine.detach(), torch.tensor([math.sqrt(2 / 22)], dtype=F64), ETA)[0]
    root = math.sqrt(float(1 / (ETA**2 * (1 - internal_reflectance(torch.tensor([math.sqrt(2 / 22)], dtype=F64),
                                                                        ETA)[0]))))
    torch.testing.assert_close(value.detach(), direct * root, rtol=0, atol=2e-3)
    # No coat: 1 everywhere, slope 0.
    none, flat = coat_transmission(cosine, torch.tensor(0.0, dtype=F64), shininess, 0.04)
    assert bool((none == 1).all() and (flat == 0).all())


def test_a_profile_reads_the_same_transmission_in_fewer_steps():
    generator = torch.Generator().manual_seed(0)
    coat = torch.tensor([0.0, 0.5, 1.0], dtype=F64)[torch.randint(0, 3, (2, 1, 5, 6), generator=generator)]
    shininess = torch.tensor([3.0, 20.0, 300.0, 1e4], dtype=F64)[torch.randint(0, 4, (2, 1, 5, 6), generator=generator)]
    cosine = torch.rand(2, 4, 5, 6, dtype=F64, generator=generator) * 1.2 - 0.1
    cosine.requires_grad_(True)
    profile = coat_profile(coat, shininess, 0.04)
    assert profile.rows.numel() <= 12 * 65 and profile.offset.shape == (2, 1, 5, 6)
    value, slope = profile_transmission(cosine, profile)
    expected, expected_slope = coat_transmission(cosine, coat, shininess, 0.04)
    torch.testing.assert_close(value, expected)
    torch.testing.assert_close(slope, expected_slope)
    (grad,) = torch.autograd.grad(value.sum(), cosine)
    torch.testing.assert_close(grad, slope)
    assert coat_profile(coat, shininess, 0.04, max_rows=4) is None  # too many pairs: the caller reads the table
    # A NaN cosine (a diverged light) gives NaN, not an index out of the table.
    nan = torch.tensor([float("nan"), 0.5], dtype=F64)
    assert torch.isnan(profile_transmission(nan.view(2, 1, 1, 1), profile)[0][0]).all()
    assert torch.isnan(coat_transmission(nan, torch.tensor(1.0, dtype=F64), torch.tensor(20.0, dtype=F64), 0.04)[0][0])


def _coated_scene(shininess: torch.Tensor):
    depth = torch.full((1, 6, 8), 2.0, dtype=F64)
    K = torch.tensor([[[8.0, 0, 4.0], [0, 8.0, 3.0], [0, 0, 1]]], dtype=F64)
    gbuffer = GBuffer.from_depth(depth, K)
    material = Material(kd=torch.full((1, 6, 8, 3), 0.5, dtype=F64), shininess=shininess,
                        coat=torch.ones(1, 6, 8, 1, dtype=F64))
    return gbuffer, material, torch.tensor([[[0.3, -1.0, 0.5]]], dtype=F64)


def test_a_material_changed_in_place_is_rendered_with_its_new_coat():
    shininess = torch.tensor(5.0, dtype=F64)
    gbuffer, material, light = _coated_scene(shininess)
    rough = light_transport(gbuffer, material, light, shadows="none").diffuse
    shininess.fill_(2000.0)  # the same Material, now a smooth coat
    smooth = light_transport(gbuffer, material, light, shadows="none").diffuse
    fresh = light_transport(gbuffer, Material(kd=material.kd, shininess=2000.0, coat=material.coat), light,
                            shadows="none").diffuse
    torch.testing.assert_close(smooth, fresh)
    assert float((smooth - rough).abs().max()) > 1e-3


def test_the_coated_image_is_differentiable_in_the_shininess():
    shininess = torch.tensor(20.0, dtype=F64, requires_grad=True)
    gbuffer, material, light = _coated_scene(shininess)
    assert torch.autograd.gradcheck(
        lambda s: light_transport(gbuffer, Material(kd=material.kd, shininess=s, coat=material.coat), light,
                                  shadows="none").diffuse, (shininess,))


def test_the_shipped_tables_are_the_quadratures_and_are_read_instead_of_it(monkeypatch):
    # STORED_TABLES spares every fresh process the quadrature (0.5 s): its values must be what
    # the quadrature finds now, for the default coat, and any other coat is still found by it.
    from render import coat

    eta = coat.coat_eta(0.04)
    stored = coat._stored_tables(eta)
    assert stored is not None, "render/coat_tables_f0_0.04.npz is missing or stale: run write_stored_tables()"
    found = coat._quadrature_tables(eta)
    for a, b in zip(stored, found):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-15)
    assert coat._stored_tables(coat.coat_eta(0.05)) is None
    monkeypatch.setattr(coat, "TABLE_COSINES", coat.TABLE_COSINES + 1)  # another layout: the file is not read
    assert coat._stored_tables(eta) is None


def test_a_coat_is_rendered_without_importing_sympy_and_shapes_broadcast_as_torch_says():
    # torch.broadcast_shapes imports sympy on its first call (half a second in every fresh
    # estimator worker); render.geometry.broadcast_shape stands in for it.
    import subprocess
    import sys

    from render.geometry import broadcast_shape

    for shapes in [((2, 1, 3), (4, 1), (3,)), ((3,), (3,)), ((), (2, 3)), ((2, 3), (1, 3), (2, 1))]:
        assert broadcast_shape(*shapes) == tuple(torch.broadcast_shapes(*shapes))
    with pytest.raises(ValueError, match="do not broadcast"):
        broadcast_shape((2, 3), (3, 3))
    code = ("import sys, torch; from render.coat import coat_profile, coat_transmission; "
            "coat_transmission(torch.rand(4, 5), torch.ones(4, 1), torch.full((1,), 50.0), 0.04); "
            "coat_profile(torch.ones(2, 3, 1), torch.full((2, 1, 1), 50.0), 0.04); print('sympy' in sys.modules)")
    ran = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert ran.returncode == 0, ran.stderr
    assert ran.stdout.strip() == "False"
