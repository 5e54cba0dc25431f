"""A room's lights from a posed scan against each frame estimated on its own.

    python -m benchmarks.scan make --out data/scans          # posed capture folders, once
    python -m benchmarks.scan make --out data/scans30 --frames 30 --seeds 4106 4110
    python -m benchmarks.scan make --behind --out data/scans_behind   # the first light behind the camera
    python -m benchmarks.scan make --mitsuba --out data/scans_mitsuba   # Mitsuba 3 renders (the mitsuba extra)
    python -m benchmarks.scan make --mitsuba --behind --out data/scans_mitsuba_behind
    python -m benchmarks.scan run --scans data/scans_mitsuba --name scan_mitsuba
    python -m benchmarks.scan run --scans data/scans --timing data/scans30   # benchmarks/results/scan_<device>_<date>.*
    python -m benchmarks.scan figure --scan data/scans/indirect_noisy/scan_4110 --room room.json --out docs/scan_top.png
    python -m benchmarks.scan animate --scan data/scans30/indirect_noisy/scan_4110 --out docs/scan.gif

``make`` renders posed scans of our procedural rooms with the exact ray caster
(:func:`selfsup.scenes.sequences.render_orbit`: the camera turned from -30 to +30 degrees
about the vertical through the room's middle, 12 frames, 160x120, one or two lights) and
writes each as a capture folder (the recipe's 8-bit sRGB at one exposure, millimetre
depth) with ``poses.json`` and the world's true lights (``truth.json``), in two sets:
``direct`` (the exact render) and ``indirect_noisy`` (indirect light and a sensor's noise);
with ``--mitsuba`` the same rooms' scans (8 of them) rendered by Mitsuba 3, ``mitsuba_direct``
and ``mitsuba_gi`` (path traced, 256 samples a pixel a light); with ``--behind`` each room's
first light hangs behind the camera and above it, out of view in every frame
(:func:`selfsup.scenes.sequences.light_behind_camera`; sets ``behind_*``, ``mitsuba_behind_*``).

``run`` estimates every frame on its own (``mode=estimate``'s defaults) and the whole scan
(``mode=scan``'s defaults), and scores both in the world against the truth: a frame's
worst light error (its estimate mapped by its pose; a missing or extra light: the
worst), the scan's, both as shares of the scan's size (:func:`room_size`), and whether the count is right;
and, without the truth, the spread: the median distance of the frames' lights mapped to the
world from the scan's nearest light. ``mode=track`` through each scan (``track.refresh=0``) with
its poses and without: the median over frames of the worst tracked light's world error and
the full estimates it made. With ``--timing``, the command's wall time on 30-frame scans.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import side_by_side, write_animation, write_results

SEEDS = tuple(range(4100, 4112))
COLUMNS = ["scan", "lights", "frames", "per_frame_median_error", "per_frame_success", "per_frame_count_right",
           "scan_error", "scan_success", "scan_count_right", "scan_lights", "spread", "scan_seconds",
           "tracked_posed_error", "tracked_posed_full", "tracked_unposed_error", "tracked_unposed_full"]


# The sets: the exact render, and the render with indirect light (a first bounce and the
# later ones, at up to twice their strength, drawn per frame) through the sensor's depth
# noise, holes and image noise (benchmarks.captures.SENSOR).
SETS = ("direct", "indirect_noisy")


def _room(seed: int, index: int, count: int, behind: bool):
    """Room ``index`` of ``count`` seeds (the first half one light, the rest two) at 160x120,
    its first light behind the camera with ``behind``; None (said) where there is no room for it."""
    from selfsup.scenes.sampler import SamplerConfig, sample_scene
    from selfsup.scenes.sequences import light_behind_camera

    config = SamplerConfig(height=120, width=160)
    spec = sample_scene(seed, config, n_lights=1 if index < count // 2 else 2)
    if behind:
        spec = light_behind_camera(spec, margin=config.light_margin)
        if spec is None:
            print(f"seed {seed}: no room behind the camera for a light; left out", flush=True)
    return spec


def make(out: Path, seeds=SEEDS, frames: int = 12, swing_deg: float = 30.0, sets=SETS, behind: bool = False
         ) -> list[Path]:
    """One posed capture folder per set and seed under ``out/<set>``: the first half of the
    seeds one light, the rest two. With ``behind`` the first light hangs behind the camera
    and above it (:func:`selfsup.scenes.sequences.light_behind_camera`: out of view in every
    frame, lighting what every frame sees), the sets named ``behind_<set>``."""
    from benchmarks.captures import SENSOR, capture_exposure, write_capture
    from selfsup.scenes.degrade import Degradations
    from selfsup.scenes.sequences import render_orbit

    degradations = {"direct": Degradations(), "indirect_noisy": Degradations(indirect=2.0, **SENSOR)}
    folders = []
    for set_name in sets:
        for k, seed in enumerate(seeds):
            spec = _room(seed, k, len(seeds), behind)
            if spec is None:
                continue
            n_lights = spec.light_position.shape[0]
            scenes, poses, truth = render_orbit(seed, frames, swing_deg, degradations=degradations[set_name],
                                                spec=spec)
            folder = out / (f"behind_{set_name}" if behind else set_name) / f"scan_{seed}"
            exposure = capture_exposure(scenes[len(scenes) // 2], folder.name)  # one exposure: a locked camera
            for scene in scenes:
                write_capture(scene, folder, scene.id, exposure=exposure)
            (folder / "poses.json").write_text(json.dumps({s.id: p.tolist() for s, p in zip(scenes, poses)}))
            (folder / "truth.json").write_text(json.dumps({"lights": truth.tolist(),
                                                           "scene_size": float(scenes[0].scene_scale)}))
            folders.append(folder)
            print(f"{folder}: {frames} frames, {n_lights} light(s)", flush=True)
    return folders


def make_mitsuba(out: Path, seeds=SEEDS[:4] + SEEDS[6:10], frames: int = 12, swing_deg: float = 30.0,
                 behind: bool = False) -> list[Path]:
    """Posed scans rendered by Mitsuba 3 (the ``mitsuba`` extra), ``out/mitsuba_direct`` and
    ``out/mitsuba_gi`` (path traced): the rooms of :func:`make` (the same seeds' specs, the
    camera turned as :func:`selfsup.scenes.sequences.render_orbit` turns it), each frame
    rendered by :func:`benchmarks.mitsuba_scenes.render_variants` at the first frame's exposure.
    ``behind``: the first light behind the camera, as :func:`make`'s, in ``out/mitsuba_behind_*``."""
    import mitsuba as mi

    from benchmarks.captures import capture_exposure, write_capture
    from benchmarks.mitsuba_scenes import render_variants
    from selfsup.scenes.sequences import orbit_pose, orbited

    mi.set_variant("scalar_rgb")
    folders = []
    prefix = "mitsuba_behind" if behind else "mitsuba"
    for k, seed in enumerate(seeds):
        spec = _room(seed, k, len(seeds), behind)
        if spec is None:
            continue
        n_lights = spec.light_position.shape[0]
        angles = torch.linspace(-swing_deg, swing_deg, frames).tolist()
        exposure, capture = None, {}
        for f, angle in enumerate(angles):
            rendered = render_variants(orbited(spec, angle), f"mitsuba_orbit_{seed}_{f:03d}", exposure=exposure,
                                       variants=("direct", "gi"))
            if exposure is None:  # the first frame's, kept: a camera with its exposure locked
                exposure = float(rendered["direct"].light_intensity[0, 0] / spec.light_relative_intensity[0, 0])
            for variant, scene in rendered.items():
                folder = out / f"{prefix}_{variant}" / f"scan_{seed}"
                capture.setdefault(variant, capture_exposure(scene, folder.name))
                write_capture(scene, folder, f"orbit_{seed}_{f:03d}", exposure=capture[variant])
        for variant in ("direct", "gi"):
            folder = out / f"{prefix}_{variant}" / f"scan_{seed}"
            (folder / "poses.json").write_text(json.dumps({f"orbit_{seed}_{f:03d}": orbit_pose(spec, a).tolist()
                                                           for f, a in enumerate(angles)}))
            (folder / "truth.json").write_text(json.dumps({"lights": spec.light_position.double().tolist(),
                                                           "scene_size": float(rendered["direct"].scene_scale)}))
            folders.append(folder)
        print(f"scan_{seed}: {frames} frames, {n_lights} light(s), Mitsuba direct and path traced", flush=True)
    return folders


