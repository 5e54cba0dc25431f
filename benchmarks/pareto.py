"""Speed against error: our estimator and its methods beside the alternatives, on the same captures.

    python -m benchmarks.captures make --scenes data/mitsuba --out data/captures/mitsuba   # once
    python train.py mode=benchmark benchmark=pareto

The one-light frames of capture folders made from Mitsuba 3 renders (8-bit sRGB at an
unknown exposure, millimetre depth, no albedo; ``benchmark.captures``: the direct,
path-traced and sensor-noisy sets), each estimated by:

- ``mode=estimate`` (``cnn+refine``, the default), ``estimate=fast`` (the preset of
  ``configs/estimate/fast.yaml``), ``estimate.method=refine`` (grid search + LM),
  ``estimate.method=cnn`` (the network alone): the command's own pipeline, every other
  setting its default, the light count its own choice;
- ``paper gradient descent``: the paper's method (Blinn-Phong with its cube-map shadows,
  plain squared error, rate 0.02 in scene sizes, from above the middle of the scene, at
  most 300 steps) with the capture's albedo taken as 0.5;
- ``Mitsuba 3 inverse rendering`` (:mod:`benchmarks.mitsuba_inverse`): a mesh of the
  depth map, albedo 0.5, Adam on one point light through ``llvm_ad_rgb`` (needs the
  ``mitsuba`` extra; left out when it is not installed).

Reported per method and set: success (every true light within 0.05 of the scene size,
and the right count), the median worst position error and the median seconds per frame
(the frame in memory). A markdown table and (with matplotlib, ``pip install '.[plot]'``)
a PNG, ``benchmarks/results/pareto_<device>_<date>.*``.
"""

from __future__ import annotations

import logging
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import device_name, write_results
from selfsup.metrics import SUCCESS_THRESHOLD

log = logging.getLogger(__name__)
PRESETS = Path(__file__).resolve().parents[1] / "configs" / "estimate"
COLUMNS = ["method", "set", "frames", "success_rate", "median_worst_error", "median_seconds"]
DEFAULT_CAPTURES = ("data/captures/mitsuba/direct", "data/captures/mitsuba/gi", "data/captures/mitsuba/noisy")


def _ours(**settings):
    from selfsup.estimation import EstimateOptions, estimate_scene

    options = EstimateOptions(**settings)

    def run(scene):
        record = estimate_scene(scene, options)
        return np.array([light["position"] for light in record["lights"]], dtype=np.float64).reshape(-1, 3)
    return run


def _preset(name: str) -> dict:
    # The tuned constants that configs/estimate/<name>.yaml changes: the preset's one source.
    from omegaconf import OmegaConf

    return OmegaConf.to_container(OmegaConf.load(PRESETS / f"{name}.yaml"))["tuning"]


def _paper_gd(max_iters: int = 300):
    from benchmarks.paper_table import fixed_start
    from selfsup.estimation.options import RefineOptions
    from selfsup.estimation.prepare import problem_of
    from selfsup.estimation.solvers import refine

    options = RefineOptions(method="gd", learning_rate=0.02, robust=False, max_iters=(max_iters,), strides=(1,),
                            specular=False)

    def run(scene):
        problem = problem_of(scene, "paper")
        return refine(problem, fixed_start(problem), options).position[0].double().numpy()
    return run


def _mitsuba():
    from benchmarks.mitsuba_inverse import fit_frame

    def run(scene):
        position, _, _ = fit_frame(scene.image.double().numpy(), scene.depth.double().numpy(), scene.K.double().numpy())
        return position[None]
    return run


def methods() -> dict:
    """name -> a function of a scene giving its light positions ``(L, 3)``."""
    out = {"mode=estimate (cnn+refine)": _ours(), "estimate=fast": _ours(tuning=_preset("fast")),
           "estimate.method=refine": _ours(method="refine"),
           "estimate.method=cnn": _ours(method="cnn"), "paper gradient descent": _paper_gd()}
    import importlib.util

    if importlib.util.find_spec("mitsuba") is not None:
        out["Mitsuba 3 inverse rendering"] = _mitsuba()
    else:
        log.warning("mitsuba is not installed (pip install '.[mitsuba]'): its inverse rendering is left out")
    return out


def _worst_error(found: np.ndarray, truth) -> tuple[float, bool]:
    true = truth.light_pos.double().numpy()
    if found.shape[0] == 0:
        return float("inf"), False
    distance = np.linalg.norm(true[:, None] - found[None], axis=-1).min(1) / float(truth.scene_scale)
    worst = float(distance.max())
    return worst, worst < SUCCESS_THRESHOLD and found.shape[0] == true.shape[0]


