"""Hydra entry point: builds objects from configs/ and runs the selected mode.

    python train.py                                        # mode=train on procedural scenes
    python train.py mode=eval eval.checkpoint=outputs/<run>/best.pt
    python train.py mode=generate generate.out=data/test generate.count=200
    python train.py mode=estimate estimate.input=scenes/ estimate.output=lights.jsonl
    python train.py mode=track track.input=captures/ track.output=track.jsonl
    python train.py mode=scan scan.input=posed_capture/ scan.output=room.json
    python train.py mode=adapt adapt.input=my_captures/ adapt.out=adapted.pt
    python train.py mode=insert insert.scene=scene.npz insert.estimates=lights.jsonl insert.output=insert.png
    python train.py mode=benchmark benchmark=render_speed benchmark.quick=true
"""

from __future__ import annotations

import logging
import os
import sys
from typing import NoReturn

import hydra
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

from selfsup.estimation.jobs import OutputInUseError

log = logging.getLogger(__name__)
MODES = ("train", "eval", "generate", "estimate", "track", "scan", "adapt", "insert", "benchmark")
FULL_ERROR = os.environ.get("HYDRA_FULL_ERROR") == "1"  # the user's: a traceback instead of one line


def _run_dir(mode: str, folder: str) -> str:
    # Hydra's run folder: ``folder`` (outputs/<date>/<time>) for training, whose checkpoints and
    # logs live there; a temporary one for the other modes, which write what the user asked for
    # and nothing else in the working tree.
    import tempfile

    return folder if mode == "train" else tempfile.mkdtemp(prefix=f"shadowlight-{mode}-")


OmegaConf.register_new_resolver("run_dir", _run_dir, replace=True)


def _remove_temporary_run_dir() -> None:
    # The temporary run folder of a mode other than training (_run_dir): Hydra's config copy and
    # log, which nobody reads once the run is over; left behind, every run added one to /tmp.
    import shutil
    import tempfile

    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return
    folder = HydraConfig.get().runtime.output_dir
    if os.path.basename(folder).startswith("shadowlight-") and \
            os.path.dirname(os.path.abspath(folder)) == os.path.abspath(tempfile.gettempdir()):
        shutil.rmtree(folder, ignore_errors=True)


def _plain(node) -> dict:
    try:
        return OmegaConf.to_container(node, resolve=True, throw_on_missing=True)
    except MissingMandatoryValue as error:  # a required setting (??? in configs/) left out
        key = error.full_key or "a setting"
        raise ValueError(f"{key} is required: add {key}=<value> to the command line (the head of train.py shows "
                         "each mode's command)") from None


def build_data(cfg: DictConfig):
    """``(SamplerConfig, Degradations, samples)`` from the ``data`` group."""
    from selfsup.scenes.dataset import sampler_config
    from selfsup.scenes.degrade import Degradations

    return sampler_config(**_plain(cfg.data.sampler)), Degradations(**_plain(cfg.data.degradations)), cfg.data.samples


def _loss_options(cfg: DictConfig):
    """``(LossOptions, TeacherOptions)`` of the experiment's ``loss`` node (its ``teacher``
    sub-node: the weights of the pool teacher's terms in training); for the iterative
    network (``model.architecture=iterative``) its ``SequenceLossOptions`` and None."""
    from selfsup.losses import LossOptions, TeacherOptions

    loss = _plain(cfg.loss)
    if cfg.model.get("architecture", "lightnet") == "iterative":
        from selfsup.sequence_loss import SequenceLossOptions

        return SequenceLossOptions(**loss), None
    teacher = TeacherOptions(**(loss.pop("teacher", None) or {}))
    return LossOptions(**loss), teacher


