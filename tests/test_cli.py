"""The command line: a user's mistake is one line on stderr and exit status 2, no traceback."""

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
    (["mode=estimate", "estimate.inptu=x", "estimate.output=o.jsonl"], "estimate.inptu"),  # misspelled
    (["mode=estimate", "estimate.input=x"], "estimate.output is required"),  # missing
    (["mode=estimate", "estimate.input=/no/such/folder", "estimate.output=o.jsonl"], "does not exist"),  # no path
    (["mode=estimate", "estimate.input=.", "estimate.output=o.jsonl", "estimate.method=magic"], "estimate.method"),
    (["mode=teach"], "unknown mode 'teach'"),
])
def test_a_users_mistake_is_one_line_and_status_2(tmp_path, args, words):
    result = _train(*args, f"hydra.run.dir={tmp_path}/run")
    assert result.returncode == 2, result.stderr[-2000:]
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and words in lines[0] and "Traceback" not in result.stderr, result.stderr[-2000:]


def test_hydra_full_error_shows_the_traceback(tmp_path):
    result = _train("mode=teach", f"hydra.run.dir={tmp_path}/run", env={"HYDRA_FULL_ERROR": "1"})
    assert result.returncode != 0 and "Traceback" in result.stderr
