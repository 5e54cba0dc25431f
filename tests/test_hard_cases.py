"""Every hard case of benchmarks/stability.py, small: finite outputs and a bounded error."""

import pytest

from benchmarks.stability import cases, evaluate_case
from selfsup.estimation.options import EstimateOptions, Tuning, RefineOptions

CASES = list(cases(height=48, width=64))


@pytest.mark.parametrize("name, scene", CASES, ids=[name for name, _ in CASES])
def test_hard_case_gives_finite_lights_and_a_bounded_error(name, scene):
    options = EstimateOptions(method="cnn+refine", max_lights=1, tuning=Tuning(refine=RefineOptions(max_iters=(10, 3))))
    row = evaluate_case(name, scene, options)
    assert row["converged"], row["note"]
    assert row["finite"] and row["lights_found"] == 1
    assert row["position_error"] < 0.25, row


def test_clipped_pixels_are_found_and_left_out():
    import torch

    from selfsup.estimation.prepare import saturated_pixels

    image = torch.rand(1, 3, 20, 30) + 0.1
    mask = torch.ones(1, 20, 30, dtype=torch.bool)
    assert not saturated_pixels(image, mask).any()  # a maximum at one pixel is no clipping
    clipped = image.clamp(max=0.9)
    found = saturated_pixels(clipped, mask)
    assert torch.equal(found, (image > 0.9).any(1))
    mask[0, :, :5] = False  # invalid pixels never count, whatever they hold
    assert not (saturated_pixels(clipped, mask) & ~mask).any()


def test_clipped_highlights_do_not_become_a_second_light():
    # Without leaving the clipped pixels out, the flat-topped highlight was fitted with
    # a second light (benchmarks/results/stability_*: 2 lights, error 1.0).
    # At 48x64 the second light did not pay for itself anyway: full size here.
    name, scene = next((n, s) for n, s in cases(height=120, width=160) if n.startswith("highlights clipped"))
    row = evaluate_case(name, scene, EstimateOptions(method="cnn+refine"))
    assert row["lights_found"] == 1 and row["position_error"] < 0.01, row


def test_a_huge_scene_with_unknown_ambient_is_fitted_as_precisely_as_with_known():
    # The ambient's column (kd) outweighs the lights' (1/d^2) a million-fold at 1e3 m;
    # a ridge relative to the normal matrix's trace pulled the fit to 0.01 of the scene.
    found = {name: scene for name, scene in cases(height=48, width=64) if name.startswith("huge")}
    for name, scene in found.items():
        row = evaluate_case(name, scene, EstimateOptions())
        assert row["lights_found"] == 1 and row["position_error"] < 1e-3, row
    assert len(found) == 2
