"""Plausibility of the estimator's lights on real sensor frames, which have no truth.

    python -m benchmarks.real_frames --input ../shared/real_captures
    python -m benchmarks.real_frames --input DIR --set KEY=VALUE ...   # a trial: estimate.* overrides

``--input`` is a capture folder (``docs/scene-format.md``, "Capture folders") or a
folder of them (each sub-folder that is one is a set). Every set is estimated by the
command a user runs (``python train.py mode=estimate``, default settings plus ``--set``),
timed from start to end (Python's start-up and the network's load included), and every
frame's record is judged without truth by what a lamp in a room does:

- ``share``: the brightest light's share of the light on the visible surfaces (its
  diffuse shading with cast shadows, summed over the valid pixels, against the
  ambient's and every light's); a light under 0.1 explains almost nothing;
- ``min_chroma``: over the lights and the ambient, the weakest channel over the
  strongest (a white-balanced camera sees lamps near grey; under 0.2 is a coloured
  knob, not a lamp);
- ``height``: the brightest light's height above the camera in metres, along the
  gravity of ``gravity.json`` (``{"gravity_world": [x, y, z]}``, beside ``poses.json``)
  where given, else along the camera's -y;
- ``distance``: its distance from the camera;
- with ``poses.json`` (camera-to-world, OpenCV axes): the brightest light of every frame
  in world coordinates, and its distance from their median (``world_spread``); beside it
  the spread a light glued to the camera would have (``glued_spread``: the frames' median
  camera-frame light carried by each pose);
- ``seconds``: the command's wall time over the set's frames.

A frame whose record has no light (``light_found: false``) counts as such
(``no_light``, of all frames), not as a failed share: ``share`` and ``height`` count the
frames with a light; the contact sheet draws the light it did not
present grey and dotted, with its share in brackets. Results: ``benchmarks/results/real_frames_<device>_<date>.*``
(one row per set, one per frame in the JSON) and a contact sheet
``real_frames_<device>_<date>.png``: every frame with its lights drawn in (a disc where a
light projects into the image, an arrow at the border towards one outside; the label
gives its share and height).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import write_results
from render import Material, light_transport
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.prepare import within_pixels
from selfsup.scenes.capture import capture_frames, is_capture_folder, linear_to_srgb, read_capture
from selfsup.scenes.io import scene_gbuffer

ROOT = Path(__file__).resolve().parents[1]
COLUMNS = ["set", "frames", "no_light", "share_ge_0.1", "chroma_ge_0.2", "height_ge_0.3m", "median_share",
           "median_min_chroma", "median_height_m", "median_distance_m", "world_spread_m", "glued_spread_m",
           "median_angle_deg", "lambert_angle_deg", "lambert_depth_angle_deg", "seconds_per_frame"]
SHARE_TARGET, CHROMA_TARGET, HEIGHT_TARGET = 0.1, 0.2, 0.3


def capture_sets(root: Path) -> list[Path]:
    """The capture folders under ``root``: itself, or its sub-folders that are one, and theirs
    one level down (``objects/bear``, ``objects/cat``), sorted."""
    if is_capture_folder(root):
        return [root]
    sets = []
    for sub in sorted(p for p in root.iterdir() if p.is_dir()):
        sets += [sub] if is_capture_folder(sub) else sorted(p for p in sub.iterdir() if p.is_dir() and is_capture_folder(p))
    if not sets:
        raise FileNotFoundError(f"{root} is not a capture folder (color/ and depth/) and holds none")
    return sets


def run_command(folder: Path, settings: list[str]) -> tuple[list[dict], float]:
    """Records of ``python train.py mode=estimate`` on ``folder`` with ``settings``, and its wall time."""
    with tempfile.TemporaryDirectory() as tmp:
        started = time.perf_counter()
        done = subprocess.run([sys.executable, "train.py", "mode=estimate", f"estimate.input={folder.resolve()}",
                               f"estimate.output={tmp}/o.jsonl", "estimate.progress=false", f"hydra.run.dir={tmp}/run",
                               *settings], cwd=ROOT, capture_output=True, text=True)
        wall = time.perf_counter() - started
        out = Path(tmp) / "o.jsonl"
        if not out.exists():
            raise RuntimeError(f"mode=estimate wrote nothing on {folder}:\n{done.stderr[-2000:]}")
        return [json.loads(line) for line in out.read_text().splitlines()], wall


def up_in_camera(folder: Path, frame_id: str) -> np.ndarray:
    """The unit 'up' of the room in the camera frame: against ``gravity.json``'s gravity
    carried by the frame's pose, else the camera's -y (OpenCV: y points down)."""
    gravity, poses = folder / "gravity.json", folder / "poses.json"
    if gravity.exists() and poses.exists():
        g = np.asarray(json.loads(gravity.read_text())["gravity_world"], dtype=float)
        rotation = np.asarray(json.loads(poses.read_text())[frame_id], dtype=float)[:3, :3]  # camera to world
        up = -(rotation.T @ g)
        return up / np.linalg.norm(up)
    return np.array([0.0, -1.0, 0.0])


def light_shares(record: dict, frame, lights: list[dict] | None = None) -> tuple[list[float], object]:
    """Each light's share of the light on the frame's visible surfaces (diffuse, with cast
    shadows, at the estimator's working resolution) and the working-resolution scene;
    ``lights``: others than the record's (its unsupported ones), with its ambient."""
    scene = within_pixels(read_capture(frame), EstimateOptions())
    gbuffer = scene_gbuffer(scene.depth[None], scene.K[None], None, [scene.id])
    lights = record["lights"] if lights is None else lights
    if not lights:
        return [], scene
    position = torch.tensor([[light["position"] for light in lights]], dtype=torch.float32)
    intensity = torch.tensor([light["intensity"] for light in lights], dtype=torch.float32).mean(-1)
    diffuse = light_transport(gbuffer, Material(kd=torch.ones_like(scene.image)[None]), position,
                              shadows="epipolar", specular=False).diffuse[0]  # (L, H, W)
    direct = (intensity[:, None, None] * diffuse * gbuffer.mask[0]).flatten(1).sum(1)  # (L,)
    ambient = float(np.mean(record["ambient"])) * float(gbuffer.mask.sum())
    total = float(direct.sum()) + ambient
    return (direct / max(total, 1e-30)).tolist(), scene


def min_chroma(record: dict) -> float:
    """The least, over the lights and the ambient (where it is not black), of the weakest channel over the strongest."""
    colours = [light["intensity"] for light in record["lights"]] + [record["ambient"]]
    ratios = [min(c) / max(c) for c in colours if max(c) > 0]
    return min(ratios) if ratios else 1.0


def judge_set(folder: Path, records: list[dict]) -> list[dict]:
    """One row per frame of ``folder`` (see the module's docstring)."""
    frames = {f.id: f for f in capture_frames(folder)}
    poses_file = folder / "poses.json"
    poses = json.loads(poses_file.read_text()) if poses_file.exists() else {}
    rows = []
    for record in records:
        shares, scene = light_shares(record, frames[record["id"]])
        unsupported = record.get("unsupported_lights") or []
        row = {"id": record["id"], "lights": len(record["lights"]), "seconds": record.get("seconds"),
               "light_found": bool(record["lights"]), "min_chroma": round(min_chroma(record), 3), "scene": scene,
               "record": record, "shares": shares, "evidence": record.get("evidence"),
               "vignetting": record.get("vignetting"),
               "unsupported": [(light["position"], record_share) for light, record_share in
                               zip(unsupported, [light.get("share", 0.0) for light in unsupported])]}
        if record["lights"]:
            brightest = int(np.argmax(shares))
            p = np.asarray(record["lights"][brightest]["position"], dtype=float)
            row.update(share=round(shares[brightest], 4), distance=round(float(np.linalg.norm(p)), 3),
                       height=round(float(p @ up_in_camera(folder, record["id"])), 3), position=p.tolist())
            if record["id"] in poses:
                pose = np.asarray(poses[record["id"]], dtype=float)
                row["pose"] = pose.tolist()
                row["world"] = (pose[:3, :3] @ p + pose[:3, 3]).tolist()
        rows.append(row)
    return rows


def brightest_at(lights: list[dict], centre: np.ndarray) -> dict:
    """The light that gives ``centre`` the most light: mean intensity over squared distance."""
    return max(lights, key=lambda light: float(np.mean(light["intensity"]))
               / max(float(np.sum((np.asarray(light["position"]) - centre) ** 2)), 1e-12))


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0))))


