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

Reflectance (``estimate.reflectance``): a file whose kd is one constant over every
valid pixel says nothing of the albedo (the paper's protocol row "m = 0" gives
kd = ks = 0.5 over textured scenes). With ``auto`` (default) such files are fitted
by :mod:`selfsup.albedo_free` (the shading's log-differences between neighbours,
which no piecewise-constant albedo error moves) and every other file by the image
fit above; ``given`` | ``albedo_free`` force one of the two.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
from torch import Tensor

from render import Material, light_transport
from render.geometry import normal_noise, plane_fit, smooth_normals, surface_segments
from render.shadows import EpipolarShadowOptions, ShadowMethod
from selfsup import albedo_free
from selfsup.refine import (Fit, FitProblem, RefineOptions, evaluate, position_covariance, refine, reweighted,
                            robust_loss, search, solve_linear, subsample)
from selfsup.scenes.io import Scene, SceneFileError, read_scene, scene_gbuffer

__all__ = ["EstimateOptions", "Candidate", "bic", "saturated_pixels", "problem_of", "problems_of", "prepare", "estimate_scene",
           "estimate_batch", "records", "has_specular", "estimate_files", "scene_files", "segment_gains",
           "plane_window_px", "block_px", "effective_samples", "shadow_gain", "reflectance_unknown", "worker_count",
           "usable_cores", "judged_problem", "pixel_stride", "within_pixels"]

log = logging.getLogger(__name__)
METHODS = ("cnn+refine", "cnn", "refine")
SHADOW_METHODS = tuple(m.value for m in ShadowMethod)
NORMAL_SMOOTHING = ("auto", "always", "never")
REFLECTANCE = ("auto", "given", "albedo_free")
INDIRECT = ("auto", "never")
COAT = ("auto", "never", "always")


