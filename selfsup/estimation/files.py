"""Scene files in, JSON Lines out: reading, batching by size, the worker pool, failures kept per file.

:func:`estimate_files` is ``mode=estimate``: every file is read, files that can share
a batch are estimated together (:func:`selfsup.estimation.stages.estimate_batch`),
batches are spread over worker processes, and a file that fails is named with its
reason while the others are written.
"""

from __future__ import annotations

import collections
import contextlib
import itertools
import json
import logging
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from collections.abc import Iterator
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import torch

from selfsup.estimation.network import cached_network, checkpoints_of
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.prepare import in_file_units, prepare, within_pixels, working_range
from selfsup.estimation.records import records
from selfsup.estimation.stages import estimate_batch
from selfsup.estimation.inputs import (Input, count_inputs, estimate_inputs, item_id, iter_inputs, parse_shard,
                                       read_item, scene_files, sharded)
from selfsup.estimation.jobs import (Ranks, barrier, completed_ids, finish_ranks, locked, merge_parts, part_path,
                                     parts_folder, ranks_from_env)
from selfsup.scenes.io import Scene, SceneFileError

__all__ = ["estimate_files", "estimate_inputs", "scene_files", "worker_count", "usable_cores", "start_method",
           "failure_reason", "record_line", "progress_bar", "resolve_device", "worker_threads", "estimate_items"]

log = logging.getLogger(__name__)


def _signature(scene: Scene) -> tuple:
    # Scenes that can share a batch: one image size, the same optional fields, one falloff.
    return (tuple(scene.image.shape), scene.ks is None, scene.normals is None, scene.ambient is None,
            tuple(scene.shininess.shape), scene.falloff)


def _estimate_group(group: list[tuple[Input, Scene]], options: EstimateOptions, device: torch.device,
                    read_seconds: dict[Input, float] | None = None) -> tuple[dict[Input, dict], dict[Input, str]]:
    # Records and failure reasons of scenes that can share a batch. ``seconds``: the scene's
    # reading (read_seconds) and its estimate, its own where it was alone (batch_size 1),
    # else its share of the batch's time. A batch that fails is retried scene by scene, so
    # one bad scene never costs the others.
    read_seconds = read_seconds or {}
    started = time.perf_counter()
    try:
        with torch.no_grad():
            scaled = [working_range(scene) for _, scene in group]
            problem = prepare([scene for scene, _ in scaled], options, device)
            out = [in_file_units(record, factor) for record, (_, factor) in
                   zip(records([scene.id for scene, _ in scaled], problem, estimate_batch(problem, options), options),
                       scaled)]
    except Exception as error:  # noqa: BLE001 -- whatever a frame raises is that frame's error, never the run's
        if len(group) > 1:
            done: dict[Input, dict] = {}
            failed: dict[Input, str] = {}
            for item in group:
                one_done, one_failed = _estimate_group([item], options, device, read_seconds)
                done.update(one_done)
                failed.update(one_failed)
            return done, failed
        return {}, {group[0][0]: failure_reason(error)}
    share = (time.perf_counter() - started) / len(group)
    return {path: {**record, "seconds": round(share + read_seconds.get(path, 0.0), 4), "batch_size": len(group)}
            for (path, _), record in zip(group, out)}, {}


# Frames a batch holds on an accelerator with ``estimate.batch=auto`` (on the CPU: 1, each
# frame its own time; two forked workers of one frame each were within 5% of batches of 4,
# benchmarks/results/estimation_measurements.md, "Many files").
ACCELERATOR_BATCH = 256


def batch_size(batch: int | str, device: torch.device) -> int:
    """Frames estimated together: ``batch`` as given (>= 1), or for ``auto`` 1 on the CPU
    and :data:`ACCELERATOR_BATCH` on an accelerator."""
    if batch == "auto":
        return 1 if device.type == "cpu" else ACCELERATOR_BATCH
    if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
        raise ValueError(f"estimate.batch must be 'auto' or an integer >= 1, got {batch!r}")
    return batch


def failure_reason(error: Exception) -> str:
    """The one-line reason a file failed: a :class:`SceneFileError`'s own, else the error's type and message."""
    return error.reason if isinstance(error, SceneFileError) else f"{type(error).__name__}: {error}"