def run(captures: list[str] | tuple[str, ...] = DEFAULT_CAPTURES, frames: int = 24, write: bool = True):
    """Rows of (method, set): the one-light frames (the first ``frames``) of each capture folder."""
    from benchmarks.captures import read_truth
    from selfsup.scenes.capture import capture_frames, read_capture

    folders = [Path(c) for c in captures]
    missing = [str(f) for f in folders if not f.is_dir()]
    if missing:
        raise FileNotFoundError(f"no capture folder {', '.join(missing)}: make them with python -m benchmarks."
                                "mitsuba_scenes --out data/mitsuba --count 48 and python -m benchmarks.captures make "
                                "--scenes data/mitsuba --out data/captures/mitsuba")
    rows = []
    for folder in folders:
        data = []
        for frame in capture_frames(folder):
            truth = read_truth(folder / "truth" / f"{frame.color.stem}.npz")
            if truth.light_pos.shape[0] == 1:
                data.append((read_capture(frame), truth))
        data = data[:frames]
        for name, method in methods().items():
            errors, hits, seconds = [], 0, []
            for scene, truth in data:
                started = time.perf_counter()
                with torch.no_grad():
                    found = method(scene)
                seconds.append(time.perf_counter() - started)
                worst, success = _worst_error(found, truth)
                errors.append(worst)
                hits += success
            rows.append({"method": name, "set": folder.name, "frames": len(data),
                         "success_rate": round(hits / max(len(data), 1), 3),
                         "median_worst_error": round(statistics.median(errors), 4),
                         "median_seconds": round(statistics.median(seconds), 3)})
            log.info("%s", rows[-1])
    path = None
    if write:
        header = (f"One-light frames of capture folders made from Mitsuba 3 renders ({', '.join(map(str, folders))}; "
                  "8-bit sRGB at an unknown exposure, millimetre depth, no albedo), each method on the same frames; "
                  f"success = the one light found, within {SUCCESS_THRESHOLD} of the scene size; median worst "
                  "position error of the scene size; median seconds per frame on this device (the frame in memory). "
                  "Plot: the .png of this file's name.")
        path = write_results("pareto", torch.device("cpu"), rows, header, COLUMNS)
        _plot(rows, torch.device("cpu"), path.with_suffix(".png"))
    return rows, path


def _plot(rows: list[dict], device: torch.device, out: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log.warning("matplotlib is not installed (pip install '.[plot]'): no Pareto plot written")
        return
    import datetime

    names = list(dict.fromkeys(r["method"] for r in rows))
    sets = list(dict.fromkeys(r["set"] for r in rows))
    markers = ["o", "s", "^", "D", "v", "P"]
    colours = plt.get_cmap("tab10")
    figure, axes = plt.subplots(figsize=(7.5, 4.2))
    for i, name in enumerate(names):
        for j, set_name in enumerate(sets):
            row = next((r for r in rows if r["method"] == name and r["set"] == set_name), None)
            if row is None:
                continue
            axes.scatter(row["median_seconds"], 100 * row["success_rate"], s=55, marker=markers[j % len(markers)],
                         color=colours(i), edgecolors="black", linewidths=0.5, zorder=3,
                         label=name if j == 0 else None)
    for j, set_name in enumerate(sets):  # the sets' markers, in grey
        axes.scatter([], [], marker=markers[j % len(markers)], color="lightgrey", edgecolors="black", linewidths=0.5,
                     label=f"set: {set_name}")
    axes.set_xscale("log")
    # Plain numbers at a few round seconds (the log axis's own minor labels overlap).
    ticks = [t for t in (0.05, 0.1, 0.2, 0.3, 0.5, 1, 2, 3, 5, 10, 20) if min(r["median_seconds"] for r in rows) / 1.5 <= t
             <= max(r["median_seconds"] for r in rows) * 1.5]
    axes.set_xticks(ticks, [f"{t:g}" for t in ticks])
    axes.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    axes.set_ylim(-3, 103)
    axes.set_xlabel("median seconds per frame (log scale)")
    axes.set_ylabel("success (% of one-light frames)")
    date = datetime.date.today().isoformat()
    axes.set_title(f"One-light Mitsuba captures, no albedo: success against time ({device_name(device)}, {date})",
                   fontsize=8)
    axes.grid(True, which="both", lw=0.3, alpha=0.5)
    axes.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5), frameon=False)
    figure.tight_layout()
    figure.savefig(out, dpi=110)
    plt.close(figure)
