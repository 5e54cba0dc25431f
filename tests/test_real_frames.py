"""The real-frames plausibility report's judgements (benchmarks/real_frames.py), on made-up records."""

import json

import numpy as np
import pytest

from benchmarks.real_frames import _spread, min_chroma, summarise, up_in_camera


def test_up_follows_the_gravity_file_through_each_pose_else_the_cameras_minus_y(tmp_path):
    assert np.allclose(up_in_camera(tmp_path, "a"), [0, -1, 0])
    # A camera rolled 90 degrees about its optical axis: the room's up (world -z gravity's
    # opposite) is the camera's +x.
    roll = np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]], dtype=float)
    (tmp_path / "poses.json").write_text(json.dumps({"a": roll.tolist()}))
    (tmp_path / "gravity.json").write_text(json.dumps({"gravity_world": [0, 0, -9.8]}))
    up = up_in_camera(tmp_path, "a")
    assert np.allclose(roll[:3, :3] @ up, [0, 0, 1])


def test_a_light_fixed_in_the_world_has_no_spread_and_the_glued_baseline_follows_the_camera():
    light_world = np.array([0.5, -2.0, 3.0])
    rows = []
    for k in range(5):
        pose = np.eye(4)
        pose[:3, 3] = [0.2 * k, 0, 0]  # the camera walks along x
        position = light_world - pose[:3, 3]
        rows.append({"light_found": True, "share": 0.5, "min_chroma": 1.0, "height": 2.0, "distance": 3.0,
                     "position": position.tolist(), "pose": pose.tolist(), "world": light_world.tolist()})
    summary = summarise("walk", rows, wall=1.0)
    assert summary["world_spread_m"] == 0.0 and summary["glued_spread_m"] == pytest.approx(0.2)
    assert summary["share_ge_0.1"] == "5/5 (100%)" and summary["seconds_per_frame"] == 0.2
    rows[0]["light_found"] = False  # shares and heights count the frames with a light
    assert summarise("walk", rows, wall=1.0)["height_ge_0.3m"] == "4/4 (100%)"
    assert _spread(np.zeros((3, 3))) == 0.0


def test_the_weakest_channel_counts_the_ambient_unless_it_is_black():
    assert min_chroma({"lights": [{"intensity": [0.83, 0.0, 0.0]}], "ambient": [0.1, 0.1, 0.1]}) == 0.0
    assert min_chroma({"lights": [{"intensity": [1.0, 0.5, 0.5]}], "ambient": [0.0, 0.0, 0.0]}) == 0.5