def build_trainer(cfg: DictConfig):
    """The :class:`selfsup.engine.Trainer` of the ``data``, ``model``, ``renderer``,
    ``optim``, ``trainer``, ``logger`` groups and the experiment's ``loss`` node."""
    import dataclasses

    from render import ShadowedBlinnPhong
    from selfsup.engine import DataOptions, LoggerOptions, OptimOptions, Trainer, TrainerOptions

    sampler, degradations, _ = build_data(cfg)
    pool = _plain(cfg.data.pool)
    resolution = {key: pool.pop(key) for key in ("height", "width", "n_lights_probs")}
    samples = pool.pop("samples")
    sampler = dataclasses.replace(sampler, **{k: tuple(v) if isinstance(v, list) else v for k, v in resolution.items()})
    model = _plain(cfg.model)
    model["widths"] = tuple(model["widths"])
    if model.get("architecture") == "iterative" and model["max_lights"] < len(sampler.n_lights_probs):
        pass  # slots are the lights the network places; a room may have more (the brightest are placed)
    elif model["max_lights"] < len(sampler.n_lights_probs):
        raise ValueError(f"model.max_lights={model['max_lights']} is below the {len(sampler.n_lights_probs)} lights "
                         "data.pool.n_lights_probs can draw")
    optim = _plain(cfg.optim)
    optim["betas"] = tuple(optim["betas"])
    loss, teacher = _loss_options(cfg)
    data = DataOptions(**pool)
    search = None
    if data.teacher_scenes:
        from selfsup.teacher import PoolTeacher

        search = PoolTeacher(sampler, degradations, samples, data.teacher_scenes, model["max_lights"],
                             data.teacher_cache, data.teacher_scale, data.teacher_method, cfg.trainer.progress)
    prepare_pool = None
    if data.render_scale > 1:
        from selfsup.estimation.prepare import prepared_pool as prepare_pool
    return Trainer(model_config=model, sampler=sampler, degradations=degradations, samples=samples, prepare_pool=prepare_pool,
                   pool=data, optim=OptimOptions(**optim), trainer=TrainerOptions(**_plain(cfg.trainer)),
                   logger=LoggerOptions(**_plain(cfg.logger)), loss=loss, teacher=teacher, teacher_search=search,
                   renderer=ShadowedBlinnPhong(**_plain(cfg.renderer), check_finite=False), seed=cfg.seed,
                   config=OmegaConf.to_container(cfg, resolve=True))


def estimate_settings(node) -> tuple:
    """``(EstimateOptions, the command's own settings)`` of an ``estimate`` config node: the
    estimator's choices and tuned constants, and where it reads and writes (input, output,
    workers, ...), as ``mode=estimate`` passes them to :func:`selfsup.estimation.estimate_files`."""
    from selfsup.estimation import EstimateOptions

    est = _plain(node)
    io = {k: est.pop(k) for k in ("input", "output", "progress", "batch", "device", "workers", "depth",
                                  "depth_scale", "intrinsics", "overwrite", "shard")}
    return EstimateOptions(**est), io


def training_summary(result: dict) -> str:
    """One human line of a training run's end: validation error, angle, success, checkpoint."""
    v = result.get("validation") or {}

    def number(key: str, fmt: str) -> str:
        return format(v[key], fmt) if isinstance(v.get(key), (int, float)) else "n/a"

    # A run that trainer.max_minutes ended before its steps says so in this line, not in a warning above it.
    steps = (f"{result['step']} of {result['max_steps']} steps (stopped by trainer.max_minutes={result['max_minutes']})"
             if result.get("stopped_by_time") else
             f"{result['step']} of {result['max_steps']} steps (stopped at trainer.stop_step)"
             if result.get("stop_step") and result["step"] < result["max_steps"] else f"{result['step']} steps")
    return (f"trained {steps} in {result['minutes']:.1f} min; validation on {v.get('scenes', 'n/a')} "
            f"scenes: median position error {number('median_position_error', '.3f')} of the scene size, median "
            f"angle {number('median_angular_error', '.1f')} degrees, success {number('success_rate', '.0%')}, right "
            f"light count {number('count_accuracy', '.0%')}; best checkpoint {result['best']}")


