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


def test_a_set_with_true_directions_is_scored_by_angle_beside_the_lambertian_baseline(tmp_path):
    from benchmarks.real_frames import summarise, truth_angles
    from selfsup.scenes.camera import CameraModel, camera_capture, write_capture_frame
    from selfsup.scenes.exact import render_spec
    from selfsup.scenes.studio import sphere_centre, studio_spec

    direction = np.array([0.3, -0.5, -0.81]) / np.linalg.norm([0.3, -0.5, -0.81])
    spec = studio_spec(tuple(direction), others=False, ks=0.0)
    rendered = render_spec(spec).scene
    camera = CameraModel(key=None, white_balance=False, vignetting=0.0, jpeg_quality=None, misregistration_px=0.0,
                         disparity_step=0.0, depth_bumps=0.0, edge_holes=0.0, random_holes=0.0)
    for frame_id in ("a", "b"):
        write_capture_frame(tmp_path, frame_id, camera_capture(rendered.image, rendered.depth, rendered.K, camera, 0,
                                                               exposure=1.0))
    centre = sphere_centre(spec).double().numpy()
    (tmp_path / "truth.json").write_text(json.dumps({"centre": centre.tolist(), "frames": {
        "a": {"direction": direction.tolist()}, "b": {"direction": direction.tolist()}}}))
    along = {"position": (centre + 5 * direction).tolist(), "intensity": [1.0, 1.0, 1.0]}
    dim = {"position": (centre + np.array([3.0, 0, 0])).tolist(), "intensity": [0.01, 0.01, 0.01]}
    rows = [{"id": "a", "light_found": True, "record": {"lights": [dim, along]}, "min_chroma": 1.0, "share": 0.9,
             "height": 1.0, "distance": 5.0},
            {"id": "b", "light_found": False, "record": {"lights": []}, "min_chroma": 1.0}]
    truth_angles(tmp_path, rows)
    assert rows[0]["angle"] == pytest.approx(0.0, abs=1e-3) and rows[1]["angle"] == 90.0  # no light: 90 degrees
    assert rows[0]["lambert_angle"] < 5.0  # the baseline on a matte sphere (a lamp 20 radii away, not a direction)
    assert summarise("ball", rows, wall=1.0)["median_angle_deg"] == 45.0
