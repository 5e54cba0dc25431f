"""The real-photograph case, made by our own generator: glossy objects of one albedo under one
lamp in the dark, through a camera (auto exposure, sRGB, 8 bits, millimetre depth)."""

import dataclasses
import math

import pytest
import torch

from selfsup.estimation import EstimateOptions, Tuning, albedo_free
from selfsup.estimation.normals import surface_segments
from selfsup.estimation.prepare import prepare, problem_of, saturated_pixels, within_pixels, working_range
from selfsup.estimation.stages import estimate_scene
from selfsup.scenes.exact import render_spec
from selfsup.scenes.studio import HARD_PAINTS, lamp_angle_deg, photograph, sphere_centre, studio_spec


@pytest.mark.parametrize("others,direction", [(False, (0.3, -0.5, -0.81)), (True, (-0.6, -0.3, -0.74))])
def test_a_glossy_object_in_the_dark_gives_its_light_within_two_degrees(tmp_path, others, direction):
    # The shared DiLiGenT ball got "no light" in every frame: the normals refitted through
    # planes 21x21 pixels wide were 19 degrees off on the ball, and the image's edges of shading
    # cut it into bands whose free levels took the shading. Before, these two frames got "no
    # light" and 3.9 degrees.
    spec = studio_spec(direction, others=others)
    record = estimate_scene(photograph(tmp_path, spec), EstimateOptions())
    assert record["light_found"] is True and len(record["lights"]) == 1 and record["evidence"] > 20
    assert lamp_angle_deg(record, spec, direction) < 2.0
    assert record["lights"][0]["share"] > 0.8 and max(record["ambient"]) < 0.2 * record["lights"][0]["intensity"][0]
    # The highlight is not modelled (a diffuse-only fit): its pixels are left out, and the record says how many.
    assert record["specular"] is False and record["highlight_pixels"] > 20


GRAZING = [(0.8, -0.2, -0.56), (-0.85, -0.1, -0.5)]
# Known short (strict: it fails the suite once it passes): a region joined across a stripe's
# dim edge, where sRGB leaves the albedo's step a few codes, puts this lamp 10.8 degrees off.
# Segmenting the log image places it within 0.2 but loses Mitsuba rooms (decisions, 2026-12-04).
STRIPES_SHORT = pytest.mark.xfail(strict=True, reason="a region joined across a dim stripe edge: 10.8 degrees")


@pytest.mark.parametrize("name,direction", [
    pytest.param(name, direction, marks=STRIPES_SHORT if (name.startswith("grey stripes") and direction == GRAZING[0]) else ())
    for name in sorted(HARD_PAINTS) for direction in GRAZING])
def test_hard_objects_in_the_dark_give_their_light_within_two_degrees(tmp_path, name, direction):
    # Grazing lamps from either side: the box and the cylinder cast shadows on the sphere and
    # on the dark around them.
    spec = studio_spec(direction, others=True, **HARD_PAINTS[name])
    record = estimate_scene(photograph(tmp_path, spec), EstimateOptions())
    assert record["light_found"] is True and len(record["lights"]) == 1
    assert lamp_angle_deg(record, spec, direction) < 2.0


# Parts that hide each other: with the true depth the lamp is found; with the depth integrated
# from the normals (as the DiLiGenT objects' depth was made) the hidden jumps become a tilted
# sheet whose normals are 4 degrees off at the median, and the light lands 8.4 degrees off (a
# Lambertian fit given that depth's normals: 10.5 over 24 frames). Known short, strict.
SHEET_SHORT = pytest.mark.xfail(strict=True, reason="depth integrated across hidden jumps: 8.4 degrees")


@pytest.mark.parametrize("depth", ["rendered", pytest.param("integrated", marks=SHEET_SHORT)])
def test_parts_that_hide_each_other_give_their_light_within_two_degrees(tmp_path, depth):
    direction = (0.775, -0.566, -0.283)
    spec = studio_spec(direction, arrangement="overlapping", seed=16)
    record = estimate_scene(photograph(tmp_path, spec, seed=16, depth=depth), EstimateOptions())
    assert record["light_found"] is True and len(record["lights"]) == 1
    assert lamp_angle_deg(record, spec, direction) < 2.0


