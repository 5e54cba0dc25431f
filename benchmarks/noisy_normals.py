"""Error of the normals the estimator refits from noisy depth, against the clean ones.

    python -m benchmarks.noisy_normals data/mitsuba data/mitsuba_closed [--every 2]

Each folder holds ``noisy/`` and ``direct/`` variants of the same scenes (as
``benchmarks.mitsuba_scenes`` writes them); the noisy file's normals are refitted by
:func:`selfsup.estimation.prepare` with ``estimate.plane_shifts`` empty (each pixel's
own plane window) and with the default shifts, and compared, pixel by pixel over the
valid ones, with the direct file's normals. Writes percentiles of the angle and the
share over 10 degrees to ``benchmarks/results/noisy_normals_<device>_<date>.*``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from benchmarks.common import write_results
from selfsup.estimation.options import EstimateOptions, Tuning
from selfsup.estimation.prepare import prepare
from selfsup.scenes.io import read_scene

PERCENTILES = (50, 75, 90, 95, 98)
COLUMNS = ["plane_shifts", "files", "pixels"] + [f"p{p}_deg" for p in PERCENTILES] + ["over_10_deg"]


def normal_errors(pairs: list[tuple[Path, Path]], options: EstimateOptions) -> torch.Tensor:
    """Angles (degrees) between the refitted normals of each noisy file and its clean file's normals."""
    angles = []
    for noisy_file, clean_file in pairs:
        noisy, clean = read_scene(noisy_file), read_scene(clean_file)
        if clean.normals is None:
            raise ValueError(f"{clean_file} holds no normals to compare with")
        problem = prepare([noisy], options)
        cos = (problem.gbuffer.normals[0] * clean.normals).sum(-1).clamp(-1, 1)
        angles.append(torch.rad2deg(torch.acos(cos))[problem.gbuffer.mask[0]])
    return torch.cat(angles)


def run(folders: list[str], every: int = 1, write: bool = True) -> list[dict]:
    pairs = [(noisy, Path(folder) / "direct" / noisy.name) for folder in folders
             for noisy in sorted((Path(folder) / "noisy").glob("*.npz"))[::every]]
    if not pairs:
        raise ValueError(f"no noisy/*.npz files under {folders}")
    rows = []
    for options in (EstimateOptions(tuning=Tuning(plane_shifts=())), EstimateOptions()):
        angles = normal_errors(pairs, options)
        levels = torch.quantile(angles.double(), torch.tensor(PERCENTILES, dtype=torch.float64) / 100)
        rows.append({"plane_shifts": str(list(options.tuning.plane_shifts)), "files": len(pairs), "pixels": angles.numel(),
                     **{f"p{p}_deg": round(float(v), 2) for p, v in zip(PERCENTILES, levels)},
                     "over_10_deg": round(float((angles > 10).double().mean()), 3)})
        print(rows[-1])
    if write:
        print(write_results("noisy_normals", torch.device("cpu"), rows,
                            f"Normals refitted from the noisy files of {', '.join(folders)} (one file in {every}) "
                            "by the estimator's prepare, against the direct files' normals: angle percentiles "
                            "(degrees) over valid pixels and the share over 10 degrees.", COLUMNS))
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="+")
    parser.add_argument("--every", type=int, default=1, help="take every n-th file of each folder")
    args = parser.parse_args()
    run(args.folders, args.every)
