"""Where the albedo-free lights start (selfsup/estimation/albedo_free/light_search.py): split
starts, each light searched again, pairs found together, and the network's lights."""

import pytest
import torch

from selfsup.estimation import albedo_free
from selfsup.estimation.albedo_free import fit as albedo_fit
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.stages import estimate_scene
from selfsup.estimation.prepare import problem_of
from tests.estimation.test_albedo_free import MEDIUM, _scene, _unknown_albedo


def _shading_log(problem, fit):
    obs = albedo_free.observe(problem)
    return albedo_fit._log_model(albedo_fit._transport(obs, fit.position), fit.log_weight)[0]


def test_a_fit_without_a_light_or_with_one_alone_keeps_their_shading_up_to_its_scale():
    problem = problem_of(_unknown_albedo(_scene(11, n_lights=2)), shadows="none", dtype=torch.float64)
    position = torch.tensor([[[0.3, -1.0, 2.0], [-0.5, -0.8, 2.5], [0.0, -1.2, 1.5]]], dtype=torch.float64)
    fit = albedo_free.AlbedoFreeFit(position, torch.tensor([[-2.0, 0.0, 0.7, -0.4]], dtype=torch.float64),
                                    torch.ones(1, dtype=torch.float64), torch.ones(1, dtype=torch.long))
    for light in range(3):
        kept = [i for i in range(3) if i != light]
        alone = fit.without(light)
        assert float(alone.log_weight[0, 1]) == 0.0  # the gauge: the new first light's
        w = fit.log_weight.exp()[0]
        transport = albedo_fit._transport(albedo_free.observe(problem), position)[0]
        expected = (w[0] + sum(w[1 + i] * transport[i] for i in kept)).log()
        difference = _shading_log(problem, alone)[0] - expected
        mask = problem.gbuffer.mask[0]
        assert float(difference[mask].std()) < 1e-9  # one constant: the gauge's scale
        only = fit.only(light)  # this light and the ambient alone
        assert only.position.shape == (1, 1, 3) and float(only.log_weight[0, 1]) == 0.0
        expected = (w[0] + w[1 + light] * transport[light]).log()
        assert float((_shading_log(problem, only)[0] - expected)[mask].std()) < 1e-9
    with pytest.raises(ValueError, match="cannot leave light 3 out"):
        fit.without(3)
    with pytest.raises(ValueError, match="no light 3"):
        fit.only(3)


@pytest.mark.parametrize("lights", [1, 2])
def test_split_starts_replace_each_light_by_two_that_shade_as_it_does_when_not_moved(lights):
    problem = problem_of(_unknown_albedo(_scene(11, n_lights=2)), shadows="none", dtype=torch.float64)
    position = torch.tensor([[[0.3, -1.0, 2.0], [-0.5, -0.8, 2.5]][:lights]], dtype=torch.float64)
    log_weight = torch.tensor([[-2.0, 0.0, 0.7][: lights + 1]], dtype=torch.float64)
    fixed = albedo_free.AlbedoFreeFit(position, log_weight, torch.ones(1), torch.ones(1, dtype=torch.long))
    size = torch.tensor([2.0], dtype=torch.float64)
    starts, weights = albedo_free.split_starts(fixed, size)
    assert starts.shape == (1, 3 * lights, lights + 1, 3) and weights.shape == (1, 3 * lights, lights + 2)
    for j in range(lights):  # each split light's two halves lie 0.15 x size either side of it, along x, y, z
        halves = starts[0, 3 * j : 3 * j + 3][:, [j, lights]]
        torch.testing.assert_close(halves[:, 0] - halves[:, 1], 0.6 * torch.eye(3, dtype=torch.float64))
        torch.testing.assert_close(halves.mean(1), position[0, j].expand(3, 3))
    assert bool((weights[..., 1] == 0).all())  # the gauge
    unmoved, _ = albedo_free.split_starts(fixed, size, step=0.0)
    reference = _shading_log(problem, fixed)[0]
    mask = problem.gbuffer.mask[0]
    for s in range(3 * lights):
        split = albedo_free.AlbedoFreeFit(unmoved[:, s], weights[:, s], fixed.loss, fixed.pairs)
        assert float((_shading_log(problem, split)[0] - reference)[mask].std()) < 1e-9