def test_a_light_that_explains_the_shading_is_found_where_an_integrated_depth_misses_it(tmp_path):
    # Gold paint over parts that hide each other, the depth integrated from the normals: the
    # sheet's normals miss the shading by more than the sensor's noise, and judged at that noise
    # the ambient alone beat a light giving all the light (evidence -3.1, "no light", as on
    # DiLiGenT's gold-painted figure). Judged at the frame's own misfit, the light is found.
    direction = (-0.799, -0.397, -0.451)
    spec = studio_spec(direction, arrangement="overlapping", seed=9, **HARD_PAINTS["gold paint, parts shadowing each other"])
    record = estimate_scene(photograph(tmp_path, spec, seed=9, depth="integrated"), EstimateOptions())
    assert record["light_found"] is True and len(record["lights"]) == 1 and record["evidence"] > 0
    assert record["lights"][0]["share"] > 0.8
    assert lamp_angle_deg(record, spec, direction) < 20.0  # 15.2: the sheet's normals (the xfail above)


def test_parts_that_hide_each_other_give_their_light_where_their_normals_are_given(tmp_path):
    # The same frame, the integrated depth and the true normals beside it (normals/<id>.npy):
    # the normals, not the depth, set the light (24 such frames: median 0.58 degrees, all found).
    direction = (0.775, -0.566, -0.283)
    spec = studio_spec(direction, arrangement="overlapping", seed=16)
    scene = photograph(tmp_path, spec, seed=16, depth="integrated", normals=True)
    assert scene.normals is not None
    record = estimate_scene(scene, EstimateOptions())
    assert record["light_found"] is True and len(record["lights"]) == 1
    assert lamp_angle_deg(record, spec, direction) < 2.0  # 0.97 (2026-12-07)


def test_a_studio_paint_is_checked():
    with pytest.raises(ValueError, match="pattern must be one of"):
        studio_spec((0.0, 0.0, -1.0), pattern="plaid")
    with pytest.raises(ValueError, match="pattern_scale"):
        studio_spec((0.0, 0.0, -1.0), pattern="stripes", pattern_scale=0.0)


def test_a_matte_object_leaves_no_highlight_out(tmp_path):
    direction = (0.3, -0.5, -0.81)
    spec = studio_spec(direction, others=False, ks=0.0)
    record = estimate_scene(photograph(tmp_path, spec), EstimateOptions())
    assert record["light_found"] is True and lamp_angle_deg(record, spec, direction) < 2.0
    assert record["highlight_pixels"] <= 5


def test_the_same_objects_under_diffuse_light_alone_find_no_light(tmp_path):
    spec = studio_spec(None, others=True, ambient=0.3)
    scene = photograph(tmp_path, spec)
    record = estimate_scene(scene, EstimateOptions())
    assert record["light_found"] is False and record["lights"] == [] and record["evidence"] < 0
    # The networks alone, settled and counted on the frame, say so too (their light's share is nil).
    alone = estimate_scene(scene, EstimateOptions(method="cnn"))
    assert alone["light_found"] is False and alone["lights"] == [] and alone["unsupported_lights"]


def test_a_smooth_surface_of_one_albedo_is_one_region_and_shading_does_not_cut_it(tmp_path):
    spec = studio_spec((0.3, -0.5, -0.81), others=False)
    scene, _ = working_range(within_pixels(photograph(tmp_path, spec), EstimateOptions()))
    problem = prepare([scene], EstimateOptions())
    g = problem.gbuffer
    geometry = surface_segments(g.points, g.normals, g.mask)
    joined = albedo_free.albedo_segments(problem, geometry=geometry)[0]
    cut = albedo_free.albedo_segments(problem, geometry=geometry, edge_step=None)[0]
    lit = g.mask[0] & (problem.image[0].mean(0) > 0.05 * problem.image[0].mean(0).max())

    def largest_share(labels):
        counts = torch.bincount(labels[lit & (labels >= 0)])
        return float(counts.max() / counts.sum())

    assert largest_share(joined) > 0.95  # the lit sphere: one region (a few pixels by the terminator apart)
    assert largest_share(cut) < 0.5  # the image's edges alone cut it at its shading (0.29)


