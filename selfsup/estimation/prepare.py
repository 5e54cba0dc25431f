"""Per-frame inputs of the fit: scene files to a :class:`FitProblem`, normals refitted, clipped pixels, working range.

:func:`prepare` turns same-sized scenes into one batch of the fit problem with the
input settings of the tuning (noisy normals refitted as planes of the depth,
clipped pixels left out); :func:`within_pixels` and :func:`working_range` bring a
large image, or one in far-off units, to what the fit works at, and
:func:`in_file_units` puts the record back into the file's units.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import torch
from torch import Tensor

from render import Material
from selfsup.estimation.normals import SMOOTHING_RADIUS, normal_noise, planes_that_hold, smooth_normals
from selfsup.estimation.options import EstimateOptions, Tuning
from selfsup.estimation.problem import FitProblem
from selfsup.scenes.io import Scene, SceneFileError, scene_gbuffer

__all__ = ["prepare", "problems_of", "problem_of", "saturated_pixels", "full_scales", "CLIP_LEVEL", "plane_window_px", "pixel_stride",
           "within_pixels", "cropped_to_depth", "working_range", "in_file_units", "WORKING_RANGE", "prepared_pool"]

log = logging.getLogger(__name__)


# A capture's clipped pixels lie at the top of its encoding: a channel's peak below this share
# of the full scale is a dim frame's brightest level, however many pixels share it (a surface
# under flat light, quantised to 8 bits, holds one code over thousands of pixels).
CLIP_LEVEL = 0.95


def saturated_pixels(image: Tensor, mask: Tensor, min_share: float = 0.002, full_scale: Tensor | None = None) -> Tensor:
    """Pixels ``(B, H, W)`` with a clipped channel.

    A channel is clipped when at least ``min_share`` of the valid pixels (and at
    least 3) hold exactly its largest value, as a sensor's or a tone mapper's
    clipping leaves them; an unclipped image has its maximum at one pixel. Where
    ``full_scale (B,)`` is given (the linear value of a capture's top code; 0: none
    known, as for a scene file), only a peak at :data:`CLIP_LEVEL` of it or above is a clip.

    Args:
        image: ``(B, 3, H, W)``; mask: ``(B, H, W)`` valid pixels.
    """
    masked = torch.where(mask[:, None], image, torch.full_like(image, -torch.inf))
    peak = masked.flatten(2).amax(-1)[..., None, None]  # (B, 3, 1, 1)
    at_peak = (masked == peak) & mask[:, None]
    count = at_peak.flatten(2).sum(-1)  # (B, 3)
    # A channel black everywhere is dark, not clipped.
    clipped = (count >= 3) & (count >= min_share * mask.flatten(1).sum(-1, keepdim=True)) & (peak[..., 0, 0] > 0)
    if full_scale is not None:
        clipped &= peak[..., 0, 0] >= CLIP_LEVEL * full_scale.to(image)[:, None]
    return (at_peak & clipped[..., None, None]).any(1)


def full_scales(scenes: list[Scene]) -> Tensor:
    """``(B,)`` each scene's full scale (``meta["full_scale"]``: a capture's top code in its
    linear image's units; 0 where the file says none)."""
    return torch.tensor([float(scene.meta.get("full_scale") or 0.0) for scene in scenes])


def problem_of(scene: Scene, shadows: str = "epipolar", dtype=torch.float32, normal_smoothing: str = "never",
               normal_noise_threshold: float = Tuning.normal_noise_threshold, mask_saturated: bool = False, *,
               plane_window: float = Tuning.plane_window,
               plane_shifts: tuple[float, ...] = Tuning.plane_shifts) -> FitProblem:
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
                normal_noise_threshold: float = Tuning.normal_noise_threshold, mask_saturated: bool = False, device=None, *,
                plane_window: float = Tuning.plane_window,
                plane_shifts: tuple[float, ...] = Tuning.plane_shifts) -> FitProblem:
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
    unseen = (~gbuffer.mask.flatten(1).any(1)).tolist()
    if any(unseen):  # a normal from the depth needs valid neighbours: one lone valid pixel has none
        raise SceneFileError(scenes[unseen.index(True)].id, "no pixel has a depth and a normal (a normal from the "
                                                            "depth needs neighbours with a depth)")
    dark = (~((image > 0) & gbuffer.mask[:, None]).flatten(1).any(1)).tolist()
    if any(dark):
        raise SceneFileError(scenes[dark.index(True)].id, "the image is zero on every valid pixel: no light to estimate")
    if mask_saturated:
        clipped = saturated_pixels(image, gbuffer.mask, full_scale=full_scales(scenes).to(image.device))
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
            # planes through a wide window average it away (docs/estimation.md: at 160x120 a 17x17 window
            # sampled every 2 pixels beat 9x9 windows and the file's smoothed normals).
            shorter = min(gbuffer.mask.shape[1:])
            windows = [plane_window_px(fx, plane_window, shorter) for fx in gbuffer.intrinsics[at, 0, 0].tolist()]
            for radius, step in sorted(set(windows)):
                rows = at[torch.tensor([w == (radius, step) for w in windows], device=at.device)]
                points, mask = gbuffer.points[rows], gbuffer.mask[rows]
                planes = planes_that_hold(points, mask, radius=radius, shifts=plane_shifts)
                mask = mask & planes.has_normal
                # Smoothed only where a plane held over a window as wide as the smoothing's:
                # elsewhere the surface curves or creases within it, and its mean normal leans.
                smoothed = torch.where((planes.radius >= SMOOTHING_RADIUS)[..., None],
                                       smooth_normals(points, planes.normals, mask, radius=SMOOTHING_RADIUS),
                                       planes.normals)
                gbuffer = replace(gbuffer, normals=gbuffer.normals.index_put((rows,), smoothed),
                                  mask=gbuffer.mask.index_put((rows,), mask))
                if normal_tilt is None:
                    normal_tilt = torch.zeros_like(gbuffer.mask, dtype=image.dtype)
                # The smoothing's window is within the plane's: it averages errors that are nearly
                # one already, so the plane's tilt variance is kept as it is.
                normal_tilt = normal_tilt.index_put((rows,), planes.tilt_variance.to(image.dtype))
    cropped = [bool(scene.meta.get("cropped_from")) for scene in scenes]
    return FitProblem(gbuffer, material, image, _stacked_field(scenes, "ambient", device), scenes[0].falloff, shadows,
                      normal_tilt=normal_tilt,
                      cropped=torch.tensor(cropped, device=image.device) if any(cropped) else None)


