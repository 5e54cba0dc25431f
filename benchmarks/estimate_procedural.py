"""Per-image estimation (``mode=estimate``'s pipeline) on fixed-seed procedural scenes.

Issue 5's targets, 160x120: true reflectance success >= 98% and median position
error <= 0.005; the paper's reflectance-error rows (kd = ks = 0.5, fractal noise
m = 0.1 .. 0.3) success >= 90%; two-light scenes the right light count >= 90%;
``cnn+refine`` <= 0.25 s per scene on the 2-core CPU. Also the calibration of
``position_std``: the share of true lights inside their 2-sigma ellipsoid
(Mahalanobis distance^2 under the 3x3 ``position_cov`` below 8.03, the 3-D
chi-square 95.4% point).

    python -m benchmarks.estimate_procedural --scenes 20 --method cnn+refine [--shadows none --search-shadows none]
        [--normal-smoothing auto] [--reflectance-gains 1] [--sets "sensor depth and image noise"]  # a subset is printed, not written
        [--option block_width=0.1 --option refine.robust_scale=0.05]  # any other setting: printed, not written

Results: benchmarks/results/estimate_procedural_<method>_shadows_<s>_search_<s>_<device>_<date>.{md,json}.
"""

from __future__ import annotations

import argparse
import ast
import statistics
import time

import torch

from benchmarks.common import score_record, write_results
from selfsup.estimation.options import EstimateOptions, RefineOptions
from selfsup.estimation.stages import estimate_scene
from selfsup.metrics import CHI2_3D_2SIGMA
from selfsup.scenes.dataset import render_item
from selfsup.scenes.degrade import Degradations
from selfsup.scenes.sampler import SamplerConfig

SETS = {
    "true reflectance, 1 light": (dict(), [1.0]),
    "kd = ks = 0.5 (paper m=0.0)": (dict(reflectance="half"), [1.0]),
    "fractal noise m=0.1": (dict(reflectance="noise", reflectance_noise=0.1), [1.0]),
    "fractal noise m=0.3": (dict(reflectance="noise", reflectance_noise=0.3), [1.0]),
    "true reflectance, 2 lights": (dict(), [0.0, 1.0]),
    # configs/eval's sensor set: depth noise and quantisation growing with z^2, holes, image noise
    "sensor depth and image noise": (dict(depth_noise=0.003, depth_quantisation=0.001, edge_hole_jump=0.05,
                                          random_holes=0.01, image_noise=0.005), [1.0]),
}
COLUMNS = ["set", "method", "scenes", "median_position_error", "success_rate", "count_accuracy",
           "two_sigma_coverage", "median_position_std", "median_intensity_error", "median_seconds"]


def score(record: dict, scene) -> tuple[float, bool, bool, int]:
    """One estimate against its scene's truth: worst position error (of the scene size),
    success, right light count, and how many true lights fall inside their 2-sigma ellipsoid."""
    errors, inside = score_record(record, scene)
    return max(errors.position), errors.success, errors.count_right, inside


def set_scene(name: str, index: int, seed: int):
    """Scene ``index`` of the fixed-seed set ``name`` (160x120, 2x2 AA), degraded as the set says."""
    degradations, lights = SETS[name]
    sampler = SamplerConfig(height=120, width=160, n_lights_probs=tuple(lights))
    return render_item(seed * 1_000_003 + index, sampler, Degradations(**degradations), 2)[1]


def run_set(name: str, count: int, seed: int, options: EstimateOptions) -> dict:
    worst, success, count_right, inside, total_lights, seconds, stds, intensity = [], 0, 0, 0, 0, [], [], []
    for index in range(count):
        scene = set_scene(name, index, seed)
        started = time.perf_counter()
        with torch.no_grad():
            record = estimate_scene(scene, options)
        seconds.append(time.perf_counter() - started)
        errors, within = score_record(record, scene)
        worst.append(max(errors.position))
        success += errors.success
        count_right += errors.count_right
        if errors.count_right:
            intensity.append(max(errors.intensity))
        inside += within
        total_lights += scene.light_pos.shape[0]
        stds += [float(torch.tensor(light["position_std"]).norm()) / float(scene.scene_scale) for light in record["lights"]]
    return {"set": name, "method": options.method, "scenes": count,
            "median_position_error": round(statistics.median(worst), 4), "success_rate": round(success / count, 3),
            "count_accuracy": round(count_right / count, 3), "two_sigma_coverage": round(inside / total_lights, 3),
            "median_position_std": round(statistics.median(stds), 4) if stds else "",
            "median_intensity_error": round(statistics.median(intensity), 4) if intensity else "",
            "median_seconds": round(statistics.median(seconds), 3)}


