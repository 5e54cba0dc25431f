"""The fit problem: selections, noise levels, the closed-form solve and its robust weights."""

import dataclasses




import pytest
import torch
from selfsup.estimation.options import EstimateOptions, Tuning, RefineOptions


from selfsup.estimation.prepare import problem_of, problems_of



from selfsup.estimation.problem import solve_at, robust_loss
from selfsup.estimation.solvers import refine





from estimation_helpers import MEDIUM, SMALL, _rel_error, _scene


def test_lm_recovers_intensity_and_unknown_ambient_exactly():
    config = dataclasses.replace(SMALL, ambient_zero_prob=0.0)
    scene = _scene(2, config=config)
    scene.ambient = None
    problem = problem_of(scene, shadows="epipolar")
    fit = refine(problem, scene.light_pos[None] * 1.05, RefineOptions(max_iters=(20, 10)))
    torch.testing.assert_close(fit.intensity[0], scene.light_intensity, rtol=0.05, atol=0)
    assert _rel_error(fit.position[0], scene) < 0.01  # the depth-map shadows differ from exact rays


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
    # reweighted and solve_at build the least-squares columns once for all their solves.
    import selfsup.estimation.problem as refine_module
    from selfsup.estimation.problem import reweighted

    problem = problem_of(_scene(5), "none")
    problem = dataclasses.replace(problem, ambient=torch.full((1, 3), 0.05) if known_ambient else None)
    diffuse, specular = refine_module.transport_maps(problem, problem.image.new_tensor([[[0.5, -1.0, 2.0]]]), False)
    options = RefineOptions(irls_passes=3)
    built = []
    original = refine_module.intensity_design
    monkeypatch.setattr(refine_module, "intensity_design", lambda *a: built.append(1) or original(*a))
    shared = reweighted(problem, diffuse, specular, options)
    assert len(built) == 1
    weights = refine_module.irls_weights(problem, None, options)
    for _ in range(3):  # each pass solved afresh, as before the design was shared
        model = refine_module.solve_linear(problem, diffuse, specular, weights)[2]
        weights = refine_module.irls_weights(problem, model - problem.image, options)
    assert len(built) == 4 and torch.equal(shared, weights)
    k = 1 if known_ambient else 2  # the ambient's column when it is unknown
    assert refine_module.design_columns(problem, diffuse, specular).shape == (1, 3, k, problem.image[0, 0].numel())


def test_cat_undoes_select():
    from selfsup.estimation.problem import FitProblem

    problem = FitProblem.cat([problem_of(_scene(4)), problem_of(_scene(5))])
    assert problem.batch == 2 and problem.material.ks.shape[-1] == 3
    again = FitProblem.cat([problem.select(torch.tensor([1])), problem.select(torch.tensor([0]))])
    assert torch.equal(again.image, problem.image.flip(0)) and torch.equal(again.gbuffer.points, problem.gbuffer.points.flip(0))
    assert torch.equal(again.material.shininess, problem.material.shininess.flip(0))


def test_a_selection_keeps_each_images_median_and_a_subsample_finds_its_own():
    from selfsup.estimation.problem import subsample

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


def test_noise_level_measures_added_noise_and_floors_the_robust_scale():
    from selfsup.estimation.problem import cauchy_scale

    scene = _scene(3, config=MEDIUM)
    clean = problem_of(scene, "none")
    noisy = dataclasses.replace(clean, image=clean.image + 0.02 * torch.randn(
        clean.image.shape, generator=torch.Generator().manual_seed(0)))
    assert float(clean.noise_level()) < 0.002  # shading curvature and edges only
    assert 0.017 < float(noisy.noise_level()) < 0.023
    options = RefineOptions(robust_scale=0.05)
    # The clean image's scale is robust_scale x median; the noisy one's, the noise level above it.
    torch.testing.assert_close(cauchy_scale(clean, options), options.robust_scale * clean.median_observed())
    assert float(options.robust_scale * noisy.median_observed()) < float(noisy.noise_level())
    torch.testing.assert_close(cauchy_scale(noisy, options), options.robust_noise_floor * noisy.noise_level())
    torch.testing.assert_close(cauchy_scale(noisy, dataclasses.replace(options, robust_noise_floor=0.0)),
                               options.robust_scale * noisy.median_observed())
    for bad in (dict(robust_scale=0.0), dict(robust_noise_floor=-1.0)):
        with pytest.raises(ValueError, match="robust"):
            RefineOptions(**bad)
    with pytest.raises(ValueError, match="final_robust_scale"):
        EstimateOptions(tuning=Tuning(final_robust_scale=0))


def test_robust_solve_at_fixed_positions_converges():
    # More reweighting passes never raise the robust loss of the solved intensities/ambient.
    scene = _scene(6)
    problem = problem_of(scene, "none")
    image = problem.image.clone()
    image[..., :16, :] += 2 * image.amax()  # outliers: a bright band the model cannot explain
    problem = dataclasses.replace(problem, image=image)
    options = RefineOptions(specular=False)
    losses = [float(robust_loss(problem, solve_at(problem, scene.light_pos[None], options, passes=k)[3], options)[0])
              for k in (1, 2, 4, 8)]
    assert all(b <= a * (1 + 1e-5) for a, b in zip(losses, losses[1:])), losses
    assert losses[2] < 0.99 * losses[0] and losses[3] > 0.99 * losses[2], losses
    with pytest.raises(ValueError, match="irls_passes"):
        RefineOptions(irls_passes=0)
