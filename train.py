"""Hydra entry point: builds objects from configs/ and runs the selected mode.

    python train.py                                        # mode=train on procedural scenes
    python train.py mode=eval eval.checkpoint=outputs/<run>/best.pt
    python train.py mode=generate generate.out=data/test generate.count=200
    python train.py mode=estimate estimate.input=scenes/ estimate.output=lights.jsonl
    python train.py mode=insert insert.scene=scene.npz insert.estimates=lights.jsonl insert.output=insert.png
    python train.py mode=benchmark benchmark=render_speed benchmark.quick=true
"""

from __future__ import annotations

import logging

import hydra
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

log = logging.getLogger(__name__)
MODES = ("train", "eval", "generate", "estimate", "insert", "benchmark")


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


def build_trainer(cfg: DictConfig):
    """The :class:`selfsup.engine.Trainer` of the ``data``, ``model``, ``renderer``,
    ``optim``, ``trainer``, ``logger`` groups and the experiment's ``loss`` node."""
    import dataclasses

    from render import ShadowedBlinnPhong
    from selfsup.engine import DataOptions, LoggerOptions, OptimOptions, Trainer, TrainerOptions
    from selfsup.losses import LossOptions

    sampler, degradations, _ = build_data(cfg)
    pool = _plain(cfg.data.pool)
    resolution = {key: pool.pop(key) for key in ("height", "width", "n_lights_probs")}
    samples = pool.pop("samples")
    sampler = dataclasses.replace(sampler, **{k: tuple(v) if isinstance(v, list) else v for k, v in resolution.items()})
    model = _plain(cfg.model)
    model["widths"] = tuple(model["widths"])
    if model["max_lights"] < len(sampler.n_lights_probs):
        raise ValueError(f"model.max_lights={model['max_lights']} is below the {len(sampler.n_lights_probs)} lights "
                         "data.pool.n_lights_probs can draw")
    optim = _plain(cfg.optim)
    optim["betas"] = tuple(optim["betas"])
    return Trainer(model_config=model, sampler=sampler, degradations=degradations, samples=samples,
                   pool=DataOptions(**pool), optim=OptimOptions(**optim), trainer=TrainerOptions(**_plain(cfg.trainer)),
                   logger=LoggerOptions(**_plain(cfg.logger)), loss=LossOptions(**_plain(cfg.loss)),
                   renderer=ShadowedBlinnPhong(**_plain(cfg.renderer), check_finite=False), seed=cfg.seed,
                   config=OmegaConf.to_container(cfg, resolve=True))


def run(cfg: DictConfig):
    """Run ``cfg.mode``; a plain function so tests can call it with a composed config."""
    if cfg.mode not in MODES:
        raise ValueError(f"unknown mode {cfg.mode!r}; available: {', '.join(MODES)}")
    torch.manual_seed(cfg.seed)
    if cfg.mode == "train":
        result = build_trainer(cfg).fit()
        log.info("trained %d steps in %.1f min; validation %s; checkpoints %s", result["step"], result["minutes"],
                 result["validation"], result["best"])
        return result
    if cfg.mode == "eval":
        rows, path = instantiate(cfg.eval, sets=_plain(cfg.eval.sets), files=_plain(cfg.eval.files) or None,
                                 n_lights_probs=list(cfg.eval.n_lights_probs))
        for row in rows:
            log.info("%s", row)
        log.info("results: %s", path)
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
        from selfsup.estimation import EstimateOptions, estimate_files

        est = _plain(cfg.estimate)
        io = {k: est.pop(k) for k in ("input", "output", "progress", "batch", "device", "workers", "depth",
                                      "depth_scale", "intrinsics")}
        return estimate_files(options=EstimateOptions(**est), **io)


@hydra.main(version_base="1.3", config_path="configs", config_name="train")
def main(cfg: DictConfig) -> None:
    from selfsup.scenes.dataset import retain_freed_memory

    retain_freed_memory()  # our own process: rendering and estimation free large arrays by the hundred
    result = run(cfg)
    if cfg.mode == "estimate" and result["failed"]:
        raise SystemExit(1)  # some files failed: each is named in the log above


if __name__ == "__main__":
    main()
