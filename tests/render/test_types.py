import math

import pytest
import torch

from render import GBuffer, Material, PointLights
from render.geometry import fit_intrinsics, unproject_depth

K1 = torch.tensor([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])


def test_unproject_matches_contract():
    depth = torch.rand(1, 4, 5) + 1
    K = torch.tensor([[[3.0, 0, 2.2], [0, 4.0, 1.1], [0, 0, 1]]])
    pts = unproject_depth(depth, K)
    i, j = 2, 3
    expected = depth[0, i, j] * torch.linalg.inv(K[0]) @ torch.tensor([j, i, 1.0])
    torch.testing.assert_close(pts[0, i, j], expected)


def test_skewed_intrinsics_rejected():
    K = K1.clone()
    K[0, 1] = 0.5
    with pytest.raises(ValueError, match="skew"):
        GBuffer.from_depth(torch.ones(1, 8, 8), K)


@pytest.mark.parametrize("entry, value", [((0, 0), 0.0), ((1, 1), -100.0), ((2, 2), 0.0), ((1, 0), 3.0)])
def test_non_pinhole_intrinsics_are_named(entry, value):
    # A zero or negative focal length left every pixel masked, silently.
    K = K1.clone()
    K[entry] = value
    with pytest.raises(ValueError, match="pinhole intrinsics"):
        GBuffer.from_depth(torch.ones(2, 8, 8), K)


@pytest.mark.parametrize("shadows", ["none", "epipolar", "paper"])
def test_an_empty_batch_or_no_light_renders_without_error(shadows):
    from render import ShadowedBlinnPhong

    g = GBuffer.from_depth(torch.ones(0, 6, 8), K1)
    position = torch.zeros(0, 2, 3, requires_grad=True)
    image = ShadowedBlinnPhong(shadows=shadows)(g, Material(kd=torch.zeros(0, 6, 8, 3)),
                                                PointLights(position=position, intensity=torch.ones(0, 2, 3)),
                                                torch.zeros(0, 3))
    assert image.shape == (0, 3, 6, 8)
    image.sum().backward()
    assert position.grad.shape == (0, 2, 3)
    # No light at all (a network's empty slot set), through the functional form too.
    from render import light_transport

    g = GBuffer.from_depth(torch.full((2, 6, 8), 2.0), K1)
    transport = light_transport(g, Material(kd=torch.full((2, 6, 8, 3), 0.5)), torch.zeros(2, 0, 3), shadows=shadows)
    assert transport.diffuse.shape == (2, 0, 6, 8)


def test_plane_normals_exact_and_facing_camera():
    # A tilted plane z = 2 + 0.5 y: normal ~ (0, -0.5, 1) normalised, flipped to face camera.
    H, W = 48, 64
    v = torch.arange(H, dtype=torch.float64)[:, None].expand(H, W)
    K = K1.double()
    yn = (v - K[1, 2]) / K[1, 1]
    depth = (2.0 / (1 - 0.5 * yn))[None]
    g = GBuffer.from_depth(depth, K)
    expected = torch.tensor([0.0, 0.5, -1.0], dtype=torch.float64) / math.sqrt(1.25)
    assert g.mask.all()
    torch.testing.assert_close(g.normals[0], expected.expand(H, W, 3), atol=1e-9, rtol=0)
    assert ((g.normals * -g.points).sum(-1) > 0).all()


def test_normals_do_not_cross_depth_discontinuities():
    depth = torch.full((1, 20, 20), 4.0)
    depth[:, :, 10:] = 2.0  # a step: two fronto-parallel planes
    g = GBuffer.from_depth(depth, K1)
    expected = torch.tensor([0.0, 0.0, -1.0])
    torch.testing.assert_close(g.normals[0][g.mask[0]], expected.expand(int(g.mask.sum()), 3), atol=1e-6, rtol=0)
    assert g.mask[0, :, 9].all() and g.mask[0, :, 10].all()


def test_missing_depth_stays_masked_and_zero():
    depth = torch.full((1, 10, 10), 2.0)
    depth[0, 3, 4] = 0
    depth[0, 5, 5] = float("nan")
    depth[0, 6, 6] = float("inf")
    g = GBuffer.from_depth(depth, K1)
    for i, j in ((3, 4), (5, 5), (6, 6)):
        assert not g.mask[0, i, j]
        assert (g.points[0, i, j] == 0).all() and (g.normals[0, i, j] == 0).all()
    assert torch.isfinite(g.points).all() and torch.isfinite(g.normals).all()


def test_select_takes_the_rows_of_a_checked_buffer_as_a_fresh_one_would():
    depth = torch.rand(3, 6, 7) + 1.0
    depth[1, 2, 3] = float("nan")  # a hole: its zeros travel with the row
    g = GBuffer.from_depth(depth, K1.expand(3, 3, 3))
    index = torch.tensor([2, 1, 1])
    selected = g.select(index)
    fresh = GBuffer(g.points[index], g.normals[index], g.mask[index], g.intrinsics[index])
    for name in ("points", "normals", "mask", "intrinsics"):
        assert torch.equal(getattr(selected, name), getattr(fresh, name))
    assert selected.batch_size == 3 and not selected.mask[1, 2, 3]
    assert GBuffer(g.points, g.normals, g.mask).select(index).intrinsics is None


