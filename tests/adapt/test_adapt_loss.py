"""The albedo-free loss of mode=adapt: the albedo solved per region, the gradient through shading and shadows, the guards."""

import dataclasses

import pytest
import torch

from render import Material, PointLights, ShadowedBlinnPhong, render
from selfsup.adapt import GuardOptions, degenerate_lights, guard_penalty, refusals, surface_violation
from selfsup.linear import segment_albedo
from selfsup.losses import LossOptions, SceneBatch, reconstruction_loss
from selfsup.model import LightNet, scene_frame
from tests.conftest import CAMERA_SIDE_LIGHTS, exact_view, gbuffer_of

H, W = 48, 64
LIGHT = CAMERA_SIDE_LIGHTS[0]


def _two_albedo_scene(dtype=torch.float32):
    """The sphere-and-box view lit by ``LIGHT`` through our layer (its shadows), the left half
    of the image one albedo and the right half another; its regions and the true kd."""
    g = gbuffer_of(exact_view(tuple(LIGHT), H, W), dtype)
    right = torch.arange(W) >= W // 2
    kd = torch.where(right[None, None, :, None], torch.tensor([0.2, 0.5, 0.3], dtype=dtype),
                     torch.tensor([0.7, 0.6, 0.4], dtype=dtype)).expand(1, H, W, 3).contiguous()
    lights = PointLights(torch.tensor([[LIGHT]], dtype=dtype), torch.full((1, 1, 3), 8.0, dtype=dtype))
    image = render(g, Material(kd=kd), lights, torch.full((1, 3), 0.02, dtype=dtype)).image
    labels = torch.where(g.mask, right.expand(H, W).long(), torch.tensor(2)).view(1, H * W)
    return image, g, kd, (labels, 2)


def _prediction(position: torch.Tensor, image, g):
    # The network's output with its one slot moved to ``position (1, 1, 3)``.
    network = LightNet(max_lights=1)
    return dataclasses.replace(network(image.float(), g), position=position)


def test_segment_albedo_recovers_each_regions_colour_up_to_one_scale():
    image, g, kd, (labels, count) = _two_albedo_scene(torch.float64)
    transport = ShadowedBlinnPhong().transport(g, Material(kd=kd), torch.tensor([[LIGHT]], dtype=torch.float64))
    weights = g.mask[:, None].expand_as(image).to(image.dtype)
    solved = segment_albedo(transport.diffuse, image, weights, labels, count, iterations=3)
    ratio = (solved / kd)[g.mask]  # one scale a channel (light and albedo trade it), over every pixel
    assert float((ratio.std(0) / ratio.mean(0)).max()) < 1e-6
    mean = solved[g.mask].mean(0)
    assert torch.allclose(mean, torch.full_like(mean, 0.5))  # grey on average: the capture's convention


def test_albedo_free_loss_is_least_at_the_true_light_and_reads_no_albedo():
    image, g, kd, segments = _two_albedo_scene()
    renderer = ShadowedBlinnPhong(check_finite=False)
    grey = Material(kd=torch.full_like(kd, 0.5))
    scenes = SceneBatch(image, g, grey)
    true = torch.tensor([[LIGHT]])

    def cost(position, material=grey):
        terms = reconstruction_loss(_prediction(position, image, g), SceneBatch(image, g, material), renderer,
                                    LossOptions(), segments=segments)
        return float(terms.photometric)

    at_truth = cost(true)
    assert at_truth < 1e-4
    for shift in ([0.3, 0, 0], [0, 0.3, 0], [0, 0, 0.4]):
        assert cost(true + torch.tensor(shift)) > 5 * at_truth + 1e-4
    assert cost(true, Material(kd=torch.rand_like(kd))) == pytest.approx(at_truth, rel=1e-5)  # kd is never read
    with_given_kd = reconstruction_loss(_prediction(true, image, g), scenes, renderer, LossOptions())
    assert float(with_given_kd.photometric) > 10 * at_truth  # grey kd is wrong here: the solve is what fits


def test_gradient_reaches_the_light_position_through_shading_and_shadows():
    image, g, kd, segments = _two_albedo_scene()
    grey = Material(kd=torch.full_like(kd, 0.5))
    start = torch.tensor([[LIGHT]]) + torch.tensor([0.2, -0.1, 0.3])
    gradients = {}
    for shadows in ("epipolar", "none"):
        position = start.clone().requires_grad_(True)
        terms = reconstruction_loss(_prediction(position, image, g), SceneBatch(image, g, grey),
                                    ShadowedBlinnPhong(shadows=shadows, check_finite=False), LossOptions(),
                                    segments=segments)
        (grad,) = torch.autograd.grad(terms.total, position)
        assert torch.isfinite(grad).all() and grad.abs().sum() > 0
        gradients[shadows] = grad
    # The shadows' effect reaches the gradient: with them the gradient is not the shading's alone.
    assert (gradients["epipolar"] - gradients["none"]).norm() > 0.01 * gradients["none"].norm()
    # And a step down it lowers the loss.
    position = start.clone().requires_grad_(True)
    for _ in range(20):
        terms = reconstruction_loss(_prediction(position, image, g), SceneBatch(image, g, grey),
                                    ShadowedBlinnPhong(check_finite=False), LossOptions(), segments=segments)
        (grad,) = torch.autograd.grad(terms.total, position)
        with torch.no_grad():
            position -= 0.05 * grad / grad.norm().clamp_min(1e-12)
    assert (position - torch.tensor([[LIGHT]])).norm() < (start - torch.tensor([[LIGHT]])).norm()


