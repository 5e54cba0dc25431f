"""Degenerate answers refused: lights that explain nothing, colour as a free knob, a record's shares."""

import dataclasses

import pytest
import torch

from selfsup.estimation.files import batch_size
from selfsup.estimation.options import EstimateOptions, Tuning
from selfsup.estimation.stages import estimate_scene

from estimation_helpers import MEDIUM, _rel_error, _scene


def _unknown_albedo(scene, value=0.5):
    # A capture: kd one constant wherever there is a surface.
    return dataclasses.replace(scene, kd=torch.where(scene.depth[..., None] > 0, torch.full_like(scene.kd, value), 0.0))


def _tinted(scene, rgb):
    # The scene under lights of colour ``rgb`` (the image is linear in the lights' intensities).
    tint = torch.tensor(rgb, dtype=scene.image.dtype)
    return dataclasses.replace(scene, image=scene.image * tint,
                               light_intensity=None if scene.light_intensity is None else scene.light_intensity * tint)


def test_a_frame_lit_by_ambient_alone_reports_no_light():
    # Shading one constant (each surface its albedo alone): no light explains anything, and
    # the record says so instead of presenting one with a small position_std.
    scene = _unknown_albedo(_scene(3, config=MEDIUM))
    albedo = 0.2 + 0.6 * torch.rand(scene.image.shape[:2], generator=torch.Generator().manual_seed(0))[..., None]
    flat = dataclasses.replace(scene, image=torch.where(scene.depth[..., None] > 0, albedo.expand(-1, -1, 3) * 0.3, 0.0))
    record = estimate_scene(flat, EstimateOptions(max_lights=1))
    assert record["light_found"] is False and record["lights"] == [] and record["direct_share"] == 0.0
    assert record["evidence"] <= 0 or max(light["share"] for light in record["unsupported_lights"]) < 0.1
    assert min(record["ambient"]) > 0  # the light is the ambient's, without direction


def test_a_lit_capture_reports_its_light_with_its_share_and_evidence():
    scene = _scene(3, config=MEDIUM)
    record = estimate_scene(_unknown_albedo(scene), EstimateOptions(max_lights=1))
    assert record["light_found"] is True and record["evidence"] > 0
    light = record["lights"][0]
    assert light["share"] >= Tuning().min_found_share and record["direct_share"] == pytest.approx(light["share"])
    assert _rel_error(torch.tensor(light["position"]), scene) < 0.05


def test_a_coloured_image_of_unknown_albedo_gets_neutral_lights_unless_colour_is_free():
    # Under a red-only light the channels solved on their own gave [x, 0, 0]; with the albedo
    # unknown the colour is the surfaces' as much as the light's: every light and the ambient
    # take the image's white, and their level is the grey image's.
    scene = _unknown_albedo(_scene(3, config=MEDIUM))
    red = _tinted(scene, [1.0, 0.02, 0.02])
    neutral = estimate_scene(red, EstimateOptions(max_lights=1))
    for colour in [light["intensity"] for light in neutral["lights"]] + [neutral["ambient"]]:
        assert max(colour) - min(colour) <= 1e-6 * max(max(colour), 1e-12)
    grey = estimate_scene(scene, EstimateOptions(max_lights=1))
    assert neutral["lights"][0]["position"] == pytest.approx(grey["lights"][0]["position"], abs=2e-3)  # segments of a red image differ a little
    assert neutral["lights"][0]["intensity"][0] == pytest.approx(grey["lights"][0]["intensity"][0] * 1.04 / 3, rel=0.06)
    free = estimate_scene(red, EstimateOptions(max_lights=1, tuning=Tuning(light_colour="free")))
    channels = free["lights"][0]["intensity"]
    assert min(channels) < 0.05 * max(channels)  # the old knob, kept on request
    shared = estimate_scene(red, EstimateOptions(max_lights=1, tuning=Tuning(light_colour="shared")))
    light, ambient = torch.tensor(shared["lights"][0]["intensity"]), torch.tensor(shared["ambient"])
    assert torch.allclose(light / light.sum() * ambient.sum(), ambient, atol=1e-5)  # one colour for both (or none)
    assert float(light[1] / light[0]) < 0.2  # the image's mean colour, red


def test_bad_plausibility_settings_are_named():
    with pytest.raises(ValueError, match="light_colour"):
        Tuning(light_colour="rgb")
    with pytest.raises(ValueError, match="min_found_share"):
        Tuning(min_found_share=1.5)
    for spread in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="evidence_spread"):
            Tuning(evidence_spread=spread)
    with pytest.raises(ValueError, match="estimate.batch must be 'auto' or an integer >= 1"):
        batch_size(0, torch.device("cpu"))
    assert batch_size("auto", torch.device("cpu")) == 1 and batch_size("auto", torch.device("cuda")) == 256


def test_the_falloff_of_a_lens_is_one_at_the_centre_and_the_share_lost_at_the_corners():
    from selfsup.estimation.vignetting import falloff

    K = torch.tensor([[[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]]], dtype=torch.float64).expand(2, 3, 3)
    f = falloff(K, 120, 160, torch.tensor([0.0, 0.3], dtype=torch.float64))
    assert torch.equal(f[0], torch.ones(120, 160, dtype=torch.float64))
    assert f[1, 59:61, 79:81].min() > 0.999
    corner = falloff(K[:1], 120, 160, torch.tensor([0.3], dtype=torch.float64))
    # The corner pixel's centre lies half a pixel inside the image's corner.
    assert corner[0, 0, 0] == pytest.approx(0.7, abs=0.01) and float(corner.min()) == float(corner[0, 0, 0])


def test_a_capture_through_a_vignetting_lens_keeps_its_light_where_it_is():
    # A brighter centre looked like a light near the camera: through 30% at the corners this
    # scene's light moved 0.11 of the scene; with the lens's falloff chosen per frame it
    # stays within 0.02 and the record names the falloff taken out.
    from selfsup.estimation.vignetting import falloff

    scene = _scene(11, config=MEDIUM)
    H, W = scene.image.shape[:2]
    lens = falloff(scene.K[None].double(), H, W, torch.tensor([0.3]))[0].to(scene.image.dtype)
    captured = _unknown_albedo(dataclasses.replace(scene, image=scene.image * lens[..., None]))
    for start in ("search", "settled"):  # the networks' settled light too is refined under each falloff
        record = estimate_scene(captured, EstimateOptions(max_lights=1, tuning=Tuning(cnn_start=start)))
        assert _rel_error(torch.tensor(record["lights"][0]["position"]), scene) < 0.02, start
        assert 0.15 <= record["vignetting"] <= 0.45, start
    ignored = estimate_scene(captured, EstimateOptions(max_lights=1, tuning=Tuning(vignetting="none")))
    light = (ignored["lights"] or ignored["unsupported_lights"])[0]
    assert _rel_error(torch.tensor(light["position"]), scene) > 0.05 and ignored["vignetting"] == 0.0


def test_the_strength_between_the_tried_ones_is_the_parabolas_lowest_point():
    from selfsup.estimation.vignetting import SHARES, _interpolated

    grid = torch.tensor(SHARES, dtype=torch.float64)
    truth = 0.3
    values = ((grid - truth) ** 2)[:, None].repeat(1, 2)  # (S, B): a parabola, lowest at 0.3
    values[:, 1] = torch.tensor([5.0, 1.0, 0.0])  # lowest at the last strength: kept there
    choice = values.argmin(0)
    assert _interpolated(values, choice).tolist() == pytest.approx([truth, SHARES[-1]])
