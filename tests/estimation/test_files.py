"""Scene files in, JSON Lines out: bad files, batches, workers, the benchmarks that drive the command."""

import dataclasses
import json


import sys
import numpy as np
import pytest
import torch
from selfsup.estimation.options import EstimateOptions, Tuning, RefineOptions

from selfsup.estimation.inputs import estimate_inputs
from selfsup.estimation.files import estimate_files








from selfsup.scenes.io import write_scene


from estimation_helpers import SMALL, _scene, _written


def test_missing_checkpoint_stops_before_any_file(tmp_path):
    write_scene(tmp_path / "a.npz", _scene(6))
    options = EstimateOptions(method="cnn+refine", checkpoint=str(tmp_path / "none.pt"))
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        estimate_files(tmp_path, tmp_path / "out.jsonl", options, progress=False)
    assert not (tmp_path / "out.jsonl").exists()


def test_estimate_files_writes_jsonl_and_skips_bad_files(tmp_path):
    good = _scene(6)
    write_scene(tmp_path / "a_good.npz", good)
    np.savez(tmp_path / "b_missing.npz", image=np.zeros((4, 4, 3), np.float32))
    arrays = dict(np.load(tmp_path / "a_good.npz"))
    for name, change in {
        "c_nan": lambda a: a["image"].__setitem__((0, 0, 0), np.nan),
        "d_empty": lambda a: a["depth"].__setitem__(slice(None), 0),
        "e_shape": lambda a: a.__setitem__("kd", a["kd"][:, :-1]),
    }.items():
        bad = {k: v.copy() for k, v in arrays.items()}
        change(bad)
        np.savez(tmp_path / f"{name}.npz", **bad)
    options = EstimateOptions(max_lights=1, tuning=Tuning(refine=RefineOptions(max_iters=(10, 3))))
    summary = estimate_files(tmp_path, tmp_path / "out" / "lights.jsonl", options, progress=False)
    assert summary["done"] == 1 and summary["failed"] == 4
    reasons = " ".join(summary["failures"].values())
    for word in ("missing", "non-finite", "empty valid mask", "kd must have shape"):
        assert word in reasons
    record = json.loads((tmp_path / "out" / "lights.jsonl").read_text().splitlines()[0])
    assert set(record) >= {"id", "lights", "ambient", "seconds"}
    assert set(record["lights"][0]) >= {"position", "intensity", "position_std"}


def test_a_record_with_a_non_finite_number_fails_its_file_not_the_output(tmp_path, monkeypatch):
    # Python writes NaN as a bare NaN, which no strict JSON reader accepts: one such line
    # would cost every line of the file. Such a record fails its own file, named.
    import selfsup.estimation.files

    for name, seed in (("a.npz", 6), ("b.npz", 7)):
        write_scene(tmp_path / name, _scene(seed))
    records = selfsup.estimation.files.records

    def with_a_nan(ids, *args, **kwargs):
        out = records(ids, *args, **kwargs)
        for record in out:
            if record["id"] == _scene(7).id:
                record["lights"][0]["position_std"][0] = float("nan")
        return out

    monkeypatch.setattr(selfsup.estimation.files, "records", with_a_nan)
    options = EstimateOptions(max_lights=1, tuning=Tuning(refine=RefineOptions(max_iters=(10, 3))))
    summary = estimate_files(tmp_path, tmp_path / "lights.jsonl", options, progress=False)
    assert summary["done"] == 1 and summary["failed"] == 1
    assert "non-finite" in summary["failures"][str(tmp_path / "b.npz")]
    lines = (tmp_path / "lights.jsonl").read_text().splitlines()
    assert len(lines) == 1 and json.loads(lines[0], parse_constant=lambda c: pytest.fail(c))["id"] == _scene(6).id


def test_a_folder_of_folders_is_estimated_with_ids_that_name_the_sub_folder(tmp_path):
    # The devset's root holds direct/, gi/ and noisy/: every sub-folder's frames, each id
    # prefixed with its folder (two folders may hold a.npz); a folder without frames is none.
    for folder in ("gi", "empty", "noisy"):
        (tmp_path / folder).mkdir()
    tiny = dataclasses.replace(SMALL, height=24, width=32)
    write_scene(tmp_path / "gi" / "a.npz", _scene(6, config=tiny))
    write_scene(tmp_path / "noisy" / "a.npz", _scene(7, config=tiny))
    summary = estimate_files(tmp_path, tmp_path / "o.jsonl", EstimateOptions(method="refine", max_lights=1),
                             progress=False)
    ids = [json.loads(line)["id"] for line in (tmp_path / "o.jsonl").read_text().splitlines()]
    assert summary["done"] == 2 and ids == [f"gi/{_scene(6, config=tiny).id}", f"noisy/{_scene(7, config=tiny).id}"]
    # mode=track wants one sequence: it names the sub-folders instead.
    with pytest.raises(FileNotFoundError, match=r"\(its sub-folders gi, noisy hold some: give one of them\)"):
        estimate_inputs(tmp_path, key="track.input")


