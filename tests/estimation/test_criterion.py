"""Model selection: light counts, weak lights, the criterion's shadows and blocks."""

import dataclasses




import pytest
import torch
from selfsup.estimation.options import EstimateOptions, Tuning, RefineOptions
from selfsup.estimation.stages import estimate_batch, estimate_scene

from selfsup.estimation.prepare import prepare, problem_of
from selfsup.estimation.records import records

from render import EpipolarShadowOptions, GBuffer

from selfsup.estimation.solvers import refine, search





from estimation_helpers import MEDIUM, _rel_error, _rel_error_paired, _scene


@pytest.mark.parametrize("seed, n_lights", [(4, 1), (11, 2)])
def test_model_selection_picks_the_number_of_lights(seed, n_lights):
    scene = _scene(seed, n_lights, config=MEDIUM)
    record = estimate_scene(scene, EstimateOptions(method="refine", tuning=Tuning(refine=RefineOptions(max_iters=(15, 5)))))
    assert len(record["lights"]) == n_lights, record["candidates"]


@pytest.mark.parametrize("shadows", ["epipolar", "paper"])
def test_shadowed_selection_refines_the_shadow_free_search(shadows):
    # estimate.shadows=epipolar|paper: the search runs on shading alone, each
    # candidate is refined and judged with the shadows; two lights stay two.
    scene = _scene(11, 2, config=MEDIUM)
    record = estimate_scene(scene, EstimateOptions(method="refine", shadows=shadows, tuning=Tuning(refine=RefineOptions(max_iters=(15, 5)))))
    assert len(record["lights"]) == 2, record["candidates"]
    position = torch.tensor([light["position"] for light in record["lights"]])
    assert _rel_error_paired(position, scene) < 0.05


def test_a_true_light_shows_its_shadows_and_a_stand_in_does_not():
    from selfsup.estimation.criterion import shadow_gain

    for seed in (2, 3, 4):
        two = _scene(seed, n_lights=2, config=MEDIUM)
        gains = [float(shadow_gain(problem_of(two, "none"), two.light_pos[None], torch.tensor([j]), False,
                                   RefineOptions())) for j in (0, 1)]
        assert min(gains) > 0.1, gains  # measured 0.21-0.64
        # A second light in a one-light image, away in front of the scene: its shadows are not there.
        one = _scene(seed, config=MEDIUM)
        problem = problem_of(one, "none")
        centre = problem.gbuffer.points[0][problem.gbuffer.mask[0]].mean(0)
        stand_in = torch.stack([one.light_pos[0], centre + torch.tensor([0.0, -1.0, -1.5])])[None]
        assert float(shadow_gain(problem, stand_in, torch.tensor([1]), False, RefineOptions())) < 0.01
    with pytest.raises(ValueError, match="weak_light_shadow_gain"):
        EstimateOptions(tuning=Tuning(weak_light_shadow_gain=-1))


def test_the_criterion_block_follows_the_image_width():
    from selfsup.estimation.criterion import block_px

    options = EstimateOptions(tuning=Tuning(block_width=0.05))
    assert [block_px(options, w) for w in (160, 80, 320, 8)] == [8, 4, 16, 1]
    assert block_px(EstimateOptions(), 160) == 16  # the defaults: 0.1 of the width, 0.05 albedo-free
    assert block_px(EstimateOptions(), 160, albedo_free=True) == 8
    with pytest.raises(ValueError, match="block_width"):
        EstimateOptions(tuning=Tuning(block_width=0))


def test_a_light_with_no_intensity_is_never_kept_on_a_clean_image():
    # An empty room (no cast shadows), rendered without noise: one light fits it to float
    # precision, and the relative shadow gain of a second, dark light is rounding (5.5%
    # here). Without the share floor that light was kept, with intensity 0 or 1e-6.
    scene = _scene(4, 1, config=dataclasses.replace(MEDIUM, n_objects=(0, 0)))
    record = estimate_scene(scene, EstimateOptions())
    assert len(record["lights"]) == 1 and _rel_error(torch.tensor(record["lights"][0]["position"]), scene) < 1e-3
    # The dark light appears with the candidates fitted at stride 2 from 8 grid starts
    # (the defaults until 2026-11-23); the floor must hold wherever it appears.
    earlier = dict(cnn_starts=8, refine=RefineOptions(strides=(2, 1)))
    assert len(estimate_scene(scene, EstimateOptions.from_settings(**earlier))["lights"]) == 1
    unfloored = estimate_scene(scene, EstimateOptions.from_settings(weak_light_min_share=0.0, **earlier))
    brightness = sorted(max(light["intensity"]) for light in unfloored["lights"])
    assert len(brightness) == 2 and brightness[0] < 1e-4 * brightness[1]
    with pytest.raises(ValueError, match="weak_light_min_share"):
        EstimateOptions(tuning=Tuning(weak_light_min_share=-0.1))


