"""mode=adapt end to end: capture folders in, an adapted checkpoint out that estimate and track take; resume; bad frames."""

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from selfsup.adapt import FrameOptions, collate_frames, load_frames
from selfsup.checkpoint import LIGHTNET_CHECKPOINT, load_checkpoint, load_network
from tests.test_readme import ROOT
from train import run

EXAMPLE = ROOT / "examples" / "capture"
SMALL = ["adapt.batch=2", "adapt.val_every=1", "adapt.procedural.scenes=8", "adapt.procedural_batch=2",
         "adapt.validation_scenes=4", "adapt.progress=false", "adapt.device=cpu"]


def _cfg(*overrides):
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "configs")):
        return compose(config_name="train", overrides=["mode=adapt", *SMALL, *overrides])


def _captures(tmp_path: Path) -> Path:
    """examples/capture twice over (six frames) and three frames that cannot be used."""
    folder = tmp_path / "captures"
    for sub in ("color", "depth", "intrinsics"):
        shutil.copytree(EXAMPLE / sub, folder / sub, dirs_exist_ok=True)
        for path in (EXAMPLE / sub).iterdir():
            shutil.copy(path, folder / sub / f"again_{path.name}")
    color = iio.imread(EXAMPLE / "color" / "room_00.png")
    depth = iio.imread(EXAMPLE / "depth" / "room_00.png")
    iio.imwrite(folder / "color" / "z_no_depth.png", color)
    iio.imwrite(folder / "depth" / "z_no_depth.png", np.zeros_like(depth))
    iio.imwrite(folder / "color" / "z_black.png", np.zeros_like(color))
    iio.imwrite(folder / "depth" / "z_black.png", depth)
    iio.imwrite(folder / "color" / "z_no_depth_file.png", color)
    for name in ("z_no_depth", "z_black", "z_no_depth_file"):
        shutil.copy(EXAMPLE / "intrinsics" / "room_00.json", folder / "intrinsics" / f"{name}.json")
    return folder


def _estimate_and_track(tmp_path: Path, checkpoint: Path):
    """mode=estimate (the network alone) and mode=track on examples/capture with ``checkpoint``."""
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "configs")):
        estimate = compose(config_name="train", overrides=[
            "mode=estimate", f"estimate.input={EXAMPLE}", f"estimate.output={tmp_path / 'lights.jsonl'}",
            f"estimate.checkpoint={checkpoint}", "estimate.method=cnn", "estimate.progress=false", "estimate.workers=1"])
        track = compose(config_name="train", overrides=[
            "mode=track", f"track.input={EXAMPLE}", f"track.output={tmp_path / 'track.jsonl'}",
            f"track.checkpoint={checkpoint}", "track.progress=false"])
    return estimate, track


def test_unusable_frames_are_named_and_skipped_and_the_rest_split(tmp_path):
    frames = load_frames([_captures(tmp_path)], FrameOptions(holdout=0.5, block=2))
    assert sorted(Path(name).stem for name in frames.skipped) == ["z_black", "z_no_depth", "z_no_depth_file"]
    assert all(reason for reason in frames.skipped.values())
    assert len(frames.train) + len(frames.held) == 6 and frames.held and frames.train
    held = {frame.id for frame in frames.held}
    assert held == {"again_room_02", "room_00"}  # every second block of two, in name order
    batch = collate_frames(frames.train[:2])
    assert batch.network_image.shape == (2, 3, 120, 160) and batch.image.shape == (2, 3, 60, 80)  # loss_stride 2
    labels, count = batch.segments
    assert labels.shape == (2, 60 * 80) and int(labels.max()) == count


def test_too_few_usable_frames_is_a_clear_error(tmp_path):
    folder = tmp_path / "one"
    for sub in ("color", "depth", "intrinsics"):
        (folder / sub).mkdir(parents=True)
        name = "room_00.json" if sub == "intrinsics" else "room_00.png"
        shutil.copy(EXAMPLE / sub / name, folder / sub / name)
    with pytest.raises(ValueError, match="at least 2"):
        load_frames([folder], FrameOptions())