def run(cfg: DictConfig):
    """Run ``cfg.mode``; a plain function so tests can call it with a composed config."""
    if cfg.mode not in MODES:
        raise ValueError(f"unknown mode {cfg.mode!r}; available: {', '.join(MODES)}")
    torch.manual_seed(cfg.seed)
    if cfg.mode == "train":
        result = build_trainer(cfg).fit()
        log.info("%s", training_summary(result))
        return result
    if cfg.mode == "eval":
        rows, path = instantiate(cfg.eval, sets=_plain(cfg.eval.sets), files=_plain(cfg.eval.files) or None,
                                 n_lights_probs=list(cfg.eval.n_lights_probs))
        for row in rows:
            log.info("%s", row)
        if path:
            log.info("results written to %s", path)
        else:
            log.info("eval.write=true also writes them to benchmarks/results/")
        return rows, path
    if cfg.mode == "insert":
        from selfsup.insert import insert_files

        path = insert_files(**{k: tuple(v) if isinstance(v, list) else v for k, v in _plain(cfg.insert).items()})
        log.info("wrote %s", path)
        return path
    if cfg.mode == "benchmark":
        result = instantiate(cfg.benchmark)
        log.info("benchmark %s done", cfg.benchmark._target_)
        return result
    if cfg.mode == "generate":
        from selfsup.scenes.generate import generate_set

        sampler, degradations, samples = build_data(cfg)
        return generate_set(sampler=sampler, degradations=degradations, samples=samples, **_plain(cfg.generate))
    if cfg.mode == "estimate":
        from selfsup.estimation import estimate_files

        options, io = estimate_settings(cfg.estimate)
        return estimate_files(options=options, **io)
    if cfg.mode == "track":
        return _track(_plain(cfg.track))
    if cfg.mode == "scan":
        return _scan(_plain(cfg.scan))
    if cfg.mode == "adapt":
        return _adapt(cfg)


def _adapt(cfg: DictConfig) -> dict:
    # mode=adapt: the run's settings, what is refused, the loss (the experiment's), the
    # renderer, and the procedural scenes (mixed in: the shipped network's recipe; the
    # validation: the data group's scenes) from the config.
    import dataclasses

    from render import ShadowedBlinnPhong
    from selfsup.adapt import AdaptOptions, FrameOptions, GuardOptions, Procedural, TeacherOptions, adapt_files

    settings = _plain(cfg.adapt)
    io = {k: settings.pop(k) for k in ("input", "out", "checkpoint")}
    frames = settings.pop("frames")
    frames["intrinsics"] = None if frames["intrinsics"] is None else tuple(frames["intrinsics"])
    mixed = settings.pop("procedural")
    validation_scenes = settings.pop("validation_scenes")
    guards = GuardOptions(**settings.pop("guards"))
    teacher = TeacherOptions(**settings.pop("teacher"))
    sampler, degradations, samples = build_data(cfg)
    procedural = Procedural(
        sampler=dataclasses.replace(sampler, height=mixed["height"], width=mixed["width"],
                                    n_lights_probs=tuple(mixed["n_lights_probs"]), light_margin=mixed["light_margin"],
                                    light_power_range=tuple(mixed["light_power_range"])),
        degradations=dataclasses.replace(degradations, indirect=mixed["indirect"], camera=mixed["camera"]),
        samples=mixed["samples"], scenes=mixed["scenes"],
        validation_sampler=dataclasses.replace(sampler, n_lights_probs=tuple(cfg.data.pool.n_lights_probs)),
        validation_degradations=degradations, validation_samples=samples, validation_scenes=validation_scenes)
    return adapt_files(io["input"], io["out"], io["checkpoint"], options=AdaptOptions(**settings),
                       frame_options=FrameOptions(**frames), guards=guards,
                       loss=_loss_options(cfg)[0], procedural=procedural, teacher=teacher,
                       renderer=ShadowedBlinnPhong(**_plain(cfg.renderer), check_finite=False))


def _scan(settings: dict) -> dict:
    # mode=scan: the frames' estimate options and the fusion's constants from one config node.
    from selfsup.estimation import EstimateOptions
    from selfsup.scan import FuseOptions, scan_files

    io = {k: settings.pop(k) for k in ("input", "output", "frames_output", "max_frames", "progress", "device",
                                       "workers", "depth_scale", "intrinsics")}
    fuse = FuseOptions(**settings.pop("fuse", {}))
    return scan_files(options=EstimateOptions(**settings), fuse_options=fuse, **io)


def _track(settings: dict) -> dict:
    # mode=track: the tracker's tuning and the full estimates' options from one config node.
    from selfsup.estimation import EstimateOptions, Tuning
    from selfsup.tracking import TrackTuning, track_files

    io = {k: settings.pop(k) for k in ("input", "output", "progress", "device", "depth_scale", "intrinsics",
                                       "refresh", "overwrite")}
    tuning = TrackTuning(**settings.pop("tuning", {}))
    estimate_tuning = Tuning(**settings.pop("estimate_tuning", {}))
    return track_files(options=EstimateOptions(**settings, tuning=estimate_tuning), tuning=tuning, **io)


