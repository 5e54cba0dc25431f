"""Self-supervised adaptation (``mode=adapt``) measured on rooms the network never saw.

    python -m benchmarks.adapt make --out data/adapt          # Mitsuba 3 captures (the mitsuba extra), once
    python -m benchmarks.adapt run --data data/adapt          # adapt, then score before and after
    python -m benchmarks.adapt landscape --data data/adapt    # where the re-render loss is least

``make`` renders ``--rooms`` Mitsuba 3 rooms (:mod:`benchmarks.mitsuba_scenes`: two of
three with one light, the third with two), each seen from ``--views`` camera positions
(the camera turned about the room's middle, -20 to +20 degrees), as capture folders of
the recipe of :mod:`benchmarks.captures` (8-bit sRGB at an exposure drawn per frame,
millimetre depth, no albedo) in two sets: ``gi`` (path traced, 256 samples a pixel a
light) and ``noisy`` (direct light through a structured-light sensor's depth noise and
holes and image noise). The rooms are split by room: the even ones into
``out/adapt/<set>``, the odd ones into ``out/test/<set>``; then ``--extra-rooms`` (72) more
rooms of ``--extra-views`` (2) frames each go into the adapt half (the network learns rooms,
not views: more rooms, fewer views each; the test half stays 24 rooms of 4 views). The truth
(``truth/``) is read only to score the test half.

``run`` adapts the shipped network (``--start``: another checkpoint, the iterative network's
included) on both adapt folders with ``mode=adapt``'s settings
(the command itself, timed), then scores the network alone (``estimate.method=cnn``)
and the whole estimator (the default ``cnn+refine``) on the test folders with the
shipped and the adapted checkpoint, and the network on two procedural sets of
``mode=eval`` (true reflectance, and capture-like) with both. One results file,
``benchmarks/results/adapt_<device>_<date>.*``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
SETS = ("gi", "noisy")
COLUMNS = ["network", "estimator", "set", "frames", "success", "one_light_success", "two_light_right_count",
           "median_worst_error", "seconds_per_frame"]


def room_lights(room: int) -> int:
    """Lights of room ``room``: two in every third pair of rooms (both halves get the same mix)."""
    return 2 if (room // 2) % 3 == 2 else 1


def make(out: Path, rooms: int = 48, views: int = 4, seed: int = 7300, swing_deg: float = 20.0,
         extra_rooms: int = 0, extra_views: int = 2) -> None:
    """Capture folders ``out/{adapt,test}/{gi,noisy}`` of ``rooms`` Mitsuba rooms, ``views``
    frames each, split by room; then ``extra_rooms`` more rooms of ``extra_views`` frames
    each, all into the adapt half (more rooms to learn from, the test half unchanged)."""
    import mitsuba as mi

    from benchmarks.captures import write_capture
    from benchmarks.mitsuba_scenes import render_variants
    from selfsup.scenes.sampler import SamplerConfig, sample_scene
    from selfsup.scenes.sequences import orbited

    mi.set_variant("scalar_rgb")
    for room in range(rooms + extra_rooms):
        half = "test" if room < rooms and room % 2 == 1 else "adapt"
        count = views if room < rooms else extra_views
        angles = torch.linspace(-swing_deg, swing_deg, count).tolist() if count > 1 else [0.0]
        lights = room_lights(room)
        spec = sample_scene(seed * 1_000_003 + room, SamplerConfig(height=120, width=160), n_lights=lights)
        started = time.perf_counter()
        for view, angle in enumerate(angles):
            frame = f"room_{seed}_{room:03d}_{view}"
            if all((out / half / s / "truth" / f"{frame}.npz").is_file() for s in SETS):
                continue  # made by an earlier run
            rendered = render_variants(orbited(spec, angle), frame, variants=("gi", "noisy"))
            for set_name, scene in rendered.items():
                write_capture(scene, out / half / set_name, frame)
        print(json.dumps({"room": room, "half": half, "lights": lights, "views": count,
                          "seconds": round(time.perf_counter() - started, 1)}), flush=True)


def _adapt_command(data: Path, checkpoint: Path, extra: list[str], search: Path | None = None) -> tuple[float, str]:
    """Run ``mode=adapt`` on the adapt half; its wall time (start-up included) and its summary line.
    ``search``: the per-frame search's records of an earlier run of the same start (its
    ``teacher.jsonl``), read instead of searched again (the wall time then leaves the search out)."""
    folders = ",".join(str((data / "adapt" / s).resolve()) for s in SETS)
    command = [sys.executable, "train.py", "mode=adapt", f"adapt.input=[{folders}]", f"adapt.out={checkpoint}",
               "adapt.progress=false", *extra]
    shutil.rmtree(f"{checkpoint}.run", ignore_errors=True)  # a run from scratch: its search and steps timed
    if search is not None:
        Path(f"{checkpoint}.run").mkdir(parents=True)
        shutil.copy(search, Path(f"{checkpoint}.run") / "teacher.jsonl")
    started = time.perf_counter()
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        raise RuntimeError(f"mode=adapt failed ({done.returncode}):\n{done.stderr[-3000:]}")
    summary = [line for line in done.stderr.splitlines() if "adapted on" in line]  # the log's last line
    return seconds, summary[-1].split(" - ", 1)[-1] if summary else ""


def _procedural(checkpoint: Path | None, scenes: int) -> dict[str, dict]:
    """The network alone on two of ``mode=eval``'s procedural sets (seed 9000, 160x120): ``true
    reflectance`` (its cost volumes see the albedo; what mode=adapt's forgetting guard
    validates on) and ``captures, camera and indirect light`` (no albedo, 1-3 lights)."""
    from selfsup.checkpoint import LIGHTNET_CHECKPOINT, load_network
    from selfsup.evaluate import evaluate_network, summarise
    from selfsup.scenes.dataset import ProceduralScenes, materialise, sampler_config
    from selfsup.scenes.degrade import Degradations

    network, _ = load_network(checkpoint or LIGHTNET_CHECKPOINT)
    sets = {"true reflectance": ((0.75, 0.25), Degradations(), True),
            "captures, camera and indirect light": ((0.45, 0.35, 0.2), Degradations(camera=True, indirect=2.0), False)}
    out = {}
    for name, (probs, degradations, albedo) in sets.items():
        pool = materialise(ProceduralScenes(sampler_config(height=120, width=160, n_lights_probs=list(probs)), degradations,
                                            length=scenes, base_seed=9000, samples=2,
                                            max_lights=max(network.max_lights, len(probs))),
                           workers=2, progress=False)
        out[name] = summarise(evaluate_network(network, pool, albedo=albedo))
    return out


def _earlier_adaptation(checkpoint: Path) -> str:
    """The summary an adapted checkpoint carries (``mode=adapt`` writes its metrics beside the weights)."""
    saved = torch.load(checkpoint, map_location="cpu", weights_only=True)
    if not saved.get("metrics", {}).get("adapted"):
        raise SystemExit(f"{checkpoint} was not written by mode=adapt (no 'adapted' metrics); run without --adapted")
    metrics, before = saved["metrics"], saved.get("before", {})
    # The step whose weights were kept (the best held-back loss), not the run's last.
    return (f"the weights of adaptation step {metrics['step']} from {saved.get('adapted_from')}: held-back loss "
            f"{before.get('held_loss', float('nan')):.3f} -> {metrics['held_loss']:.3f}")


def run(data: Path, out_checkpoint: Path, extra: list[str], procedural_scenes: int = 200, write: bool = True,
        start: Path | None = None, name: str = "adapt", search: Path | None = None, adapted: bool = False):
    from benchmarks.captures import run as estimate_sets
    from benchmarks.common import write_results
    from selfsup.estimation import EstimateOptions

    if adapted and (search is not None or extra):
        raise SystemExit("--adapted scores an earlier run's checkpoint: --search and mode=adapt settings do not apply")
    if start is not None:
        extra = [f"adapt.checkpoint={start.resolve()}", *extra]
    if adapted:  # scored only: an earlier run's adapted checkpoint, its own summary
        line = _earlier_adaptation(out_checkpoint)
        timing = f"an earlier run's checkpoint {out_checkpoint.name}, not timed here ({line}). "
    else:
        seconds, line = _adapt_command(data, out_checkpoint, extra, search)
        searched = f"; the search read from {search}, not timed" if search else ""
        timing = f"{seconds:.0f} s for the command, start-up included{searched} ({line}). "
    print(f"adaptation: {timing}", flush=True)
    rows = []
    for label, checkpoint in (("shipped" if start is None else start.name, start), ("adapted", out_checkpoint)):
        for method in ("cnn", "cnn+refine"):
            options = EstimateOptions(method=method, checkpoint=None if checkpoint is None else str(checkpoint))
            scored, _ = estimate_sets([data / "test"], SETS, write=False, options=options)
            rows += [{"network": label, "estimator": "network alone" if method == "cnn" else "whole (cnn+refine)",
                      "frames": row["scenes"], **{k: v for k, v in row.items() if k in COLUMNS}} for row in scored]
        for set_name, summary in _procedural(checkpoint, procedural_scenes).items():
            rows.append({"network": label, "estimator": "network alone", "set": f"procedural: {set_name}",
                         "frames": procedural_scenes, "success": f"{summary['success_rate']:.3f}",
                         "one_light_success": f"{summary['one_light_success']:.3f}",
                         "two_light_right_count": f"{summary['two_light_right_count']:.3f}",
                         "median_worst_error": round(summary["median_position_error"], 4)})
    if write:
        subject = "The shipped network" if start is None else f"The network of {start}"
        header = (f"{subject} adapted by `mode=adapt` on the adapt half of {data} (Mitsuba rooms split by room; "
                  f"`python -m benchmarks.adapt make`), scored on the test half: success = every light within 0.05 "
                  f"of the scene size; procedural = two of `mode=eval`'s sets (seed 9000, 160x120), the network "
                  f"alone: true reflectance (its cost volumes see the albedo; mode=adapt's forgetting guard validates "
                  f"on this set's first 100) and capture-like (a drawn camera, indirect light, 1-3 lights, no albedo). "
                  f"Adaptation: {timing}Settings changed: {' '.join(extra) or 'none'}.")
        print(write_results(name, torch.device("cpu"), rows, header, COLUMNS))
    return rows


def landscape(data: Path, sets=SETS, radius: float = 0.1, steps: int = 3, write: bool = True) -> list[dict]:
    """Where the albedo-free re-render loss (:func:`selfsup.losses.reconstruction_loss` with
    the frames' regions, ``mode=adapt``'s loss of one light) is least on a ``steps^3`` grid
    of ``+-radius`` of the scene size about each one-light test frame's true light: the
    argmin's distance from the truth (of the scene size). A loss whose gradient leads to the
    lamp has its argmin at the truth (distance 0)."""
    import statistics
    from dataclasses import replace

    from benchmarks.captures import read_truth
    from benchmarks.common import write_results
    from render import Material, ShadowedBlinnPhong
    from selfsup.adapt import FrameOptions, collate_frames, load_frames
    from selfsup.checkpoint import LIGHTNET_CHECKPOINT, load_network
    from selfsup.losses import LossOptions, SceneBatch, reconstruction_loss

    network, _ = load_network(LIGHTNET_CHECKPOINT)
    renderer = ShadowedBlinnPhong(check_finite=False)
    axis = torch.linspace(-radius, radius, steps)
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    rows = []
    for set_name in sets:
        folder = data / "test" / set_name
        loaded = load_frames([folder], FrameOptions(holdout=0.5, block=1))
        distances = []
        for frame in loaded.train + loaded.held:
            truth = read_truth(folder / "truth" / f"{frame.id}.npz")
            if truth.light_pos.shape[0] != 1:
                continue
            batch = collate_frames([frame])
            grey = SceneBatch(batch.image, batch.gbuffer, Material(kd=torch.full((1, *batch.image.shape[2:], 3), 0.5)))
            with torch.no_grad():
                one = network(batch.network_image, batch.network_gbuffer, None)
                costs = []
                for offset in grid:  # one slot, at each grid point
                    at = (truth.light_pos[0] + offset * float(truth.scene_scale)).view(1, 1, 3)
                    single = replace(one, position=at, intensity=one.intensity[:, :1], presence=one.presence[:, :1],
                                     count_logits=one.count_logits[:, :1], anchor_logits=one.anchor_logits[:, :1],
                                     anchor_position=one.anchor_position[:, :1])
                    costs.append(float(reconstruction_loss(single, grey, renderer, LossOptions(),
                                                           segments=batch.segments).photometric))
            distances.append(float(grid[int(torch.tensor(costs).argmin())].norm()))
        rows.append({"set": set_name, "frames": len(distances),
                     "median_argmin_distance": round(statistics.median(distances), 4),
                     "argmin_within_0.05": f"{sum(d < 0.05 for d in distances)}/{len(distances)}",
                     "argmin_at_truth": f"{sum(d == 0 for d in distances)}/{len(distances)}"})
        print(rows[-1], flush=True)
    if write:
        header = (f"Where mode=adapt's albedo-free re-render loss (one light; regions of one albedo solved, epipolar "
                  f"shadows, 80x60) is least on a {steps}^3 grid of +-{radius} of the scene size about the true light "
                  f"of each one-light frame of {data}/test (Mitsuba rooms, `python -m benchmarks.adapt make`): the "
                  f"argmin's distance from the truth, of the scene size. A loss that leads to the lamp has it at 0.")
        print(write_results("adapt_loss_landscape", torch.device("cpu"), rows, header,
                            ["set", "frames", "median_argmin_distance", "argmin_within_0.05", "argmin_at_truth"]))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    m = commands.add_parser("make", help="render the Mitsuba rooms as capture folders")
    m.add_argument("--out", type=Path, required=True)
    m.add_argument("--rooms", type=int, default=48)
    m.add_argument("--views", type=int, default=4)
    m.add_argument("--seed", type=int, default=7300)
    m.add_argument("--extra-rooms", type=int, default=72, help="more rooms, all in the adapt half")
    m.add_argument("--extra-views", type=int, default=2)
    r = commands.add_parser("run", help="adapt on the adapt half, score on the test half")
    r.add_argument("--data", type=Path, required=True)
    r.add_argument("--checkpoint", type=Path, default=Path("data/adapted.pt"), help="where the adapted network goes")
    r.add_argument("--name", default="adapt", help="the results file's name")
    r.add_argument("--search", type=Path, default=None,
                   help="an earlier run's teacher.jsonl of the same start, read instead of searched again")
    r.add_argument("--start", type=Path, default=None, help="the network adapted (default: the shipped one)")
    r.add_argument("--procedural", type=int, default=200, help="procedural validation scenes")
    r.add_argument("--adapted", action="store_true",
                   help="--checkpoint is an earlier run's adapted network: score it, do not adapt again")
    r.add_argument("--no-write", action="store_true")
    r.add_argument("overrides", nargs="*", help="mode=adapt settings, e.g. adapt.steps=300")
    g = commands.add_parser("landscape", help="where the re-render loss is least about the true light")
    g.add_argument("--data", type=Path, required=True)
    g.add_argument("--steps", type=int, default=3, help="grid points a side (+-0.1 of the scene size)")
    args = parser.parse_args()
    if args.command == "make":
        try:
            import mitsuba  # noqa: F401
        except ImportError:
            parser.exit(2, "benchmarks.adapt make needs Mitsuba 3: python -m pip install mitsuba\n")
        make(args.out, args.rooms, args.views, args.seed, extra_rooms=args.extra_rooms, extra_views=args.extra_views)
    elif args.command == "landscape":
        landscape(args.data, steps=args.steps)
    else:
        run(args.data, args.checkpoint.resolve(), args.overrides, args.procedural, write=not args.no_write,
            start=args.start, name=args.name, search=args.search, adapted=args.adapted)


if __name__ == "__main__":
    main()