@dataclass
class EstimateOptions:
    """Settings of ``mode=estimate`` (mirrors ``configs/estimate/default.yaml``).

    ``max_lights``: the most lights a scene may get; each must carry at least
    ``min_light_share`` of the rendered direct light, or, weaker, show its own cast
    shadows: modelling them (:func:`shadow_gain`) must lower the robust loss by at
    least ``weak_light_shadow_gain`` (0: never), or pay for itself
    ``weak_light_penalty`` times: :func:`bic` must fall with its parameters counted
    that many times (0: never); and it must carry
    at least ``weak_light_min_share``: on a clean image that one light fits to
    float precision, the relative gain of a light with no intensity at all is
    rounding, and reached 4-6% on empty procedural rooms. ``block_width``:
    residuals are spatially correlated, so the criterion and the uncertainty count
    one independent sample per square block of ``block_width`` x the image width
    (:func:`block_px`; 16 pixels at 160x120): the model's errors follow the scene's
    structure, which a finer image samples with more pixels, not more independent
    ones. Smooth albedo errors (fractal noise, m = 0.3) bought a spurious second
    light in a fifth of the procedural scenes with 8-pixel blocks, in none with 16;
    16 alone missed more weak true second lights, most of which ``weak_light_penalty``
    keeps (README, "The criterion's block"). ``shadows``: the renderer's shadow
    method of the final refinement and the criterion; ``search_shadows``: that of
    the global search (``none``: shading alone, the smoother landscape).
    ``checkpoint``: the network of the ``cnn`` methods (None: the shipped one).
    ``normal_smoothing``: ``auto`` replaces the normals when their measured noise
    (:func:`render.geometry.normal_noise`) exceeds ``normal_noise_threshold``
    degrees, as normals of a consumer depth sensor do, by planes fitted to the
    depth (:func:`render.geometry.plane_normals`; :func:`plane_window_px`: a window
    of ``plane_window`` x the focal length, the same extent in metres at any image
    resolution) then smoothed edge-preserving (:func:`render.geometry.smooth_normals`);
    ``always`` | ``never``. A file's noisy normals are refitted rather than smoothed:
    they come from the same noisy depth, by a smaller window than the light fit needs.
    ``plane_shifts``: each refitted pixel may take the plane of a window beside its own,
    these fractions of the window's half-size away (``plane_fit``'s ``shifts``; empty:
    its own window alone), so that creases keep their sides: on the Mitsuba
    sensor-noise files the two-light successes went from 11 to 15 of 24 (README,
    "Normals of noisy depth beside creases").
    ``coat``: the specular pixels' diffuse light through a rough clear coat
    (``render.Material.coat``, :mod:`render.coat`: the coat's transmittance in and
    out, its roughness from the shininess, as rough plastic reflects it). ``auto``
    (default) fits the one-light model with the coat too and keeps it for the later
    models where it lowers the criterion, then refits a chosen model of two or more
    lights with the other setting and keeps the better (a missing light sways the
    one-light choice); ``never`` (the scene format's Blinn-Phong model alone);
    ``always`` (every file with ks). At the true lights, Mitsuba's rough plastic
    over our coated model is 0.98-1.00 (median per file) against 0.65-0.92 bare;
    on the Mitsuba direct files auto took the successes from 38 to 42 of 48, the
    procedural (Blinn-Phong) files kept theirs (README, "Glossy surfaces through a
    clear coat").
    ``mask_saturated``: leave clipped pixels out (:func:`saturated_pixels`); the
    model cannot explain a highlight cut flat, and fitted it with a second light.
    ``final_robust_scale``: the Cauchy scale (x median observed value, floored at
    ``refine.robust_noise_floor`` x the noise level) of the chosen model's last,
    full-resolution refinement; the search, the candidates' fits and the model
    selection use ``refine.robust_scale``. The narrow one places the lights best
    (cast shadows and interreflections the model lacks weigh little) but, as the
    criterion's scale, it leaves them unexplained at little cost and a second
    light that explains part of them pays for itself; as the search's, it costs
    more iterations.
    ``reflectance_gains``: rounds of re-estimation with the albedo of each smooth
    surface rescaled by what the last fit says it is (:func:`segment_gains`), for
    reflectance known only up to a factor per surface (0: trust the file's kd).
    ``reflectance``: ``auto`` fits a file whose kd is one constant (:func:`reflectance_unknown`)
    by :mod:`selfsup.albedo_free`, any other by the image; ``given`` | ``albedo_free``
    force one. ``albedo_free_scale``: that fit's Cauchy scale, a relative change of
    the shading between neighbouring pixels (at least the image's relative noise);
    ``albedo_free_block_width``: its ``block_width``. Its residuals are differences
    between neighbours, which remove what smooth errors share: with the image fit's
    16-pixel blocks a two-light scene of unknown albedo got one light.
    ``indirect``: ``auto`` judges the candidate models of a file that does not give
    its ambient (light unaccounted for) with each light's indirect light added
    (:mod:`selfsup.indirect`: the first bounce between the visible surfaces, times
    the later ones' geometric series), intensities and ambient solved again; the
    fits themselves stay direct-only. Without it a second light stood in for the
    interreflections of a quarter of the one-light path-traced Mitsuba scenes
    (README); ``never``: the direct model alone.
    ``albedo_error``: the standard deviation, in albedo units, of the error of the
    file's kd (0: exact); the position uncertainty then adds what such an error,
    the same over each of the criterion's blocks and independent between blocks and
    channels, moves the lights by (:func:`selfsup.refine.position_covariance`; README,
    "Uncertainty under reflectance errors"). The albedo-free fit uses no kd and
    ignores it.
    ``indirect_variation``, ``indirect_length``: where the file does not give its
    ambient (light unaccounted for), the position uncertainty adds what light that
    varies over the scene moves the lights by: the fitted ambient taken for the mean
    of ``ambient (1 + e(x))``, ``e`` a smooth Gaussian random field over the 3D points
    of that standard deviation and correlation length (of the scene size)
    (:func:`selfsup.refine.position_covariance`; README, "Uncertainty under indirect
    light"). The defaults are measured on path-traced renders, not fitted to the
    coverage (``python -m benchmarks.indirect_field``): on our open Mitsuba rooms the
    indirect light varies by 0.42 of its mean between 16-pixel blocks (median), its
    covariance halves at about 0.18 of the scene size (where a Gaussian kernel of
    length 0.15 halves), and the constant fit takes up
    0.61 of it as ambient (0.42 / 0.61, about 0.7). 0: off. Files that give their
    ambient are untouched.
    ``normal_error``: where the normals were fitted to noisy depth (``normal_smoothing``),
    the position uncertainty adds what their remaining error moves the lights by: each
    criterion block's normals tilted as one, by the plane fits' own tilt variance (from
    the scatter of the depth off each plane, :func:`render.geometry.plane_fit`)
    (:func:`selfsup.refine.position_covariance`; README, "Uncertainty under noisy
    depth"). Files whose normals were kept are untouched.
    ``criterion_shadows``: the shadow method under which every candidate model is
    judged, its light positions fixed and its intensities and ambient solved again
    (:func:`judged_problem`); two lights close together differ from one mostly by
    their double shadows, which shading alone cannot show. ``criterion_stride``:
    the criterion looks at every that-many-th pixel of each row and column (its
    blocks shrink alike: the same independent samples, a quarter of the shadow work
    at 2). Judged under ``epipolar`` at stride 2 rather than by the shading-only fit
    (README, "Judged with cast shadows"): two-light procedural scenes (seed 4242)
    got the right count in 41 of 48 against 39, the Mitsuba sets 199 successes of
    288 against 192, the devset the same answers; ``none`` at stride 1 judges the
    fit's own model.
    ``criterion_thickness``: with ``criterion_shadows=epipolar``, the solid behind
    each pixel ends this share of the scene size behind its surface
    (:class:`render.shadows.EpipolarShadowOptions` ``scene_thickness``) instead of
    reaching to infinity; None: unbounded. Rays passing behind an object's
    silhouette, or to a light hidden behind it, then get through: on 1,024
    two-light procedural scenes (seed 4242) the right count went from 88.3% to
    92.0% (README, "The criterion's shadows with a finite solid").
    ``max_pixels``: a file with more pixels is estimated on every ``k``-th pixel of
    its rows and columns, the least ``k`` that leaves at most this many
    (:func:`pixel_stride`; None: every pixel). The default, 320x240, leaves the
    devset's and the procedural sets' 160x120 alone; on 16 procedural files at
    640x480, every 2nd pixel gave the same light counts and answers within 0.0014
    of the scene size of those with every pixel (but for one scene both missed by
    0.29), in 0.54 s against 2.0 (clean, medians) and 0.78 against 3.3 (sensor
    noise) per file (README, "Large images").
    """

    method: str = "cnn+refine"
    checkpoint: str | None = None  # None: the shipped network
    cnn_grid: tuple[int, int, int] = (7, 6, 7)  # cnn+refine: the grid searched beside the network's slots
    cnn_starts: int = 4  # the grid's best started beside the network's slots (8 gave the same answers, slower)
    max_lights: int = 2
    block_width: float = 0.1
    min_light_share: float = 0.1
    weak_light_shadow_gain: float = 0.01
    weak_light_min_share: float = 0.01
    weak_light_penalty: float = 2.0
    shadows: str = "none"
    search_shadows: str = "none"
    normal_smoothing: str = "auto"
    normal_noise_threshold: float = 0.5
    plane_window: float = 0.06
    plane_shifts: tuple[float, ...] = (1.0, 0.5, 0.25)
    mask_saturated: bool = True
    final_robust_scale: float = 0.05
    reflectance_gains: int = 0
    reflectance: str = "auto"
    indirect: str = "auto"
    criterion_shadows: str = "epipolar"
    criterion_stride: int = 2
    criterion_thickness: float | None = 0.03
    albedo_free_scale: float = 0.02
    albedo_free_block_width: float = 0.05
    albedo_error: float = 0.0
    indirect_variation: float = 0.7
    indirect_length: float = 0.15
    normal_error: bool = True
    coat: str = "auto"
    max_pixels: int | None = 76800
    refine: RefineOptions = field(default_factory=RefineOptions)

    def __post_init__(self):
        self.cnn_grid = tuple(self.cnn_grid)
        if len(self.cnn_grid) != 3 or min(self.cnn_grid) < 2 or self.cnn_starts < 1:
            raise ValueError(f"cnn_grid needs 3 sizes >= 2 and cnn_starts >= 1, got {self.cnn_grid}, {self.cnn_starts}")
        if self.method not in METHODS:
            raise ValueError(f"estimate.method must be one of {METHODS}, got {self.method!r}")
        if self.max_lights < 1:
            raise ValueError(f"max_lights must be >= 1, got {self.max_lights}")
        if not self.weak_light_shadow_gain >= 0:
            raise ValueError(f"estimate.weak_light_shadow_gain must be >= 0, got {self.weak_light_shadow_gain}")
        if not (self.weak_light_penalty == 0 or self.weak_light_penalty >= 1):
            raise ValueError(f"estimate.weak_light_penalty must be 0 (off) or >= 1, got {self.weak_light_penalty}")
        if not self.weak_light_min_share >= 0:
            raise ValueError(f"estimate.weak_light_min_share must be >= 0, got {self.weak_light_min_share}")
        if not 0 <= self.min_light_share <= 1:
            raise ValueError(f"estimate.min_light_share must be a share in [0, 1], got {self.min_light_share}")
        for name in ("block_width", "albedo_free_block_width"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"estimate.{name} must be in (0, 1] (of the image width), got {getattr(self, name)}")
        if not self.final_robust_scale > 0:
            raise ValueError(f"estimate.final_robust_scale must be > 0, got {self.final_robust_scale}")
        if self.reflectance_gains < 0:
            raise ValueError(f"reflectance_gains must be >= 0 rounds, got {self.reflectance_gains}")
        if self.reflectance not in REFLECTANCE:
            raise ValueError(f"estimate.reflectance must be one of {REFLECTANCE}, got {self.reflectance!r}")
        if not (self.albedo_error >= 0 and math.isfinite(self.albedo_error)):
            raise ValueError(f"estimate.albedo_error must be a finite standard deviation >= 0 (albedo units), "
                             f"got {self.albedo_error}")
        if not (self.indirect_variation >= 0 and math.isfinite(self.indirect_variation)):
            raise ValueError(f"estimate.indirect_variation must be a finite standard deviation >= 0 (of the ambient), "
                             f"got {self.indirect_variation}")
        if not (self.indirect_length > 0 and math.isfinite(self.indirect_length)):
            raise ValueError(f"estimate.indirect_length must be a finite length > 0 (of the scene size), "
                             f"got {self.indirect_length}")
        if not self.albedo_free_scale > 0:
            raise ValueError(f"estimate.albedo_free_scale must be > 0, got {self.albedo_free_scale}")
        if self.normal_smoothing not in NORMAL_SMOOTHING:
            raise ValueError(f"estimate.normal_smoothing must be one of {NORMAL_SMOOTHING}, got {self.normal_smoothing!r}")
        if not self.normal_noise_threshold >= 0:
            raise ValueError(f"estimate.normal_noise_threshold must be >= 0 degrees, got {self.normal_noise_threshold}")
        if not 0 < self.plane_window < 1:
            raise ValueError(f"estimate.plane_window must be in (0, 1) (of the focal length), got {self.plane_window}")
        self.plane_shifts = tuple(self.plane_shifts)
        if not all(0 < f <= 1 for f in self.plane_shifts):
            raise ValueError(f"estimate.plane_shifts must be fractions in (0, 1] of the plane window, got "
                             f"{self.plane_shifts}")
        if self.coat not in COAT:
            raise ValueError(f"estimate.coat must be one of {COAT}, got {self.coat!r}")
        if self.indirect not in INDIRECT:
            raise ValueError(f"estimate.indirect must be one of {INDIRECT}, got {self.indirect!r}")
        if self.criterion_thickness is not None and not 0 < self.criterion_thickness < math.inf:
            raise ValueError(f"estimate.criterion_thickness must be null or a share of the scene size > 0, "
                             f"got {self.criterion_thickness}")
        if self.max_pixels is not None and not (isinstance(self.max_pixels, int) and self.max_pixels >= 1):
            raise ValueError(f"estimate.max_pixels must be null or an integer >= 1, got {self.max_pixels!r}")
        if self.criterion_stride < 1:
            raise ValueError(f"estimate.criterion_stride must be >= 1 pixel, got {self.criterion_stride}")
        for name in ("shadows", "search_shadows", "criterion_shadows"):
            if getattr(self, name) not in SHADOW_METHODS:
                raise ValueError(f"estimate.{name} must be one of {SHADOW_METHODS}, got {getattr(self, name)!r}")


@dataclass
class Candidate:
    """One fitted model: its fit, light count, specular switch and criterion value."""

    fit: Fit
    n_lights: int
    specular: bool
    criterion: float
    covariance: Tensor | None = None  # (L, 3, 3) when the fit found its own (the albedo-free one's)
    reflectance: str = "given"  # which data the fit explained: "given" (the image) | "albedo_free"
    samples: float | None = None  # the independent samples the criterion counted (effective_samples)
    coat: bool = False  # whether the specular pixels' diffuse light went through a clear coat (render.Material.coat)


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
    # A channel black everywhere is dark, not clipped.
    clipped = (count >= 3) & (count >= min_share * mask.flatten(1).sum(-1, keepdim=True)) & (peak[..., 0, 0] > 0)
    return (at_peak & clipped[..., None, None]).any(1)


