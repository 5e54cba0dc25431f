"""Scene files in, lights out: search/refinement, model selection, uncertainty, JSON Lines.

For each scene the candidate models are fitted (1 .. ``max_lights`` lights; with
and without the specular term when the file has a non-zero ``ks``) and the one
with the least penalised fit wins (:func:`bic`). Each light gets a position
standard deviation from the Gauss-Newton covariance of the chosen fit.

Methods (``estimate.method``):

- ``refine``: no network; a grid search finds the starts (:func:`selfsup.refine.search`);
- ``cnn+refine`` (default): the network's light slots are the starts of the
  refinement, which makes it one to two orders of magnitude faster;
- ``cnn``: the network alone (slots with presence above one half), intensities
  and ambient solved in closed form at its positions.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
from torch import Tensor

from render import light_transport
from selfsup.refine import (Fit, FitProblem, RefineOptions, evaluate, position_covariance, refine, robust_loss,
                            search)
from selfsup.scenes.io import Scene, SceneFileError, read_scene, render_inputs

__all__ = ["EstimateOptions", "Candidate", "bic", "problem_of", "estimate_scene", "estimate_files", "scene_files"]

log = logging.getLogger(__name__)
METHODS = ("cnn+refine", "cnn", "refine")


@dataclass
class EstimateOptions:
    """Settings of ``mode=estimate`` (mirrors ``configs/estimate/default.yaml``).

    ``max_lights``: the most lights a scene may get; each must carry at least
    ``min_light_share`` of the rendered direct light. ``block_px``: residuals are
    spatially correlated, so the criterion counts one independent sample per
    ``block_px x block_px`` pixels. ``shadows``: the renderer's shadow method.
    ``checkpoint``: the network of the ``cnn`` methods (None: the shipped one).
    """

    method: str = "cnn+refine"
    checkpoint: str | None = None  # None: the shipped network
    cnn_grid: tuple[int, int, int] = (7, 6, 7)  # cnn+refine: the grid searched beside the network's slots
    cnn_starts: int = 8
    max_lights: int = 2
    block_px: int = 8
    min_light_share: float = 0.1
    shadows: str = "epipolar"
    refine: RefineOptions = field(default_factory=RefineOptions)

    def __post_init__(self):
        self.cnn_grid = tuple(self.cnn_grid)
        if len(self.cnn_grid) != 3 or min(self.cnn_grid) < 2 or self.cnn_starts < 1:
            raise ValueError(f"cnn_grid needs 3 sizes >= 2 and cnn_starts >= 1, got {self.cnn_grid}, {self.cnn_starts}")
        if self.method not in METHODS:
            raise ValueError(f"estimate.method must be one of {METHODS}, got {self.method!r}")
        if self.max_lights < 1:
            raise ValueError(f"max_lights must be >= 1, got {self.max_lights}")


@dataclass
class Candidate:
    """One fitted model: its fit, light count, specular switch and criterion value."""

    fit: Fit
    n_lights: int
    specular: bool
    criterion: float


def problem_of(scene: Scene, shadows: str = "epipolar", dtype=torch.float32) -> FitProblem:
    """A batch-of-one :class:`FitProblem` from a scene file's contents."""
    gbuffer, material, _ = render_inputs(scene)
    if not bool(gbuffer.mask.any()):
        raise SceneFileError(scene.id, "no valid pixel left after estimating normals")
    return FitProblem(gbuffer, material, scene.image.permute(2, 0, 1)[None].to(dtype),
                      None if scene.ambient is None else scene.ambient[None], scene.falloff, shadows)


def bic(loss: float, n_values: int, n_params: int, block_px: int) -> float:
    """Bayesian information criterion on ``n_values / block_px^2`` independent samples.

    ``loss`` is the (robust) sum of squared residuals over ``n_values`` values.
    """
    n_eff = max(n_values / block_px**2, n_params + 2.0)
    return n_eff * math.log(max(loss, 1e-30) / n_values) + n_params * math.log(n_eff)


