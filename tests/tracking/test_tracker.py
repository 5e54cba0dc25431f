"""The tracker: a full estimate first, warm steps after, a full estimate again when the lights change."""

import json
import math

import numpy as np
import pytest
import torch

from selfsup.estimation import EstimateOptions
from selfsup.scenes.degrade import Degradations
from selfsup.scenes.io import write_scene
from selfsup.scenes.sampler import SamplerConfig
from selfsup.scenes.sequences import render_sequence, write_sequence
from selfsup.tracking import Tracker, TrackTuning, natural_order, track_files

SMALL = SamplerConfig(height=60, width=80)


def _worst_error(record: dict, scene) -> float:
    found = torch.tensor([light["position"] for light in record["lights"]], dtype=torch.float64).reshape(-1, 3)
    if found.shape[0] == 0:
        return math.inf
    return float(torch.cdist(scene.light_pos.double(), found).amin(1).max()) / float(scene.scene_scale)


@pytest.fixture(scope="module")
def switch_frames():
    return render_sequence("switch", 21, frames=9, config=SMALL)


def test_the_first_frame_is_estimated_in_full_and_still_frames_warm(switch_frames):
    tracker = Tracker()
    records = [tracker.update(scene) for scene in switch_frames[:3]]
    assert [r["reason"] for r in records] == ["first", None, None]
    assert [r["full"] for r in records] == [True, False, False]
    for index, (record, scene) in enumerate(zip(records, switch_frames)):
        assert _worst_error(record, scene) < 0.02
        assert record["latency_ms"] > 0 and record["frame"] == index
    assert records[1]["lights"][0]["track"] == records[0]["lights"][0]["track"] == 0
    cov = np.array(records[2]["lights"][0]["position_cov"])
    assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)


def test_a_light_switched_on_then_off_is_counted_within_a_frame(switch_frames):
    tracker = Tracker()
    records = [tracker.update(scene) for scene in switch_frames]
    truth = [s.light_pos.shape[0] for s in switch_frames]
    assert truth == [1, 1, 1, 2, 2, 2, 1, 1, 1]
    assert [len(r["lights"]) for r in records] == truth
    assert records[3]["full"] and records[6]["full"]  # the evidence sent both switches to a full estimate
    assert not any(r["full"] for r in records[4:6] + records[7:])
    first_track = records[0]["lights"][0]["track"]
    assert first_track in [light["track"] for light in records[4]["lights"]]  # the still light kept its track


def test_frames_without_albedo_are_tracked_albedo_free():
    frames = render_sequence("moving_light", 22, frames=8, config=SMALL, degradations=Degradations(reflectance="half"))
    tracker = Tracker()
    records = [tracker.update(scene) for scene in frames]
    assert all(r["reflectance"] == "albedo_free" for r in records)
    assert not any(r["full"] for r in records[1:])
    for light in [light for r in records for light in r["lights"]]:  # warm frames in the image's white too
        assert max(light["intensity"]) - min(light["intensity"]) <= 1e-5 * max(light["intensity"])
    assert max(_worst_error(r, s) for r, s in zip(records, frames)) < 0.05


def test_warm_steps_without_albedo_fit_on_albedo_classes_as_full_estimates_do():
    # The warm steps' segments are merged into albedo classes under the tracked lights
    # (estimate.tuning.albedo_class_rounds > 0), as the full estimate's are; not with 0.
    frames = render_sequence("moving_light", 22, frames=2, config=SMALL, degradations=Degradations(reflectance="half"))
    counts = {}
    for rounds in (0, 1):
        tracker = Tracker(options=EstimateOptions().tuned(albedo_class_rounds=rounds))
        for scene in frames:
            tracker.update(scene)
        counts[rounds] = int(tracker._geometry.labels.max())
    assert counts[1] < counts[0], counts


def test_refresh_estimates_every_nth_frame_in_full(switch_frames):
    tracker = Tracker(refresh=2)
    reasons = [tracker.update(scene)["reason"] for scene in switch_frames[:3]]
    assert reasons == ["first", None, "refresh"]  # the second frame after the full one is the refresh


def test_reset_forgets_the_lights(switch_frames):
    tracker = Tracker()
    tracker.update(switch_frames[0])
    assert tracker.lights.shape == (1, 3)
    tracker.reset()
    assert tracker.lights.shape == (0, 3)
    assert tracker.update(switch_frames[1])["full"]


@pytest.mark.parametrize("kwargs, words", [
    (dict(warm_iterations=0), "warm_iterations must be an integer >= 1"),
    (dict(jump_ratio=float("nan")), "jump_ratio must be a finite number > 0"),
    (dict(warm_residuals="edges"), "warm_residuals must be one of"),
])
def test_bad_tuning_is_named(kwargs, words):
    with pytest.raises(ValueError, match=words):
        TrackTuning(**kwargs)


def test_a_bad_refresh_is_named():
    with pytest.raises(ValueError, match="track.refresh must be an integer >= 0"):
        Tracker(refresh=-1)


def test_natural_order_puts_frame_9_before_frame_10():
    assert natural_order(["frame_10.png", "frame_9.png", "frame_1.png"]) == ["frame_1.png", "frame_9.png",
                                                                          "frame_10.png"]