def problem_of(scene: Scene, shadows: str = "epipolar", dtype=torch.float32, normal_smoothing: str = "never",
               normal_noise_threshold: float = 0.5, mask_saturated: bool = False, *,
               plane_window: float = EstimateOptions.plane_window,
               plane_shifts: tuple[float, ...] = EstimateOptions.plane_shifts) -> FitProblem:
    """A batch-of-one :class:`FitProblem` from a scene file's contents (see :func:`problems_of`)."""
    return problems_of([scene], shadows, dtype, normal_smoothing, normal_noise_threshold, mask_saturated,
                       plane_window=plane_window, plane_shifts=plane_shifts)


def _stacked_field(scenes: list[Scene], name: str, device=None) -> Tensor | None:
    # One field of every scene, stacked (B, ...) and moved to ``device`` in one copy; None
    # when no scene holds it.
    values = [getattr(scene, name) for scene in scenes]
    if all(v is None for v in values):
        return None
    if any(v is None for v in values) or len({tuple(v.shape) for v in values}) > 1:
        raise ValueError(f"scenes of one batch must all hold {name} with one shape")
    device = values[0].device if device is None else torch.device(device)
    if device.type != "cuda" or any(v.device.type != "cpu" for v in values) or len({v.dtype for v in values}) > 1:
        return torch.stack(values).to(device)
    # Host to CUDA through page-locked memory, as a DataLoader with pin_memory does:
    # stacked into a (cached) pinned block and copied without a staging pass. On an
    # H100 host, 1,024 scenes' fields took 0.11 s so against 0.54-0.71 s stacked in
    # pageable memory (measured 2026-11-23; the first batch pays the block's allocation).
    staged = torch.empty((len(values),) + tuple(values[0].shape), dtype=values[0].dtype, pin_memory=True)
    return torch.stack(values, out=staged).to(device, non_blocking=True)