def _worst(found: np.ndarray, truth: np.ndarray) -> tuple[float, bool]:
    # The worst light error (metres) of ``found (n, 3)`` against ``truth (m, 3)``, each true
    # light paired with the nearest found one; a wrong count: inf. And whether the count is right.
    if len(found) != len(truth) or len(found) == 0:
        return float("inf"), len(found) == len(truth)
    distance = np.linalg.norm(found[:, None] - truth[None], axis=-1)
    if len(truth) == 2:
        return float(min(max(distance[0, 0], distance[1, 1]), max(distance[0, 1], distance[1, 0]))), True
    return float(distance.min(0).max()), True


def room_size(folder: Path) -> float:
    """The scan's size as ``mode=scan`` measures it: the diagonal of the 2-98% box of every
    frame's points in the world. (The renders' own ``scene_scale`` is the box of every
    point: where a camera looks out along the open floor, thousands of times the room.)"""
    from selfsup.scan.files import scene_points, scene_size
    from selfsup.scenes.capture import capture_geometry
    from selfsup.scenes.poses import posed_frames

    frames = posed_frames(folder)
    return scene_size(np.concatenate([scene_points(*capture_geometry(f.frame), f.pose) for f in frames]))


def score(folder: Path, frames_records: list[dict], room: dict, size: float) -> dict:
    """One row: the frames' and the scan's world errors, counts and the spread, as shares
    of ``size`` (:func:`room_size`)."""
    world = np.array(json.loads((folder / "truth.json").read_text())["lights"])
    poses = {key: np.array(value) for key, value in json.loads((folder / "poses.json").read_text()).items()}
    errors, counts, mapped = [], [], []
    for record in frames_records:
        pose = poses[record["id"]]
        found = np.array([pose[:3, :3] @ light["position"] + pose[:3, 3] for light in record["lights"]]).reshape(-1, 3)
        error, right = _worst(found, world)
        errors.append(error / size)
        counts.append(right)
        mapped.extend(found)
    scan_found = np.array([light["position"] for light in room["lights"]]).reshape(-1, 3)
    scan_error, scan_right = _worst(scan_found, world)
    spread = (statistics.median(float(np.linalg.norm(scan_found - p, axis=1).min()) / size for p in mapped)
              if mapped and len(scan_found) else None)
    return {"scan": folder.name, "lights": len(world), "frames": len(frames_records),
            "per_frame_median_error": round(statistics.median(errors), 4),
            "per_frame_success": f"{sum(e < 0.05 for e in errors)}/{len(errors)}",
            "per_frame_count_right": f"{sum(counts)}/{len(counts)}", "scan_error": round(scan_error / size, 4),
            "scan_success": scan_error / size < 0.05, "scan_count_right": scan_right, "scan_lights": len(scan_found),
            "spread": None if spread is None else round(spread, 4), "scan_seconds": room["seconds"]}