def lambert_direction(scene, centre: np.ndarray, normals: np.ndarray | None = None, from_depth: bool = False) -> np.ndarray:
    """A baseline of a set with truth: least squares of the linear grey image to ``n . b`` over the
    object's pixels between a tenth and 0.95 of the 99th percentile (no shadow, no clipping): ``b``.
    The normals ``n``: ``normals (H, W, 3)`` where given (a set's true normals), else with
    ``from_depth`` the depth's (cross product of central differences of the back-projected
    pixels, interior pixels: as the objects' ``score.py`` computes them), else those of a sphere
    about ``centre`` (the ball's). ``scene``: the frame as :func:`read_capture` reads it."""
    depth = scene.depth.double().numpy()
    K = scene.K.double().numpy()
    v, u = np.mgrid[0:depth.shape[0], 0:depth.shape[1]].astype(np.float64)
    points = np.stack([(u - K[0, 2]) * depth / K[0, 0], (v - K[1, 2]) * depth / K[1, 1], depth], -1)
    valid = depth > 0
    if normals is not None:
        n = normals.astype(np.float64)
        valid &= np.linalg.norm(n, axis=-1) > 0.5
    elif from_depth:
        n = np.zeros_like(points)
        n[1:-1, 1:-1] = np.cross(points[2:, 1:-1] - points[:-2, 1:-1], points[1:-1, 2:] - points[1:-1, :-2])
        inner = np.zeros_like(valid)
        inner[1:-1, 1:-1] = valid[1:-1, 1:-1] & valid[2:, 1:-1] & valid[:-2, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2]
        valid = inner & (np.linalg.norm(n, axis=-1) > 0)
        n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    else:
        n = points - centre
        n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    grey = scene.image.numpy().mean(-1)[valid]
    top = np.percentile(grey, 99)
    use = (grey > 0.1 * top) & (grey < 0.95 * top)
    return np.linalg.lstsq(n[valid][use], grey[use], rcond=None)[0]


