"""The command line: a user's mistake is one line on stderr and exit status 2, no traceback."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]


def _train(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "train.py", *args], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, **(env or {})}, timeout=300)


@pytest.mark.parametrize("args, words", [
    # misspelled: the group's settings named, the nearest first (Hydra's "+estimate.inptu" led nowhere)
    (["mode=estimate", "estimate.inptu=x", "estimate.output=o.jsonl"], "did you mean estimate.input? its settings are"),
    (["mode=estimate", "estimate.tunin.x=3", "estimate.output=o.jsonl"], "+estimate.tuning.NAME=VALUE"),
    (["mode=estimate", "estimate.input=x"], "estimate.output is required"),  # missing
    (["mode=estimate", "estimate.input=/no/such/folder", "estimate.output=o.jsonl"], "does not exist"),  # no path
    (["mode=estimate", "estimate.input=.", "estimate.output=o.jsonl", "estimate.method=magic"], "estimate.method"),
    (["mode=teach"], "unknown mode 'teach'"),
    (["mode=track", "track.inptu=x", "track.output=o.jsonl"], "track.inptu is not a setting of track: did you mean"),
    (["mode=track", "track.input=/no/such/folder", "track.output=o.jsonl"],
     "track.input /no/such/folder does not exist"),
    (["mode=track", "track.input=.", "track.output=o.jsonl", "+track.tuning.warm_iterations=0"],
     "warm_iterations must be"),
])
def test_a_users_mistake_is_one_line_and_status_2(tmp_path, args, words):
    result = _train(*args, f"hydra.run.dir={tmp_path}/run")
    assert result.returncode == 2, result.stderr[-2000:]
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and words in lines[0] and "Traceback" not in result.stderr, result.stderr[-2000:]


def test_hydra_full_error_shows_the_traceback(tmp_path):
    result = _train("mode=teach", f"hydra.run.dir={tmp_path}/run", env={"HYDRA_FULL_ERROR": "1"})
    assert result.returncode != 0 and "Traceback" in result.stderr


def test_estimate_writes_what_was_asked_and_no_run_folder(tmp_path):
    # Only training makes outputs/<date>/<time>/; mode=estimate leaves the output file alone,
    # no temporary run folder behind (each run left a /tmp/shadowlight-estimate-* before) and
    # its log on stderr, where the progress bar is (stdout stays empty for `> file`).
    work, temporary = tmp_path / "work", tmp_path / "tmp"
    work.mkdir(), temporary.mkdir()
    result = subprocess.run([sys.executable, str(ROOT / "train.py"), "mode=estimate",
                             f"estimate.input={ROOT / 'examples' / 'capture'}", "estimate.output=lights.jsonl",
                             "estimate.progress=false"], capture_output=True, text=True, cwd=work, timeout=300,
                            env={**os.environ, "TMPDIR": str(temporary)})
    assert result.returncode == 0, result.stderr[-2000:]
    assert sorted(p.name for p in work.iterdir()) == ["lights.jsonl"]
    assert list(temporary.glob("shadowlight-*")) == []
    assert result.stdout == "" and "estimated 3 scene(s)" in result.stderr


def test_training_ends_with_a_human_summary():
    sys.path.insert(0, str(ROOT))
    from train import training_summary

    line = training_summary({"step": 900, "minutes": 2.7, "best": "outputs/x/best.pt",
                             "validation": {"scenes": 150, "median_position_error": 0.02767, "median_angular_error": 2.84,
                                            "success_rate": 0.5933, "count_accuracy": 0.7133}})
    assert line == ("trained 900 steps in 2.7 min; validation on 150 scenes: median position error 0.028 of the scene "
                    "size, median angle 2.8 degrees, success 59%, right light count 71%; best checkpoint "
                    "outputs/x/best.pt")
    stopped = training_summary({"step": 400, "minutes": 5.0, "best": "b.pt", "max_steps": 900, "max_minutes": 5,
                                "stopped_by_time": True, "validation": {}})
    assert stopped.startswith("trained 400 of 900 steps (stopped by trainer.max_minutes=5) in 5.0 min")


def test_track_writes_a_record_per_frame(tmp_path):
    # mode=track on the example captures: one JSON line per frame, in the frames' order.
    result = subprocess.run([sys.executable, str(ROOT / "train.py"), "mode=track",
                             f"track.input={ROOT / 'examples' / 'capture'}", "track.output=track.jsonl",
                             "track.progress=false"], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["track.jsonl"]
    records = [json.loads(line) for line in (tmp_path / "track.jsonl").read_text().splitlines()]
    assert [r["id"] for r in records] == ["room_00", "room_01", "room_02"]
    assert records[0]["reason"] == "first" and all(r["lights"] for r in records)
