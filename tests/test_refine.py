"""Per-image refinement, model selection, uncertainty and the estimate command."""

import dataclasses
import json
import logging
import math
import sys

import numpy as np
import pytest
import torch

from selfsup.estimate import (EstimateOptions, estimate_batch, estimate_files, estimate_scene, pixel_stride, prepare, problem_of,
                              problems_of, records)
from selfsup.metrics import light_errors
from render import EpipolarShadowOptions, GBuffer, Material
from selfsup.refine import (FitProblem, RefineOptions, _lm, _normal_equations, evaluate, position_blocks, refine,
                            robust_loss, search)
from selfsup.scenes.exact import render_spec
from selfsup.scenes.io import write_scene
from selfsup.scenes.sampler import SamplerConfig, sample_scene

SMALL = SamplerConfig(height=48, width=64, specular_prob=0.0, ambient_zero_prob=1.0)
MEDIUM = dataclasses.replace(SMALL, height=96, width=128)  # the grid search works at stride 4: keep 24x32 there


def _scene(seed, n_lights=1, config=SMALL):
    return render_spec(sample_scene(seed, config, n_lights=n_lights), samples=1).scene


def _rel_error(position, scene):
    return float((position - scene.light_pos).norm(dim=-1).max() / scene.scene_scale)


def _rel_error_paired(position, scene):
    return max(light_errors(position, None, scene.light_pos, None, float(scene.scene_scale),
                            scene.light_pos.mean(0)).position)


@pytest.mark.parametrize("method, iters, tol, shadows", [
    ("lm", (4, 0), 1e-3, "none"),  # the variable-projection step: 0.04 -> 0.0001 in 3 steps
    ("adam", (60, 0), 0.03, "epipolar"),
])
def test_each_optimiser_moves_towards_the_true_light(method, iters, tol, shadows):
    scene = _scene(1)
    problem = problem_of(scene, shadows)
    start = scene.light_pos[None] + 0.04 * scene.scene_scale * torch.tensor([1.0, -1.0, 1.0]) / 3**0.5
    options = RefineOptions(method=method, max_iters=iters, strides=(1, 1), learning_rate=0.01 if method == "adam" else 0.02)
    fit = refine(problem, start, options)
    assert _rel_error(fit.position[0], scene) < min(tol, _rel_error(start[0], scene))
    assert torch.isfinite(fit.intensity).all() and (fit.intensity >= 0).all()


def test_lm_with_shadows_converges_from_the_best_of_several_starts():
    # Shadow edges make the landscape rough: from one start 0.04 away, LM stops anywhere
    # from 0.0004 to 0.03 (measured 2026-11-23 over four directions; which one it reaches
    # flips with float rounding). The estimator therefore keeps the best of several starts,
    # as here: every fit lowers its start's cost, and the cheapest is at the light.
    scene = _scene(1)
    directions = torch.tensor([[1.0, -1.0, 1.0], [-1.0, 1.0, 1.0], [1.0, 1.0, -1.0], [-1.0, -1.0, -1.0]]) / 3**0.5
    problem = problem_of(scene, "epipolar").select(torch.zeros(len(directions), dtype=torch.long))
    start = scene.light_pos[None] + 0.04 * scene.scene_scale * directions[:, None]
    options = RefineOptions(method="lm", max_iters=(40, 10), strides=(1, 1))
    fit = refine(problem, start, options)
    start_cost = refine(problem, start, dataclasses.replace(options, max_iters=(0,), strides=(1,))).cost
    assert (fit.cost < start_cost).all()
    assert _rel_error(fit.position[int(fit.cost.argmin())], scene) < 1e-3


@pytest.mark.xfail(strict=True, reason="known issue: the paper's rate 0.02 on our normalised energy overshoots")
def test_paper_gradient_descent_lowers_the_energy_and_stops_on_its_own():
    scene = _scene(1)
    problem = problem_of(scene)
    start = scene.light_pos[None] + 0.04 * scene.scene_scale * torch.tensor([1.0, -1.0, 1.0]) / 3**0.5
    options = RefineOptions(method="gd", max_iters=(500,), strides=(1,))
    fit = refine(problem, start, options)
    before = robust_loss(problem, evaluate(problem, start, options)[3], options)
    assert float(robust_loss(problem, fit.model, options)[0]) < float(before[0])
    assert 0 < int(fit.iterations[0]) < 500  # the relative-change rule (1e-4) ended it


def test_lm_recovers_intensity_and_unknown_ambient_exactly():
    config = dataclasses.replace(SMALL, ambient_zero_prob=0.0)
    scene = _scene(2, config=config)
    scene.ambient = None
    problem = problem_of(scene, shadows="epipolar")
    fit = refine(problem, scene.light_pos[None] * 1.05, RefineOptions(max_iters=(20, 10)))
    torch.testing.assert_close(fit.intensity[0], scene.light_intensity, rtol=0.05, atol=0)
    assert _rel_error(fit.position[0], scene) < 0.01  # the depth-map shadows differ from exact rays


def test_search_finds_the_light_without_a_start():
    scene = _scene(3, config=MEDIUM)
    fit = search(problem_of(scene), 1, RefineOptions(max_iters=(15, 5)))
    assert _rel_error(fit.position[0], scene) < 0.02


@pytest.mark.parametrize("seed, n_lights", [(4, 1), (11, 2)])
def test_model_selection_picks_the_number_of_lights(seed, n_lights):
    scene = _scene(seed, n_lights, config=MEDIUM)
    record = estimate_scene(scene, EstimateOptions(method="refine", refine=RefineOptions(max_iters=(15, 5))))
    assert len(record["lights"]) == n_lights, record["candidates"]


@pytest.mark.parametrize("shadows", ["epipolar", "paper"])
def test_shadowed_selection_refines_the_shadow_free_search(shadows):
    # estimate.shadows=epipolar|paper: the search runs on shading alone, each
    # candidate is refined and judged with the shadows; two lights stay two.
    scene = _scene(11, 2, config=MEDIUM)
    record = estimate_scene(scene, EstimateOptions(method="refine", shadows=shadows,
                                                   refine=RefineOptions(max_iters=(15, 5))))
    assert len(record["lights"]) == 2, record["candidates"]
    position = torch.tensor([light["position"] for light in record["lights"]])
    assert _rel_error_paired(position, scene) < 0.05


@pytest.mark.parametrize("name", ["shadows", "search_shadows"])
def test_unknown_shadow_model_is_named(name):
    with pytest.raises(ValueError, match=f"estimate.{name} must be one of"):
        EstimateOptions(**{name: "raytraced"})


@pytest.mark.parametrize("seed, n_lights", [(4, 1), (11, 2)])
def test_shipped_network_starts_the_refinement_and_selection(seed, n_lights):
    scene = _scene(seed, n_lights, config=MEDIUM)
    record = estimate_scene(scene, EstimateOptions(method="cnn+refine", refine=RefineOptions(max_iters=(15, 5))))
    assert len(record["lights"]) == n_lights, record["candidates"]
    position = torch.tensor([light["position"] for light in record["lights"]])
    assert _rel_error_paired(position, scene) < 0.05  # success, as scene-format.md defines it


def test_a_batch_gives_each_scene_the_answer_it_gets_alone():
    # One light, two lights and a specular scene in one batch: mixed counts and switches.
    scenes = [_scene(4, 1, MEDIUM), _scene(11, 2, MEDIUM),
              _scene(3, 1, dataclasses.replace(MEDIUM, specular_prob=1.0))]
    options = EstimateOptions(method="cnn+refine", refine=RefineOptions(max_iters=(15, 5)))
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


def test_missing_checkpoint_stops_before_any_file(tmp_path):
    write_scene(tmp_path / "a.npz", _scene(6))
    options = EstimateOptions(method="cnn+refine", checkpoint=str(tmp_path / "none.pt"))
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        estimate_files(tmp_path, tmp_path / "out.jsonl", options, progress=False)
    assert not (tmp_path / "out.jsonl").exists()


def test_unknown_method_is_named():
    with pytest.raises(ValueError, match="estimate.method must be one of"):
        EstimateOptions(method="magic")


def test_uncertainty_is_present_finite_and_small_on_an_exact_scene():
    scene = _scene(5)
    record = estimate_scene(scene, EstimateOptions(method="refine", max_lights=1, refine=RefineOptions(max_iters=(15, 5))))
    std = torch.tensor(record["lights"][0]["position_std"])
    assert std.shape == (3,) and torch.isfinite(std).all() and (std > 0).all()
    assert float(std.max()) < 0.05 * float(scene.scene_scale)


