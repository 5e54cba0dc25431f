"""The estimation command on the shared devset (scenes of an independent renderer), where present."""

from pathlib import Path

import pytest

from benchmarks.devset_estimate import run

DEVSET = Path(__file__).resolve().parents[2] / "shared" / "devset"


@pytest.mark.skipif(not DEVSET.exists(), reason="shared/devset not present")
@pytest.mark.parametrize("name", ["direct", "gi", "noisy"])
def test_every_devset_light_is_found_within_the_success_radius(name):
    # Direct light, interreflections with an unknown ambient, sensor depth and image
    # noise: every light within 5% of the scene size and the right count (2026-11-23:
    # worst lights 0.0045, 0.017 and 0.0086; before that day's changes noisy 030 missed).
    rows, path = run(DEVSET, [name], write=False)
    assert path is None
    scenes, summary = rows[:-1], rows[-1]
    assert len(scenes) == 6 and summary["success"] == "6/6" and summary["found"] == 6, summary
    for row in scenes:
        assert row["success"] and row["found"] == row["true"], row
