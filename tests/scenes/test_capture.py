"""Capture folders (colour, depth, intrinsics) read as scenes, and estimated by mode=estimate."""

import json
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from benchmarks.captures import make_capture, read_truth
from selfsup.estimation import EstimateOptions, RefineOptions, Tuning, estimate_files
from selfsup.estimation.inputs import estimate_inputs
from selfsup.scenes.capture import (ASSUMED_ALBEDO, capture_frames, color_and_depth_frame, frame_of_color,
                                    linear_to_srgb, read_capture, srgb_to_linear)
from selfsup.scenes.exact import render_spec
from selfsup.scenes.io import SceneFileError, write_scene
from selfsup.scenes.sampler import SamplerConfig, sample_scene

ROOT = Path(__file__).parents[2]
SMALL = SamplerConfig(height=48, width=64, specular_prob=0.0, n_lights_probs=(1.0,))
FAST = EstimateOptions(max_lights=1, tuning=Tuning(refine=RefineOptions(max_iters=(10, 3))))


def _capture(folder: Path, seeds=(3, 4)) -> list:
    """A capture folder of procedural scenes, by the benchmark's recipe (8-bit sRGB, mm depth)."""
    scenes = []
    for seed in seeds:
        scene = render_spec(sample_scene(seed, SMALL), samples=1).scene
        (folder / "scenes").mkdir(parents=True, exist_ok=True)
        write_scene(folder / "scenes" / f"{seed}.npz", scene)
        make_capture(folder / "scenes" / f"{seed}.npz", folder / "cap", f"frame_{seed:03d}")
        scenes.append(scene)
    return scenes


def test_a_capture_folders_normal_maps_are_read_on_the_depths_grid(tmp_path):
    (scene,) = _capture(tmp_path, seeds=(3,))
    (tmp_path / "cap" / "normals").mkdir()
    normals = 2.0 * scene.normals.numpy()  # not unit: made unit on reading
    normals[0, :5] = 0.0  # missing: taken from the depth there
    np.save(tmp_path / "cap" / "normals" / "frame_003.npy", normals)
    (frame,) = capture_frames(tmp_path / "cap")
    read = read_capture(frame)
    assert read.meta["normals"].endswith("frame_003.npy")
    torch.testing.assert_close(read.normals[1:], torch.nn.functional.normalize(scene.normals[1:], dim=-1))  # zeros stay
    assert bool((read.normals[0, :5] == 0).all())
    assert read_capture(frame_of_color(frame.color)).normals is not None  # a list's frame finds them too
    assert read_capture(color_and_depth_frame(frame.color, frame.depth)).normals is not None  # and one colour file's
    for bad, match in ((normals[:, :-1], "on the depth's grid"), (normals.astype(np.int32), "float array"),
                       (np.where(normals == 0, np.nan, normals), "NaN or inf")):
        np.save(tmp_path / "cap" / "normals" / "frame_003.npy", bad)
        with pytest.raises(SceneFileError, match=match):
            read_capture(frame)


def test_srgb_decoding_inverts_the_encoding_and_matches_the_standard():
    x = np.linspace(0, 1, 1001)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12)
    assert srgb_to_linear(np.array(0.5)) == pytest.approx(0.21404, abs=1e-5)  # the sRGB curve's mid grey
    assert srgb_to_linear(np.array(0.04045)) == pytest.approx(0.04045 / 12.92)


def test_a_capture_frame_reads_as_the_scene_it_was_made_from(tmp_path):
    (scene,) = _capture(tmp_path, seeds=(3,))
    (frame,) = capture_frames(tmp_path / "cap")
    read = read_capture(frame)
    truth = read_truth(tmp_path / "cap" / "truth" / "frame_003.npz")
    assert read.id == "frame_003" and read.normals is None and read.ambient is None and read.ks is None
    assert torch.equal(read.kd, torch.full_like(read.kd, ASSUMED_ALBEDO))
    valid = scene.depth > 0
    assert (read.depth[valid] - scene.depth[valid]).abs().max() <= 0.0005 + 1e-6  # millimetres, rounded
    torch.testing.assert_close(read.K, scene.K)
    # 8 bits of sRGB: the linear image times the exposure, within half a code step (clipped pixels aside).
    exposed = (scene.image * truth.meta["exposure"]).clamp(0, 1)
    step = torch.from_numpy(srgb_to_linear(np.clip(linear_to_srgb(exposed.double().numpy()) + 0.5 / 255, 0, 1))).float()
    assert bool(((read.image - exposed).abs() <= (step - exposed).abs() + 1e-6).all())


