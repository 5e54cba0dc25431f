"""The shipped example capture (examples/capture) runs through the README's quick start."""

import json
from pathlib import Path

import torch

from benchmarks.captures import read_truth
from selfsup.estimation import EstimateOptions, estimate_files
from selfsup.insert import insert_files

EXAMPLE = Path(__file__).parents[1] / "examples" / "capture"


def test_the_example_capture_is_estimated_and_an_object_inserted(tmp_path):
    summary = estimate_files(EXAMPLE, tmp_path / "lights.jsonl", EstimateOptions(), progress=False)
    assert summary["done"] == 3 and summary["failed"] == 0
    records = [json.loads(line) for line in (tmp_path / "lights.jsonl").read_text().splitlines()]
    assert [r["id"] for r in records] == ["room_00", "room_01", "room_02"]
    truth = read_truth(EXAMPLE / "truth" / "room_00.npz")  # a one-light room: found where it is
    error = (torch.tensor(records[0]["lights"][0]["position"]) - truth.light_pos[0]).norm() / truth.scene_scale
    assert float(error) < 0.05
    picture = insert_files(str(EXAMPLE / "color" / "room_00.png"), str(tmp_path / "insert.png"),
                           estimates=str(tmp_path / "lights.jsonl"))
    assert Path(picture).stat().st_size > 1000
