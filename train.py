"""Hydra entry point: builds objects from configs/ and runs the selected mode.

    python train.py                                   # default: mode=benchmark benchmark=shadow_accuracy
    python train.py mode=benchmark benchmark=render_speed benchmark.quick=true
"""

from __future__ import annotations

import logging

import hydra
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig

log = logging.getLogger(__name__)
MODES = ("benchmark",)


def run(cfg: DictConfig):
    """Run ``cfg.mode``; a plain function so tests can call it with a composed config."""
    if cfg.mode not in MODES:
        raise ValueError(f"unknown mode {cfg.mode!r}; available: {', '.join(MODES)}")
    torch.manual_seed(cfg.seed)
    result = instantiate(cfg.benchmark)
    log.info("benchmark %s done", cfg.benchmark._target_)
    return result


@hydra.main(version_base="1.3", config_path="configs", config_name="train")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
