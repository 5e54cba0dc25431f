import pytest
import torch

from render import CubeShadowOptions, EpipolarShadowOptions, GBuffer, Material, PointLights, render
from render.shadows import cube_shadow_visibility, epipolar_shadow_visibility
from selfsup.scenes.analytic import compare_to_exact, shadow_edge_band
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


@pytest.mark.parametrize("thickness", [None, 0.3])
def test_epipolar_gradient_is_exact_for_the_smoothed_model(thickness):
    # float64 finite differences of the whole visibility map against autograd; with a
    # thickness, the slab choice is held fixed like the occluder choice.
    light = [0.2, -1.5, 2.0]
    view = exact_view(tuple(light), 30, 40)
    g = gbuffer_of(view)
    opts = EpipolarShadowOptions(width_px=3.0, thickness=thickness, **({} if thickness else {"scene_thickness": None}))
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


def _plate_before_wall(light, thickness, plate_half=0.6, plate_z=3.0, wall_z=5.0, H=30, W=40):
    # A square plate at plate_z in front of a wall at wall_z, seen by the camera; behind
    # each of its pixels a solid of ``thickness`` along the camera ray. Exact visibility of
    # the wall's pixels from the light by 4000 points along each shadow ray.
    K = torch.tensor([[30.0, 0, 19.5], [0, 30.0, 14.5], [0, 0, 1]], dtype=torch.float64)
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    ray = torch.stack([(u - 19.5) / 30.0, (v - 14.5) / 30.0], -1)
    on_plate = (ray * plate_z).abs().amax(-1) <= plate_half
    depth = torch.where(on_plate, plate_z, wall_z).to(torch.float64)
    g = GBuffer.from_depth(depth[None], K[None])
    light = torch.tensor(light, dtype=torch.float64)
    t = torch.linspace(0, 1, 4002, dtype=torch.float64)[1:-1, None]
    on_ray = g.points[0][..., None, :] + t * (light - g.points[0][..., None, :])  # (H, W, 4000, 3)
    at_plate = on_ray * (plate_z / on_ray[..., 2:])  # where each point's camera ray meets the plate's plane
    behind = on_ray.norm(dim=-1) / at_plate.norm(dim=-1)  # 1 on the plate, growing with depth
    inside = ((at_plate[..., :2].abs().amax(-1) <= plate_half) & (behind >= 1)
              & (behind <= 1 + thickness / at_plate.norm(dim=-1)))
    return g, light, ~on_plate, ~inside.any(-1)


@pytest.mark.parametrize("light", [[0.2, -0.1, 4.0], [1.0, 0.0, 3.8], [-1.2, 0.4, 2.0], [0.9, -0.5, 1.0]])
def test_epipolar_thickness_lets_rays_pass_behind_an_object(light):
    # Unbounded, the plate is a solid reaching to infinity: a light behind it is inside
    # it (every wall pixel shadowed), and rays passing behind its silhouette are blocked.
    # With a thickness the shadows are those of the plate with that slab behind it.
    g, lp, wall, lit = _plate_before_wall(light, thickness=0.5)
    run = lambda opts: epipolar_shadow_visibility(g.points, g.mask, g.intrinsics, lp[None, None], opts)[0, 0] > 0.5
    unbounded, slab = run(EpipolarShadowOptions(scene_thickness=None)), run(EpipolarShadowOptions(thickness=0.5))
    # Three pixels either side of the exact edge (also where it lies just outside the
    # image) left out: the sweep's edge sits up to 1.5 pixel-sized angles off at the
    # plate (bias and width), and the wall, farther from the light, magnifies that.
    band = shadow_edge_band(lit.double(), pixels=3)
    band[:3], band[-3:], band[:, :3], band[:, -3:] = True, True, True, True
    keep = wall & ~band
    assert (slab == lit)[keep].all()
    if light[2] > 3.0:  # behind the plate's surface: the unbounded solid is wrong
        assert (unbounded != lit)[keep].sum() > 100
    if light[2] > 3.5:  # behind the slab too: nothing shadows the wall
        assert lit[wall].all() and slab[wall].all()