def light_shares(problem: FitProblem, fit: Fit, specular: bool) -> Tensor:
    """Each light's share ``(B, L)`` of the direct light the fit renders (summed over pixels)."""
    t = light_transport(problem.gbuffer, problem.material, fit.position, falloff=problem.falloff,
                        shadows=problem.shadows, specular=specular)
    kd = problem.material.kd.permute(0, 3, 1, 2)[:, :, None]  # (B, 3, 1, H, W)
    per_light = kd * t.diffuse[:, None]
    if t.specular is not None:
        per_light = per_light + problem.material.ks.permute(0, 3, 1, 2)[:, :, None] * t.specular[:, None]
    energy = (per_light.sum((-1, -2)) * fit.intensity.transpose(1, 2)).sum(1)  # (B, L)
    return energy / energy.sum(-1, keepdim=True).clamp_min(1e-30)


@functools.lru_cache(maxsize=4)
def _network(checkpoint: str | None):
    from selfsup.checkpoint import load_network

    return load_network(checkpoint)[0]


@torch.no_grad()
def network_slots(scene: Scene, problem: FitProblem, checkpoint: str | None = None) -> tuple[Tensor, Tensor]:
    """The network's light slots for one scene: positions ``(1, K, 3)`` and presence ``(K,)``,
    most present first."""
    network = _network(checkpoint)
    prediction = network(problem.image.float(), problem.gbuffer, problem.material.kd.float())
    order = prediction.presence[0].argsort(descending=True)
    return prediction.position[:, order].to(problem.image.dtype), prediction.presence[0, order]


def estimate_scene(scene: Scene, options: EstimateOptions) -> dict:
    """Estimate the lights of one scene; returns the JSON-ready record (no ``seconds``).

    Models tried: one light (searched with the specular term if the file has ks),
    the same light refined without it, then more lights with the better of the two
    while each added light lowers :func:`bic` and carries at least
    ``min_light_share`` of the rendered direct light. With ``cnn+refine`` the
    searches start from the network's slots (each slot alone for one light, the
    chosen lights plus the next slot for more); ``cnn`` keeps the slots as they are.
    """
    problem = problem_of(scene, options.shadows)
    has_specular = scene.ks is not None and bool((scene.ks > 0).any())
    n_values = int(problem.gbuffer.mask.sum()) * 3
    unknown_ambient = 3 if problem.ambient is None else 0

    def candidate(fit: Fit, n_lights: int, specular: bool) -> Candidate:
        loss = float(robust_loss(problem, fit.model, replace(options.refine, specular=specular))[0])
        k = 6 * n_lights + unknown_ambient + int(specular)
        return Candidate(fit, n_lights, specular, bic(loss, n_values, k, options.block_px))

    slots = presence = None
    if options.method in ("cnn", "cnn+refine"):
        slots, presence = network_slots(scene, problem, options.checkpoint)
    if options.method == "cnn":
        return _network_record(scene, problem, slots, presence, has_specular, options)

    def first_light(opts: RefineOptions) -> Fit:
        if slots is None:
            return search(problem, 1, opts)
        return search(problem, 1, opts, extra_starts=slots, per_axis=options.cnn_grid, starts=options.cnn_starts)

    def more_lights(n_lights: int, fixed: Tensor, opts: RefineOptions) -> Fit:
        if slots is None:
            return search(problem, n_lights, opts, fixed=fixed)
        return search(problem, n_lights, opts, fixed=fixed, extra_starts=slots, per_axis=options.cnn_grid,
                      starts=options.cnn_starts)

    first = first_light(replace(options.refine, specular=has_specular))
    tried = [candidate(first, 1, has_specular)]
    if has_specular:
        tried.append(candidate(refine(problem, first.position, replace(options.refine, specular=False)), 1, False))
    best = min(tried, key=lambda c: c.criterion)
    for n_lights in range(2, options.max_lights + 1):
        opts = replace(options.refine, specular=best.specular)
        more = candidate(more_lights(n_lights, best.fit.position, opts), n_lights, best.specular)
        tried.append(more)
        share = float(light_shares(problem, more.fit, best.specular).min())
        if more.criterion >= best.criterion or share < options.min_light_share:
            break  # a light that does not pay for itself: more would not either
        best = more
    return _record(scene, problem, best, tried, options)


