"""The driver's stages: network starts, batches, the clear coat, reflectance gains, options."""

import dataclasses


import math

import pytest
import torch
from selfsup.estimation.options import EstimateOptions, Tuning, RefineOptions
from selfsup.estimation.stages import estimate_batch, estimate_scene

from selfsup.estimation.prepare import prepare
from selfsup.estimation.records import records

from render import GBuffer, Material



from selfsup.scenes.exact import render_spec

from selfsup.scenes.sampler import sample_scene

from estimation_helpers import MEDIUM, _rel_error, _rel_error_paired, _scene


@pytest.mark.parametrize("name", ["shadows", "search_shadows"])
def test_unknown_shadow_model_is_named(name):
    with pytest.raises(ValueError, match=f"estimate.{'tuning.' if name == 'search_shadows' else ''}{name} must be one of"):
        EstimateOptions.from_settings(**{name: "raytraced"})


@pytest.mark.parametrize("seed, n_lights", [(4, 1), (11, 2)])
def test_shipped_network_starts_the_refinement_and_selection(seed, n_lights):
    scene = _scene(seed, n_lights, config=MEDIUM)
    record = estimate_scene(scene, EstimateOptions(method="cnn+refine", tuning=Tuning(refine=RefineOptions(max_iters=(15, 5)))))
    assert len(record["lights"]) == n_lights, record["candidates"]
    position = torch.tensor([light["position"] for light in record["lights"]])
    assert _rel_error_paired(position, scene) < 0.05  # success, as scene-format.md defines it


def test_a_batch_gives_each_scene_the_answer_it_gets_alone():
    # One light, two lights and a specular scene in one batch: mixed counts and switches.
    scenes = [_scene(4, 1, MEDIUM), _scene(11, 2, MEDIUM),
              _scene(3, 1, dataclasses.replace(MEDIUM, specular_prob=1.0))]
    options = EstimateOptions(method="cnn+refine", tuning=Tuning(refine=RefineOptions(max_iters=(15, 5))))
    problem = prepare(scenes, options)
    batched = records([s.id for s in scenes], problem, estimate_batch(problem, options), options)
    for scene, record in zip(scenes, batched):
        alone = estimate_scene(scene, options)
        assert [c["n_lights"] for c in record["candidates"]] == [c["n_lights"] for c in alone["candidates"]]
        assert record["specular"] == alone["specular"]
        for ours, theirs in zip(record["lights"], alone["lights"]):
            gap = (torch.tensor(ours["position"]) - torch.tensor(theirs["position"])).norm()
            assert float(gap) < 1e-3 * float(scene.scene_scale)
    assert [len(r["lights"]) for r in batched[:2]] == [1, 2]


def test_network_alone_gives_a_full_record(tmp_path):
    # Any checkpoint works (here an untrained network): the record has the contract's fields.
    from selfsup.checkpoint import save_network
    from selfsup.model import LightNet

    path = save_network(tmp_path / "net.pt", LightNet(max_lights=2, hidden=32), {"max_lights": 2, "hidden": 32})
    record = estimate_scene(_scene(4), EstimateOptions(method="cnn", checkpoint=str(path)))
    assert 1 <= len(record["lights"]) <= 2 and len(record["candidates"]) == 1
    light = record["lights"][0]
    assert len(light["position"]) == len(light["intensity"]) == len(light["position_std"]) == 3
    assert all(math.isfinite(v) for v in light["position"] + light["intensity"] + record["ambient"])


def test_unknown_method_is_named():
    with pytest.raises(ValueError, match="estimate.method must be one of"):
        EstimateOptions(method="magic")


def test_segment_gains_recover_each_surfaces_albedo_factor():
    from selfsup.estimation.gains import segment_gains

    torch.manual_seed(0)
    model = torch.rand(1, 3, 10, 12) + 0.5
    segments = torch.zeros(1, 10, 12, dtype=torch.long)
    segments[:, :, 6:] = 6  # labels are any ints; -1 is outside
    segments[:, 0, 0] = 1  # a one-pixel segment: too small to judge
    segments[:, 9, 11] = -1
    factor = torch.tensor([[0.5, 2.0, 1.5], [3.0, 0.8, 1.0]])  # (segment, channel)
    truth = torch.where(segments[..., None] == 6, factor[1], factor[0])  # (1, H, W, 3)
    image = model * truth.permute(0, 3, 1, 2)
    image[0, :, 2, 2] = 100.0  # an outlier pixel: the median ignores it
    gains = segment_gains(image, model, segments, min_pixels=10)
    inside = segments[0] >= 0
    judged = inside & (segments[0] != 1)
    assert torch.allclose(gains[0][judged], truth[0][judged], rtol=1e-5)
    assert (gains[0][~judged] == 1).all()