def prepare(scenes: list[Scene], options: EstimateOptions, device=None) -> FitProblem:
    """:func:`problems_of` with the input settings of ``options`` (shadows, normal
    smoothing, clipped pixels): the problem :func:`estimate_batch` expects."""
    return problems_of(scenes, options.shadows, normal_smoothing=options.tuning.normal_smoothing,
                       normal_noise_threshold=options.tuning.normal_noise_threshold,
                       mask_saturated=options.tuning.mask_saturated, device=device, plane_window=options.tuning.plane_window,
                       plane_shifts=options.tuning.plane_shifts)


def pixel_stride(height: int, width: int, max_pixels: int | None) -> int:
    """The least stride ``k`` whose every-``k``-th-pixel subsample of a ``height x width``
    image, ``ceil(H / k) x ceil(W / k)`` pixels, has at most ``max_pixels`` (1 when
    ``max_pixels`` is None)."""
    stride = 1
    while max_pixels is not None and -(-height // stride) * -(-width // stride) > max_pixels:
        stride += 1
    return stride


def within_pixels(scene: Scene, options: EstimateOptions) -> Scene:
    """``scene`` binned (:meth:`Scene.binned`, blocks of :func:`pixel_stride` pixels a side)
    to at most ``options.tuning.max_pixels`` if it is larger: the estimator chooses its
    working resolution, so a 640x480 frame costs what a 160x120 one does. Then, where the
    pixels with a depth fill at most :data:`CROP_SHARE` of the frame (an object photographed
    in the dark), cropped to their box and :data:`CROP_MARGIN` pixels about it: the empty
    rest would cost as much as they do and say nothing."""
    H, W = scene.image.shape[:2]
    stride = pixel_stride(H, W, options.tuning.max_pixels)
    if stride > 1:
        log.info("%s: %dx%d estimated on %dx%d blocks (estimate.tuning.max_pixels=%d)", scene.id, W, H, stride, stride,
                 options.tuning.max_pixels)
    return cropped_to_depth(scene.binned(stride))


# within_pixels crops a frame whose pixels with a depth lie in a box of at most this share of
# it, to that box and this many pixels about it.
CROP_SHARE = 0.5
CROP_MARGIN = 2


def cropped_to_depth(scene: Scene) -> Scene:
    """``scene`` cropped to the box of its pixels with a depth and :data:`CROP_MARGIN` about
    it, where that box is at most :data:`CROP_SHARE` of the frame; else as it is."""
    valid = scene.depth_valid
    if not bool(valid.any()):
        return scene  # problems_of names a frame without depth
    H, W = valid.shape
    rows, cols = valid.any(1).nonzero()[:, 0], valid.any(0).nonzero()[:, 0]
    top, bottom = max(int(rows[0]) - CROP_MARGIN, 0), min(int(rows[-1]) + CROP_MARGIN + 1, H)
    left, right = max(int(cols[0]) - CROP_MARGIN, 0), min(int(cols[-1]) + CROP_MARGIN + 1, W)
    if (bottom - top) * (right - left) > CROP_SHARE * H * W:
        return scene
    log.info("%s: the pixels with a depth fill %dx%d of %dx%d: estimated on that box", scene.id, right - left,
             bottom - top, W, H)
    crop = scene.cropped(top, left, bottom - top, right - left)
    return replace(crop, meta={**crop.meta, "cropped_from": [W, H, left, top]})


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
    model is linear in them): :func:`in_file_units` undoes it in the record."""
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
    meta = scene.meta if scene.meta.get("full_scale") is None else {**scene.meta, "full_scale": scene.meta["full_scale"] * factor}
    return replace(scene, image=scene.image * factor, ambient=ambient, meta=meta), factor


def in_file_units(record: dict, factor: float) -> dict:
    # A record of a scene that working_range multiplied by ``factor``, in the file's units.
    if factor != 1.0:
        for light in record["lights"]:
            light["intensity"] = [value / factor for value in light["intensity"]]
        record["ambient"] = [value / factor for value in record["ambient"]]
    return record


def prepared_pool(pool: dict[str, Tensor], long_side: int, tuning: Tuning = Tuning(), batch: int = 32) -> dict[str, Tensor]:
    """A rendered pool of scene items (:func:`selfsup.scenes.dataset.scene_to_item`, stacked)
    as :func:`prepare` makes a capture's frames, then on the network's working grid
    (:func:`selfsup.network.grid.work_grid` at ``long_side``): normals refitted from the
    depth where it is noisy, clipped pixels left out, colour, albedo, points and normals
    averaged over the grid's cells. So training frames reach the network as a capture's do
    (a camera's frame at its resolution, prepared, then pooled), not rendered at the grid's
    size, where a sensor's disparity steps and a JPEG's blocks are several cells wide.

    Returns the pool's items on the grid: ``image``, ``kd``, ``ks``, ``shininess``,
    ``normals`` (zeros off the mask), ``depth`` (the cells' mean z, 0 off the mask) and ``K``
    (scaled) replaced; the rest (lights, scales, ambient) as they were.
    """
    count = pool["image"].shape[0]
    quiet = log.level
    log.setLevel(max(quiet, logging.WARNING))  # thousands of frames' clipped-pixel counts are no news
    try:
        return _prepared_pool(pool, count, long_side, tuning, batch)
    finally:
        log.setLevel(quiet)


def _prepared_pool(pool: dict[str, Tensor], count: int, long_side: int, tuning: Tuning, batch: int) -> dict[str, Tensor]:
    from selfsup.network.grid import work_grid

    keys = ("image", "kd", "ks", "shininess", "normals", "depth", "K")
    parts: dict[str, list[Tensor]] = {key: [] for key in keys}
    order: list[int] = []
    for start in range(0, count, batch):
        rows = list(range(start, min(count, start + batch)))
        known = [bool(pool["normals"][i].abs().amax() > 0) for i in rows]  # exact renders give normals; sensors not
        for group in ([i for i, k in zip(rows, known) if not k], [i for i, k in zip(rows, known) if k]):
            if not group:
                continue
            scenes = [Scene(image=pool["image"][i], depth=pool["depth"][i], K=pool["K"][i], kd=pool["kd"][i],
                            ks=pool["ks"][i], shininess=pool["shininess"][i],
                            normals=pool["normals"][i] if known[i - start] else None,
                            meta={"id": f"pool_{i}", "full_scale": 1.0}) for i in group]
            problem = problems_of(scenes, "none", normal_smoothing=tuning.normal_smoothing,
                                  normal_noise_threshold=tuning.normal_noise_threshold,
                                  mask_saturated=tuning.mask_saturated, plane_window=tuning.plane_window,
                                  plane_shifts=tuning.plane_shifts)
            g, m = problem.gbuffer, problem.material
            grid = work_grid(problem.image, g, long_side)
            # The materials averaged over the same cells with the same weights, as a 5-channel "image".
            materials = torch.cat([m.kd.permute(0, 3, 1, 2), m.ks.permute(0, 3, 1, 2)[:, :1],
                                   m.shininess_map()[:, None].expand(len(group), 1, *g.mask.shape[1:])], 1)
            pooled = work_grid(materials[:, :3], g, long_side).image, work_grid(materials[:, 2:], g, long_side).image
            mask = grid.gbuffer.mask
            parts["image"].append(grid.image.permute(0, 2, 3, 1))
            parts["kd"].append(pooled[0].permute(0, 2, 3, 1))
            parts["ks"].append(pooled[1][:, 1:2].permute(0, 2, 3, 1))
            parts["shininess"].append(torch.where(mask, pooled[1][:, 2], torch.ones_like(pooled[1][:, 2])))
            parts["normals"].append(grid.gbuffer.normals * mask[..., None])
            parts["depth"].append(torch.where(mask, grid.gbuffer.points[..., 2], torch.zeros_like(pooled[1][:, 2])))
            parts["K"].append(grid.gbuffer.intrinsics)
            order.extend(group)
    back = torch.argsort(torch.tensor(order))  # the groups' rows back in the pool's order
    out = dict(pool)
    for key in keys:
        out[key] = torch.cat(parts[key])[back]
    return out