@pytest.mark.parametrize("light", [[1.0, 0.0, 3.8], [0.9, -0.5, 1.0]])
def test_the_bounded_solid_scans_only_where_the_unbounded_minimum_does_not_count(light, monkeypatch):
    # The shortcut (a node whose unbounded minimum lies in a slab reaching the ray keeps it)
    # gives exactly the full scan's visibility and gradient.
    import render.shadows.epipolar as epipolar

    g, lp, _, _ = _plate_before_wall(light, thickness=0.5)

    def run():
        position = lp[None, None].clone().requires_grad_(True)
        vis = epipolar_shadow_visibility(g.points, g.mask, g.intrinsics, position, EpipolarShadowOptions(thickness=0.5))
        (vis * torch.linspace(0, 1, vis.numel()).reshape(vis.shape)).sum().backward()
        return vis.detach(), position.grad

    fast = run()
    monkeypatch.setattr(epipolar, "_bounded_minima", lambda running, argmin, front, back, rows, node, gamma, soft:
                        epipolar._slab_minima(front, back, rows, node, gamma, soft))
    full = run()
    assert torch.equal(fast[0], full[0]) and torch.equal(fast[1], full[1])


def test_the_slab_end_is_the_angle_of_the_point_behind_the_surface(monkeypatch):
    # One cross product serves the surface's angle and its slab end's (the point behind is k X):
    # the same angles as building that point and taking its angle, before the cut at depth steps.
    import render.shadows.epipolar as epipolar

    g, lp, _, _ = _plate_before_wall([0.9, -0.5, 1.0], thickness=0.5)
    pts, valid = g.points.flatten(1, 2), g.mask.flatten(1)
    light = lp[None].to(pts)
    monkeypatch.setattr(epipolar, "_slab_ends", lambda front, back, valid, H, W: back)
    gamma, back = epipolar._slab_end_angles(pts, valid, light, torch.tensor([0.5], dtype=pts.dtype), *g.mask.shape[1:])
    behind = pts * (1 + 0.5 / pts.norm(dim=-1, keepdim=True))
    assert torch.allclose(gamma, epipolar._angle_from_camera_ray(pts, light[:, None]), atol=1e-12, rtol=0)
    expected = epipolar._angle_from_camera_ray(behind, light[:, None])
    assert torch.allclose(back[valid], expected[valid], atol=1e-12, rtol=0)


def test_a_bounded_solid_that_shadows_nothing_still_has_a_zero_gradient():
    # A flat wall: no pixel shadowed, none in a soft edge; the visibility is all ones and
    # backward works (it raised "expected a non-empty list", then "does not require grad").
    K = torch.tensor([[[40.0, 0, 19.5], [0, 40.0, 14.5], [0, 0, 1]]], dtype=torch.float64)
    g = GBuffer.from_depth(torch.full((1, 30, 40), 3.0, dtype=torch.float64), K)
    position = torch.tensor([[[0.3, -0.4, 1.0]]], dtype=torch.float64, requires_grad=True)
    vis = epipolar_shadow_visibility(g.points, g.mask, g.intrinsics, position, EpipolarShadowOptions(thickness=0.5))
    vis.sum().backward()
    assert bool((vis == 1).all()) and torch.equal(position.grad, torch.zeros_like(position))


def test_epipolar_thickness_of_the_scene_is_a_share_of_its_diagonal():
    g, lp, _, _ = _plate_before_wall([0.9, -0.5, 1.0], thickness=0.5)
    points = g.points[0][g.mask[0]]
    diagonal = (points.amax(0) - points.amin(0)).norm().item()
    run = lambda opts: epipolar_shadow_visibility(g.points, g.mask, g.intrinsics, lp[None, None], opts)
    assert torch.equal(run(EpipolarShadowOptions(scene_thickness=0.1)), run(EpipolarShadowOptions(thickness=0.1 * diagonal)))
    # Larger than any ray's depth behind the surface: the unbounded solid's answer.
    assert torch.allclose(run(EpipolarShadowOptions(thickness=1e6)), run(EpipolarShadowOptions(scene_thickness=None)),
                          atol=1e-9)


@pytest.mark.parametrize("fields", [{"thickness": 0.0}, {"thickness": float("inf")}, {"scene_thickness": -0.1},
                                    {"scene_thickness": float("nan")}, {"thickness": 0.1, "scene_thickness": 0.1}])
def test_epipolar_thickness_rejects_absurd_values(fields):
    with pytest.raises(ValueError, match="thickness"):
        EpipolarShadowOptions(**fields)


def test_footprint_splats_shadow_like_the_fixed_ones_where_points_are_dense():
    # A plate before a wall, a light in front: the footprint-sized splats and bias give the
    # same shadow as the fixed defaults away from its edges, and no acne on the lit wall.
    g, lp, wall, lit = _plate_before_wall([0.2, -0.1, 0.5], thickness=0.5)
    run = lambda opts: cube_shadow_visibility(g.points, g.mask, lp[None, None], opts)[0, 0] > 0.5
    footprint = run(CubeShadowOptions(footprint=True, splat_radius=0, bias=0.0))
    band = shadow_edge_band(lit.double(), pixels=3)
    keep = wall & ~band
    assert (footprint == lit)[keep].float().mean() > 0.99