def test_position_covariance_does_not_depend_on_the_units():
    # Curvatures of 1e-4 next to 1e4, as a distant light's position beside intensities:
    # the float32 matrix's covariance must be its exact inverse, whatever the units.
    generator = torch.Generator().manual_seed(0)
    a = torch.randn(12, 9, generator=generator, dtype=torch.float64)
    units = torch.tensor([1e-2, 3e-2, 1e-2, 1.0, 1.0, 1.0, 1e2, 1e2, 1e2], dtype=torch.float64)
    info = (a * units).T @ (a * units)  # (9, 9): two lights' positions, then three more parameters
    exact = torch.linalg.inv(info)
    blocks = position_blocks(info.float()[None], torch.ones(1), 2)
    assert blocks.dtype == torch.float32
    for light in range(2):
        rows = slice(3 * light, 3 * light + 3)
        torch.testing.assert_close(blocks[0, light].double(), exact[rows, rows], rtol=1e-4, atol=0)
    # Nothing constrains a parameter: an enormous variance, not none.
    info[0, :] = info[:, 0] = 0
    assert float(position_blocks(info.float()[None], torch.ones(1), 2)[0, 0, 0, 0]) > 1e9
    # Nothing constrains anything (a light that lights no pixel, the ambient given): still
    # numbers, enormous on the diagonal (the zero matrix's inverse was inf, and inf x 0 NaN).
    for sigma2 in (1.0, 1e30):
        blocks = position_blocks(torch.zeros(1, 6, 6), torch.tensor([sigma2]), 2)
        assert bool(torch.isfinite(blocks).all()) and float(blocks.diagonal(dim1=-2, dim2=-1).amin()) > 1e9


def test_position_std_follows_the_scene_into_millimetres():
    scene = _scene(5)
    options = EstimateOptions(method="refine", max_lights=1, refine=RefineOptions(max_iters=(15, 5)))
    metres = estimate_scene(scene, options)["lights"][0]
    millimetres = estimate_scene(dataclasses.replace(scene, depth=scene.depth * 1000), options)["lights"][0]
    torch.testing.assert_close(torch.tensor(millimetres["position"]), 1000 * torch.tensor(metres["position"]),
                               rtol=1e-3, atol=0)
    torch.testing.assert_close(torch.tensor(millimetres["position_std"]), 1000 * torch.tensor(metres["position_std"]),
                               rtol=0.05, atol=0)


@pytest.mark.parametrize("known_ambient", [False, True])
def test_lm_steps_do_not_depend_on_the_units(known_ambient):
    # The same file in millimetres: every LM step is the metre step x 1000. There the
    # curvatures of the positions, the intensities (x 1e6 under inverse-square falloff) and
    # the ambient differ by many orders; a floor relative to the largest of all moved the steps.
    # (With the ambient known the old floor left these steps alone: that case is a guard.)
    scene = _scene(5)
    options = EstimateOptions()
    start = scene.light_pos[None] + torch.tensor([0.3, -0.2, 0.25])
    steps = []
    for k in (1.0, 1000.0):
        problem = prepare([dataclasses.replace(scene, depth=scene.depth * k)], options)
        if not known_ambient:
            problem = dataclasses.replace(problem, ambient=None)
        steps.append(_lm(problem, start.clone() * k, RefineOptions(), 3)[0] / k)
    torch.testing.assert_close(steps[1], steps[0], rtol=0, atol=1e-5 * float(scene.scene_scale))


@pytest.mark.parametrize("known_ambient", [False, True])
def test_block_normal_equations_equal_those_of_the_dense_jacobian(known_ambient):
    # The dense Jacobian over every parameter, written out: the positions' rows, then a
    # row per (channel, light) holding that light's basis image in that channel alone,
    # then (ambient unknown) a row per channel holding kd there.
    generator = torch.Generator().manual_seed(3)
    B, L, H, W = 2, 2, 3, 4
    kd = torch.rand(B, H, W, 3, generator=generator, dtype=torch.float64)
    problem = FitProblem(GBuffer(torch.rand(B, H, W, 3, dtype=torch.float64), torch.rand(B, H, W, 3, dtype=torch.float64),
                                 torch.ones(B, H, W, dtype=torch.bool)),
                         Material(kd=kd), torch.rand(B, 3, H, W, dtype=torch.float64),
                         ambient=torch.rand(B, 3, dtype=torch.float64) if known_ambient else None)
    j_pos = torch.randn(B, 3 * L, 3 * H * W, generator=generator, dtype=torch.float64)
    cols = torch.rand(B, 3, L, H, W, generator=generator, dtype=torch.float64)
    weights = torch.rand(B, 3, H, W, generator=generator, dtype=torch.float64)
    residual = torch.randn(B, 3, H, W, generator=generator, dtype=torch.float64)
    columns = [cols[:, c, i] for c in range(3) for i in range(L)] + ([] if known_ambient else [kd[..., c] for c in range(3)])
    channels = [c for c in range(3) for _ in range(L)] + ([] if known_ambient else [0, 1, 2])
    linear = torch.zeros(B, len(columns), 3, H * W, dtype=torch.float64)
    for row, (column, c) in enumerate(zip(columns, channels)):
        linear[:, row, c] = column.flatten(1)
    dense = torch.cat([j_pos, linear.flatten(2)], 1)
    weighted = dense * weights.flatten(1)[:, None]
    normal, gradient = _normal_equations(problem, j_pos, cols, weights, residual)
    # The linear parameters' order differs (channel by channel, ambient last in each):
    # compare what the position step depends on, the Schur complement and its gradient.
    def reduced(matrix, vector):
        p = 3 * L
        solve = torch.linalg.solve(matrix[:, p:, p:], torch.cat([matrix[:, p:, :p], vector[:, p:, None]], -1))
        return matrix[:, :p, :p] - matrix[:, :p, p:] @ solve[..., :p], vector[:, :p] - (matrix[:, :p, p:] @ solve[..., p:]).squeeze(-1)
    expected = reduced(weighted @ dense.transpose(1, 2), (weighted @ residual.flatten(1)[..., None]).squeeze(-1))
    assert normal.shape == (B, 3 * L + len(columns), 3 * L + len(columns))
    torch.testing.assert_close(reduced(normal, gradient), expected)
    torch.testing.assert_close(normal[:, : 3 * L, : 3 * L], (weighted @ dense.transpose(1, 2))[:, : 3 * L, : 3 * L])


def _exact_fit(problem: FitProblem, truth: torch.Tensor, options: RefineOptions):
    """``problem.image`` replaced by the model's own at the lights ``truth`` and fitted from
    there (an exact fit), with what the first-order tests compare it by: the fit, its
    basis images, positions' Jacobian and diffuse transport (:func:`_jacobians`, no
    specular term), the valid mask ``(B, 3, H, W)`` and the information matrix."""
    from selfsup.refine import _jacobians, scene_frame

    problem.image = refine(problem, truth, dataclasses.replace(options, max_iters=(0,))).model
    fit = refine(problem, truth, options)
    h = (options.fd_step * scene_frame(problem)[1])[:, None, None]
    cols, j_pos, diffuse = _jacobians(problem, fit.position, fit.intensity, h, False)
    mask = problem.gbuffer.mask[:, None].expand_as(problem.image).to(problem.image.dtype)
    info, _ = _normal_equations(problem, j_pos, cols, mask)
    return fit, cols, j_pos, diffuse, mask, info


