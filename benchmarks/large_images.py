"""Large images: ``estimate.max_pixels`` against every pixel, on 640x480 procedural scenes.

A capture from a consumer RGB-D sensor is often 640x480, 16x the pixels of the
devset; the estimator's time grows with them. ``estimate.max_pixels`` (default
76800, 320x240) estimates such a file on every k-th pixel of its rows and
columns. This measures what that costs in accuracy and gains in time: each scene
is estimated twice, with every pixel (``max_pixels=None``) and with the default,
and the rows give both errors (worst light, of the scene size), the light counts,
the distance between the two answers (worst paired light, of the scene size) and
both times. Scenes: the procedural sampler at 640x480 (2x2 AA), half of them with
two lights, and the same specs with the estimate_procedural sensor set's
degradations (depth noise, quantisation, holes, image noise).

    python -m benchmarks.large_images --scenes 8 [--height 480 --width 640]

Results: benchmarks/results/large_images_<device>_<date>.{md,json}.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchmarks.common import score_record, write_results
from benchmarks.estimate_procedural import SETS
from selfsup.estimation.options import EstimateOptions, Tuning
from selfsup.estimation.stages import estimate_scene
from selfsup.estimation.prepare import pixel_stride
from selfsup.metrics import light_errors
from selfsup.scenes.dataset import render_item
from selfsup.scenes.degrade import Degradations
from selfsup.scenes.sampler import SamplerConfig

COLUMNS = ["set", "id", "true", "found_all", "found_default", "error_all", "error_default", "answers_apart",
           "seconds_all", "seconds_default", "stride"]
VARIANTS = {"clean": Degradations(), "sensor noise": Degradations(**SETS["sensor depth and image noise"][0])}


def _estimate(scene, options: EstimateOptions) -> tuple[dict, float]:
    started = time.perf_counter()
    with torch.no_grad():
        record = estimate_scene(scene, options)
    return record, time.perf_counter() - started


def _apart(a: dict, b: dict, scale: float) -> float:
    """Worst distance between two records' lights, paired as the errors pair them (1.0 for an unpaired one)."""
    pa = torch.tensor([light["position"] for light in a["lights"]]).reshape(-1, 3)
    pb = torch.tensor([light["position"] for light in b["lights"]]).reshape(-1, 3)
    return max(light_errors(pa, None, pb, None, scale, pb.mean(0)).position)


def run(scenes: int, height: int, width: int, seed: int, max_pixels: int | None = Tuning.max_pixels
        ) -> list[dict]:
    sampler = SamplerConfig(height=height, width=width, n_lights_probs=(0.5, 0.5))
    every, default = EstimateOptions(tuning=Tuning(max_pixels=None)), EstimateOptions(tuning=Tuning(max_pixels=max_pixels))
    rows = []
    for name, degradations in VARIANTS.items():
        for index in range(scenes):
            scene = render_item(seed * 1_000_003 + index, sampler, degradations, 2)[1]
            all_record, all_seconds = _estimate(scene, every)
            sub_record, sub_seconds = _estimate(scene, default)
            all_errors, sub_errors = score_record(all_record, scene)[0], score_record(sub_record, scene)[0]
            rows.append({"set": name, "id": scene.id, "true": int(scene.light_pos.shape[0]),
                         "found_all": len(all_record["lights"]), "found_default": len(sub_record["lights"]),
                         "error_all": round(max(all_errors.position), 4), "error_default": round(max(sub_errors.position), 4),
                         "answers_apart": round(_apart(sub_record, all_record, float(scene.scene_scale)), 4),
                         "seconds_all": round(all_seconds, 3), "seconds_default": round(sub_seconds, 3),
                         "stride": pixel_stride(height, width, default.tuning.max_pixels)})
            print(rows[-1], flush=True)
        part = [r for r in rows if r["set"] == name]
        rows.append({"set": name, "id": "all (median, count)", "true": len(part),
                     "found_all": sum(r["found_all"] == r["true"] for r in part),
                     "found_default": sum(r["found_default"] == r["true"] for r in part),
                     "error_all": round(statistics.median(r["error_all"] for r in part), 4),
                     "error_default": round(statistics.median(r["error_default"] for r in part), 4),
                     "answers_apart": max(r["answers_apart"] for r in part),
                     "seconds_all": round(statistics.median(r["seconds_all"] for r in part), 3),
                     "seconds_default": round(statistics.median(r["seconds_default"] for r in part), 3),
                     "stride": part[0]["stride"]})
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", type=int, default=8, help="scenes per variant (clean, sensor noise)")
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--seed", type=int, default=777)
    args = parser.parse_args()
    rows = run(args.scenes, args.height, args.width, args.seed)
    header = (f"Procedural scenes at {args.width}x{args.height} (2x2 AA, half with two lights; seed {args.seed}), "
              "clean and with the estimate_procedural sensor set's degradations, each estimated with the default "
              "mode=estimate settings twice, one file at a time: with every pixel (estimate.max_pixels=null, '_all') "
              "and with the default estimate.max_pixels=76800 ('_default', on every 'stride'-th pixel). found: "
              "lights found (the 'all' rows: scenes with the right count); error: worst light, of the scene size "
              "(1.0: a light missed; the 'all' rows: medians); answers_apart: the worst distance between the two "
              "answers' paired lights, of the scene size (the 'all' rows: the largest); seconds: per scene "
              "(the 'all' rows: medians).")
    write_results("large_images", torch.device("cpu"), rows, header, COLUMNS)


if __name__ == "__main__":
    main()