def record_line(record: dict) -> str:
    """``record`` as one line of strict JSON. Raises ValueError naming a non-finite number
    (NaN or inf), which one line would carry into every strict reader's failure."""
    try:
        return json.dumps(record, allow_nan=False)
    except ValueError:
        raise ValueError("its estimate holds a non-finite number (NaN or inf), which JSON cannot carry") from None


def progress_bar(total: int, desc: str, unit: str, enabled: bool):
    """``(bar, printing)``: a tqdm bar (None without tqdm, which is optional) and the context
    under which log lines are printed above it, not into its line."""
    try:
        from tqdm import tqdm
        from tqdm.contrib.logging import logging_redirect_tqdm
    except ImportError:
        return None, contextlib.nullcontext()
    return (tqdm(total=total, desc=desc, unit=unit, disable=not enabled),
            logging_redirect_tqdm() if enabled else contextlib.nullcontext())


def resolve_device(name: str) -> torch.device:
    """``cpu``, ``cuda[:i]`` or ``auto`` (CUDA when there is one) as a device; CUDA asked
    for where there is none is an error."""
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


def _estimate_chunk(chunk: list[Input], options: EstimateOptions, device: torch.device
                    ) -> tuple[dict[Input, dict], dict[Input, str]]:
    # Records and failure reasons of consecutive files: read, grouped by what can share a
    # batch, estimated group by group. Runs in this process or in a worker.
    groups: dict[tuple, list[tuple[Input, Scene]]] = {}
    done: dict[Input, dict] = {}
    reasons: dict[Input, str] = {}
    read_seconds: dict[Input, float] = {}
    for path in chunk:
        started = time.perf_counter()
        try:
            scene = within_pixels(read_item(path), options)
        except Exception as error:  # noqa: BLE001 -- a frame that cannot be read is named, the others go on
            reasons[path] = failure_reason(error)
            continue
        read_seconds[path] = time.perf_counter() - started
        groups.setdefault(_signature(scene), []).append((path, scene))
    for group in groups.values():
        group_done, group_failed = _estimate_group(group, options, device, read_seconds)
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


# Chunks queued per worker process ahead of the one written: enough to keep each busy,
# few enough that a million-frame input is never queued whole.
CHUNKS_AHEAD = 2


def _chunk_results(chunks: Iterator[list[Input]], options: EstimateOptions, device: torch.device, workers: int):
    # (chunk, done, reasons) of every chunk, in the chunks' order. With workers > 1 the
    # chunks run in that many processes (forked or spawned: start_method), at most
    # CHUNKS_AHEAD a worker queued at a time; a chunk whose worker died (out of memory,
    # killed) is estimated again in this process, so no file is lost with it.
    if workers == 1:
        for chunk in chunks:
            yield (chunk, *_estimate_chunk(chunk, options, device))
        return
    threads = worker_threads(workers)
    context = multiprocessing.get_context(start_method(threads, device))
    queued: collections.deque = collections.deque()
    with ProcessPoolExecutor(workers, mp_context=context, initializer=_worker_start, initargs=(threads,)) as pool:
        try:
            for chunk in itertools.chain(chunks, [None]):
                if chunk is not None:
                    queued.append((chunk, pool.submit(_estimate_chunk, chunk, options, device)))
                while queued and (chunk is None or len(queued) >= CHUNKS_AHEAD * workers):
                    first, future = queued.popleft()
                    try:
                        done, reasons = future.result()
                    except BrokenProcessPool as error:
                        log.warning("a worker stopped (%s); estimating %s here", error, ", ".join(map(str, first)))
                        done, reasons = _estimate_chunk(first, options, device)
                    yield first, done, reasons
        finally:
            # Stopped early (Ctrl-C, a failed write): the pool's exit would otherwise
            # wait for every queued chunk to be estimated.
            for _, future in queued:
                future.cancel()


def _batches(items: Iterator[Input], size: int) -> Iterator[list[Input]]:
    # Consecutive items, ``size`` at a time.
    while batch := list(itertools.islice(items, size)):
        yield batch