def truth_angles(folder: Path, rows: list[dict]) -> None:
    """Where ``folder/truth.json`` gives each frame's light direction from an object's centre
    (``{"centre": [x, y, z], "frames": {id: {"direction": [...]}}}``, as the ball set's):
    each row's ``angle`` (degrees; 90 where no light is presented) between it and the
    direction from the centre to the light that lights the centre most, and the Lambertian
    baselines' (:func:`lambert_direction`): ``lambert_angle`` given the set's true normals
    (``normals_gt.npy``; a sphere's about the centre where there are none, the ball's) and
    ``lambert_depth_angle`` given the depth's normals."""
    path = folder / "truth.json"
    if not path.exists():
        return
    truth = json.loads(path.read_text())
    centre = np.asarray(truth["centre"], dtype=float)
    true_normals = np.load(folder / "normals_gt.npy") if (folder / "normals_gt.npy").exists() else None
    frames = {f.id: f for f in capture_frames(folder)}
    for row in rows:
        known = truth["frames"].get(row["id"])
        if known is None:
            continue
        direction = np.asarray(known["direction"], dtype=float)
        lights = row["record"]["lights"]
        row["angle"] = round(angle_deg(np.asarray(brightest_at(lights, centre)["position"]) - centre, direction), 3) \
            if lights else 90.0
        scene = read_capture(frames[row["id"]])
        row["lambert_angle"] = round(angle_deg(lambert_direction(scene, centre, true_normals), direction), 3)
        row["lambert_depth_angle"] = round(angle_deg(lambert_direction(scene, centre, from_depth=True), direction), 3)


