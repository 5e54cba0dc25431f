"""Position covariances and the scores of the error sources the residual cannot show."""

import dataclasses




import pytest
import torch
from selfsup.estimation.options import EstimateOptions, Tuning, RefineOptions
from selfsup.estimation.stages import estimate_scene

from selfsup.estimation.prepare import problem_of


from render import GBuffer, Material
from selfsup.estimation.problem import FitProblem
from selfsup.estimation.solvers import normal_equations, refine
from selfsup.estimation.uncertainty import position_blocks




from estimation_helpers import MEDIUM, SMALL, _scene


def test_uncertainty_is_present_finite_and_small_on_an_exact_scene():
    scene = _scene(5)
    record = estimate_scene(scene, EstimateOptions(method="refine", max_lights=1, tuning=Tuning(refine=RefineOptions(max_iters=(15, 5)))))
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
    options = EstimateOptions(method="refine", max_lights=1, tuning=Tuning(refine=RefineOptions(max_iters=(15, 5))))
    metres = estimate_scene(scene, options)["lights"][0]
    millimetres = estimate_scene(dataclasses.replace(scene, depth=scene.depth * 1000), options)["lights"][0]
    torch.testing.assert_close(torch.tensor(millimetres["position"]), 1000 * torch.tensor(metres["position"]),
                               rtol=1e-3, atol=0)
    torch.testing.assert_close(torch.tensor(millimetres["position_std"]), 1000 * torch.tensor(metres["position_std"]),
                               rtol=0.05, atol=0)


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
    normal, gradient = normal_equations(problem, j_pos, cols, weights, residual)
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
    basis images, positions' Jacobian and diffuse transport (:func:`jacobians`, no
    specular term), the valid mask ``(B, 3, H, W)`` and the information matrix."""
    from selfsup.estimation.solvers import jacobians
    from selfsup.estimation.problem import centre_and_size

    problem.image = refine(problem, truth, dataclasses.replace(options, max_iters=(0,))).model
    fit = refine(problem, truth, options)
    h = (options.fd_step * centre_and_size(problem)[1])[:, None, None]
    cols, j_pos, diffuse = jacobians(problem, fit.position, fit.intensity, h, False)
    mask = problem.gbuffer.mask[:, None].expand_as(problem.image).to(problem.image.dtype)
    info, _ = normal_equations(problem, j_pos, cols, mask)
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
    from selfsup.estimation.uncertainty import albedo_scores

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
    from selfsup.estimation.uncertainty import normal_tilt_scores, tilt_axes

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
    from selfsup.estimation.solvers import jacobians
    from selfsup.estimation.uncertainty import block_scores
    from selfsup.estimation.problem import centre_and_size

    problem = problem_of(_scene(5), "none", dtype=torch.float64)
    problem.ambient = None
    B, _, H, W = problem.image.shape
    block = 7
    assert H % block and W % block  # both borders hold partial blocks
    position = problem.gbuffer.extent()[0][:, None] + torch.tensor([0.3, -0.5, 0.1], dtype=torch.float64)
    h = (1e-3 * centre_and_size(problem)[1])[:, None, None]
    cols, j_pos, _ = jacobians(problem, position, torch.ones(B, 1, 3, dtype=torch.float64), h, False)
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
    from selfsup.estimation.solvers import jacobians
    from selfsup.estimation.uncertainty import block_scores
    from selfsup.estimation.problem import centre_and_size

    scene = _scene(5)
    problem = problem_of(scene, "none", dtype=torch.float64)
    problem.ambient = torch.full((1, 3), 0.05, dtype=torch.float64)  # the image: the model's own, with ambient light
    options = RefineOptions(max_iters=(80,), strides=(1,), robust=False, tol=1e-14, step_tol=1e-12)
    truth = scene.light_pos[None].double()
    problem.image = refine(problem, truth, dataclasses.replace(options, max_iters=(0,))).model
    problem.ambient = None
    fit = refine(problem, truth, options)
    torch.testing.assert_close(fit.ambient, torch.full((1, 3), 0.05, dtype=torch.float64))
    h = (options.fd_step * centre_and_size(problem)[1])[:, None, None]
    cols, j_pos, _ = jacobians(problem, fit.position, fit.intensity, h, False)
    mask = problem.gbuffer.mask[:, None].expand_as(problem.image).double()
    info, _ = normal_equations(problem, j_pos, cols, mask)
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
    options = EstimateOptions(method="refine", max_lights=1, tuning=Tuning(refine=RefineOptions(max_iters=(15, 5))))
    without = options.tuned(indirect_variation=0.0)
    given = [estimate_scene(scene, o)["lights"][0] for o in (options, without)]
    assert given[0]["position_std"] == given[1]["position_std"]  # the file gives its ambient: nothing unaccounted
    scene.ambient = None
    unknown = [estimate_scene(scene, o)["lights"][0] for o in (options, without)]
    assert unknown[0]["position"] == unknown[1]["position"]  # the same fit; only its uncertainty grows
    assert all(w > e for w, e in zip(unknown[0]["position_std"], unknown[1]["position_std"]))
    for bad in (dict(indirect_variation=-0.1), dict(indirect_variation=float("nan")), dict(indirect_length=0.0),
                dict(indirect_length=float("inf"))):
        with pytest.raises(ValueError, match="estimate.tuning.indirect_"):
            EstimateOptions.from_settings(**bad)


def test_normal_error_widens_only_where_normals_were_refitted_from_noisy_depth():
    from selfsup.scenes.degrade import Degradations, degrade

    scene = _scene(2, config=MEDIUM)
    options = EstimateOptions(method="refine", max_lights=1, tuning=Tuning(refine=RefineOptions(max_iters=(15, 5))))
    without = options.tuned(normal_error=False)
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
    options = EstimateOptions(method="refine", max_lights=1, tuning=Tuning(refine=RefineOptions(max_iters=(15, 5))))
    exact = estimate_scene(scene, options)["lights"][0]
    same = estimate_scene(scene, options.tuned(albedo_error=0.0))["lights"][0]
    wider = estimate_scene(scene, options.tuned(albedo_error=0.05))["lights"][0]
    assert same["position_std"] == exact["position_std"]
    assert wider["position"] == exact["position"]  # the fit is the same; only its uncertainty grows
    assert all(w > e for w, e in zip(wider["position_std"], exact["position_std"]))
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="estimate.tuning.albedo_error"):
            EstimateOptions(tuning=Tuning(albedo_error=bad))


def test_inside_two_sigma_counts_true_lights_within_their_estimates_ellipsoid():
    from selfsup.metrics import inside_two_sigma

    estimated = torch.tensor([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    cov = torch.stack([torch.eye(3), torch.diag(torch.tensor([9.0, 1.0, 1.0]))])
    # Mahalanobis^2: 4 (inside), 16 / 9 along the wide axis (inside); then 9 and 25 (outside).
    assert inside_two_sigma(estimated, cov, torch.tensor([[2.0, 0.0, 0.0], [14.0, 0.0, 0.0]])) == 2
    assert inside_two_sigma(estimated, cov, torch.tensor([[3.0, 0.0, 0.0], [10.0, 5.0, 0.0]])) == 0
    # A true light with no estimate to pair with is outside.
    assert inside_two_sigma(estimated[:1], cov[:1], torch.tensor([[0.5, 0.0, 0.0], [10.0, 0.0, 0.0]])) == 1