def test_a_weak_true_light_that_pays_twice_over_is_kept():
    # Two-light scene 44 of the procedural benchmark (seed 9100): its second light carries
    # 7.5% of the direct light, below min_light_share, shows no shadow gain, and lowers
    # BIC by 650 (2026-11-23), far more than twice its parameters' cost (33). The
    # weak lights of one-light scenes that pay lowered it by 2-22.
    from benchmarks.estimate_procedural import score, set_scene

    scene = set_scene("true reflectance, 2 lights", 44, 9100)
    record = estimate_scene(scene, EstimateOptions())
    assert len(record["lights"]) == 2 and score(record, scene)[1]
    assert len(estimate_scene(scene, EstimateOptions(tuning=Tuning(weak_light_penalty=0)))["lights"]) == 1
    with pytest.raises(ValueError, match="weak_light_penalty"):
        EstimateOptions(tuning=Tuning(weak_light_penalty=0.5))


def test_a_light_that_pays_only_against_a_missed_one_light_search_is_dropped(monkeypatch):
    # The one-light search misses (made to here: it returns the true light mirrored across
    # the scene, barely refined), so a second light pays for itself beside it (the share
    # floors are off, as for a stand-in that carries light: Mitsuba gi scene 012 of
    # seed 7000 got such a one). The chosen pair is refitted without each of its lights:
    # one light at the truth wins.
    import selfsup.estimation.stages

    scene = _scene(4, 1, config=MEDIUM)
    truth = torch.as_tensor(scene.light_pos, dtype=torch.float32)

    def missing_search(problem, n_lights, options=None, fixed=None, **kwargs):
        if n_lights > 1:
            return search(problem, n_lights, options, fixed=fixed, **kwargs)
        centre = problem.gbuffer.extent()[0]
        wrong = truth.clone()
        wrong[:, :2] = 2 * centre[:, :2] - truth[:, :2]
        once = dataclasses.replace(options, max_iters=tuple(1 for _ in options.max_iters))
        return refine(problem, wrong[None].expand(problem.batch, -1, -1), once)

    monkeypatch.setattr(selfsup.estimation.stages, "search", missing_search)
    record = estimate_scene(scene, EstimateOptions(method="refine", tuning=Tuning(min_light_share=0.0, weak_light_min_share=0.0)))
    counts = [c["n_lights"] for c in record["candidates"]]
    assert counts[:2] == [1, 2] and counts[2:] == [1, 1], record["candidates"]  # the pair, then each light dropped
    assert record["candidates"][1]["criterion"] < record["candidates"][0]["criterion"]  # the pair beat the miss
    assert len(record["lights"]) == 1 and _rel_error(torch.tensor([record["lights"][0]["position"]]), scene) < 1e-3


def test_two_close_lights_are_told_from_one_by_their_double_shadows():
    # Two-light scene 15 of the procedural benchmark (seed 4242): lights of equal intensity
    # 0.029 of the scene apart, whose shading is nearly one light's. Judged by shading alone
    # one light was enough; judged with cast shadows both are found (2026-11-23: the
    # worst light 0.0002 of the scene off).
    from benchmarks.estimate_procedural import score, set_scene

    scene = set_scene("true reflectance, 2 lights", 15, 4242)
    record = estimate_scene(scene, EstimateOptions())
    assert len(record["lights"]) == 2 and score(record, scene)[1]
    shading_alone = EstimateOptions(tuning=Tuning(criterion_shadows="none", criterion_stride=1))
    assert len(estimate_scene(scene, shading_alone)["lights"]) == 1