def _network_record(scene: Scene, problem: FitProblem, slots: Tensor, presence: Tensor, has_specular: bool,
                    options: EstimateOptions) -> dict:
    # The network's present slots (at least one), intensities and ambient solved there.
    keep = max(1, min(int((presence > 0.5).sum()), options.max_lights))
    opts = replace(options.refine, specular=has_specular)
    cost, intensity, ambient, model, _, _, _ = evaluate(problem, slots[:, :keep], opts)
    fit = Fit(slots[:, :keep], intensity, ambient, cost, model, torch.zeros(1, dtype=torch.long),
              ((model - problem.image) ** 2 * problem.gbuffer.mask[:, None]).flatten(1).sum(1),
              problem.gbuffer.mask.flatten(1).sum(1) * 3)
    n_values = int(problem.gbuffer.mask.sum()) * 3
    loss = float(robust_loss(problem, model, opts)[0])
    k = 6 * keep + (3 if problem.ambient is None else 0) + int(has_specular)
    chosen = Candidate(fit, keep, has_specular, bic(loss, n_values, k, options.block_px))
    return _record(scene, problem, chosen, [chosen], options)


def _record(scene: Scene, problem: FitProblem, best: Candidate, tried: list[Candidate], options: EstimateOptions) -> dict:
    refine_opts = replace(options.refine, specular=best.specular)
    cov = position_covariance(problem, best.fit, refine_opts, correlation_px=float(options.block_px**2))
    std = cov.diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt()[0]
    lights = [
        {"position": best.fit.position[0, i].tolist(), "intensity": best.fit.intensity[0, i].tolist(),
         "position_std": std[i].tolist(), "position_cov": cov[0, i].tolist()}
        for i in range(best.n_lights)
    ]
    return {
        "id": scene.id, "lights": lights, "ambient": best.fit.ambient[0].tolist(),
        "specular": best.specular,
        "candidates": [{"n_lights": c.n_lights, "specular": c.specular, "criterion": round(c.criterion, 3)}
                       for c in tried],
    }


def scene_files(path: str | Path) -> list[Path]:
    """The ``.npz`` files of a directory (sorted), or the one file given."""
    path = Path(path)
    if path.is_dir():
        return sorted(p for p in path.glob("*.npz"))
    if path.exists():
        return [path]
    raise FileNotFoundError(f"estimate.input {path} does not exist")


def estimate_files(input: str | Path, output: str | Path, options: EstimateOptions, progress: bool = True) -> dict:
    """Estimate every scene file under ``input``; one JSON line per good file in ``output``.

    A bad file is logged with its name and reason and skipped; the summary returned
    counts ``done``, ``failed`` (with reasons) and the median seconds per scene.
    """
    files = scene_files(input)
    if not files:
        raise FileNotFoundError(f"no .npz scene files in {input}")
    if options.method in ("cnn", "cnn+refine"):
        _network(options.checkpoint)  # a missing or bad checkpoint stops here, before any file
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    failed, seconds = {}, []
    try:
        from tqdm import tqdm
        bar = tqdm(files, desc="estimate", unit="scene", disable=not progress)
    except ImportError:  # tqdm is optional: no progress bar then
        bar = files
    with output.open("w") as out:
        for path in bar:
            try:
                scene = read_scene(path)
                start = time.perf_counter()
                with torch.no_grad():
                    record = estimate_scene(scene, options)
                record["seconds"] = round(time.perf_counter() - start, 4)
            except (SceneFileError, ValueError, RuntimeError) as error:
                reason = error.reason if isinstance(error, SceneFileError) else f"{type(error).__name__}: {error}"
                failed[str(path)] = reason
                log.error("skipped %s: %s", path, reason)
                continue
            seconds.append(record["seconds"])
            out.write(json.dumps(record) + "\n")
            out.flush()
    summary = {"done": len(seconds), "failed": len(failed), "failures": failed,
               "median_seconds": sorted(seconds)[len(seconds) // 2] if seconds else None, "output": str(output)}
    log.info("estimated %d scene(s), %d failed; median %.3f s per scene; wrote %s", summary["done"],
             summary["failed"], summary["median_seconds"] or 0.0, output)
    return summary