def parse_options(pairs: list[str]) -> dict:
    """``["block_width=0.1", "refine.robust_scale=0.05"]`` -> keyword arguments of
    :class:`EstimateOptions` (``refine.*`` become a :class:`RefineOptions`); values are
    Python literals, or else the text itself (``method=cnn``, ``checkpoint=path/to.pt``)."""
    estimate, refine = {}, {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            raise ValueError(f"--option takes KEY=VALUE, got {pair!r}")
        target, key = (refine, key[len("refine."):]) if key.startswith("refine.") else (estimate, key)
        try:
            target[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):  # a bare word or path: the string itself (method=cnn)
            target[key] = value
    if refine:
        estimate["refine"] = RefineOptions(**refine)
    return estimate


def run(scenes: int = 20, method: str = "cnn+refine", seed: int = 9100, sets: list[str] | None = None,
        write: bool = True, shadows: str = "none", search_shadows: str = "none", normal_smoothing: str = "auto",
        reflectance_gains: int = 0, extra: dict | None = None):
    options = EstimateOptions.from_settings(method=method, shadows=shadows, search_shadows=search_shadows,
                              normal_smoothing=normal_smoothing, reflectance_gains=reflectance_gains, **(extra or {}))
    rows = []
    for name in SETS:
        if sets and name not in sets:
            continue
        rows.append(run_set(name, scenes, seed, options))
        print(rows[-1], flush=True)
    path = None
    if write:
        header = (f"{scenes} scenes per set (seeds {seed}*1000003+i), 160x120, 2x2 AA; estimate.method={method}, "
                  f"estimate.shadows={shadows}, estimate.search_shadows={search_shadows}, "
                  f"estimate.normal_smoothing={normal_smoothing}, estimate.reflectance_gains={reflectance_gains}, "
                  "defaults otherwise. Position error: worst light per scene, of the scene size; success: every "
                  "light < 0.05; two_sigma_coverage: share of true lights inside their 2-sigma ellipsoid "
                  f"(Mahalanobis^2 < {CHI2_3D_2SIGMA}); median_position_std: the norm of a light's position_std, of the "
                  "scene size, median over the lights found; median_intensity_error: the worst paired light's "
                  "|I_est - I_true| / |I_true|, median over the scenes given the right count (with a wrong kd the "
                  "intensities take its scale); seconds per scene on this device.")
        name = f"estimate_procedural_{method.replace('+', '_')}_shadows_{shadows}_search_{search_shadows}"
        name += f"_gains_{reflectance_gains}" if reflectance_gains else ""
        path = write_results(name, torch.device("cpu"), rows, header, COLUMNS)
    return rows, path


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenes", type=int, default=20)
    parser.add_argument("--method", default="cnn+refine")
    parser.add_argument("--seed", type=int, default=9100)
    parser.add_argument("--shadows", default="none")
    parser.add_argument("--search-shadows", default="none")
    parser.add_argument("--normal-smoothing", default="auto")
    parser.add_argument("--reflectance-gains", type=int, default=0)
    parser.add_argument("--sets", nargs="*", help="names of the sets to run (default: all)")
    parser.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                        help="another EstimateOptions field (refine.* for RefineOptions); printed, not written")
    args = parser.parse_args()
    torch.set_num_threads(2)
    print(run(args.scenes, args.method, args.seed, sets=args.sets, write=not (args.sets or args.option),
              shadows=args.shadows, search_shadows=args.search_shadows, normal_smoothing=args.normal_smoothing,
              reflectance_gains=args.reflectance_gains, extra=parse_options(args.option))[1])
