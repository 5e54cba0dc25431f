"""Batched estimation throughput: scenes per second against error (issue 5: ``cnn+refine``
at least 500 scenes/s batched on one H100).

The same fixed-seed procedural sets as ``benchmarks.estimate_procedural`` (160x120),
estimated in batches by :func:`selfsup.estimation.estimate_batch`, the very pipeline of
``mode=estimate`` (search, model selection, covariance) run on the whole batch at once.
Seconds count everything from the scene files' tensors on the host to the records:
moving to the device, preparing the inputs (normals, clipped pixels), the network, the
refinement and the covariances. A warm-up batch runs first (CUDA start, network load).

    python -m benchmarks.estimate_throughput --device cuda --scenes 512 --batch 64 256 512

Results: benchmarks/results/estimate_throughput_<device>_<date>.{md,json}.
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import time


import torch

from benchmarks.common import device_name, write_results
from benchmarks.estimate_procedural import SETS, parse_options, score, set_scene
from selfsup.estimation.options import EstimateOptions, Tuning
from selfsup.estimation.stages import estimate_batch
from selfsup.estimation.prepare import prepare
from selfsup.estimation.records import records

COLUMNS = ["set", "method", "batch", "scenes", "scenes_per_s", "inputs_share", "estimate_share", "records_share",
           "median_position_error", "success_rate", "count_accuracy"]
DEFAULT_SETS = ("true reflectance, 1 light", "true reflectance, 2 lights")


def _render(job: tuple[str, int, int]):
    return set_scene(*job)


def _one_thread() -> None:  # each render process on its own core
    torch.set_num_threads(1)


def render_set(name: str, count: int, seed: int, workers: int) -> list:
    """The set's first ``count`` scenes, rendered by ``workers`` processes (0: in this one)."""
    jobs = [(name, index, seed) for index in range(count)]
    if workers == 0:
        return [_render(job) for job in jobs]
    # Thousands of scenes hold more tensors than a process may pass as file descriptors.
    torch.multiprocessing.set_sharing_strategy("file_system")
    with multiprocessing.get_context("spawn").Pool(workers, initializer=_one_thread) as pool:
        shared = pool.map(_render, jobs, chunksize=4)
    # Into this process's own memory, as scenes read from files are: the first touch of
    # shared-memory pages would otherwise be timed as input preparation.
    return [scene.to("cpu", copy=True) for scene in shared]


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def estimate_scenes(scenes: list, options: EstimateOptions, device: torch.device,
                    phases: dict[str, float] | None = None) -> list[dict]:
    """Records of ``scenes`` (same size) estimated as one batch on ``device``; adds the
    seconds of each phase (inputs, estimate, records) to ``phases`` when given."""
    clock = [time.perf_counter()]

    def lap(name: str) -> None:
        if phases is not None:
            _sync(device)
            clock.append(time.perf_counter())
            phases[name] = phases.get(name, 0.0) + clock[-1] - clock[-2]

    problem = prepare(scenes, options, device)
    lap("inputs")
    results = estimate_batch(problem, options)
    lap("estimate")
    out = records([scene.id for scene in scenes], problem, results, options)
    lap("records")
    return out


def measure(name: str, scenes: list, batch: int, options: EstimateOptions, device: torch.device) -> dict:
    out: list[dict] = []
    phases: dict[str, float] = {}
    with torch.no_grad():
        _sync(device)
        started = time.perf_counter()
        for first in range(0, len(scenes), batch):
            out += estimate_scenes(scenes[first : first + batch], options, device, phases)
        _sync(device)
        seconds = time.perf_counter() - started
    scored = [score(record, scene) for record, scene in zip(out, scenes)]
    return {"set": name, "method": options.method, "batch": batch, "scenes": len(scenes),
            "scenes_per_s": round(len(scenes) / seconds, 2),
            **{f"{phase}_share": round(value / seconds, 2) for phase, value in phases.items()},
            "median_position_error": round(statistics.median(s[0] for s in scored), 4),
            "success_rate": round(sum(s[1] for s in scored) / len(scored), 3),
            "count_accuracy": round(sum(s[2] for s in scored) / len(scored), 3)}


def run(scenes: int = 64, batches: tuple[int, ...] = (16, 64), device: str = "auto", seed: int = 9100,
        sets: tuple[str, ...] = DEFAULT_SETS, workers: int = 0, write: bool = True,
        options: EstimateOptions | None = None):
    device = torch.device("cuda" if device == "auto" and torch.cuda.is_available() else
                          ("cpu" if device == "auto" else device))
    options = options or EstimateOptions()
    rows = []
    for name in sets:
        if name not in SETS:
            raise ValueError(f"unknown set {name!r}; sets: {list(SETS)}")
        started = time.perf_counter()
        pool = render_set(name, scenes, seed, workers)
        print(f"{name}: rendered {scenes} scenes in {time.perf_counter() - started:.1f} s", flush=True)
        with torch.no_grad():
            estimate_scenes(pool[: min(batches)], options, device)  # warm-up
        for batch in batches:
            try:
                rows.append(measure(name, pool, batch, options, device))
            except torch.cuda.OutOfMemoryError:
                rows.append({"set": name, "method": options.method, "batch": batch, "scenes": scenes,
                             "scenes_per_s": "out of device memory"})
                torch.cuda.empty_cache()
            print(rows[-1], flush=True)
    path = None
    if write:
        header = (f"Fixed-seed procedural sets (seeds {seed}*1000003+i, as estimate_procedural), 160x120, 2x2 AA; "
                  f"estimate.method={options.method}, estimate.shadows={options.shadows}, "
                  f"estimate.min_light_share={options.tuning.min_light_share}, "
                  f"estimate.search_shadows={options.tuning.search_shadows}, defaults otherwise; {device_name(device)}. "
                  "scenes_per_s: all scenes through selfsup.estimation.estimate_batch in batches of `batch`, "
                  "inputs from host tensors to records (covariances included), after a warm-up batch; *_share: the part of "
                  "that time spent preparing inputs, estimating, and writing records. Errors as in "
                  "estimate_procedural (worst light per scene, of the scene size; success: every light < 0.05).")
        path = write_results("estimate_throughput", device, rows, header, COLUMNS)
    return rows, path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=64, help="scenes per set")
    parser.add_argument("--batch", type=int, nargs="+", default=[16, 64], help="batch sizes to measure")
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda")
    parser.add_argument("--seed", type=int, default=9100)
    parser.add_argument("--sets", nargs="+", default=list(DEFAULT_SETS))
    parser.add_argument("--workers", type=int, default=0, help="processes rendering the scenes")
    parser.add_argument("--method", default="cnn+refine")
    parser.add_argument("--min-light-share", type=float, default=Tuning.min_light_share,
                        help="estimate.min_light_share (what an added light must carry)")
    parser.add_argument("--threads", type=int, default=0, help=">0: torch.set_num_threads (CPU)")
    parser.add_argument("--no-write", action="store_true", help="print only")
    parser.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                        help="another EstimateOptions field (refine.* for RefineOptions); printed, not written")
    args = parser.parse_args()
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    options = EstimateOptions.from_settings(method=args.method, min_light_share=args.min_light_share,
                                            **parse_options(args.option))
    print(run(args.scenes, tuple(args.batch), args.device, args.seed, tuple(args.sets), args.workers,
              not (args.no_write or args.option), options)[1])


if __name__ == "__main__":
    main()