def test_a_light_moved_back_in_place_leaves_the_model_as_it_was():
    scene = _scene(11, n_lights=2, config=MEDIUM)
    problem = problem_of(_unknown_albedo(scene), shadows="none", dtype=torch.float64)
    three = torch.cat([scene.light_pos[None], scene.light_pos[None, :1] + 0.3], 1).double()  # (1, 3, 3)
    fit = albedo_free.refine_positions(albedo_free.observe(problem), three,
                                       torch.tensor([[-3.0, 0.0, -0.5, 0.4]], dtype=torch.float64), iterations=0)
    reference = _shading_log(problem, fit)[0]
    mask = problem.gbuffer.mask[0]
    for light in range(3):
        moved = fit.with_last_at(light)
        assert torch.equal(moved.position[0, light], fit.position[0, 2])
        assert torch.equal(moved.position[0, [i for i in range(3) if i != light]], fit.position[0, :2])
        assert float(moved.log_weight[0, 1]) == 0.0  # the first light is the gauge
        # the same shading up to the overall scale the gauge fixes (a constant in log)
        assert float((_shading_log(problem, moved)[0] - reference)[mask].std()) < 1e-9
    with pytest.raises(ValueError, match="index 3"):
        fit.with_last_at(3)


def test_searching_each_light_again_frees_a_light_held_between_two():
    # The first light fitted alone lands between the two; the second searched with it held
    # there cannot undo that. Searched again with the second held, it finds its place.
    scene = _scene(11, n_lights=2, config=MEDIUM)
    problem = problem_of(_unknown_albedo(scene), shadows="none")
    truth = scene.light_pos[None]
    between = truth.mean(1, keepdim=True)
    held = albedo_free.refine_positions(albedo_free.observe(problem), torch.cat([between, truth[:, 1:]], 1),
                                        torch.tensor([[-3.0, 0.0, 0.0]]), iterations=0)

    def worst_error(fit):
        return max(float((fit.position[0] - light).norm(dim=-1).min() / scene.scene_scale) for light in scene.light_pos)

    assert worst_error(held) > 0.1
    fit = albedo_free.search_each(problem, held)
    assert worst_error(fit) < 0.05 and float(fit.loss[0]) < float(held.loss[0])


def _held_away(problem, scene):
    # One light fitted where neither is: half a scene in front of the two, towards the camera.
    away = scene.light_pos.mean(0) + 0.5 * scene.scene_scale * torch.tensor([0.0, 0.0, -1.0])
    return albedo_free.refine_positions(albedo_free.observe(problem), away[None, None], torch.tensor([[-3.0, 0.0]]),
                                        iterations=0)


def _worst_error(fit, scene):
    return max(float((fit.position[0] - light).norm(dim=-1).min() / scene.scene_scale) for light in scene.light_pos)


def test_pairs_found_together_free_two_lights_that_a_wrong_single_light_hides():
    # Held where the one-light fit wrongly lies, the first light keeps the second's search
    # from both lights; the anchor pairs move both (devset capture direct 031's case).
    scene = _scene(4, n_lights=2, config=MEDIUM)
    problem = problem_of(_unknown_albedo(scene), shadows="none")
    held = _held_away(problem, scene)
    alone = albedo_free.search(problem, 2, fixed=held, anchors=False)
    together = albedo_free.search(problem, 2, fixed=held)
    assert _worst_error(alone, scene) > 0.1
    assert _worst_error(together, scene) < 0.01 and float(together.loss[0]) < 0.5 * float(alone.loss[0])


def test_anchor_pairs_rank_each_image_of_a_batch_as_alone():
    from selfsup.estimation.prepare import problems_of
    from selfsup.estimation.problem import centre_and_size, subsample

    def pairs(problem, count=3):
        coarse = subsample(problem, 4)
        return albedo_free.anchor_pairs(albedo_free.observe(coarse), coarse, centre_and_size(problem)[1], count)

    scenes = [_unknown_albedo(_scene(seed, n_lights=2)) for seed in (4, 8)]
    position, log_weight = pairs(problems_of(scenes, shadows="none"))
    assert position.shape == (2, 3, 2, 3) and log_weight.shape == (2, 3, 3)
    assert bool((log_weight[..., 1] == 0).all())  # the gauge: the anchor's
    for i, scene in enumerate(scenes):  # each image's segments are its own
        alone = pairs(problem_of(scene, shadows="none"))
        torch.testing.assert_close(position[i : i + 1], alone[0])
        torch.testing.assert_close(log_weight[i : i + 1], alone[1])


