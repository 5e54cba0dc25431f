"""The per-frame search as the network's teacher: its lights are where the albedo-free photometric error is least.

The network places a slot by choosing one of its position hypotheses (a classification)
and refining it; only the last, small step follows a loss's gradient. On real-looking
frames the photometric error's gradient at the network's answer points to a local minimum
of textures, highlights and indirect light, not to the lamp (measured on Mitsuba frames: on
a grid of +-0.1 of the scene size about the true light the re-render error is least at the
light in 25-28 of 64 frames, benchmarks/results/adapt_loss_landscape_cpu2_2026-11-29.md).
The estimator's per-frame search minimises the albedo-free error globally, with cast
shadows and each region's albedo solved (grid, robust fit, model selection), which finds
the lamp on most frames; what it finds is the target of each slot's hypothesis scores,
its position and (optionally) the count (:func:`selfsup.losses.teacher_loss`). No ground
truth enters: the teacher is the photometric objective's own minimiser.

Two users: ``mode=adapt`` teaches on a user's captures (:func:`selfsup.adapt.frames.teach`),
and training teaches on its procedural pool (:func:`pool_teacher`: the pool's scenes
rendered again at a finer grid, searched as captures, the answers cached by seed).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from selfsup.estimation.files import estimate_items, record_line
from selfsup.estimation.inputs import SceneInMemory
from selfsup.estimation.jobs import read_records
from selfsup.estimation.options import EstimateOptions
from selfsup.scenes.dataset import ProceduralScenes
from selfsup.scenes.io import Scene

__all__ = ["PoolTeacher", "pool_teacher", "teacher_cache_path", "read_answers"]

log = logging.getLogger(__name__)


def teacher_cache_path(folder: str | Path, sampler, degradations, samples: int, base_seed: int, scale: int,
                       method: str) -> Path:
    """The JSON Lines file of ``folder`` that holds the teacher's answers for one pool recipe:
    its name hashes everything that changes them (sampler, degradations, anti-aliasing,
    seed, scale, the search's method), so that a changed recipe searches again."""
    recipe = json.dumps({"sampler": dataclasses.asdict(sampler), "degradations": dataclasses.asdict(degradations),
                         "samples": samples, "base_seed": base_seed, "scale": scale, "method": method},
                        sort_keys=True, default=str)
    return Path(folder) / f"teacher_{hashlib.sha256(recipe.encode()).hexdigest()[:16]}.jsonl"


def read_answers(cache: Path) -> dict[int, list]:
    """``{pool index: [[x, y, z], ...]}`` of a teacher cache (records ``{"id": "pool-<i>",
    "index": i, "lights": ...}``; a killed run's torn last line is cut off and searched again,
    :func:`selfsup.estimation.jobs.read_records`)."""
    return {int(record["index"]): record["lights"] for record in read_records(Path(cache))}


def pool_teacher(sampler, degradations, samples: int, base_seed: int, count: int, max_lights: int, cache: Path,
                 scale: int = 2, method: str = "refine", workers: int | str = "auto", chunk: int = 64,
                 progress: bool = False) -> tuple[Tensor, Tensor, dict]:
    """The per-frame search's lights on the first ``count`` scenes of a procedural pool.

    Each scene (item ``i`` of ``ProceduralScenes(sampler, degradations, base_seed=base_seed)``:
    the pool's own scene, its lights and camera independent of the grid) is rendered again
    at ``scale`` times the pool's height and width (the search places about half the
    one-light rooms of the captures recipe at 128x96, ``benchmarks/teacher_bound.py``; 6 of
    15 at 64x48, ad hoc), its albedo withheld as a capture's, and estimated by ``mode=estimate``'s defaults with ``method`` (``refine``:
    the grid search, no network, so that the teacher does not depend on the weights it
    trains; up to two lights, the estimator's ``max_lights``).
    Answers are appended to ``cache`` (JSON Lines, one frame a line, by index) as they come
    and read back instead of searched again: a killed run resumes.

    Returns ``(position (count, max_lights, 3), mask (count, max_lights) bool, stats)``:
    the teacher's lights, brightest first (none where it found no light or failed), and
    ``stats`` (``searched``, ``seconds``, ``frames_with_lights``).
    """
    if count < 0 or scale < 1:
        raise ValueError(f"teacher count must be >= 0 and scale >= 1, got {count} and {scale}")
    cache = Path(cache)
    cache.parent.mkdir(parents=True, exist_ok=True)
    answers = read_answers(cache)
    missing = [i for i in range(count) if i not in answers]
    fine = dataclasses.replace(sampler, height=sampler.height * scale, width=sampler.width * scale)
    # The pool's rooms may hold more lights than the slots taught (the trainer's pool holds them all).
    scenes = ProceduralScenes(fine, degradations, length=max(count, 1), base_seed=base_seed, samples=samples,
                              max_lights=max(max_lights, len(sampler.n_lights_probs)))
    options = EstimateOptions(method=method)  # mode=estimate's own settings (its max_lights: 2)
    started = time.perf_counter()
    with cache.open("a") as out:
        for first in range(0, len(missing), chunk):
            indices = missing[first:first + chunk]
            frames = {SceneInMemory(_as_capture(item, f"pool-{i}")): i for i, item in
                      zip(indices, scenes.__getitems__(indices))}
            for frame, record, reason in estimate_items(list(frames), options, workers=workers, batch=4):
                index = frames[frame]
                if record is None:
                    log.warning("the teacher's search failed on pool scene %d (%s): no lights taught there", index,
                                reason)
                lights = [light["position"] for light in (record or {"lights": []})["lights"]]
                answers[index] = lights
                out.write(record_line({"id": str(frame), "index": index, "lights": lights}) + "\n")
            out.flush()
            if progress:
                log.info("teacher: %d of %d pool scenes searched (%.0f s)", first + len(indices), len(missing),
                         time.perf_counter() - started)
    position = torch.zeros(count, max_lights, 3)
    mask = torch.zeros(count, max_lights, dtype=torch.bool)
    for i in range(count):
        lights = torch.tensor(answers[i], dtype=torch.float32).reshape(-1, 3)[:max_lights]
        position[i, :len(lights)], mask[i, :len(lights)] = lights, True
    stats = {"searched": len(missing), "seconds": time.perf_counter() - started,
             "frames_with_lights": int(mask.any(1).sum())}
    return position, mask, stats


def _as_capture(item: dict[str, Tensor], frame_id: str) -> Scene:
    # A pool item as the estimator reads a capture frame: linear colour, depth, K; the albedo
    # one constant (unknown), no normals, ambient or lights; full scale 1 (8-bit codes' top).
    H, W = item["depth"].shape
    return Scene(image=item["image"], depth=item["depth"], K=item["K"], kd=torch.full((H, W, 3), 0.5),
                      meta={"id": frame_id, "generator": "capture", "falloff": "inverse_square", "full_scale": 1.0})


@dataclass(frozen=True)
class PoolTeacher:
    """:func:`pool_teacher` for one training recipe, as the trainer calls it: ``teacher(base_seed)
    -> (position (count, K, 3), mask (count, K))`` for the pool of ``base_seed``, its answers
    in ``folder`` (:func:`teacher_cache_path`)."""

    sampler: object
    degradations: object
    samples: int
    count: int
    max_lights: int
    folder: str | Path
    scale: int = 2
    method: str = "refine"
    progress: bool = False

    def __call__(self, base_seed: int) -> tuple[Tensor, Tensor]:
        cache = teacher_cache_path(self.folder, self.sampler, self.degradations, self.samples, base_seed, self.scale,
                                   self.method)
        position, mask, stats = pool_teacher(self.sampler, self.degradations, self.samples, base_seed, self.count,
                                             self.max_lights, cache, self.scale, self.method, progress=self.progress)
        log.info("teacher: %d of %d pool scenes with lights (%d searched in %.0f s; cache %s)",
                 stats["frames_with_lights"], self.count, stats["searched"], stats["seconds"], cache)
        return position, mask