def test_intrinsics_per_frame_win_over_the_folder_and_the_override_over_both(tmp_path):
    _capture(tmp_path, seeds=(3,))
    cap = tmp_path / "cap"
    (cap / "intrinsics.json").write_text(json.dumps({"K": [[50, 0, 30], [0, 51, 20], [0, 0, 1]]}))
    assert read_capture(capture_frames(cap)[0]).K[0, 0] != 50  # the frame's own file
    (cap / "intrinsics" / "frame_003.json").unlink()
    K = read_capture(capture_frames(cap)[0]).K
    assert K[0, 0] == 50 and K[1, 1] == 51 and K[0, 2] == 30 and K[1, 2] == 20
    K = read_capture(capture_frames(cap, intrinsics=(60, 61, 31, 21))[0]).K
    assert K[0, 0] == 60 and K[1, 1] == 61 and K[0, 2] == 31 and K[1, 2] == 21


def test_float_depth_is_metres_and_16_bit_depth_follows_the_depth_scale(tmp_path):
    _capture(tmp_path, seeds=(3,))
    cap = tmp_path / "cap"
    millimetres = read_capture(capture_frames(cap)[0]).depth
    assert read_capture(capture_frames(cap, depth_scale=2000)[0]).depth.max() == pytest.approx(
        float(millimetres.max()) / 2, rel=1e-6)
    np.save(cap / "depth" / "frame_003.npy", millimetres.numpy())
    (cap / "depth" / "frame_003.png").unlink()
    torch.testing.assert_close(read_capture(capture_frames(cap)[0]).depth, millimetres)


def test_colour_larger_than_the_depth_is_area_averaged_onto_its_grid(tmp_path):
    _capture(tmp_path, seeds=(3,))
    cap = tmp_path / "cap"
    small = read_capture(capture_frames(cap)[0])
    color = iio.imread(cap / "color" / "frame_003.png")
    iio.imwrite(cap / "color" / "frame_003.png", np.repeat(np.repeat(color, 3, axis=0), 3, axis=1))  # 3x each way
    large = read_capture(capture_frames(cap)[0])
    assert large.image.shape == small.image.shape and large.meta["color_size"] == [192, 144]
    torch.testing.assert_close(large.image, small.image, atol=1e-6, rtol=1e-6)  # 3x3 equal pixels average to one
    torch.testing.assert_close(large.K, small.K)  # the depth image's intrinsics
    iio.imwrite(cap / "color" / "frame_003.png", np.repeat(color, 2, axis=0))  # 2:1 stretched: another aspect
    with pytest.raises(SceneFileError, match="differ in aspect"):
        read_capture(capture_frames(cap)[0])


@pytest.mark.parametrize("damage, words", [
    ("depth_8_bit", "depth is 8-bit"),
    ("depth_zero", "zero (missing) on every pixel"),
    ("no_depth", "no depth file of stem 'frame_004'"),
    ("no_intrinsics", "no intrinsics: write"),
    ("intrinsics_without_cy", "frame_004.json lacks cy: it must be JSON"),
    ("intrinsics_not_json", "frame_004.json must be JSON"),
    ("unreadable", "cannot read the image"),
])
def test_a_bad_frame_is_named_with_its_fix_and_the_others_are_estimated(tmp_path, damage, words):
    _capture(tmp_path)
    cap = tmp_path / "cap"
    if damage == "depth_8_bit":
        iio.imwrite(cap / "depth" / "frame_004.png", np.full((48, 64), 200, np.uint8))
    elif damage == "depth_zero":
        iio.imwrite(cap / "depth" / "frame_004.png", np.zeros((48, 64), np.uint16))
    elif damage == "no_depth":
        (cap / "depth" / "frame_004.png").unlink()
    elif damage == "no_intrinsics":
        (cap / "intrinsics" / "frame_004.json").unlink()
    elif damage == "intrinsics_without_cy":  # named by its file and key, not by the colour file and a KeyError
        (cap / "intrinsics" / "frame_004.json").write_text('{"fx": 50, "fy": 50, "cx": 32}')
    elif damage == "intrinsics_not_json":
        (cap / "intrinsics" / "frame_004.json").write_text("fx=50")
    else:
        (cap / "color" / "frame_004.png").write_bytes(b"not a png")
    summary = estimate_files(cap, tmp_path / "lights.jsonl", FAST, progress=False)
    assert summary["done"] == 1 and summary["failed"] == 1
    (reason,) = summary["failures"].values()
    assert words in reason and "\n" not in reason
    records = [json.loads(line) for line in (tmp_path / "lights.jsonl").read_text().splitlines()]
    assert [r["id"] for r in records] == ["frame_003"]