def test_track_files_skips_a_bad_frame_and_writes_the_others(tmp_path, switch_frames):
    folder = tmp_path / "seq"
    write_sequence(switch_frames[:3], folder)
    (folder / "frame_001.npz").write_bytes(b"not a scene")
    output = tmp_path / "track.jsonl"
    summary = track_files(folder, output, EstimateOptions(), progress=False)
    assert summary["done"] == 2 and summary["failed"] == 1 and "frame_001.npz" in next(iter(summary["failures"]))
    records = [json.loads(line) for line in output.read_text().splitlines()]
    assert [r["id"] for r in records] == [switch_frames[0].id, switch_frames[2].id]
    assert [r["frame"] for r in records] == [0, 1]


def test_track_files_leaves_no_output_when_every_frame_fails(tmp_path):
    folder = tmp_path / "bad"
    folder.mkdir()
    (folder / "frame_000.npz").write_bytes(b"nope")
    output = tmp_path / "track.jsonl"
    summary = track_files(folder, output, progress=False)
    assert summary["done"] == 0 and summary["output"] is None and not output.exists()


def test_a_dark_frame_is_named(tmp_path, switch_frames):
    dark = switch_frames[0]
    dark = type(dark)(**{**dark.__dict__, "image": torch.zeros_like(dark.image)})
    write_scene(tmp_path / "dark.npz", dark)
    with pytest.raises(ValueError, match="zero on every valid pixel"):
        Tracker().update(tmp_path / "dark.npz")


def test_a_frame_with_nan_pixels_is_named_and_the_tracker_goes_on(switch_frames):
    tracker = Tracker()
    tracker.update(switch_frames[0])
    bad = type(switch_frames[1])(**{**switch_frames[1].__dict__, "image": switch_frames[1].image.clone()})
    bad.image[5:9, 5:9] = float("nan")
    with pytest.raises(ValueError, match="image holds 48 non-finite values"):
        tracker.update(bad)
    record = tracker.update(switch_frames[2])
    assert record["reason"] is None and _worst_error(record, switch_frames[2]) < 0.02


def test_a_smaller_frame_mid_sequence_is_tracked_on_its_own_grid(switch_frames):
    tracker = Tracker()
    tracker.update(switch_frames[0])
    record = tracker.update(switch_frames[1].subsampled(2))
    assert record["lights"] and _worst_error(record, switch_frames[1]) < 0.02


def test_frames_no_light_explains_are_tracked_without_lights_and_estimated_afresh(switch_frames):
    # A frame lit by ambient light alone has no light in its record (light_found false): the
    # tracker keeps none and estimates the next frame in full (it crashed on the empty record).
    import dataclasses

    scene = switch_frames[0]
    albedo = 0.2 + 0.6 * torch.rand(scene.image.shape[:2], generator=torch.Generator().manual_seed(0))[..., None]
    flat = dataclasses.replace(scene, image=torch.where(scene.depth[..., None] > 0, albedo.expand(-1, -1, 3) * 0.3, 0.0),
                               kd=torch.where(scene.depth[..., None] > 0, torch.full_like(scene.kd, 0.5), 0.0),
                               ks=None, ambient=None)
    tracker = Tracker(EstimateOptions(max_lights=1))
    records = [tracker.update(flat), tracker.update(flat)]
    assert [r["lights"] for r in records] == [[], []]
    assert [r["reason"] for r in records] == ["first", "share"] and all(r["full"] for r in records)


def test_a_rerun_tracks_on_from_the_last_full_estimate_and_keeps_the_frames_before(tmp_path, switch_frames):
    folder = tmp_path / "seq"
    write_sequence(switch_frames[:5], folder)
    output = tmp_path / "track.jsonl"
    assert track_files(folder, output, refresh=2, progress=False)["done"] == 5
    whole = output.read_text().splitlines()
    full = [json.loads(line)["full"] for line in whole]
    last_full = max(k for k in range(4) if full[k])
    assert full[0] and 0 < last_full < 4  # the first frame and a refresh (or a change) before the cut
    # A kill after the fourth record, in the middle of writing the fifth.
    output.write_text("\n".join(whole[:4]) + "\n" + whole[4][:20])
    summary = track_files(folder, output, refresh=2, progress=False)
    assert summary["skipped"] == last_full and summary["done"] == 5 - last_full  # tracked on from that full estimate
    again = output.read_text().splitlines()
    assert again[:last_full] == whole[:last_full]
    assert [(r["id"], r["frame"]) for r in map(json.loads, again)] == [(s.id, k) for k, s in enumerate(switch_frames[:5])]
    assert track_files(folder, output, refresh=2, progress=False, overwrite=True)["skipped"] == 0


def test_a_cut_to_another_room_is_estimated_in_full_not_warm_started():
    # examples/capture holds three unrelated rooms: frames 2-3 were warm-started from the room
    # before and came out 0.33 of the scene wrong with no warning; a cut is estimated afresh,
    # as mode=estimate estimates each frame.
    from pathlib import Path

    from selfsup.estimation import estimate_scene
    from selfsup.scenes.capture import capture_frames, read_capture

    frames = capture_frames(Path(__file__).parents[2] / "examples" / "capture")
    tracker = Tracker()
    records = [tracker.update(frame) for frame in frames]
    assert [(r["full"], r["reason"]) for r in records] == [(True, "first"), (True, "cut"), (True, "cut")]
    for record, frame in zip(records[1:], frames[1:]):
        alone = estimate_scene(read_capture(frame), EstimateOptions())
        found = torch.tensor([light["position"] for light in record["lights"]])
        np.testing.assert_allclose(found, [light["position"] for light in alone["lights"]], atol=1e-4)
