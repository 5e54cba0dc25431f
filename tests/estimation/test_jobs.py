"""Estimation at dataset scale: reruns resume, shards and ranks cover the input once, kills lose nothing."""

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from selfsup.estimation.files import estimate_files
from selfsup.estimation.inputs import count_inputs, item_id, iter_inputs, parse_shard, sharded
from selfsup.estimation.jobs import OutputInUseError, completed_ids, locked, merge_parts
from tests.scenes.test_capture import FAST, _capture

ROOT = Path(__file__).resolve().parents[2]
SEEDS = (3, 4, 5, 6, 7)
TIMING = ("seconds", "batch_size")


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("jobs")
    _capture(folder, seeds=SEEDS)
    return folder / "cap"


def _records(path: Path) -> list[dict]:
    return [{k: v for k, v in json.loads(line).items() if k not in TIMING} for line in path.read_text().splitlines()]


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    # Records compared to the last bit are made on one thread, as each of two ranks on two
    # cores (and each worker process) makes them: a sum split over threads rounds differently.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def reference(capture, tmp_path_factory, one_thread) -> list[dict]:
    # One process, one run: what every other way of running must write, to the last bit.
    output = tmp_path_factory.mktemp("reference") / "lights.jsonl"
    summary = estimate_files(capture, output, FAST, progress=False, workers=1)
    assert summary["done"] == len(SEEDS)
    return _records(output)


