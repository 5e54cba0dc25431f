"""mode=scan: posed frames in (three layouts), one set of world-frame lights out."""

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from benchmarks.captures import write_capture
from selfsup.metrics import SUCCESS_THRESHOLD
from selfsup.scan import FuseOptions, WorldLight, fuse, keyframes, scan_files
from selfsup.scenes.poses import PoseError, PosedFrame, check_pose, posed_frames, quaternion_pose
from selfsup.scenes.sampler import SamplerConfig
from selfsup.scenes.sequences import render_orbit

SMALL = SamplerConfig(height=96, width=128, specular_prob=0.0)
FRAMES = 6


@pytest.fixture(scope="module")
def orbit():
    return render_orbit(31, frames=FRAMES, swing_deg=25.0, config=SMALL)


def _write_posed(orbit, folder):
    scenes, poses, _ = orbit
    for scene in scenes:
        write_capture(scene, folder, scene.id, exposure=1.0)
    (folder / "poses.json").write_text(json.dumps({s.id: p.tolist() for s, p in zip(scenes, poses)}))
    return folder


def test_a_scan_finds_the_rooms_light_in_the_world_and_each_frame_sees_it_in_its_camera(orbit, tmp_path):
    scenes, poses, truth = orbit
    folder = _write_posed(orbit, tmp_path / "cap")
    summary = scan_files(folder, tmp_path / "room.json", tmp_path / "frames.jsonl", progress=False)
    room = json.loads((tmp_path / "room.json").read_text())
    assert summary["lights"] == len(room["lights"]) == 1 and summary["failed"] == 0
    size = float(scenes[0].scene_scale)
    error = np.linalg.norm(np.array(room["lights"][0]["position"]) - truth[0].numpy()) / size
    assert error < SUCCESS_THRESHOLD, error
    assert room["frames"] == FRAMES and room["lights"][0]["support"] >= 0.5
    records = [json.loads(line) for line in (tmp_path / "frames.jsonl").read_text().splitlines()]
    assert [r["id"] for r in records] == [s.id for s in scenes]
    for record, scene, pose in zip(records, scenes, poses):  # the world light in each camera: where it is there
        camera = np.array(record["lights"][0]["position"])
        back = pose[:3, :3].numpy() @ camera + pose[:3, 3].numpy()
        np.testing.assert_allclose(back, room["lights"][0]["position"], atol=1e-6)
        assert all(v > 0 for v in record["lights"][0]["intensity"])


def test_the_scan_command_writes_its_object_and_names_a_frame_without_a_pose(orbit, tmp_path):
    import subprocess
    import sys

    folder = _write_posed(orbit, tmp_path / "cap")
    poses = json.loads((folder / "poses.json").read_text())
    del poses[orbit[0][2].id]
    (folder / "poses.json").write_text(json.dumps(poses))
    done = subprocess.run([sys.executable, "train.py", "mode=scan", f"scan.input={folder}",
                           f"scan.output={tmp_path / 'room.json'}", "scan.progress=false"],
                          capture_output=True, text=True, cwd=Path(__file__).parents[2])
    assert done.returncode == 2 and "1 frame(s) without a pose (orbit_31_002)" in done.stderr, done.stderr[-2000:]