def timed_scans(scans: Path) -> list[dict]:
    """``python train.py mode=scan`` (its defaults) on every posed folder under each set of
    ``scans`` (``make --frames 30``): a row per scan with the command's wall time (start-up included)."""
    import subprocess
    import sys

    rows = []
    root = Path(__file__).resolve().parents[1]
    for folder in sorted(scans.glob("*/*/poses.json")):
        folder = folder.parent
        with tempfile.TemporaryDirectory() as tmp:
            started = time.perf_counter()
            subprocess.run([sys.executable, "train.py", "mode=scan", f"scan.input={folder.resolve()}",
                            f"scan.output={tmp}/room.json", "scan.progress=false"], cwd=root, check=True,
                           capture_output=True)
            wall = time.perf_counter() - started
            room = json.loads((Path(tmp) / "room.json").read_text())
        rows.append({"scan": f"timing: {folder.parent.name}/{folder.name}", "lights": "", "frames": room["frames"],
                     "scan_lights": len(room["lights"]), "scan_seconds": round(wall, 1)})
        print(rows[-1], flush=True)
    return rows


def tracked(folder: Path, posed: bool, size: float, options=None) -> dict:
    """``mode=track`` (refresh 0: full estimates on evidence only) through a posed scan, with
    its poses (the lights carried through the camera's moves) or without (a copy of the
    folder without ``poses.json``): the median over frames of the worst tracked light's world
    error as a share of ``size`` (each frame's lights mapped by its pose; a wrong count: inf) and
    the full estimates."""
    from selfsup.tracking import track_files

    world = np.array(json.loads((folder / "truth.json").read_text())["lights"])
    poses = {key: np.array(value) for key, value in json.loads((folder / "poses.json").read_text()).items()}
    with tempfile.TemporaryDirectory() as tmp:
        source = folder
        if not posed:
            source = Path(tmp) / "frames"
            source.mkdir()
            for sub in ("color", "depth", "intrinsics"):
                (source / sub).symlink_to((folder / sub).resolve())
        summary = track_files(source, Path(tmp) / "track.jsonl", options, refresh=0, progress=False)
        records = [json.loads(line) for line in (Path(tmp) / "track.jsonl").read_text().splitlines()]
    errors = []
    for record in records:
        pose = poses[record["id"]]
        found = np.array([pose[:3, :3] @ light["position"] + pose[:3, 3] for light in record["lights"]]).reshape(-1, 3)
        errors.append(_worst(found, world)[0] / size)
    return {"error": round(statistics.median(errors), 4), "full": summary["full"]}