def test_a_rerun_appends_only_the_frames_not_in_the_output(capture, reference, tmp_path):
    output = tmp_path / "lights.jsonl"
    lines = [json.dumps(record) for record in reference]
    # Two complete records, then a third cut off mid-write by a kill.
    output.write_text(lines[0] + "\n" + lines[1] + "\n" + lines[2][: len(lines[2]) // 2])
    summary = estimate_files(capture, output, FAST, progress=False, workers=1)
    assert summary["skipped"] == 2 and summary["done"] == len(SEEDS) - 2
    assert _records(output) == reference  # the torn line dropped and redone, nothing twice
    again = estimate_files(capture, output, FAST, progress=False, workers=1)
    assert again["skipped"] == len(SEEDS) and again["done"] == 0 and _records(output) == reference
    fresh = estimate_files(capture, output, FAST, progress=False, workers=1, overwrite=True)
    assert fresh["skipped"] == 0 and fresh["done"] == len(SEEDS) and _records(output) == reference


def test_an_output_that_is_not_ours_is_refused_not_appended_to(capture, tmp_path):
    output = tmp_path / "notes.jsonl"
    output.write_text("a line of someone's notes\n{\"id\": \"x\"}\n")
    with pytest.raises(ValueError, match="line 1 is not a record of ours.*estimate.overwrite=true"):
        estimate_files(capture, output, FAST, progress=False)
    assert completed_ids(tmp_path / "absent.jsonl") == set()


def test_a_second_run_on_an_output_being_written_is_refused(capture, tmp_path):
    # A rank of a killed torchrun job still running (torchrun starts its workers in their own
    # sessions: killing the job's group leaves them) would write its frames twice beside a rerun.
    output = tmp_path / "lights.jsonl"
    with locked(output):
        with pytest.raises(OutputInUseError, match="being written by another process"):
            estimate_files(capture, output, FAST, progress=False)
    assert estimate_files(capture, output, FAST, progress=False, workers=1)["done"] == len(SEEDS)


def test_shards_cover_the_input_exactly_once_and_bad_shards_are_named(capture, reference, tmp_path):
    ids = [item_id(item) for item in iter_inputs(capture)]
    parts = [[item_id(item) for item in sharded(iter_inputs(capture), k, 3)] for k in range(3)]
    assert sorted(sum(parts, [])) == sorted(ids) and parts[1] == ids[1::3]
    written = []
    for k in range(2):
        estimate_files(capture, tmp_path / f"part{k}.jsonl", FAST, progress=False, workers=1, shard=f"{k}/2")
        written += _records(tmp_path / f"part{k}.jsonl")
    assert sorted(written, key=lambda r: r["id"]) == reference
    assert parse_shard(None) == (0, 1) and parse_shard("2/5") == (2, 5)
    for bad in ("5/5", "-1/3", "1/0", "a/b", "3"):
        with pytest.raises(ValueError, match="estimate.shard"):
            parse_shard(bad)


def test_a_list_of_frames_is_read_line_by_line_and_a_bad_line_is_that_frames_error(capture, reference, tmp_path):
    frames = sorted((capture / "color").iterdir())
    listing = tmp_path / "frames.txt"
    lines = ["# my frames", str(frames[0]), "", os.path.relpath(frames[1], tmp_path), "missing/color/x.png",
             str(capture / "depth" / "frame_003.png"), "notes.md"]
    listing.write_text("\n".join(lines) + "\n")
    assert count_inputs(listing) == 5
    summary = estimate_files(listing, tmp_path / "o.jsonl", FAST, progress=False, workers=1)
    assert summary["done"] == 2 and summary["failed"] == 3, summary["failures"]
    assert _records(tmp_path / "o.jsonl") == reference[:2]
    reasons = " | ".join(f"{name}: {reason}" for name, reason in summary["failures"].items())
    assert "missing/color/x.png" in reasons and "notes.md" in reasons and "not a colour image" in reasons


def test_merging_the_parts_restores_the_inputs_order_and_keeps_what_it_cannot_place(tmp_path):
    def write(path, ids):
        path.write_text("".join(json.dumps({"id": i}) + "\n" for i in ids))

    output = tmp_path / "o.jsonl"
    write(output, ["a"])  # an earlier run's record
    write(tmp_path / "r0.jsonl", ["c", "e", "stray"])  # rank 0: positions 0, 2, 4 ("e" failed? no: "g" did)
    write(tmp_path / "r1.jsonl", ["b", "f"])  # rank 1: positions 1, 3, 5 ("d" failed)
    order = [("a", 0), ("b", 1), ("c", 0), ("d", 1), ("e", 0), ("f", 1)]
    assert merge_parts(output, [tmp_path / "r0.jsonl", tmp_path / "r1.jsonl"], iter(order)) == 6
    assert [json.loads(line)["id"] for line in output.read_text().splitlines()] == ["a", "b", "c", "e", "f", "stray"]


ONE_THREAD = {**os.environ, "OMP_NUM_THREADS": "1"}  # as the reference (torchrun sets it for its ranks)


def _command(capture: Path, output: Path, *extra: str) -> list[str]:
    return ["train.py", "mode=estimate", f"estimate.input={capture}", f"estimate.output={output}",
            "estimate.max_lights=1", "estimate.workers=1", "estimate.progress=false",
            "+estimate.tuning.refine.max_iters=[10,3]", f"hydra.run.dir={output.parent / 'run'}", *extra]


def test_two_torchrun_ranks_write_what_one_process_writes(capture, reference, tmp_path):
    output = tmp_path / "lights.jsonl"
    done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                           *_command(capture, output)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert _records(output) == reference and not (tmp_path / "lights.jsonl.parts").exists()


COPIES = 4  # the kill test's folder: each frame four times over, long enough a run to kill in its middle


@pytest.fixture(scope="module")
def longer(capture, tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("longer")
    for sub in ("color", "depth", "intrinsics"):
        (folder / sub).mkdir()
        for path in sorted((capture / sub).iterdir()):
            for copy in range(COPIES):
                shutil.copy(path, folder / sub / f"{path.stem}_{copy}{path.suffix}")
    return folder


def test_a_run_killed_at_random_points_and_rerun_loses_and_duplicates_nothing(longer, tmp_path):
    frames = len(SEEDS) * COPIES
    expected = tmp_path / "uninterrupted.jsonl"
    subprocess.run([sys.executable, *_command(longer, expected)], cwd=ROOT, env=ONE_THREAD, check=True,
                   capture_output=True, timeout=600)
    output = tmp_path / "lights.jsonl"
    seed = int(os.environ.get("KILL_SEED", time.time_ns() % 10_000))  # KILL_SEED=... repeats a run
    draw, left = random.Random(seed), []
    for _ in range(2):
        run = subprocess.Popen([sys.executable, *_command(longer, output)], cwd=ROOT, env=ONE_THREAD,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline, after = time.monotonic() + 300, draw.randint(0, frames - 4)  # kill after this many records
        while run.poll() is None and time.monotonic() < deadline:
            if output.exists() and output.read_bytes().count(b"\n") >= after:
                time.sleep(draw.uniform(0, 0.3))
                run.send_signal(signal.SIGKILL)
                break
            time.sleep(0.02)
        run.wait(timeout=60)
        left.append(output.read_bytes().count(b"\n") if output.exists() else 0)
    assert min(left) < frames, f"no kill came before the end (KILL_SEED={seed}): {left}"
    subprocess.run([sys.executable, *_command(longer, output)], cwd=ROOT, env=ONE_THREAD, check=True,
                   capture_output=True, timeout=600)
    assert _records(output) == _records(expected), f"KILL_SEED={seed}"  # every frame once, in order
