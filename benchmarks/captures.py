"""Camera captures made from scene files, and the estimator scored on them.

    python -m benchmarks.captures make --scenes data/mitsuba --out data/captures/mitsuba
    python -m benchmarks.captures procedural --out data/procedural     # our own scenes: direct/ and noisy/ files
    python -m benchmarks.captures make --scenes data/procedural --out data/captures/procedural --sets direct noisy
    python -m benchmarks.captures run --captures data/captures/mitsuba data/captures/mitsuba_closed data/captures/procedural
    python -m benchmarks.captures realities --out data/captures/realities    # cameras' and rooms' realities
    python -m benchmarks.captures run --captures data/captures/realities --sets plain camera camera_640 phone panel window

``make`` turns each set (``direct``, ``gi``, ``noisy``) of scene files into a capture
folder of the layout ``mode=estimate`` reads (``docs/scene-format.md``, "Capture
folders") by the recipe of ``../shared/devset_captures/README.md``: the linear image
times an exposure that puts the 99th percentile of the valid pixels' values at 0.5-2.0
of full scale (drawn per frame, log-uniform, from the frame's name: the same folder
every time), encoded as sRGB and rounded to 8 bits (clipped pixels included); depth
rounded to 16-bit millimetres; intrinsics per frame. No albedo, materials, normals or
ambient. ``truth/<id>.npz`` keeps the lights for scoring (intensities in the exposed
image's units), the depth in metres, K and the scene size.

``run`` estimates every set of each captures root with the default ``mode=estimate``
settings and scores it against ``truth/``: success (every light within 0.05 of the
scene size), one-light success, two-light right count, the median worst position
error and seconds; a results file ``benchmarks/results/capture_estimate_<device>_<date>.*``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import statistics
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from benchmarks.common import score_record, write_results
from selfsup.scenes.capture import linear_to_srgb
from selfsup.scenes.io import read_scene

SETS = ("direct", "gi", "noisy")
EXPOSURE_RANGE = (0.5, 2.0)  # the 99th percentile of the valid values lands in this share of full scale
COLUMNS = ["root", "set", "scenes", "success", "one_light_success", "two_light_right_count", "median_worst_error",
           "one_light_median_angle",
           "two_sigma_coverage", "placed_two_sigma_coverage", "seconds_per_frame", "command_seconds_per_frame"]
ROOT = Path(__file__).resolve().parents[1]


def command_seconds(folder: Path, device: str = "cpu", options=None) -> float:
    """Wall time of ``python train.py mode=estimate estimate.device=<device>`` on ``folder``,
    Python's start-up and the network's load included, over its frames (the settings that
    ``options`` changes given on its command line, the others as by default: on 2 cores, 2
    workers)."""
    import subprocess
    import sys

    from selfsup.estimation import Tuning
    from selfsup.scenes.capture import capture_frames

    changed = options.changed_settings() if options is not None else {}
    settings = [f"+estimate.tuning.{key}={value}" if key in Tuning.names() else f"estimate.{key}={value}"
                for key, value in changed.items()]
    with tempfile.TemporaryDirectory() as tmp:
        started = time.perf_counter()
        subprocess.run([sys.executable, "train.py", "mode=estimate", f"estimate.input={folder.resolve()}",
                        f"estimate.output={tmp}/o.jsonl", "estimate.progress=false", f"estimate.device={device}",
                        f"hydra.run.dir={tmp}/run", *settings], cwd=ROOT, check=True, capture_output=True)
        return round((time.perf_counter() - started) / max(len(capture_frames(folder)), 1), 3)


def _exposure_draw(name: str) -> float:
    # A log-uniform draw in EXPOSURE_RANGE from the frame's name (reproducible, order-free).
    u = int(hashlib.sha256(name.encode()).hexdigest()[:12], 16) / 16**12
    lo, hi = (math.log(x) for x in EXPOSURE_RANGE)
    return math.exp(lo + u * (hi - lo))


def make_capture(scene_path: Path, out: Path, frame_id: str) -> None:
    """One scene file as a capture frame of folder ``out`` (colour, depth, intrinsics, truth)."""
    write_capture(read_scene(scene_path), out, frame_id, source=str(scene_path))


def capture_exposure(scene, frame_id: str) -> float:
    """The exposure of the recipe: the 99th percentile of the valid values at a share of
    full scale drawn from ``frame_id`` (:func:`_exposure_draw`)."""
    image, depth = scene.image.double().numpy(), scene.depth.double().numpy()
    valid = np.isfinite(depth) & (depth > 0)
    return _exposure_draw(frame_id) / max(float(np.percentile(image[valid], 99)), 1e-12)


def write_capture(scene, out: Path, frame_id: str, exposure: float | None = None, source: str = "") -> None:
    """``scene`` as a capture frame of folder ``out`` at ``exposure`` (None: the recipe's
    draw, :func:`capture_exposure`; a sequence keeps one for every frame, as a camera with
    its exposure locked)."""
    exposure = capture_exposure(scene, frame_id) if exposure is None else exposure
    image, depth = scene.image.double().numpy(), scene.depth.double().numpy()
    valid = np.isfinite(depth) & (depth > 0)
    color = np.round(linear_to_srgb(image * exposure) * 255).astype(np.uint8)
    millimetres = np.round(np.where(valid, depth, 0.0) * 1000).clip(0, 65535).astype(np.uint16)
    import imageio.v3 as iio

    for sub in ("color", "depth", "intrinsics", "truth"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    iio.imwrite(out / "color" / f"{frame_id}.png", color)
    iio.imwrite(out / "depth" / f"{frame_id}.png", millimetres)
    K = scene.K.double().numpy()
    (out / "intrinsics" / f"{frame_id}.json").write_text(json.dumps(
        {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}))
    meta = {**scene.meta, "id": frame_id, "source_file": source, "exposure": exposure}
    truth = {"depth": scene.depth.numpy(), "K": scene.K.numpy(), "meta": np.array(json.dumps(meta))}
    if scene.light_pos is not None:
        truth.update(light_pos=scene.light_pos.numpy(), light_intensity=scene.light_intensity.numpy() * exposure)
    if scene.scene_scale is not None:
        truth["scene_scale"] = scene.scene_scale.numpy()
    np.savez_compressed(out / "truth" / f"{frame_id}.npz", **truth)


def make(scenes: Path, out: Path, sets=SETS) -> list[Path]:
    """Capture folders ``out/<set>`` of the scene files of ``scenes/<set>``."""
    made = []
    for set_name in sets:
        files = sorted((scenes / set_name).glob("*.npz"))
        for path in files:
            make_capture(path, out / set_name, f"capture_{scenes.name}_{set_name}_{path.stem}")
        made.append(out / set_name)
        print(f"{out / set_name}: {len(files)} frames", flush=True)
    return made


# The sensor set of configs/eval and benchmarks/estimate_procedural: depth noise and
# quantisation growing with z^2, holes, image noise.
SENSOR = dict(depth_noise=0.003, depth_quantisation=0.001, edge_hole_jump=0.05, random_holes=0.01, image_noise=0.005)


def procedural_scenes(seeds: list[int], n_lights: int, sensor: bool) -> list:
    """The scenes of ``seeds`` as :func:`procedural` writes them: our generator at 160x120
    (2x2 AA), ``n_lights`` lights each, exact or under the :data:`SENSOR` degradations."""
    from selfsup.scenes.dataset import render_items
    from selfsup.scenes.degrade import Degradations
    from selfsup.scenes.sampler import SamplerConfig

    sampler = SamplerConfig(height=120, width=160, n_lights_probs=(1.0,) if n_lights == 1 else (0.0, 1.0))
    degradations = Degradations(**SENSOR) if sensor else Degradations()
    return [scene for _, scene in render_items(seeds, sampler, degradations, 2)]


def procedural(out: Path, count: int = 48, seed: int = 7000) -> None:
    """Scene files of our generator (:func:`procedural_scenes`) in ``out/direct`` (exact) and
    ``out/noisy`` (the sensor degradations): the first half of the scenes with one light,
    the rest with two, as the Mitsuba sets."""
    from selfsup.scenes.io import write_scene

    for set_name, sensor in (("direct", False), ("noisy", True)):
        (out / set_name).mkdir(parents=True, exist_ok=True)
        for lights, first in ((1, 0), (2, count // 2)):
            indices = range(first, first + count // 2)
            for i, scene in zip(indices, procedural_scenes([seed + i for i in indices], lights, sensor)):
                write_scene(out / set_name / f"scene_{i:03d}.npz", scene)
        print(f"{out / set_name}: {count} scene files", flush=True)


# The camera-realities sets (``realities``): (light, render width x height, camera model settings).
REALITY_SETS = {
    "plain": ("point", (160, 120), dict(key=None, white_balance=False, vignetting=0.0, jpeg_quality=None,
                                        misregistration_px=0.0, disparity_step=0.0, depth_bumps=0.0, edge_holes=0.0,
                                        random_holes=0.0)),
    "camera": ("point", (160, 120), {}),
    "camera_640": ("point", (640, 480), {}),
    "phone": ("point", (768, 576), dict(color_size=(1920, 1440), depth_size=(256, 192))),
    "panel": ("panel", (160, 120), {}),
    "window": ("window", (160, 120), {}),
}
# One camera reality at a time beside the plain recipe, and the whole camera but its lens:
# which of them costs what (docs/decisions.md, 2026-11-28).
_PLAIN = REALITY_SETS["plain"][2]
REALITY_SETS.update({name: ("point", (160, 120), {**_PLAIN, **change}) for name, change in {
    "lens_15": dict(vignetting=0.15), "lens_30": dict(vignetting=0.3), "lens_45": dict(vignetting=0.45),
    "exposure": dict(key=(0.12, 0.3)), "white_balance": dict(white_balance=True), "jpeg": dict(jpeg_quality=85),
    "misregistered": dict(misregistration_px=2.0),
    "depth_sensor": dict(disparity_step=0.0028, depth_bumps=0.002, edge_holes=0.04, random_holes=0.01),
}.items()})
REALITY_SETS["camera_no_lens"] = ("point", (160, 120), dict(vignetting=0.0))


def realities(out: Path, count: int = 12, seed: int = 9000, sets=tuple(REALITY_SETS)) -> None:
    """Capture folders ``out/<set>`` of our procedural rooms (one light each, the same
    ``count`` rooms in every set) through what cameras and rooms do
    (:mod:`selfsup.scenes.camera`): ``plain`` (the recipe's sRGB, 8 bits and millimetres
    at an exposure that puts the mean at 0.2 of full scale), ``camera`` (auto exposure,
    white balance, vignetting, JPEG, colour 0-2 px off the depth, a structured-light
    depth sensor), ``camera_640`` (the same at 640x480), ``phone`` (1920x1440 JPEG colour
    beside 256x192 depth), ``panel`` and ``window`` (area lights: a 0.6 m ceiling panel,
    a 1.2 m window in front of the back wall; truth at their centres). ``truth/`` as
    :func:`write_capture` writes it, the intensities those of the light's whole area."""
    from selfsup.scenes.camera import CameraModel, camera_capture, with_area_lights, write_capture_frame
    from selfsup.scenes.exact import render_specs
    from selfsup.scenes.sampler import SamplerConfig, sample_scene

    for set_name in sets:
        light, (width, height), settings = REALITY_SETS[set_name]
        model = CameraModel(**settings)
        specs, centres = [], []
        for k in range(count):
            spec = sample_scene(seed + k, SamplerConfig(height=height, width=width, specular_prob=0.0,
                                                        n_lights_probs=(1.0,)))
            centre = spec.light_position
            if light != "point":
                spec, centre = with_area_lights(spec, light, size=0.6 if light == "panel" else 1.2,
                                                points=4 if light == "panel" else 5)
            specs.append(spec)
            centres.append(centre)
        folder = out / set_name
        (folder / "truth").mkdir(parents=True, exist_ok=True)
        for k, (rendered, centre) in enumerate(zip(render_specs(specs, samples=1), centres)):
            scene, frame_id = rendered.scene, f"{set_name}_{k:03d}"
            valid = scene.depth > 0
            plain_exposure = 0.2 / max(float(scene.image[valid].mean()), 1e-12)
            shot = camera_capture(scene.image, scene.depth, scene.K, model, seed + k, exposure=plain_exposure)
            write_capture_frame(folder, frame_id, shot)
            per_light = scene.light_intensity.reshape(centre.shape[0], -1, 3).sum(1)  # an area's points summed
            meta = {**scene.meta, "id": frame_id, "set": set_name, "exposure": shot.exposure,
                    "white_balance_gains": shot.gains.tolist(), "colour_shift_px": list(shot.shift_px)}
            np.savez_compressed(folder / "truth" / f"{frame_id}.npz", depth=scene.depth.numpy(), K=scene.K.numpy(),
                                meta=np.array(json.dumps(meta)), light_pos=centre.numpy(),
                                light_intensity=(per_light * shot.exposure).numpy(),
                                scene_scale=scene.scene_scale.numpy())
        print(f"{folder}: {count} frames", flush=True)


