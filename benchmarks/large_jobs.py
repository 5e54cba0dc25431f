"""Estimation at dataset scale: ranks against one process, kills, a million-frame list.

    python -m benchmarks.large_jobs make --out data/large_jobs --frames 200    # a capture folder, once
    python -m benchmarks.large_jobs run --frames data/large_jobs/cap            # writes benchmarks/results/

Every run is the command a user runs (``python train.py mode=estimate``, default settings,
``estimate.workers=1``: the processes are the ranks), timed from its start to its end
(Python's start-up included) on the frames of ``--frames``, the fastest of ``--repeats``:

- ``one process, 1 thread`` (``OMP_NUM_THREADS=1``): the reference every other output is
  compared with, record for record (timing fields aside) and to the last bit;
- ``torchrun, 1 rank``: one process on every core (torch's threads: the machine's cores);
- ``torchrun, N ranks`` (``--nproc_per_node=N``): each rank on ``cores / N`` threads
  (torchrun sets ``OMP_NUM_THREADS=1`` for several ranks; ``mode=estimate`` gives each rank
  its share of the cores), one shard each, rank 0 merging the parts;
- ``one process, N forked workers`` (``estimate.workers=N``): the one-machine way without torchrun;
- ``kill`` trials: two ranks with ``--max-restarts=1``, one rank killed with SIGKILL after a
  random number of its records (torchrun restarts the group, which resumes its parts), then
  the whole job killed at a random moment and run again by hand; the output then holds
  every frame once: lost and duplicated ids counted;
- ``list memory``: a list file of 1,000,000 lines (the folder's frames over and over), the
  peak resident memory of the command when its first record is written, against a list
  of one line.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import torch

from benchmarks.common import write_results

ROOT = Path(__file__).resolve().parents[1]
TIMING = ("seconds", "batch_size")
COLUMNS = ["run", "processes", "threads_each", "frames", "wall_seconds", "frames_per_second",
           "speed_up_vs_1_rank", "speed_up_vs_1_thread", "identical_to_reference", "lost", "duplicated", "note"]


def make(out: Path, frames: int, seed: int = 12000) -> Path:
    """A capture folder ``out/cap`` of ``frames`` procedural rooms (160x120, one or two lights)."""
    from benchmarks.captures import write_capture
    from selfsup.scenes.dataset import render_items
    from selfsup.scenes.degrade import Degradations
    from selfsup.scenes.sampler import SamplerConfig

    sampler = SamplerConfig(height=120, width=160, n_lights_probs=(0.5, 0.5))
    seeds = [seed + i for i in range(frames)]
    for i, (_, scene) in enumerate(render_items(seeds, sampler, Degradations(), 2)):
        write_capture(scene, out / "cap", f"frame_{i:06d}")
    print(f"{out / 'cap'}: {frames} frames", flush=True)
    return out / "cap"


def _command(frames: Path, output: Path, *extra: str, workers: int = 1) -> list[str]:
    return ["train.py", "mode=estimate", f"estimate.input={frames}", f"estimate.output={output}",
            f"estimate.workers={workers}", "estimate.progress=false",
            f"hydra.run.dir={output.parent / ('run_' + output.stem)}", *extra]


def _torchrun(ranks: int, *extra: str) -> list[str]:
    return [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={ranks}", *extra]


def _records(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [{k: v for k, v in json.loads(line).items() if k not in TIMING} for line in path.read_text().splitlines()]


def _timed(command: list[str], env: dict | None = None) -> float:
    started = time.perf_counter()
    done = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{done.stderr[-3000:]}")
    return time.perf_counter() - started


def _fastest(command: list[str], output: Path, repeats: int, env: dict | None = None) -> tuple[float, str]:
    # The fastest of ``repeats`` runs of ``command`` writing ``output`` (started over each time:
    # a shared machine's other load only ever slows a run) and every run's wall time.
    walls = []
    for _ in range(repeats):
        output.unlink(missing_ok=True)
        walls.append(_timed(command, env))
    return min(walls), "runs " + " / ".join(f"{wall:.1f}" for wall in walls) + " s"


def _largest_shift(records: list[dict], reference: list[dict]) -> float:
    # The largest distance between a light of ``records`` and the same light of ``reference``
    # (inf where the ids or light counts differ).
    if [r["id"] for r in records] != [r["id"] for r in reference]:
        return float("inf")
    shift = 0.0
    for record, other in zip(records, reference):
        if len(record["lights"]) != len(other["lights"]):
            return float("inf")
        for light, same in zip(record["lights"], other["lights"]):
            shift = max(shift, sum((a - b) ** 2 for a, b in zip(light["position"], same["position"])) ** 0.5)
    return shift


def _children(pid: int) -> list[int]:
    # The processes whose parent is ``pid`` (Linux /proc).
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    found.append(int(entry.name))
            except (OSError, IndexError, ValueError):
                continue
    return found


def _rank_of(pid: int) -> int | None:
    try:
        environ = (Path("/proc") / str(pid) / "environ").read_bytes().split(b"\0")
    except OSError:
        return None
    value = next((item.split(b"=", 1)[1] for item in environ if item.startswith(b"RANK=")), None)
    return None if value is None else int(value)


def _lines(path: Path) -> int:
    return path.read_bytes().count(b"\n") if path.exists() else 0


def _kill_trial(frames: Path, output: Path, draw: random.Random, total: int) -> str:
    # A rank killed after a random number of its records (torchrun restarts the group), then
    # the whole job killed at a random moment and run again by hand. Returns what was done.
    part = output.parent / f"{output.name}.parts" / "rank00001-of-00002.jsonl"
    job = subprocess.Popen(_torchrun(2, "--max-restarts=1", *_command(frames, output)), cwd=ROOT,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    after = draw.randint(1, max(1, total // 2 - 5))
    while job.poll() is None and _lines(part) < after:
        time.sleep(0.05)
    killed = [pid for pid in _children(job.pid) if _rank_of(pid) == 1]
    for pid in killed:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    time.sleep(draw.uniform(2.0, 8.0))  # the restarted group resumes; then the whole job dies
    whole = job.poll() is None
    if whole:  # the agent and its workers (torchrun starts each worker in a session of its own)
        workers = _children(job.pid)
        os.killpg(job.pid, signal.SIGKILL)
        for pid in workers:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
    job.wait()
    time.sleep(0.5)  # the killed workers' locks are the kernel's to drop
    _timed(_torchrun(2, *_command(frames, output)))
    return (f"rank 1 killed after {after} of its records (torchrun restarted it)" if killed else "no rank to kill") + (
        "; the whole job killed later and rerun" if whole else "; the job ended before the second kill, rerun")


def _peak_at_first_record(listing: Path, output: Path) -> float:
    # Peak resident memory (MB) of the command when its first record is written.
    run = subprocess.Popen([sys.executable, *_command(listing, output)], cwd=ROOT, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
    try:
        while run.poll() is None and _lines(output) < 1:
            time.sleep(0.01)
        status = (Path("/proc") / str(run.pid) / "status").read_text()
        return int(next(line for line in status.splitlines() if line.startswith("VmHWM")).split()[1]) / 1024
    finally:
        run.kill()
        run.wait()


def run(frames: Path, work: Path, ranks: int = 2, kills: int = 3, list_lines: int = 1_000_000,
        seed: int = 0, write: bool = True, repeats: int = 2) -> list[dict]:
    """The rows of the module's doc; written to ``benchmarks/results/large_jobs_<device>_<date>.*``."""
    work.mkdir(parents=True, exist_ok=True)
    total = len(list((frames / "color").iterdir()))
    cores = os.cpu_count() or 1
    one_thread = {**os.environ, "OMP_NUM_THREADS": "1"}
    rows = []

    def row(name, processes, threads, output, wall, reference=None, note=""):
        records = _records(output)
        ids = [record["id"] for record in records]
        rows.append({"run": name, "processes": processes, "threads_each": threads, "frames": len(records),
                     "wall_seconds": round(wall, 1), "frames_per_second": round(len(records) / wall, 2),
                     "speed_up_vs_1_rank": None, "speed_up_vs_1_thread": None,
                     "identical_to_reference": None if reference is None else records == reference,
                     "lost": total - len(set(ids)), "duplicated": len(ids) - len(set(ids)), "note": note})
        print(rows[-1], flush=True)
        return records

    wall, runs = _fastest([sys.executable, *_command(frames, work / "reference.jsonl")], work / "reference.jsonl",
                          repeats, one_thread)
    reference = row("one process, 1 thread (reference)", 1, 1, work / "reference.jsonl", wall, note=runs)
    wall, runs = _fastest(_torchrun(1, *_command(frames, work / "one_rank.jsonl")), work / "one_rank.jsonl", repeats)
    shift = _largest_shift(_records(work / "one_rank.jsonl"), reference)
    row("torchrun, 1 rank", 1, cores, work / "one_rank.jsonl", wall,
        note=f"{runs}; {cores} threads sum in another order than one: lights within {shift:.1e} m of the reference's")
    wall, runs = _fastest(_torchrun(ranks, *_command(frames, work / "ranks.jsonl")), work / "ranks.jsonl", repeats)
    row(f"torchrun, {ranks} ranks", ranks, max(1, cores // ranks), work / "ranks.jsonl", wall, reference, note=runs)
    rows[-1]["speed_up_vs_1_rank"] = round(rows[-1]["frames_per_second"] / rows[1]["frames_per_second"], 2)
    rows[-1]["speed_up_vs_1_thread"] = round(rows[-1]["frames_per_second"] / rows[0]["frames_per_second"], 2)
    wall, runs = _fastest([sys.executable, *_command(frames, work / "workers.jsonl", workers=ranks)],
                          work / "workers.jsonl", repeats)
    row(f"one process, {ranks} forked workers", ranks, max(1, cores // ranks), work / "workers.jsonl", wall, reference,
        note=f"{runs}; estimate.workers: the one-machine way without torchrun")
    draw = random.Random(seed)
    for trial in range(kills):
        output = work / f"killed_{trial}.jsonl"
        started = time.perf_counter()
        note = _kill_trial(frames, output, draw, total)
        row(f"kill trial {trial + 1}", 2, max(1, cores // 2), output, time.perf_counter() - started, reference, note)
    listing, single = work / "million.txt", work / "one.txt"
    colours = sorted(str(path.resolve()) for path in (frames / "color").iterdir())
    single.write_text(colours[0] + "\n")
    with listing.open("w") as out:
        for line in range(list_lines):
            out.write(colours[line % len(colours)] + "\n")
    one = _peak_at_first_record(single, work / "one_list.jsonl")
    million = _peak_at_first_record(listing, work / "million_list.jsonl")
    rows.append({"run": f"list of {list_lines} frames: peak memory at the first record", "processes": 1,
                 "threads_each": cores, "frames": list_lines, "wall_seconds": None, "frames_per_second": None,
                 "speed_up_vs_1_rank": None, "speed_up_vs_1_thread": None, "identical_to_reference": None,
                 "lost": None, "duplicated": None,
                 "note": f"{million:.0f} MB against {one:.0f} MB for a list of one line: "
                         f"{million - one:.0f} MB for the list"})
    print(rows[-1], flush=True)
    if write:
        header = (f"`python -m benchmarks.large_jobs run --frames {frames}` on {total} procedural capture frames "
                  f"(160x120, one or two lights; `python -m benchmarks.large_jobs make`), {cores} cores. "
                  + " ".join(__doc__.split("\n\n", 2)[2].split()))
        write_results("large_jobs", torch.device("cpu"), rows, header, COLUMNS)
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    m = sub.add_parser("make", help="a capture folder of procedural rooms")
    m.add_argument("--out", type=Path, default=Path("data/large_jobs"))
    m.add_argument("--frames", type=int, default=200)
    r = sub.add_parser("run", help="ranks, kills and a million-frame list; writes the results file")
    r.add_argument("--frames", type=Path, default=Path("data/large_jobs/cap"))
    r.add_argument("--work", type=Path, default=Path("data/large_jobs/runs"))
    r.add_argument("--ranks", type=int, default=2)
    r.add_argument("--kills", type=int, default=3)
    r.add_argument("--list-lines", type=int, default=1_000_000)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--repeats", type=int, default=2, help="timed runs of each kind; the fastest is reported")
    r.add_argument("--no-write", action="store_true")
    args = parser.parse_args(argv)
    if args.command == "make":
        make(args.out, args.frames)
    else:
        run(args.frames.resolve(), args.work.resolve(), args.ranks, args.kills, args.list_lines, args.seed,
            not args.no_write, args.repeats)


if __name__ == "__main__":
    main()
