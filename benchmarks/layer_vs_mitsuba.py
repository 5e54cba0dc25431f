"""The renderer layer against an independent renderer: our images of Mitsuba's scenes, given their true lights.

    python -m benchmarks.layer_vs_mitsuba --scenes data/mitsuba/direct data/mitsuba_closed/direct [--rooms 48]
    python -m benchmarks.layer_vs_mitsuba --bounce --scenes data/mitsuba/gi data/mitsuba_closed/gi

For every scene file of Mitsuba 3's direct light (``benchmarks/mitsuba_scenes.py``: its
geometry, albedo and true lights), ``render.render`` with each shadow setting renders the
image, and the median over the scenes of the relative L1 error on the diffuse pixels
(``ks == 0``: no Blinn-Phong-against-Beckmann mismatch) is reported: ``sum |ours - mitsuba|
/ sum mitsuba`` per scene, and the time of one forward pass. With ``--rooms N`` (default 48)
each setting's lit/shadowed agreement with exact shadow rays on N procedural rooms sits
beside (:func:`benchmarks.shadow_accuracy.setting_agreement`), so one table holds error,
agreement and cost. Results to
``benchmarks/results/layer_vs_mitsuba_<device>_<date>.*``.

``--bounce`` takes Mitsuba's path-traced files instead (``gi``: interreflections, no ambient
given) and compares, with the true lights and albedo and the layer's default shadows, the
direct light alone, the direct light and the best constant ambient per channel (least
squares on the diffuse pixels), and the layer's ``indirect="bounce"`` with its strength and
an ambient per channel solved beside it (the bounce's own cost in ms):
``benchmarks/results/layer_bounce_vs_mitsuba_<device>_<date>.*``.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from benchmarks.common import diffuse_relative_l1, write_results
from benchmarks.shadow_accuracy import procedural_rooms, setting_agreement, shares
from render import PointLights, render
from render.shadows import CubeShadowOptions, EpipolarShadowOptions
from selfsup.scenes.io import read_scene, render_inputs

COLUMNS = ["setting", "scenes", "median_relative_l1", "mean_relative_l1", "ms_per_image"]
AGREEMENT = ["rooms_agree", "rooms_missed", "rooms_extra"]


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
        rel.append(diffuse_relative_l1(image[0], scene, gbuffer.mask[0]))
    return rel, 1000 * statistics.median(times)


def _solved(observed: torch.Tensor, columns: list[torch.Tensor], pixels: torch.Tensor) -> torch.Tensor:
    # observed - fixed ~ sum_k c_k columns[k] (each (3, H, W)), least squares over ``pixels`` (H, W)
    # per channel for per-channel columns: the model's image. columns[0] is the fixed part.
    fixed, free = columns[0], columns[1:]
    out = fixed.clone()
    for c in range(3):
        A = torch.stack([f[c][pixels] for f in free], 1).double()
        b = (observed[c][pixels] - fixed[c][pixels]).double()
        coef = torch.linalg.lstsq(A, b[:, None]).solution[:, 0].clamp_min(0).to(observed.dtype)
        out[c] = fixed[c] + sum(k * f[c] for k, f in zip(coef, free))
    return out


def bounce_errors(files: list[Path], device: torch.device) -> dict[str, tuple[list[float], float]]:
    """Per model, the relative L1 on diffuse valid pixels of each path-traced file and the
    median ms of its render: ``direct``, ``direct + ambient``, ``direct + bounce + ambient``."""
    out = {"direct": ([], []), "direct + best ambient": ([], []), "direct + bounce (strength and ambient solved)": ([], [])}
    for path in files:
        scene = read_scene(path).to(device)
        gbuffer, material, lights = render_inputs(scene)
        point_lights = PointLights(lights.position, lights.intensity)
        started = time.perf_counter()
        with torch.no_grad():
            terms = render(gbuffer, material, point_lights, None, falloff=scene.falloff, indirect="bounce")
        bounce_ms = 1000 * (time.perf_counter() - started)
        started = time.perf_counter()
        with torch.no_grad():
            direct = render(gbuffer, material, point_lights, None, falloff=scene.falloff).image[0]
        direct_ms = 1000 * (time.perf_counter() - started)
        diffuse = gbuffer.mask[0] if scene.ks is None else gbuffer.mask[0] & (scene.ks.amax(-1) == 0)
        observed = scene.image.permute(2, 0, 1)
        kd = material.kd[0].permute(2, 0, 1) * gbuffer.mask[0]
        ambient = [direct] + [kd * (torch.arange(3, device=kd.device) == c)[:, None, None] for c in range(3)]
        bounce = [direct, terms.indirect[0]] + ambient[1:]
        for name, image, ms in (("direct", direct, direct_ms),
                                ("direct + best ambient", _solved(observed, ambient, diffuse), direct_ms),
                                ("direct + bounce (strength and ambient solved)", _solved(observed, bounce, diffuse),
                                 bounce_ms)):
            out[name][0].append(diffuse_relative_l1(image, scene, gbuffer.mask[0]))
            out[name][1].append(ms)
    return {name: (rel, statistics.median(ms)) for name, (rel, ms) in out.items()}


def run_bounce(folders: list[Path], device: str = "cpu", write: bool = True) -> tuple[list[dict], Path | None]:
    files = [p for folder in folders for p in sorted(folder.glob("*.npz"))]
    if not files:
        raise ValueError(f"no scene files (*.npz) in {', '.join(str(f) for f in folders)}: make them with "
                         "python -m benchmarks.mitsuba_scenes --out data/mitsuba")
    where = torch.device(device)
    rows = [{"setting": name, "scenes": len(rel), "median_relative_l1": round(statistics.median(rel), 4),
             "mean_relative_l1": round(statistics.mean(rel), 4), "ms_per_image": round(ms, 2)}
            for name, (rel, ms) in bounce_errors(files, where).items()]
    for row in rows:
        print(row, flush=True)
    path = None
    if write:
        header = (f"Path-traced scene files of Mitsuba 3 ({', '.join(str(f) for f in folders)}; "
                  "benchmarks/mitsuba_scenes.py gi: interreflections, no ambient given), rendered by render.render "
                  "with the file's geometry, kd and true lights, the layer's default shadows: the direct light alone, "
                  "with the best constant ambient per channel, and with indirect='bounce' (its strength and an ambient "
                  "per channel solved by least squares on the diffuse pixels); relative L1 = sum |ours - Mitsuba| / "
                  "sum Mitsuba over the diffuse valid pixels (ks = 0); ms: median time of one forward render (no "
                  "gradient), the bounce's with it.")
        path = write_results("layer_bounce_vs_mitsuba", where, rows, header, COLUMNS)
    return rows, path


def agreement(runs: dict[str, tuple[str, object]], rooms: int, seed: int = 9100) -> dict[str, dict]:
    """Each setting of ``runs`` (:func:`settings`): its agreement, missed and extra shadow
    (:func:`benchmarks.shadow_accuracy.shares`) summed over ``rooms`` procedural rooms."""
    total: dict[str, int] = {}
    for exact in procedural_rooms(rooms, seed):
        for key, value in setting_agreement(exact.scene, exact.visibility, runs).items():
            total[key] = total.get(key, 0) + value
    return {name: {f"rooms_{k.removeprefix(name + '_')}": v for k, v in shares(total, [name]).items()
                   if k != "shadowed_share"} for name in runs}


def run(folders: list[Path], device: str = "cpu", write: bool = True, rooms: int = 48) -> tuple[list[dict], Path | None]:
    files = [p for folder in folders for p in sorted(folder.glob("*.npz"))]
    if not files:
        raise ValueError(f"no scene files (*.npz) in {', '.join(str(f) for f in folders)}: make them with "
                         "python -m benchmarks.mitsuba_scenes --out data/mitsuba")
    where = torch.device(device)
    runs = settings()
    agreed = agreement(runs, rooms) if rooms else {}
    rows = []
    for name, (method, options) in runs.items():
        rel, ms = errors(files, method, options, where)
        rows.append({"setting": name, "scenes": len(rel), "median_relative_l1": round(statistics.median(rel), 4),
                     "mean_relative_l1": round(statistics.mean(rel), 4), "ms_per_image": round(ms, 2),
                     **agreed.get(name, {})})
        print(rows[-1], flush=True)
    path = None
    if write:
        header = (f"Scene files of Mitsuba 3's direct light ({', '.join(str(f) for f in folders)}; "
                  "benchmarks/mitsuba_scenes.py), rendered by render.render with the file's geometry, kd and true "
                  "lights under each shadow setting; relative L1 = sum |ours - Mitsuba| / sum Mitsuba over the "
                  "diffuse valid pixels (ks = 0) of each scene; median and mean over the scenes; ms: median time "
                  "of one forward render (no gradient) on this device.")
        if rooms:
            header += (f" rooms_*: the same setting's cast shadows on {rooms} procedural two-light rooms (seed 9100, "
                       "160x120, exact depth) against exact shadow rays, every light, on the pixels facing the light "
                       "away from a 1-pixel band at exact shadow edges: agree = share of those pixels of the same "
                       "lit/shadowed class; missed (shadowed, lit by the setting) and extra (lit, shadowed by it) as "
                       "shares of the exactly shadowed pixels (benchmarks/shadow_accuracy.py).")
        path = write_results("layer_vs_mitsuba", where, rows, header, COLUMNS + (AGREEMENT if rooms else []))
    return rows, path


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=Path, nargs="+", required=True, help="folders of direct-light scene files")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--rooms", type=int, default=48, help="procedural rooms of the agreement columns (0: none)")
    parser.add_argument("--no-write", action="store_true")
    parser.add_argument("--bounce", action="store_true", help="path-traced files: direct, ambient and bounce models")
    args = parser.parse_args()
    if args.bounce:
        print(run_bounce(args.scenes, args.device, not args.no_write)[1])
    else:
        print(run(args.scenes, args.device, not args.no_write, args.rooms)[1])