def test_poses_that_are_not_rigid_camera_to_world_are_named():
    pose = np.eye(4)
    assert check_pose(pose, "f").shape == (4, 4)
    with pytest.raises(PoseError, match="f: a pose must be a 4x4"):
        check_pose(np.eye(3), "f")
    with pytest.raises(PoseError, match="not a rotation"):
        check_pose(np.diag([2.0, 1, 1, 1]), "f")
    with pytest.raises(PoseError, match="determinant -1, a mirror"):
        check_pose(np.diag([1.0, -1, 1, 1]), "f")
    with pytest.raises(PoseError, match="last row"):
        check_pose(np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]), "f")
    with pytest.raises(PoseError, match="unit length"):
        quaternion_pose(0, 0, 0, 0, 0, 0, 2, name="f")
    turn = quaternion_pose(1, 2, 3, 0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4), name="f")  # 90 degrees about z
    np.testing.assert_allclose(turn[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(turn[:3, 3], [1, 2, 3])


def test_tum_and_seven_scenes_layouts_read_as_posed_frames(orbit, tmp_path):
    scenes, poses, _ = orbit
    cap = _write_posed(orbit, tmp_path / "cap")
    # TUM: rgb/ and depth/ by timestamps, depth 5000 a metre, poses as quaternions in time.
    tum = tmp_path / "tum"
    (tum / "rgb").mkdir(parents=True)
    (tum / "depth").mkdir()
    rgb, depth, truth = [], [], []
    for k, (scene, pose) in enumerate(zip(scenes, poses)):
        t = 100.0 + k / 30
        (tum / "rgb" / f"{t:.6f}.png").write_bytes((cap / "color" / f"{scene.id}.png").read_bytes())
        millimetres = iio.imread(cap / "depth" / f"{scene.id}.png").astype(np.float64)
        iio.imwrite(tum / "depth" / f"{t + 0.005:.6f}.png", np.round(millimetres * 5).astype(np.uint16))
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth.append(f"{t + 0.005:.6f} depth/{t + 0.005:.6f}.png")
        q = _quaternion(pose[:3, :3].numpy())
        truth.append(f"{t - 0.003:.6f} " + " ".join(f"{v:.9f}" for v in [*pose[:3, 3].tolist(), *q]))
    for name, lines in (("rgb.txt", rgb), ("depth.txt", depth), ("groundtruth.txt", truth)):
        (tum / name).write_text("# comment\n" + "\n".join(lines) + "\n")
    (tum / "intrinsics.json").write_text((cap / "intrinsics" / f"{scenes[0].id}.json").read_text())
    frames = posed_frames(tum)
    assert len(frames) == FRAMES
    np.testing.assert_allclose(frames[2].pose, poses[2].numpy(), atol=1e-6)
    from selfsup.scenes.capture import read_capture
    np.testing.assert_allclose(read_capture(frames[2].frame).depth.numpy(),
                               read_capture(posed_frames(cap)[2].frame).depth.numpy(), atol=1e-6)
    # 7-Scenes: frame-NNNNNN.color.png, .depth.png (65535: missing), .pose.txt.
    seven = tmp_path / "seven"
    seven.mkdir()
    for k, (scene, pose) in enumerate(zip(scenes, poses)):
        (seven / f"frame-{k:06d}.color.png").write_bytes((cap / "color" / f"{scene.id}.png").read_bytes())
        millimetres = iio.imread(cap / "depth" / f"{scene.id}.png")
        iio.imwrite(seven / f"frame-{k:06d}.depth.png", np.where(millimetres == 0, 65535, millimetres).astype(np.uint16))
        np.savetxt(seven / f"frame-{k:06d}.pose.txt", pose.numpy())
    (seven / "intrinsics.json").write_text((cap / "intrinsics" / f"{scenes[0].id}.json").read_text())
    frames = posed_frames(seven)
    assert [f.id for f in frames] == [f"frame-{k:06d}" for k in range(FRAMES)]
    depth = read_capture(frames[1].frame).depth.numpy()
    np.testing.assert_allclose(depth, read_capture(posed_frames(cap)[1].frame).depth.numpy(), atol=1e-6)
    with pytest.raises(FileNotFoundError, match="no posed frames"):
        posed_frames(tmp_path / "cap" / "color")


def _quaternion(R):
    # (qx, qy, qz, qw) of a rotation matrix, from its largest diagonal term (any turn).
    trace = np.trace(R)
    if trace > max(R[0, 0], R[1, 1], R[2, 2]):
        w = np.sqrt(1 + trace) / 2
        return [(R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w), w]
    i = int(np.argmax(np.diag(R)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = np.sqrt(1 + R[i, i] - R[j, j] - R[k, k]) * 2
    q = [0.0, 0.0, 0.0, (R[k, j] - R[j, k]) / s]
    q[i], q[j], q[k] = s / 4, (R[j, i] + R[i, j]) / s, (R[k, i] + R[i, k]) / s
    return q


def test_fusion_keeps_lights_many_views_agree_on_and_leaves_one_views_invention_out():
    def light(p, frame, share=0.9, sigma=0.01):
        return WorldLight(np.array(p, dtype=float), np.eye(3) * sigma**2, share, np.ones(3), frame)

    frames = [[light([1.0, 0.01 * k, 2.0], k)] for k in range(6)]
    frames[3].append(light([-1.0, 0.0, 1.0], 3, share=0.2))  # one frame's second light
    fused = fuse(frames, size=4.0, options=FuseOptions())
    assert len(fused) == 1 and fused[0].support == 1.0
    np.testing.assert_allclose(fused[0].position, [1.0, 0.025, 2.0], atol=1e-9)
    assert np.all(np.diag(fused[0].cov) > 0)
    with pytest.raises(ValueError, match="scan.fuse.min_support"):
        FuseOptions(min_support=0)


def test_keyframes_cover_the_views_first():
    def frame(angle):
        pose = np.eye(4)
        pose[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
        return PosedFrame(None, pose)

    frames = [frame(a) for a in np.linspace(0, 1.0, 11)]
    assert keyframes(frames, 3) == [0, 5, 10] and keyframes(frames, 0) == list(range(11))
    assert keyframes(frames, 20) == list(range(11))


def test_tracking_a_posed_scan_keeps_a_still_light_still_in_the_world(orbit, tmp_path):
    from selfsup.tracking import track_files

    scenes, poses, truth = orbit
    folder = _write_posed(orbit, tmp_path / "cap")
    summary = track_files(folder, tmp_path / "track.jsonl", refresh=0, progress=False)
    assert summary["done"] == FRAMES
    records = [json.loads(line) for line in (tmp_path / "track.jsonl").read_text().splitlines()]
    size = float(scenes[0].scene_scale)
    for record, pose in zip(records, poses):
        (light,) = record["lights"]
        world = np.array(light["world_position"])
        assert np.linalg.norm(world - truth[0].numpy()) / size < SUCCESS_THRESHOLD, (record["frame"], record["reason"])
        np.testing.assert_allclose(pose[:3, :3].numpy() @ light["position"] + pose[:3, 3].numpy(), world, atol=1e-9)
    assert [r["reason"] for r in records].count(None) >= FRAMES - 2  # warm frames: the camera's move is not the light's


def test_a_stray_scanner_export_reads_as_posed_frames(orbit, tmp_path):
    # rgb.mp4 at twice the depth's size with the video's intrinsics, depth/ and confidence/
    # (0 low, 2 high), odometry.csv with ARKit's camera axes (y up, z backwards).
    av = pytest.importorskip("av")  # the video extra
    from selfsup.scenes.capture import read_capture
    from selfsup.scenes.poses import ARKIT_TO_OPENCV

    scenes, poses, _ = orbit
    cap = _write_posed(orbit, tmp_path / "cap")
    stray = tmp_path / "stray"
    (stray / "depth").mkdir(parents=True)
    (stray / "confidence").mkdir()
    height, width = scenes[0].depth.shape
    with av.open(str(stray / "rgb.mp4"), mode="w") as video:
        stream = video.add_stream("mpeg4", rate=30)
        stream.width, stream.height, stream.pix_fmt = 2 * width, 2 * height, "yuv420p"
        stream.bit_rate = 20_000_000  # a phone records at about this rate
        for k, scene in enumerate(scenes):
            colour = iio.imread(cap / "color" / f"{scene.id}.png")
            big = np.repeat(np.repeat(colour, 2, axis=0), 2, axis=1)
            for packet in stream.encode(av.VideoFrame.from_ndarray(big, format="rgb24")):
                video.mux(packet)
            millimetres = iio.imread(cap / "depth" / f"{scene.id}.png")
            iio.imwrite(stray / "depth" / f"{k:06d}.png", millimetres)
            confidence = np.full(millimetres.shape, 2, np.uint8)
            confidence[:4] = 0  # the top rows' depth of low confidence: left out
            iio.imwrite(stray / "confidence" / f"{k:06d}.png", confidence)
        for packet in stream.encode():
            video.mux(packet)
    K = json.loads((cap / "intrinsics" / f"{scenes[0].id}.json").read_text())
    video_K = [[K["fx"] * 2, 0, (K["cx"] + 0.5) * 2 - 0.5], [0, K["fy"] * 2, (K["cy"] + 0.5) * 2 - 0.5], [0, 0, 1]]
    np.savetxt(stray / "camera_matrix.csv", np.array(video_K), delimiter=",")
    rows = ["timestamp, frame, x, y, z, qx, qy, qz, qw"]
    for k, pose in enumerate(poses):
        q = _quaternion(pose[:3, :3].numpy() @ ARKIT_TO_OPENCV)
        rows.append(", ".join(str(v) for v in [k / 30, k, *pose[:3, 3].tolist(), *q]))
    (stray / "odometry.csv").write_text("\n".join(rows) + "\n")
    frames = posed_frames(stray)
    assert [f.id for f in frames] == [f"{k:06d}" for k in range(FRAMES)]
    np.testing.assert_allclose(frames[3].pose, poses[3].numpy(), atol=1e-6)
    for k in (1, 4, 2):  # forward, then back (the video is opened again)
        read, same = read_capture(frames[k].frame), read_capture(posed_frames(cap)[k].frame)
        np.testing.assert_allclose(read.K.numpy(), same.K.numpy(), atol=1e-4)
        assert (read.depth[:4] == 0).all() and torch.equal(read.depth[4:], same.depth[4:])
        assert float((read.image - same.image).abs().mean()) < 0.02  # the video's compression


@pytest.mark.parametrize("written, named", [
    (lambda pose: np.linalg.inv(pose), "world-to-camera"),
    (lambda pose: pose @ np.diag([1.0, -1.0, -1.0, 1.0]), "OpenGL camera axes"),
])
def test_poses_in_another_convention_are_named_by_how_the_depths_disagree(orbit, tmp_path, written, named):
    # The frames' depths, each seen from the next under the poses: 98% agree with the right
    # poses, 30-56% with inverted or OpenGL ones (the error says which convention agrees).
    scenes, poses, _ = orbit
    folder = _write_posed(orbit, tmp_path / "cap")
    (folder / "poses.json").write_text(json.dumps({s.id: written(p.numpy()).tolist() for s, p in zip(scenes, poses)}))
    with pytest.raises(PoseError, match=f"the poses look like {named}.*agree on 9[0-9]% of their points that way"):
        scan_files(folder, tmp_path / "room.json", progress=False)


def test_a_light_hung_behind_the_camera_stays_out_of_view_in_every_frame_of_an_orbit():
    from selfsup.scenes.sampler import sample_scene, signed_distance
    from selfsup.scenes.sequences import light_behind_camera, orbited

    spec = sample_scene(4100, SMALL, n_lights=2)
    behind = light_behind_camera(spec, margin=SMALL.light_margin)
    moved, kept = behind.light_position[0].double(), behind.light_position[1]
    assert torch.equal(kept, spec.light_position[1])  # the other light where it was
    up = spec.prims.planes[0, 3:6].double()
    assert moved[2] < 0 and float(moved @ up) > 0  # behind the camera and above it
    assert float(signed_distance(behind.prims, behind.light_position[:1])) > SMALL.light_margin
    # As bright where the camera stands: the power scaled by the squared distance to it.
    before = spec.light_relative_intensity[0].double() / spec.light_position[0].double().norm() ** 2
    after = behind.light_relative_intensity[0].double() / moved.norm() ** 2
    torch.testing.assert_close(after, before, rtol=1e-5, atol=0)
    for angle in (-30.0, 0.0, 30.0):  # behind every turned camera of render_orbit's scans
        assert float(orbited(behind, angle).light_position[0, 2]) < 0
    assert light_behind_camera(spec, margin=100.0) is None  # no such place clear of the surfaces