def test_the_command_estimates_a_capture_folder_and_exits_non_zero_when_a_frame_fails(tmp_path):
    _capture(tmp_path)
    cap = tmp_path / "cap"
    (cap / "notes.txt").write_text("other files are ignored")
    (cap / "depth" / "frame_004.png").unlink()
    result = subprocess.run([sys.executable, "train.py", "mode=estimate", f"estimate.input={cap}",
                             f"estimate.output={tmp_path}/o.jsonl", "estimate.max_lights=1", "estimate.progress=false",
                             "+estimate.tuning.refine.max_iters=[10,3]", f"hydra.run.dir={tmp_path}/run"],
                            capture_output=True, text=True, cwd=str(ROOT))
    assert result.returncode == 1, result.stderr[-2000:]
    assert "frame_004" in result.stdout + result.stderr
    (record,) = [json.loads(line) for line in (tmp_path / "o.jsonl").read_text().splitlines()]
    # accuracy: benchmarks/captures.py (this tiny frame's light is wrong, and the record says it is unsupported)
    assert record["id"] == "frame_003" and len(record["lights"] or record["unsupported_lights"]) == 1


def test_a_single_colour_file_takes_its_depth_from_estimate_depth(tmp_path):
    _capture(tmp_path, seeds=(3,))
    cap = tmp_path / "cap"
    color, depth = cap / "color" / "frame_003.png", cap / "depth" / "frame_003.png"
    (frame,) = estimate_inputs(color, depth)
    assert frame == color_and_depth_frame(color, depth) and frame.intrinsics_file == cap / "intrinsics" / "frame_003.json"
    with pytest.raises(ValueError, match="give its depth with estimate.depth"):
        estimate_inputs(color)
    with pytest.raises(FileNotFoundError, match="estimate.depth .* does not exist"):
        estimate_inputs(color, tmp_path / "none.png")
    (tmp_path / "notes.md").write_text("x")
    with pytest.raises(ValueError, match="is not a .npz scene file"):
        estimate_inputs(tmp_path / "notes.md")


def test_a_folder_of_capture_folders_names_them(tmp_path):
    _capture(tmp_path, seeds=(3,))
    with pytest.raises(FileNotFoundError, match="its sub-folders cap"):
        estimate_inputs(tmp_path)


def test_a_light_the_albedo_free_fit_pushes_towards_infinity_stays_within_reach(tmp_path):
    # This small capture's log shading is nearly that of a light at infinity: its fit crept
    # off to 1,800 scene sizes with an infinite uncertainty, which JSON cannot carry, and the
    # frame failed. Steps beyond RUNAWAY_SIZES scene sizes are not taken.
    from selfsup.estimation.solvers import RUNAWAY_SIZES

    _capture(tmp_path, seeds=(3,))
    summary = estimate_files(tmp_path / "cap", tmp_path / "o.jsonl", FAST, progress=False)
    assert summary["done"] == 1, summary["failures"]
    (record,) = [json.loads(line) for line in (tmp_path / "o.jsonl").read_text().splitlines()]
    truth = read_truth(tmp_path / "cap" / "truth" / "frame_003.npz")
    scene = read_capture(capture_frames(tmp_path / "cap")[0])
    points = scene.depth[scene.depth > 0]
    (light,) = record["lights"] or record["unsupported_lights"]  # a wrong light: the record does not present it
    position = torch.tensor(light["position"])
    assert float(position.norm()) < 2 * RUNAWAY_SIZES * float(truth.scene_scale) + float(points.max())
    assert all(np.isfinite(light["position_std"]))