def run(scans: Path, write: bool = True, timing: Path | None = None, name: str = "scan", options=None) -> list[dict]:
    """Every posed folder under each set of ``scans`` estimated frame by frame and as a scan:
    a row per scan and a summary row per set; with ``timing``, :func:`timed_scans` of it.
    ``options``: the estimate settings of the frames, the scan's keyframes and the tracker
    (an :class:`~selfsup.estimation.EstimateOptions`; None: the defaults)."""
    from selfsup.estimation import EstimateOptions, estimate_files
    from selfsup.scan import scan_files

    options = options or EstimateOptions()
    rows = []
    for set_folder in sorted(p for p in scans.iterdir() if p.is_dir()):
        scored = []
        for folder in sorted(p for p in set_folder.iterdir() if (p / "poses.json").is_file()):
            with tempfile.TemporaryDirectory() as tmp:
                estimate_files(folder, Path(tmp) / "frames.jsonl", options, progress=False, workers=1)
                records = [json.loads(line) for line in (Path(tmp) / "frames.jsonl").read_text().splitlines()]
                started = time.perf_counter()
                scan_files(folder, Path(tmp) / "room.json", options=options, progress=False)
                room = json.loads((Path(tmp) / "room.json").read_text())
                room["seconds"] = round(time.perf_counter() - started, 1)
            size = room_size(folder)  # every frame's depth read once for the three scores
            with_poses, without = tracked(folder, True, size, options), tracked(folder, False, size, options)
            scored.append({**score(folder, records, room, size), "scan": f"{set_folder.name}/{folder.name}",
                           "tracked_posed_error": with_poses["error"], "tracked_posed_full": with_poses["full"],
                           "tracked_unposed_error": without["error"], "tracked_unposed_full": without["full"]})
            print(scored[-1], flush=True)
        rows += scored + [_summary(set_folder.name, scored)]
    if timing is not None:
        rows += timed_scans(timing)
    if write:
        command = (f"python -m benchmarks.scan run --scans {scans} --name {name}" + (f" --timing {timing}" if timing else "")
                   + "".join(f" --option {key}={value}" for key, value in options.changed_settings().items()))
        names = [p.name for p in scans.iterdir() if p.is_dir()]
        flags = "".join(f" --{flag}" for flag in ("mitsuba", "behind") if any(flag in n for n in names))
        header = (f"`{command}` (made by `python -m benchmarks.scan make{flags} --out {scans}`). "
                  + " ".join(__doc__.split("\n\n", 2)[2].split()))
        write_results(name, torch.device("cpu"), rows, header, COLUMNS)
    return rows


