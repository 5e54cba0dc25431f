"""Lights of a live frame sequence: each frame started from the last one's lights.

:class:`Tracker` keeps one filtered state per light (:mod:`selfsup.tracking.kalman`).
The first frame is estimated in full (:func:`selfsup.estimation.estimate_batch`, the
``mode=estimate`` pipeline). Each next frame is a *warm* step: the lights start where
the filter predicts them, a few Levenberg-Marquardt steps of the model the full
estimate chose refine them (the albedo-free fit of :mod:`selfsup.estimation.albedo_free`
for a frame without albedo, the image fit of :mod:`selfsup.estimation.solvers`
otherwise), and their positions and covariances update the filter. A frame is
estimated in full again when the evidence says the lights changed (:data:`REASONS`):
the image changed in a way the fit does not explain, its residual jumps above the
recent frames', a light moves farther than the filter allows, or a light's share of
the light falls (switched off). The geometry (normals of the depth, smooth surfaces)
is kept while the depth stays the same. ``docs/tracking.md`` tells it in full.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
from torch import Tensor

from render import Material
from selfsup.estimation import albedo_free
from selfsup.estimation.criterion import block_px, light_shares
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.prepare import full_scales, prepare, saturated_pixels, within_pixels, working_range
from selfsup.estimation.normals import surface_segments
from selfsup.estimation.problem import FitProblem, centre_and_size, subsample
from selfsup.estimation.records import records
from selfsup.estimation.intensities import intensities_of
from selfsup.estimation.reflectance import albedo_free_covariance
from selfsup.estimation.solvers import refine
from selfsup.estimation.stages import estimate_batch, with_coat
from selfsup.estimation.uncertainty import position_covariance
from selfsup.scenes.capture import CaptureFrame, read_input
from selfsup.scenes.io import Scene, SceneFileError
from selfsup.scenes.poses import check_pose
from selfsup.tracking.kalman import LightState, moved, pair_lights, predict, start_state, update
from selfsup.tracking.tuning import TrackTuning

__all__ = ["Tracker", "TrackTuning", "REASONS"]

CHANGE_LIT = 0.2  # the change test's pixels: image and model at least this share of their medians
MOVED_BLOCK_PX = 8  # the blocks over which the depth's change is averaged (TrackTuning.moved_sigma)
MOVED_HOLES = 0.05  # or when this share of the pixels gained or lost their depth (a sensor's holes come and go)

# Why a frame was estimated in full (a record's "reason"; None: a warm step).
REASONS = ("first", "refresh", "change", "residual", "motion", "share", "cut")


def _inverse_depth(depth: Tensor) -> Tensor:
    # (H, W) 1 / depth on the valid pixels (finite, > 0), 0 elsewhere.
    valid = (depth > 0) & torch.isfinite(depth)
    return torch.where(valid, 1 / torch.where(valid, depth, 1.0), 0.0)


def _check_frame(scene: Scene) -> None:
    # A frame given in memory (a file's reader checks its own): a clear error, not NaN lights.
    for name in ("image", "kd", "K"):
        value = getattr(scene, name)
        if not bool(torch.isfinite(value).all()):
            raise SceneFileError(scene.id, f"{name} holds {int((~torch.isfinite(value)).sum())} non-finite values "
                                           "(NaN or inf): give finite values (0 depth marks a missing pixel)")
    if bool((scene.image < 0).any()):
        raise SceneFileError(scene.id, "the image holds negative values: give linear, non-negative values")


@dataclass
class _Measured:
    # One frame's lights as measured (working units): positions (L, 3), their covariances
    # (L, 3, 3), intensities (L, 3), ambient (3,), the model image (1, 3, H, W), the
    # albedo-free log weights (L + 1,); a warm fit's loss per residual and each light's share (L,).
    # All but the model image are float64 on the CPU, where the filter keeps its states,
    # whatever device the fit ran on; the model image stays on the fit's device.
    position: Tensor
    covariance: Tensor
    intensity: Tensor
    ambient: Tensor
    model: Tensor
    log_weight: Tensor | None = None
    loss: float | None = None
    share: Tensor | None = None


def _host(values: Tensor) -> Tensor:
    # A fit's small result as the filter keeps it: float64 on the CPU.
    return values.detach().to("cpu", torch.float64)


@dataclass
class _Geometry:
    # What a frame of the same depth reuses: the prepared problem of the frame that made it
    # (its normals, mask before clipped pixels, normal tilt) and its smooth surfaces.
    depth: Tensor
    problem: FitProblem
    inverse: Tensor  # (H, W) 1 / depth where valid, 0 elsewhere: what later frames' depths are compared with
    surfaces: Tensor | None = None
    labels: Tensor | None = None  # (1, H, W) at the warm stride
    labels_at: Tensor | None = None  # (L, 3): the lights when they were found


@dataclass
class _Model:
    # What the last full estimate chose, which every warm step keeps.
    albedo_free: bool
    specular: bool
    coat: bool


@dataclass
class _Track:
    id: int
    state: LightState
    intensity: Tensor
    log_weight: Tensor | None = None


@dataclass
class Tracker:
    """Lights per frame of a sequence, each frame started from the last one's.

    ``update(frame)`` takes a :class:`selfsup.scenes.io.Scene`, a scene file, a colour
    image of a capture folder or a :class:`selfsup.scenes.capture.CaptureFrame`, and
    returns the frame's record (``docs/scene-format.md``, "Tracking output"): the
    filtered lights with their track ids and covariances, the frame's latency, and
    whether (and why) it was estimated in full. ``refresh``: estimate every that-many-th
    frame in full whatever the evidence (0: only on evidence); the tracked lights are kept
    unless that estimate explains the frame better (a wrong start is left within a second
    at 30 frames per second). ``first_frame``: the number the first frame's record carries
    (a sequence tracked on from a frame after its start).

    Example:
        >>> tracker = Tracker()
        >>> for frame in frames:  # doctest: +SKIP
        ...     record = tracker.update(frame)
        ...     lights = [light["position"] for light in record["lights"]]
    """

    options: EstimateOptions = field(default_factory=EstimateOptions)
    tuning: TrackTuning = field(default_factory=TrackTuning)
    refresh: int = 30
    device: str | torch.device = "cpu"
    first_frame: int = 0
    _tracks: list[_Track] = field(default_factory=list, init=False, repr=False)
    _model: _Model | None = field(default=None, init=False, repr=False)
    _geometry: _Geometry | None = field(default=None, init=False, repr=False)
    _reference: deque = field(default_factory=deque, init=False, repr=False)
    _frame: int = field(default=0, init=False, repr=False)
    _since_full: int = field(default=0, init=False, repr=False)
    _change_rests: int = field(default=0, init=False, repr=False)  # frames the change test still rests
    _cut: bool = field(default=False, init=False, repr=False)  # the frame shows another place than the last
    _pose: Tensor | None = field(default=None, init=False, repr=False)  # the last frame's camera-to-world
    _next_id: int = field(default=0, init=False, repr=False)
    _ambient: Tensor | None = field(default=None, init=False, repr=False)  # the albedo-free ambient's log weight (1,)
    _ambient_rgb: Tensor | None = field(default=None, init=False, repr=False)  # (3,) working units
    # (H, W) log(image / model) of the last frame, what the change test compares with
    _unexplained: Tensor | None = field(default=None, init=False, repr=False)

    def __post_init__(self):
        if isinstance(self.tuning, dict):  # from a config
            self.tuning = TrackTuning(**self.tuning)
        if isinstance(self.refresh, bool) or not isinstance(self.refresh, int) or self.refresh < 0:
            raise ValueError(f"track.refresh must be an integer >= 0 (0: full estimates on evidence only), "
                             f"got {self.refresh!r}")
        self.device = torch.device(self.device)
        self._reference = deque(maxlen=self.tuning.reference_frames)

    def reset(self) -> None:
        """Forget every light: the next frame is estimated in full."""
        self._tracks, self._model, self._geometry, self._ambient = [], None, None, None
        self._reference.clear()
        self._since_full = self._change_rests = 0

    @property
    def lights(self) -> Tensor:
        """The filtered light positions ``(L, 3)`` now (metres, camera frame)."""
        if not self._tracks:
            return torch.zeros(0, 3, dtype=torch.float64)
        return torch.stack([t.state.position for t in self._tracks])

    def update(self, frame: Scene | str | Path | CaptureFrame, pose=None) -> dict:
        """The record of the next frame (see the class). Reading the frame is part of its latency.

        ``pose``: the frame's camera-to-world ``(4, 4)`` (OpenCV axes, metres), where the
        sequence has poses: the tracked lights are then carried from the last frame's camera
        into this one's before they are predicted (a still light stays still in the room
        while the camera moves), and each light of the record also gets its
        ``world_position``."""
        started = time.perf_counter()
        scene = frame if isinstance(frame, Scene) else read_input(frame)
        read = time.perf_counter() - started
        _check_frame(scene)
        self._follow(pose, scene.id)
        scene, factor = working_range(within_pixels(scene, self.options))
        with torch.no_grad():
            full_resolution = self._problem(scene)
            problem = subsample(full_resolution, self.tuning.warm_stride)
            size = float(centre_and_size(problem)[1][0])
            reason = self._due() or ("cut" if self._cut else None)
            measured = None
            if reason is None:
                predicted = [predict(t.state, self.tuning.acceleration_std * size) for t in self._tracks]
                labels = self._labels(full_resolution, size)
                measured = self._warm(problem, torch.stack([p.position for p in predicted]), labels)
                reason = self._changed(problem, measured, predicted, size)
                if reason is None and self.refresh and self._since_full + 1 >= self.refresh:
                    reason = "refresh"
            if reason is None:
                self._filtered(measured, predicted, size)
            elif reason == "refresh":
                measured = self._refreshed(problem, scene, measured, predicted, size, labels)
            else:
                measured = self._full(scene)
                if reason == "cut":  # another place: no light continues a track of the last one
                    self._tracks = []
                same = self._restarted(measured, size)
                if reason == "change" and same:  # a change the lights it has cannot explain: not a switch
                    self._change_rests = self.tuning.change_cooldown
            self._unexplained = self._log_ratio(problem, measured.model)
        self._frame += 1
        return self._record(scene.id, reason, factor, time.perf_counter() - started, read)

    def _follow(self, pose, name: str) -> None:
        # The camera's move since the last posed frame applied to every track (states in the
        # new camera's frame); no pose: the tracks stay as they are.
        if pose is None:
            self._pose = None
            return
        pose = torch.as_tensor(check_pose(pose, f"{name}: its pose"), dtype=torch.float64)
        if self._pose is not None:
            relative = torch.linalg.inv(pose) @ self._pose  # the last camera's points in this one's frame
            for track in self._tracks:
                track.state = moved(track.state, relative[:3, :3], relative[:3, 3])
        self._pose = pose

    # -- the frame's problem, its geometry kept while the depth stays --------------------------

    def _problem(self, scene: Scene) -> FitProblem:
        # The frame's problem; the kept geometry's normals where the depth is the same.
        kept = self._geometry
        depth = scene.depth.to(self.device)
        inverse = _inverse_depth(depth)
        self._cut = kept is not None and self._is_cut(kept, inverse)
        if kept is None or not self._depth_change(kept, depth, inverse):
            base = prepare([scene], self.options.tuned(mask_saturated=False), self.device)
            self._geometry = _Geometry(depth, base, inverse)
            self._unexplained = None  # pixels no longer correspond
        base = self._geometry.problem
        image = scene.image.to(self.device, base.image.dtype).permute(2, 0, 1)[None]
        mask = base.gbuffer.mask
        if self.options.tuning.mask_saturated:
            mask = mask & ~saturated_pixels(image, mask, full_scale=full_scales([scene]).to(image.device))
        if not bool(((image > 0) & mask[:, None]).any()):
            raise SceneFileError(scene.id, "the image is zero on every valid pixel: no light to estimate")
        kd = scene.kd.to(self.device, base.material.kd.dtype)[None]
        ks = None if scene.ks is None else scene.ks.to(self.device, kd.dtype)[None]
        material = Material(kd=kd, ks=ks, shininess=base.material.shininess)
        ambient = None if scene.ambient is None else scene.ambient.to(self.device, kd.dtype)[None]
        return FitProblem(replace(base.gbuffer, mask=mask), material, image, ambient, base.falloff, base.shadows,
                          normal_tilt=base.normal_tilt)

    def _is_cut(self, kept: _Geometry, inverse: Tensor) -> bool:
        # Whether the frame of ``inverse`` (inverse depth, 0 where missing) shows another place
        # than the kept frame: its size changed, or more than cut_blocks of the blocks seen in
        # both changed their mean inverse depth by more than cut_change of it.
        if kept.inverse.shape != inverse.shape:
            return True
        both = ((kept.inverse > 0) & (inverse > 0))[None, None].to(inverse.dtype)
        px = MOVED_BLOCK_PX
        pool = lambda x: torch.nn.functional.avg_pool2d(x, px, px, ceil_mode=True)[0, 0]  # noqa: E731
        before, after, seen = pool(kept.inverse[None, None] * both), pool(inverse[None, None] * both), pool(both)
        usable = seen >= 0.5
        if not bool(usable.any()):
            return True
        change = (after - before).abs()[usable] / before[usable].clamp_min(torch.finfo(before.dtype).tiny)
        return float((change > self.tuning.cut_change).float().mean()) > self.tuning.cut_blocks

    def _depth_change(self, kept: _Geometry, depth: Tensor, inverse: Tensor) -> bool:
        # Whether ``depth`` (``inverse``: its inverse, 0 where missing) is the kept frame's seen
        # from the same place: its inverse depth (affine in the pixel on a plane) changed,
        # averaged over blocks, by no more than its noise allows on all but ``moved_blocks`` of them.
        if kept.depth.shape != depth.shape:
            return False
        valid_kept, valid = kept.inverse > 0, inverse > 0
        both = valid_kept & valid
        if float((valid_kept != valid).float().mean()) > MOVED_HOLES or not bool(both.any()):
            return False
        triples = valid[:, :-2] & valid[:, 1:-1] & valid[:, 2:]
        second = (inverse[:, :-2] - 2 * inverse[:, 1:-1] + inverse[:, 2:])[triples]
        level = float(inverse[valid].median())
        noise = max(1.4826 / math.sqrt(6) * float(second.abs().median()) if second.numel() else 0.0, 1e-6 * level)
        change = torch.where(both, inverse - kept.inverse, 0.0)
        px = MOVED_BLOCK_PX
        sums = torch.nn.functional.avg_pool2d(change[None, None], px, px, ceil_mode=True)[0, 0] * px * px
        counts = torch.nn.functional.avg_pool2d(both[None, None].to(change.dtype), px, px, ceil_mode=True)[0, 0]
        counts = counts * px * px
        usable = counts >= px * px / 2
        if not bool(usable.any()):
            return False
        score = sums[usable].abs() / (math.sqrt(2) * noise * counts[usable].sqrt())
        return float((score > self.tuning.moved_sigma).float().mean()) <= self.tuning.moved_blocks

    def _labels(self, problem: FitProblem, size: float) -> Tensor | None:
        # The albedo segments of the frame (full resolution), at the warm step's stride: the
        # kept geometry's surfaces cut by the image's edges. Cast shadows move with the lights,
        # so they are found again once a light moved relabel_motion from where it was when they were.
        if self.tuning.warm_residuals != "segments" or self._model is None or not self._model.albedo_free:
            return None
        kept, lights = self._geometry, self.lights
        if (kept.labels is not None and kept.labels_at.shape == lights.shape
                and float((kept.labels_at - lights).norm(dim=-1).max()) <= self.tuning.relabel_motion * size):
            return kept.labels
        g = problem.gbuffer
        if kept.surfaces is None:
            kept.surfaces = surface_segments(g.points, g.normals, g.mask)
        stride = self.tuning.warm_stride
        tuning = self.options.tuning
        labels = albedo_free.tuned_segments(problem, tuning, kept.surfaces)
        if tuning.albedo_class_rounds > 0:  # merged into albedo classes under the tracked lights, as a full estimate's
            like = problem.image
            labels = albedo_free.albedo_classes(problem, labels, lights.to(like)[None], self._log_weights().to(like)[None],
                                                tuning.albedo_class_level, tuning.albedo_class_chroma, kept.surfaces)
        kept.labels, kept.labels_at = labels[:, ::stride, ::stride], lights
        return kept.labels

    # -- full and warm estimates ------------------------------------------------------------------

    def _due(self) -> str | None:
        if not self._tracks or self._model is None:
            return "first" if self._frame == 0 else "share"  # every light lost: estimated afresh
        return None

    def _refreshed(self, problem: FitProblem, scene: Scene, warm: _Measured, predicted: list[LightState],
                   size: float, labels: Tensor | None) -> _Measured:
        # A refresh: the full estimate replaces the tracked lights unless it chose the same
        # model and light count and, refined as a warm step, explains the frame no better
        # than they do (a full estimate can miss what the tracker holds, as a weak second light).
        model, reference = self._model, list(self._reference)
        full = self._full(scene)
        if self._model == model and full.position.shape == warm.position.shape:
            if self._model.albedo_free:
                self._ambient = full.log_weight[:1]
                for track, weight in zip(self._tracks, full.log_weight[1:]):
                    track.log_weight = weight
            again = self._warm(problem, full.position, labels)
            if warm.loss <= again.loss:
                self._reference.extend(reference)
                self._filtered(warm, predicted, size)
                return warm
        self._restarted(full, size)
        return full

    def _full(self, scene: Scene) -> _Measured:
        # The mode=estimate pipeline on this frame at full resolution; the model it chose is
        # kept for the warm steps.
        options = self.options
        problem = prepare([scene], options, self.device)
        best, tried = estimate_batch(problem, options)[0]
        record = records([scene.id], problem, [(best, tried)], options)[0]
        free = best.reflectance == "albedo_free"
        self._model = _Model(free, best.specular, best.coat)
        position = torch.tensor([light["position"] for light in record["lights"]], dtype=torch.float64).reshape(-1, 3)
        cov = torch.tensor([light["position_cov"] for light in record["lights"]], dtype=torch.float64).reshape(-1, 3, 3)
        intensity = torch.tensor([light["intensity"] for light in record["lights"]],
                                 dtype=torch.float64).reshape(-1, 3)
        ambient = torch.tensor(record["ambient"], dtype=torch.float64)
        log_weight = None
        if free:  # the shading's weights: the grey ambient, then each light's grey intensity
            # (A frame whose record found no light has the ambient alone: every next frame is estimated afresh.)
            peak = float(intensity.max()) if intensity.numel() else float(ambient.max())
            grey = torch.cat([ambient.mean()[None], intensity.mean(-1)]).clamp_min(1e-6 * peak)
            log_weight = grey.log()
        self._reference.clear()
        self._since_full = 0
        stride = self.tuning.warm_stride
        return _Measured(position, cov, intensity, ambient, best.fit.model[..., ::stride, ::stride], log_weight)

    def _warm(self, problem: FitProblem, start: Tensor, labels: Tensor | None) -> _Measured:
        # A few LM steps of the chosen model from ``start (L, 3)``.
        start = start.to(problem.image.device, problem.image.dtype)[None]
        if self._model.albedo_free:
            return self._warm_albedo_free(problem, start, labels)
        return self._warm_given(problem, start)

    def _log_weights(self) -> Tensor:
        # The albedo-free model's log weights (L + 1,): the ambient's, then each tracked light's.
        return torch.cat([self._ambient, torch.stack([t.log_weight for t in self._tracks])])

    def _warm_albedo_free(self, problem: FitProblem, start: Tensor, labels: Tensor | None) -> _Measured:
        tuning = self.options.tuning
        obs = albedo_free.observe(problem, tuning.albedo_free_scale, residuals=self.tuning.warm_residuals,
                                  labels=labels)
        log_weight = self._log_weights().to(start)[None]
        fit = albedo_free.refine_positions(obs, start, log_weight, self.tuning.warm_iterations)
        cov = albedo_free_covariance(obs, fit, problem, self.options)
        solved, _ = intensities_of(problem, fit, self.options)  # as the full estimates report them
        share = albedo_free.light_shares(problem, fit)
        loss = float(fit.loss[0]) / max(float(fit.pairs[0]), 1.0)
        return _Measured(_host(fit.position[0]), _host(cov[0]), _host(solved.intensity[0]), _host(solved.ambient[0]),
                         solved.model, _host(fit.log_weight[0]), loss, _host(share[0]))

    def _warm_given(self, problem: FitProblem, start: Tensor) -> _Measured:
        tuning, model = self.options.tuning, self._model
        if model.coat:
            problem = problem.with_material(with_coat(problem.material, [True]))
        steps = replace(tuning.refine, specular=model.specular, strides=tuning.refine.strides[-1:],
                        max_iters=(self.tuning.warm_iterations,), robust_scale=tuning.final_robust_scale)
        fit = refine(problem, start, steps)
        block = block_px(self.options, problem.image.shape[-1])
        cov = position_covariance(problem, fit, steps, correlation_px=float(block**2),
                                  albedo_error=tuning.albedo_error, albedo_block_px=block,
                                  indirect_variation=tuning.indirect_variation,
                                  indirect_length=tuning.indirect_length, normal_error=tuning.normal_error)
        share = light_shares(problem, fit, model.specular)
        loss = float(fit.cost[0]) / max(float(fit.n[0]), 1.0)
        return _Measured(_host(fit.position[0]), _host(cov[0]), _host(fit.intensity[0]), _host(fit.ambient[0]),
                         fit.model, loss=loss, share=_host(share[0]))

    def _log_ratio(self, problem: FitProblem, model: Tensor) -> Tensor:
        # (H, W) log(image / model) of the grey values; NaN where the pixel is invalid or
        # either is darker than CHANGE_LIT of its median (shadows and dark sides: noise and
        # quantisation, and the ambient the fit knows least).
        image, model = problem.image[0].mean(0), model[0].mean(0).to(problem.image.dtype)
        mask = problem.gbuffer.mask[0]
        lit = (image > CHANGE_LIT * image[mask].median()) & (model > CHANGE_LIT * model[mask].median())
        ratio = torch.log(image.clamp_min(1e-30)) - torch.log(model.clamp_min(1e-30))
        return torch.where(mask & lit, ratio, torch.full_like(ratio, float("nan")))

    def _changed_share(self, problem: FitProblem, model: Tensor) -> float:
        # The share of the pixels usable in both frames whose change the warm fit leaves
        # unexplained by more than change_step (or 3 sigma of the image noise's log ratio),
        # a change of the whole image's gain (exposure) taken out.
        if self._unexplained is None:
            return 0.0
        change = self._log_ratio(problem, model) - self._unexplained
        both = torch.isfinite(change)
        if not bool(both.any()):
            return 1.0
        change = (change[both] - change[both].median()).abs()
        relative_noise = float(problem.noise_level()[0] / problem.median_observed()[0].clamp_min(1e-30))
        step = max(self.tuning.change_step, 3 * math.sqrt(2) * relative_noise)
        return float((change > step).float().mean())

    def _changed(self, problem: FitProblem, measured: _Measured, predicted: list[LightState], size: float
                 ) -> str | None:
        # Why the warm step's answer is not to be trusted, or None.
        if bool((measured.share < self.options.tuning.min_light_share).any()):
            return "share"
        if self._change_rests > 0:
            self._change_rests -= 1
        elif self._changed_share(problem, measured.model) > self.tuning.change_share:
            return "change"
        expected = torch.stack([p.position for p in predicted])
        if float((measured.position - expected).norm(dim=-1).max()) > self.tuning.fast_motion * size:
            return "motion"
        if len(self._reference) and measured.loss > self.tuning.jump_ratio * sorted(self._reference)[
                len(self._reference) // 2]:
            return "residual"
        if not all(math.isfinite(v) for v in measured.position.flatten().tolist()):
            return "residual"
        return None

    # -- the filter ----------------------------------------------------------------------------

    def _measurement_cov(self, cov: Tensor, size: float) -> Tensor:
        floor = (self.tuning.measurement_floor * size) ** 2
        return cov + torch.eye(3, dtype=torch.float64) * floor

    def _filtered(self, measured: _Measured, predicted: list[LightState], size: float) -> None:
        # A warm frame: every track's prediction updated with its light's measurement.
        for k, track in enumerate(self._tracks):
            covariance = self._measurement_cov(measured.covariance[k], size)
            track.state = update(predicted[k], measured.position[k], covariance)
            track.intensity = measured.intensity[k]
            if measured.log_weight is not None:
                track.log_weight = measured.log_weight[k + 1]
        if measured.log_weight is not None:
            self._ambient = measured.log_weight[:1]
        self._ambient_rgb = measured.ambient
        self._reference.append(measured.loss)
        self._since_full += 1

    def _restarted(self, measured: _Measured, size: float) -> bool:
        # A full estimate: tracks continue where a found light is near a tracked one; the
        # others end and new ones start; every state restarts at its measurement. Returns
        # whether the lights are the ones tracked (each found light continues a track, none ends).
        pairs = pair_lights(self.lights, measured.position, self.tuning.match_radius * size)
        same = len(pairs) == len(self._tracks) and None not in pairs
        tracks = []
        for k, previous in enumerate(pairs):
            state = start_state(measured.position[k], self._measurement_cov(measured.covariance[k], size),
                                self.tuning.velocity_std * size)
            if previous is None:
                track_id, self._next_id = self._next_id, self._next_id + 1
            else:
                track_id = self._tracks[previous].id
            tracks.append(_Track(track_id, state, measured.intensity[k],
                                 None if measured.log_weight is None else measured.log_weight[k + 1]))
        self._tracks = tracks
        self._ambient = None if measured.log_weight is None else measured.log_weight[:1]
        self._ambient_rgb = measured.ambient
        return same

    # -- the record ------------------------------------------------------------------------------

    def _record(self, scene_id: str, reason: str | None, factor: float, seconds: float, read: float) -> dict:
        lights = []
        for track in sorted(self._tracks, key=lambda t: t.id):
            cov = track.state.position_cov
            lights.append({"track": track.id, "position": track.state.position.tolist(),
                           "velocity": track.state.mean[3:].tolist(),
                           "intensity": (track.intensity / factor).tolist(),
                           "position_std": cov.diagonal().clamp_min(0).sqrt().tolist(),
                           "position_cov": cov.tolist()})
            if self._pose is not None:
                world = self._pose[:3, :3] @ track.state.position + self._pose[:3, 3]
                lights[-1]["world_position"] = world.tolist()
        model = self._model
        return {"id": scene_id, "frame": self.first_frame + self._frame - 1, "lights": lights,
                "ambient": (self._ambient_rgb / factor).tolist(),
                "reflectance": "albedo_free" if model.albedo_free else "given", "specular": model.specular,
                "coat": model.coat, "full": reason is not None, "reason": reason,
                "latency_ms": round(seconds * 1000, 2), "read_ms": round(read * 1000, 2)}