def test_the_capture_benchmark_scores_the_covariance_of_the_placed_lights(tmp_path):
    from benchmarks.captures import score, summary

    _capture(tmp_path, seeds=(3, 4))
    cap = tmp_path / "cap"
    records = []
    for frame_id, offset, std in (("frame_003", 0.01, 0.01), ("frame_004", 0.01, 0.001)):  # 1 sigma; 10 sigma off
        truth = read_truth(cap / "truth" / f"{frame_id}.npz")
        size = float(truth.scene_scale)
        position = truth.light_pos[0].double() + torch.tensor([offset * size, 0.0, 0.0], dtype=torch.float64)
        cov = (torch.eye(3, dtype=torch.float64) * (std * size) ** 2).tolist()
        records.append({"id": frame_id, "lights": [{"position": position.tolist(), "intensity": [1.0, 1.0, 1.0],
                                                    "position_cov": cov}], "seconds": 0.1})
    estimates = tmp_path / "o.jsonl"
    estimates.write_text("".join(json.dumps(r) + "\n" for r in records))
    rows = score(cap, estimates)
    assert [(r["placed"], r["placed_inside"], r["inside"]) for r in rows] == [(1, 1, 1), (1, 0, 0)]
    row = summary("cap", "direct", rows, 2, 1.0)
    assert row["two_sigma_coverage"] == row["placed_two_sigma_coverage"] == "1/2 (50%)"


def test_hostile_frames_beside_a_good_one_are_each_named_and_the_good_one_estimated(tmp_path):
    # A 2x2 frame raised IndexError from the noise level's median, which no handler took:
    # the command died with a traceback and the good frame beside it got no record.
    _capture(tmp_path, seeds=(3,))
    cap = tmp_path / "cap"
    rng = np.random.default_rng(0)
    hostile = {"tiny": (2, 2), "one": (1, 1), "lone": (48, 64), "nan": (48, 64)}
    for name, (h, w) in hostile.items():
        iio.imwrite(cap / "color" / f"{name}.png", rng.integers(40, 200, (h, w, 3)).astype(np.uint8))
        if name == "nan":
            np.save(cap / "depth" / f"{name}.npy", np.full((h, w), np.nan, np.float32))
            continue
        depth = np.full((h, w), 2000, np.uint16) + np.arange(w, dtype=np.uint16)
        if name == "lone":  # one valid pixel: no normal from the depth
            depth = np.zeros((h, w), np.uint16)
            depth[24, 32] = 2000
        iio.imwrite(cap / "depth" / f"{name}.png", depth)
        (cap / "intrinsics" / f"{name}.json").write_text('{"fx": 50, "fy": 50, "cx": 1, "cy": 1}')
    (cap / "intrinsics" / "nan.json").write_text('{"fx": 50, "fy": 50, "cx": 32, "cy": 24}')
    # A phone's 8000x6000 colour beside its 256x192 depth: a good frame, estimated on the
    # depth's grid (read in bands: 0.8 GB peak for the whole command, 5.1 GB when decoded at once).
    iio.imwrite(cap / "color" / "huge.png", np.tile(rng.integers(40, 200, (6000, 1, 3), dtype=np.uint8), (1, 8000, 1)))
    iio.imwrite(cap / "depth" / "huge.png", np.full((192, 256), 2000, np.uint16) + np.arange(256, dtype=np.uint16))
    (cap / "intrinsics" / "huge.json").write_text('{"fx": 200, "fy": 200, "cx": 128, "cy": 96}')
    for batch in (1, 6):  # alone, and in one batch retried frame by frame
        summary = estimate_files(cap, tmp_path / "o.jsonl", FAST, progress=False, batch=batch, workers=1,
                                 overwrite=True)
        assert summary["done"] == 2 and summary["failed"] == 4, summary["failures"]
        assert all(name in " ".join(summary["failures"]) for name in hostile)
        assert all("\n" not in reason for reason in summary["failures"].values())
        records = [json.loads(line) for line in (tmp_path / "o.jsonl").read_text().splitlines()]
        assert [record["id"] for record in records] == ["frame_003", "huge"]
    (huge,) = [frame for frame in capture_frames(cap) if frame.id == "huge"]
    assert read_capture(huge).image.shape[:2] == (192, 256)


def test_a_larger_colour_resampled_in_bands_is_the_whole_images_area_average():
    from selfsup.scenes.capture import RESAMPLE_ROWS, _area_resample, _area_weights

    rng = np.random.default_rng(1)
    codes = rng.integers(0, 256, (300, 400, 3), dtype=np.uint8)
    table = srgb_to_linear(np.arange(256) / 255.0)
    height, width = 3 * RESAMPLE_ROWS + 5, 52  # bands that end mid-pixel of the source
    whole = np.einsum("ih,hwc,jw->ijc", _area_weights(300, height), table[codes], _area_weights(400, width))
    np.testing.assert_allclose(_area_resample(codes, table, height, width), whole, rtol=1e-12, atol=1e-15)
