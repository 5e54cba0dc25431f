"""The network (or the whole estimator) on our generator's objects in the dark, against truth.

    python -m benchmarks.studio_frames --option method=cnn --option checkpoint=selfsup/checkpoints/iterative_studio.pt
    python -m benchmarks.studio_frames --option method=cnn --option checkpoint=selfsup/checkpoints/iterative.pt --name studio_frames_rooms
    python -m benchmarks.studio_frames --count 24 --arrangement overlapping --depth integrated --name studio_frames_integrated
    python -m benchmarks.studio_frames --count 24 --arrangement overlapping --depth integrated --normals --name studio_frames_integrated_normals

``--count`` frames (default 12) of :func:`selfsup.scenes.studio.studio_spec`, each photographed as
a photometric-stereo set is (:func:`selfsup.scenes.studio.photograph`: auto exposure, sRGB, 8
bits, millimetre depth): the lamp's direction from the sphere drawn from a fixed seed (in front of
the object, above the camera's axis), the paint cycling through plain and
:data:`selfsup.scenes.studio.HARD_PAINTS`, the box and cylinder beside it in every other frame.
Each frame is estimated with ``mode=estimate``'s settings plus ``--option``s and scored by the
angle between the true direction and the sphere's centre to the brightest light. Results:
``benchmarks/results/<name>_<device>_<date>.*`` (a row per frame and a median row).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile

import numpy as np
import torch

from benchmarks.common import write_results
from benchmarks.estimate_procedural import parse_options
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.stages import estimate_scene
from selfsup.scenes.studio import ARRANGEMENTS, DEPTHS, HARD_PAINTS, lamp_angle_deg, photograph, studio_spec

COLUMNS = ["frame", "paint", "others", "direction", "angle_deg", "light_found"]


def frames(count: int, seed: int = 0) -> list[tuple[tuple[float, float, float], str, bool]]:
    """``count`` (direction, paint name, others): directions towards the camera and above its axis."""
    rng = np.random.default_rng(seed)
    paints = ["plain", *HARD_PAINTS]
    out = []
    for k in range(count):
        d = rng.normal(size=3)
        d[2], d[1] = -abs(d[2]) - 0.3, -abs(d[1])
        d /= np.linalg.norm(d)
        out.append((tuple(float(x) for x in d), paints[k % len(paints)], bool(k % 2)))
    return out


def run(count: int, options: EstimateOptions, name: str, write: bool = True, arrangement: str = "apart",
        depth: str = "rendered", normals: bool = False) -> list[dict]:
    rows = []
    for k, (direction, paint, others) in enumerate(frames(count)):
        others = others or arrangement == "overlapping"  # overlapping: the parts in every frame
        spec = studio_spec(direction, others=others, seed=k, arrangement=arrangement, **HARD_PAINTS.get(paint, {}))
        with tempfile.TemporaryDirectory() as folder:
            record = estimate_scene(photograph(folder, spec, seed=k, depth=depth, normals=normals), options)
        rows.append({"frame": k, "paint": paint, "others": others, "direction": [round(x, 3) for x in direction],
                     "angle_deg": round(lamp_angle_deg(record, spec, direction), 2), "light_found": record["light_found"]})
        print(rows[-1], flush=True)
    rows.append({"frame": "**median**", "angle_deg": round(statistics.median(r["angle_deg"] for r in rows), 2)})
    if write:
        header = (f"Objects in the dark (`python -m benchmarks.studio_frames`, {count} frames, the box and the "
                  f"cylinder {arrangement}, the depth {depth}{', the true normals given' if normals else ''}), each "
                  f"estimated with the settings changed: {options_text(options)}; the angle between the "
                  "true lamp direction and the sphere's centre to the brightest light (90 where none).")
        print(write_results(name, torch.device("cpu"), rows, header, COLUMNS))
    return rows


def options_text(options: EstimateOptions) -> str:
    return f"method={options.method}, checkpoint={options.checkpoint}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, default=12)
    parser.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                        help="an estimate setting or tuned constant, e.g. method=cnn (repeatable)")
    parser.add_argument("--name", default="studio_frames")
    parser.add_argument("--arrangement", choices=ARRANGEMENTS, default="apart",
                        help="overlapping: the box and the cylinder in every frame, hiding parts of the sphere and hidden")
    parser.add_argument("--depth", choices=DEPTHS, default="rendered",
                        help="integrated: the depth integrated from the true normals, as DiLiGenT's objects' was made")
    parser.add_argument("--normals", action="store_true",
                        help="the true normals written in each capture folder (normals/<id>.npy) and read instead of the depth's")
    args = parser.parse_args()
    if args.count < 1:
        raise SystemExit("--count must be >= 1")
    run(args.count, EstimateOptions.from_settings(**parse_options(args.option)), args.name, arrangement=args.arrangement,
        depth=args.depth, normals=args.normals)


if __name__ == "__main__":
    main()
