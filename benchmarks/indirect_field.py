"""How the indirect light of path-traced scenes varies: the measurements behind the
defaults of ``estimate.indirect_variation`` and ``estimate.indirect_length``.

For a folder with ``direct/`` and ``gi/`` renders of the same scenes (the devset,
or ``benchmarks.mitsuba_scenes``' sets), the indirect irradiance of each pixel is
``(gi - direct) / kd`` (channels averaged; pixels with kd under 0.05 left out),
averaged over square blocks (the estimator's criterion blocks: 16 pixels at 160
wide). Per scene: its relative standard deviation between blocks
(``relative_std``), the covariance of the relative deviations ``e = E / mean(E) -
1`` between blocks binned by the distance of their 3D centres (of the scene size;
pooled over the scenes), and how much of the mean indirect irradiance the
estimator's fitted constant ambient takes up (``ambient_share``: the gi file
estimated with the default options).

    python -m benchmarks.indirect_field --folders ../shared/devset data/mitsuba

Results: benchmarks/results/indirect_field_<device>_<date>.{md,json}.
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import torch
from torch import Tensor

from benchmarks.common import write_results
from render import GBuffer
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.criterion import block_px
from selfsup.estimation.stages import estimate_scene
from selfsup.estimation.uncertainty import block_sums
from selfsup.scenes.io import read_scene

COLUMNS = ["folder", "scenes", "median_relative_std", "range_relative_std", "median_ambient_share",
           "covariance_by_distance"]
DISTANCE_BINS = 10  # of 0.1 of the scene size each


def block_irradiance(direct, gi, block: int) -> tuple[Tensor, Tensor]:
    """Mean indirect irradiance ``(n,)`` of the blocks with at least half their pixels
    usable, and their 3D centres ``(n, 3)`` in units of the scene size (the file's ``scene_scale``)."""
    kd = gi.kd.mean(-1)
    usable = (gi.depth > 0) & (kd > 0.05)
    irradiance = torch.where(usable, (gi.image - direct.image).mean(-1) / kd.clamp_min(0.05), 0.0)
    points = GBuffer.from_depth(gi.depth[None], gi.K[None]).points[0]
    points = torch.where(usable[..., None], points, 0.0)
    sums = block_sums(torch.cat([irradiance[None], points.permute(2, 0, 1), usable[None]]).double()[None], block)[0]
    count = sums[4]
    keep = count >= block * block / 2
    mean = sums[:4, keep] / count[keep]
    return mean[0], mean[1:].T / float(gi.scene_scale)


def run(folders: list[str], write: bool = True) -> tuple[list[dict], Path | None]:
    options = EstimateOptions()
    rows = []
    for folder in folders:
        stds, shares = [], []
        covariance, pairs = torch.zeros(DISTANCE_BINS, dtype=torch.float64), torch.zeros(DISTANCE_BINS)
        for path in sorted((Path(folder) / "gi").glob("*.npz")):
            gi, direct = read_scene(path), read_scene(Path(folder) / "direct" / path.name)
            irradiance, centre = block_irradiance(direct, gi, block_px(options, gi.image.shape[1]))
            e = irradiance / irradiance.mean() - 1
            stds.append(float(e.square().mean().sqrt()))
            distance = torch.cdist(centre, centre)
            bin_of = (distance / (1 / DISTANCE_BINS)).long().flatten()
            inside = bin_of < DISTANCE_BINS
            covariance.index_add_(0, bin_of[inside], (e[:, None] * e[None]).flatten()[inside])
            pairs.index_add_(0, bin_of[inside], torch.ones(int(inside.sum())))
            fitted = estimate_scene(gi, options)["ambient"]
            shares.append(statistics.mean(fitted) / float(irradiance.mean()))
        by_distance = (covariance / pairs.clamp_min(1)).tolist()
        rows.append({"folder": Path(folder).name, "scenes": len(stds),
                     "median_relative_std": round(statistics.median(stds), 3),
                     "range_relative_std": f"{min(stds):.2f}-{max(stds):.2f}",
                     "median_ambient_share": round(statistics.median(shares), 3),
                     "covariance_by_distance": " ".join(f"{c:+.3f}" for c, n in zip(by_distance, pairs) if n)})
        print(rows[-1], flush=True)
    path = None
    if write:
        header = ("Indirect irradiance (gi - direct) / kd of path-traced scenes, averaged over the estimator's "
                  "criterion blocks: relative_std, its standard deviation between blocks over its mean (per "
                  "scene; median and range); covariance_by_distance, the covariance of the relative deviations "
                  "between blocks whose 3D centres lie 0-0.1, 0.1-0.2, ... of the scene size apart (pooled; "
                  "the scene's own mean removed, which makes the far bins negative); median_ambient_share, the "
                  "default estimate's fitted ambient over the mean indirect irradiance. The default "
                  "estimate.indirect_variation is about median_relative_std / median_ambient_share, "
                  "estimate.indirect_length about where the covariance has halved, over 1.18 (where a "
                  "Gaussian kernel halves).")
        path = write_results("indirect_field", torch.device("cpu"), rows, header, COLUMNS)
    return rows, path


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--folders", nargs="+", required=True, help="folders holding direct/ and gi/ scene files")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(run(args.folders)[1])