def read_truth(path: Path) -> SimpleNamespace:
    """A capture's truth file as the fields :func:`benchmarks.common.score_record` reads."""
    data = np.load(path, allow_pickle=False)
    t = {k: torch.from_numpy(np.array(data[k], dtype=np.float32)) for k in data.files if k != "meta"}
    return SimpleNamespace(**t, meta=json.loads(str(data["meta"])))


def score(folder: Path, estimates: Path) -> list[dict]:
    """One row per frame of ``estimates`` against ``folder/truth``: found and true light
    counts, the worst position error, success, seconds; how many true lights lie inside
    the 2-sigma ellipsoid (``position_cov``) of the estimate paired with them, and of the
    true lights placed (paired within 0.05 of the scene size), how many and how many inside."""
    from selfsup.metrics import SUCCESS_THRESHOLD, paired_inside_two_sigma

    rows = []
    for line in estimates.read_text().splitlines():
        record = json.loads(line)
        truth = read_truth(folder / "truth" / f"{record['id']}.npz")
        errors, _ = score_record(record, truth)
        found = torch.tensor([light["position"] for light in record["lights"]], dtype=torch.float64).reshape(-1, 3)
        cov = torch.tensor([light["position_cov"] for light in record["lights"]], dtype=torch.float64)
        paired = paired_inside_two_sigma(found, cov.reshape(-1, 3, 3), truth.light_pos)
        placed = [inside for distance, inside in paired if distance < SUCCESS_THRESHOLD * float(truth.scene_scale)]
        rows.append({"id": record["id"], "found": len(record["lights"]), "true": truth.light_pos.shape[0],
                     "worst": max(errors.position), "success": errors.success, "seconds": record["seconds"],
                     "angle": errors.angular[0] if errors.angular else None,
                     "inside": sum(inside for _, inside in paired), "placed": len(placed),
                     "placed_inside": sum(placed)})
    return rows


