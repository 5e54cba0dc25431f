"""The tracker's tuned constants: :class:`TrackTuning` (``track.tuning.NAME`` on the command line)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from selfsup.estimation.options import ALBEDO_FREE_RESIDUALS

__all__ = ["TrackTuning"]


@dataclass(frozen=True)
class TrackTuning:
    """The tracker's tuned constants (``docs/tracking.md`` gives how each was chosen).

    Lengths are shares of the scene size (the valid points' bounding-box diagonal).

    warm_iterations: LM steps of a warm frame.
    warm_stride: a warm frame is fitted on every that-many-th pixel of each row and
        column; full estimates use every pixel.
    relabel_motion: the albedo segments (whose edges include the cast shadows') are kept
        while every light stays this close to where it was when they were found.
    warm_residuals: the albedo-free warm step's residuals: ``segments`` (as the full
        estimate: each frame's albedo segments, found at full resolution, the kept
        geometry's surfaces cut by the frame's image edges, merged into albedo classes
        under the tracked lights where ``estimate.tuning.albedo_class_rounds`` > 0) |
        ``pairs`` (neighbours' differences: no segmentation, faster, biased where the
        shadows move).
    change_cooldown: after a ``change`` whose full estimate found the lights it had
        (the change was light the model cannot explain, not a switch), the change test
        rests for this many frames.
    change_step, change_share: while the geometry is kept, a frame where more than
        ``change_share`` of the valid pixels changed by more than ``change_step`` (relative,
        beyond the image noise) from the last frame in a way the warm fit does not explain
        is estimated in full: ``log(image / model)`` compared pixel by pixel with the
        last frame's, so the albedo cancels (a light switched on or off).
    jump_ratio, reference_frames: a warm frame whose loss per residual exceeds this
        multiple of the median of the last ``reference_frames`` frames' is estimated in full.
    fast_motion: a warm step that puts a light farther than this from the filter's
        prediction sends the frame to the full estimate.
    acceleration_std: the filter's process noise (per frame squared).
    velocity_std: a new track's velocity uncertainty (per frame).
    measurement_floor: standard deviation added to every measured position (the
        covariance of a few LM steps from a warm start is a lower bound).
    match_radius: after a full estimate, a light this close to a tracked one continues its track.
    moved_sigma, moved_blocks: the camera moved (the geometry is found again) when more
        than ``moved_blocks`` of the ``tracker.MOVED_BLOCK_PX``-pixel square blocks changed their
        mean inverse depth by more than ``moved_sigma`` standard deviations of its noise
        (or ``tracker.MOVED_HOLES`` of the pixels gained or lost their depth).
    cut_change, cut_blocks: a cut (the frame shows another place: a new scene, a jump in a
        video) when more than ``cut_blocks`` of those blocks changed their mean inverse depth
        by more than ``cut_change`` of it (or the depth's size changed): the frame is
        estimated in full, its lights not warm-started from the last frame's. A moving
        camera changes few blocks this much (at most 0.05 of them over 5.5 degrees a frame
        of our orbits and between the real shelf_bin frames; 0.32-0.35 between the three
        rooms of examples/capture).
    """

    warm_iterations: int = 3
    warm_stride: int = 2
    relabel_motion: float = 0.01
    warm_residuals: str = "segments"
    change_step: float = 0.1
    change_cooldown: int = 8
    change_share: float = 0.05
    jump_ratio: float = 2.0
    reference_frames: int = 8
    fast_motion: float = 0.1
    acceleration_std: float = 0.004
    velocity_std: float = 0.02
    measurement_floor: float = 0.001
    match_radius: float = 0.15
    moved_sigma: float = 4.0
    moved_blocks: float = 0.1
    cut_change: float = 0.2
    cut_blocks: float = 0.2

    def __post_init__(self):
        if self.warm_residuals not in ALBEDO_FREE_RESIDUALS:
            raise ValueError(f"track.tuning.warm_residuals must be one of {ALBEDO_FREE_RESIDUALS}, "
                             f"got {self.warm_residuals!r}")
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in ("warm_iterations", "warm_stride", "reference_frames", "change_cooldown"):
                if isinstance(value, bool) or not isinstance(value, int) or value < (f.name != "change_cooldown"):
                    raise ValueError(f"track.tuning.{f.name} must be an integer >= 1, got {value!r}")
            elif f.name != "warm_residuals" and not (isinstance(value, (int, float)) and math.isfinite(value)
                                                     and value > 0):
                raise ValueError(f"track.tuning.{f.name} must be a finite number > 0, got {value!r}")