def test_estimate_command_exits_non_zero_when_a_file_fails(tmp_path):
    import subprocess
    import sys

    write_scene(tmp_path / "good.npz", _scene(7, config=dataclasses.replace(SMALL, height=24, width=32)))
    np.savez(tmp_path / "bad.npz", image=np.zeros((4, 4, 3), np.float32))
    result = subprocess.run([sys.executable, "train.py", "mode=estimate", f"estimate.input={tmp_path}",
                             f"estimate.output={tmp_path}/o.jsonl", "estimate.max_lights=1", "estimate.progress=false",
                             "+estimate.tuning.refine.max_iters=[5,2]", f"hydra.run.dir={tmp_path}/run"],
                            capture_output=True, text=True, cwd=str(__import__("pathlib").Path(__file__).parents[2]))
    assert result.returncode == 1, result.stderr[-2000:]
    log = result.stdout + result.stderr
    assert "bad.npz" in log and "missing key" in log
    assert len((tmp_path / "o.jsonl").read_text().splitlines()) == 1


def test_throughput_benchmark_scores_a_batch_end_to_end():
    from benchmarks.estimate_throughput import run

    rows, path = run(scenes=2, batches=(2,), device="cpu", sets=("true reflectance, 1 light",), write=False,
                     options=EstimateOptions(tuning=Tuning(refine=RefineOptions(max_iters=(15, 5)))))
    assert path is None and len(rows) == 1
    row = rows[0]
    assert row["scenes"] == 2 and row["scenes_per_s"] > 0 and row["success_rate"] == 1.0
    assert abs(row["inputs_share"] + row["estimate_share"] + row["records_share"] - 1) < 0.05


def test_files_speed_benchmark_times_the_command_on_a_directory():
    from benchmarks.estimate_files_speed import run

    rows, path = run(scenes=2, workers=(1,), batches=(2,), sets=("true reflectance, 1 light",), rounds=1, write=False,
                     options=EstimateOptions(tuning=Tuning(refine=RefineOptions(max_iters=(15, 5)))))
    assert path is None and len(rows) == 1
    row = rows[0]
    assert row["scenes"] == 2 and row["workers"] == 1 and row["seconds_per_scene"] > 0 and row["success_rate"] == 1.0


def test_large_images_benchmark_compares_every_pixel_with_the_subsample():
    from benchmarks.large_images import run

    rows = run(1, 48, 64, 777, max_pixels=768)
    assert [r["id"] for r in rows][1::2] == ["all (median, count)"] * 2
    for row in rows:
        assert row["stride"] == 2 and row["found_all"] == row["found_default"] == 1
        assert row["answers_apart"] < 0.05 and row["seconds_all"] > 0 and row["seconds_default"] > 0


def test_batched_files_match_single_files_and_a_bad_one_costs_no_other(tmp_path):
    config = dataclasses.replace(SMALL, height=24, width=32)
    for seed in (6, 7):
        write_scene(tmp_path / f"good_{seed}.npz", _scene(seed, config=config))
    # Readable, but every pixel clipped (left out): it fails inside the batch's
    # preparation, which is then retried file by file.
    arrays = dict(np.load(tmp_path / "good_6.npz"))
    arrays["image"] = np.ones_like(arrays["image"])
    np.savez(tmp_path / "clipped.npz", **arrays)
    options = EstimateOptions(max_lights=1, tuning=Tuning(refine=RefineOptions(max_iters=(10, 3))))
    single = estimate_files(tmp_path, tmp_path / "one.jsonl", options, progress=False)
    batched = estimate_files(tmp_path, tmp_path / "four.jsonl", options, progress=False, batch=4)
    assert single["done"] == batched["done"] == 2 and list(batched["failures"]) == [str(tmp_path / "clipped.npz")]
    assert "no valid pixel" in batched["failures"][str(tmp_path / "clipped.npz")]
    one, four = ([json.loads(line) for line in (tmp_path / name).read_text().splitlines()] for name in ("one.jsonl", "four.jsonl"))
    assert [r["id"] for r in one] == [r["id"] for r in four]
    for a, b in zip(one, four):
        assert np.allclose(a["lights"][0]["position"], b["lights"][0]["position"], atol=1e-3)
    with pytest.raises(ValueError, match="estimate.batch must be .auto. or an integer >= 1"):
        estimate_files(tmp_path, tmp_path / "x.jsonl", options, progress=False, batch=0)


