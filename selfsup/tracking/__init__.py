"""Lights of frame sequences, each frame started from the last (``mode=track``, ``docs/tracking.md``).

- :mod:`~selfsup.tracking.files`: a sequence of frames in, JSON Lines out (``mode=track``);
- :mod:`~selfsup.tracking.tracker`: :class:`Tracker`, one frame at a time (a live stream);
- :mod:`~selfsup.tracking.kalman`: each light's constant-velocity filter and the pairing of lights to tracks.

Example:
    >>> from selfsup.tracking import Tracker
    >>> tracker = Tracker()
    >>> record = tracker.update("captures/color/frame_000.png")  # doctest: +SKIP
"""

from selfsup.tracking.files import natural_order, track_files
from selfsup.tracking.tracker import REASONS, Tracker
from selfsup.tracking.tuning import TrackTuning

__all__ = ["Tracker", "TrackTuning", "REASONS", "track_files", "natural_order"]