def test_a_networks_lights_start_the_search_where_the_grid_alone_does_not_reach():
    # Held where the one-light fit wrongly lies and searched without the anchor pairs, the
    # second light is not found (the test above); a start at the true pair (a network's
    # lights) is taken, and a start of the wrong shape is named.
    scene = _scene(4, n_lights=2, config=MEDIUM)
    problem = problem_of(_unknown_albedo(scene), shadows="none")
    held = _held_away(problem, scene)
    started = albedo_free.search(problem, 2, fixed=held, anchors=False, extra_starts=scene.light_pos[None, None] + 0.02)
    assert _worst_error(started, scene) < 0.01
    with pytest.raises(ValueError, match="extra_starts"):
        albedo_free.search(problem, 2, fixed=held, extra_starts=scene.light_pos[None, None, :1])


def test_cnn_refine_gives_the_networks_lights_to_the_albedo_free_searches(monkeypatch):
    # A capture-like file (kd one constant) under cnn+refine with cnn_start=search: the first search of one light
    # and of two gets the network's first one and two slots (searching each light again,
    # the others held, needs none); method=refine gives none.
    seen = []
    search = albedo_free.search

    def recording(problem, n_lights=1, *args, extra_starts=None, **kwargs):
        seen.append(None if extra_starts is None else tuple(extra_starts.shape))
        return search(problem, n_lights, *args, extra_starts=extra_starts, **kwargs)

    monkeypatch.setattr(albedo_free, "search", recording)
    scene = _unknown_albedo(_scene(3))
    estimate_scene(scene, EstimateOptions.from_settings(method="cnn+refine", max_lights=2, cnn_start="search"))
    given = [shape for shape in seen if shape is not None]
    assert {shape[2] for shape in given} == {1, 2} and all(shape[1] == 1 and shape[-1] == 3 for shape in given), seen
    seen.clear()
    estimate_scene(scene, EstimateOptions(method="refine", max_lights=2))
    assert seen and all(shape is None for shape in seen)


def _capture_and_near_slots(n_lights):
    # A capture-like frame of n_lights and a network's two slots near its lights (the second far
    # from any light where there is one): (scene, slots (1, 2, 3)).
    scene = _unknown_albedo(_scene(3 if n_lights == 1 else 4, n_lights=n_lights, config=MEDIUM))
    offset = torch.tensor([0.03, -0.02, 0.02]) * scene.scene_scale
    slots = scene.light_pos[None, :2] + offset if n_lights == 2 else torch.stack(
        [scene.light_pos[0], scene.light_pos[0] + torch.tensor([1.0, -0.5, 0.5])])[None] + offset
    return scene, slots


@pytest.mark.parametrize("n_lights", [1, 2])
def test_where_the_network_is_sure_its_first_light_is_refined_not_searched(monkeypatch, n_lights):
    # cnn+refine with a network sure of itself (confidence 1): its first light refined where it
    # put it (no search of it); one light more searched beside it (its second a start), the
    # criterion choosing the count as after a search.
    from selfsup.estimation import network as network_module
    from selfsup.estimation import stages

    scene, slots = _capture_and_near_slots(n_lights)

    def sure_slots(problem, checkpoint=None, with_confidence=False):
        return slots.to(problem.image), torch.ones(1, 2, dtype=torch.bool), torch.ones(1)

    search = albedo_free.search

    def no_search(problem, n_lights=1, *args, fixed=None, **kwargs):
        if fixed is None:
            raise AssertionError("searched where the network was sure")
        return search(problem, n_lights, *args, fixed=fixed, **kwargs)

    monkeypatch.setattr(stages, "network_slots", sure_slots)
    monkeypatch.setattr(albedo_free, "search", no_search)
    monkeypatch.setattr(network_module, "network_slots", sure_slots)
    record = estimate_scene(scene, EstimateOptions.from_settings(method="cnn+refine", max_lights=2, cnn_start="search"))
    found = torch.tensor([light["position"] for light in record["lights"]])
    assert len(found) == n_lights
    assert float(torch.cdist(found, scene.light_pos).amin(0).max() / scene.scene_scale) < 0.01
    # Unsure (tuning.cnn_sure above its confidence): the search runs.
    with pytest.raises(AssertionError, match="searched"):
        estimate_scene(scene, EstimateOptions.from_settings(method="cnn+refine", max_lights=2, cnn_start="search",
                                                            cnn_sure=1.5))