def test_a_dim_flat_frame_is_not_clipped_but_a_full_one_is():
    image = torch.full((1, 3, 8, 8), 0.3)
    mask = torch.ones(1, 8, 8, dtype=torch.bool)
    assert saturated_pixels(image, mask).all()  # a scene file: exact ties at the peak are a clip
    assert not saturated_pixels(image, mask, full_scale=torch.tensor([1.0])).any()  # a capture's dim level is not
    image[..., :4] = 1.0
    clipped = saturated_pixels(image, mask, full_scale=torch.tensor([1.0]))
    assert clipped[..., :4].all() and not clipped[..., 4:].any()


def _room_with_bounce(seed, strength):
    # A procedural one-light room (our renderer), its light's bounce added at ``strength``
    # (render.indirect, the layer's term), as a capture: kd unknown.
    import dataclasses

    from render import GBuffer
    from selfsup.scenes.indirect import with_bounce
    from selfsup.scenes.sampler import SamplerConfig, sample_scene

    rendered = render_spec(sample_scene(seed, SamplerConfig(height=96, width=128, specular_prob=0.0,
                                                            ambient_zero_prob=1.0)), samples=1)
    scene = rendered.scene
    g = GBuffer.from_depth(scene.depth[None], scene.K[None], normals=scene.normals[None])
    image = with_bounce(scene.image.permute(2, 0, 1)[None], g, scene.kd[None], scene.light_pos[None],
                        scene.light_intensity[None], rendered.visibility.permute(2, 0, 1)[None], strength)[0]
    captured = dataclasses.replace(scene, image=image.permute(1, 2, 0), ambient=None,
                                   kd=torch.where(scene.depth[..., None] > 0, torch.full_like(scene.kd, 0.5), 0.0))
    return captured


def test_the_albedo_free_fit_takes_the_bounce_where_the_room_returns_light_and_leaves_it_out_where_not():
    from estimation_helpers import _rel_error

    # Our renderer's bounce, which the fit models: the light 0.0066 of the scene off with it,
    # 0.035 without (2026-12-01).
    auto = EstimateOptions(max_lights=1, tuning=Tuning(albedo_free_bounce="auto"))
    bounced = _room_with_bounce(3, 1.0)
    record = estimate_scene(bounced, auto)
    assert record["bounce_share"] is not None and record["bounce_share"] > 0.02
    assert _rel_error(torch.tensor([record["lights"][0]["position"]]), bounced) < 0.05
    plain = estimate_scene(_room_with_bounce(3, 0.0), auto)
    assert plain["bounce_share"] is None  # no light returned: the bounce does not pay for its parameter
    assert estimate_scene(bounced, EstimateOptions(max_lights=1))["bounce_share"] is None  # off by default


# Lamps of our generator's analogues (the plain object, dark metal, grey stripes, gold paint): the
# network trained with objects in the dark (experiment=iterative_studio) places them 0.9, 5.2,
# 6.7 and 3.0 degrees off alone; the rooms' network (selfsup/checkpoints/iterative.pt) 0.5, 26.3,
# 27.1 and 21.8 (2026-12-05). Settled on each frame's albedo segments (tuning.cnn_settle, 5 LM
# steps at half resolution), counted by the settled lights' criterion (tuning.cnn_count): 0.1, 0.1,
# 6.3 (the grey stripes, one light; the network's count kept a second light and put the first 2.9
# off) and 3.0 (2026-12-07).
STUDIO_FRAMES = [((0.13, -0.14, -0.98), {}, False),
                 ((0.12, -0.62, -0.77), HARD_PAINTS["dark metal"], True),
                 ((0.69, -0.5, -0.53), HARD_PAINTS["grey stripes painted across the shapes"], False),
                 ((-0.87, -0.43, -0.24), HARD_PAINTS["gold paint, parts shadowing each other"], True)]


def test_the_network_trained_in_the_dark_places_a_lamp_alone(tmp_path):
    options = EstimateOptions(method="cnn", checkpoint="selfsup/checkpoints/iterative_studio.pt")
    angles = []
    for k, (direction, paint, others) in enumerate(STUDIO_FRAMES):
        spec = studio_spec(direction, others=others, seed=k, **paint)
        record = estimate_scene(photograph(tmp_path / str(k), spec, seed=k), options)
        assert record["lights"] or record["unsupported_lights"]
        angles.append(lamp_angle_deg(record, spec, direction))
        # The albedo unknown (the gold paint's colour is the surfaces' as much as the lamp's): the
        # lights and the ambient are the image's white, as the albedo-free fit's.
        for colour in [light["intensity"] for light in record["lights"] + record["unsupported_lights"]] + [record["ambient"]]:
            assert max(colour) - min(colour) <= 1e-6 * max(max(colour), 1e-12)
    assert sorted(angles)[2] < 4.0 and max(angles) < 8.0  # of four: the third best, and the worst