def _spread(points: np.ndarray) -> float:
    # The median distance of points (N, 3) from their (per-axis) median.
    return float(np.median(np.linalg.norm(points - np.median(points, 0), axis=1)))


def summarise(name: str, rows: list[dict], wall: float) -> dict:
    """One set's row of the results table."""
    found = [r for r in rows if r["light_found"]]
    n = len(rows)

    def pct(count: int, total: int = n) -> str:
        return f"{count}/{total} ({100 * count / total:.0f}%)" if total else "-"

    def median(key: str) -> float | None:
        values = [r[key] for r in found]
        return round(statistics.median(values), 3) if values else None

    posed = [r for r in found if "world" in r]
    summary = {"set": name, "frames": n, "no_light": pct(n - len(found)),
               "share_ge_0.1": pct(sum(r["share"] >= SHARE_TARGET for r in found), len(found)),
               "chroma_ge_0.2": pct(sum(r["min_chroma"] >= CHROMA_TARGET for r in rows)),
               "height_ge_0.3m": pct(sum(r["height"] >= HEIGHT_TARGET for r in found), len(found)),
               "median_share": median("share"), "median_min_chroma": round(statistics.median(r["min_chroma"] for r in rows), 3),
               "median_height_m": median("height"), "median_distance_m": median("distance"),
               "seconds_per_frame": round(wall / max(n, 1), 3)}
    scored = [r for r in rows if "angle" in r]
    if scored:
        summary["median_angle_deg"] = round(statistics.median(r["angle"] for r in scored), 2)
        summary["lambert_angle_deg"] = round(statistics.median(r["lambert_angle"] for r in scored), 2)
        summary["lambert_depth_angle_deg"] = round(statistics.median(r["lambert_depth_angle"] for r in scored), 2)
    if len(posed) >= 2:
        summary["world_spread_m"] = round(_spread(np.array([r["world"] for r in posed])), 3)
        camera = np.median(np.array([r["position"] for r in posed]), 0)  # a light glued to the camera
        glued = np.array([np.asarray(r["pose"])[:3, :3] @ camera + np.asarray(r["pose"])[:3, 3] for r in posed])
        summary["glued_spread_m"] = round(_spread(glued), 3)
    return summary


