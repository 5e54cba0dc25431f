"""Our renderer against an independent one: the devset's Mitsuba direct-light images.

Each ``direct`` scene of ../shared/devset is rendered with its true lights and
ambient by every shadow method; per valid pixel the error is
``sum_c |ours - mitsuba| / sum_c mitsuba``. Reported: the median error and the
share of pixels within 10%. The glossy objects are Mitsuba microfacet plastic,
which Blinn-Phong only approximates, so no method reaches 100%.
Results: benchmarks/results/devset_render_<device>_<date>.{md,json}.

    python -m benchmarks.devset_render [--devset ../shared/devset]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from benchmarks.common import write_results
from render import render
from selfsup.scenes.io import read_scene, render_inputs

METHODS = ("none", "paper", "epipolar")


def run(devset: str | Path, write: bool = True):
    rows = []
    for path in sorted(Path(devset, "direct").glob("*.npz")):
        scene = read_scene(path)
        g, material, lights = render_inputs(scene)
        ambient = scene.ambient[None] if scene.ambient is not None else None
        row = {"scene": scene.id}
        ref = scene.image.permute(2, 0, 1)
        for method in METHODS:
            image = render(g, material, lights, ambient, shadows=method, falloff=scene.falloff).image[0]
            err = ((image - ref).abs().sum(0) / ref.sum(0).clamp_min(1e-6))[g.mask[0]]
            row[f"{method}_median_error"] = round(err.median().item(), 4)
            row[f"{method}_within_10pct"] = round((err < 0.1).double().mean().item(), 4)
        rows.append(row)
    mean = {"scene": "**mean**"}
    for key in rows[0]:
        if key != "scene":
            mean[key] = round(sum(r[key] for r in rows) / len(rows), 4)
    rows.append(mean)
    path = None
    if write:
        columns = ["scene"] + [f"{m}_{k}" for m in METHODS for k in ("median_error", "within_10pct")]
        header = "Mitsuba 3 direct-light renders (devset/direct) against ours with the true lights, 160x120, float32."
        path = write_results("devset_render", torch.device("cpu"), rows, header, columns)
    return rows, path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--devset", default=str(Path(__file__).resolve().parents[2] / "shared" / "devset"))
    args = parser.parse_args()
    rows, path = run(args.devset)
    for row in rows:
        print(row)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
