"""Hydra entry point: builds objects from configs/ and runs the selected mode.

    python train.py                                        # mode=train on procedural scenes
    python train.py mode=generate generate.out=data/test generate.count=200
    python train.py mode=estimate estimate.input=scenes/ estimate.output=lights.jsonl
    python train.py mode=benchmark benchmark=render_speed benchmark.quick=true
"""

from __future__ import annotations

import logging

import hydra
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger(__name__)
MODES = ("benchmark", "generate", "estimate")


def _plain(node) -> dict:
    return OmegaConf.to_container(node, resolve=True, throw_on_missing=True)


def build_data(cfg: DictConfig):
    """``(SamplerConfig, Degradations, samples)`` from the ``data`` group."""
    from selfsup.scenes.dataset import sampler_config
    from selfsup.scenes.degrade import Degradations

    return sampler_config(**_plain(cfg.data.sampler)), Degradations(**_plain(cfg.data.degradations)), cfg.data.samples


def run(cfg: DictConfig):
    """Run ``cfg.mode``; a plain function so tests can call it with a composed config."""
    if cfg.mode not in MODES:
        raise ValueError(f"unknown mode {cfg.mode!r}; available: {', '.join(MODES)}")
    torch.manual_seed(cfg.seed)
    if cfg.mode == "benchmark":
        result = instantiate(cfg.benchmark)
        log.info("benchmark %s done", cfg.benchmark._target_)
        return result
    if cfg.mode == "generate":
        from selfsup.scenes.generate import generate_set

        sampler, degradations, samples = build_data(cfg)
        return generate_set(sampler=sampler, degradations=degradations, samples=samples, **_plain(cfg.generate))
    if cfg.mode == "estimate":
        from selfsup.estimate import EstimateOptions, estimate_files
        from selfsup.refine import RefineOptions

        est = _plain(cfg.estimate)
        refine = RefineOptions(**{k: tuple(v) if isinstance(v, list) else v for k, v in est.pop("refine").items()})
        io = {k: est.pop(k) for k in ("input", "output", "progress")}
        return estimate_files(io["input"], io["output"], EstimateOptions(refine=refine, **est), progress=io["progress"])


@hydra.main(version_base="1.3", config_path="configs", config_name="train")
def main(cfg: DictConfig) -> None:
    result = run(cfg)
    if cfg.mode == "estimate" and result["failed"]:
        raise SystemExit(1)  # some files failed: each is named in the log above


if __name__ == "__main__":
    main()