def test_the_network_alone_is_settled_on_the_frame(tmp_path):
    # The dark metal frame: the network's slot 5.2 degrees off, settled 0.1; with cnn_settle=0
    # the slot as the network put it. An absurd setting is named.
    direction, paint, others = STUDIO_FRAMES[1]
    spec = studio_spec(direction, others=others, seed=1, **paint)
    scene = photograph(tmp_path, spec, seed=1)
    angles = [lamp_angle_deg(estimate_scene(scene, EstimateOptions(method="cnn", checkpoint="selfsup/checkpoints/iterative_studio.pt",
                                                                tuning=Tuning(cnn_settle=steps))), spec, direction)
              for steps in (0, 5)]
    assert angles[0] > 3.0 and angles[1] < 1.0
    # With no checkpoint named both shipped networks propose and the frame takes the lower settled
    # loss: the dark network's light here, where the rooms' network alone, settled by 5 steps, lands
    # 16 degrees off (by the default 15, 2.3).
    rooms, both = [lamp_angle_deg(estimate_scene(scene, EstimateOptions(method="cnn", checkpoint=checkpoint,
                                                                        tuning=Tuning(cnn_settle=5))), spec, direction)
                   for checkpoint in ("selfsup/checkpoints/iterative.pt", None)]
    assert rooms > 10.0 and both < 1.0
    with pytest.raises(ValueError, match="estimate.tuning.cnn_settle"):
        Tuning(cnn_settle=-1)


def test_the_studio_frames_benchmark_scores_a_frame_by_its_lamp_angle():
    from benchmarks.studio_frames import frames, run

    drawn = frames(5)
    assert [paint for _, paint, _ in drawn] == ["plain", *HARD_PAINTS, "plain"]
    assert all(d[2] < 0 and d[1] <= 0 and abs(math.hypot(*d) - 1) < 1e-9 for d, _, _ in drawn)  # towards the camera, above
    rows = run(1, EstimateOptions(method="cnn", checkpoint="selfsup/checkpoints/iterative_studio.pt"), "x", write=False)
    assert rows[0]["light_found"] and rows[0]["angle_deg"] < 5.0 and rows[-1]["angle_deg"] == rows[0]["angle_deg"]


@pytest.mark.parametrize("gloss", ["auto", "instead"])
def test_a_specular_lobe_in_the_albedo_free_fit_takes_rough_metal_with_one_light(tmp_path, gloss):
    # Rough dark metal (diffuse 0.03, a broad lobe): the diffuse-only fit widens the lobe with a
    # second light, 4.6 degrees off; with a lobe (tried at the first light, auto, or in the
    # second light's place, instead) one light and its lobe, 0.1.
    direction = (-0.6, -0.3, -0.74)
    spec = studio_spec(direction, others=False, albedo=(0.03, 0.03, 0.03), ks=0.9, shininess=12.0)
    scene = photograph(tmp_path, spec)
    plain = estimate_scene(scene, EstimateOptions(tuning=Tuning(albedo_free_gloss="never")))
    assert len(plain["lights"]) == 2 and plain["gloss"] is None
    record = estimate_scene(scene, EstimateOptions(tuning=Tuning(albedo_free_gloss=gloss)))
    assert record["light_found"] is True and len(record["lights"]) == 1
    assert lamp_angle_deg(record, spec, direction) < 2.0
    assert record["gloss"]["ratio"] > 1.0 and record["gloss"]["shininess"] > 0
    if gloss == "instead":  # the lobe's models are in the record beside the diffuse ones the first beat
        lobe = [c for c in record["candidates"] if c["specular"]]
        assert [c["n_lights"] for c in lobe] == [1, 2]  # one light more was searched beside it
        assert lobe[0]["criterion"] < min(c["criterion"] for c in record["candidates"] if not c["specular"])


GLOSSY_PAINTS = {"rough dark metal": dict(albedo=(0.03, 0.03, 0.03), ks=0.9, shininess=12.0),
                 "rough gold-like paint": dict(albedo=(0.1, 0.08, 0.03), ks=0.8, shininess=8.0),
                 "glossy white paint": dict(ks=0.6, shininess=20.0)}


