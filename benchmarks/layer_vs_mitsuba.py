"""The renderer layer against an independent renderer: our images of Mitsuba's scenes, given their true lights.

    python -m benchmarks.layer_vs_mitsuba --scenes data/mitsuba/direct data/mitsuba_closed/direct

For every scene file of Mitsuba 3's direct light (``benchmarks/mitsuba_scenes.py``: its
geometry, albedo and true lights), ``render.render`` with each shadow setting renders the
image, and the median over the scenes of the relative L1 error on the diffuse pixels
(``ks == 0``: no Blinn-Phong-against-Beckmann mismatch) is reported: ``sum |ours - mitsuba|
/ sum mitsuba`` per scene, and the time of one forward pass. Results to
``benchmarks/results/layer_vs_mitsuba_<device>_<date>.*``.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from benchmarks.common import write_results
from render import PointLights, render
from render.shadows import CubeShadowOptions, EpipolarShadowOptions
from selfsup.scenes.io import read_scene, render_inputs

COLUMNS = ["setting", "scenes", "median_relative_l1", "mean_relative_l1", "ms_per_image"]


def settings() -> dict[str, tuple[str, object]]:
    """The shadow settings compared: name -> (method, options)."""
    out = {"none": ("none", None), "paper (defaults)": ("paper", None),
           "epipolar, layer default": ("epipolar", None),
           "epipolar, unbounded solid": ("epipolar", EpipolarShadowOptions(scene_thickness=None, thickness=None))}
    for t in (0.01, 0.02, 0.03, 0.05):
        out[f"epipolar, scene_thickness={t}"] = ("epipolar", EpipolarShadowOptions(scene_thickness=t))
    for radius, bias in ((0, 0.02), (2, 0.02), (1, 0.01), (1, 0.05)):
        out[f"paper, splat_radius={radius}, bias={bias}"] = ("paper", CubeShadowOptions(splat_radius=radius, bias=bias))
    out["paper, footprint splats and bias"] = ("paper", CubeShadowOptions(footprint=True, splat_radius=0, bias=0.0))
    return out


def errors(files: list[Path], method: str, options, device: torch.device) -> tuple[list[float], float]:
    """Relative L1 on diffuse valid pixels of each file, and the median ms of one render."""
    rel, times = [], []
    for path in files:
        scene = read_scene(path).to(device)
        gbuffer, material, lights = render_inputs(scene)
        ambient = None if scene.ambient is None else scene.ambient[None]
        started = time.perf_counter()
        with torch.no_grad():
            image = render(gbuffer, material, PointLights(lights.position, lights.intensity), ambient,
                           falloff=scene.falloff, shadows=method, shadow_options=options).image
        times.append(time.perf_counter() - started)
        diffuse = gbuffer.mask[0]
        if scene.ks is not None:
            diffuse = diffuse & (scene.ks.amax(-1) == 0)
        observed = scene.image.permute(2, 0, 1)
        pixels = diffuse[None].expand_as(observed)
        rel.append(float((image[0] - observed).abs()[pixels].sum() / observed[pixels].sum().clamp_min(1e-12)))
    return rel, 1000 * statistics.median(times)


def run(folders: list[Path], device: str = "cpu", write: bool = True) -> tuple[list[dict], Path | None]:
    files = [p for folder in folders for p in sorted(folder.glob("*.npz"))]
    where = torch.device(device)
    rows = []
    for name, (method, options) in settings().items():
        rel, ms = errors(files, method, options, where)
        rows.append({"setting": name, "scenes": len(rel), "median_relative_l1": round(statistics.median(rel), 4),
                     "mean_relative_l1": round(statistics.mean(rel), 4), "ms_per_image": round(ms, 2)})
        print(rows[-1], flush=True)
    path = None
    if write:
        header = (f"Scene files of Mitsuba 3's direct light ({', '.join(str(f) for f in folders)}; "
                  "benchmarks/mitsuba_scenes.py), rendered by render.render with the file's geometry, kd and true "
                  "lights under each shadow setting; relative L1 = sum |ours - Mitsuba| / sum Mitsuba over the "
                  "diffuse valid pixels (ks = 0) of each scene; median and mean over the scenes; ms: median time "
                  "of one forward render (no gradient) on this device.")
        path = write_results("layer_vs_mitsuba", where, rows, header, COLUMNS)
    return rows, path


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=Path, nargs="+", required=True, help="folders of direct-light scene files")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args()
    print(run(args.scenes, args.device, not args.no_write)[1])
