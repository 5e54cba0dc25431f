"""Frames of a video file (a phone scanning app's ``rgb.mp4``), read forward through PyAV.

PyAV is the optional ``video`` extra (``pip install '.[video]'``): without it, reading a
frame of a video names the extra to install. A scan's frames are read in order, so the
open video and its position are kept between calls: reading frame ``k`` after frame ``j < k``
decodes only the frames between (a frame before the last one read opens the video again).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from selfsup.scenes.io import SceneFileError

__all__ = ["video_frame", "video_size"]

_OPEN: dict = {}  # the one video kept open: {"path", "container", "frames" (iterator), "next" (index)}


def _av(path: Path):
    try:
        import av
    except ImportError:
        raise SceneFileError(path, "reading a video needs PyAV: pip install '.[video]' (or pip install av)") from None
    return av


def _open(path: Path) -> dict:
    av = _av(path)
    if _OPEN:
        _OPEN["container"].close()
        _OPEN.clear()
    try:
        container = av.open(str(path))
    except Exception as error:  # PyAV raises its own kinds for a bad file
        raise SceneFileError(path, f"cannot open the video ({type(error).__name__}: {error})") from None
    _OPEN.update(path=path, container=container, frames=container.decode(video=0), next=0)
    return _OPEN


def video_frame(path: Path, index: int) -> np.ndarray:
    """Frame ``index`` (0-based) of the video ``path`` as 8-bit RGB ``(H, W, 3)``."""
    state = _OPEN if _OPEN.get("path") == path and _OPEN["next"] <= index else _open(path)
    for frame in state["frames"]:
        state["next"] += 1
        if state["next"] - 1 == index:
            return frame.to_ndarray(format="rgb24")
    raise SceneFileError(path, f"the video has {state['next']} frames, no frame {index}")


def video_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of the video's frames."""
    av = _av(path)
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        return int(stream.codec_context.width), int(stream.codec_context.height)