def _summary(name: str, rows: list[dict]) -> dict:
    # A set's row: medians of the errors, sums of the successes and counts.
    return {"scan": f"{name}: median over {len(rows)} scans", "lights": "", "frames": sum(r["frames"] for r in rows),
            "per_frame_median_error": round(statistics.median(r["per_frame_median_error"] for r in rows), 4),
            "per_frame_success": _sum_fraction(r["per_frame_success"] for r in rows),
            "per_frame_count_right": _sum_fraction(r["per_frame_count_right"] for r in rows),
            "scan_error": round(statistics.median(r["scan_error"] for r in rows), 4),
            "scan_success": f"{sum(r['scan_success'] for r in rows)}/{len(rows)}",
            "scan_count_right": f"{sum(r['scan_count_right'] for r in rows)}/{len(rows)}", "scan_lights": "",
            "spread": round(statistics.median(r["spread"] for r in rows if r["spread"] is not None), 4),
            "scan_seconds": round(statistics.median(r["scan_seconds"] for r in rows), 1),
            "tracked_posed_error": round(statistics.median(r["tracked_posed_error"] for r in rows), 4),
            "tracked_posed_full": sum(r["tracked_posed_full"] for r in rows),
            "tracked_unposed_error": round(statistics.median(r["tracked_unposed_error"] for r in rows), 4),
            "tracked_unposed_full": sum(r["tracked_unposed_full"] for r in rows)}