def test_a_light_hidden_behind_a_box_is_found_once_the_solid_behind_surfaces_ends():
    # Two-light scene 173 of the procedural benchmark (seed 4242): one light hides from
    # the camera behind a box. Under the unbounded heightfield it sits inside the solid
    # behind the box, every pixel is in its shadow, and the pair loses to one light;
    # with the criterion's solid ending 0.03 of the scene behind each surface both are
    # found (2026-11-25: worst light 0.002 of the scene off).
    from benchmarks.estimate_procedural import score, set_scene

    scene = set_scene("true reflectance, 2 lights", 173, 4242)
    record = estimate_scene(scene, EstimateOptions())
    assert len(record["lights"]) == 2 and score(record, scene)[1]
    unbounded = estimate_scene(scene, EstimateOptions(tuning=Tuning(criterion_thickness=None)))
    # One light; inside the unbounded solid it lights no visible surface, so it is not presented as found.
    assert len(unbounded["lights"] or unbounded["unsupported_lights"]) == 1


def test_the_criterion_judges_the_fit_itself_only_where_nothing_differs():
    from selfsup.estimation.criterion import judged_problem

    problem = problem_of(_scene(3), "none")
    assert judged_problem(problem, EstimateOptions(tuning=Tuning(criterion_shadows="none", criterion_stride=1))) is problem
    judged = judged_problem(problem, EstimateOptions())  # epipolar, every second pixel, a finite solid
    assert judged.shadows == "epipolar" and tuple(judged.image.shape[-2:]) == (24, 32) and not judged.indirect
    assert judged.shadow_options == EpipolarShadowOptions(scene_thickness=EstimateOptions().tuning.criterion_thickness)
    assert judged.select(torch.tensor([0, 0])).shadow_options == judged.shadow_options
    unbounded = judged_problem(problem, EstimateOptions(tuning=Tuning(criterion_thickness=None))).shadow_options
    assert unbounded.scene_thickness is None and unbounded.thickness is None  # the unbounded solid, asked for
    assert judged_problem(dataclasses.replace(problem, ambient=None), EstimateOptions()).indirect
    assert not judged_problem(dataclasses.replace(problem, ambient=None), EstimateOptions(tuning=Tuning(indirect="never"))).indirect
    # Valid pixels on odd rows alone: every second pixel would see none of them, so every pixel is judged.
    g = problem.gbuffer
    odd_rows = torch.zeros_like(g.mask)
    odd_rows[:, 1::2] = g.mask[:, 1::2]
    sparse = dataclasses.replace(problem, gbuffer=GBuffer(g.points, g.normals, odd_rows, g.intrinsics))
    assert judged_problem(sparse, EstimateOptions()).image.shape == problem.image.shape
    with pytest.raises(ValueError, match="criterion_stride"):
        EstimateOptions(tuning=Tuning(criterion_stride=0))
    with pytest.raises(ValueError, match="criterion_shadows"):
        EstimateOptions(tuning=Tuning(criterion_shadows="soft"))
    for absurd in (0.0, -0.1, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="criterion_thickness"):
            EstimateOptions(tuning=Tuning(criterion_thickness=absurd))


def test_a_mirrored_scene_gets_the_mirrored_light():
    # Flipping the image left-right (K's principal point and the x axis with it) is the
    # same scene seen in a mirror: the estimate must mirror too (grid, starts, pyramid
    # and criterion hold no preferred side).
    scene = _scene(7, config=MEDIUM)
    W = scene.depth.shape[1]
    K = scene.K.clone()
    K[0, 2] = W - 1 - K[0, 2]
    mirror = torch.tensor([-1.0, 1.0, 1.0])
    flipped = dataclasses.replace(scene, image=scene.image.flip(1), depth=scene.depth.flip(1), kd=scene.kd.flip(1),
                                  ks=None if scene.ks is None else scene.ks.flip(1), K=K,
                                  shininess=scene.shininess.flip(1) if scene.shininess.dim() == 2 else scene.shininess,
                                  normals=None if scene.normals is None else scene.normals.flip(1) * mirror)
    options = EstimateOptions(method="refine", tuning=Tuning(refine=RefineOptions(max_iters=(15, 5))))
    plain, mirrored = estimate_scene(scene, options), estimate_scene(flipped, options)
    assert len(plain["lights"]) == len(mirrored["lights"]) == 1
    back = torch.tensor(mirrored["lights"][0]["position"]) * mirror
    assert float((back - torch.tensor(plain["lights"][0]["position"])).norm() / scene.scene_scale) < 1e-3