def summary(root: str, set_name: str, rows: list[dict], frames: int, wall: float) -> dict:
    """The table's row of one set: ``success`` over every frame (a frame that failed counts
    as a miss); the one- and two-light columns over the frames estimated."""
    one = [r for r in rows if r["true"] == 1]
    two = [r for r in rows if r["true"] == 2]

    def share(hits: int, total: int) -> str:
        return f"{hits}/{total} ({100 * hits / total:.0f}%)" if total else "-"

    return {"root": root, "set": set_name, "scenes": frames, "success": share(sum(r["success"] for r in rows), frames),
            "one_light_success": share(sum(r["success"] for r in one), len(one)),
            "two_light_right_count": share(sum(r["found"] == 2 for r in two), len(two)),
            "median_worst_error": round(statistics.median([r["worst"] for r in rows]), 4) if rows else "",
            "one_light_median_angle": round(statistics.median([180.0 if r["angle"] is None else r["angle"] for r in one]), 2)
            if one else "",
            "two_sigma_coverage": share(sum(r["inside"] for r in rows), sum(r["true"] for r in rows)),
            "placed_two_sigma_coverage": share(sum(r["placed_inside"] for r in rows), sum(r["placed"] for r in rows)),
            "seconds_per_frame": round(wall / max(frames, 1), 3)}