@pytest.mark.parametrize("paint,direction", [("rough dark metal", (0.3, -0.5, -0.81)),
                                             ("rough dark metal", (-0.2, -0.6, -0.77)),
                                             ("rough gold-like paint", (0.3, -0.5, -0.81)),
                                             ("glossy white paint", (-0.6, -0.3, -0.74))])
def test_glossy_objects_beside_others_take_one_light_and_its_lobe(tmp_path, paint, direction):
    # Beside the box and the cylinder these took two lights (2.6, 9.8, 9.8 and 0.8 degrees off):
    # the metal's one diffuse light lands 17-20 degrees off, between the lamp and the lobe's
    # peak, and a lobe started there lost to the pair; one of the pair's lights, near the lamp,
    # is now a start too. The last two paints' lobes lie between the grid's shapes: refined.
    spec = studio_spec(direction, others=True, **GLOSSY_PAINTS[paint])
    record = estimate_scene(photograph(tmp_path, spec), EstimateOptions())
    assert record["light_found"] is True and len(record["lights"]) == 1 and record["gloss"] is not None
    assert lamp_angle_deg(record, spec, direction) < 1.5


def test_the_highlights_mirror_points_to_a_metals_lamp(tmp_path):
    # Dark metal beside a box and a cylinder: the diffuse fit's light lands 12-18 degrees off; the
    # view ray reflected about the normal of the frame's brightest patch (against its segment's
    # level) points within 6 of the lamp, from the sphere's centre (4.1 and 5.2, 2026-12-07).
    from selfsup.estimation.reflectance import albedo_free_segments

    for direction in ((0.3, -0.5, -0.81), (-0.2, -0.6, -0.77)):
        spec = studio_spec(direction, others=True, **GLOSSY_PAINTS["rough dark metal"])
        options = EstimateOptions()
        problem = prepare([photograph(tmp_path / str(direction), spec)], options)
        labels, _ = albedo_free_segments(problem, options)
        centre, toward = sphere_centre(spec).to(problem.image), problem.image.new_tensor(direction)
        off = torch.nn.functional.normalize(toward / toward.norm() + problem.image.new_tensor([0.0, 0.0, -1.0]), dim=0)
        zero = problem.image.new_zeros(1)
        found = albedo_free.AlbedoFreeFit((centre + 0.4 * off)[None, None], problem.image.new_tensor([[-2.0, 0.0]]),
                                          zero, zero)
        start = albedo_free.mirror_start(problem, found, labels, options.tuning.albedo_free_scale)

        def angle(seen):
            return math.degrees(math.acos(float(seen @ toward / seen.norm() / toward.norm())))

        assert angle(off) > 15.0 and angle(start.position[0, 0] - centre) < 6.0
        assert torch.equal(start.log_weight, found.log_weight)


@pytest.mark.parametrize("paint,direction,lobe", [("rough gold-like paint", (-0.2, -0.6, -0.77), True),
                                                  ("glossy white paint", (-0.6, -0.3, -0.74), False)])
