"""Procedural scene generation throughput (sample + exact render + degradations).

Target (issue 3): at least 100 scenes/s at 128x128, one light, 2x2 anti-aliasing,
on the 2-core CPU. Measured over ``count`` consecutive seeds, after one warm-up:
one scene per call, ``batch`` scenes ray cast together (what the dataset's batches
and ``mode=generate`` do), and through a DataLoader with ``workers`` processes
(what training gets; ``loader_count`` scenes, timed with the workers' start-up and
steady, after each worker's first batch). Results:
benchmarks/results/generate_speed_<device>_<date>.{md,json}.

    python train.py mode=benchmark benchmark=generate_speed
"""

from __future__ import annotations

import dataclasses
import time

import torch
from torch.utils.data import DataLoader

from benchmarks.common import write_results
from selfsup.scenes.dataset import ProceduralScenes, collate, render_items
from selfsup.scenes.degrade import Degradations
from selfsup.scenes.sampler import SamplerConfig

SETTINGS = (
    ("128x128, 1 light, 2x2 AA (target)", dict(height=128, width=128), 2),
    ("128x128, 1 light, no AA", dict(height=128, width=128), 1),
    ("64x64, 1 light, 2x2 AA", dict(height=64, width=64), 2),
    ("160x120, 1 light, 2x2 AA", dict(height=120, width=160), 2),
)
SENSOR = Degradations(depth_noise=0.0015, depth_quantisation=0.0005, edge_hole_jump=0.05, random_holes=0.01,
                      image_noise=0.005)


def _in_process(config: SamplerConfig, samples: int, count: int, together: int) -> tuple[float, float]:
    # (seconds, share of supersampled pixels) for seeds 1..count, ``together`` per call.
    render_items(list(range(together)), config, SENSOR, samples)
    start = time.perf_counter()
    aa = 0.0
    for first in range(1, count + 1, together):
        for rendered, _ in render_items(list(range(first, min(first + together, count + 1))), config, SENSOR, samples):
            aa += rendered.scene.meta["aa_pixels"] / (config.height * config.width)
    return time.perf_counter() - start, aa / count


def _loader(config: SamplerConfig, samples: int, count: int, batch: int, workers: int) -> tuple[float, float]:
    """(seconds for all ``count`` scenes, worker start-up included; scenes/s after the
    first ``workers`` batches, when every worker is under way: what a long run gets)."""
    data = ProceduralScenes(config, SENSOR, length=count, base_seed=1, samples=samples)
    loader = DataLoader(data, batch_size=batch, num_workers=workers, collate_fn=collate)
    start = time.perf_counter()
    arrived = []
    for item in loader:
        arrived.append((time.perf_counter(), item["image"].shape[0]))
    settled = max(1, workers) - 1
    if len(arrived) <= settled + 1:
        raise ValueError(f"count={count} gives {len(arrived)} batches; steady state needs more than {settled + 1}")
    steady = sum(n for _, n in arrived[settled + 1 :]) / (arrived[-1][0] - arrived[settled][0])
    return arrived[-1][0] - start, steady


def run(count: int = 128, batch: int = 32, workers: int = 2, loader_count: int = 512, loader_runs: int = 3,
        write: bool = True) -> list[dict]:
    """Every setting in process; the target setting through a DataLoader too, ``loader_runs``
    times (the shared 2-core machine's speed drifts by 20% between minutes: the rows give
    the median run and the range)."""
    rows = []
    for name, size, samples in SETTINGS:
        config = dataclasses.replace(SamplerConfig(), **size)
        for together in (1, batch):
            seconds, aa_share = _in_process(config, samples, count, together)
            rows.append({"setting": name, "how": "one per call" if together == 1 else f"{together} per call",
                         "scenes_per_s": round(count / seconds, 1), "ms_per_scene": round(1e3 * seconds / count, 1),
                         "supersampled_pixels": f"{aa_share:.0%}", "runs": 1, "range_scenes_per_s": ""})
        if workers and samples == 2 and size["height"] == 128:
            runs = [_loader(config, samples, loader_count, batch, workers) for _ in range(max(1, loader_runs))]
            with_start = sorted(loader_count / seconds for seconds, _ in runs)
            steady = sorted(rate for _, rate in runs)
            how = f"DataLoader, {workers} workers, batch {batch}"
            for label, rates in ((f"{loader_count} scenes with start-up", with_start),
                                 ("steady (after each worker's first batch)", steady)):
                median = rates[len(rates) // 2]
                rows.append({"setting": name, "how": f"{how}, {label}", "scenes_per_s": round(median, 1),
                             "ms_per_scene": round(1e3 / median, 1), "supersampled_pixels": "", "runs": len(rates),
                             "range_scenes_per_s": f"{rates[0]:.1f}-{rates[-1]:.1f}"})

    if write:
        print(write_results("generate_speed", torch.device("cpu"), rows,
                            f"{count} scenes per setting, each sampled, rendered exactly and degraded (sensor-like "
                            "depth and image noise). 'one per call': render_item; 'N per call': render_items, the "
                            "scenes ray cast together; DataLoader: ProceduralScenes through worker processes "
                            "(one torch thread each), with their start-up, and steady: after every worker "
                            "delivered its first batch; the DataLoader rows give the median of their runs and the range.",
                            ["setting", "how", "scenes_per_s", "ms_per_scene", "supersampled_pixels", "runs",
                             "range_scenes_per_s"]))
    return rows
