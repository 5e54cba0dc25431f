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
its position and (optionally) the count. No ground truth enters: the teacher is the
photometric objective's own minimiser.

Two users: ``mode=adapt`` teaches on a user's captures (:func:`selfsup.adapt.frames.teach`),
and training teaches on its procedural pool (:func:`pool_teacher`: the pool's scenes
rendered again at a finer grid, searched as captures, the answers cached by seed).
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from selfsup.linear import pseudo_huber
from selfsup.model import LightPrediction

__all__ = ["TeacherOptions", "teacher_loss", "pool_teacher", "teacher_cache_path"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TeacherOptions:
    """Weights of the teacher's terms (mirrors ``adapt.teacher`` and ``loss.teacher``): ``position`` (pseudo-Huber of
    the slot-to-light distance over the scene size, width ``scale``), ``anchors`` (cross
    entropy of the hypothesis scores against a Gaussian of width ``anchor_width`` of the scene
    size about the light), ``count`` (cross entropy of the count head against the lights found;
    0 by default: at 0.5 the adapted network stopped counting second lights, 25% -> 3% of the
    two-light test rooms, benchmarks/results/adapt_teacher_count_cpu2_2026-11-29.md). All 0:
    the photometric loss alone."""

    position: float = 1.0
    anchors: float = 0.1
    count: float = 0.0
    scale: float = 0.02
    anchor_width: float = 0.05

    def __post_init__(self):
        for name in ("position", "anchors", "count"):
            if getattr(self, name) < 0:
                raise ValueError(f"adapt.teacher.{name} must be >= 0, got {getattr(self, name)}")
        if self.scale <= 0 or self.anchor_width <= 0:
            raise ValueError("adapt.teacher.scale and adapt.teacher.anchor_width must be > 0")


def _assignment(position: Tensor, teacher: Tensor, mask: Tensor) -> Tensor:
    """``(B, K)`` long: the slot each teacher row goes to (a permutation of the slots, the one
    of least summed distance over the rows that are lights)."""
    B, K, _ = position.shape
    distance = torch.cdist(teacher, position.detach())  # (B, K rows, K slots)
    orders = torch.tensor(list(itertools.permutations(range(K))), device=position.device)  # (P, K)
    cost = (distance[:, torch.arange(K, device=position.device)[None], orders] * mask[:, None]).sum(-1)  # (B, P)
    return orders[cost.argmin(1)]


def teacher_loss(prediction: LightPrediction, teacher: Tensor, mask: Tensor, size: Tensor,
                 options: TeacherOptions) -> tuple[Tensor, dict[str, float]]:
    """``()`` loss of ``prediction`` against the teacher's lights ``teacher (B, K, 3)`` (rows of
    ``mask (B, K)``; an image without any is left out) and its parts; ``size (B,)`` the scenes' sizes."""
    zero = prediction.position.new_zeros(())
    has = mask.any(1)
    if not bool(has.any()):
        return zero, {}
    position, anchors, logits = prediction.position[has], prediction.anchor_position[has], prediction.anchor_logits[has]
    teacher, mask, size = teacher[has].to(position), mask[has], size[has].to(position)
    slot = _assignment(position, teacher, mask)  # (b, K)
    rows = torch.arange(len(slot), device=slot.device)[:, None]
    placed = position[rows, slot]  # (b, K, 3): the slot of each teacher row
    distance = (placed - teacher).norm(dim=-1) / size[:, None]
    weight = mask.to(position.dtype)
    position_term = (pseudo_huber(distance, options.scale) * weight).sum() / weight.sum()
    # Each assigned slot's hypotheses: a Gaussian about the teacher's light.
    spread = (anchors[rows, slot] - teacher[:, :, None]).norm(dim=-1) / size[:, None, None]  # (b, K, M)
    target = torch.softmax(-0.5 * (spread / options.anchor_width) ** 2, -1)
    anchor_term = -((target * torch.log_softmax(logits[rows, slot], -1)).sum(-1) * weight).sum() / weight.sum()
    count_term = F.cross_entropy(prediction.count_logits[has], mask.sum(1) - 1)
    total = options.position * position_term + options.anchors * anchor_term + options.count * count_term
    return total, {"teacher_position": float(position_term.detach()), "teacher_anchors": float(anchor_term.detach()),
                   "teacher_count": float(count_term.detach())}


def teacher_cache_path(folder: str | Path, sampler, degradations, samples: int, base_seed: int, scale: int,
                       method: str) -> Path:
    """The JSON Lines file of ``folder`` that holds the teacher's answers for one pool recipe:
    its name hashes everything that changes them (sampler, degradations, anti-aliasing,
    seed, scale, the search's method), so that a changed recipe searches again."""
    recipe = json.dumps({"sampler": dataclasses.asdict(sampler), "degradations": dataclasses.asdict(degradations),
                         "samples": samples, "base_seed": base_seed, "scale": scale, "method": method},
                        sort_keys=True, default=str)
    return Path(folder) / f"teacher_{hashlib.sha256(recipe.encode()).hexdigest()[:16]}.jsonl"


def _read_answers(cache: Path) -> dict[int, list]:
    answers = {}
    if cache.exists():
        for line in cache.read_text().splitlines():
            try:
                record = json.loads(line)
                answers[int(record["index"])] = record["lights"]
            except (ValueError, KeyError, TypeError):
                continue  # a killed run's torn last line: that frame is searched again
    return answers


def pool_teacher(sampler, degradations, samples: int, base_seed: int, count: int, max_lights: int, cache: Path,
                 scale: int = 2, method: str = "refine", workers: int | str = "auto", chunk: int = 64,
                 progress: bool = False) -> tuple[Tensor, Tensor, dict]:
    """The per-frame search's lights on the first ``count`` scenes of a procedural pool.

    Each scene (item ``i`` of ``ProceduralScenes(sampler, degradations, base_seed=base_seed)``:
    the pool's own scene, its lights and camera independent of the grid) is rendered again
    at ``scale`` times the pool's height and width (the search is right on about three
    quarters of one-light rooms at 128x96, on 40% at 64x48), its albedo withheld as a
    capture's, and estimated by ``mode=estimate``'s defaults with ``method`` (``refine``:
    the grid search, no network, so that the teacher does not depend on the weights it
    trains; up to two lights, the estimator's ``max_lights``).
    Answers are appended to ``cache`` (JSON Lines, one frame a line, by index) as they come
    and read back instead of searched again: a killed run resumes.

    Returns ``(position (count, max_lights, 3), mask (count, max_lights) bool, stats)``:
    the teacher's lights, brightest first (none where it found no light or failed), and
    ``stats`` (``searched``, ``seconds``, ``frames_with_lights``).
    """
    from selfsup.estimation.files import estimate_items
    from selfsup.estimation.inputs import SceneInMemory
    from selfsup.estimation.options import EstimateOptions
    from selfsup.scenes.dataset import ProceduralScenes
    from selfsup.scenes.io import Scene

    if count < 0 or scale < 1:
        raise ValueError(f"teacher count must be >= 0 and scale >= 1, got {count} and {scale}")
    cache = Path(cache)
    cache.parent.mkdir(parents=True, exist_ok=True)
    answers = _read_answers(cache)
    missing = [i for i in range(count) if i not in answers]
    fine = dataclasses.replace(sampler, height=sampler.height * scale, width=sampler.width * scale)
    scenes = ProceduralScenes(fine, degradations, length=max(count, 1), base_seed=base_seed, samples=samples,
                              max_lights=max_lights)
    options = EstimateOptions(method=method)  # mode=estimate's own settings (its max_lights: 2)
    started = time.perf_counter()
    with cache.open("a") as out:
        for first in range(0, len(missing), chunk):
            indices = missing[first:first + chunk]
            frames = [SceneInMemory(_as_capture(item, f"pool-{i}", Scene)) for i, item in
                      zip(indices, scenes.__getitems__(indices))]
            for frame, record, reason in estimate_items(frames, options, workers=workers, batch=4):
                index = int(str(frame).split("-")[1])
                if record is None:
                    log.warning("the teacher's search failed on pool scene %d (%s): no lights taught there", index,
                                reason)
                lights = [light["position"] for light in (record or {"lights": []})["lights"]]
                answers[index] = lights
                out.write(json.dumps({"index": index, "lights": lights}) + "\n")
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


def _as_capture(item: dict[str, Tensor], frame_id: str, scene_type):
    # A pool item as the estimator reads a capture frame: linear colour, depth, K; the albedo
    # one constant (unknown), no normals, ambient or lights; full scale 1 (8-bit codes' top).
    H, W = item["depth"].shape
    return scene_type(image=item["image"], depth=item["depth"], K=item["K"], kd=torch.full((H, W, 3), 0.5),
                      meta={"id": frame_id, "generator": "capture", "falloff": "inverse_square", "full_scale": 1.0})