def test_a_lobe_that_outshines_one_diffuse_light_is_tried_beside_it(tmp_path, paint, direction, lobe):
    # Gold-like paint (ks / kd = 8) beside a box and a cylinder: one diffuse light 18.7 degrees off
    # where no second light paid (one CPU thread), so no lobe was tried in a pair's place. Beside one
    # light a lobe is tried from the highlight's mirror, kept only where it outshines the diffuse
    # light: the white paint's sheen (0.75; its light right without it) stays diffuse, the highlight
    # left out, as the DiLiGenT bear's (0.4-0.56).
    from selfsup.estimation.criterion import bic
    from selfsup.estimation.reflectance import albedo_free_segments

    spec = studio_spec(direction, others=True, **GLOSSY_PAINTS[paint])
    options = EstimateOptions()
    problem = prepare([photograph(tmp_path, spec), photograph(tmp_path / "again", spec)], options)
    labels, _ = albedo_free_segments(problem, options)
    centre, toward = sphere_centre(spec).to(problem.image), problem.image.new_tensor(direction)
    off = torch.nn.functional.normalize(toward / toward.norm() + problem.image.new_tensor([0.0, 0.0, -0.4]), dim=0)
    found = albedo_free.refine_from(problem, (centre + 0.4 * off).expand(2, 1, 3), labels=labels)

    def criterion(fit, extra=None):
        extra = extra or [0] * fit.position.shape[0]
        return [bic(loss, int(pairs), 4 + more, 4) for loss, pairs, more in
                zip(fit.loss.tolist(), fit.pairs.tolist(), extra)]

    lobed_problem, lobed = albedo_free.choose_lone_lobe(problem, found, labels, 0.02, criterion)
    kept = lobed_problem.gloss is not None and bool((lobed_problem.gloss[:, 0] >= 1.0).all())
    assert kept is lobe and (lobed_problem.gloss is None) is not lobe

    def angles(fit):
        seen = fit.position[:, 0] - centre
        return torch.rad2deg(torch.acos((seen @ toward / seen.norm(dim=-1) / toward.norm()).clamp(-1, 1)))

    if lobe:  # the diffuse light between the lamp and the highlight; the lobe's light at the lamp
        assert bool((angles(found) > 10.0).all()) and bool((angles(lobed) < 2.0).all())
    else:
        assert torch.equal(lobed.position, found.position)
    with pytest.raises(ValueError, match="beside one light"):
        albedo_free.choose_lone_lobe(problem, albedo_free.AlbedoFreeFit(found.position.repeat(1, 2, 1),
                                                                        problem.image.new_zeros(2, 3), found.loss,
                                                                        found.pairs), labels, 0.02, criterion)


def test_a_lobe_between_the_grids_shapes_is_refined_to_its_own(tmp_path):
    # ks / kd = 0.75 and Blinn-Phong 20, where the grid has 0.3 / 1 and 12 / 40.
    direction = (-0.6, -0.3, -0.74)
    spec = studio_spec(direction, others=True, **GLOSSY_PAINTS["glossy white paint"])
    record = estimate_scene(photograph(tmp_path, spec), EstimateOptions())
    assert len(record["lights"]) == 1 and lamp_angle_deg(record, spec, direction) < 1.5
    assert 0.55 < record["gloss"]["ratio"] < 0.95 and 15.0 < record["gloss"]["shininess"] < 27.0


@pytest.mark.parametrize("paint,others", [("glossy white paint", False), ("rough gold-like paint", True)])
def test_glossy_objects_under_two_lamps_take_both_and_a_lobe(tmp_path, paint, others):
    # Two lamps 75 degrees apart: the diffuse pair landed 16-21 degrees off both (each light
    # between a lamp and a highlight); with the lobe beside the pair, within 2 degrees.
    first, second = (-0.6, -0.3, -0.74), (0.5, 0.2, -0.84)
    spec = studio_spec(first, others=others, **GLOSSY_PAINTS[paint])
    centre = sphere_centre(spec).float()
    towards = torch.tensor(second) / torch.tensor(second).norm()
    spec = dataclasses.replace(spec, light_position=torch.cat([spec.light_position, (centre + towards * 5.0)[None]]),
                               light_relative_intensity=spec.light_relative_intensity.repeat(2, 1))
    record = estimate_scene(photograph(tmp_path, spec), EstimateOptions())
    assert len(record["lights"]) == 2 and record["gloss"] is not None
    for light in record["lights"]:
        seen = torch.tensor(light["position"], dtype=torch.float64) - centre.double()
        angles = [math.degrees(math.acos(float(torch.nn.functional.cosine_similarity(
            seen, torch.tensor(d, dtype=torch.float64), dim=0).clamp(-1, 1)))) for d in (first, second)]
        assert min(angles) < 2.0


def test_two_lights_closer_than_the_lobes_width_are_one_lamp(tmp_path):
    # Beside a lobe of Blinn-Phong s, a second light is a lamp only beyond acos(2 ** (-1 / s))
    # of the first, seen from the scene's centre (s = 16: 16.8 degrees).
    from selfsup.estimation.albedo_free import AlbedoFreeFit
    from selfsup.estimation.reflectance import _resolved_beside_lobe

    problem = problem_of(photograph(tmp_path, studio_spec((-0.6, -0.3, -0.74), others=False)))
    problem = problem.with_gloss(problem.image.new_tensor([[1.0, 16.0]]))
    centre = problem.gbuffer.extent()[0]  # (1, 3)

    def pair(apart_deg: float) -> AlbedoFreeFit:
        a = math.radians(apart_deg)
        seen = problem.image.new_tensor([[0.0, 0.0, -1.0], [math.sin(a), 0.0, -math.cos(a)]])
        zero = problem.image.new_zeros(1)
        return AlbedoFreeFit((centre + 3.0 * seen)[None], problem.image.new_zeros(1, 3), zero, zero)

    assert _resolved_beside_lobe(problem, pair(20.0)).tolist() == [True]
    assert _resolved_beside_lobe(problem, pair(8.0)).tolist() == [False]


