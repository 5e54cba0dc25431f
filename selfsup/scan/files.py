"""``mode=scan``: a posed RGB-D sequence in, one set of world-frame lights out.

The frames (:func:`selfsup.scenes.poses.posed_frames`: a capture folder with poses, a TUM
RGB-D or a 7-Scenes sequence) are cut to at most ``max_frames`` keyframes chosen for
coverage (:func:`keyframes`), each is estimated on its own as ``mode=estimate`` does (its
own exposure, its unknown albedo, its cast shadows), and the frames' lights are fused in
the world (:mod:`selfsup.scan.fuse`). The output is one JSON object (``docs/scan.md``); with
``frames_output`` every frame's record of the same lights in its camera frame (JSON Lines,
the estimation record format, intensities solved on that frame), for ``mode=insert``.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from selfsup.estimation.files import estimate_items, failure_reason, progress_bar, record_line, resolve_device
from selfsup.estimation.jobs import locked
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.prepare import prepare, within_pixels, working_range
from selfsup.estimation.problem import solve_at
from selfsup.scan.fuse import FusedLight, FuseOptions, fuse, world_lights
from selfsup.scenes.capture import capture_geometry, read_capture
from selfsup.scenes.io import Scene
from selfsup.scenes.poses import PosedFrame, check_convention, posed_frames

__all__ = ["scan_files", "keyframes", "scene_points", "scene_size"]

log = logging.getLogger(__name__)
# The first frames whose depths, seen from one another, tell a pose file's convention
# (:func:`selfsup.scenes.poses.check_convention`).
CONVENTION_FRAMES = 4


def keyframes(frames: list[PosedFrame], count: int) -> list[int]:
    """Indices of at most ``count`` frames chosen for coverage, in order: from the first,
    each next the frame farthest from those chosen, by camera position (in units of the
    cameras' spread) plus viewing direction (radians)."""
    if count <= 0 or count >= len(frames):
        return list(range(len(frames)))
    position = np.stack([f.pose[:3, 3] for f in frames])
    direction = np.stack([f.pose[:3, 2] for f in frames])  # the camera's z axis in the world
    spread = max(float(np.linalg.norm(position - position.mean(0), axis=1).max()), 1e-9)
    chosen = [0]
    gap = np.full(len(frames), np.inf)
    for _ in range(count - 1):
        last = chosen[-1]
        angle = np.arccos(np.clip(direction @ direction[last], -1.0, 1.0))
        gap = np.minimum(gap, np.linalg.norm(position - position[last], axis=1) / spread + angle)
        chosen.append(int(gap.argmax()))
    return sorted(set(chosen))


def scene_points(depth: np.ndarray, K: np.ndarray, pose: np.ndarray, stride: int = 4) -> np.ndarray:
    """Every ``stride``-th valid pixel's point ``(N, 3)`` of a ``depth (H, W)`` map (metres,
    intrinsics ``K (3, 3)``) in the world of ``pose`` (camera-to-world)."""
    depth = depth[::stride, ::stride]
    v, u = np.mgrid[0 : depth.shape[0] * stride : stride, 0 : depth.shape[1] * stride : stride]
    valid = np.isfinite(depth) & (depth > 0)
    z = depth[valid]
    camera = np.stack([(u[valid] - K[0, 2]) / K[0, 0] * z, (v[valid] - K[1, 2]) / K[1, 1] * z, z], 1)
    return camera @ pose[:3, :3].T + pose[:3, 3]


def scene_size(points: np.ndarray) -> float:
    """The scene's size: the diagonal of its points' ``(N, 3)`` 2-98% box (stray depth left out)."""
    if len(points) < 2:
        return 1.0
    low, high = np.percentile(points, [2, 98], axis=0)
    return max(float(np.linalg.norm(high - low)), 1e-6)


def _camera_record(frame: PosedFrame, scene: Scene, lights: list[FusedLight], options: EstimateOptions) -> dict:
    # The scan's lights in ``frame``'s camera: positions and covariances mapped, intensities
    # and ambient solved on the frame at those positions (the frame's exposure), grey.
    R, t = frame.pose[:3, :3], frame.pose[:3, 3]
    positions = np.stack([R.T @ (light.position - t) for light in lights]) if lights else np.zeros((0, 3))
    record = {"id": frame.id, "lights": [], "ambient": [0.0, 0.0, 0.0], "light_found": bool(lights)}
    if lights:
        scaled, factor = working_range(within_pixels(scene, options))
        problem = prepare([scaled], options)
        with torch.no_grad():
            _, intensity, ambient, *_ = solve_at(problem, torch.as_tensor(positions, dtype=problem.image.dtype)[None],
                                                 replace(options.tuning.refine, specular=False))
        # Grey, as the estimator's lights of a capture (light_colour=neutral): each channel's mean.
        intensity = (intensity[0].clamp_min(0).mean(-1, keepdim=True).expand(-1, 3) / factor).tolist()
        record["ambient"] = (ambient[0].clamp_min(0).mean().expand(3) / factor).tolist()
        for light, position, value in zip(lights, positions, intensity):
            cov = R.T @ light.cov @ R
            record["lights"].append({"position": position.tolist(), "intensity": value,
                                     "position_std": np.sqrt(np.diag(cov)).tolist(), "position_cov": cov.tolist()})
    return record


def _scan_record(lights: list[FusedLight], frames: list[PosedFrame], used: list[int], found: int, size: float,
                 seconds: float) -> dict:
    # The output object: the world lights, brightest first, and how the scan found them.
    out = []
    for light in lights:
        # Intensities in the units of the frames' images: each member's, the median over them
        # (the exposures differ between frames: the levels are a typical frame's).
        intensity = np.median(np.stack([m.intensity for m in light.members]), axis=0)
        frames_of = sorted({frames[used[m.frame]].id for m in light.members})
        out.append({"position": light.position.tolist(), "intensity": intensity.tolist(),
                    "position_std": np.sqrt(np.diag(light.cov)).tolist(), "position_cov": light.cov.tolist(),
                    "support": round(light.support, 3), "frames": frames_of})
    return {"lights": out, "frames": len(frames), "frames_used": [frames[i].id for i in used],
            "frames_with_light": found, "scene_size": round(size, 4), "seconds": round(seconds, 3)}


def scan_files(input: str | Path, output: str | Path, frames_output: str | Path | None = None,
               options: EstimateOptions | None = None, fuse_options: FuseOptions | None = None, max_frames: int = 30,
               progress: bool = True, device: str = "cpu", depth_scale: float = 1000.0,
               intrinsics: tuple[float, float, float, float] | None = None, workers: int | str = "auto") -> dict:
    """Fit one set of world-frame lights to the posed frames under ``input``; write the
    scan's JSON object to ``output`` and, with ``frames_output``, every frame's record of
    those lights in its camera (JSON Lines). ``max_frames``: keyframes estimated (0: all),
    spread over ``workers`` processes as ``mode=estimate`` spreads files. A frame that cannot
    be read or estimated is named and left out. Returns a summary:
    ``lights`` (how many), ``frames``, ``used``, ``failed`` (with reasons), the wall time.
    """
    started = time.perf_counter()
    options = options or EstimateOptions()
    fuse_options = fuse_options or FuseOptions()
    if not (isinstance(max_frames, int) and max_frames >= 0):
        raise ValueError(f"scan.max_frames must be an integer >= 0 (0: every frame), got {max_frames!r}")
    resolve_device(device)
    frames = posed_frames(input, depth_scale, intrinsics)
    if not frames:
        raise FileNotFoundError(f"scan.input {input}: no posed frames")
    check_convention([(*capture_geometry(f.frame), f.pose) for f in frames[:CONVENTION_FRAMES]], f"scan.input {input}")
    used = keyframes(frames, max_frames)
    failed: dict[str, str] = {}
    per_frame, points, kept = [], [], []
    bar, printing = progress_bar(len(used), "scan", "frame", progress)
    with printing:
        for index, (_, record, reason) in zip(used, estimate_items([frames[i].frame for i in used], options, device,
                                                                   workers)):
            frame = frames[index]
            if record is None:
                failed[str(frame)] = reason
                log.error("skipped %s: %s", frame, reason)
            else:
                per_frame.append(world_lights(record, frame.pose, len(kept)))
                points.append(scene_points(*capture_geometry(frame.frame), frame.pose))
                kept.append(index)
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    if not kept:
        raise ValueError(f"scan.input {input}: no frame could be estimated ({len(failed)} failed)")
    size = scene_size(np.concatenate(points))
    lights = fuse(per_frame, size, fuse_options)
    result = _scan_record(lights, frames, kept, sum(1 for f in per_frame if f), size, time.perf_counter() - started)
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(json.dumps(result, indent=1, allow_nan=False) + "\n")
    if frames_output is not None:
        with locked(Path(frames_output)) as out:
            out.truncate(0)
            for frame in frames:
                try:
                    out.write(record_line(_camera_record(frame, read_capture(frame.frame), lights, options)) + "\n")
                except (ValueError, RuntimeError) as error:
                    failed.setdefault(str(frame), failure_reason(error))
                    log.error("no frame record for %s: %s", frame, failed[str(frame)])
    wall = time.perf_counter() - started
    log.info("scan of %d frame(s) (%d estimated, %d failed): %d light(s) in the world, in %.1f s; wrote %s",
             len(frames), len(kept), len(failed), len(lights), wall, output)
    return {"lights": len(lights), "frames": len(frames), "used": len(kept), "failed": len(failed),
            "failures": failed, "wall_seconds": round(wall, 3), "output": str(output),
            "scene_size": round(size, 4)}
