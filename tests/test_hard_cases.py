"""Every hard case of benchmarks/stability.py, small: finite outputs and a bounded error."""

import pytest

from benchmarks.stability import cases, evaluate_case
from selfsup.estimate import EstimateOptions
from selfsup.refine import RefineOptions

CASES = list(cases(height=48, width=64))


@pytest.mark.parametrize("name, scene", CASES, ids=[name for name, _ in CASES])
def test_hard_case_gives_finite_lights_and_a_bounded_error(name, scene):
    options = EstimateOptions(method="cnn+refine", max_lights=1, refine=RefineOptions(max_iters=(10, 3)))
    row = evaluate_case(name, scene, options)
    assert row["converged"], row["note"]
    assert row["finite"] and row["lights_found"] == 1
    assert row["position_error"] < 0.25, row