def test_files_with_one_shininess_for_every_pixel_are_estimated(tmp_path):
    # shininess of shape () (the format allows it) alone and in a batch of two.
    config = dataclasses.replace(SMALL, height=24, width=32)
    for seed in (6, 7):
        arrays = dict(np.load(_written(tmp_path, seed, config)))
        arrays["shininess"] = np.array(30.0, np.float32)
        np.savez(tmp_path / f"scene_{seed}.npz", **arrays)
    options = EstimateOptions(max_lights=1, tuning=Tuning(refine=RefineOptions(max_iters=(10, 3))))
    for batch in (1, 2):
        summary = estimate_files(tmp_path, tmp_path / f"out_{batch}.jsonl", options, progress=False, batch=batch)
        assert summary["done"] == 2 and not summary["failures"]


def test_files_without_normals_or_light_are_handled_as_the_format_says(tmp_path):
    # All-zero normals are missing ones: estimated from the depth, as for a file without
    # the key (they were masked out, and such a file had no valid pixel left). A black
    # image has no light to estimate: named, not a crash or a clipped-pixel complaint.
    config = dataclasses.replace(SMALL, height=24, width=32)
    arrays = dict(np.load(_written(tmp_path, 6, config)))
    np.savez(tmp_path / "a_given.npz", **arrays)
    np.savez(tmp_path / "b_no_key.npz", **{k: v for k, v in arrays.items() if k != "normals"})
    np.savez(tmp_path / "c_zero.npz", **{**arrays, "normals": np.zeros_like(arrays["normals"])})
    np.savez(tmp_path / "d_black.npz", **{**arrays, "image": np.zeros_like(arrays["image"])})
    options = EstimateOptions(max_lights=1, tuning=Tuning(refine=RefineOptions(max_iters=(10, 3))))
    summary = estimate_files(tmp_path, tmp_path / "out.jsonl", options, progress=False)
    assert summary["done"] == 3 and list(summary["failures"]) == [str(tmp_path / "d_black.npz")]
    assert "zero on every valid pixel" in summary["failures"][str(tmp_path / "d_black.npz")]
    given, no_key, zero = (json.loads(line) for line in (tmp_path / "out.jsonl").read_text().splitlines())
    assert zero["lights"][0]["position"] == no_key["lights"][0]["position"]
    assert np.linalg.norm(np.subtract(zero["lights"][0]["position"], given["lights"][0]["position"])) < 0.05