def test_the_lobes_jacobian_is_its_transports_derivative():
    # The albedo-free LM's Jacobian with a lobe against central differences of its residual (float64).
    from selfsup.estimation.albedo_free.fit import _evaluate, _jacobian
    from selfsup.estimation.albedo_free.observation import observe

    spec = studio_spec((0.3, -0.5, -0.81), others=False, width=40, height=30, albedo=(0.5, 0.5, 0.5), ks=0.5,
                       shininess=12.0)
    scene = render_spec(spec).scene
    problem = prepare([scene], EstimateOptions())
    problem = problem.with_gloss(torch.tensor([[3.0, 12.0]], dtype=problem.image.dtype))
    obs = observe(problem, residuals="pairs")
    import dataclasses

    g, m = obs.gbuffer, obs.material
    obs64 = dataclasses.replace(obs, log_shading=obs.log_shading.double(), observed=obs.observed.double(),
                                scale=obs.scale.double(),
                                gbuffer=dataclasses.replace(g, points=g.points.double(), normals=g.normals.double()),
                                material=dataclasses.replace(m, kd=m.kd.double(), ks=m.ks.double(),
                                                             shininess=m.shininess.double()))
    position = spec.light_position[None].double() * 1.1
    log_weight = torch.tensor([[-3.0, 0.0]], dtype=torch.float64)
    residual, jac = _jacobian(obs64, position, log_weight)
    step = 1e-6
    for k in range(3):
        moved = [position.clone(), position.clone()]
        moved[0][0, 0, k] += step
        moved[1][0, 0, k] -= step
        numeric = (_evaluate(obs64, moved[0], log_weight)[1] - _evaluate(obs64, moved[1], log_weight)[1]) / (2 * step)
        assert torch.allclose(jac[0, k], numeric[0], rtol=1e-4, atol=1e-6 * float(numeric.abs().max()))


def test_a_lobed_fits_intensities_are_solved_with_its_lobe(tmp_path):
    # An image that is exactly the glossy model (a rough metal's lobe, ratio 5, Blinn-Phong 12):
    # its light and ambient in the image's units come back as made; solved on the diffuse
    # shading alone (the lobe left out) they would not.
    from selfsup.estimation.albedo_free import AlbedoFreeFit, glossy_material, model_transport
    from selfsup.estimation.intensities import intensities_of

    problem = problem_of(photograph(tmp_path, studio_spec((-0.6, -0.3, -0.74), others=False)), "none",
                         dtype=torch.float64)
    problem = problem.with_gloss(problem.image.new_tensor([[5.0, 12.0]]))
    centre = problem.gbuffer.extent()[0]
    position = (centre + problem.image.new_tensor([[-0.6, -0.3, -0.74]]) * 5.0)[:, None]  # (1, 1, 3)
    transport = model_transport(problem.gbuffer, glossy_material(problem.material.kd, problem.gloss),
                                problem.falloff, position)[:, 0]  # (1, H, W)
    ambient, light, scale = 0.05, 1.0, 0.3
    shading = (ambient + light * transport) * problem.gbuffer.mask
    image = scale * problem.material.kd.permute(0, 3, 1, 2) * shading[:, None]
    problem = dataclasses.replace(problem, image=image)
    log_weight = problem.image.new_tensor([[math.log(ambient / light), 0.0]])
    zero = problem.image.new_zeros(1)
    solved, _ = intensities_of(problem, AlbedoFreeFit(position, log_weight, zero, zero), EstimateOptions())
    assert torch.allclose(solved.intensity[0, 0], torch.full((3,), scale * light, dtype=torch.float64), rtol=1e-4)
    assert torch.allclose(solved.ambient[0], torch.full((3,), scale * ambient, dtype=torch.float64), rtol=1e-4)