def contact_sheet(rows: list[dict], path: Path, tile: tuple[int, int] = (320, 240), columns: int = 5) -> None:
    """Every frame (sRGB) with its lights drawn in, labelled by share and height."""
    from PIL import Image, ImageDraw

    width, height = tile
    sheet = Image.new("RGB", (width * columns, height * (-(-len(rows) // columns))), "black")
    for k, row in enumerate(rows):
        scene = row["scene"]
        H, W = scene.image.shape[:2]
        srgb = (linear_to_srgb(scene.image.clamp(0, 1).numpy()) * 255).round().astype(np.uint8)
        image = Image.fromarray(srgb).resize(tile)
        draw = ImageDraw.Draw(image)
        sx, sy = width / W, height / H
        K = scene.K.numpy()
        for light, share in zip(row["record"]["lights"], row["shares"]):
            x, y, z = light["position"]
            u, v = (K[0, 0] * x / z + K[0, 2]) * sx if z > 1e-6 else None, (K[1, 1] * y / z + K[1, 2]) * sy if z > 1e-6 else None
            inside = u is not None and 0 <= u < width and 0 <= v < height
            colour = (255, 255, 0) if share >= SHARE_TARGET else (255, 64, 64)
            if inside:
                draw.ellipse([u - 7, v - 7, u + 7, v + 7], outline=colour, width=3)
                at = (u + 9, v - 6)
            else:  # an arrow at the border, from the centre towards the light's direction in the image plane
                d = np.array([x, y]) / max(float(np.hypot(x, y)), 1e-9)
                c = np.array([width / 2, height / 2])
                t = min((width / 2 - 12) / max(abs(d[0]), 1e-9), (height / 2 - 12) / max(abs(d[1]), 1e-9))
                tip = c + d * t
                draw.line([tuple(tip - d * 24), tuple(tip)], fill=colour, width=3)
                draw.ellipse([tip[0] - 4, tip[1] - 4, tip[0] + 4, tip[1] + 4], fill=colour)
                at = (float(np.clip(tip[0] - d[0] * 40, 2, width - 90)), float(np.clip(tip[1] - d[1] * 30, 2, height - 14)))
            up = row.get("height") if light is row["record"]["lights"][int(np.argmax(row["shares"]))] else None
            label = f"{share:.2f}" + (f" h{up:+.2f}m" if up is not None else "")
            draw.rectangle([at[0] - 1, at[1] - 1, at[0] + 7 * len(label), at[1] + 11], fill=(0, 0, 0))
            draw.text(at, label, fill=colour)
        for (x, y, z), share in row["unsupported"]:  # a light the record does not present: grey, dotted
            if z > 1e-6:
                u, v = (K[0, 0] * x / z + K[0, 2]) * sx, (K[1, 1] * y / z + K[1, 2]) * sy
                if 0 <= u < width and 0 <= v < height:
                    for a in range(0, 360, 45):
                        draw.arc([u - 7, v - 7, u + 7, v + 7], a, a + 20, fill=(170, 170, 170), width=2)
                    draw.text((u + 9, v - 6), f"({share:.2f})", fill=(170, 170, 170))
        caption = f"{row['id'][:28]}" + ("" if row["light_found"] else "  no light")
        draw.rectangle([0, 0, 7 * len(caption) + 4, 13], fill=(0, 0, 0))
        draw.text((2, 1), caption, fill=(255, 255, 255))
        sheet.paste(image, ((k % columns) * width, (k // columns) * height))
    sheet.save(path)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--input", type=Path, required=True, help="a capture folder or a folder of them")
    parser.add_argument("--set", dest="settings", nargs="*", default=[],
                        help="estimate.* overrides for the command, e.g. +estimate.tuning.max_pixels=76800")
    parser.add_argument("--name", default="real_frames", help="the results files' name")
    args = parser.parse_args(argv)
    settings = [s if s.startswith(("estimate.", "+estimate.")) else f"estimate.{s}" for s in args.settings]
    summaries, frames = [], []
    all_rows = []
    for folder in capture_sets(args.input):
        records, wall = run_command(folder, settings)
        rows = judge_set(folder, records)
        truth_angles(folder, rows)
        name = folder.name if folder != args.input else args.input.name
        summaries.append(summarise(name, rows, wall))
        print(json.dumps(summaries[-1]), flush=True)
        all_rows += rows
        frames += [{"set": name, **{k: v for k, v in r.items() if k not in ("scene", "record")}} for r in rows]
    if len(summaries) > 1:
        total = summarise("all", all_rows, sum(s["seconds_per_frame"] * s["frames"] for s in summaries))
        for key in ("world_spread_m", "glued_spread_m", "median_angle_deg", "lambert_angle_deg", "lambert_depth_angle_deg"):  # across sets: meaningless
            total.pop(key, None)
        summaries.append(total)
    device = torch.device("cpu")
    header = (f"Plausibility on real frames (no truth), `python -m benchmarks.real_frames --input {args.input}"
              + (f" --set {' '.join(args.settings)}" if args.settings else "") + "`: the brightest light's share "
              f"of the surfaces' light (target >= {SHARE_TARGET}), lights' and ambient's weakest channel over the "
              f"strongest (>= {CHROMA_TARGET}), the brightest light's height above the camera (>= {HEIGHT_TARGET} m "
              "in rooms lit from the ceiling), world-frame spread of posed frames' brightest light against a light "
              "glued to the camera, the command's seconds per frame (start-up included). no_light: of all frames; the share and "
              "height columns: of the frames with a light. Frames: the JSON file; "
              "contact sheet: the PNG of the same name.")
    path = write_results(args.name, device, summaries, header, COLUMNS)
    data = json.loads(path.with_suffix(".json").read_text())
    data["frames"] = frames
    data["settings"] = settings
    path.with_suffix(".json").write_text(json.dumps(data, indent=1))
    contact_sheet(all_rows, path.with_suffix(".png"))
    print(path)


if __name__ == "__main__":
    main()
