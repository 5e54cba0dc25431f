"""Procedural scene generation throughput (sample + exact render + degradations).

Target (issue 3): at least 100 scenes/s at 128x128, one light, 2x2 anti-aliasing,
on the 2-core CPU. Measured over ``count`` consecutive seeds, after one warm-up.
Results: benchmarks/results/generate_speed_<device>_<date>.{md,json}.

    python train.py mode=benchmark benchmark=generate_speed
"""

from __future__ import annotations

import dataclasses
import time

import torch

from benchmarks.common import write_results
from selfsup.scenes.dataset import render_item
from selfsup.scenes.degrade import Degradations
from selfsup.scenes.sampler import SamplerConfig

SETTINGS = (
    ("128x128, 1 light, 2x2 AA (target)", dict(height=128, width=128), 2),
    ("128x128, 1 light, no AA", dict(height=128, width=128), 1),
    ("64x64, 1 light, 2x2 AA", dict(height=64, width=64), 2),
    ("160x120, 1 light, 2x2 AA", dict(height=120, width=160), 2),
)


def run(count: int = 100, write: bool = True) -> list[dict]:
    rows = []
    sensor = Degradations(depth_noise=0.0015, depth_quantisation=0.0005, edge_hole_jump=0.05, random_holes=0.01,
                          image_noise=0.005)
    for name, size, samples in SETTINGS:
        config = dataclasses.replace(SamplerConfig(), **size)
        render_item(0, config, sensor, samples)
        start = time.perf_counter()
        aa_share = 0.0
        for seed in range(1, count + 1):
            rendered, _ = render_item(seed, config, sensor, samples)
            aa_share += rendered.scene.meta["aa_pixels"] / (size["height"] * size["width"])
        seconds = time.perf_counter() - start
        rows.append({"setting": name, "scenes_per_s": round(count / seconds, 1),
                     "ms_per_scene": round(1e3 * seconds / count, 1), "supersampled_pixels": f"{aa_share / count:.0%}"})
    if write:
        print(write_results("generate_speed", torch.device("cpu"), rows,
                            f"{count} scenes per setting, each sampled, rendered exactly and degraded (sensor-like "
                            "depth and image noise); one process.",
                            ["setting", "scenes_per_s", "ms_per_scene", "supersampled_pixels"]))
    return rows