def estimate_items(items: list[Input], options: EstimateOptions, device: str = "cpu", workers: int | str = "auto",
                   batch: int | str = 1) -> Iterator[tuple[Input, dict | None, str | None]]:
    """``(item, record, None)`` or ``(item, None, reason)`` of each of ``items`` in order,
    estimated as :func:`estimate_files` estimates files (batched, over worker processes)
    but kept in memory: for callers that go on with the records (``mode=scan``)."""
    where = resolve_device(device)
    batch = batch_size(batch, where)
    workers = min(worker_count(workers, len(items), where), max(1, -(-len(items) // batch)))
    if options.method in ("cnn", "cnn+refine"):
        for path in checkpoints_of(options):
            cached_network(path, str(where))  # loaded before the workers fork
    for chunk, done, reasons in _chunk_results(_batches(iter(items), batch), options, where, workers):
        for item in chunk:
            yield item, done.get(item), reasons.get(item)


def _write_records(chunks, out, bar, failed: dict[str, str], seconds: list[float]) -> None:
    # Each chunk's records in its frames' order, one complete line at a time; failures named.
    for chunk, done, reasons in chunks:
        for item in chunk:
            if item in reasons:
                failed[str(item)] = reasons[item]
                log.error("skipped %s: %s", item, reasons[item])
            elif item in done:
                try:
                    line = record_line(done[item])
                except ValueError as error:
                    failed[str(item)] = str(error)
                    log.error("skipped %s: %s", item, failed[str(item)])
                    continue
                seconds.append(done[item]["seconds"])
                out.write(line + "\n")
        out.flush()
        if bar is not None:
            bar.update(len(chunk))


def _estimate_pending(out, done_ids: set[str], frames: dict, shard: tuple[int, int], total: int,
                      options: EstimateOptions, where: torch.device, batch: int, workers: int | str,
                      progress: bool) -> dict:
    # The frames of the shard not in ``done_ids`` estimated and appended to ``out``: the
    # counts the summary reports (skipped, failed with reasons, seconds, workers).
    index, count = shard
    workers = min(worker_count(workers, max(total, 1), where), max(1, -(-total // batch)))
    failed: dict[str, str] = {}
    seconds: list[float] = []
    bar, printing = progress_bar(total, "estimate", "scene", progress)
    skipped = 0

    def pending() -> Iterator[Input]:
        # The shard's frames whose ids are not done, the done ones counted as they pass.
        nonlocal skipped
        for item in sharded(iter_inputs(**frames), index, count):
            if done_ids and item_id(item) in done_ids:
                skipped += 1
                if bar is not None:
                    bar.update(1)
            else:
                yield item

    with printing:
        _write_records(_chunk_results(_batches(pending(), batch), options, where, workers), out, bar, failed, seconds)
    if bar is not None:
        bar.close()
    if skipped:
        log.info("%d frame(s) already in %s: skipped (estimate.overwrite=true starts over)", skipped, out.name)
    return {"skipped": skipped, "failed": failed, "seconds": seconds, "workers": workers}


def estimate_files(input: str | Path, output: str | Path, options: EstimateOptions, progress: bool = True,
                   batch: int | str = 1, device: str = "cpu", workers: int | str = 1, depth: str | Path | None = None,
                   depth_scale: float = 1000.0, intrinsics: tuple[float, float, float, float] | None = None,
                   overwrite: bool = False, shard: str | None = None) -> dict:
    """Estimate every frame under ``input``; one JSON line per good one in ``output``.

    ``input``: a capture folder, a folder of them, a list file of frames, a colour image with
    its ``depth`` file, a directory of ``.npz`` scene files or one
    (:mod:`selfsup.estimation.inputs`); ``depth_scale``: a 16-bit depth image's units per
    metre; ``intrinsics``: ``(fx, fy, cx, cy)`` overriding a capture's files. A bad frame is
    logged with its name and reason and skipped; the summary returned counts ``done``,
    ``failed`` (with reasons), ``skipped`` (already in ``output``), the median seconds per
    frame, the wall time of the whole run, the workers used and how they started (``start``:
    :func:`start_method`, None for this process alone).

    ``output`` is never overwritten unless ``overwrite``: a rerun appends the frames whose ids
    are not in it yet (:func:`selfsup.estimation.jobs.completed_ids`). ``shard`` ``"K/N"``:
    every N-th frame from the K-th only. Under torchrun each rank takes its shard of that,
    writes its own part and rank 0 merges the parts into ``output`` in the input's order
    (:mod:`selfsup.estimation.jobs`; one rank per accelerator, ``workers`` 1).

    ``batch`` > 1 estimates up to that many consecutive files together
    (:func:`estimate_batch`; files of one size and the same fields share a batch; ``auto``:
    :func:`batch_size`), each record's ``seconds`` being its reading and its share of the
    batch's time (its own time where ``batch_size`` is 1); a failing batch is retried file
    by file. ``device``: ``cpu``, ``cuda`` or ``auto``. ``workers``: processes the batches
    are spread over (:func:`worker_count`; ``auto``: one per core on the CPU, started as
    :func:`start_method` says); a record's ``seconds`` is then the time in its worker, and
    the run's time per frame is ``wall_seconds / done``. Records are written in the
    frames' order whatever the workers.
    """
    started = time.perf_counter()
    ranks = ranks_from_env()
    where = _rank_device(resolve_device(device), ranks)
    batch = batch_size(batch, where)
    index, count = parse_shard(shard)
    if ranks is not None:  # each rank a shard of the shard
        index, count = index + count * ranks.rank, count * ranks.world
        workers = 1
        torch.set_num_threads(max(1, usable_cores() // ranks.local_world))
    frames = dict(input=input, depth=depth, depth_scale=depth_scale, intrinsics=intrinsics, nested=True)
    total = len(range(index, count_inputs(**frames), count))
    if options.method in ("cnn", "cnn+refine"):
        for path in checkpoints_of(options):
            cached_network(path, str(where))  # a missing or bad checkpoint stops here, before any file
    output = Path(output)
    target = output if ranks is None else part_path(output, ranks)
    if ranks is None and not overwrite and parts_folder(output).exists():
        log.warning("%s holds the parts of an unfinished torchrun job: rerun that job to merge them",
                    parts_folder(output))
    with locked(target) as out:
        if overwrite:
            out.truncate(0)
        done_ids = set() if overwrite else completed_ids(target) | (completed_ids(output) if ranks else set())
        summary = _estimate_pending(out, done_ids, frames, (index, count), total, options, where, batch, workers,
                                    progress)
    skipped, failed, seconds, workers = (summary[k] for k in ("skipped", "failed", "seconds", "workers"))
    written = len(done_ids) + len(seconds)
    if ranks is not None:
        written = _merge_ranks(output, ranks, frames, shard, overwrite, written)
    elif not written:  # every file failed: no empty output left behind to be taken for a result
        output.unlink(missing_ok=True)
    wall = time.perf_counter() - started
    summary = {"done": len(seconds), "failed": len(failed), "failures": failed, "skipped": skipped,
               "median_seconds": sorted(seconds)[len(seconds) // 2] if seconds else None,
               "wall_seconds": round(wall, 3), "workers": workers,
               "start": start_method(worker_threads(workers), where) if workers > 1 else None,
               "output": str(output) if written else None}
    log.info("estimated %d scene(s), %d failed, %d skipped, in %.1f s (%d worker(s), %.3f s per file; median %.3f s "
             "each); %s", summary["done"], summary["failed"], skipped, wall, workers,
             wall / max(len(seconds) + len(failed), 1), summary["median_seconds"] or 0.0,
             f"{output} holds {written} record(s)" if written else "wrote nothing")
    return summary


def _rank_device(device: torch.device, ranks: Ranks | None) -> torch.device:
    # One accelerator a rank (its local rank's), the CPU shared.
    if ranks is None or device.type != "cuda":
        return device
    return torch.device("cuda", ranks.local_rank % torch.cuda.device_count())


def _merge_ranks(output: Path, ranks: Ranks, frames: dict, shard: str | None, overwrite: bool, written: int) -> int:
    # Every rank waits for the others; rank 0 merges their parts into ``output`` (the
    # records it holds already kept unless ``overwrite``). Returns the records in ``output``
    # (rank 0; the others: ``written``, their own).
    barrier(ranks)
    if ranks.rank == 0:
        index, count = parse_shard(shard)
        parts = [part_path(output, Ranks(rank, ranks.world, 0, 1)) for rank in range(ranks.world)]
        positions = sharded(iter_inputs(**frames), index, count)
        order = ((item_id(item), position % ranks.world) for position, item in enumerate(positions))
        with locked(output):  # no single process appending to it meanwhile
            written = merge_parts(output, parts, order, keep_output=not overwrite)
        log.info("merged the parts of %d ranks into %s", ranks.world, output)
    barrier(ranks)
    finish_ranks()
    return written