def test_the_narrow_final_scale_places_the_light_closer():
    # The exact images hold cast shadows that the default fit (shading alone) lacks: a
    # narrow Cauchy scale in the last refinement weighs them less (2026-11-23, seeds
    # 1-8: 0.00001-0.00003 against 0.00007-0.00025 of the scene size).
    for seed in (2, 4):
        scene = _scene(seed, config=MEDIUM)
        errors = {}
        for final in (0.2, 0.05):
            record = estimate_scene(scene, EstimateOptions(tuning=Tuning(final_robust_scale=final)))
            assert len(record["lights"]) == 1
            errors[final] = _rel_error(torch.tensor(record["lights"][0]["position"]), scene)
        assert errors[0.05] < 0.3 * errors[0.2], errors


def test_intensities_under_unaccounted_light_are_solved_with_its_indirect_light():
    # An image with each light's first bounce (selfsup.indirect, the model itself) added
    # and no ambient given: the fit, direct light only, takes the bounce for more lamp;
    # the reported intensities, solved again with it at the chosen position, do not.
    from render import light_transport
    from selfsup.scenes.indirect import indirect_columns

    scene = _scene(6, config=MEDIUM)
    problem = prepare([scene], EstimateOptions())
    true = scene.light_pos[None]
    diffuse = light_transport(problem.gbuffer, problem.material, true, falloff="inverse_square", shadows="none",
                              specular=False).diffuse
    bounce = (indirect_columns(problem.gbuffer, problem.material.kd, diffuse)
              * scene.light_intensity.T[None, :, :, None, None]).sum(2)[0]  # (3, H, W)
    scene = dataclasses.replace(scene, image=scene.image + bounce.permute(1, 2, 0), ambient=None)
    options = EstimateOptions(max_lights=1)
    problem = prepare([scene], options)
    best = estimate_batch(problem, options)[0][0]
    record = records([scene.id], problem, [(best, [best])], options)[0]

    def error(intensity):
        return float((torch.as_tensor(intensity).reshape(3) - scene.light_intensity[0]).abs().max() / scene.light_intensity[0].max())

    fitted, reported = error(best.fit.intensity[0, 0]), error(record["lights"][0]["intensity"])
    assert reported < 0.5 * fitted and reported < 0.03, (fitted, reported)
    assert record["lights"][0]["position"] == best.fit.position[0, 0].tolist()
    never = records([scene.id], problem, [(best, [best])], options.tuned(indirect="never"))[0]
    assert never["lights"][0]["intensity"] == best.fit.intensity[0, 0].tolist()


def test_a_light_giving_the_surfaces_almost_no_light_is_not_presented():
    # Beside a found light, one that gives the visible surfaces under weak_light_min_share of
    # their light (cast shadows counted) is not presented: it goes to unsupported_lights and its
    # light to the ambient (a one-light procedural room's second light, which the geometry hid
    # from nearly every visible surface, gave 0.46% of the light). At 1.5% it is presented.
    scene = _scene(6, config=MEDIUM)
    options = EstimateOptions(max_lights=1)
    problem = prepare([scene], options)
    best = estimate_batch(problem, options)[0][0]
    found = records([scene.id], problem, [(best, [best])], options)[0]
    assert found["light_found"] and len(found["lights"]) == 1
    beside = scene.light_pos[0] + torch.tensor([0.3, 0.0, 0.0]) * scene.scene_scale

    def with_second(ratio):
        fit = dataclasses.replace(best.fit, position=torch.cat([best.fit.position, beside[None, None]], 1),
                                  intensity=torch.cat([best.fit.intensity, ratio * best.fit.intensity], 1))
        two = dataclasses.replace(best, fit=fit, n_lights=2, covariance=None)
        return records([scene.id], problem, [(two, [two])], options.tuned(indirect="never"))[0]

    faint, weak = with_second(0.003), with_second(0.02)
    assert len(weak["lights"]) == 2 and 0.01 < min(light["share"] for light in weak["lights"]) < 0.05
    assert faint["light_found"] and len(faint["lights"]) == 1 and len(faint["unsupported_lights"]) == 1
    assert faint["unsupported_lights"][0]["share"] < options.tuning.weak_light_min_share
    assert faint["lights"][0]["position"] == best.fit.position[0, 0].tolist()
    assert sum(faint["ambient"]) > sum(found["ambient"])
    assert faint["direct_share"] == faint["lights"][0]["share"]