def figure(folder: Path, room: Path, out: Path, up: int = 1) -> Path:
    """The scan's fused points seen from above (the world's axis ``up``, down in OpenCV's
    y-down camera of the first frame) with its lights (crosses), their 2-sigma ellipses in
    that view, the true lights (circles, where ``truth.json`` is there) and the cameras."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from selfsup.scan import scene_points
    from selfsup.scenes.capture import capture_geometry
    from selfsup.scenes.poses import posed_frames

    frames = posed_frames(folder)
    points = np.concatenate([scene_points(*capture_geometry(f.frame), f.pose, stride=6) for f in frames])
    axes = [a for a in range(3) if a != up]
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.scatter(points[:, axes[0]], points[:, axes[1]], s=0.6, c=points[:, up], cmap="viridis", alpha=0.5)
    cameras = np.stack([f.pose[:3, 3] for f in frames])
    ax.plot(cameras[:, axes[0]], cameras[:, axes[1]], "-", color="tab:blue", label="cameras")
    result = json.loads(room.read_text())
    circle = np.stack([np.cos(np.linspace(0, 2 * np.pi, 64)), np.sin(np.linspace(0, 2 * np.pi, 64))])
    for k, light in enumerate(result["lights"]):
        centre = np.array(light["position"])[axes]
        cov = np.array(light["position_cov"])[np.ix_(axes, axes)]
        values, vectors = np.linalg.eigh(cov)
        ellipse = centre[:, None] + vectors @ (2 * np.sqrt(np.clip(values, 0, None))[:, None] * circle)
        ax.plot(*ellipse, color="tab:orange")
        ax.scatter(*centre, marker="x", s=120, color="tab:orange", label="scan's lights (2 sigma)" if k == 0 else None)
    if (folder / "truth.json").is_file():
        truth = np.array(json.loads((folder / "truth.json").read_text())["lights"])
        ax.scatter(truth[:, axes[0]], truth[:, axes[1]], s=140, facecolors="none", edgecolors="tab:green",
                   linewidths=2, label="true lights")
    ax.set_aspect("equal")
    ax.invert_yaxis()
    ax.set_xlabel(f"world {'xyz'[axes[0]]} (m)")
    ax.set_ylabel(f"world {'xyz'[axes[1]]} (m)")
    ax.set_title(f"{folder.name}: {len(frames)} posed frames fused, seen from above", fontsize=10)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out


def animate(folder: Path, out: Path, size: float = 0.04, pixel: tuple[float, float] = (0.5, 0.75),
            scale: int = 2, fps: float = 4.0, stride: int = 2) -> Path:
    """A GIF of a posed scan: each frame beside the same frame with a virtual cube anchored in
    the room (placed where the first frame puts it, :func:`selfsup.insert.place_object`, and
    carried to each frame by the poses) lit by the scan's lights (``mode=scan``'s
    ``frames_output``: the fused world lights in that frame's camera, intensities solved on it);
    every ``stride``-th frame, ``scale`` times enlarged."""
    import dataclasses

    from selfsup.insert import Mesh, insert_object, lights_from_record, place_object
    from selfsup.scan import scan_files
    from selfsup.scenes.capture import read_capture
    from selfsup.scenes.io import render_inputs
    from selfsup.scenes.poses import posed_frames

    frames = posed_frames(folder)
    with tempfile.TemporaryDirectory() as tmp:
        scan_files(folder, Path(tmp) / "room.json", Path(tmp) / "frames.jsonl", progress=False)
        records = {r["id"]: r for r in map(json.loads, (Path(tmp) / "frames.jsonl").read_text().splitlines())}
    first = read_capture(frames[0].frame)
    cube = place_object(render_inputs(first)[0], Mesh.cube(), pixel, size)
    pose0 = torch.as_tensor(frames[0].pose, dtype=cube.vertices.dtype)
    world = cube.vertices @ pose0[:3, :3].T + pose0[:3, 3]
    pictures = []
    for frame in frames[::stride]:
        scene = read_capture(frame.frame)
        pose = torch.as_tensor(frame.pose, dtype=world.dtype)
        here = dataclasses.replace(cube, vertices=(world - pose[:3, 3]) @ pose[:3, :3])  # R^T (p - t), row-wise
        composite, _ = insert_object(scene, *lights_from_record(records[frame.id]), here)
        pictures.append(side_by_side(scene.image, composite, scene.depth, scale))
    return write_animation(out, pictures, fps)


def _sum_fraction(values) -> str:
    pairs = [tuple(int(x) for x in v.split("/")) for v in values]
    return f"{sum(a for a, _ in pairs)}/{sum(b for _, b in pairs)}"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    m = sub.add_parser("make", help="posed capture folders of procedural rooms")
    m.add_argument("--out", type=Path, default=Path("data/scans"))
    m.add_argument("--frames", type=int, default=12)
    m.add_argument("--seeds", type=int, nargs="*", default=list(SEEDS))
    m.add_argument("--behind", action="store_true", help="the first light behind the camera in every frame")
    m.add_argument("--mitsuba", action="store_true", help="render the scans with Mitsuba 3 instead (8 rooms, the mitsuba extra)")
    r = sub.add_parser("run", help="frames against scans; writes the results file")
    r.add_argument("--scans", type=Path, default=Path("data/scans"))
    r.add_argument("--no-write", action="store_true")
    r.add_argument("--timing", type=Path, help="posed scans to time the command on (make --frames 30)")
    r.add_argument("--name", default="scan", help="the results file's name")
    r.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="an estimate setting of the frames, the scan and the tracker (checkpoint=...)")
    f = sub.add_parser("figure", help="one scan's fused points from above with its lights")
    f.add_argument("--scan", type=Path, required=True, help="a posed capture folder")
    f.add_argument("--room", type=Path, required=True, help="its mode=scan output")
    f.add_argument("--out", type=Path, default=Path("docs/scan_top.png"))
    a = sub.add_parser("animate", help="a GIF of a virtual cube anchored in a scan's room, lit by its lights")
    a.add_argument("--scan", type=Path, required=True, help="a posed capture folder")
    a.add_argument("--out", type=Path, default=Path("docs/scan.gif"))
    args = parser.parse_args(argv)
    if args.command == "animate":
        animate(args.scan, args.out)
    elif args.command == "make" and args.mitsuba:
        make_mitsuba(args.out, frames=args.frames, behind=args.behind)
    elif args.command == "make":
        make(args.out, tuple(args.seeds), args.frames, behind=args.behind)
    elif args.command == "figure":
        print(f"wrote {figure(args.scan, args.room, args.out)}")
    else:
        from benchmarks.estimate_procedural import parse_options
        from selfsup.estimation import EstimateOptions

        options = EstimateOptions.from_settings(**parse_options(args.option))
        run(args.scans, not args.no_write, args.timing, args.name, options)


if __name__ == "__main__":
    main()