@pytest.mark.parametrize("method", [
    "spawn",
    pytest.param("fork", marks=pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forked workers: Linux only")),
])
def test_worker_processes_write_what_one_process_writes_in_the_files_order(tmp_path, method, monkeypatch):
    import selfsup.estimation.files as estimate_module

    monkeypatch.setattr(estimate_module, "start_method", lambda threads, device: method)
    config = dataclasses.replace(SMALL, height=24, width=32)
    for seed in (6, 7, 8):
        write_scene(tmp_path / f"good_{seed}.npz", _scene(seed, config=config))
    np.savez(tmp_path / "good_7_missing.npz", image=np.zeros((4, 4, 3), np.float32))
    options = EstimateOptions(max_lights=1, tuning=Tuning(refine=RefineOptions(max_iters=(10, 3))))
    alone = estimate_files(tmp_path, tmp_path / "one.jsonl", options, progress=False, workers=1)
    spread = estimate_files(tmp_path, tmp_path / "two.jsonl", options, progress=False, workers=2)
    assert spread["workers"] == 2 and alone["workers"] == 1 and spread["start"] == method and alone["start"] is None
    assert alone["done"] == spread["done"] == 3 and list(spread["failures"]) == [str(tmp_path / "good_7_missing.npz")]
    one, two = ([json.loads(line) for line in (tmp_path / name).read_text().splitlines()] for name in ("one.jsonl", "two.jsonl"))
    assert [r["id"] for r in two] == [r["id"] for r in one] == ["procedural_6", "procedural_7", "procedural_8"]
    for a, b in zip(one, two):
        assert np.allclose(a["lights"][0]["position"], b["lights"][0]["position"], atol=1e-3)
    assert spread["wall_seconds"] > 0


class _FakePool:
    """Stands in for ``ProcessPoolExecutor`` (constructed like it, a context manager):
    ``answer(index, future, fn, args)`` settles, or leaves pending, each submitted future."""

    def __init__(self, answer):
        self.answer = answer
        self.futures = []

    def __call__(self, *args, **kwargs):
        return self

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def submit(self, fn, *args):
        from concurrent.futures import Future

        future = Future()
        self.answer(len(self.futures), future, fn, args)
        self.futures.append(future)
        return future


def test_files_of_a_worker_that_died_are_estimated_here(tmp_path, monkeypatch):
    # A worker killed mid-run (out of memory, a signal) breaks the pool: every chunk it
    # had not answered is estimated again in this process, none is lost.
    from concurrent.futures.process import BrokenProcessPool

    import selfsup.estimation.files as estimate_module

    def dying(index, future, fn, args):  # the first chunk answered, then the pool breaks
        if index == 0:
            future.set_result(fn(*args))
        else:
            future.set_exception(BrokenProcessPool("a worker stopped"))

    monkeypatch.setattr(estimate_module, "ProcessPoolExecutor", _FakePool(dying))
    config = dataclasses.replace(SMALL, height=24, width=32)
    for seed in (6, 7, 8):
        write_scene(tmp_path / f"good_{seed}.npz", _scene(seed, config=config))
    options = EstimateOptions(max_lights=1, tuning=Tuning(refine=RefineOptions(max_iters=(10, 3))))
    summary = estimate_files(tmp_path, tmp_path / "out.jsonl", options, progress=False, workers=2)
    assert summary["done"] == 3 and summary["failed"] == 0
    ids = [json.loads(line)["id"] for line in (tmp_path / "out.jsonl").read_text().splitlines()]
    assert ids == ["procedural_6", "procedural_7", "procedural_8"]


def test_a_run_stopped_early_cancels_the_chunks_still_queued(monkeypatch):
    # Ctrl-C or a failed write while the workers run: the queued chunks are cancelled,
    # so the pool's exit does not wait for them all to be estimated.
    import selfsup.estimation.files as estimate_module

    def queued(index, future, fn, args):  # the first chunk answered, the others still queued
        if index == 0:
            future.set_result(({}, {}))

    pool = _FakePool(queued)
    monkeypatch.setattr(estimate_module, "ProcessPoolExecutor", pool)
    results = estimate_module._chunk_results([["a"], ["b"], ["c"]], EstimateOptions(), torch.device("cpu"), workers=2)
    assert next(results)[0] == ["a"]
    results.close()  # what an exception in the consumer does to the generator
    assert [f.cancelled() for f in pool.futures] == [False, True, True]


def test_worker_count_auto_spreads_only_directories_worth_a_start(monkeypatch):
    import selfsup.estimation.files as estimate_module
    from selfsup.estimation.files import FILES_PER_SPAWNED_WORKER, worker_count

    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    monkeypatch.setattr(estimate_module, "usable_cores", lambda: 4)
    monkeypatch.setattr(estimate_module, "start_method", lambda threads, device: "fork")
    assert [worker_count("auto", files, cpu) for files in (1, 3, 100)] == [1, 3, 4]
    monkeypatch.setattr(estimate_module, "start_method", lambda threads, device: "spawn")
    assert worker_count("auto", 1, cpu) == 1 and worker_count("auto", 2 * FILES_PER_SPAWNED_WORKER - 1, cpu) == 1
    assert worker_count("auto", 1000 * FILES_PER_SPAWNED_WORKER, cpu) == 4
    assert worker_count("auto", 1000, cuda) == 1 and worker_count(3, 1, cpu) == 3
    for bad in (0, -1, "two", 1.5, True):
        with pytest.raises(ValueError, match="estimate.workers must be"):
            worker_count(bad, 10, cpu)


def test_workers_are_forked_only_where_that_is_safe():
    from selfsup.estimation.files import start_method

    cpu = torch.device("cpu")
    assert start_method(1, cpu) == ("fork" if sys.platform.startswith("linux") else "spawn")
    assert start_method(2, cpu) == "spawn"  # a multi-thread child may hang in the inherited OpenMP pool
    assert start_method(1, torch.device("cuda")) == "spawn"  # a forked child cannot use CUDA


def test_benchmark_options_reach_estimate_and_refine_settings():
    from benchmarks.estimate_procedural import parse_options

    extra = parse_options(["block_width=0.1", "refine.robust_scale=0.05", "weak_light_shadow_gain=0"])
    options = EstimateOptions.from_settings(**extra)
    assert (options.tuning.block_width, options.tuning.weak_light_shadow_gain, options.tuning.refine.robust_scale) == (0.1, 0, 0.05)
    with pytest.raises(ValueError, match="KEY=VALUE"):
        parse_options(["block_width"])
    # Words and paths as the docs write them, quoted or not.
    assert parse_options(["method=cnn", "checkpoint=selfsup/checkpoints/iterative.pt"]) == \
        parse_options(["method='cnn'", "checkpoint='selfsup/checkpoints/iterative.pt'"]) == \
        {"method": "cnn", "checkpoint": "selfsup/checkpoints/iterative.pt"}
