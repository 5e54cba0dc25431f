"""The solvers: LM, the first-order methods, the grid search."""

import dataclasses




import pytest
import torch
from selfsup.estimation.options import EstimateOptions, Tuning, RefineOptions


from selfsup.estimation.prepare import prepare, problem_of



from selfsup.estimation.problem import solve_at, robust_loss
from selfsup.estimation.solvers import _lm, refine, search





from estimation_helpers import MEDIUM, _rel_error, _scene


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
    # as here: every fit lowers its start's cost, and the cheapest is the one at the light.
    scene = _scene(1)
    directions = torch.tensor([[1.0, -1.0, 1.0], [-1.0, 1.0, 1.0], [1.0, 1.0, -1.0], [-1.0, -1.0, -1.0]]) / 3**0.5
    problem = problem_of(scene, "epipolar").select(torch.zeros(len(directions), dtype=torch.long))
    start = scene.light_pos[None] + 0.04 * scene.scene_scale * directions[:, None]
    options = RefineOptions(method="lm", max_iters=(40, 10), strides=(1, 1))
    fit = refine(problem, start, options)
    start_cost = refine(problem, start, dataclasses.replace(options, max_iters=(0,), strides=(1,))).cost
    assert (fit.cost < start_cost).all()
    # The cheapest fit is the nearest the light (0.0004 of the scene on one machine, 0.0037 on
    # another: where LM stops between shadow edges flips with the CPU's float rounding).
    errors = [_rel_error(fit.position[i], scene) for i in range(len(directions))]
    assert int(fit.cost.argmin()) == min(range(len(errors)), key=errors.__getitem__) and min(errors) < 0.005


@pytest.mark.xfail(strict=True, reason="known issue: the paper's rate 0.02 on our normalised energy overshoots")
def test_paper_gradient_descent_lowers_the_energy_and_stops_on_its_own():
    scene = _scene(1)
    problem = problem_of(scene)
    start = scene.light_pos[None] + 0.04 * scene.scene_scale * torch.tensor([1.0, -1.0, 1.0]) / 3**0.5
    options = RefineOptions(method="gd", max_iters=(500,), strides=(1,))
    fit = refine(problem, start, options)
    before = robust_loss(problem, solve_at(problem, start, options)[3], options)
    assert float(robust_loss(problem, fit.model, options)[0]) < float(before[0])
    assert 0 < int(fit.iterations[0]) < 500  # the relative-change rule (1e-4) ended it


def test_search_finds_the_light_without_a_start():
    scene = _scene(3, config=MEDIUM)
    fit = search(problem_of(scene), 1, RefineOptions(max_iters=(15, 5)))
    assert _rel_error(fit.position[0], scene) < 0.02


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


@pytest.mark.parametrize("method", ["gd", "adam"])
def test_first_order_steps_never_leave_a_nan_position(method, monkeypatch):
    import selfsup.estimation.solvers as refine_module

    scene = _scene(5)
    problem = problem_of(scene, shadows="none")
    original, calls = refine_module.transport_maps, [0]

    def poisoned(problem, position, specular):  # from the third render on, NaN maps
        calls[0] += 1
        diffuse, spec = original(problem, position, specular)
        return (diffuse * float("nan") if calls[0] >= 3 else diffuse), spec

    monkeypatch.setattr(refine_module, "transport_maps", poisoned)
    start = scene.light_pos[None] + 0.05 * scene.scene_scale
    fit = refine(problem, start, RefineOptions(method=method, max_iters=(8,), strides=(1,)))
    assert torch.isfinite(fit.position).all() and int(fit.iterations[0]) < 8


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
            EstimateOptions(tuning=Tuning(min_light_share=share))
