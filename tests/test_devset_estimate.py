"""The estimation command on the shared devset (scenes of an independent renderer), where present."""

from pathlib import Path

import pytest

from benchmarks.devset_estimate import score
from selfsup.estimate import EstimateOptions, estimate_files

DEVSET = Path(__file__).resolve().parents[2] / "shared" / "devset"


@pytest.mark.skipif(not DEVSET.exists(), reason="shared/devset not present")
@pytest.mark.parametrize("name", ["direct", "gi", "noisy"])
def test_every_devset_light_is_found_within_the_success_radius(name, tmp_path):
    # Direct light, interreflections with an unknown ambient, sensor depth and image
    # noise: every light within 5% of the scene size and the right count (2026-11-23:
    # worst lights 0.0045, 0.017 and 0.0086; before that day's changes noisy 030 missed).
    output = tmp_path / "lights.jsonl"
    summary = estimate_files(DEVSET / name, output, EstimateOptions(), progress=False)
    assert summary["done"] == 6 and not summary["failed"], summary
    rows = score(DEVSET / name, output)
    assert len(rows) == 6
    for row in rows:
        assert row["success"] and row["found"] == row["true"], row
