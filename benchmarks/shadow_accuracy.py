"""Shadow methods against exact ray casting on an analytic scene.

Sphere and box on a floor with a back wall, lights spread around the scene
(camera side, above, behind the objects, low at the side, behind the camera).
For each light and method: the share of valid pixels, away from a one-pixel
band at exact shadow edges, whose lit/shadowed class (visibility > 0.5) agrees
with exact shadow rays; the share of exactly lit pixels whose rendered value is
within 1e-4 relative; and the time of one forward pass. Results go to
benchmarks/results/shadow_accuracy_<device>_<date>.{md,json}.

    python benchmarks/shadow_accuracy.py [--height 120 --width 160]
"""

from __future__ import annotations

import argparse
import time

import torch

from benchmarks.common import write_results
from render import GBuffer, Material, PointLights, render
from selfsup.scenes.analytic import compare_to_exact, intrinsics_for, objects_on_floor, render_exact_view

LIGHTS = {
    "camera side, right": [0.6, -1.0, 0.5],
    "camera side, left": [-0.8, -0.9, 1.2],
    "above, front": [0.2, -1.5, 2.0],
    "above, front left": [-1.0, -1.5, 3.0],
    "above the objects": [0.2, -2.0, 4.3],
    "behind the objects": [0.0, -2.0, 5.5],
    "low, right": [1.5, -0.5, 2.0],
    "low, left side": [-2.5, 0.0, 4.0],
    "behind the camera": [2.0, -1.0, -1.0],
}


def run(height: int = 120, width: int = 160, methods=("epipolar", "paper"), write: bool = True):
    K = intrinsics_for(height, width)
    prims = objects_on_floor()
    rows = []
    for name, light in LIGHTS.items():
        lp = torch.tensor([light], dtype=torch.float64)
        view = render_exact_view(prims, K, height, width, lp, torch.full((1, 3), 10.0), ks=0.3)
        g = GBuffer(points=view.points[None], normals=view.normals[None], mask=view.mask[None], intrinsics=K[None])
        mat = Material(kd=torch.full((1, height, width, 3), 0.6, dtype=torch.float64),
                       ks=torch.full((1, height, width, 1), 0.3, dtype=torch.float64), shininess=20.0)
        lights = PointLights(position=lp[None], intensity=torch.full((1, 1, 3), 10.0, dtype=torch.float64))
        exact = view.visibility[..., 0]
        row = {"light": name, "position": light, "shadowed_share": round((exact[view.mask] < 0.5).double().mean().item(), 3)}
        for method in methods:
            t0 = time.perf_counter()
            out = render(g, mat, lights, torch.full((1, 3), 0.05, dtype=torch.float64), shadows=method)
            row[f"{method}_seconds"] = round(time.perf_counter() - t0, 4)
            score = compare_to_exact(view, out.visibility[0, 0], out.image[0].permute(1, 2, 0))
            row[f"{method}_agree"] = round(score.agree, 4)
            row[f"{method}_lit_within_1e-4"] = round(score.lit_within_1e4, 4)
        rows.append(row)
    mean = {"light": "**mean**"}
    for key in rows[0]:
        if key.endswith(("_agree", "_within_1e-4", "_seconds")):
            mean[key] = round(sum(r[key] for r in rows) / len(rows), 4)
    rows.append(mean)
    path = None
    if write:
        columns = ["light", "position", "shadowed_share"] + [f"{m}_{k}" for m in methods for k in ("agree", "lit_within_1e-4", "seconds")]
        header = (f"{width}x{height}, float64, exact G-buffer; agree = lit/shadowed class matches exact shadow rays "
                  f"on valid pixels away from a 1-pixel band at exact shadow edges (attached shadows included).")
        path = write_results("shadow_accuracy", torch.device("cpu"), rows, header, columns)
    return rows, path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--width", type=int, default=160)
    args = parser.parse_args()
    rows, path = run(args.height, args.width)
    for row in rows:
        print(row)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