def test_adapt_writes_a_checkpoint_that_estimate_and_track_take_and_resumes(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    folder = _captures(tmp_path)
    out = tmp_path / "adapted.pt"
    command = [sys.executable, str(ROOT / "train.py"), "mode=adapt", *SMALL, f"adapt.input={folder}",
               f"adapt.out={out}", "adapt.steps=4", f"hydra.run.dir={tmp_path / 'hydra'}"]
    # A run killed after its first validation, then the same command again: it goes on from last.pt.
    started = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    last = Path(f"{out}.run") / "last.pt"
    deadline = time.monotonic() + 240
    while not last.is_file() and started.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    started.kill()
    started.wait()
    assert last.is_file()
    killed_at = load_checkpoint(last)
    assert 1 <= killed_at["step"] <= 4
    resumed = run(_cfg(f"adapt.input={folder}", f"adapt.out={out}", "adapt.steps=4"))
    assert resumed["frames"] + resumed["held"] == 6 and len(resumed["skipped"]) == 3 and resumed["steps"] == 4
    assert resumed["before"] == killed_at["start"] and "held-back loss" in resumed["line"]
    network, state = load_network(out)
    assert state["adapted_from"] == "shipped" and "held_loss" in state["metrics"]
    from benchmarks.adapt import _earlier_adaptation  # the benchmark scores an adaptation it did not run
    from benchmarks.adapt import run as adapt_benchmark
    kept_step = state["metrics"]["step"]  # the best held-back loss's step: 4 or one before it
    assert 1 <= kept_step <= 4
    assert _earlier_adaptation(out).startswith(f"the weights of adaptation step {kept_step} from shipped: held-back loss")
    with pytest.raises(SystemExit, match="not written by mode=adapt"):
        _earlier_adaptation(LIGHTNET_CHECKPOINT)
    with pytest.raises(SystemExit, match="do not apply"):  # refused before anything runs
        adapt_benchmark(tmp_path, out, ["adapt.steps=4"], adapted=True)
    assert load_checkpoint(last)["step"] == 4
    teacher = [json.loads(line) for line in (Path(f"{out}.run") / "teacher.jsonl").read_text().splitlines()]
    assert len(teacher) == 6 and len({record["id"] for record in teacher}) == 6  # searched once, kept for the resume
    with pytest.raises(ValueError, match="same steps"):
        run(_cfg(f"adapt.input={folder}", f"adapt.out={out}", "adapt.steps=5"))
    events = EventAccumulator(str(Path(f"{out}.run") / "tensorboard"))
    events.Reload()
    assert "adapt/user" in events.Tags()["scalars"] and "held/held_loss" in events.Tags()["scalars"]
    assert any(tag.startswith("held/before") for tag in events.Tags()["images"])
    assert any(tag.startswith("held/after") for tag in events.Tags()["images"])
    estimate, track = _estimate_and_track(tmp_path, out)
    assert run(estimate)["failed"] == 0
    assert len((tmp_path / "lights.jsonl").read_text().splitlines()) == 3
    assert not run(track)["failed"]
    records = [json.loads(line) for line in (tmp_path / "track.jsonl").read_text().splitlines()]
    assert len(records) == 3 and all(r["lights"] for r in records)


def test_bad_settings_are_named(tmp_path):
    folder = tmp_path / "none"
    folder.mkdir()
    with pytest.raises(ValueError, match=r"\.pt checkpoint"):
        run(_cfg(f"adapt.input={EXAMPLE}", f"adapt.out={tmp_path / 'adapted.txt'}"))
    with pytest.raises(FileNotFoundError, match="no .npz scene files or capture folder"):
        run(_cfg(f"adapt.input={folder}", f"adapt.out={tmp_path / 'a.pt'}"))
    with pytest.raises(ValueError, match="adapt.frames.holdout"):
        run(_cfg(f"adapt.input={EXAMPLE}", f"adapt.out={tmp_path / 'a.pt'}", "adapt.frames.holdout=1.5"))
    with pytest.raises(ValueError, match="adapt.resume"):
        run(_cfg(f"adapt.input={EXAMPLE}", f"adapt.out={tmp_path / 'a.pt'}", "adapt.resume=maybe"))


def test_the_iterative_network_adapts_and_its_checkpoint_estimates(tmp_path):
    # A small iterative network through mode=adapt: its own losses at every step (the albedo-free
    # re-render and the search's lights on the frames, its recipe's on prepared procedural scenes).
    from selfsup.checkpoint import save_network
    from selfsup.network import IterativeLightNet

    small = dict(long_side=16, widths=[8, 8], global_width=8, update_width=8, steps=1)
    start = save_network(tmp_path / "iterative.pt", IterativeLightNet(**small), {"architecture": "iterative", **small})
    out = tmp_path / "adapted.pt"
    summary = run(_cfg(f"adapt.input={EXAMPLE}", f"adapt.out={out}", f"adapt.checkpoint={start}", "adapt.steps=2",
                       "adapt.tensorboard=false"))
    assert summary["steps"] == 2 and "held-back loss" in summary["line"]
    network, state = load_network(out)
    assert isinstance(network, IterativeLightNet) and state["adapted_from"] == str(start)
    estimate, track = _estimate_and_track(tmp_path, out)
    assert run(estimate)["failed"] == 0
    assert not run(track)["failed"]
    assert len((tmp_path / "track.jsonl").read_text().splitlines()) == 3


def test_the_search_is_kept_and_read_back_not_run_again(tmp_path, monkeypatch):
    import selfsup.estimation.files
    from selfsup.adapt import teach

    frames = load_frames([EXAMPLE], FrameOptions())
    everything = frames.train + frames.held
    cache = tmp_path / "teacher.jsonl"
    assert teach(everything, None, cache) == 3
    found = {frame.id: frame.teacher.clone() for frame in everything}
    truth = {path.stem: np.load(path)["light_pos"] for path in (EXAMPLE / "truth").glob("*.npz")}
    for frame_id, lights in found.items():  # what the search finds are the example rooms' lights
        assert len(lights) >= 1
        assert np.linalg.norm(lights[:, None].numpy() - truth[frame_id][None], axis=-1).min(1).max() < 0.3
    cache.write_text(cache.read_text() + '{"id": "torn')  # a killed run's last line

    def never(*args, **kwargs):
        raise AssertionError("searched again")

    monkeypatch.setattr(selfsup.estimation.files, "estimate_items", never)
    assert teach(everything, None, cache) == 3
    assert all(torch.equal(frame.teacher, found[frame.id]) for frame in everything)


def test_a_collapsed_checkpoint_is_refused_and_the_start_kept(tmp_path, monkeypatch, caplog):
    import selfsup.adapt.loop as loop

    real = loop._Run.validate
    calls = []

    def collapsing(self):  # the start as measured, then every slot on and a light in a wall
        values, grid = real(self)
        calls.append(values)
        if len(calls) > 1:
            values = dict(values, held_loss=0.0, mean_count=values["mean_count"] + 2.0, degenerate_share=1.0)
        return values, grid

    monkeypatch.setattr(loop._Run, "validate", collapsing)
    out = tmp_path / "adapted.pt"
    result = run(_cfg(f"adapt.input={EXAMPLE}", f"adapt.out={out}", "adapt.steps=2", "adapt.tensorboard=false",
                      "adapt.teacher.position=0", "adapt.teacher.anchors=0"))
    assert len(calls) == 3 and result["accepted_step"] == 0 and "no step beat the start" in result["line"]
    assert "slots switched on" in caplog.text and "in or behind surfaces" in caplog.text
    adapted, shipped = load_network(out)[0], load_network(LIGHTNET_CHECKPOINT)[0]  # what mode=adapt starts from
    assert all(torch.equal(a, b) for a, b in zip(adapted.state_dict().values(), shipped.state_dict().values()))
