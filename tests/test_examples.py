"""The shipped examples (examples/capture, examples/sequence) run through the README's quick start and Tracker snippet."""

import json
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir

from benchmarks.captures import read_truth
from selfsup.estimation import EstimateOptions, estimate_files
from selfsup.insert import insert_files

EXAMPLE = Path(__file__).parents[1] / "examples" / "capture"
CONFIGS = Path(__file__).parents[1] / "configs"


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


def test_the_fast_preset_changes_its_three_constants_and_places_the_example_rooms_lights(tmp_path):
    # estimate=fast (configs/estimate/fast.yaml) is the default group with three tuned constants
    # changed; run as the command reads it, it places the two one-light rooms as the default does.
    from train import estimate_settings

    overrides = ["estimate=fast", f"estimate.input={EXAMPLE}", f"estimate.output={tmp_path / 'lights.jsonl'}",
                 "estimate.progress=false"]
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        options, io = estimate_settings(compose(config_name="train", overrides=overrides).estimate)
    assert options.changed_settings() == {"cnn_start": "settled", "albedo_free_gloss": "never", "vignetting": "none"}
    summary = estimate_files(options=options, **io)  # as mode=estimate runs it
    assert summary["done"] == 3 and summary["failed"] == 0
    records = {r["id"]: r for r in map(json.loads, (tmp_path / "lights.jsonl").read_text().splitlines())}
    for room in ("room_00", "room_01"):  # one light each
        truth = read_truth(EXAMPLE / "truth" / f"{room}.npz")
        assert len(records[room]["lights"]) == 1
        error = (torch.tensor(records[room]["lights"][0]["position"]) - truth.light_pos[0]).norm() / truth.scene_scale
        assert float(error) < 0.05, (room, float(error))


def test_the_example_sequence_is_tracked_where_its_light_moves():
    # The README's Tracker snippet runs on examples/sequence: one room, one light moving
    # along a half circle (examples/capture is three unrelated rooms, no video).
    from selfsup.tracking import Tracker

    sequence = EXAMPLE.parent / "sequence"
    tracker = Tracker()
    frames = sorted((sequence / "color").glob("*.png"))
    assert len(frames) == 6
    for frame in frames:
        record = tracker.update(frame)
        truth = read_truth(sequence / "truth" / f"{frame.stem}.npz")
        (light,) = record["lights"]
        error = (torch.tensor(light["position"]) - truth.light_pos[0]).norm() / truth.scene_scale
        assert float(error) < 0.05, (frame.stem, float(error))


def test_the_estimation_figure_shows_each_stage_of_the_example_room():
    # benchmarks/estimation_figure.py (docs/estimation.md's figure): every panel the image's
    # size, segments merged into fewer classes, a finite residual on the segments' pixels,
    # and the answer drawn within a few pixels of the true light.
    from benchmarks.estimation_figure import DEFAULT_FRAME, stages

    panels = stages(DEFAULT_FRAME)
    height, width = panels["shading"].shape
    assert all(panels[name].shape[:2] == (height, width) for name in ("colour", "normals", "segments", "residual"))
    assert 1 < panels["classes"].max() < panels["segments"].max()
    assert 0.5 < float(np.isfinite(panels["residual"]).mean()) < 1.0
    assert panels["found"] and len(panels["answer"]) == len(panels["truth"]) == 1
    assert float(np.linalg.norm(panels["answer"][0] - panels["truth"][0])) < 5.0