def test_reflectance_gains_correct_albedo_wrong_by_a_factor_per_surface():
    # kd of every smooth surface scaled by its own factor in [0.5, 2]: the plain fit takes
    # the brightness differences for shading (0.016 of the scene size, measured 2026-11-23);
    # one round of per-surface gains brings it to 0.007, two to 0.004.
    from render import GBuffer
    from selfsup.estimation.normals import surface_segments

    scene = _scene(7, config=MEDIUM)
    g = GBuffer.from_depth(scene.depth[None], scene.K[None])
    segments = surface_segments(g.points, g.normals, g.mask)[0]
    labels = segments.unique()
    factors = torch.exp(torch.empty(len(labels), 3).uniform_(-0.7, 0.7, generator=torch.Generator().manual_seed(7)))
    table = torch.ones(segments.numel(), 3)
    table[labels.clamp_min(0)] = factors
    wrong = dataclasses.replace(scene, kd=(scene.kd * table[segments.clamp_min(0)]).clamp(0, 1) * (segments >= 0)[..., None])
    errors = []
    for rounds in (0, 1):
        record = estimate_scene(wrong, EstimateOptions(max_lights=1, tuning=Tuning(reflectance_gains=rounds)))
        errors.append(_rel_error(torch.tensor(record["lights"][0]["position"]), scene))
    assert errors[1] < 0.01 and errors[1] < 0.6 * errors[0], errors
    with pytest.raises(ValueError, match="reflectance_gains"):
        EstimateOptions(tuning=Tuning(reflectance_gains=-1))


def _coated_copy(rendered):
    # The scene's image with its specular pixels' diffuse light through a clear coat
    # (render.Material.coat), from the exact geometry, visibility and lights.
    from render import light_transport
    scene = rendered.scene
    g = GBuffer.from_depth(scene.depth[None], scene.K[None], normals=scene.normals[None])
    coat = (scene.ks > 0).to(scene.kd.dtype)[None]
    lights = scene.light_pos[None]
    bare = light_transport(g, Material(kd=scene.kd[None]), lights, shadows="none").diffuse
    through = light_transport(g, Material(kd=scene.kd[None], coat=coat), lights, shadows="none").diffuse
    visible = rendered.visibility.permute(2, 0, 1)[None]  # (1, L, H, W)
    change = torch.einsum("blhw,lc->hwc", (through - bare) * visible, scene.light_intensity)
    return dataclasses.replace(scene, image=(scene.image + scene.kd * change).clamp_min(0))


def test_a_coated_scene_chooses_the_coat_and_a_bare_one_does_not():
    config = dataclasses.replace(MEDIUM, specular_prob=1.0)
    rendered = render_spec(sample_scene(3, config, n_lights=1), samples=1)
    coated = _coated_copy(rendered)
    assert float((coated.image - rendered.scene.image).abs().max()) > 0.02  # the coat shows
    options = EstimateOptions(method="refine", max_lights=1, tuning=Tuning(coat="auto"))
    on_coated = estimate_scene(coated, options)
    on_bare = estimate_scene(rendered.scene, options)
    assert on_coated["coat"] and not on_bare["coat"]
    assert [c["coat"] for c in on_bare["candidates"]].count(True) >= 1  # it was tried there too
    for record, scene in ((on_coated, coated), (on_bare, rendered.scene)):
        assert _rel_error(torch.tensor([l["position"] for l in record["lights"]]), scene) < 0.005
    never = estimate_scene(coated, options.tuned(coat="never"))
    assert not never["coat"] and all(not c["coat"] for c in never["candidates"])
    with pytest.raises(ValueError, match="estimate.tuning.coat"):
        EstimateOptions(tuning=Tuning(coat="sometimes"))


def test_a_pass_of_the_estimator_starts_from_the_coats_its_options_give():
    # reflectance_gains runs the estimator again on the same problem: a coat the last
    # pass chose must not stay on the material of the next one.
    from selfsup.estimation.stages import with_coat, estimate_batch
    from selfsup.estimation.prepare import prepare

    config = dataclasses.replace(MEDIUM, specular_prob=1.0)
    scene = render_spec(sample_scene(3, config, n_lights=1), samples=1).scene
    options = EstimateOptions(method="refine", max_lights=1, tuning=Tuning(coat="never"))
    problem = prepare([scene], options)
    problem.material = with_coat(problem.material, [True])  # as a pass under auto leaves it
    ((best, tried),) = estimate_batch(problem, options)
    assert problem.material.coat is None and not best.coat and not any(c.coat for c in tried)


def test_a_coated_two_light_scene_judges_both_coat_settings_at_two_lights():
    # The one-light fit of a two-light scene chooses the coat unreliably, so the chosen
    # two-light model is refitted with the other setting too and the better one kept.
    config = dataclasses.replace(MEDIUM, specular_prob=1.0)
    rendered = render_spec(sample_scene(4, config, n_lights=2), samples=1)
    coated = _coated_copy(rendered)
    record = estimate_scene(coated, EstimateOptions(method="refine", max_lights=2, tuning=Tuning(coat="auto")))
    assert len(record["lights"]) == 2 and record["coat"]
    assert {c["coat"] for c in record["candidates"] if c["n_lights"] == 2} == {True, False}
    assert _rel_error_paired(torch.tensor([l["position"] for l in record["lights"]]), coated) < 0.01