def test_a_frame_without_pixels_to_explain_is_refused():
    image, g, kd, (labels, count) = _two_albedo_scene()
    empty = dataclasses.replace(g, mask=torch.zeros_like(g.mask))
    with pytest.raises(ValueError, match="no valid pixel"):
        reconstruction_loss(_prediction(torch.tensor([[LIGHT]]), image, g), SceneBatch(image, empty, Material(kd=kd)),
                            ShadowedBlinnPhong(check_finite=False), LossOptions(), segments=(labels, count))


def test_guards_flag_lights_against_and_behind_the_surfaces_and_push_them_out():
    image, g, kd, _ = _two_albedo_scene()
    size = scene_frame(image, g).size
    guards = GuardOptions()
    centre = g.points[0][H // 2, W // 2]
    free = torch.tensor(LIGHT)
    on_surface = centre + 0.005 * g.normals[0][H // 2, W // 2]
    behind = centre * 1.5  # along the ray of its pixel, past the surface seen there
    position = torch.stack([free, on_surface, behind])[None]
    flags = degenerate_lights(position, g, size, guards)
    assert flags.tolist() == [[False, True, True]]
    too_close, beyond = surface_violation(position, g, size, guards)
    assert float(too_close[0, 1]) > 0 and float(beyond[0, 2]) > 0 and float(too_close[0, 0] + beyond[0, 0]) == 0
    moved = position.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(guard_penalty(moved, g, size, guards), moved)
    assert float(grad[0, 0].abs().sum()) == 0  # a light in free space feels nothing
    assert float((grad[0, 2] * centre).sum()) > 0  # behind: pushed back towards the camera


def test_refusals_name_collapse_degenerate_lights_and_forgetting():
    start = {"degenerate_share": 0.0, "mean_count": 1.2, "procedural_median_error": 0.05}
    guards = GuardOptions()
    assert refusals(start, dict(start), guards) == []
    assert refusals(start, dict(start, held_loss=0.0), guards) == []
    all_on = refusals(start, dict(start, mean_count=3.0), guards)
    assert len(all_on) == 1 and "slots switched on" in all_on[0]
    assert "in or behind surfaces" in refusals(start, dict(start, degenerate_share=0.5), guards)[0]
    assert "forgetting" in refusals(start, dict(start, procedural_median_error=0.06), guards)[0]
    assert refusals(start, dict(start, procedural_median_error=0.054), guards) == []
    with pytest.raises(ValueError, match="clearance"):
        GuardOptions(clearance=-1)


def test_teacher_loss_assigns_slots_and_reaches_positions_scores_and_count():
    from selfsup.adapt import TeacherOptions, teacher_loss

    image, g, _, _ = _two_albedo_scene()
    network = LightNet(max_lights=2)
    prediction = network(image, g)
    size = scene_frame(image, g).size
    # The teacher's two lights are the slots' own positions, in the other order: no position error.
    teacher = prediction.position.detach().flip(1)
    mask = torch.ones(1, 2, dtype=torch.bool)
    options = TeacherOptions(count=0.5)  # the count's term on (off by default)
    total, parts = teacher_loss(prediction, teacher, mask, size, options)
    assert parts["teacher_position"] < 1e-6
    moved = teacher + torch.tensor([0.3, 0.0, 0.0])
    total, parts = teacher_loss(prediction, moved, mask, size, options)
    assert parts["teacher_position"] > 0.01
    total.backward()
    for name in ("anchor_out.weight", "count_out.0.weight"):
        grad = dict(network.named_parameters())[name].grad
        assert grad is not None and grad.abs().sum() > 0, name
    nothing, parts = teacher_loss(prediction, moved, torch.zeros_like(mask), size, options)
    assert float(nothing) == 0 and parts == {}  # a frame where the search found no light teaches nothing


def test_a_mirrored_batch_is_the_mirrored_room_and_mirroring_twice_is_none():
    from render import GBuffer
    from selfsup.adapt.frames import FrameBatch, mirrored

    image, g, _, (labels, count) = _two_albedo_scene()
    g = GBuffer(g.points.float(), g.normals.float(), g.mask, intrinsics=g.intrinsics.float())
    image = image.float()
    teacher = torch.tensor([[LIGHT, [0.0, 0.0, 0.0]]], dtype=torch.float32)
    batch = FrameBatch(["a"], image, g, image, g, (labels, count), teacher, torch.tensor([[True, False]]))
    flipped = mirrored(batch, torch.tensor([True]))
    assert torch.equal(flipped.image[0, :, :, 0], image[0, :, :, -1])
    assert torch.equal(flipped.gbuffer.points[0, :, 0, 0], -g.points[0, :, -1, 0])
    assert float(flipped.teacher[0, 0, 0]) == pytest.approx(-LIGHT[0])
    # Each mirrored point still projects onto its own pixel through the mirrored intrinsics.
    K, points = flipped.gbuffer.intrinsics[0], flipped.gbuffer.points[0]
    v, u = torch.nonzero(flipped.gbuffer.mask[0], as_tuple=True)
    projected = points[v, u] @ K.T
    assert torch.allclose(projected[:, 0] / projected[:, 2], u.float(), atol=1e-3)
    back = mirrored(flipped, torch.tensor([True]))
    assert torch.equal(back.image, image) and torch.equal(back.gbuffer.points, g.points)
    assert torch.equal(back.segments[0], labels) and torch.equal(back.teacher, teacher)
    kept = mirrored(batch, torch.tensor([False]))
    assert torch.equal(kept.image, image) and torch.equal(kept.teacher, teacher)
