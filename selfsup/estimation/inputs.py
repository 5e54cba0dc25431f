"""What ``estimate.input`` names, as a stream of frames, and the shard of it one process takes.

An input is a capture folder (``color/`` beside ``depth/``), a directory of ``.npz`` scene
files, one scene file, one colour file with ``estimate.depth``, a **folder of folders**
(each sub-folder a capture folder or a directory of scene files; ids become
``<sub-folder>/<id>`` so that they stay unique), or a **list file** (``.txt`` / ``.lst``:
one frame a line, a scene file or a colour file of a capture folder, relative to the
list's folder; blank lines and ``#`` comments skipped). A list is read line by line as the
frames are estimated: a million-frame list is never held in memory. A line that names no
usable frame is a :class:`BadInput`, that frame's error, never the run's.

Shards (``estimate.shard=K/N``, and one per rank under torchrun): every N-th frame of the
input's order from the K-th (folders: sorted by name; lists: the list's order), so N
processes cover the input exactly once.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from selfsup.scenes.capture import (COLOR_SUFFIXES, CaptureFrame, capture_frames, color_and_depth_frame,
                                    frame_of_color, is_capture_folder, read_input)
from selfsup.scenes.io import Scene, SceneFileError, read_scene

__all__ = ["SceneFile", "SceneInMemory", "BadInput", "Input", "scene_files", "estimate_inputs", "iter_inputs", "count_inputs",
           "read_item", "item_id", "parse_shard", "sharded", "LIST_SUFFIXES"]

LIST_SUFFIXES = (".txt", ".lst")


@dataclass(frozen=True)
class SceneFile:
    """A scene file of a folder of folders: its ``path`` and the ``prefix`` its id takes."""

    path: Path
    prefix: str = ""

    def __str__(self) -> str:
        return str(self.path)


@dataclass(frozen=True)
class BadInput:
    """A list line that names no usable frame: ``name`` (the line) and the ``reason``."""

    name: str
    reason: str

    def __str__(self) -> str:
        return self.name


@dataclass(frozen=True, eq=False)
class SceneInMemory:
    """A scene already in memory (a training pool's frame given to the estimator as its
    teacher): estimated like a scene file, its id ``scene.meta["id"]``, which names it
    (equal ids are one frame: worker processes return copies)."""

    scene: Scene

    def __str__(self) -> str:
        return self.scene.id

    def __eq__(self, other) -> bool:
        return isinstance(other, SceneInMemory) and other.scene.id == self.scene.id

    def __hash__(self) -> int:
        return hash(("SceneInMemory", self.scene.id))


Input = Path | CaptureFrame | SceneFile | SceneInMemory | BadInput  # str() of each names it


def scene_files(path: str | Path) -> list[Path]:
    """The ``.npz`` files of a directory (sorted), or the one file given."""
    path = Path(path)
    if path.is_dir():
        return sorted(p for p in path.glob("*.npz"))
    if path.exists():
        return [path]
    raise FileNotFoundError(f"estimate.input {path} does not exist")


def _holds_frames(path: Path) -> bool:
    return path.is_dir() and (is_capture_folder(path) or any(path.glob("*.npz")))


def iter_inputs(input: str | Path, depth: str | Path | None = None, depth_scale: float = 1000.0,
                intrinsics: tuple[float, float, float, float] | None = None, key: str = "estimate.input",
                nested: bool = False) -> Iterator[Input]:
    """The frames ``input`` names, in order (see the module's doc); ``nested``: a folder of
    folders is taken (else named in the error, as ``mode=track`` wants one sequence).
    ``key``: the setting the errors name. The checks that need no frame run before the
    first one is yielded.

    Raises:
        FileNotFoundError: nothing there, or nothing estimable in the directory.
        ValueError: a file that is neither a scene file, a colour image with its depth nor a list.
    """
    path = Path(input)
    if not path.exists():
        raise FileNotFoundError(f"{key} {path} does not exist")
    if depth is not None and not Path(depth).is_file():
        raise FileNotFoundError(f"estimate.depth {depth} does not exist")
    if path.is_file() and path.suffix.lower() in LIST_SUFFIXES:
        return _list_frames(path, depth_scale, intrinsics)
    if is_capture_folder(path):
        frames = capture_frames(path, depth_scale, intrinsics)
        if not frames:
            raise FileNotFoundError(f"no colour images ({', '.join(COLOR_SUFFIXES)}) in {path / 'color'}")
        return iter(frames)
    if path.is_file() and path.suffix.lower() in COLOR_SUFFIXES:
        if depth is None:
            raise ValueError(f"{key} {path} is a colour image: give its depth with estimate.depth=<file> "
                             "(16-bit millimetres, or .npy / .tif metres), or give the capture folder")
        return iter([color_and_depth_frame(path, depth, depth_scale, intrinsics)])
    if path.is_file() and path.suffix.lower() != ".npz":
        raise ValueError(f"{key} {path} is not a .npz scene file, a colour image ({', '.join(COLOR_SUFFIXES)}), "
                         f"a list of frames ({', '.join(LIST_SUFFIXES)}) or a capture folder (color/ and depth/)")
    files = scene_files(path)
    if files:
        return iter(files)
    folders = sorted(p for p in path.iterdir() if _holds_frames(p))
    if not folders:
        raise FileNotFoundError(f"no .npz scene files or capture folder (color/ and depth/) in {path}")
    if not nested:
        raise FileNotFoundError(f"no .npz scene files or capture folder (color/ and depth/) in {path} (its "
                                f"sub-folders {', '.join(p.name for p in folders)} hold some: give one of them)")
    return itertools.chain.from_iterable(_folder_frames(folder, depth_scale, intrinsics) for folder in folders)


def _folder_frames(folder: Path, depth_scale: float, intrinsics) -> list[Input]:
    # One sub-folder of a folder of folders, its ids prefixed with its name.
    prefix = f"{folder.name}/"
    if is_capture_folder(folder):
        return list(capture_frames(folder, depth_scale, intrinsics, prefix=prefix))
    return [SceneFile(path, prefix) for path in scene_files(folder)]


def _list_names(path: Path) -> Iterator[str]:
    # A list file's frame names, line by line: blank lines and ``#`` comments skipped.
    with path.open() as lines:
        for line in lines:
            name = line.strip()
            if name and not name.startswith("#"):
                yield name


def _list_frames(path: Path, depth_scale: float, intrinsics) -> Iterator[Input]:
    # The frames of a list file, line by line (``intrinsics``: overriding each capture frame's).
    for name in _list_names(path):
        frame = Path(name) if Path(name).is_absolute() else path.parent / name
        if frame.suffix.lower() == ".npz":
            yield frame if frame.is_file() else BadInput(name, f"{frame}: no such scene file")
        elif frame.suffix.lower() in COLOR_SUFFIXES:
            try:
                found = frame_of_color(frame, depth_scale)
            except SceneFileError as error:
                yield BadInput(name, error.reason)
            else:
                yield found if intrinsics is None else replace(found, intrinsics=tuple(map(float, intrinsics)))
        else:
            yield BadInput(name, f"not a .npz scene file or a colour image ({', '.join(COLOR_SUFFIXES)}) of a "
                                 "capture folder")


def count_inputs(input: str | Path, **kwargs) -> int:
    """How many frames :func:`iter_inputs` yields (``kwargs``: its own); a list file's
    lines are counted as they are read, no frame looked up."""
    path = Path(input)
    if path.is_file() and path.suffix.lower() in LIST_SUFFIXES:
        return sum(1 for _ in _list_names(path))
    return sum(1 for _ in iter_inputs(input, **kwargs))


def estimate_inputs(input: str | Path, depth: str | Path | None = None, depth_scale: float = 1000.0,
                    intrinsics: tuple[float, float, float, float] | None = None, key: str = "estimate.input",
                    nested: bool = False) -> list[Input]:
    """:func:`iter_inputs` as a list (a sequence's frames, a small job's)."""
    return list(iter_inputs(input, depth, depth_scale, intrinsics, key, nested))


def read_item(item: Input) -> Scene:
    """The scene of one input (:class:`BadInput`: its reason as a :class:`SceneFileError`)."""
    if isinstance(item, BadInput):
        raise SceneFileError(item.name, item.reason)
    if isinstance(item, SceneInMemory):
        return item.scene
    if isinstance(item, SceneFile):
        scene = read_scene(item.path)
        return replace(scene, meta={**scene.meta, "id": item.prefix + scene.id})
    return read_input(item)


def item_id(item: Input) -> str:
    """The id the record of ``item`` will carry, without reading its images: a capture
    frame's stem, a scene file's ``meta.id`` (its stem where it has none); a bad line's name."""
    if isinstance(item, CaptureFrame):
        return item.id
    if isinstance(item, (BadInput, SceneInMemory)):
        return str(item)
    path, prefix = (item.path, item.prefix) if isinstance(item, SceneFile) else (Path(item), "")
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"])) if "meta" in data.files else {}
    except (OSError, ValueError, KeyError):
        meta = {}  # unreadable: reading it names the problem
    return prefix + str(meta.get("id", path.stem) if isinstance(meta, dict) else path.stem)


def parse_shard(shard: str | None) -> tuple[int, int]:
    """``estimate.shard`` ``"K/N"`` as ``(K, N)`` with ``0 <= K < N``; None: ``(0, 1)``, everything."""
    if shard is None:
        return 0, 1
    try:
        index, count = (int(part) for part in str(shard).split("/"))
    except ValueError:
        raise ValueError(f"estimate.shard must be K/N (this process's part K of N, 0 <= K < N), got {shard!r}") from None
    if count < 1 or not 0 <= index < count:
        raise ValueError(f"estimate.shard={shard}: K/N needs N >= 1 and 0 <= K < N")
    return index, count


def sharded(items: Iterator[Input], index: int, count: int) -> Iterator[Input]:
    """Every ``count``-th of ``items`` from the ``index``-th (0-based)."""
    return itertools.islice(items, index, None, count)
