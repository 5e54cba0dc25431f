"""Camera captures made from scene files, and the estimator scored on them.

    python -m benchmarks.captures make --scenes data/mitsuba --out data/captures/mitsuba
    python -m benchmarks.captures run --captures data/captures/mitsuba data/captures/mitsuba_closed

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
           "seconds_per_frame"]


def _exposure_draw(name: str) -> float:
    # A log-uniform draw in EXPOSURE_RANGE from the frame's name (reproducible, order-free).
    u = int(hashlib.sha256(name.encode()).hexdigest()[:12], 16) / 16**12
    lo, hi = (math.log(x) for x in EXPOSURE_RANGE)
    return math.exp(lo + u * (hi - lo))


def make_capture(scene_path: Path, out: Path, frame_id: str) -> None:
    """One scene file as a capture frame of folder ``out`` (colour, depth, intrinsics, truth)."""
    scene = read_scene(scene_path)
    image, depth = scene.image.double().numpy(), scene.depth.double().numpy()
    valid = np.isfinite(depth) & (depth > 0)
    level = float(np.percentile(image[valid], 99))
    exposure = _exposure_draw(frame_id) / max(level, 1e-12)
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
    meta = {**scene.meta, "id": frame_id, "source_file": str(scene_path), "exposure": exposure}
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


def read_truth(path: Path) -> SimpleNamespace:
    """A capture's truth file as the fields :func:`benchmarks.common.score_record` reads."""
    data = np.load(path, allow_pickle=False)
    t = {k: torch.from_numpy(np.array(data[k], dtype=np.float32)) for k in data.files if k != "meta"}
    return SimpleNamespace(**t, meta=json.loads(str(data["meta"])))


def score(folder: Path, estimates: Path) -> list[dict]:
    """One row per frame of ``estimates`` against ``folder/truth``: found and true light
    counts, the worst position error, success, seconds."""
    rows = []
    for line in estimates.read_text().splitlines():
        record = json.loads(line)
        truth = read_truth(folder / "truth" / f"{record['id']}.npz")
        errors, _ = score_record(record, truth)
        rows.append({"id": record["id"], "found": len(record["lights"]), "true": truth.light_pos.shape[0],
                     "worst": max(errors.position), "success": errors.success, "seconds": record["seconds"]})
    return rows


def summary(root: str, set_name: str, rows: list[dict], frames: int, wall: float) -> dict:
    """The table's row of one set: shares over the frames (a failed frame counts as a miss)."""
    one = [r for r in rows if r["true"] == 1]
    two = [r for r in rows if r["true"] == 2]

    def share(hits: int, total: int) -> str:
        return f"{hits}/{total} ({100 * hits / total:.0f}%)" if total else "-"

    return {"root": root, "set": set_name, "scenes": frames, "success": share(sum(r["success"] for r in rows), frames),
            "one_light_success": share(sum(r["success"] for r in one), len(one)),
            "two_light_right_count": share(sum(r["found"] == 2 for r in two), len(two)),
            "median_worst_error": round(statistics.median([r["worst"] for r in rows]), 4) if rows else "",
            "seconds_per_frame": round(wall / max(frames, 1), 3)}


def run(roots: list[Path], sets=SETS, write: bool = True, options=None) -> tuple[list[dict], Path | None]:
    """Estimate every set of each captures root (``mode=estimate``'s defaults, or
    ``options``) and score it; one row per set."""
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
                estimate_files(folder, output, options, progress=False, batch=4, workers="auto")
                wall = time.perf_counter() - started
                scored = score(folder, output) if output.exists() else []
            rows.append(summary(root.name, set_name, scored, len(capture_frames(folder)), wall))
            print(rows[-1], flush=True)
    path = None
    if write:
        header = ("Capture folders (8-bit sRGB colour at an unknown exposure, 16-bit millimetre depth, intrinsics; no "
                  "albedo, materials, normals or ambient) made by `python -m benchmarks.captures make` from scene "
                  "files, estimated by `mode=estimate` with the default settings (batch 4, workers auto) and scored "
                  "against truth/: success = every light within 0.05 of the scene size; one-light success; two-light "
                  "right count = two lights found in the two-light scenes; median worst position error (of the scene "
                  "size); seconds per frame = the command's wall time over the frames (the network's load included, "
                  "Python's start not).")
        path = write_results("capture_estimate", torch.device("cpu"), rows, header, COLUMNS)
    return rows, path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    m = sub.add_parser("make", help="capture folders from scene files")
    m.add_argument("--scenes", type=Path, required=True, help="a folder with direct/ gi/ noisy/ scene files")
    m.add_argument("--out", type=Path, required=True)
    m.add_argument("--sets", nargs="+", default=list(SETS))
    r = sub.add_parser("run", help="estimate and score capture folders")
    r.add_argument("--captures", type=Path, nargs="+", required=True, help="roots with direct/ gi/ noisy/ captures")
    r.add_argument("--sets", nargs="+", default=list(SETS))
    r.add_argument("--no-write", action="store_true")
    r.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="an estimate setting or tuned constant, e.g. coat='never' (repeatable)")
    args = parser.parse_args()
    if args.command == "make":
        make(args.scenes, args.out, args.sets)
    else:
        from benchmarks.estimate_procedural import parse_options
        from selfsup.estimation import EstimateOptions

        options = EstimateOptions.from_settings(**parse_options(args.option))
        print(run(args.captures, args.sets, write=not args.no_write, options=options)[1])


if __name__ == "__main__":
    main()
