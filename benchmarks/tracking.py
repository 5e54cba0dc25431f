"""Frame sequences for the tracker, and the tracker scored on them against per-frame estimation.

    python -m benchmarks.tracking make --out data/sequences                  # procedural: files/ captures/ noisy/
    python -m benchmarks.tracking mitsuba --out data/sequences_mitsuba       # a few rendered by Mitsuba 3
    python -m benchmarks.tracking run --sequences data/sequences data/sequences_mitsuba
    python -m benchmarks.tracking animate --sequence data/sequences/captures/moving_light_500 --out docs/tracking.gif

``make`` renders the sequences of :mod:`selfsup.scenes.sequences` (every kind, ``--seeds``
scenes each, ``--frames`` frames) three ways: ``files/`` scene files with the true
albedo, ``captures/`` capture folders of the same frames (8-bit sRGB, millimetre depth,
no albedo; one exposure for the whole sequence, as a camera with its exposure locked),
``noisy/`` capture folders of frames with the sensor degradations of
:data:`benchmarks.captures.SENSOR` (each frame its own draw). ``mitsuba`` renders
``moving_light`` and ``switch`` sequences with Mitsuba 3 (direct light) as capture
folders, the independent renderer's check.

``run`` tracks every sequence (``mode=track``'s :class:`selfsup.tracking.Tracker`, frames
read from disk: the reading is part of each latency) and estimates each of its frames
on its own (``mode=estimate``'s pipeline), and scores both against the truth: per-frame
success (every light within 0.05 of the scene size, the right count), jitter (the
frame-to-frame motion of a light whose true position did not change, of the scene
size), the frames after a light switches on or off until the count is right, and the
latency. Results: ``benchmarks/results/tracking_<device>_<date>.*``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from benchmarks.captures import SENSOR, read_truth, write_capture
from benchmarks.common import score_record, side_by_side, write_animation, write_results
from selfsup.scenes.sequences import SEQUENCE_KINDS

SETS = ("files", "captures", "noisy")
COLUMNS = ["root", "set", "kind", "sequences", "frames", "tracked_success", "independent_success", "tracked_count",
           "independent_count", "jitter_median", "jitter_p95", "independent_jitter_median", "recovery_frames",
           "full_share", "warm_ms_median", "warm_ms_p90", "full_ms_median", "independent_ms_median", "read_ms_median"]


def make(out: Path, seeds: int = 2, frames: int = 24, first_seed: int = 500) -> None:
    """The procedural sequences (see the module) under ``out/files``, ``out/captures``, ``out/noisy``."""
    from selfsup.scenes.degrade import Degradations
    from selfsup.scenes.sequences import render_sequence, write_sequence

    for kind in SEQUENCE_KINDS:
        for seed in range(first_seed, first_seed + seeds):
            name = f"{kind}_{seed}"
            exact = render_sequence(kind, seed, frames)
            write_sequence(exact, out / "files" / name)
            _write_captures(exact, out / "captures" / name, name)
            _write_captures(render_sequence(kind, seed, frames, degradations=Degradations(**SENSOR)),
                            out / "noisy" / name, name)
            print(f"{name}: {frames} frames", flush=True)


def _write_captures(scenes: list, folder: Path, name: str) -> None:
    from benchmarks.captures import capture_exposure

    exposure = capture_exposure(scenes[0], name)  # the first frame's, kept: the camera's exposure is locked
    for f, scene in enumerate(scenes):
        write_capture(scene, folder, f"frame_{f:03d}", exposure)


def mitsuba(out: Path, frames: int = 16, seeds: tuple[int, ...] = (600,)) -> None:
    """``moving_light`` and ``switch`` sequences rendered by Mitsuba 3 (direct light), as
    capture folders ``out/captures/<kind>_<seed>`` (exact depth) and ``out/noisy/...``
    (its sensor noise)."""
    import mitsuba as mi

    from benchmarks.captures import capture_exposure
    from benchmarks.mitsuba_scenes import render_variants
    from selfsup.scenes.sampler import SamplerConfig
    from selfsup.scenes.sequences import sequence_specs

    mi.set_variant("scalar_rgb")
    for kind in ("moving_light", "switch"):
        for seed in seeds:
            name = f"{kind}_{seed}"
            exposure = locked = None
            for f, spec in enumerate(sequence_specs(kind, seed, frames, SamplerConfig(height=120, width=160))):
                scenes = render_variants(spec, f"{name}_{f:03d}", exposure=exposure, variants=("direct", "noisy"),
                                         noise_seed=seed * 1000 + f)
                if exposure is None:  # the first frame's, for every frame
                    exposure = float(scenes["direct"].light_intensity[0, 0] / spec.light_relative_intensity[0, 0])
                if locked is None:
                    locked = capture_exposure(scenes["direct"], name)
                for variant, set_name in (("direct", "captures"), ("noisy", "noisy")):
                    write_capture(scenes[variant], out / set_name / name, f"frame_{f:03d}", locked)
            print(f"{name}: {frames} frames", flush=True)


def _inputs(folder: Path) -> list:
    from selfsup.estimation.files import estimate_inputs
    from selfsup.tracking.files import natural_order

    return natural_order(estimate_inputs(folder))


def _truth(folder: Path, scene) -> object:
    # The frame's truth: the scene file itself, or the capture's truth file.
    if scene.light_pos is not None:
        return scene
    return read_truth(folder / "truth" / f"{scene.id}.npz")


def _scored(record: dict, truth) -> dict:
    errors, _ = score_record(record, truth)
    return {"success": errors.success, "count": len(record["lights"]) == truth.light_pos.shape[0],
            "true": truth.light_pos.double(), "found": [(light.get("track"), torch.tensor(light["position"]))
                                                       for light in record["lights"]],
            "size": float(truth.scene_scale)}


def _jitter(frames: list[dict]) -> list[float]:
    """Frame-to-frame motion (of the scene size) of the estimate nearest each true light
    whose position did not change (a tracked light: the same track's motion)."""
    motions = []
    for before, now in zip(frames, frames[1:]):
        if before["true"].shape != now["true"].shape or not now["found"] or not before["found"]:
            continue
        for k in range(now["true"].shape[0]):
            if float((now["true"][k] - before["true"][k]).norm()) > 1e-9:
                continue
            nearest = min(now["found"], key=lambda f: float((f[1].double() - now["true"][k]).norm()))
            if nearest[0] is not None:
                previous = [f for f in before["found"] if f[0] == nearest[0]]
            else:
                previous = [min(before["found"], key=lambda f: float((f[1].double() - before["true"][k]).norm()))]
            if previous:
                motions.append(float((nearest[1] - previous[0][1]).norm()) / now["size"])
    return motions


def _recovery(frames: list[dict]) -> list[int]:
    """Frames after each change of the true light count until the count is right (0: at once)."""
    waits = []
    for f in range(1, len(frames)):
        if frames[f]["true"].shape[0] != frames[f - 1]["true"].shape[0]:
            wait = next((g - f for g in range(f, len(frames)) if frames[g]["count"]), len(frames) - f)
            waits.append(wait)
    return waits


def track_sequence(folder: Path, options=None, tuning=None, refresh: int = 30, device: str = "cpu") -> dict:
    """Track and independently estimate every frame of one sequence folder on ``device``;
    per-frame scores and latencies. Each frame is read once, timed apart, and given to
    both in memory."""
    from selfsup.estimation import EstimateOptions, estimate_scene
    from selfsup.scenes.capture import read_input
    from selfsup.tracking import Tracker, TrackTuning

    options = options or EstimateOptions()
    tracker = Tracker(options, tuning or TrackTuning(), refresh, device)
    tracked, independent, warm, full, alone, reads = [], [], [], [], [], []
    for item in _inputs(folder):
        started = time.perf_counter()
        scene = read_input(item)
        reads.append(1000 * (time.perf_counter() - started))
        record = tracker.update(scene)
        truth = _truth(folder, scene)
        tracked.append(_scored(record, truth))
        (full if record["full"] else warm).append(record["latency_ms"])
        started = time.perf_counter()
        own = estimate_scene(scene, options, device)
        alone.append(1000 * (time.perf_counter() - started))
        independent.append(_scored(own, truth))
    return {"tracked": tracked, "independent": independent, "warm_ms": warm, "full_ms": full, "alone_ms": alone,
            "read_ms": reads}


def _share(hits: int, total: int) -> str:
    return f"{hits}/{total} ({100 * hits / total:.0f}%)" if total else "-"


def _quantile(values: list[float], q: float) -> float | str:
    if not values:
        return ""
    ordered = sorted(values)
    return round(ordered[min(len(ordered) - 1, int(q * len(ordered)))], 5)


def summary(root: str, set_name: str, kind: str, runs: list[dict]) -> dict:
    tracked = [f for r in runs for f in r["tracked"]]
    independent = [f for r in runs for f in r["independent"]]
    jitter = [m for r in runs for m in _jitter(r["tracked"])]
    alone_jitter = [m for r in runs for m in _jitter(r["independent"])]
    recovery = [w for r in runs for w in _recovery(r["tracked"])]
    warm = [m for r in runs for m in r["warm_ms"]]
    full = [m for r in runs for m in r["full_ms"]]
    alone = [m for r in runs for m in r["alone_ms"]]
    reads = [m for r in runs for m in r["read_ms"]]
    n = len(tracked)
    return {"root": root, "set": set_name, "kind": kind, "sequences": len(runs), "frames": n,
            "tracked_success": _share(sum(f["success"] for f in tracked), n),
            "independent_success": _share(sum(f["success"] for f in independent), n),
            "tracked_count": _share(sum(f["count"] for f in tracked), n),
            "independent_count": _share(sum(f["count"] for f in independent), n),
            "jitter_median": _quantile(jitter, 0.5), "jitter_p95": _quantile(jitter, 0.95),
            "independent_jitter_median": _quantile(alone_jitter, 0.5),
            "recovery_frames": " ".join(str(w) for w in recovery) if recovery else "-",
            "full_share": _share(len(full), n),
            "warm_ms_median": round(statistics.median(warm), 1) if warm else "",
            "warm_ms_p90": _quantile(warm, 0.9), "full_ms_median": round(statistics.median(full), 1) if full else "",
            "independent_ms_median": round(statistics.median(alone), 1) if alone else "",
            "read_ms_median": round(statistics.median(reads), 1) if reads else ""}


def run(roots: list[Path], sets=SETS, write: bool = True, name: str = "tracking", kinds=SEQUENCE_KINDS,
        refresh: int = 30, device: str = "cpu", options=None) -> tuple[list[dict], Path | None]:
    """Score every sequence under ``roots/<set>/<kind>_<seed>`` (the ``kinds`` given), the
    tracker's ``refresh`` as ``track.refresh`` and its full estimates' ``options`` (an
    :class:`~selfsup.estimation.EstimateOptions`; None: the defaults); one row per root, set and kind."""
    rows = []
    for root in roots:
        for set_name in sets:
            if not (root / set_name).is_dir():
                continue
            folders = sorted(p for p in (root / set_name).iterdir() if p.is_dir())
            for kind in kinds:
                runs = [track_sequence(p, options, refresh=refresh, device=device) for p in folders
                        if p.name.rsplit("_", 1)[0] == kind]
                if runs:
                    rows.append(summary(root.name, set_name, kind, runs))
                    print(json.dumps(rows[-1]), flush=True)
    path = None
    if write:
        header = ("Frame sequences (`python -m benchmarks.tracking make` / `mitsuba`) tracked by `mode=track`'s "
                  "Tracker with its defaults and, for comparison, each frame estimated on its own by `mode=estimate`'s "
                  "pipeline. Success = every light within 0.05 of the scene size; count = the right number of lights; "
                  "jitter = frame-to-frame motion of the estimate of a light whose true position did not change (of "
                  "the scene size; median and 95th percentile); recovery = frames after a light switched on or off "
                  "until the count was right (0: that frame); full share = frames the tracker estimated in full; "
                  "latencies per frame from the frame in memory to its record, as a live stream gives it (warm: the "
                  "tracker's warm steps; full: its full estimates; independent: mode=estimate's pipeline on the "
                  f"frame); read = reading the frame from its files, apart. track.refresh = {refresh} (sequences of 24 "
                  "frames, Mitsuba 16: the default 30 never comes due).")
        if options is not None and options.changed_settings():
            header += f" Estimation settings changed: {options.changed_settings()}."
        path = write_results(name, torch.device(device), rows, header, COLUMNS)
    return rows, path


def animate(sequence: Path, out: Path, size: float = 0.04, pixel: tuple[float, float] = (0.5, 0.75),
            object: str = "cube", scale: int = 2, fps: float = 8.0) -> Path:
    """A GIF of ``sequence``'s frames: each captured frame beside the same frame with a
    virtual object inserted under the lights the tracker gives for it (placed where the
    first frame puts it, as :func:`selfsup.insert.place_object`), ``scale`` times enlarged."""
    from selfsup.insert import Mesh, Sphere, insert_object, lights_from_record, place_object
    from selfsup.scenes.capture import read_input
    from selfsup.scenes.io import render_inputs
    from selfsup.tracking import Tracker

    tracker = Tracker()
    shape = Mesh.cube() if object == "cube" else Sphere(centre=torch.zeros(3), radius=1.0)
    placed, pictures = None, []
    for item in _inputs(sequence):
        scene = read_input(item)
        record = tracker.update(scene)
        if placed is None:
            placed = place_object(render_inputs(scene)[0], shape, pixel, size)
        composite, _ = insert_object(scene, *lights_from_record(record), placed)
        pictures.append(side_by_side(scene.image, composite, scene.depth, scale))
    return write_animation(out, pictures, fps)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    m = sub.add_parser("make", help="procedural sequences: files/, captures/, noisy/")
    m.add_argument("--out", type=Path, required=True)
    m.add_argument("--seeds", type=int, default=2, help="scenes per kind")
    m.add_argument("--frames", type=int, default=24)
    g = sub.add_parser("mitsuba", help="moving_light and switch sequences rendered by Mitsuba 3")
    g.add_argument("--out", type=Path, required=True)
    g.add_argument("--frames", type=int, default=16)
    a = sub.add_parser("animate", help="a GIF of a virtual object lit by the tracked lights")
    a.add_argument("--sequence", type=Path, required=True)
    a.add_argument("--out", type=Path, required=True)
    a.add_argument("--object", default="cube", choices=("cube", "sphere"))
    a.add_argument("--pixel", type=float, nargs=2, default=(0.5, 0.75),
                   help="where it stands, as shares of width and height")
    a.add_argument("--size", type=float, default=0.04, help="its half side, of the scene size")
    r = sub.add_parser("run", help="track and score sequences")
    r.add_argument("--sequences", type=Path, nargs="+", required=True)
    r.add_argument("--sets", nargs="+", default=list(SETS))
    r.add_argument("--no-write", action="store_true")
    r.add_argument("--name", default="tracking")
    r.add_argument("--kinds", nargs="+", default=list(SEQUENCE_KINDS), choices=SEQUENCE_KINDS)
    r.add_argument("--refresh", type=int, default=30, help="track.refresh")
    r.add_argument("--device", default="cpu", help="cpu or cuda[:i]: where the tracker and the estimator run")
    r.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="an estimate setting of the tracker's full estimates and the per-frame ones (checkpoint=...)")
    args = parser.parse_args()
    if args.command == "make":
        make(args.out, args.seeds, args.frames)
    elif args.command == "mitsuba":
        mitsuba(args.out, args.frames)
    elif args.command == "animate":
        animate(args.sequence, args.out, args.size, tuple(args.pixel), args.object)
    else:
        options = None
        if args.option:
            from benchmarks.estimate_procedural import parse_options
            from selfsup.estimation import EstimateOptions

            options = EstimateOptions.from_settings(**parse_options(args.option))
        print(run(args.sequences, args.sets, write=not args.no_write, name=args.name, kinds=args.kinds,
                  refresh=args.refresh, device=args.device, options=options)[1])


if __name__ == "__main__":
    main()
