"""Shared helpers of the benchmark scripts: device naming, timing, results files, image errors."""

from __future__ import annotations

import datetime as _dt
import json
import platform
import time
from pathlib import Path

import torch

from render import GBuffer
from selfsup.metrics import inside_two_sigma, light_errors

RESULTS = Path(__file__).resolve().parent / "results"


def diffuse_relative_l1(image: torch.Tensor, scene, mask: torch.Tensor) -> float:
    """``sum |image - scene.image| / sum scene.image`` over the valid (``mask (H, W)``) diffuse
    (ks = 0) pixels of ``image (3, H, W)``."""
    diffuse = mask if scene.ks is None else mask & (scene.ks.amax(-1) == 0)
    observed = scene.image.permute(2, 0, 1)
    pixels = diffuse[None].expand_as(observed)
    return float((image - observed).abs()[pixels].sum() / observed[pixels].sum().clamp_min(1e-12))


def score_record(record: dict, scene):
    """One estimation record (a JSON line of ``mode=estimate``) against its scene
    file's truth: the :class:`selfsup.metrics.LightErrors` (angles about the centroid
    of the scene's valid points; relative intensity errors of the paired lights) and
    how many true lights fall inside the 2-sigma ellipsoid of their paired estimate's
    ``position_cov``."""
    position = torch.tensor([light["position"] for light in record["lights"]]).reshape(-1, 3)
    intensity = torch.tensor([light["intensity"] for light in record["lights"]]).reshape(-1, 3)
    cov = torch.tensor([light["position_cov"] for light in record["lights"]], dtype=torch.float64).reshape(-1, 3, 3)
    g = GBuffer.from_depth(scene.depth[None], scene.K[None])
    errors = light_errors(position, intensity, scene.light_pos, scene.light_intensity, float(scene.scene_scale),
                          g.points[0][g.mask[0]].mean(0))
    return errors, inside_two_sigma(position, cov, scene.light_pos)


def device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"{platform.processor() or platform.machine()} CPU, {torch.get_num_threads()} threads"


def device_slug(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device).replace(" ", "-").lower()
    return f"cpu{torch.get_num_threads()}"


def timed(fn, device: torch.device, min_repeats: int = 3, min_seconds: float = 0.5) -> float:
    """Median wall time of ``fn()`` in seconds after one warm-up call."""
    fn()
    times = []
    start = time.perf_counter()
    while len(times) < min_repeats or time.perf_counter() - start < min_seconds:
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - t0)
        if len(times) >= 50:
            break
    times.sort()
    return times[len(times) // 2]


def machine_reference(repeats: int = 7) -> dict:
    """This CPU's speed now, on a fixed workload that no code of the project touches.

    The shared 2-core machine's speed drifts by 20-40% between minutes and days, so
    CPU results of different dates compare only through it: ``elementwise_ns``, one
    thread's time per element and pass of ``x * a + b`` over 65,536 float32 (two passes,
    the product then the sum into a kept tensor: the kind of pass the ray caster and
    the solvers are made of), and ``matmul_gflops``, a 512 x 512 float32
    matmul on the current threads. Medians of ``repeats`` timings; about 0.1 s.
    """
    threads = torch.get_num_threads()
    x = torch.rand(65536)
    out = torch.empty_like(x)
    a = torch.rand(512, 512)
    elementwise, matmul = [], []
    try:
        torch.set_num_threads(1)
        for _ in range(repeats):
            t0 = time.perf_counter()
            for _ in range(50):
                torch.add(x * 1.0001, 0.5, out=out)
            elementwise.append((time.perf_counter() - t0) / (50 * 2 * x.numel()))
    finally:
        torch.set_num_threads(threads)
    for _ in range(repeats):
        t0 = time.perf_counter()
        a @ a
        matmul.append(time.perf_counter() - t0)
    elementwise.sort()
    matmul.sort()
    return {"elementwise_ns": round(1e9 * elementwise[repeats // 2], 3),
            "matmul_gflops": round(2 * 512**3 / matmul[repeats // 2] / 1e9, 1), "threads": threads}


def write_results(name: str, device: torch.device, rows: list[dict], header: str, columns: list[str]) -> Path:
    """Write ``rows`` as markdown and JSON to ``benchmarks/results/<name>_<device>_<date>.*``
    (``..._<date>_2.*``, ``_3``, ... where a run of the same day wrote that name already: a
    rerun never replaces the results an earlier one left); CPU results carry the
    :func:`machine_reference` timed as they are written. Returns the markdown file's path."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    date = _dt.date.today().isoformat()
    base = f"{name}_{device_slug(device)}_{date}"
    stem, run = RESULTS / base, 1
    while stem.with_suffix(".md").exists() or stem.with_suffix(".json").exists():
        run += 1
        stem = RESULTS / f"{base}_{run}"
    meta = {"device": device_name(device), "date": date, "torch": torch.__version__}
    lines = [f"# {name}", "", f"Device: {meta['device']}; torch {meta['torch']}; date {date}.", ""]
    if device.type == "cpu":
        meta["machine_reference"] = reference = machine_reference()
        lines += [f"Machine reference (a fixed workload timed as this file was written; compare CPU results "
                  f"of different dates by it): {reference['elementwise_ns']} ns per element of an elementwise "
                  f"pass (one thread), {reference['matmul_gflops']} GFLOP/s in a 512 x 512 matmul "
                  f"({reference['threads']} threads).", ""]
    stem.with_suffix(".json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    lines += [header, ""]
    lines.append("| " + " | ".join(columns) + " |")
    lines.append("|" + "---|" * len(columns))
    for row in rows:
        lines.append("| " + " | ".join(str(row.get(c, "")) for c in columns) + " |")
    stem.with_suffix(".md").write_text("\n".join(lines) + "\n")
    return stem.with_suffix(".md")


def side_by_side(image: torch.Tensor, composite: torch.Tensor, depth: torch.Tensor, scale: int = 1):
    """A frame's ``image`` beside its ``composite`` (both linear ``(H, W, 3)``), sRGB-encoded at
    the image's 99th percentile on valid ``depth`` (> 0), 8 bits, ``scale`` times enlarged:
    an animation's frame (``(H scale, (2 W + 2) scale, 3)`` uint8)."""
    import numpy as np

    from selfsup.scenes.capture import linear_to_srgb

    level = float(image[depth > 0].quantile(0.99)) or 1.0
    panels = [linear_to_srgb((x / level).clamp(0, 1).numpy()) for x in (image, composite)]
    row = np.concatenate([panels[0], np.ones_like(panels[0][:, :2]), panels[1]], 1)
    row = np.round(np.clip(row, 0, 1) * 255).astype(np.uint8)
    return row.repeat(scale, 0).repeat(scale, 1)


def write_animation(out: Path, pictures: list, fps: float) -> Path:
    """``pictures`` (equal ``(H, W, 3)`` uint8 arrays) as a looping GIF at ``fps``; says its size."""
    import imageio.v3 as iio
    import numpy as np

    out.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(out, np.stack(pictures), duration=1000 / fps, loop=0)
    print(f"{out}: {len(pictures)} frames, {out.stat().st_size / 1024:.0f} KiB", flush=True)
    return out