def test_given_normals_are_normalised_and_zero_ones_masked():
    n = torch.zeros(1, 6, 6, 3)
    n[..., 2] = -2.0
    n[0, 1, 1] = 0
    g = GBuffer.from_depth(torch.full((1, 6, 6), 1.0), K1, normals=n)
    assert not g.mask[0, 1, 1]
    torch.testing.assert_close(g.normals[0, 0, 0], torch.tensor([0.0, 0, -1]))


def test_missing_given_normals_can_come_from_the_depth():
    # A plane facing the camera: the estimate from depth is its normal, (0, 0, -1).
    n = torch.zeros(1, 6, 6, 3)
    n[..., 2] = -1.0
    n[0, 2, 2] = 0
    n[0, 3, 4] = float("nan")
    g = GBuffer.from_depth(torch.full((1, 6, 6), 1.0), K1, normals=n, missing_normals="from_depth")
    assert g.mask[0, 2, 2] and g.mask[0, 3, 4]
    torch.testing.assert_close(g.normals[0, 2, 2], torch.tensor([0.0, 0, -1]))
    torch.testing.assert_close(g.normals[0, 3, 4], torch.tensor([0.0, 0, -1]))
    everywhere = GBuffer.from_depth(torch.full((1, 6, 6), 1.0), K1, normals=torch.zeros(1, 6, 6, 3),
                                    missing_normals="from_depth")
    assert torch.equal(everywhere.mask, GBuffer.from_depth(torch.full((1, 6, 6), 1.0), K1).mask)
    with pytest.raises(ValueError, match="missing_normals must be"):
        GBuffer.from_depth(torch.full((1, 6, 6), 1.0), K1, normals=n, missing_normals="zero")


def test_shape_errors_name_the_problem():
    with pytest.raises(ValueError, match=r"depth must have shape \(B, H, W\)"):
        GBuffer.from_depth(torch.ones(8, 8), K1)
    with pytest.raises(ValueError, match="K must have shape"):
        GBuffer.from_depth(torch.ones(2, 8, 8), torch.eye(4))
    with pytest.raises(ValueError, match=r"light position must have shape \(B, L, 3\)"):
        PointLights(position=torch.zeros(2, 3), intensity=torch.zeros(2, 3))
    with pytest.raises(ValueError, match="intensity"):
        PointLights(position=torch.zeros(2, 1, 3), intensity=torch.zeros(2, 2, 3))
    with pytest.raises(ValueError, match="ks must have shape"):
        Material(kd=torch.zeros(1, 4, 4, 3), ks=torch.zeros(1, 4, 4, 2))
    with pytest.raises(ValueError, match="shininess"):
        Material(kd=torch.zeros(1, 4, 4, 3), shininess=torch.ones(1, 3, 3))
    with pytest.raises(TypeError, match="mask must be a bool"):
        GBuffer(points=torch.zeros(1, 2, 2, 3), normals=torch.zeros(1, 2, 2, 3), mask=torch.ones(1, 2, 2))
    with pytest.raises(TypeError, match="kd must be a torch.Tensor"):
        Material(kd=[[0.5]])


def test_nan_in_holes_is_harmless_but_nan_in_valid_pixels_is_reported():
    pts = torch.ones(1, 2, 2, 3)
    pts[0, 0, 0] = float("nan")
    mask = torch.ones(1, 2, 2, dtype=torch.bool)
    mask[0, 0, 0] = False
    g = GBuffer(points=pts, normals=torch.ones(1, 2, 2, 3), mask=mask)
    g.check_finite()
    assert torch.isfinite(g.points).all()
    with pytest.raises(ValueError, match="points holds 3 non-finite"):
        GBuffer(points=pts, normals=torch.ones(1, 2, 2, 3), mask=torch.ones(1, 2, 2, dtype=torch.bool)).check_finite()


def test_fit_intrinsics_recovers_K():
    depth = torch.rand(2, 12, 16, dtype=torch.float64) + 1
    K = K1.double().expand(2, 3, 3)
    g = GBuffer.from_depth(depth, K)
    torch.testing.assert_close(fit_intrinsics(g.points, g.mask), K)


def test_planes_are_kept_made_again_after_an_in_place_change_and_carry_gradients():
    from render import light_transport

    depth = torch.rand(1, 6, 7, dtype=torch.float64) + 1.0
    g = GBuffer.from_depth(depth, K1.double()[None])
    points, normals = g.planes()
    assert torch.equal(points, g.points.permute(0, 3, 1, 2)) and torch.equal(normals, g.normals.permute(0, 3, 1, 2))
    assert g.planes()[0] is points  # kept: a solver renders one buffer hundreds of times
    g.points.add_(0.5)
    assert torch.equal(g.planes()[0], g.points.permute(0, 3, 1, 2))  # in place: made again
    # Geometry that needs a gradient is never kept: the transport differentiates in it.
    light = torch.tensor([[[0.3, -0.6, 0.4]]], dtype=torch.float64)
    material = Material(kd=torch.full((1, 6, 7, 3), 0.5, dtype=torch.float64),
                        ks=torch.full((1, 6, 7, 1), 0.3, dtype=torch.float64), shininess=torch.tensor(8.0, dtype=torch.float64))

    def transport(p, n):
        t = light_transport(GBuffer(p, n, g.mask), material, light, shadows="none")
        return t.diffuse, t.specular

    p = g.points.clone().requires_grad_(True)
    n = g.normals.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(transport, (p, n))