def run(roots: list[Path], sets=SETS, write: bool = True, options=None, name: str = "capture_estimate",
        command_time: bool = False, device: str = "cpu") -> tuple[list[dict], Path | None]:
    """Estimate every set of each captures root (``mode=estimate``'s defaults, or
    ``options``) on ``device`` and score it; one row per set."""
    from selfsup.estimation import EstimateOptions, estimate_files
    from selfsup.scenes.capture import capture_frames

    options = options or EstimateOptions()
    rows = []
    for root in roots:
        for set_name in sets:
            folder = root / set_name
            if not folder.is_dir():
                continue
            with tempfile.TemporaryDirectory() as tmp:
                output = Path(tmp) / "lights.jsonl"
                started = time.perf_counter()
                estimate_files(folder, output, options, progress=False, batch=4, workers="auto", device=device)
                wall = time.perf_counter() - started
                scored = score(folder, output) if output.exists() else []
            rows.append(summary(root.name, set_name, scored, len(capture_frames(folder)), wall))
            rows[-1]["command_seconds_per_frame"] = command_seconds(folder, device, options) if command_time else ""
            print(rows[-1], flush=True)
    path = None
    if write:
        header = ("Capture folders (8-bit sRGB colour at an unknown exposure, 16-bit millimetre depth, intrinsics; no "
                  "albedo, materials, normals or ambient) made by `python -m benchmarks.captures make` from scene "
                  "files, estimated by `mode=estimate` with the default settings (batch 4, workers auto) and scored "
                  "against truth/: success = every light within 0.05 of the scene size; one-light success; two-light "
                  "right count = two lights found in the two-light scenes; median worst position error (of the scene "
                  "size); one-light median angle = degrees between the true and the found light seen from the centroid of the frame's points (one-light rooms; none found: 180); two-sigma coverage = true lights inside the 2-sigma ellipsoid (95.4%) of the estimate paired with "
                  "them (`position_cov`; an unpaired light is outside), of all true lights; placed two-sigma coverage = "
                  "the same of the true lights placed within 0.05; seconds per frame = estimate_files' wall time over the frames (the network's load included, "
                  "Python's start not); command seconds per frame (with --command-time) = `python train.py "
                  "mode=estimate` on the folder, start-up included, over its frames."
                  + (f" Settings changed: {options.changed_settings()}." if options.changed_settings() else ""))
        path = write_results(name, torch.device(device), rows, header, COLUMNS)
    return rows, path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    m = sub.add_parser("make", help="capture folders from scene files")
    m.add_argument("--scenes", type=Path, required=True, help="a folder with direct/ gi/ noisy/ scene files")
    m.add_argument("--out", type=Path, required=True)
    m.add_argument("--sets", nargs="+", default=list(SETS))
    g = sub.add_parser("procedural", help="scene files of our generator, exact and with sensor noise")
    g.add_argument("--out", type=Path, required=True)
    g.add_argument("--count", type=int, default=48)
    g.add_argument("--seed", type=int, default=7000)
    c = sub.add_parser("realities", help="capture folders through what cameras and rooms do (selfsup.scenes.camera)")
    c.add_argument("--out", type=Path, required=True)
    c.add_argument("--count", type=int, default=12)
    c.add_argument("--seed", type=int, default=9000)
    c.add_argument("--sets", nargs="+", default=list(REALITY_SETS))
    r = sub.add_parser("run", help="estimate and score capture folders")
    r.add_argument("--captures", type=Path, nargs="+", required=True, help="roots with direct/ gi/ noisy/ captures")
    r.add_argument("--sets", nargs="+", default=list(SETS))
    r.add_argument("--no-write", action="store_true")
    r.add_argument("--name", default="capture_estimate", help="the results file's name")
    r.add_argument("--command-time", action="store_true", help="also time the command itself on each folder")
    r.add_argument("--device", default="cpu", help="cpu or cuda[:i]: where the estimator and the command run")
    r.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="an estimate setting or tuned constant, e.g. coat='never' (repeatable)")
    args = parser.parse_args()
    if args.command == "make":
        make(args.scenes, args.out, args.sets)
    elif args.command == "procedural":
        procedural(args.out, args.count, args.seed)
    elif args.command == "realities":
        realities(args.out, args.count, args.seed, args.sets)
    else:
        from benchmarks.estimate_procedural import parse_options
        from selfsup.estimation import EstimateOptions

        options = EstimateOptions.from_settings(**parse_options(args.option))
        print(run(args.captures, args.sets, write=not args.no_write, options=options, name=args.name,
                  command_time=args.command_time, device=args.device)[1])


if __name__ == "__main__":
    main()
