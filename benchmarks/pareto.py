"""Speed against error of every way to estimate one light (issue 6, item 2).

Methods, on the same fixed-seed procedural scenes (one light, 160x120, true
reflectance, specular objects as the generator draws them):

- ``cnn``: the network alone;
- ``cnn + LM k``: Levenberg-Marquardt with epipolar shadows from the network's
  first slot, capped at k iterations at half resolution (and k/3 at full);
- ``grid + LM (refine)``: the grid search and LM of ``estimate.method=refine``;
- ``Boom model``: ambient + diffuse, no cast shadows, grid + LM;
- ``Neverova model``: + specular, no cast shadows, grid + LM.

Output: median position error, success rate and median seconds per scene, a
markdown table and (with matplotlib installed: ``pip install '.[plot]'``) a PNG
with the Pareto front, under benchmarks/results/pareto_<device>_<date>.*.

    python train.py mode=benchmark benchmark=pareto
"""

from __future__ import annotations

import dataclasses
import logging
import statistics
import time

import torch

from benchmarks.common import RESULTS, device_name, device_slug, write_results
from render import GBuffer
from selfsup.estimation.network import network_slots
from selfsup.estimation.prepare import problem_of
from selfsup.metrics import SUCCESS_THRESHOLD, light_errors
from selfsup.estimation.options import RefineOptions
from selfsup.estimation.solvers import refine, search
from selfsup.scenes.exact import render_spec
from selfsup.scenes.sampler import SamplerConfig, sample_scene

log = logging.getLogger(__name__)
COLUMNS = ["method", "scenes", "median_position_error", "success_rate", "median_seconds"]


def _methods(caps: list[int]):
    def cnn(scene, problem):
        return network_slots(problem)[0][:, :1]

    def capped(k):
        def run(scene, problem):
            start = network_slots(problem)[0][:, :1]
            return refine(problem, start, RefineOptions(max_iters=(k, max(1, k // 3)), strides=(2, 1))).position
        return run

    def grid(specular: bool | None, shadows: str):
        def run(scene, problem):
            has_specular = scene.ks is not None and bool((scene.ks > 0).any())
            return search(dataclasses.replace(problem, shadows=shadows), 1,
                          RefineOptions(specular=has_specular if specular is None else specular)).position
        return run

    yield "cnn", cnn
    for k in caps:
        yield f"cnn + LM {k}", capped(k)
    yield "grid + LM (refine)", grid(None, "epipolar")
    yield "Boom model (no specular, no shadows)", grid(False, "none")
    yield "Neverova model (specular, no shadows)", grid(None, "none")


def run(scenes: int = 10, seed: int = 9200, caps: list[int] | None = None, write: bool = True):
    sampler = SamplerConfig(height=120, width=160)
    data = [render_spec(sample_scene(seed * 1_000_003 + i, sampler, n_lights=1), samples=2).scene
            for i in range(scenes)]
    rows = []
    for name, method in _methods(list(caps or [5, 10, 20, 50])):
        errors, seconds = [], []
        for scene in data:
            problem = problem_of(scene)
            started = time.perf_counter()
            with torch.no_grad():
                position = method(scene, problem)[0]
            seconds.append(time.perf_counter() - started)
            g = GBuffer.from_depth(scene.depth[None], scene.K[None])
            errors.append(max(light_errors(position, None, scene.light_pos, None, float(scene.scene_scale),
                                           g.points[0][g.mask[0]].mean(0)).position))
        rows.append({"method": name, "scenes": scenes, "median_position_error": round(statistics.median(errors), 4),
                     "success_rate": round(sum(e < SUCCESS_THRESHOLD for e in errors) / scenes, 3),
                     "median_seconds": round(statistics.median(seconds), 3)})
        log.info("%s", rows[-1])
    path = None
    if write:
        header = (f"{scenes} one-light procedural scenes (seeds {seed}*1000003+i), 160x120, 2x2 AA, true "
                  "reflectance; position error of the scene size (median over scenes); seconds per scene on this "
                  "device. Plot: pareto_<device>_<date>.png (median error against median seconds, log-log).")
        path = write_results("pareto", torch.device("cpu"), rows, header, COLUMNS)
        _plot(rows, torch.device("cpu"))
    return rows, path


def _plot(rows: list[dict], device: torch.device) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log.warning("matplotlib is not installed (pip install '.[plot]'): no Pareto plot written")
        return
    import datetime

    front, best = [], float("inf")
    for row in sorted(rows, key=lambda r: r["median_seconds"]):
        if row["median_position_error"] < best:
            best = row["median_position_error"]
            front.append(row)
    figure, axes = plt.subplots(figsize=(7, 4.5))
    for row in rows:
        axes.scatter(row["median_seconds"], max(row["median_position_error"], 1e-4), zorder=3)
        axes.annotate(row["method"], (row["median_seconds"], max(row["median_position_error"], 1e-4)), fontsize=7,
                      xytext=(4, 4), textcoords="offset points")
    axes.plot([r["median_seconds"] for r in front], [max(r["median_position_error"], 1e-4) for r in front], "k--",
              lw=1, label="Pareto front")
    axes.axhline(SUCCESS_THRESHOLD, color="grey", lw=0.8, ls=":", label="success threshold")
    axes.set_xscale("log")
    axes.set_yscale("log")
    axes.set_xlabel("median seconds per scene")
    axes.set_ylabel("median position error (of scene size)")
    date = datetime.date.today().isoformat()
    axes.set_title(f"Speed against error, {device_name(device)}, {date}", fontsize=9)
    axes.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(RESULTS / f"pareto_{device_slug(device)}_{date}.png", dpi=110)
    plt.close(figure)
