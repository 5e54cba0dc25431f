"""A sequence of frames in, one JSON line per frame out: ``mode=track``.

The frames are those ``mode=estimate`` reads (:func:`selfsup.estimation.inputs.estimate_inputs`:
a capture folder, or a directory of ``.npz`` scene files) in the natural order of their
names (``frame_9`` before ``frame_10``). A frame that cannot be read or estimated is
named with its reason and skipped; the tracker goes on from the frames before it.
"""

from __future__ import annotations

import logging
import re
import time
from pathlib import Path


from selfsup.estimation.files import failure_reason, progress_bar, record_line, resolve_device
from selfsup.estimation.inputs import estimate_inputs, item_id
from selfsup.estimation.jobs import locked, resume_track
from selfsup.estimation.network import cached_network, checkpoints_of
from selfsup.estimation.options import EstimateOptions
from selfsup.scenes.capture import is_capture_folder
from selfsup.scenes.io import SceneFileError
from selfsup.scenes.poses import posed_frames
from selfsup.tracking.tracker import Tracker
from selfsup.tracking.tuning import TrackTuning

__all__ = ["track_files", "natural_order"]

log = logging.getLogger(__name__)


def natural_order(items: list) -> list:
    """``items`` sorted by their names' text, numbers compared as numbers (``frame_9`` before ``frame_10``)."""
    def key(item) -> list:
        return [(0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", str(item))]

    return sorted(items, key=key)


def _poses(input: str | Path, depth_scale: float, intrinsics) -> dict:
    # Each frame's camera-to-world pose where ``input`` is a posed sequence (a capture folder
    # with poses.json or poses.txt, a TUM RGB-D or a 7-Scenes sequence), by frame; else {}.
    path = Path(input)
    if not path.is_dir():
        return {}
    if is_capture_folder(path) and not any((path / name).is_file() for name in ("poses.json", "poses.txt")):
        return {}
    try:
        return {posed.frame: posed.pose for posed in posed_frames(path, depth_scale, intrinsics)}
    except FileNotFoundError:  # no posed layout: frames alone
        return {}


def track_files(input: str | Path, output: str | Path, options: EstimateOptions | None = None,
                tuning: TrackTuning | None = None, refresh: int = 30, progress: bool = True, device: str = "cpu",
                depth_scale: float = 1000.0, intrinsics: tuple[float, float, float, float] | None = None,
                overwrite: bool = False) -> dict:
    """Track the lights through the frames under ``input``; one JSON line per frame in ``output``.

    ``input``: a capture folder or a directory of scene files (their frames in natural
    order), or a posed sequence (:func:`selfsup.scenes.poses.posed_frames`: the lights are then
    carried through the camera's moves, and each gets its ``world_position``); ``options``: the full estimates' settings (:class:`EstimateOptions`);
    ``tuning``: the tracker's constants; ``refresh``: a full estimate every that-many-th
    frame whatever the evidence (0: on evidence only); ``depth_scale``, ``intrinsics``:
    as ``mode=estimate``. ``output`` is never overwritten unless ``overwrite``: a rerun
    keeps its records before the last full estimate and tracks on from that frame
    (:func:`selfsup.estimation.jobs.resume_track`). Returns a summary: ``done``, ``failed``
    (with reasons), ``skipped`` (kept from the output), ``full`` (frames estimated in
    full), the median warm latency in ms, the wall time.
    """
    started = time.perf_counter()
    options = options or EstimateOptions()
    where = resolve_device(device)
    poses = _poses(input, depth_scale, intrinsics)
    frames = natural_order(list(poses) if poses else estimate_inputs(input, None, depth_scale, intrinsics,
                                                                     key="track.input"))
    if options.method in ("cnn", "cnn+refine"):
        for path in checkpoints_of(options):
            cached_network(path, str(where))  # a missing or bad checkpoint stops here, before any frame
    output = Path(output)
    with locked(output) as out:  # one run at a time on an output
        if overwrite:
            out.truncate(0)
        kept = resume_track(output)
        frames = [frame for frame in frames if item_id(frame) not in kept] if kept else frames
        if kept:
            log.info("%d frame(s) of %s kept, tracking on from its last full estimate (track.overwrite=true "
                     "starts over)", len(kept), output)
        tracker = Tracker(options, tuning or TrackTuning(), refresh, where, first_frame=len(kept))
        failed: dict[str, str] = {}
        warm, full = [], 0
        bar, printing = progress_bar(len(frames), "track", "frame", progress)
        with printing:
            for frame in frames:
                try:
                    record = tracker.update(frame, poses.get(frame) if poses else None)
                    line = record_line(record)
                except (SceneFileError, ValueError, RuntimeError) as error:
                    failed[str(frame)] = failure_reason(error)
                    log.error("skipped %s: %s", frame, failed[str(frame)])
                else:
                    out.write(line + "\n")
                    out.flush()
                    if record["full"]:
                        full += 1
                    else:
                        warm.append(record["latency_ms"])
                if bar is not None:
                    bar.update(1)
        if bar is not None:
            bar.close()
    done = len(frames) - len(failed)
    if not done and not kept:  # every frame failed: no empty output left behind to be taken for a result
        output.unlink(missing_ok=True)
    wall = time.perf_counter() - started
    summary = {"done": done, "failed": len(failed), "failures": failed, "skipped": len(kept), "full": full,
               "warm_ms_median": sorted(warm)[len(warm) // 2] if warm else None, "wall_seconds": round(wall, 3),
               "output": str(output) if done or kept else None}
    log.info("tracked %d frame(s), %d failed, %d estimated in full, in %.1f s (warm frames %.1f ms median); wrote %s",
             done, len(failed), full, wall, summary["warm_ms_median"] or 0.0, output if done else "nothing")
    return summary
