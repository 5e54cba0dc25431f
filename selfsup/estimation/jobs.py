"""Estimation jobs that never lose work: resumable JSON Lines outputs, torchrun ranks, merging.

An output is appended to one complete line at a time, so a kill at any moment leaves
every complete line a valid record. A rerun reads the ids already there
(:func:`completed_ids`, which cuts a torn last line off) and estimates the rest.

Under torchrun (``RANK`` / ``WORLD_SIZE`` in the environment, :func:`ranks_from_env`) each
rank writes its own part (:func:`part_path`), resumable like any output; once every rank
is through (a barrier of ``torch.distributed``), rank 0 merges the parts into the output in
the input's order (:func:`merge_parts`) and removes them.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import logging
import os
import shutil
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

__all__ = ["OutputInUseError", "locked", "read_records", "completed_ids", "resume_track", "Ranks", "ranks_from_env", "part_path",
           "parts_folder", "merge_parts", "barrier", "finish_ranks"]

log = logging.getLogger(__name__)


class OutputInUseError(RuntimeError):
    """Another process is writing this output (or part) now."""


@contextlib.contextmanager
def locked(path: Path) -> Iterator[TextIO]:
    """``path`` opened for appending under an exclusive lock, held while the block runs: a
    second run on the same output (a rank of a killed torchrun job still running, a
    command started twice) would write its frames twice. The OS drops the lock with its
    process, however it ends. No lock where the OS has no ``flock`` (Windows).

    Raises:
        OutputInUseError: another process holds the lock.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a") as out:
        try:
            import fcntl
        except ImportError:  # not POSIX
            yield out
            return
        try:
            fcntl.flock(out.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise OutputInUseError(f"{path} is being written by another process (a run started twice, or a rank of "
                                   "a killed torchrun job still running): wait for it or stop it") from None
        yield out


def _records(path: Path) -> Iterator[tuple[int, dict]]:
    # (bytes before it, record) of each record of the JSON Lines file ``path`` (none where it
    # does not exist). A last line without its newline, or not a JSON object with an id (a
    # kill mid-write), is cut off the file once the records are read; such a line before the
    # last is refused (ValueError): the file is not an output of ours, or was edited.
    if not path.exists():
        return
    good_bytes = 0
    with path.open("rb") as lines:
        for number, line in enumerate(lines, 1):
            record = _record(line) if line.endswith(b"\n") else None
            if record is None:
                if lines.read(1):  # not the last line
                    raise ValueError(f"{path} line {number} is not a record of ours: give another output, or start "
                                     "over with estimate.overwrite=true")
                log.warning("%s: its last line was cut off mid-write (a killed run): redoing that frame", path)
                break
            yield good_bytes, record
            good_bytes += len(line)
    if good_bytes < path.stat().st_size:
        os.truncate(path, good_bytes)


def read_records(path: Path) -> Iterator[dict]:
    """The records of the JSON Lines file ``path`` (none where it does not exist), a torn
    last line (a kill mid-write) cut off the file; a bad line before the last is refused
    (ValueError), as :func:`completed_ids` says."""
    return (record for _, record in _records(path))


def completed_ids(path: Path) -> set[str]:
    """The ids of the records in the JSON Lines file ``path`` (none where it does not exist).

    A last line without its newline, or not a JSON object with an ``id`` (a kill mid-write),
    is cut off the file and its frame redone.

    Raises:
        ValueError: a line before the last that is not a record: the file is not an output
            of ours (or was edited), and appending to it would mix the two.
    """
    return {str(record["id"]) for record in read_records(path)}


def resume_track(path: Path) -> set[str]:
    """Where a tracked sequence's rerun starts: the ids of the records of ``path`` before its
    last full estimate (the tracker's state is not in the file, so it is redone from a frame
    that needs none); the file is cut there. A torn last line counts as no record.

    Raises:
        ValueError: a line before the last that is not a record of ours (as :func:`completed_ids`).
    """
    ids: list[str] = []
    last_full = (0, 0)  # (records before it, bytes before it) of the last full estimate
    for offset, record in _records(path):
        if record.get("full"):
            last_full = (len(ids), offset)
        ids.append(str(record["id"]))
    before, cut = last_full
    if path.exists():
        os.truncate(path, cut)
    return set(ids[:before])


def _record(line: bytes) -> dict | None:
    # One JSON Lines record (an object with an id), or None where the line is no record.
    try:
        record = json.loads(line)
    except ValueError:
        return None
    return record if isinstance(record, dict) and "id" in record else None


def _record_id(line: bytes) -> str | None:
    # The id of one JSON Lines record, or None where the line is no record.
    record = _record(line)
    return None if record is None else str(record["id"])


@dataclass(frozen=True)
class Ranks:
    """This process's place among torchrun's: ``rank`` of ``world``, ``local_rank`` of
    ``local_world`` on this machine."""

    rank: int
    world: int
    local_rank: int
    local_world: int


def ranks_from_env() -> Ranks | None:
    """The torchrun ranks of this process, or None outside torchrun (or a world of one)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return None
    rank = int(os.environ["RANK"])
    return Ranks(rank, world, int(os.environ.get("LOCAL_RANK", rank)), int(os.environ.get("LOCAL_WORLD_SIZE", world)))


def parts_folder(output: Path) -> Path:
    """Where the ranks of a job writing ``output`` keep their parts."""
    return output.parent / f"{output.name}.parts"


def part_path(output: Path, ranks: Ranks) -> Path:
    """The part of ``output`` that rank ``ranks.rank`` writes."""
    return parts_folder(output) / f"rank{ranks.rank:05d}-of-{ranks.world:05d}.jsonl"


# The ranks wait for the slowest at the end: as long as a dataset takes.
BARRIER_TIMEOUT = datetime.timedelta(days=7)


def barrier(ranks: Ranks) -> None:
    """Wait until every rank is here (torch.distributed's gloo group, joined on first use)."""
    import torch.distributed as dist

    if not dist.is_initialized():
        dist.init_process_group("gloo", rank=ranks.rank, world_size=ranks.world, timeout=BARRIER_TIMEOUT)
    dist.barrier()


def finish_ranks() -> None:
    """Leave the process group :func:`barrier` joined (if it did)."""
    import torch.distributed as dist

    if dist.is_initialized():
        dist.destroy_process_group()


class _Lines:
    # A JSON Lines file read one record at a time, its head's id at hand.
    def __init__(self, path: Path):
        self.file = path.open("rb") if path.exists() else None
        self.head: bytes | None = None
        self.head_id: str | None = None
        self.advance()

    def advance(self) -> None:
        self.head = self.file.readline() if self.file is not None else b""
        self.head_id = _record_id(self.head) if self.head else None
        if not self.head and self.file is not None:
            self.file.close()

    def rest(self) -> Iterator[bytes]:
        while self.head:
            yield self.head
            self.advance()


def merge_parts(output: Path, parts: list[Path], order: Iterable[tuple[str, int]], keep_output: bool = True) -> int:
    """Merge the rank ``parts`` into ``output`` in the input's order; returns the records written.

    ``order``: ``(id, rank)`` of every frame of the job in the input's order, the rank whose
    part holds it; each part holds its frames in that order (a frame that failed is absent).
    ``keep_output``: the records ``output`` holds already (a job resumed after an earlier
    merge, or after a run of one process) come first where the order meets them. Records
    the order does not meet (an input changed between runs) are kept at the end, never
    dropped. Written to a temporary file that replaces ``output`` at once.
    """
    earlier = _Lines(output) if keep_output else _Lines(output.with_name(output.name + ".absent"))
    readers = [_Lines(path) for path in parts]
    temporary = output.with_name(output.name + ".merging")
    written = 0
    with temporary.open("wb") as out:
        for frame_id, rank in order:
            for reader in (earlier, readers[rank]):
                if reader.head_id == frame_id:
                    out.write(reader.head)
                    reader.advance()
                    written += 1
                    break
        for reader in (earlier, *readers):
            for line in reader.rest():
                log.warning("merge: %s is not where the input's order puts it; kept at the end", _record_id(line))
                out.write(line)
                written += 1
    os.replace(temporary, output)
    shutil.rmtree(parts_folder(output), ignore_errors=True)
    return written
