"""``mode=estimate`` on a directory of scene files: seconds per scene against error
(issue 5: ``cnn+refine`` at most 0.25 s per scene on the 2-core CPU).

Writes the fixed-seed procedural sets of ``benchmarks.estimate_procedural`` (160x120)
as scene files into one directory, then times :func:`selfsup.estimation.estimate_files`,
the command's own code, over it: reading the files, the estimation, the covariances
and the JSON lines, and the workers' start when there are several (``start``: a
forked worker starts at once, a spawned one imports torch and loads the network).
``seconds_per_scene`` is that wall time over the scenes; ``median_latency`` is the
median of the records' own ``seconds`` (one scene's time in its process, its share
of a batch's). Each row is one run of the whole directory; the rows of one
invocation take turns (``--rounds``), so that a machine's drift reaches every row alike.

    python -m benchmarks.estimate_files_speed --scenes 16 --workers 1 2 --batch 1 4

Results: benchmarks/results/estimate_files_speed_<device>_<date>.{md,json}.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import torch

from benchmarks.common import write_results
from benchmarks.estimate_procedural import SETS, score, set_scene
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.files import estimate_files, usable_cores
from selfsup.scenes.io import write_scene

COLUMNS = ["workers", "start", "batch", "scenes", "rounds", "seconds_per_scene", "range_seconds_per_scene",
           "median_latency", "median_position_error", "success_rate", "count_accuracy"]


def write_sets(folder: Path, sets: list[str], count: int, seed: int) -> dict[str, object]:
    """``count`` scenes of each set as ``<folder>/<set index>_<scene index>.npz``; returns
    the scenes by the id written into their files."""
    scenes = {}
    for s, name in enumerate(sets):
        if name not in SETS:
            raise ValueError(f"unknown set {name!r}; sets: {list(SETS)}")
        for index in range(count):
            scene = set_scene(name, index, seed)
            scene_id = f"{s}_{index:03d}"
            scene.meta["id"] = scene_id
            write_scene(folder / f"{scene_id}.npz", scene)
            scenes[scene_id] = scene
    return scenes


def measure(folder: Path, scenes: dict, workers: int, batch: int, options: EstimateOptions) -> dict:
    """One run of ``estimate_files`` over ``folder``: wall seconds per scene, latency, errors."""
    with tempfile.TemporaryDirectory() as out:
        output = Path(out) / "lights.jsonl"
        started = time.perf_counter()
        summary = estimate_files(folder, output, options, progress=False, batch=batch, workers=workers)
        wall = time.perf_counter() - started
        records = [json.loads(line) for line in output.read_text().splitlines()]
    if summary["failed"]:
        raise RuntimeError(f"{summary['failed']} file(s) failed: {summary['failures']}")
    scored = [score(record, scenes[record["id"]]) for record in records]
    # How the workers started (selfsup.estimation.start_method): a spawned one imports for seconds.
    return {"workers": summary["workers"], "start": summary["start"] or "-", "batch": batch, "scenes": len(records), "seconds_per_scene": wall / len(records),
            "median_latency": statistics.median(r["seconds"] for r in records),
            "median_position_error": round(statistics.median(s[0] for s in scored), 4),
            "success_rate": round(sum(s[1] for s in scored) / len(scored), 3),
            "count_accuracy": round(sum(s[2] for s in scored) / len(scored), 3)}


def run(scenes: int = 16, workers: tuple[int, ...] = (1, 2), batches: tuple[int, ...] = (1,), seed: int = 9100,
        sets: tuple[str, ...] | None = None, rounds: int = 2, write: bool = True,
        options: EstimateOptions | None = None):
    options = options or EstimateOptions()
    sets = list(sets or SETS)
    with tempfile.TemporaryDirectory() as folder:
        started = time.perf_counter()
        truth = write_sets(Path(folder), sets, scenes, seed)
        print(f"wrote {len(truth)} scene files in {time.perf_counter() - started:.1f} s", flush=True)
        runs: dict[tuple[int, int], list[dict]] = {}  # by (workers asked, batch)
        for _ in range(rounds):
            for w in workers:
                for batch in batches:
                    row = measure(Path(folder), truth, w, batch, options)
                    runs.setdefault((w, batch), []).append(row)
                    print({k: round(v, 3) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
    rows = []
    for (w, batch), measured in runs.items():
        # The answers do not depend on the round: the errors are the first run's.
        rows.append({**measured[0], "rounds": len(measured),
                     "seconds_per_scene": round(statistics.median(r["seconds_per_scene"] for r in measured), 3),
                     "range_seconds_per_scene": "{:.3f}-{:.3f}".format(min(r["seconds_per_scene"] for r in measured),
                                                                      max(r["seconds_per_scene"] for r in measured)),
                     "median_latency": round(statistics.median(r["median_latency"] for r in measured), 3)})
    path = None
    if write:
        header = (f"{scenes} scenes of each of {len(sets)} sets ({', '.join(sets)}; seeds {seed}*1000003+i as "
                  f"estimate_procedural), 160x120, written as scene files into one directory; "
                  f"selfsup.estimation.estimate_files (mode=estimate) with estimate.method={options.method} and defaults "
                  f"otherwise, on {usable_cores()} usable cores. seconds_per_scene: the run's wall time (workers' start "
                  "included) over the scenes, median (and range) of `rounds` runs taken in turn with the other rows; median_latency: "
                  "median of the records' `seconds` (a scene's time in its process). Errors as in estimate_procedural "
                  "(worst light per scene, of the scene size; success: every light < 0.05).")
        path = write_results("estimate_files_speed", torch.device("cpu"), rows, header, COLUMNS)
    return rows, path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=16, help="scenes per set")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="estimate.workers values to measure")
    parser.add_argument("--batch", type=int, nargs="+", default=[1], help="estimate.batch values to measure")
    parser.add_argument("--seed", type=int, default=9100)
    parser.add_argument("--sets", nargs="+", default=None, help="default: every set of estimate_procedural")
    parser.add_argument("--rounds", type=int, default=2, help="runs of each row, taken in turn")
    parser.add_argument("--no-write", action="store_true", help="print only")
    args = parser.parse_args()
    print(run(args.scenes, tuple(args.workers), tuple(args.batch), args.seed, args.sets, args.rounds,
              not args.no_write)[1])


if __name__ == "__main__":
    main()