@pytest.mark.parametrize("n_lights", [1, 2])
def test_the_settled_start_refines_the_networks_answer_with_no_first_light_search(monkeypatch, n_lights):
    # cnn+refine with tuning.cnn_start=settled: the networks' lights, settled and picked on
    # the frame (method=cnn's answer), are every frame's sure start, whatever a confidence says: the
    # first light refined where they put it, one light more searched beside it (the lean search).
    from selfsup.estimation import network as network_module

    scene, slots = _capture_and_near_slots(n_lights)
    asked = []

    def networks(problem, checkpoint=None, with_confidence=False):
        asked.append(checkpoint)
        assert not with_confidence, "the settled start needs no confidence"
        return slots.to(problem.image), torch.tensor([[True, n_lights == 2]])

    search = albedo_free.search

    def lean_only(problem, n_lights=1, *args, fixed=None, **kwargs):
        if fixed is None:
            raise AssertionError("the first light was searched")
        assert kwargs.get("anchors") is False and kwargs.get("per_axis") == (5, 5, 5), "not the lean search"
        return search(problem, n_lights, *args, fixed=fixed, **kwargs)

    monkeypatch.setattr(network_module, "network_slots", networks)
    monkeypatch.setattr(albedo_free, "search", lean_only)
    record = estimate_scene(scene, EstimateOptions.from_settings(max_lights=2, cnn_start="settled"))
    found = torch.tensor([light["position"] for light in record["lights"]])
    assert len(found) == n_lights
    assert float(torch.cdist(found, scene.light_pos).amin(0).max() / scene.scene_scale) < 0.01
    assert len(asked) == 2 and all(str(path).endswith((".pt")) for path in asked)  # both shipped iterative networks


def test_which_networks_each_method_loads():
    from selfsup.checkpoint import ITERATIVE_CHECKPOINT, STUDIO_CHECKPOINT
    from selfsup.estimation.network import answer_checkpoints, checkpoints_of, start_checkpoint

    shipped = (str(ITERATIVE_CHECKPOINT), str(STUDIO_CHECKPOINT))
    default = EstimateOptions()
    assert answer_checkpoints(default) == () and start_checkpoint(default) is None
    assert checkpoints_of(default) == (None,)  # the cost-volume network
    settled = EstimateOptions.from_settings(cnn_start="settled")
    assert answer_checkpoints(settled) == shipped
    assert checkpoints_of(settled) == shipped + (None,)  # the cost-volume network: files with their albedo
    named = EstimateOptions(checkpoint="mine.pt")
    assert answer_checkpoints(named) == () and checkpoints_of(named) == ("mine.pt",)
    assert checkpoints_of(EstimateOptions(method="cnn")) == shipped
    assert checkpoints_of(EstimateOptions(method="cnn", checkpoint="mine.pt")) == ("mine.pt",)
    assert answer_checkpoints(EstimateOptions(method="refine")) == ()
    with pytest.raises(ValueError, match="cnn_start"):
        EstimateOptions.from_settings(cnn_start="grid")


def test_the_settled_start_finds_the_light_where_the_networks_are_far_off(monkeypatch):
    # The settled start is only a start: networks whose lights lie two scene sizes from the lamp
    # (a frame unlike any they were trained on) still leave it the lamp, placed.
    from selfsup.estimation import network as network_module

    scene = _unknown_albedo(_scene(3, config=MEDIUM))
    size = scene.scene_scale
    slots = torch.stack([scene.light_pos[0] + torch.tensor([2.0, 2.0, -2.0]) * size,
                         scene.light_pos[0] + torch.tensor([2.3, 2.0, -2.0]) * size])[None]
    monkeypatch.setattr(network_module, "network_slots", lambda problem, checkpoint=None, with_confidence=False:
                        (slots.to(problem.image), torch.tensor([[True, False]])))
    record = estimate_scene(scene, EstimateOptions.from_settings(max_lights=2, cnn_start="settled"))
    found = torch.tensor([light["position"] for light in record["lights"]])
    assert len(found) == 1 and float((found[0] - scene.light_pos[0]).norm() / size) < 0.01