def _strongest_block(scores: torch.Tensor, parts: int, width: int, block: int) -> tuple[int, int, int, int]:
    """The column of ``scores (1, n, parts * blocks)`` (part-major: channels or tilt axes)
    that moves the first light most, as (column, part, block row, block column)."""
    column = int(scores[0, :3].norm(dim=0).argmax())
    part, index = divmod(column, scores.shape[-1] // parts)
    return (column, part, *divmod(index, -(-width // block)))


def _assert_first_order(moved, fit, info: torch.Tensor, score: torch.Tensor, scene, rtol: float) -> None:
    """The first light of ``moved`` went where ``info^-1 score`` says, to ``rtol``
    (``info (n, n)`` signed as the error's effect needs), and it did move."""
    predicted = (torch.linalg.pinv(info) @ score)[:3]
    measured = (moved.position - fit.position)[0, 0]
    assert float(measured.norm()) > 1e-6 * float(scene.scene_scale)
    torch.testing.assert_close(measured, predicted, rtol=rtol, atol=rtol * float(predicted.norm()))


@pytest.mark.parametrize("known_ambient", [True, False])
def test_albedo_scores_predict_how_a_kd_error_moves_the_fit(known_ambient):
    # To first order an error e of kd over one block and channel moves the least-squares
    # fit by -info^-1 scores e: refit after such an error (the image the model's own at
    # the true light, so the fit there is exact) and compare the positions.
    from selfsup.refine import albedo_scores

    scene = _scene(5)
    problem = problem_of(scene, "none", dtype=torch.float64)
    if not known_ambient:
        problem.ambient = None
    options = RefineOptions(max_iters=(80,), strides=(1,), robust=False, tol=1e-14, step_tol=1e-12)
    fit, cols, j_pos, diffuse, mask, info = _exact_fit(problem, scene.light_pos[None].double(), options)
    block = 16
    scores = albedo_scores(problem, fit, j_pos, cols, diffuse, mask, block)
    column, channel, row, col = _strongest_block(scores, 3, problem.image.shape[-1], block)
    e = 1e-3
    kd = problem.material.kd.clone()
    kd[0, row * block : (row + 1) * block, col * block : (col + 1) * block, channel] += e
    moved = refine(dataclasses.replace(problem, material=Material(kd=kd, ks=problem.material.ks,
                                                                  shininess=problem.material.shininess)),
                   fit.position, options)
    _assert_first_order(moved, fit, -info[0], scores[0, :, column] * e, scene, 0.02)


def test_normal_tilt_scores_predict_how_tilted_normals_move_the_fit():
    # To first order, the normals of one block tilted by e about one of the tilt axes
    # move the least-squares fit by -info^-1 s e, s that block's score for a unit tilt
    # variance (the model changes, as under a kd error).
    from selfsup.refine import normal_tilt_scores, tilt_axes

    scene = _scene(5)
    problem = problem_of(scene, "none", dtype=torch.float64)
    options = RefineOptions(max_iters=(80,), strides=(1,), robust=False, tol=1e-14, step_tol=1e-12, specular=False)
    fit, cols, j_pos, _, mask, info = _exact_fit(problem, scene.light_pos[None].double(), options)
    problem.normal_tilt = torch.ones_like(problem.gbuffer.mask, dtype=torch.float64)
    block = 16
    scores = normal_tilt_scores(problem, fit, j_pos, cols, mask, block, False)
    column, axis, row, col = _strongest_block(scores, 2, problem.image.shape[-1], block)
    e = 1e-3
    g = problem.gbuffer
    normals = g.normals.clone()
    rows, columns = slice(row * block, (row + 1) * block), slice(col * block, (col + 1) * block)
    turned = normals + e * tilt_axes(normals)[axis]
    normals[:, rows, columns] = torch.nn.functional.normalize(turned[:, rows, columns], dim=-1)
    moved = refine(dataclasses.replace(problem, gbuffer=dataclasses.replace(g, normals=normals)), fit.position, options)
    _assert_first_order(moved, fit, -info[0], scores[0, :, column] * e, scene, 0.03)
    first, second = tilt_axes(g.normals)
    valid = g.mask[0]
    for a, b in ((first, g.normals), (second, g.normals), (first, second)):
        assert float((a * b).sum(-1)[0][valid].abs().max()) < 1e-6  # orthogonal axes across the normal (float32 normals)


def test_block_scores_sum_every_block_the_partial_ones_at_the_border_too():
    from selfsup.refine import _jacobians, block_scores, scene_frame

    problem = problem_of(_scene(5), "none", dtype=torch.float64)
    problem.ambient = None
    B, _, H, W = problem.image.shape
    block = 7
    assert H % block and W % block  # both borders hold partial blocks
    position = problem.gbuffer.extent()[0][:, None] + torch.tensor([0.3, -0.5, 0.1], dtype=torch.float64)
    h = (1e-3 * scene_frame(problem)[1])[:, None, None]
    cols, j_pos, _ = _jacobians(problem, position, torch.ones(B, 1, 3, dtype=torch.float64), h, False)
    derivative = torch.rand(B, 3, H, W, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    scores = block_scores(problem, j_pos, cols, derivative, block)
    across = -(-W // block)
    n_blocks = -(-H // block) * across
    assert scores.shape == (B, 3 + 3 * 2, 3 * n_blocks)
    shared = block_scores(problem, j_pos, cols, derivative, block, shared_channels=True)
    torch.testing.assert_close(shared, scores.view(B, -1, 3, n_blocks).sum(2))  # one value for every channel
    per_pixel = j_pos.view(B, 3, 3, H, W) * derivative[:, None]
    for row, col in ((H // block, W // block), (0, W // block), (H // block, 0), (1, 2)):  # border blocks and one inside
        for channel in range(3):
            rows, columns = slice(row * block, (row + 1) * block), slice(col * block, (col + 1) * block)
            expected = per_pixel[0, :, channel, rows, columns].sum((-1, -2))
            torch.testing.assert_close(scores[0, :3, channel * n_blocks + row * across + col], expected)


def test_indirect_field_scores_predict_how_a_change_of_the_ambient_moves_the_fit():
    # The field's blocks: to first order, more ambient light over one block (e times the
    # fitted ambient, every channel) moves the fit by +info^-1 s e, s that block's score
    # (the image changes, not the model: the opposite sign of the albedo scores').
    from selfsup.refine import _jacobians, block_scores, scene_frame

    scene = _scene(5)
    problem = problem_of(scene, "none", dtype=torch.float64)
    problem.ambient = torch.full((1, 3), 0.05, dtype=torch.float64)  # the image: the model's own, with ambient light
    options = RefineOptions(max_iters=(80,), strides=(1,), robust=False, tol=1e-14, step_tol=1e-12)
    truth = scene.light_pos[None].double()
    problem.image = refine(problem, truth, dataclasses.replace(options, max_iters=(0,))).model
    problem.ambient = None
    fit = refine(problem, truth, options)
    torch.testing.assert_close(fit.ambient, torch.full((1, 3), 0.05, dtype=torch.float64))
    h = (options.fd_step * scene_frame(problem)[1])[:, None, None]
    cols, j_pos, _ = _jacobians(problem, fit.position, fit.intensity, h, False)
    mask = problem.gbuffer.mask[:, None].expand_as(problem.image).double()
    info, _ = _normal_equations(problem, j_pos, cols, mask)
    ambient_image = problem.material.kd.permute(0, 3, 1, 2) * fit.ambient[:, :, None, None]
    block = 16
    scores = block_scores(problem, j_pos, cols, ambient_image * mask, block, shared_channels=True)  # as the field's
    index = int(scores[0, :3].norm(dim=0).argmax())
    row, col = divmod(index, -(-problem.image.shape[-1] // block))
    e = 1e-2
    image = problem.image.clone()
    rows, columns = slice(row * block, (row + 1) * block), slice(col * block, (col + 1) * block)
    image[:, :, rows, columns] += e * ambient_image[:, :, rows, columns]
    moved = refine(dataclasses.replace(problem, image=image), fit.position, options)
    predicted = (torch.linalg.pinv(info[0]) @ scores[0, :, index])[:3] * e  # more light: the fit follows it
    measured = (moved.position - fit.position)[0, 0]
    assert float(measured.norm()) > 1e-6 * float(scene.scene_scale)
    torch.testing.assert_close(measured, predicted, rtol=0.02, atol=0.02 * float(predicted.norm()))


def test_indirect_variation_widens_only_where_the_ambient_is_unknown():
    scene = _scene(5, config=dataclasses.replace(SMALL, ambient_zero_prob=0.0))
    assert float(scene.ambient.min()) > 0
    options = EstimateOptions(method="refine", max_lights=1, refine=RefineOptions(max_iters=(15, 5)))
    without = dataclasses.replace(options, indirect_variation=0.0)
    given = [estimate_scene(scene, o)["lights"][0] for o in (options, without)]
    assert given[0]["position_std"] == given[1]["position_std"]  # the file gives its ambient: nothing unaccounted
    scene.ambient = None
    unknown = [estimate_scene(scene, o)["lights"][0] for o in (options, without)]
    assert unknown[0]["position"] == unknown[1]["position"]  # the same fit; only its uncertainty grows
    assert all(w > e for w, e in zip(unknown[0]["position_std"], unknown[1]["position_std"]))
    for bad in (dict(indirect_variation=-0.1), dict(indirect_variation=float("nan")), dict(indirect_length=0.0),
                dict(indirect_length=float("inf"))):
        with pytest.raises(ValueError, match="estimate.indirect_"):
            EstimateOptions(**bad)


def test_normal_error_widens_only_where_normals_were_refitted_from_noisy_depth():
    from selfsup.scenes.degrade import Degradations, degrade

    scene = _scene(2, config=MEDIUM)
    options = EstimateOptions(method="refine", max_lights=1, refine=RefineOptions(max_iters=(15, 5)))
    without = dataclasses.replace(options, normal_error=False)
    assert problem_of(scene, normal_smoothing="auto").normal_tilt is None  # clean normals are kept: exact
    clean = [estimate_scene(scene, o)["lights"][0] for o in (options, without)]
    assert clean[0]["position_std"] == clean[1]["position_std"]
    noisy = degrade(scene, Degradations(depth_noise=0.003, depth_quantisation=0.001), 2)
    tilt = problem_of(noisy, normal_smoothing="auto").normal_tilt
    assert tilt is not None and float(tilt.max()) > 0 and bool(torch.isfinite(tilt).all())
    refitted = [estimate_scene(noisy, o)["lights"][0] for o in (options, without)]
    assert refitted[0]["position"] == refitted[1]["position"]  # the same fit; only its uncertainty grows
    assert all(w > e for w, e in zip(refitted[0]["position_std"], refitted[1]["position_std"]))


def test_albedo_error_widens_the_position_std_and_zero_changes_nothing():
    scene = _scene(5)
    options = EstimateOptions(method="refine", max_lights=1, refine=RefineOptions(max_iters=(15, 5)))
    exact = estimate_scene(scene, options)["lights"][0]
    same = estimate_scene(scene, dataclasses.replace(options, albedo_error=0.0))["lights"][0]
    wider = estimate_scene(scene, dataclasses.replace(options, albedo_error=0.05))["lights"][0]
    assert same["position_std"] == exact["position_std"]
    assert wider["position"] == exact["position"]  # the fit is the same; only its uncertainty grows
    assert all(w > e for w, e in zip(wider["position_std"], exact["position_std"]))
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="estimate.albedo_error"):
            EstimateOptions(albedo_error=bad)


def test_estimate_files_writes_jsonl_and_skips_bad_files(tmp_path):
    good = _scene(6)
    write_scene(tmp_path / "a_good.npz", good)
    np.savez(tmp_path / "b_missing.npz", image=np.zeros((4, 4, 3), np.float32))
    arrays = dict(np.load(tmp_path / "a_good.npz"))
    for name, change in {
        "c_nan": lambda a: a["image"].__setitem__((0, 0, 0), np.nan),
        "d_empty": lambda a: a["depth"].__setitem__(slice(None), 0),
        "e_shape": lambda a: a.__setitem__("kd", a["kd"][:, :-1]),
    }.items():
        bad = {k: v.copy() for k, v in arrays.items()}
        change(bad)
        np.savez(tmp_path / f"{name}.npz", **bad)
    options = EstimateOptions(max_lights=1, refine=RefineOptions(max_iters=(10, 3)))
    summary = estimate_files(tmp_path, tmp_path / "out" / "lights.jsonl", options, progress=False)
    assert summary["done"] == 1 and summary["failed"] == 4
    reasons = " ".join(summary["failures"].values())
    for word in ("missing", "non-finite", "empty valid mask", "kd must have shape"):
        assert word in reasons
    record = json.loads((tmp_path / "out" / "lights.jsonl").read_text().splitlines()[0])
    assert set(record) >= {"id", "lights", "ambient", "seconds"}
    assert set(record["lights"][0]) >= {"position", "intensity", "position_std"}


def test_a_record_with_a_non_finite_number_fails_its_file_not_the_output(tmp_path, monkeypatch):
    # Python writes NaN as a bare NaN, which no strict JSON reader accepts: one such line
    # would cost every line of the file. Such a record fails its own file, named.
    import selfsup.estimate

    for name, seed in (("a.npz", 6), ("b.npz", 7)):
        write_scene(tmp_path / name, _scene(seed))
    records = selfsup.estimate.records

    def with_a_nan(ids, *args, **kwargs):
        out = records(ids, *args, **kwargs)
        for record in out:
            if record["id"] == _scene(7).id:
                record["lights"][0]["position_std"][0] = float("nan")
        return out

    monkeypatch.setattr(selfsup.estimate, "records", with_a_nan)
    options = EstimateOptions(max_lights=1, refine=RefineOptions(max_iters=(10, 3)))
    summary = estimate_files(tmp_path, tmp_path / "lights.jsonl", options, progress=False)
    assert summary["done"] == 1 and summary["failed"] == 1
    assert "non-finite" in summary["failures"][str(tmp_path / "b.npz")]
    lines = (tmp_path / "lights.jsonl").read_text().splitlines()
    assert len(lines) == 1 and json.loads(lines[0], parse_constant=lambda c: pytest.fail(c))["id"] == _scene(6).id


def test_an_image_in_other_units_gets_the_same_lights(tmp_path):
    # The fit runs in float32 with a few absolute floors: devset direct 021 times 1e-8 got its
    # light 0.0068 of the scene off (0.0005 as given) and its intensity 8% low; times 1e18
    # it failed. This scene times 1e-20 got its light 0.56 m off; times 1e20 it failed. Such
    # a file is estimated at a power of ten of its values, reported in its own units.
    scene = _scene(6)
    options = EstimateOptions(max_lights=1, refine=RefineOptions(max_iters=(10, 3)))
    given = estimate_scene(scene, options)
    for factor in (1e-20, 1e20):
        names = (f"a_{factor:g}.npz", "b_given.npz")
        write_scene(tmp_path / names[0], dataclasses.replace(scene, image=scene.image * factor))
        write_scene(tmp_path / names[1], scene)
        out = tmp_path / f"{factor:g}.jsonl"
        summary = estimate_files(tmp_path, out, options, progress=False, batch=2)  # both in one batch
        assert summary["failed"] == 0, summary["failures"]
        scaled, plain = (json.loads(line) for line in out.read_text().splitlines()[-2:])
        for record, k in ((scaled, factor), (plain, 1.0)):
            light = record["lights"][0]
            np.testing.assert_allclose(light["position"], given["lights"][0]["position"], rtol=0, atol=1e-4)
            np.testing.assert_allclose(np.array(light["intensity"]) / k, given["lights"][0]["intensity"], rtol=1e-3)
        for path in names:
            (tmp_path / path).unlink()


def test_a_folder_of_folders_names_the_ones_with_scenes(tmp_path):
    # The devset's root holds direct/, gi/ and noisy/, not scenes.
    for folder in ("gi", "empty"):
        (tmp_path / folder).mkdir()
    write_scene(tmp_path / "gi" / "a.npz", _scene(6))
    with pytest.raises(FileNotFoundError, match=r"no \.npz scene files in .* \(its sub-folders gi hold some"):
        estimate_files(tmp_path, tmp_path / "o.jsonl", EstimateOptions(), progress=False)


def test_estimate_command_exits_non_zero_when_a_file_fails(tmp_path):
    import subprocess
    import sys

    write_scene(tmp_path / "good.npz", _scene(7, config=dataclasses.replace(SMALL, height=24, width=32)))
    np.savez(tmp_path / "bad.npz", image=np.zeros((4, 4, 3), np.float32))
    result = subprocess.run([sys.executable, "train.py", "mode=estimate", f"estimate.input={tmp_path}",
                             f"estimate.output={tmp_path}/o.jsonl", "estimate.max_lights=1", "estimate.progress=false",
                             "estimate.refine.max_iters=[5,2]", f"hydra.run.dir={tmp_path}/run"],
                            capture_output=True, text=True, cwd=str(__import__("pathlib").Path(__file__).parents[1]))
    assert result.returncode == 1, result.stderr[-2000:]
    log = result.stdout + result.stderr
    assert "bad.npz" in log and "missing key" in log
    assert len((tmp_path / "o.jsonl").read_text().splitlines()) == 1


@pytest.mark.parametrize("known_ambient", [False, True])
def test_a_light_that_lights_nothing_has_a_finite_gradient(known_ambient):
    # A gradient step can carry a light behind a wall: its transport is all zero.
    # The intensities solve must give it intensity 0 and finite gradients. With a
    # known ambient and one dark light the normal matrix is all zero; a ridge
    # relative to its (zero) trace made 0 * inf = NaN in the backward, which the
    # paper's gd turned into a NaN light position (found by benchmark=paper_table).
    from selfsup.linear import basis_images, solve_intensities

    torch.manual_seed(0)
    diffuse = torch.rand(2, 1, 6, 7)
    diffuse[1] = 0  # image 1: its one light is dark everywhere
    diffuse.requires_grad_(True)
    kd = torch.rand(2, 6, 7, 3)
    ambient = torch.full((2, 3), 0.1) if known_ambient else None
    cols = basis_images(kd, None, diffuse, None)
    intensity, _, model = solve_intensities(cols, kd, torch.rand(2, 3, 6, 7), torch.ones(2, 3, 6, 7), ambient)
    assert float(intensity[1].detach().abs().max()) == 0.0
    (model ** 2).sum().backward()
    assert torch.isfinite(diffuse.grad).all()


def test_intensities_solve_alike_whatever_the_units():
    # A scene in centimetres: transport 1/d^2 shrinks 1e4-fold against the ambient's
    # column (kd), the intensities must grow 1e4-fold and the model stay. A ridge
    # relative to the normal matrix's trace silenced the lights of a devset scene
    # given in centimetres (depth x 100).
    from selfsup.linear import basis_images, solve_intensities

    generator = torch.Generator().manual_seed(0)
    diffuse = torch.rand(1, 2, 8, 9, generator=generator, dtype=torch.float64)
    kd = torch.rand(1, 8, 9, 3, generator=generator, dtype=torch.float64)
    truth = torch.tensor([[[1.0, 0.8, 0.6], [0.3, 0.4, 0.5]]], dtype=torch.float64)
    image = (basis_images(kd, None, diffuse, None) * truth.transpose(1, 2)[..., None, None]).sum(2)
    image = image + 0.1 * kd.permute(0, 3, 1, 2)
    weights = torch.ones_like(image)
    for dtype in (torch.float64, torch.float32):
        results = []
        for scale in (1.0, 1e-4, 1e-8):
            cols = basis_images(kd.to(dtype), None, (diffuse * scale).to(dtype), None)
            intensity, ambient, model = solve_intensities(cols, kd.to(dtype), image.to(dtype), weights.to(dtype))
            results.append((intensity.double() * scale, ambient.double(), model.double()))
        for intensity, ambient, model in results:
            torch.testing.assert_close(intensity, truth, rtol=1e-4, atol=0)
            torch.testing.assert_close(ambient, torch.full((1, 3), 0.1, dtype=torch.float64), rtol=1e-4, atol=0)
            torch.testing.assert_close(model, image, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("known_ambient", [False, True])
def test_reweighting_shares_one_design_and_gets_what_fresh_solves_get(known_ambient, monkeypatch):
    # reweighted and evaluate build the least-squares columns once for all their solves.
    import selfsup.refine as refine_module
    from selfsup.refine import reweighted

    problem = problem_of(_scene(5), "none")
    problem = dataclasses.replace(problem, ambient=torch.full((1, 3), 0.05) if known_ambient else None)
    diffuse, specular = refine_module._transport(problem, problem.image.new_tensor([[[0.5, -1.0, 2.0]]]), False)
    options = RefineOptions(irls_passes=3)
    built = []
    original = refine_module.intensity_design
    monkeypatch.setattr(refine_module, "intensity_design", lambda *a: built.append(1) or original(*a))
    shared = reweighted(problem, diffuse, specular, options)
    assert len(built) == 1
    weights = refine_module._weights(problem, None, options)
    for _ in range(3):  # each pass solved afresh, as before the design was shared
        model = refine_module.solve_linear(problem, diffuse, specular, weights)[2]
        weights = refine_module._weights(problem, model - problem.image, options)
    assert len(built) == 4 and torch.equal(shared, weights)
    k = 1 if known_ambient else 2  # the ambient's column when it is unknown
    assert refine_module._design(problem, diffuse, specular).shape == (1, 3, k, problem.image[0, 0].numel())


@pytest.mark.parametrize("method", ["gd", "adam"])
def test_first_order_steps_never_leave_a_nan_position(method, monkeypatch):
    import selfsup.refine as refine_module

    scene = _scene(5)
    problem = problem_of(scene, shadows="none")
    original, calls = refine_module._transport, [0]

    def poisoned(problem, position, specular):  # from the third render on, NaN maps
        calls[0] += 1
        diffuse, spec = original(problem, position, specular)
        return (diffuse * float("nan") if calls[0] >= 3 else diffuse), spec

    monkeypatch.setattr(refine_module, "_transport", poisoned)
    start = scene.light_pos[None] + 0.05 * scene.scene_scale
    fit = refine(problem, start, RefineOptions(method=method, max_iters=(8,), strides=(1,)))
    assert torch.isfinite(fit.position).all() and int(fit.iterations[0]) < 8


def test_cat_undoes_select():
    from selfsup.refine import FitProblem

    problem = FitProblem.cat([problem_of(_scene(4)), problem_of(_scene(5))])
    assert problem.batch == 2 and problem.material.ks.shape[-1] == 3
    again = FitProblem.cat([problem.select(torch.tensor([1])), problem.select(torch.tensor([0]))])
    assert torch.equal(again.image, problem.image.flip(0)) and torch.equal(again.gbuffer.points, problem.gbuffer.points.flip(0))
    assert torch.equal(again.material.shininess, problem.material.shininess.flip(0))


def test_a_selection_keeps_each_images_median_and_a_subsample_finds_its_own():
    from selfsup.refine import subsample

    problem = problems_of([_scene(1), _scene(2), _scene(3)], "none")
    problem.median_observed()
    picked = problem.select(torch.tensor([2, 0, 2]))
    assert picked._median is not None
    assert torch.equal(picked.median_observed(), problems_of([_scene(3), _scene(1), _scene(3)], "none").median_observed())
    assert torch.equal(problem.with_shadows("epipolar").median_observed(), problem.median_observed())
    # A subsample's median and noise level are its own, found once for the problem it
    # came from and for the selections of that problem.
    coarse = subsample(problem, 2)
    fresh = dataclasses.replace(coarse)  # replace() keeps nothing found: computes anew
    assert fresh._median is None and fresh._noise is None
    assert torch.equal(coarse.median_observed(), fresh.median_observed())
    assert torch.equal(coarse.noise_level(), fresh.noise_level())
    assert not torch.equal(coarse.noise_level(), problem.noise_level())
    again = subsample(problem.select(torch.tensor([2, 0, 2])), 2)  # the rows of what coarse found
    assert torch.equal(again.noise_level(), coarse.noise_level()[[2, 0, 2]])
    assert torch.equal(again.noise_level(), dataclasses.replace(again).noise_level())
    assert torch.equal(again.median_observed(), dataclasses.replace(again).median_observed())


def test_bad_refine_inputs_are_named():
    problem = problem_of(_scene(8))
    with pytest.raises(ValueError, match="position must have shape"):
        refine(problem, torch.zeros(1, 3))
    with pytest.raises(ValueError, match="non-finite"):
        refine(problem, torch.full((1, 1, 3), float("nan")))
    with pytest.raises(ValueError, match="method"):
        RefineOptions(method="newton")
    # Each ran before, silently: no refinement at all, no step, no shadow derivative, no second light.
    for bad, name in ((dict(strides=(), max_iters=()), "strides"), (dict(fd_step=0.0), "fd_step"),
                      (dict(learning_rate=0.0), "learning_rate")):
        with pytest.raises(ValueError, match=name):
            RefineOptions(**bad)
    for share in (-1.0, 2.0):
        with pytest.raises(ValueError, match="min_light_share"):
            EstimateOptions(min_light_share=share)


def test_sensor_noise_in_the_depth_is_taken_out_of_the_normals():
    # Depth noise growing with z^2 (a consumer sensor) makes normals from neighbour
    # differences tens of degrees off; auto replaces them by smoothed plane fits.
    from selfsup.scenes.degrade import Degradations, degrade

    scene = _scene(2, config=MEDIUM)
    noisy = degrade(scene, Degradations(depth_noise=0.003, depth_quantisation=0.001), 2)
    options = RefineOptions(max_iters=(20,), strides=(1,), specular=False)
    errors = {mode: _rel_error(refine(problem_of(noisy, "none", normal_smoothing=mode), scene.light_pos[None],
                                      options).position[0], scene)
              for mode in ("never", "auto")}
    assert errors["never"] > 0.015 and errors["auto"] < 0.4 * errors["never"], errors
    # A file's own normals of that depth (neighbour differences) are refitted the same way.
    with_normals = dataclasses.replace(noisy, normals=problem_of(noisy, normal_smoothing="never").gbuffer.normals[0])
    assert torch.equal(problem_of(with_normals, normal_smoothing="auto").gbuffer.normals,
                       problem_of(noisy, normal_smoothing="auto").gbuffer.normals)
    # Clean normals are below the noise threshold: auto leaves them as they are.
    assert torch.equal(problem_of(scene, normal_smoothing="auto").gbuffer.normals,
                       problem_of(scene, normal_smoothing="never").gbuffer.normals)
    with pytest.raises(ValueError, match="normal_smoothing"):
        EstimateOptions(normal_smoothing="sometimes")


def test_the_plane_window_follows_the_focal_length():
    from selfsup.estimate import plane_window_px

    # The same extent in metres at any resolution, about 9x9 samples.
    assert plane_window_px(132.3, 0.06, 120) == (8, 2)
    assert plane_window_px(66.2, 0.06, 60) == (4, 1)
    assert plane_window_px(264.6, 0.06, 240) == (16, 4)
    assert plane_window_px(5.0, 0.06, 120) == (1, 1)
    assert plane_window_px(1e6, 0.06, 120) == (15, 4)  # capped at an eighth of the shorter side
    with pytest.raises(ValueError, match="plane_window"):
        EstimateOptions(plane_window=0)
    with pytest.raises(ValueError, match="plane_shifts"):
        EstimateOptions(plane_shifts=[0.5, 2.0])
    assert EstimateOptions(plane_shifts=[]).plane_shifts == ()  # a config's list, empty: each pixel's own window


def test_noisy_normals_of_a_batch_are_each_scenes_own():
    # Scenes of different focal lengths get different plane windows, batched or alone.
    from selfsup.estimate import plane_window_px, problems_of
    from selfsup.scenes.degrade import Degradations, degrade

    noisy = [degrade(_scene(seed, config=MEDIUM), Degradations(depth_noise=0.003), seed) for seed in (2, 3)]
    assert len({plane_window_px(float(s.K[0, 0]), 0.06, 96) for s in noisy}) == 2
    together = problems_of(noisy, "none", normal_smoothing="auto").gbuffer
    for i, scene in enumerate(noisy):
        alone = problems_of([scene], "none", normal_smoothing="auto").gbuffer
        assert torch.equal(together.normals[i], alone.normals[0]) and torch.equal(together.mask[i], alone.mask[0])


def test_a_true_light_shows_its_shadows_and_a_stand_in_does_not():
    from selfsup.estimate import shadow_gain

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
        EstimateOptions(weak_light_shadow_gain=-1)


def test_the_criterion_block_follows_the_image_width():
    from selfsup.estimate import block_px

    options = EstimateOptions(block_width=0.05)
    assert [block_px(options, w) for w in (160, 80, 320, 8)] == [8, 4, 16, 1]
    assert block_px(EstimateOptions(), 160) == 16  # the defaults: 0.1 of the width, 0.05 albedo-free
    assert block_px(EstimateOptions(), 160, albedo_free=True) == 8
    with pytest.raises(ValueError, match="block_width"):
        EstimateOptions(block_width=0)


def test_noise_level_measures_added_noise_and_floors_the_robust_scale():
    from selfsup.refine import _cauchy_scale

    scene = _scene(3, config=MEDIUM)
    clean = problem_of(scene, "none")
    noisy = dataclasses.replace(clean, image=clean.image + 0.02 * torch.randn(
        clean.image.shape, generator=torch.Generator().manual_seed(0)))
    assert float(clean.noise_level()) < 0.002  # shading curvature and edges only
    assert 0.017 < float(noisy.noise_level()) < 0.023
    options = RefineOptions(robust_scale=0.05)
    # The clean image's scale is robust_scale x median; the noisy one's, the noise level above it.
    torch.testing.assert_close(_cauchy_scale(clean, options), options.robust_scale * clean.median_observed())
    assert float(options.robust_scale * noisy.median_observed()) < float(noisy.noise_level())
    torch.testing.assert_close(_cauchy_scale(noisy, options), options.robust_noise_floor * noisy.noise_level())
    torch.testing.assert_close(_cauchy_scale(noisy, dataclasses.replace(options, robust_noise_floor=0.0)),
                               options.robust_scale * noisy.median_observed())
    for bad in (dict(robust_scale=0.0), dict(robust_noise_floor=-1.0)):
        with pytest.raises(ValueError, match="robust"):
            RefineOptions(**bad)
    with pytest.raises(ValueError, match="final_robust_scale"):
        EstimateOptions(final_robust_scale=0)


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
    assert len(estimate_scene(scene, EstimateOptions(**earlier))["lights"]) == 1
    unfloored = estimate_scene(scene, EstimateOptions(weak_light_min_share=0.0, **earlier))
    brightness = sorted(max(light["intensity"]) for light in unfloored["lights"])
    assert len(brightness) == 2 and brightness[0] < 1e-4 * brightness[1]
    with pytest.raises(ValueError, match="weak_light_min_share"):
        EstimateOptions(weak_light_min_share=-0.1)


def test_a_weak_true_light_that_pays_twice_over_is_kept():
    # Two-light scene 44 of the procedural benchmark (seed 9100): its second light carries
    # 7.5% of the direct light, below min_light_share, shows no shadow gain, and lowers
    # BIC by 650 (2026-11-23), far more than twice its parameters' cost (33). The
    # weak lights of one-light scenes that pay lowered it by 2-22.
    from benchmarks.estimate_procedural import score, set_scene

    scene = set_scene("true reflectance, 2 lights", 44, 9100)
    record = estimate_scene(scene, EstimateOptions())
    assert len(record["lights"]) == 2 and score(record, scene)[1]
    assert len(estimate_scene(scene, EstimateOptions(weak_light_penalty=0))["lights"]) == 1
    with pytest.raises(ValueError, match="weak_light_penalty"):
        EstimateOptions(weak_light_penalty=0.5)


def test_a_light_that_pays_only_against_a_missed_one_light_search_is_dropped(monkeypatch):
    # The one-light search misses (made to here: it returns the true light mirrored across
    # the scene, barely refined), so a second light pays for itself beside it (the share
    # floors are off, as for a stand-in that carries light: Mitsuba gi scene 012 of
    # seed 7000 got such a one). The chosen pair is refitted without each of its lights:
    # one light at the truth wins.
    import selfsup.estimate

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

    monkeypatch.setattr(selfsup.estimate, "search", missing_search)
    record = estimate_scene(scene, EstimateOptions(method="refine", min_light_share=0.0, weak_light_min_share=0.0))
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
    shading_alone = EstimateOptions(criterion_shadows="none", criterion_stride=1)
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
    assert len(estimate_scene(scene, EstimateOptions(criterion_thickness=None))["lights"]) == 1


def test_the_criterion_judges_the_fit_itself_only_where_nothing_differs():
    from selfsup.estimate import judged_problem

    problem = problem_of(_scene(3), "none")
    assert judged_problem(problem, EstimateOptions(criterion_shadows="none", criterion_stride=1)) is problem
    judged = judged_problem(problem, EstimateOptions())  # epipolar, every second pixel, a finite solid
    assert judged.shadows == "epipolar" and tuple(judged.image.shape[-2:]) == (24, 32) and not judged.indirect
    assert judged.shadow_options == EpipolarShadowOptions(scene_thickness=EstimateOptions().criterion_thickness)
    assert judged.select(torch.tensor([0, 0])).shadow_options == judged.shadow_options
    assert judged_problem(problem, EstimateOptions(criterion_thickness=None)).shadow_options is None
    assert judged_problem(dataclasses.replace(problem, ambient=None), EstimateOptions()).indirect
    assert not judged_problem(dataclasses.replace(problem, ambient=None), EstimateOptions(indirect="never")).indirect
    # Valid pixels on odd rows alone: every second pixel would see none of them, so every pixel is judged.
    g = problem.gbuffer
    odd_rows = torch.zeros_like(g.mask)
    odd_rows[:, 1::2] = g.mask[:, 1::2]
    sparse = dataclasses.replace(problem, gbuffer=GBuffer(g.points, g.normals, odd_rows, g.intrinsics))
    assert judged_problem(sparse, EstimateOptions()).image.shape == problem.image.shape
    with pytest.raises(ValueError, match="criterion_stride"):
        EstimateOptions(criterion_stride=0)
    with pytest.raises(ValueError, match="criterion_shadows"):
        EstimateOptions(criterion_shadows="soft")
    for absurd in (0.0, -0.1, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="criterion_thickness"):
            EstimateOptions(criterion_thickness=absurd)


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
    options = EstimateOptions(method="refine", refine=RefineOptions(max_iters=(15, 5)))
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
            record = estimate_scene(scene, EstimateOptions(final_robust_scale=final))
            assert len(record["lights"]) == 1
            errors[final] = _rel_error(torch.tensor(record["lights"][0]["position"]), scene)
        assert errors[0.05] < 0.3 * errors[0.2], errors


def test_robust_solve_at_fixed_positions_converges():
    # More reweighting passes never raise the robust loss of the solved intensities/ambient.
    scene = _scene(6)
    problem = problem_of(scene, "none")
    image = problem.image.clone()
    image[..., :16, :] += 2 * image.amax()  # outliers: a bright band the model cannot explain
    problem = dataclasses.replace(problem, image=image)
    options = RefineOptions(specular=False)
    losses = [float(robust_loss(problem, evaluate(problem, scene.light_pos[None], options, passes=k)[3], options)[0])
              for k in (1, 2, 4, 8)]
    assert all(b <= a * (1 + 1e-5) for a, b in zip(losses, losses[1:])), losses
    assert losses[2] < 0.99 * losses[0] and losses[3] > 0.99 * losses[2], losses
    with pytest.raises(ValueError, match="irls_passes"):
        RefineOptions(irls_passes=0)


def test_throughput_benchmark_scores_a_batch_end_to_end():
    from benchmarks.estimate_throughput import run

    rows, path = run(scenes=2, batches=(2,), device="cpu", sets=("true reflectance, 1 light",), write=False,
                     options=EstimateOptions(refine=RefineOptions(max_iters=(15, 5))))
    assert path is None and len(rows) == 1
    row = rows[0]
    assert row["scenes"] == 2 and row["scenes_per_s"] > 0 and row["success_rate"] == 1.0
    assert abs(row["inputs_share"] + row["estimate_share"] + row["records_share"] - 1) < 0.05


def test_files_speed_benchmark_times_the_command_on_a_directory():
    from benchmarks.estimate_files_speed import run

    rows, path = run(scenes=2, workers=(1,), batches=(2,), sets=("true reflectance, 1 light",), rounds=1, write=False,
                     options=EstimateOptions(refine=RefineOptions(max_iters=(15, 5))))
    assert path is None and len(rows) == 1
    row = rows[0]
    assert row["scenes"] == 2 and row["workers"] == 1 and row["seconds_per_scene"] > 0 and row["success_rate"] == 1.0


def test_large_images_benchmark_compares_every_pixel_with_the_subsample():
    from benchmarks.large_images import run

    rows = run(1, 48, 64, 777, max_pixels=768)
    assert [r["id"] for r in rows][1::2] == ["all (median, count)"] * 2
    for row in rows:
        assert row["stride"] == 2 and row["found_all"] == row["found_default"] == 1
        assert row["answers_apart"] < 0.05 and row["seconds_all"] > 0 and row["seconds_default"] > 0


def test_batched_files_match_single_files_and_a_bad_one_costs_no_other(tmp_path):
    config = dataclasses.replace(SMALL, height=24, width=32)
    for seed in (6, 7):
        write_scene(tmp_path / f"good_{seed}.npz", _scene(seed, config=config))
    # Readable, but every pixel clipped (left out): it fails inside the batch's
    # preparation, which is then retried file by file.
    arrays = dict(np.load(tmp_path / "good_6.npz"))
    arrays["image"] = np.ones_like(arrays["image"])
    np.savez(tmp_path / "clipped.npz", **arrays)
    options = EstimateOptions(max_lights=1, refine=RefineOptions(max_iters=(10, 3)))
    single = estimate_files(tmp_path, tmp_path / "one.jsonl", options, progress=False)
    batched = estimate_files(tmp_path, tmp_path / "four.jsonl", options, progress=False, batch=4)
    assert single["done"] == batched["done"] == 2 and list(batched["failures"]) == [str(tmp_path / "clipped.npz")]
    assert "no valid pixel" in batched["failures"][str(tmp_path / "clipped.npz")]
    one, four = ([json.loads(line) for line in (tmp_path / name).read_text().splitlines()] for name in ("one.jsonl", "four.jsonl"))
    assert [r["id"] for r in one] == [r["id"] for r in four]
    for a, b in zip(one, four):
        assert np.allclose(a["lights"][0]["position"], b["lights"][0]["position"], atol=1e-3)
    with pytest.raises(ValueError, match="estimate.batch must be >= 1"):
        estimate_files(tmp_path, tmp_path / "x.jsonl", options, progress=False, batch=0)


def test_files_with_one_shininess_for_every_pixel_are_estimated(tmp_path):
    # shininess of shape () (the format allows it) alone and in a batch of two.
    config = dataclasses.replace(SMALL, height=24, width=32)
    for seed in (6, 7):
        arrays = dict(np.load(_written(tmp_path, seed, config)))
        arrays["shininess"] = np.array(30.0, np.float32)
        np.savez(tmp_path / f"scene_{seed}.npz", **arrays)
    options = EstimateOptions(max_lights=1, refine=RefineOptions(max_iters=(10, 3)))
    for batch in (1, 2):
        summary = estimate_files(tmp_path, tmp_path / f"out_{batch}.jsonl", options, progress=False, batch=batch)
        assert summary["done"] == 2 and not summary["failures"]


def test_files_without_normals_or_light_are_handled_as_the_format_says(tmp_path):
    # All-zero normals are missing ones: estimated from the depth, as for a file without
    # the key (they were masked out, and such a file had no valid pixel left). A black
    # image has no light to estimate: named, not a crash or a clipped-pixel complaint.
    config = dataclasses.replace(SMALL, height=24, width=32)
    arrays = dict(np.load(_written(tmp_path, 6, config)))
    np.savez(tmp_path / "a_given.npz", **arrays)
    np.savez(tmp_path / "b_no_key.npz", **{k: v for k, v in arrays.items() if k != "normals"})
    np.savez(tmp_path / "c_zero.npz", **{**arrays, "normals": np.zeros_like(arrays["normals"])})
    np.savez(tmp_path / "d_black.npz", **{**arrays, "image": np.zeros_like(arrays["image"])})
    options = EstimateOptions(max_lights=1, refine=RefineOptions(max_iters=(10, 3)))
    summary = estimate_files(tmp_path, tmp_path / "out.jsonl", options, progress=False)
    assert summary["done"] == 3 and list(summary["failures"]) == [str(tmp_path / "d_black.npz")]
    assert "zero on every valid pixel" in summary["failures"][str(tmp_path / "d_black.npz")]
    given, no_key, zero = (json.loads(line) for line in (tmp_path / "out.jsonl").read_text().splitlines())
    assert zero["lights"][0]["position"] == no_key["lights"][0]["position"]
    assert np.linalg.norm(np.subtract(zero["lights"][0]["position"], given["lights"][0]["position"])) < 0.05


def test_a_file_over_max_pixels_is_estimated_on_a_subsample(tmp_path, caplog):
    assert [pixel_stride(*size) for size in ((480, 640, 76800), (120, 160, 76800), (481, 641, 76800),
                                            (480, 640, None))] == [2, 1, 3, 1]
    config = dataclasses.replace(SMALL, height=48, width=64)
    _written(tmp_path, 6, config)
    options = EstimateOptions(max_lights=1, refine=RefineOptions(max_iters=(10, 3)))
    every = estimate_files(tmp_path / "written", tmp_path / "all.jsonl", dataclasses.replace(options, max_pixels=None),
                           progress=False)
    with caplog.at_level(logging.INFO, logger="selfsup.estimate"):
        sub = estimate_files(tmp_path / "written", tmp_path / "sub.jsonl", dataclasses.replace(options, max_pixels=800),
                             progress=False, workers=1)
    assert every["done"] == sub["done"] == 1
    assert "estimated on every 2nd pixel" in caplog.text
    a, b = (json.loads((tmp_path / name).read_text()) for name in ("all.jsonl", "sub.jsonl"))
    assert np.linalg.norm(np.subtract(a["lights"][0]["position"], b["lights"][0]["position"])) < 0.02
    with pytest.raises(ValueError, match="max_pixels must be null or an integer >= 1"):
        EstimateOptions(max_pixels=0)


def test_intensities_under_unaccounted_light_are_solved_with_its_indirect_light():
    # An image with each light's first bounce (selfsup.indirect, the model itself) added
    # and no ambient given: the fit, direct light only, takes the bounce for more lamp;
    # the reported intensities, solved again with it at the chosen position, do not.
    from render import light_transport
    from selfsup.indirect import indirect_columns

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
    never = records([scene.id], problem, [(best, [best])], dataclasses.replace(options, indirect="never"))[0]
    assert never["lights"][0]["intensity"] == best.fit.intensity[0, 0].tolist()


def test_normals_of_the_other_sign_convention_are_turned_round(tmp_path, caplog):
    # Normals facing away from the camera (an OpenGL-style file) gave a light on the
    # wrong side; now they are turned round, with a warning, and give the file's answer.
    config = dataclasses.replace(SMALL, height=24, width=32)
    arrays = dict(np.load(_written(tmp_path, 6, config)))
    np.savez(tmp_path / "a_given.npz", **arrays)
    normals = -arrays["normals"]
    normals[:4] = 0  # missing there: estimated from the depth, facing the camera already
    np.savez(tmp_path / "b_away.npz", **{**arrays, "normals": normals})
    options = EstimateOptions(max_lights=1, refine=RefineOptions(max_iters=(10, 3)))
    with caplog.at_level(logging.WARNING, logger="selfsup.scenes.io"):
        estimate_files(tmp_path, tmp_path / "out.jsonl", options, progress=False, workers=1)
    assert "normals face away from the camera" in caplog.text
    given, away = (json.loads(line) for line in (tmp_path / "out.jsonl").read_text().splitlines())
    assert np.linalg.norm(np.subtract(given["lights"][0]["position"], away["lights"][0]["position"])) < 0.02


def _written(folder, seed, config):
    path = folder / "written" / f"{seed}.npz"
    path.parent.mkdir(exist_ok=True)
    write_scene(path, _scene(seed, config=config))
    return path


@pytest.mark.parametrize("method", [
    "spawn",
    pytest.param("fork", marks=pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forked workers: Linux only")),
])
def test_worker_processes_write_what_one_process_writes_in_the_files_order(tmp_path, method, monkeypatch):
    import selfsup.estimate as estimate_module

    monkeypatch.setattr(estimate_module, "start_method", lambda threads, device: method)
    config = dataclasses.replace(SMALL, height=24, width=32)
    for seed in (6, 7, 8):
        write_scene(tmp_path / f"good_{seed}.npz", _scene(seed, config=config))
    np.savez(tmp_path / "good_7_missing.npz", image=np.zeros((4, 4, 3), np.float32))
    options = EstimateOptions(max_lights=1, refine=RefineOptions(max_iters=(10, 3)))
    alone = estimate_files(tmp_path, tmp_path / "one.jsonl", options, progress=False, workers=1)
    spread = estimate_files(tmp_path, tmp_path / "two.jsonl", options, progress=False, workers=2)
    assert spread["workers"] == 2 and alone["workers"] == 1 and spread["start"] == method and alone["start"] is None
    assert alone["done"] == spread["done"] == 3 and list(spread["failures"]) == [str(tmp_path / "good_7_missing.npz")]
    one, two = ([json.loads(line) for line in (tmp_path / name).read_text().splitlines()] for name in ("one.jsonl", "two.jsonl"))
    assert [r["id"] for r in two] == [r["id"] for r in one] == ["procedural_6", "procedural_7", "procedural_8"]
    for a, b in zip(one, two):
        assert np.allclose(a["lights"][0]["position"], b["lights"][0]["position"], atol=1e-3)
    assert spread["wall_seconds"] > 0


class _FakePool:
    """Stands in for ``ProcessPoolExecutor`` (constructed like it, a context manager):
    ``answer(index, future, fn, args)`` settles, or leaves pending, each submitted future."""

    def __init__(self, answer):
        self.answer = answer
        self.futures = []

    def __call__(self, *args, **kwargs):
        return self

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def submit(self, fn, *args):
        from concurrent.futures import Future

        future = Future()
        self.answer(len(self.futures), future, fn, args)
        self.futures.append(future)
        return future


def test_files_of_a_worker_that_died_are_estimated_here(tmp_path, monkeypatch):
    # A worker killed mid-run (out of memory, a signal) breaks the pool: every chunk it
    # had not answered is estimated again in this process, none is lost.
    from concurrent.futures.process import BrokenProcessPool

    import selfsup.estimate as estimate_module

    def dying(index, future, fn, args):  # the first chunk answered, then the pool breaks
        if index == 0:
            future.set_result(fn(*args))
        else:
            future.set_exception(BrokenProcessPool("a worker stopped"))

    monkeypatch.setattr(estimate_module, "ProcessPoolExecutor", _FakePool(dying))
    config = dataclasses.replace(SMALL, height=24, width=32)
    for seed in (6, 7, 8):
        write_scene(tmp_path / f"good_{seed}.npz", _scene(seed, config=config))
    options = EstimateOptions(max_lights=1, refine=RefineOptions(max_iters=(10, 3)))
    summary = estimate_files(tmp_path, tmp_path / "out.jsonl", options, progress=False, workers=2)
    assert summary["done"] == 3 and summary["failed"] == 0
    ids = [json.loads(line)["id"] for line in (tmp_path / "out.jsonl").read_text().splitlines()]
    assert ids == ["procedural_6", "procedural_7", "procedural_8"]


def test_a_run_stopped_early_cancels_the_chunks_still_queued(monkeypatch):
    # Ctrl-C or a failed write while the workers run: the queued chunks are cancelled,
    # so the pool's exit does not wait for them all to be estimated.
    import selfsup.estimate as estimate_module

    def queued(index, future, fn, args):  # the first chunk answered, the others still queued
        if index == 0:
            future.set_result(({}, {}))

    pool = _FakePool(queued)
    monkeypatch.setattr(estimate_module, "ProcessPoolExecutor", pool)
    results = estimate_module._chunk_results([["a"], ["b"], ["c"]], EstimateOptions(), torch.device("cpu"), workers=2)
    assert next(results)[0] == ["a"]
    results.close()  # what an exception in the consumer does to the generator
    assert [f.cancelled() for f in pool.futures] == [False, True, True]


def test_worker_count_auto_spreads_only_directories_worth_a_start(monkeypatch):
    import selfsup.estimate as estimate_module
    from selfsup.estimate import FILES_PER_SPAWNED_WORKER, worker_count

    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    monkeypatch.setattr(estimate_module, "usable_cores", lambda: 4)
    monkeypatch.setattr(estimate_module, "start_method", lambda threads, device: "fork")
    assert [worker_count("auto", files, cpu) for files in (1, 3, 100)] == [1, 3, 4]
    monkeypatch.setattr(estimate_module, "start_method", lambda threads, device: "spawn")
    assert worker_count("auto", 1, cpu) == 1 and worker_count("auto", 2 * FILES_PER_SPAWNED_WORKER - 1, cpu) == 1
    assert worker_count("auto", 1000 * FILES_PER_SPAWNED_WORKER, cpu) == 4
    assert worker_count("auto", 1000, cuda) == 1 and worker_count(3, 1, cpu) == 3
    for bad in (0, -1, "two", 1.5, True):
        with pytest.raises(ValueError, match="estimate.workers must be"):
            worker_count(bad, 10, cpu)


def test_workers_are_forked_only_where_that_is_safe():
    from selfsup.estimate import start_method

    cpu = torch.device("cpu")
    assert start_method(1, cpu) == ("fork" if sys.platform.startswith("linux") else "spawn")
    assert start_method(2, cpu) == "spawn"  # a multi-thread child may hang in the inherited OpenMP pool
    assert start_method(1, torch.device("cuda")) == "spawn"  # a forked child cannot use CUDA


def test_segment_gains_recover_each_surfaces_albedo_factor():
    from selfsup.estimate import segment_gains

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
    from render.geometry import surface_segments

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
        record = estimate_scene(wrong, EstimateOptions(reflectance_gains=rounds, max_lights=1))
        errors.append(_rel_error(torch.tensor(record["lights"][0]["position"]), scene))
    assert errors[1] < 0.01 and errors[1] < 0.6 * errors[0], errors
    with pytest.raises(ValueError, match="reflectance_gains"):
        EstimateOptions(reflectance_gains=-1)


def test_benchmark_options_reach_estimate_and_refine_settings():
    from benchmarks.estimate_procedural import parse_options

    extra = parse_options(["block_width=0.1", "refine.robust_scale=0.05", "weak_light_shadow_gain=0"])
    options = EstimateOptions(**extra)
    assert (options.block_width, options.weak_light_shadow_gain, options.refine.robust_scale) == (0.1, 0, 0.05)
    with pytest.raises(ValueError, match="KEY=VALUE"):
        parse_options(["block_width"])


def test_inside_two_sigma_counts_true_lights_within_their_estimates_ellipsoid():
    from selfsup.metrics import inside_two_sigma

    estimated = torch.tensor([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    cov = torch.stack([torch.eye(3), torch.diag(torch.tensor([9.0, 1.0, 1.0]))])
    # Mahalanobis^2: 4 (inside), 16 / 9 along the wide axis (inside); then 9 and 25 (outside).
    assert inside_two_sigma(estimated, cov, torch.tensor([[2.0, 0.0, 0.0], [14.0, 0.0, 0.0]])) == 2
    assert inside_two_sigma(estimated, cov, torch.tensor([[3.0, 0.0, 0.0], [10.0, 5.0, 0.0]])) == 0
    # A true light with no estimate to pair with is outside.
    assert inside_two_sigma(estimated[:1], cov[:1], torch.tensor([[0.5, 0.0, 0.0], [10.0, 0.0, 0.0]])) == 1


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
    options = EstimateOptions(method="refine", max_lights=1, coat="auto")
    on_coated = estimate_scene(coated, options)
    on_bare = estimate_scene(rendered.scene, options)
    assert on_coated["coat"] and not on_bare["coat"]
    assert [c["coat"] for c in on_bare["candidates"]].count(True) >= 1  # it was tried there too
    for record, scene in ((on_coated, coated), (on_bare, rendered.scene)):
        assert _rel_error(torch.tensor([l["position"] for l in record["lights"]]), scene) < 0.005
    never = estimate_scene(coated, dataclasses.replace(options, coat="never"))
    assert not never["coat"] and all(not c["coat"] for c in never["candidates"])
    with pytest.raises(ValueError, match="estimate.coat"):
        EstimateOptions(coat="sometimes")


def test_a_pass_of_the_estimator_starts_from_the_coats_its_options_give():
    # reflectance_gains runs the estimator again on the same problem: a coat the last
    # pass chose must not stay on the material of the next one.
    from selfsup.estimate import _with_coat, estimate_batch, prepare

    config = dataclasses.replace(MEDIUM, specular_prob=1.0)
    scene = render_spec(sample_scene(3, config, n_lights=1), samples=1).scene
    options = EstimateOptions(method="refine", max_lights=1, coat="never")
    problem = prepare([scene], options)
    problem.material = _with_coat(problem.material, [True])  # as a pass under auto leaves it
    ((best, tried),) = estimate_batch(problem, options)
    assert problem.material.coat is None and not best.coat and not any(c.coat for c in tried)


def test_a_coated_two_light_scene_judges_both_coat_settings_at_two_lights():
    # The one-light fit of a two-light scene chooses the coat unreliably, so the chosen
    # two-light model is refitted with the other setting too and the better one kept.
    config = dataclasses.replace(MEDIUM, specular_prob=1.0)
    rendered = render_spec(sample_scene(4, config, n_lights=2), samples=1)
    coated = _coated_copy(rendered)
    record = estimate_scene(coated, EstimateOptions(method="refine", max_lights=2, coat="auto"))
    assert len(record["lights"]) == 2 and record["coat"]
    assert {c["coat"] for c in record["candidates"] if c["n_lights"] == 2} == {True, False}
    assert _rel_error_paired(torch.tensor([l["position"] for l in record["lights"]]), coated) < 0.01