def plane_window_px(focal_px: float, plane_window: float, image_px: int) -> tuple[int, int]:
    """``(radius, step)`` in pixels of the plane-fit window for noisy normals: half-size
    ``plane_window x focal_px``, at least 1 and at most an eighth of ``image_px`` (the
    image's shorter side: a telephoto lens, or a wrong focal length, must not make one
    window the whole image), sampled every ``radius / 4`` pixels, rounded (about 9x9
    samples whatever the size, so the cost per pixel stays put). A window of fixed
    extent in metres: at half the resolution the same pixels' noise is spread over
    twice the pixel spacing (devset noisy at 80x60: radius 4 kept 6/6, radius 8 lost a light)."""
    radius = max(1, min(round(plane_window * focal_px), image_px // 8))
    return radius, max(1, round(radius / 4))


def problems_of(scenes: list[Scene], shadows: str = "epipolar", dtype=torch.float32, normal_smoothing: str = "never",
                normal_noise_threshold: float = 0.5, mask_saturated: bool = False, device=None, *,
                plane_window: float = EstimateOptions.plane_window,
                plane_shifts: tuple[float, ...] = EstimateOptions.plane_shifts) -> FitProblem:
    """One :class:`FitProblem` of ``B`` same-sized scenes, on ``device`` (None: the
    scenes' own; the scenes are stacked first, so each field moves in one copy);
    the normals smoothed as ``normal_smoothing`` says (see :class:`EstimateOptions`, as
    ``plane_window`` and ``plane_shifts``),
    clipped pixels (:func:`saturated_pixels`) left out when ``mask_saturated``.

    The scenes must agree on which optional fields they hold and on the falloff
    (one file's scene always does). Raises :class:`SceneFileError` naming the
    first scene left with no valid pixel.
    """
    if not scenes:
        raise ValueError("no scenes to prepare")
    falloffs = {scene.falloff for scene in scenes}
    if len(falloffs) > 1:
        raise ValueError(f"scenes of one batch must share a falloff, got {sorted(falloffs)}")
    shininess = _stacked_field(scenes, "shininess", device)
    gbuffer = scene_gbuffer(_stacked_field(scenes, "depth", device), _stacked_field(scenes, "K", device),
                            _stacked_field(scenes, "normals", device), [scene.id for scene in scenes])
    material = Material(kd=_stacked_field(scenes, "kd", device), ks=_stacked_field(scenes, "ks", device),
                        shininess=shininess[0] if len(scenes) == 1 and shininess.dim() == 1 else shininess)
    image = _stacked_field(scenes, "image", device).permute(0, 3, 1, 2).to(dtype)
    dark = (~((image > 0) & gbuffer.mask[:, None]).flatten(1).any(1)).tolist()
    if any(dark):
        raise SceneFileError(scenes[dark.index(True)].id, "the image is zero on every valid pixel: no light to estimate")
    if mask_saturated:
        clipped = saturated_pixels(image, gbuffer.mask)
        if bool(clipped.any()):
            for scene, count in zip(scenes, clipped.flatten(1).sum(1).tolist()):
                if count:
                    log.info("%s: %d clipped pixels left out", scene.id, count)
            gbuffer = replace(gbuffer, mask=gbuffer.mask & ~clipped)
    empty = (~gbuffer.mask.flatten(1).any(1)).tolist()
    if any(empty):
        raise SceneFileError(scenes[empty.index(True)].id,
                             "no valid pixel left after estimating normals and leaving out clipped pixels")
    normal_tilt = None  # (B, H, W) where normals are refitted below
    if normal_smoothing != "never":
        noisy = torch.ones(len(scenes), dtype=torch.bool, device=image.device) if normal_smoothing == "always" else (
            normal_noise(gbuffer.points, gbuffer.normals, gbuffer.mask) > normal_noise_threshold)
        if bool(noisy.any()):
            at = noisy.nonzero(as_tuple=True)[0]
            # Normals of noisy depth, a file's own included (a sensor's normals come from its
            # depth, by a few pixels' differences or a small window), are tilted by the noise:
            # planes through a wide window average it away (README: at 160x120 a 17x17 window
            # sampled every 2 pixels beat 9x9 windows and the file's smoothed normals).
            shorter = min(gbuffer.mask.shape[1:])
            windows = [plane_window_px(fx, plane_window, shorter) for fx in gbuffer.intrinsics[at, 0, 0].tolist()]
            for radius, step in sorted(set(windows)):
                rows = at[torch.tensor([w == (radius, step) for w in windows], device=at.device)]
                points, mask = gbuffer.points[rows], gbuffer.mask[rows]
                planes = plane_fit(points, mask, radius=radius, step=step, shifts=plane_shifts)
                mask = mask & planes.has_normal
                smoothed = smooth_normals(points, planes.normals, mask)
                gbuffer = replace(gbuffer, normals=gbuffer.normals.index_put((rows,), smoothed),
                                  mask=gbuffer.mask.index_put((rows,), mask))
                if normal_tilt is None:
                    normal_tilt = torch.zeros_like(gbuffer.mask, dtype=image.dtype)
                # The smoothing's window is within the plane's: it averages errors that are nearly
                # one already, so the plane's tilt variance is kept as it is.
                normal_tilt = normal_tilt.index_put((rows,), planes.tilt_variance.to(image.dtype))
    return FitProblem(gbuffer, material, image, _stacked_field(scenes, "ambient", device), scenes[0].falloff, shadows,
                      normal_tilt=normal_tilt)


def prepare(scenes: list[Scene], options: EstimateOptions, device=None) -> FitProblem:
    """:func:`problems_of` with the input settings of ``options`` (shadows, normal
    smoothing, clipped pixels): the problem :func:`estimate_batch` expects."""
    return problems_of(scenes, options.shadows, normal_smoothing=options.normal_smoothing,
                       normal_noise_threshold=options.normal_noise_threshold,
                       mask_saturated=options.mask_saturated, device=device, plane_window=options.plane_window,
                       plane_shifts=options.plane_shifts)


def block_px(options: EstimateOptions, width: int, albedo_free: bool = False) -> int:
    """Side in pixels of the criterion's independent-sample block for an image ``width``
    pixels wide: ``options.block_width x width`` (``albedo_free_block_width`` for the
    albedo-free fit), rounded, at least 1 (a procedural sensor-noise scene rendered at
    320x240 got a spurious second light with 8-pixel blocks and the right one with 16,
    as at 160x120 with 8)."""
    share = options.albedo_free_block_width if albedo_free else options.block_width
    return max(1, round(share * width))


def bic(loss: float, n_values: int, n_params: int, block_px: int) -> float:
    """Bayesian information criterion on ``n_values / block_px^2`` independent samples.

    ``loss`` is the (robust) sum of squared residuals over ``n_values`` values.
    """
    n_eff = effective_samples(n_values, n_params, block_px)
    return n_eff * math.log(max(loss, 1e-30) / n_values) + n_params * math.log(n_eff)


def effective_samples(n_values: int, n_params: int, block_px: int) -> float:
    """The independent samples :func:`bic` counts: one per ``block_px^2`` values, at
    least ``n_params + 2``."""
    return max(n_values / block_px**2, n_params + 2.0)


def shadow_gain(problem: FitProblem, position: Tensor, light: Tensor, specular: bool, options: RefineOptions
                ) -> Tensor:
    """Relative robust-loss decrease ``(B,)`` when light ``light (B,)`` of ``position (B, L, 3)``
    casts its shadows (epipolar; every other light casts its own in both fits),
    intensities and ambient solved with converged reweighting each time.

    Evidence that a weak light is a light: its shadows are in the image. A light that
    stands in for what the model lacks (indirect light, albedo errors, sensor noise)
    predicts shadows that are not there, and the loss rises. On the devset and two
    procedural sets (2026-11-23) the weak stand-ins gave -0.001 to -0.73, true second
    lights of 5-7% of the light +0.03 and +0.09 (two others +0.002 and -0.004).
    """
    shadowed = light_transport(problem.gbuffer, problem.material, position, falloff=problem.falloff,
                               shadows="epipolar", specular=specular)
    bare = light_transport(problem.gbuffer, problem.material, position, falloff=problem.falloff, shadows="none",
                           specular=specular)
    pick = torch.nn.functional.one_hot(light, position.shape[1]).to(position.dtype)[..., None, None]  # (B, L, 1, 1)
    losses = []
    for diffuse, spec in ((pick * bare.diffuse + (1 - pick) * shadowed.diffuse,
                           None if shadowed.specular is None else pick * bare.specular + (1 - pick) * shadowed.specular),
                          (shadowed.diffuse, shadowed.specular)):
        _, _, model = solve_linear(problem, diffuse, spec, reweighted(problem, diffuse, spec, options))
        losses.append(robust_loss(problem, model, options))
    without, with_shadows = losses
    return (without - with_shadows) / without.clamp_min(1e-30)


def light_shares(problem: FitProblem, fit: Fit, specular: bool) -> Tensor:
    """Each light's share ``(B, L)`` of the direct light the fit renders (summed over pixels)."""
    t = light_transport(problem.gbuffer, problem.material, fit.position, falloff=problem.falloff,
                        shadows=problem.shadows,
                        shadow_options=problem.shadow_options, specular=specular)
    kd = problem.material.kd.permute(0, 3, 1, 2)[:, :, None]  # (B, 3, 1, H, W)
    per_light = kd * t.diffuse[:, None]
    if t.specular is not None:
        per_light = per_light + problem.material.ks.permute(0, 3, 1, 2)[:, :, None] * t.specular[:, None]
    energy = (per_light.sum((-1, -2)) * fit.intensity.transpose(1, 2)).sum(1)  # (B, L)
    return energy / energy.sum(-1, keepdim=True).clamp_min(1e-30)


@functools.lru_cache(maxsize=4)
def _network(checkpoint: str | None, device: str = "cpu"):
    from selfsup.checkpoint import load_network

    return load_network(checkpoint, map_location=device)[0].to(device)


@torch.no_grad()
def network_slots(problem: FitProblem, checkpoint: str | None = None) -> tuple[Tensor, Tensor]:
    """The network's light slots: positions ``(B, K, 3)`` and presence ``(B, K)``,
    each image's most present first."""
    network = _network(checkpoint, str(problem.image.device))
    prediction = network(problem.image.float(), problem.gbuffer, problem.material.kd.float())
    order = prediction.presence.argsort(dim=1, descending=True)
    position = prediction.position.gather(1, order[..., None].expand(-1, -1, 3))
    return position.to(problem.image.dtype), prediction.presence.gather(1, order)


def has_specular(problem: FitProblem) -> Tensor:
    """Whether each image's material has a specular term: ``(B,)`` bool."""
    ks = problem.material.ks
    if ks is None:
        return torch.zeros(problem.batch, dtype=torch.bool, device=problem.image.device)
    return (ks > 0).flatten(1).any(1)


def _with_coat(material: Material, on: list[bool]) -> Material:
    # material with a clear coat on the ks > 0 pixels of the images where ``on``, none elsewhere.
    if not any(on):
        return dataclasses.replace(material, coat=None)
    chosen = torch.tensor(on, dtype=material.kd.dtype, device=material.kd.device)
    coat = (material.ks.amax(-1, keepdim=True) > 0).to(material.kd.dtype) * chosen[:, None, None, None]
    return dataclasses.replace(material, coat=coat)


def _row(fit: Fit, i: int) -> Fit:
    return Fit(*(getattr(fit, f.name)[i : i + 1] for f in dataclasses.fields(Fit)))


def _stacked(fits: list[Fit]) -> Fit:
    return Fit(*(torch.cat([getattr(f, name.name) for f in fits]) for name in dataclasses.fields(Fit)))


def _candidates(problem: FitProblem, fit: Fit, n_lights: int, specular: list[bool], options: EstimateOptions
                ) -> list[Candidate]:
    # Each image's fitted model and its criterion: robust loss, 6 parameters per light,
    # the unknown ambient (3) and the specular switch, on the problem the criterion judges.
    judged = judged_problem(problem, options)
    if judged is problem:
        model = fit.model
    else:
        model = evaluate(judged, fit.position, replace(options.refine, specular=any(specular)))[3]
    loss = robust_loss(judged, model, options.refine).tolist()
    n_values = (judged.gbuffer.mask.flatten(1).sum(1) * 3).tolist()
    ambient = 3 if problem.ambient is None else 0
    block = block_px(options, judged.image.shape[-1])
    out = []
    for i, spec in enumerate(specular):
        n_params = 6 * n_lights + ambient + int(spec)
        out.append(Candidate(_row(fit, i), n_lights, spec, bic(loss[i], int(n_values[i]), n_params, block),
                             samples=effective_samples(int(n_values[i]), n_params, block)))
    return out


def judged_problem(problem: FitProblem, options: EstimateOptions) -> FitProblem:
    """The problem on which model selection judges a fit of ``problem``: every
    ``options.criterion_stride``-th pixel (:func:`selfsup.refine.subsample`), cast
    shadows by ``options.criterion_shadows``, and each light's indirect light where
    ``options.indirect`` says the file leaves light unaccounted for (no ambient
    given). ``problem`` itself where all three leave it as it is. Every pixel where the
    stride would leave an image none of its valid ones (a mask of scattered pixels)."""
    judged = subsample(problem, options.criterion_stride)
    if not bool(judged.gbuffer.mask.flatten(1).any(1).all()):
        judged = problem
    return _criterion_light(judged, options)


def _criterion_light(problem: FitProblem, options: EstimateOptions) -> FitProblem:
    # The problem's light transport as the criterion models it: its cast shadows and, where
    # the file leaves light unaccounted for, each light's indirect light.
    if options.criterion_thickness is not None and options.criterion_shadows == "epipolar":
        problem = problem.with_shadows("epipolar", EpipolarShadowOptions(scene_thickness=options.criterion_thickness))
    elif options.criterion_shadows != problem.shadows:
        problem = problem.with_shadows(options.criterion_shadows)
    if options.indirect == "auto" and problem.ambient is None and problem.gbuffer.intrinsics is not None:
        problem = problem.with_indirect()
    return problem


def _groups(best: list[Candidate]) -> dict[tuple[int, bool], list[int]]:
    # The images of each (light count, specular switch): one batched call each.
    groups: dict[tuple[int, bool], list[int]] = {}
    for i, candidate in enumerate(best):
        groups.setdefault((candidate.n_lights, candidate.specular), []).append(i)
    return groups


def segment_gains(image: Tensor, model: Tensor, segments: Tensor, min_pixels: int = 30, lit_share: float = 0.2,
                  limits: tuple[float, float] = (0.2, 5.0)) -> Tensor:
    """Per-surface albedo factors ``(B, H, W, 3)``: on each segment and channel, the
    median of ``image / model`` over its pixels lit to at least ``lit_share`` of the
    segment's brightest model value (shadows and dark sides say little), clamped to
    ``limits``; 1 on segments with fewer than ``min_pixels`` such pixels and outside.

    Args:
        image, model: ``(B, 3, H, W)``; segments: ``(B, H, W)`` labels (-1: none),
        e.g. :func:`render.geometry.surface_segments`.
    """
    B, C, H, W = image.shape
    label = segments.reshape(B, 1, H * W).expand(B, C, H * W)
    inside = label >= 0
    # One group per (image, segment, channel): segment labels are flat pixel indices.
    group = ((torch.arange(B, device=image.device)[:, None, None] * (H * W) + label.clamp_min(0)) * C
             + torch.arange(C, device=image.device)[None, :, None]).reshape(-1)
    model = model.reshape(B, C, H * W)
    groups = B * H * W * C
    # Outside pixels share group 0's index (label clamped): their model values must not count there.
    brightest = model.new_zeros(groups).scatter_reduce_(0, group, (model * inside).reshape(-1), "amax")
    ratio = (image.reshape(B, C, H * W) / model.clamp_min(1e-12)).reshape(-1)
    use = (inside & (model > lit_share * brightest[group].view_as(model))).reshape(-1) & torch.isfinite(ratio)
    values, owner = ratio[use], group[use]
    if not values.numel():
        return torch.ones_like(image).permute(0, 2, 3, 1)
    # Each group's median: sort by value, then stably by group, and take each run's middle.
    by_value = values.argsort()
    ordered = values[by_value][owner[by_value].argsort(stable=True)]
    counts = torch.bincount(owner, minlength=groups)
    middle = (counts.cumsum(0) - counts + (counts - 1).clamp_min(0) // 2).clamp_max(values.numel() - 1)
    factor = torch.where(counts >= min_pixels, ordered[middle].clamp(*limits), torch.ones_like(ordered[middle]))
    factor = torch.where(inside.reshape(-1), factor[group], torch.ones_like(ratio))
    return factor.view(B, C, H, W).permute(0, 2, 3, 1)


def reflectance_unknown(problem: FitProblem, rel_tol: float = 1e-6) -> Tensor:
    """``(B,)``: the image's kd is one constant on its valid pixels (every channel within
    ``rel_tol`` of its maximum), so it says nothing of the surfaces' albedo."""
    kd = problem.material.kd
    mask = problem.gbuffer.mask[..., None].expand_as(kd)
    hi = torch.where(mask, kd, torch.full_like(kd, -math.inf)).flatten(1, 2).amax(1)  # (B, 3)
    lo = torch.where(mask, kd, torch.full_like(kd, math.inf)).flatten(1, 2).amin(1)
    return ((hi - lo) <= rel_tol * hi.abs().clamp_min(1e-30)).all(1)


def _albedo_free_images(problem: FitProblem, options: EstimateOptions) -> list[bool]:
    if options.method == "cnn" or options.reflectance == "given":
        return [False] * problem.batch
    if options.reflectance == "albedo_free":
        return [True] * problem.batch
    return reflectance_unknown(problem).tolist()


def _estimate_albedo_free(problem: FitProblem, options: EstimateOptions) -> list[tuple[Candidate, list[Candidate]]]:
    """Lights fitted to the log shading's neighbour differences (:mod:`selfsup.albedo_free`),
    1 .. ``max_lights`` while :func:`bic` of their Cauchy loss falls and each light
    carries ``min_light_share`` of the fitted shading; intensities and ambient then
    solved against the image with the file's kd (diffuse only: a constant ks says
    nothing of the highlights either)."""
    B, device = problem.batch, problem.image.device
    block = block_px(options, problem.image.shape[-1], albedo_free=True)
    found = albedo_free.search(problem, 1, robust_scale=options.albedo_free_scale)
    pairs = found.pairs.tolist()
    if min(pairs) < 100:
        raise ValueError(f"kd is one constant, so the lights are fitted albedo-free, but image {pairs.index(min(pairs))} "
                         f"has {min(pairs)} pairs of neighbouring pixels with kd > 0 and light (at least 100 needed)")

    def criterion(fit: albedo_free.AlbedoFreeFit) -> list[float]:
        n_params = 4 * fit.position.shape[1]  # position, and a contrast per light (the ambient's for the first)
        return [bic(loss, int(pairs), n_params, block) for loss, pairs in zip(fit.loss.tolist(), fit.pairs.tolist())]

    best = [(found, i, c) for i, c in enumerate(criterion(found))]  # (fit, row, criterion) per image
    tried = [[(1, c)] for _, _, c in best]
    growing = list(range(B))
    for n_lights in range(2, options.max_lights + 1):
        if not growing:
            break
        at = torch.tensor(growing, dtype=torch.long, device=device)
        before = albedo_free.AlbedoFreeFit.rows([best[i][:2] for i in growing])
        sub = problem.select(at)
        more = albedo_free.search(sub, n_lights, fixed=before, robust_scale=options.albedo_free_scale)
        shares = albedo_free.light_shares(sub, more).amin(1).tolist()
        still = []
        for j, (i, c, share) in enumerate(zip(growing, criterion(more), shares)):
            tried[i].append((n_lights, c))
            if c < best[i][2] and share >= options.min_light_share:
                best[i] = (more, j, c)
                still.append(i)
        growing = still
    results: list = [None] * B
    # No iterations: the intensities and ambient solved and the fit evaluated at the positions.
    solve = replace(options.refine, specular=False, max_iters=(0,), strides=(1,))
    counts = [best[i][0].position.shape[1] for i in range(B)]
    for n_lights in sorted(set(counts)):  # one batched solve and covariance per light count
        group = [i for i in range(B) if counts[i] == n_lights]
        chosen = albedo_free.AlbedoFreeFit.rows([best[i][:2] for i in group])
        sub = problem.select(torch.tensor(group, dtype=torch.long, device=device))
        fit = refine(sub, chosen.position, solve)
        cov = albedo_free.position_covariance(albedo_free.observe(sub, options.albedo_free_scale), chosen,
                                              correlation_px=float(block**2)).cpu()
        for j, i in enumerate(group):
            candidate = Candidate(_row(fit, j), n_lights, False, best[i][2], cov[j], "albedo_free")
            # The records keep the tried models' counts and criteria only.
            others = [Candidate(candidate.fit, n, False, value, None, "albedo_free") for n, value in tried[i]]
            results[i] = (candidate, others)
    return results


def estimate_batch(problem: FitProblem, options: EstimateOptions) -> list[tuple[Candidate, list[Candidate]]]:
    """Estimate the lights of a batch of same-sized images; each image's chosen model
    and every model tried (see :func:`estimate_scene`).

    Every step runs on the whole batch (the searches over ``B x candidates``
    images), so a GPU is filled; each image is judged on its own and gets the
    answer it would get alone.

    With ``options.reflectance_gains`` rounds, each round rescales the albedo of every
    smooth surface (:func:`render.geometry.surface_segments`) by :func:`segment_gains`
    of the last round's chosen fit and estimates again; ``problem.material`` is then
    replaced by the last albedo, which the records' covariances need.

    Images whose reflectance is fitted albedo-free (``options.reflectance``,
    :func:`reflectance_unknown`) go to :func:`_estimate_albedo_free` instead.
    """
    free = _albedo_free_images(problem, options)
    if any(free):
        results: list = [None] * problem.batch
        for flag, run in ((True, _estimate_albedo_free), (False, _estimate_given)):
            rows = [i for i, f in enumerate(free) if f == flag]
            if not rows:
                continue
            at = torch.tensor(rows, dtype=torch.long, device=problem.image.device)
            sub = problem.select(at)
            for i, result in zip(rows, run(sub, options)):
                results[i] = result
            if not flag and options.reflectance_gains:  # the records' covariances need the rescaled albedo
                problem.material = dataclasses.replace(problem.material,
                                                       kd=problem.material.kd.index_put((at,), sub.material.kd))
        return results
    return _estimate_given(problem, options)


def _estimate_given(problem: FitProblem, options: EstimateOptions) -> list[tuple[Candidate, list[Candidate]]]:
    # The image fit with the file's reflectance (and its reflectance_gains rounds).
    results = _estimate_once(problem, options)
    if options.reflectance_gains:
        g = problem.gbuffer
        segments = surface_segments(g.points, g.normals, g.mask)
        for _ in range(options.reflectance_gains):
            model = torch.cat([best.fit.model for best, _ in results])
            kd = problem.material.kd * segment_gains(problem.image, model, segments)
            problem.material = dataclasses.replace(problem.material, kd=kd)
            results = _estimate_once(problem, options)
    return results


def _estimate_once(problem: FitProblem, options: EstimateOptions) -> list[tuple[Candidate, list[Candidate]]]:
    B, device = problem.batch, problem.image.device
    if options.refine.robust:
        problem.median_observed()  # the robust scale, found once: every selection below keeps its rows
        problem.noise_level()  # and the scale's floor, likewise
        judged_problem(problem, options)  # and the criterion's subsample's, likewise
    specular_of = has_specular(problem).tolist()
    coat_of = [options.coat == "always" and spec for spec in specular_of]  # auto adds the images the coat wins
    if any(coat_of) or problem.material.coat is not None:
        # Exactly these coats: a pass of reflectance_gains starts bare of the coats the last one chose.
        problem.material = _with_coat(problem.material, coat_of)

    def searched_problem() -> FitProblem:
        return problem if options.search_shadows == options.shadows else problem.with_shadows(options.search_shadows)

    searched = searched_problem()
    if options.method == "refine":
        slots = None
    else:
        slots, presence = network_slots(problem, options.checkpoint)
        if options.method == "cnn":
            return [(replace(best, coat=coat_of[i]), [replace(c, coat=coat_of[i]) for c in tried])
                    for i, (best, tried) in enumerate(_network_candidates(problem, slots, presence, specular_of, options))]

    def index(images: list[int]) -> Tensor:
        return torch.tensor(images, dtype=torch.long, device=device)

    def starts(images: list[int]) -> dict:
        if slots is None:
            return {}
        return dict(extra_starts=slots[index(images)], per_axis=options.cnn_grid, starts=options.cnn_starts)

    # Candidates are fitted on all pyramid levels but the finest; only the chosen one
    # descends to it (the finest level costs as much as all the others together).
    levels = len(options.refine.strides)
    coarse = replace(options.refine, strides=options.refine.strides[: max(levels - 1, 1)],
                     max_iters=options.refine.max_iters[: max(levels - 1, 1)])

    def polished(images: list[int], fit: Fit, n_lights: int, specular: bool, labels: list[bool]):
        # The search's answer refined and judged under the final shadow model; ``specular``
        # is the term computed, ``labels`` each image's switch (equal where ks > 0).
        sub = problem.select(index(images))
        if searched is not problem:
            fit = refine(sub, fit.position, replace(coarse, specular=specular))
        return _candidates(sub, fit, n_lights, labels, options), sub, fit

    everyone = list(range(B))
    # Where ks is zero the specular term adds nothing: one search serves the whole batch.
    any_specular = any(specular_of)
    first = search(searched, 1, replace(coarse, specular=any_specular), **starts(everyone))
    tried = [[c] for c in polished(everyone, first, 1, any_specular, specular_of)[0]]
    shiny = [i for i in everyone if specular_of[i]]
    if shiny:
        at = index(shiny)
        unspecular = refine(searched.select(at), first.position[at], replace(coarse, specular=False))
        for i, c in zip(shiny, polished(shiny, unspecular, 1, False, [False] * len(shiny))[0]):
            tried[i].append(c)
    best = [min(t, key=lambda c: c.criterion) for t in tried]
    if options.coat == "always":
        best = [replace(c, coat=coat_of[i]) for i, c in enumerate(best)]
        tried = [[replace(c, coat=coat_of[i]) for c in t] for i, t in enumerate(tried)]
    elif options.coat == "auto" and shiny:
        # The one-light model again with a coat on the specular pixels, from the bare fit's
        # light; every later model of the images where it wins keeps the coat.
        trial = problem.with_material(_with_coat(problem.material, [i in shiny for i in everyone]))
        for specular in (False, True):
            group = [i for i in shiny if best[i].specular == specular]
            if not group:
                continue
            sub = trial.select(index(group))
            fit = refine(sub, torch.cat([best[i].fit.position for i in group]), replace(coarse, specular=specular))
            for i, c in zip(group, _candidates(sub, fit, 1, [specular] * len(group), options)):
                c = replace(c, coat=True)
                tried[i].append(c)
                if c.criterion < best[i].criterion:
                    best[i] = c
                    coat_of[i] = True
        if any(coat_of):
            problem.material = _with_coat(problem.material, coat_of)
            searched = searched_problem()
    growing = everyone
    for n_lights in range(2, options.max_lights + 1):
        still = []
        for specular in (False, True):
            group = [i for i in growing if best[i].specular == specular]
            if not group:
                continue
            fixed = torch.cat([best[i].fit.position for i in group])
            more = search(searched.select(index(group)), n_lights, replace(coarse, specular=specular), fixed=fixed,
                          **starts(group))
            found, sub, fit = polished(group, more, n_lights, specular, [specular] * len(group))
            per_light = light_shares(sub, fit, specular)
            shares = per_light.amin(-1).tolist()
            pays = [c.criterion < best[i].criterion for i, c in zip(group, found)]
            weak = [j for j, (p, share) in enumerate(zip(pays, shares))
                    if p and options.weak_light_min_share <= share < options.min_light_share]
            gains = {}
            if weak and options.weak_light_shadow_gain > 0:
                at = index(weak)
                gains = dict(zip(weak, shadow_gain(sub.select(at), fit.position[at], per_light[at].argmin(-1),
                                                   specular, options.refine).tolist()))
            for j, (i, c, share) in enumerate(zip(group, found, shares)):
                c = replace(c, coat=coat_of[i])
                tried[i].append(c)
                # A light that does not pay for itself: more would not either. A weak one
                # needs more evidence: its own cast shadows in the image, or paying for its
                # parameters weak_light_penalty times.
                shown = gains.get(j, -math.inf) >= options.weak_light_shadow_gain
                extra = (options.weak_light_penalty - 1) * 6 * math.log(c.samples)  # 6: its position and intensity
                strong = (options.weak_light_penalty > 0 and share >= options.weak_light_min_share
                          and c.criterion + extra < best[i].criterion)
                if pays[j] and (share >= options.min_light_share or shown or strong):
                    best[i] = c
                    still.append(i)
        growing = sorted(still)
    # A chosen model of several lights is refitted without each of its lights in turn, from
    # the others' positions: the fit of fewer lights can stop where the criterion (which
    # sees cast shadows) judges it poorly, and a light then pays for itself against that
    # stop alone. The criterion alone decides: fewer lights need no extra evidence.
    for (n_lights, specular), group in _groups(best).items():
        if n_lights < 2:
            continue
        positions = torch.cat([best[i].fit.position for i in group])  # (G, n, 3)
        rest = torch.cat([torch.cat([positions[:, :k], positions[:, k + 1:]], 1) for k in range(n_lights)])
        images = group * n_lights  # light k dropped from every image of the group, then k + 1
        sub = problem.select(index(images))
        fit = refine(sub, rest, replace(coarse, specular=specular))
        for i, c in zip(images, _candidates(sub, fit, n_lights - 1, [specular] * len(images), options)):
            c = replace(c, coat=coat_of[i])
            tried[i].append(c)
            if c.criterion < best[i].criterion:
                best[i] = c
    if options.coat == "auto" and shiny:
        # A two-light scene's one-light fit chooses the coat unreliably (the missing light
        # weighs more than the coat): its chosen model is refitted with the other setting
        # from its own lights, and the better of the two kept.
        flipped = [i for i in shiny if best[i].n_lights > 1]
        trial = problem.with_material(_with_coat(problem.material, [i in flipped and not coat_of[i] for i in everyone]))
        for (n_lights, specular), group in _groups([best[i] for i in flipped]).items():
            images = [flipped[j] for j in group]
            sub = trial.select(index(images))
            fit = refine(sub, torch.cat([best[i].fit.position for i in images]), replace(coarse, specular=specular))
            for i, c in zip(images, _candidates(sub, fit, n_lights, [specular] * len(images), options)):
                c = replace(c, coat=not coat_of[i])
                tried[i].append(c)
                if c.criterion < best[i].criterion:
                    best[i] = c
                    coat_of[i] = c.coat
        problem.material = _with_coat(problem.material, coat_of)
    if levels > 1 or options.final_robust_scale != options.refine.robust_scale:
        for (n_lights, specular), group in _groups(best).items():
            finest = replace(options.refine, specular=specular, strides=options.refine.strides[-1:],
                             max_iters=options.refine.max_iters[-1:], robust_scale=options.final_robust_scale)
            sub = problem.select(index(group))
            fit = refine(sub, torch.cat([best[i].fit.position for i in group]), finest)
            for j, i in enumerate(group):  # its criterion stays the one it was chosen by
                best[i] = replace(best[i], fit=_row(fit, j))
    return [(best[i], tried[i]) for i in everyone]


def pixel_stride(height: int, width: int, max_pixels: int | None) -> int:
    """The least stride ``k`` whose every-``k``-th-pixel subsample of a ``height x width``
    image, ``ceil(H / k) x ceil(W / k)`` pixels, has at most ``max_pixels`` (1 when
    ``max_pixels`` is None)."""
    stride = 1
    while max_pixels is not None and -(-height // stride) * -(-width // stride) > max_pixels:
        stride += 1
    return stride


def within_pixels(scene: Scene, options: EstimateOptions) -> Scene:
    """``scene``, subsampled to ``options.max_pixels`` (:func:`pixel_stride`) if it is larger."""
    H, W = scene.image.shape[:2]
    stride = pixel_stride(H, W, options.max_pixels)
    if stride > 1:
        log.info("%s: %dx%d estimated on every %d%s pixel (estimate.max_pixels=%d)", scene.id, W, H, stride,
                 {2: "nd", 3: "rd"}.get(stride, "th"), options.max_pixels)
    return scene.subsampled(stride)


# The image values the estimator works at. It fits in float32, where squares and its few
# absolute floors (the robust scale's, the criterion's) lose a file given in units far from
# these: devset direct 021 times 1e-8 got its light 0.0068 of the scene off (0.0005 as
# given) and its intensity 8% low; times 1e18 it failed in an eigendecomposition.
WORKING_RANGE = (1e-3, 1e3)


def working_range(scene: Scene) -> tuple[Scene, float]:
    """``scene`` with its image (and given ambient) multiplied by the power of ten that
    brings the median positive image value of its valid pixels into :data:`WORKING_RANGE`,
    and that factor (1: the scene as it is, as for every file of the devset and of our
    generator). The fit's intensities and ambient come out multiplied by the factor too (the
    model is linear in them): :func:`_unscaled` undoes it in the record."""
    values = scene.image[scene.depth_valid]
    values = values[values > 0]
    if values.numel() == 0:
        return scene, 1.0  # a black image: problems_of names it
    median = float(values.median())
    if WORKING_RANGE[0] <= median <= WORKING_RANGE[1]:
        return scene, 1.0
    factor = 10.0 ** -round(math.log10(median))
    log.info("%s: image values around %.3g, estimated at %g times them (intensities and ambient reported in the "
             "file's units)", scene.id, median, factor)
    ambient = None if scene.ambient is None else scene.ambient * factor
    return replace(scene, image=scene.image * factor, ambient=ambient), factor


def _unscaled(record: dict, factor: float) -> dict:
    # A record of a scene that working_range multiplied by ``factor``, in the file's units.
    if factor != 1.0:
        for light in record["lights"]:
            light["intensity"] = [value / factor for value in light["intensity"]]
        record["ambient"] = [value / factor for value in record["ambient"]]
    return record


def estimate_scene(scene: Scene, options: EstimateOptions) -> dict:
    """Estimate the lights of one scene; returns the JSON-ready record (no ``seconds``).

    Models tried: one light (searched with the specular term if the file has ks),
    the same light refined without it, then more lights with the better of the two
    while each added light lowers :func:`bic` and carries at least
    ``min_light_share`` of the rendered direct light. Searches run with
    ``search_shadows``; each model found is refined with ``shadows`` before it is
    judged. With ``cnn+refine`` the network's slots join the grid's best
    candidates as starts of every search; ``cnn`` keeps the slots as they are (no
    refinement). :func:`estimate_batch` does the work; batches of scenes go there.
    """
    scene, factor = working_range(within_pixels(scene, options))
    problem = prepare([scene], options)
    return _unscaled(records([scene.id], problem, estimate_batch(problem, options), options)[0], factor)


def _network_candidates(problem: FitProblem, slots: Tensor, presence: Tensor, specular_of: list[bool],
                        options: EstimateOptions) -> list[tuple[Candidate, list[Candidate]]]:
    # The network's present slots (at least one); refine with no iterations solves
    # their intensities and ambient and evaluates the fit.
    keep = (presence > 0.5).sum(1).clamp(1, options.max_lights).tolist()
    chosen: list[Candidate | None] = [None] * problem.batch
    for n_lights in sorted(set(keep)):
        group = [i for i, k in enumerate(keep) if k == n_lights]
        at = torch.tensor(group, dtype=torch.long, device=slots.device)
        labels = [specular_of[i] for i in group]
        sub = problem.select(at)
        fit = refine(sub, slots[at, :n_lights], replace(options.refine, specular=any(labels), max_iters=(0,), strides=(1,)))
        for i, c in zip(group, _candidates(sub, fit, n_lights, labels, options)):
            chosen[i] = c
    return [(c, [c]) for c in chosen]


def records(ids: list[str], problem: FitProblem, results: list[tuple[Candidate, list[Candidate]]],
            options: EstimateOptions) -> list[dict]:
    """The JSON-ready records (no ``seconds``) of :func:`estimate_batch`'s results, with
    each light's position covariance (one batched call per light count and switch).

    Where the file leaves light unaccounted for (no ambient) and ``options.indirect``
    is ``auto``, the reported intensities and ambient are solved again at the chosen
    positions with the light the criterion models (each light's indirect light and
    its cast shadows, :func:`judged_problem`, at every pixel): the fit's own, without
    them, take indirect light for light of the lamps. On the path-traced files the
    median worst intensity error fell, devset gi 0.114 -> 0.102, Mitsuba rooms 0.158
    -> 0.107 and 0.538 -> 0.439 (README, "Intensities under indirect light"); the
    positions and covariances stay the fit's."""
    covariances: list[Tensor | None] = [best.covariance for best, _ in results]
    lit: list[tuple[Tensor, Tensor] | None] = [None] * len(results)
    resolve = options.indirect == "auto" and problem.ambient is None and problem.gbuffer.intrinsics is not None
    own = [i for i, c in enumerate(covariances) if c is None]
    for (n_lights, specular), indices in _groups([results[i][0] for i in own]).items():
        group = [own[j] for j in indices]
        at = torch.tensor(group, dtype=torch.long, device=problem.image.device)
        fit = _stacked([results[i][0].fit for i in group])
        block = block_px(options, problem.image.shape[-1])
        cov = position_covariance(problem.select(at), fit, replace(options.refine, specular=specular),
                                  correlation_px=float(block**2), albedo_error=options.albedo_error,
                                  albedo_block_px=block, indirect_variation=options.indirect_variation,
                                  indirect_length=options.indirect_length, normal_error=options.normal_error).cpu()
        if resolve:
            final = replace(options.refine, specular=specular, robust_scale=options.final_robust_scale)
            _, intensity, ambient, *_ = evaluate(_criterion_light(problem.select(at), options), fit.position, final)
        for j, i in enumerate(group):
            covariances[i] = cov[j]
            if resolve:
                lit[i] = intensity[j : j + 1], ambient[j : j + 1]
    return [_record(scene_id, best, tried, cov, solved)
            for scene_id, (best, tried), cov, solved in zip(ids, results, covariances, lit)]


def _record(scene_id: str, best: Candidate, tried: list[Candidate], cov: Tensor,
            solved: tuple[Tensor, Tensor] | None = None) -> dict:
    # cov: (L, 3, 3) position covariance of the chosen model's lights; solved: the
    # intensities (1, L, 3) and ambient (1, 3) to report instead of the fit's.
    std = cov.diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt()
    fit = best.fit if solved is None else replace(best.fit, intensity=solved[0], ambient=solved[1])
    # Brightest light first (summed RGB intensity): the same scene gives the same record
    # whichever start each light was found from.
    order = fit.intensity[0].sum(-1).cpu().argsort(descending=True, stable=True).tolist()
    lights = [
        {"position": fit.position[0, i].tolist(), "intensity": fit.intensity[0, i].tolist(),
         "position_std": std[i].tolist(), "position_cov": cov[i].tolist()}
        for i in order
    ]
    return {
        "id": scene_id, "lights": lights, "ambient": fit.ambient[0].tolist(),
        "specular": best.specular, "coat": best.coat, "reflectance": best.reflectance,
        "candidates": [{"n_lights": c.n_lights, "specular": c.specular, "coat": c.coat, "criterion": round(c.criterion, 3)}
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


def _signature(scene: Scene) -> tuple:
    # Scenes that can share a batch: one image size, the same optional fields, one falloff.
    return (tuple(scene.image.shape), scene.ks is None, scene.normals is None, scene.ambient is None,
            tuple(scene.shininess.shape), scene.falloff)


def _estimate_group(group: list[tuple[Path, Scene]], options: EstimateOptions, device: torch.device
                    ) -> tuple[dict[Path, dict], dict[Path, str]]:
    # Records (with ``seconds``: the scene's share of the batch's time) and failure reasons
    # of scenes that can share a batch. A batch that fails is retried scene by scene, so
    # one bad scene never costs the others.
    started = time.perf_counter()
    try:
        with torch.no_grad():
            scaled = [working_range(scene) for _, scene in group]
            problem = prepare([scene for scene, _ in scaled], options, device)
            out = [_unscaled(record, factor) for record, (_, factor) in
                   zip(records([scene.id for scene, _ in scaled], problem, estimate_batch(problem, options), options),
                       scaled)]
    except (SceneFileError, ValueError, RuntimeError) as error:
        if len(group) > 1:
            done: dict[Path, dict] = {}
            failed: dict[Path, str] = {}
            for item in group:
                one_done, one_failed = _estimate_group([item], options, device)
                done.update(one_done)
                failed.update(one_failed)
            return done, failed
        reason = error.reason if isinstance(error, SceneFileError) else f"{type(error).__name__}: {error}"
        return {}, {group[0][0]: reason}
    seconds = round((time.perf_counter() - started) / len(group), 4)
    return {path: {**record, "seconds": seconds} for (path, _), record in zip(group, out)}, {}


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise RuntimeError(f"estimate.device={name} but no CUDA device is available")
    return torch.device(name)


# A spawned worker takes 3-4 s to start (imports, the network): on 18 devset files two
# spawned workers were slower than one process (6.5 against 5.2 s, 2-core CPU); from
# about 30 files a core they win. A forked one starts at once (start_method).
FILES_PER_SPAWNED_WORKER = 32


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity where the OS says)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def worker_count(workers: int | str, files: int, device: torch.device) -> int:
    """Processes ``estimate_files`` spreads ``files`` over: ``workers`` as given (at least
    1), or for ``"auto"``: on the CPU one per usable core, but no more than ``files``
    where one-thread workers are forked (:func:`start_method`; they start at once) and
    one per :data:`FILES_PER_SPAWNED_WORKER` files where they are spawned (a start of
    3-4 s of imports and the network must pay for itself); 1 on an accelerator (one
    process fills it)."""
    if workers == "auto":
        if device.type != "cpu":
            return 1
        per_worker = 1 if start_method(1, device) == "fork" else FILES_PER_SPAWNED_WORKER
        return max(1, min(usable_cores(), files // per_worker))
    if not isinstance(workers, int) or isinstance(workers, bool) or workers < 1:
        raise ValueError(f"estimate.workers must be 'auto' or an integer >= 1, got {workers!r}")
    return workers


def _estimate_chunk(chunk: list[Path], options: EstimateOptions, device: torch.device
                    ) -> tuple[dict[Path, dict], dict[Path, str]]:
    # Records and failure reasons of consecutive files: read, grouped by what can share a
    # batch, estimated group by group. Runs in this process or in a worker.
    groups: dict[tuple, list[tuple[Path, Scene]]] = {}
    done: dict[Path, dict] = {}
    reasons: dict[Path, str] = {}
    for path in chunk:
        try:
            scene = within_pixels(read_scene(path), options)
        except (SceneFileError, ValueError, RuntimeError) as error:
            reasons[path] = error.reason if isinstance(error, SceneFileError) else f"{type(error).__name__}: {error}"
            continue
        groups.setdefault(_signature(scene), []).append((path, scene))
    for group in groups.values():
        group_done, group_failed = _estimate_group(group, options, device)
        done.update(group_done)
        reasons.update(group_failed)
    return done, reasons


def _worker_start(threads: int) -> None:
    # Each worker process computes on its share of the cores.
    torch.set_num_threads(threads)


def start_method(threads: int, device: torch.device) -> str:
    """How ``estimate_files`` starts its workers of ``threads`` torch threads each.

    ``fork`` on Linux for one-thread CPU workers: a worker then starts at once with
    the modules and the network this process has loaded (a spawned one spends 3-4 s
    importing them). A forked child that stays on one thread never enters the OpenMP
    pool it inherited, the pattern of torch's DataLoader workers. ``spawn`` otherwise:
    a forked child cannot use CUDA, may hang in an inherited multi-thread pool, and
    macOS frameworks are not fork-safe.
    """
    if threads == 1 and device.type == "cpu" and sys.platform.startswith("linux") \
            and "fork" in multiprocessing.get_all_start_methods():
        return "fork"
    return "spawn"


def worker_threads(workers: int) -> int:
    """Torch threads of each of ``workers`` processes: their share of the usable cores."""
    return max(1, usable_cores() // workers)


def _chunk_results(chunks: list[list[Path]], options: EstimateOptions, device: torch.device, workers: int):
    # (chunk, done, reasons) of every chunk, in the chunks' order. With workers > 1 the
    # chunks run in that many processes (forked or spawned: start_method); a chunk whose worker died (out of
    # memory, killed) is estimated again in this process, so no file is lost with it.
    if workers == 1:
        for chunk in chunks:
            yield (chunk, *_estimate_chunk(chunk, options, device))
        return
    threads = worker_threads(workers)
    context = multiprocessing.get_context(start_method(threads, device))
    with ProcessPoolExecutor(workers, mp_context=context, initializer=_worker_start, initargs=(threads,)) as pool:
        futures = [pool.submit(_estimate_chunk, chunk, options, device) for chunk in chunks]
        try:
            for chunk, future in zip(chunks, futures):
                try:
                    done, reasons = future.result()
                except BrokenProcessPool as error:
                    log.warning("a worker stopped (%s); estimating %s here", error, ", ".join(map(str, chunk)))
                    done, reasons = _estimate_chunk(chunk, options, device)
                yield chunk, done, reasons
        finally:
            # Stopped early (Ctrl-C, a failed write): the pool's exit would otherwise
            # wait for every queued chunk to be estimated.
            for future in futures:
                future.cancel()


def estimate_files(input: str | Path, output: str | Path, options: EstimateOptions, progress: bool = True,
                   batch: int = 1, device: str = "cpu", workers: int | str = 1) -> dict:
    """Estimate every scene file under ``input``; one JSON line per good file in ``output``.

    A bad file is logged with its name and reason and skipped; the summary returned
    counts ``done``, ``failed`` (with reasons), the median seconds per scene, the wall
    time of the whole run, the workers used and how they started (``start``:
    :func:`start_method`, None for this process alone). ``batch`` > 1 estimates up to that
    many consecutive files together (:func:`estimate_batch`; files of one size and
    the same fields share a batch), each record's ``seconds`` being its share of the
    batch's time; a failing batch is retried file by file. ``device``: ``cpu``,
    ``cuda`` or ``auto``. ``workers``: processes the batches are spread over
    (:func:`worker_count`; ``auto``: one per core on the CPU, started as
    :func:`start_method` says); a record's ``seconds`` is then the time in its
    worker, and the run's time per scene is ``wall_seconds / done``. Records are
    written in the files' order whatever the workers.
    """
    if batch < 1:
        raise ValueError(f"estimate.batch must be >= 1, got {batch}")
    started = time.perf_counter()
    where = _device(device)
    files = scene_files(input)
    if not files:
        folders = sorted(p.name for p in Path(input).iterdir() if p.is_dir() and any(p.glob("*.npz")))
        raise FileNotFoundError(f"no .npz scene files in {input}" + (
            f" (its sub-folders {', '.join(folders)} hold some: give one of them)" if folders else ""))
    chunks = [files[first : first + batch] for first in range(0, len(files), batch)]
    workers = min(worker_count(workers, len(files), where), len(chunks))
    if options.method in ("cnn", "cnn+refine"):
        _network(options.checkpoint, str(where))  # a missing or bad checkpoint stops here, before any file
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    failed: dict[str, str] = {}
    seconds: list[float] = []
    try:
        from tqdm import tqdm
        bar = tqdm(total=len(files), desc="estimate", unit="scene", disable=not progress)
    except ImportError:  # tqdm is optional: no progress bar then
        bar = None
    with output.open("w") as out:
        for chunk, done, reasons in _chunk_results(chunks, options, where, workers):
            for path in chunk:  # in the files' order
                if path in reasons:
                    failed[str(path)] = reasons[path]
                    log.error("skipped %s: %s", path, reasons[path])
                elif path in done:
                    try:  # strict JSON: one NaN would break a strict reader on every line
                        line = json.dumps(done[path], allow_nan=False)
                    except ValueError:
                        failed[str(path)] = ("its estimate holds a non-finite number (NaN or inf), "
                                             "which JSON cannot carry")
                        log.error("skipped %s: %s", path, failed[str(path)])
                        continue
                    seconds.append(done[path]["seconds"])
                    out.write(line + "\n")
            out.flush()
            if bar is not None:
                bar.update(len(chunk))
    if bar is not None:
        bar.close()
    wall = time.perf_counter() - started
    summary = {"done": len(seconds), "failed": len(failed), "failures": failed,
               "median_seconds": sorted(seconds)[len(seconds) // 2] if seconds else None,
               "wall_seconds": round(wall, 3), "workers": workers,
               "start": start_method(worker_threads(workers), where) if workers > 1 else None, "output": str(output)}
    log.info("estimated %d scene(s), %d failed, in %.1f s (%d worker(s), %.3f s per file; median %.3f s each); "
             "wrote %s", summary["done"], summary["failed"], wall, workers, wall / max(len(files), 1),
             summary["median_seconds"] or 0.0, output)
    return summary
