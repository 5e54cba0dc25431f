"""Scene files in, lights out: search/refinement, model selection, uncertainty, JSON Lines.

For each scene the candidate models are fitted (1 .. ``max_lights`` lights; with
and without the specular term when the file has a non-zero ``ks``) and the one
with the least penalised fit wins (:func:`bic`). Each light gets a position
standard deviation from the Gauss-Newton covariance of the chosen fit.

Shadow models (``shadows``, ``search_shadows``): the default is shading alone
(``none``) for both. Cast shadows from one depth map guess what lies behind
the visible surfaces; the Cauchy-robust fit of shading alone treats real
shadows as outliers and was as accurate or more on every set measured, at half
the time (README, "Estimating lights from scene files"). With ``shadows=epipolar|paper`` the
global search still runs on shading alone (``search_shadows``), whose landscape
is smooth, and every candidate it finds is refined and judged with the shadows:
a search with shadows stopped, on two-light scenes especially, in basins whose
shadowed loss was higher than that of the shadow-free answer refined with shadows.

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
from render.geometry import normal_noise, plane_normals, smooth_normals
from render.shadows import ShadowMethod
from selfsup.refine import (Fit, FitProblem, RefineOptions, evaluate, position_covariance, refine, robust_loss,
                            search)
from selfsup.scenes.io import Scene, SceneFileError, read_scene, render_inputs

__all__ = ["EstimateOptions", "Candidate", "bic", "saturated_pixels", "problem_of", "estimate_scene", "estimate_files",
           "scene_files"]

log = logging.getLogger(__name__)
METHODS = ("cnn+refine", "cnn", "refine")
SHADOW_METHODS = tuple(m.value for m in ShadowMethod)
NORMAL_SMOOTHING = ("auto", "always", "never")


@dataclass
class EstimateOptions:
    """Settings of ``mode=estimate`` (mirrors ``configs/estimate/default.yaml``).

    ``max_lights``: the most lights a scene may get; each must carry at least
    ``min_light_share`` of the rendered direct light. ``block_px``: residuals are
    spatially correlated, so the criterion counts one independent sample per
    ``block_px x block_px`` pixels. ``shadows``: the renderer's shadow method of
    the final refinement and the criterion; ``search_shadows``: that of the
    global search (``none``: shading alone, the smoother landscape).
    ``checkpoint``: the network of the ``cnn`` methods (None: the shipped one).
    ``normal_smoothing``: ``auto`` smooths the normals (edge-preserving,
    :func:`render.geometry.smooth_normals`) when their measured noise
    (:func:`render.geometry.normal_noise`) exceeds ``normal_noise_threshold``
    degrees, as normals of a consumer depth sensor do; ``always`` | ``never``.
    ``mask_saturated``: leave clipped pixels out (:func:`saturated_pixels`); the
    model cannot explain a highlight cut flat, and fitted it with a second light.
    """

    method: str = "cnn+refine"
    checkpoint: str | None = None  # None: the shipped network
    cnn_grid: tuple[int, int, int] = (7, 6, 7)  # cnn+refine: the grid searched beside the network's slots
    cnn_starts: int = 8
    max_lights: int = 2
    block_px: int = 8
    min_light_share: float = 0.1
    shadows: str = "none"
    search_shadows: str = "none"
    normal_smoothing: str = "auto"
    normal_noise_threshold: float = 0.5
    mask_saturated: bool = True
    refine: RefineOptions = field(default_factory=RefineOptions)

    def __post_init__(self):
        self.cnn_grid = tuple(self.cnn_grid)
        if len(self.cnn_grid) != 3 or min(self.cnn_grid) < 2 or self.cnn_starts < 1:
            raise ValueError(f"cnn_grid needs 3 sizes >= 2 and cnn_starts >= 1, got {self.cnn_grid}, {self.cnn_starts}")
        if self.method not in METHODS:
            raise ValueError(f"estimate.method must be one of {METHODS}, got {self.method!r}")
        if self.max_lights < 1:
            raise ValueError(f"max_lights must be >= 1, got {self.max_lights}")
        if self.normal_smoothing not in NORMAL_SMOOTHING:
            raise ValueError(f"estimate.normal_smoothing must be one of {NORMAL_SMOOTHING}, got {self.normal_smoothing!r}")
        if not self.normal_noise_threshold >= 0:
            raise ValueError(f"estimate.normal_noise_threshold must be >= 0 degrees, got {self.normal_noise_threshold}")
        for name in ("shadows", "search_shadows"):
            if getattr(self, name) not in SHADOW_METHODS:
                raise ValueError(f"estimate.{name} must be one of {SHADOW_METHODS}, got {getattr(self, name)!r}")


@dataclass
class Candidate:
    """One fitted model: its fit, light count, specular switch and criterion value."""

    fit: Fit
    n_lights: int
    specular: bool
    criterion: float


def saturated_pixels(image: Tensor, mask: Tensor, min_share: float = 0.002) -> Tensor:
    """Pixels ``(B, H, W)`` with a clipped channel.

    A channel is clipped when at least ``min_share`` of the valid pixels (and at
    least 3) hold exactly its largest value, as a sensor's or a tone mapper's
    clipping leaves them; an unclipped image has its maximum at one pixel.

    Args:
        image: ``(B, 3, H, W)``; mask: ``(B, H, W)`` valid pixels.
    """
    masked = torch.where(mask[:, None], image, torch.full_like(image, -torch.inf))
    peak = masked.flatten(2).amax(-1)[..., None, None]  # (B, 3, 1, 1)
    at_peak = (masked == peak) & mask[:, None]
    count = at_peak.flatten(2).sum(-1)  # (B, 3)
    clipped = (count >= 3) & (count >= min_share * mask.flatten(1).sum(-1, keepdim=True))
    return (at_peak & clipped[..., None, None]).any(1)


def problem_of(scene: Scene, shadows: str = "epipolar", dtype=torch.float32, normal_smoothing: str = "never",
               normal_noise_threshold: float = 0.5, mask_saturated: bool = False) -> FitProblem:
    """A batch-of-one :class:`FitProblem` from a scene file's contents; the normals
    smoothed as ``normal_smoothing`` says (see :class:`EstimateOptions`), clipped
    pixels (:func:`saturated_pixels`) left out when ``mask_saturated``."""
    gbuffer, material, _ = render_inputs(scene)
    if mask_saturated:
        clipped = saturated_pixels(scene.image.permute(2, 0, 1)[None], gbuffer.mask)
        if bool(clipped.any()):
            log.info("%s: %d clipped pixels left out", scene.id, int(clipped.sum()))
            gbuffer = replace(gbuffer, mask=gbuffer.mask & ~clipped)
    if not bool(gbuffer.mask.any()):
        raise SceneFileError(scene.id, "no valid pixel left after estimating normals and leaving out clipped pixels")
    if normal_smoothing == "always" or (
            normal_smoothing == "auto"
            and float(normal_noise(gbuffer.points, gbuffer.normals, gbuffer.mask)[0]) > normal_noise_threshold):
        normals, mask = gbuffer.normals, gbuffer.mask
        if scene.normals is None:
            # Differences of noisy neighbours are tens of degrees off: fit planes to 9x9 windows instead.
            normals, has_normal = plane_normals(gbuffer.points, gbuffer.mask, radius=4)
            mask = gbuffer.mask & has_normal
        gbuffer = replace(gbuffer, normals=smooth_normals(gbuffer.points, normals, mask), mask=mask)
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
def network_slots(problem: FitProblem, checkpoint: str | None = None) -> tuple[Tensor, Tensor]:
    """The network's light slots for a batch-of-one problem: positions ``(1, K, 3)`` and
    presence ``(K,)``, most present first."""
    network = _network(checkpoint)
    prediction = network(problem.image.float(), problem.gbuffer, problem.material.kd.float())
    order = prediction.presence[0].argsort(descending=True)
    return prediction.position[:, order].to(problem.image.dtype), prediction.presence[0, order]


def _candidate(problem: FitProblem, fit: Fit, n_lights: int, specular: bool, options: EstimateOptions) -> Candidate:
    # A fitted model and its criterion: robust loss, 6 parameters per light, the
    # unknown ambient (3) and the specular switch.
    loss = float(robust_loss(problem, fit.model, replace(options.refine, specular=specular))[0])
    k = 6 * n_lights + (3 if problem.ambient is None else 0) + int(specular)
    return Candidate(fit, n_lights, specular, bic(loss, int(problem.gbuffer.mask.sum()) * 3, k, options.block_px))


def estimate_scene(scene: Scene, options: EstimateOptions) -> dict:
    """Estimate the lights of one scene; returns the JSON-ready record (no ``seconds``).

    Models tried: one light (searched with the specular term if the file has ks),
    the same light refined without it, then more lights with the better of the two
    while each added light lowers :func:`bic` and carries at least
    ``min_light_share`` of the rendered direct light. Searches run with
    ``search_shadows``; each model found is refined with ``shadows`` before it is
    judged. With ``cnn+refine`` the network's slots join the grid's best
    candidates as starts of every search; ``cnn`` keeps the slots as they are (no
    refinement).
    """
    problem = problem_of(scene, options.shadows, normal_smoothing=options.normal_smoothing,
                         normal_noise_threshold=options.normal_noise_threshold, mask_saturated=options.mask_saturated)
    searched = problem if options.search_shadows == options.shadows else replace(problem, shadows=options.search_shadows)
    has_specular = scene.ks is not None and bool((scene.ks > 0).any())
    if options.method == "refine":
        starts = {}
    else:
        slots, presence = network_slots(problem, options.checkpoint)
        if options.method == "cnn":
            return _network_record(scene, problem, slots, presence, has_specular, options)
        starts = dict(extra_starts=slots, per_axis=options.cnn_grid, starts=options.cnn_starts)

    # Candidates are fitted on all pyramid levels but the finest; only the chosen one
    # descends to it (the finest level costs as much as all the others together).
    levels = len(options.refine.strides)
    coarse = replace(options.refine, strides=options.refine.strides[: max(levels - 1, 1)],
                     max_iters=options.refine.max_iters[: max(levels - 1, 1)])

    def polished(fit: Fit, n_lights: int, specular: bool) -> Candidate:
        # The search's answer refined and judged under the final shadow model.
        if searched is not problem:
            fit = refine(problem, fit.position, replace(coarse, specular=specular))
        return _candidate(problem, fit, n_lights, specular, options)

    first = search(searched, 1, replace(coarse, specular=has_specular), **starts)
    tried = [polished(first, 1, has_specular)]
    if has_specular:
        unspecular = refine(searched, first.position, replace(coarse, specular=False))
        tried.append(polished(unspecular, 1, False))
    best = min(tried, key=lambda c: c.criterion)
    for n_lights in range(2, options.max_lights + 1):
        opts = replace(coarse, specular=best.specular)
        more = polished(search(searched, n_lights, opts, fixed=best.fit.position, **starts), n_lights, best.specular)
        tried.append(more)
        share = float(light_shares(problem, more.fit, best.specular).min())
        if more.criterion >= best.criterion or share < options.min_light_share:
            break  # a light that does not pay for itself: more would not either
        best = more
    if levels > 1:
        finest = replace(options.refine, specular=best.specular, strides=options.refine.strides[-1:],
                         max_iters=options.refine.max_iters[-1:])
        best = _candidate(problem, refine(problem, best.fit.position, finest), best.n_lights, best.specular, options)
    return _record(scene, problem, best, tried, options)


def _network_record(scene: Scene, problem: FitProblem, slots: Tensor, presence: Tensor, has_specular: bool,
                    options: EstimateOptions) -> dict:
    # The network's present slots (at least one); refine with no iterations solves
    # their intensities and ambient and evaluates the fit.
    keep = max(1, min(int((presence > 0.5).sum()), options.max_lights))
    fit = refine(problem, slots[:, :keep], replace(options.refine, specular=has_specular, max_iters=(0,), strides=(1,)))
    chosen = _candidate(problem, fit, keep, has_specular, options)
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