@hydra.main(version_base="1.3", config_path="configs", config_name="train")
def main(cfg: DictConfig) -> None:
    from selfsup.scenes.dataset import retain_freed_memory

    retain_freed_memory()  # our own process: rendering and estimation free large arrays by the hundred
    try:
        result = run(cfg)
    except USER_ERRORS as error:
        _report(error)
    finally:
        _remove_temporary_run_dir()
    if cfg.mode in ("estimate", "track", "scan") and result["failed"]:
        raise SystemExit(1)  # some files failed: each is named in the log above


def _one_line(error: BaseException) -> str:
    # An error and its cause as one line: Hydra's messages span lines ("Could not override
    # 'x'. / To append ..."), omegaconf's carry their full key on further lines.
    parts = []
    while error is not None and len(parts) < 3:
        text = " ".join(line.strip() for line in str(error).strip().splitlines() if line.strip()
                        and not line.strip().startswith(("full_key:", "object_type=", "reference_type=")))
        if text and text not in parts:
            parts.append(text)
        error = error.__cause__ or (None if error.__suppress_context__ else error.__context__)
    return ": ".join(parts)


USER_ERRORS = (ValueError, FileNotFoundError, NotADirectoryError,  # raised with a message that names the fix
               OutputInUseError)


def _unknown_key(message: str) -> str | None:
    # Hydra's "Could not override 'estimate.inptu'. To append to your config use +estimate.inptu=x"
    # leads nowhere (a new key is never read): the one line names the group's settings instead,
    # the nearest first. None for other errors, or where the group cannot be composed.
    import difflib
    import re

    found = re.search(r"Could not override '([\w.]+)'.*Key '(\w+)' is not in struct", message)
    if not found or found.group(2) not in found.group(1).split("."):
        return None
    key, leaf = found.group(1), found.group(2)
    parts = key.split(".")
    group = ".".join(parts[: parts.index(leaf)])  # the deepest group that exists: estimate of estimate.tunin.x
    try:
        from hydra import compose, initialize_config_dir

        others = [a for a in sys.argv[1:] if not a.lstrip("+~").startswith(key + "=")]
        with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
            cfg = compose("train", overrides=others)
        node = OmegaConf.select(cfg, group) if group else cfg
        keys = sorted(str(k) for k in node.keys())
    except Exception:  # noqa: BLE001 -- another mistake on the line: Hydra's own message stays
        return None
    near = difflib.get_close_matches(leaf, keys, n=1)
    hint = f"did you mean {group + '.' if group else ''}{near[0]}? " if near else ""
    where = f"{group}.{leaf}" if group else leaf
    tuned = f"; tuned constants: +{group}.tuning.NAME=VALUE" if group in ("estimate", "track") else ""
    return f"{where} is not a setting of {group or 'train.py'}: {hint}its settings are {', '.join(keys)}{tuned}"


CONFIGS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "configs")


def _report(error: BaseException) -> NoReturn:
    # One line on stderr and exit status 2, unless the user's HYDRA_FULL_ERROR=1 asks for the traceback.
    if FULL_ERROR:
        raise error
    line = _one_line(error) or type(error).__name__
    print(f"train.py: error: {_unknown_key(line) or line} (HYDRA_FULL_ERROR=1 shows where)", file=sys.stderr)
    raise SystemExit(2) from None


def cli() -> None:
    """``main`` for the command line: a user's mistake (a misspelled or missing setting, a
    path that does not exist, a bad value) is one line on stderr and exit status 2, no
    traceback; ``HYDRA_FULL_ERROR=1`` shows the traceback instead. Exit status 1 stays
    ``mode=estimate``'s "some files failed"."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    if FULL_ERROR:
        return main()
    os.environ["HYDRA_FULL_ERROR"] = "1"  # Hydra raises what it would print (a bad override): reported here
    try:
        main()
    except (HydraException, OmegaConfBaseException, *USER_ERRORS) as error:
        _report(error)


if __name__ == "__main__":
    cli()
