"""One source of defaults: every config node that mirrors a dataclass holds that dataclass's defaults.

The YAML shows the settings a user chooses; the dataclasses are what the code runs
with when called from Python. A value changed in one place and not the other fails here.
"""

import dataclasses
import inspect

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pathlib import Path

from selfsup.engine import LoggerOptions, OptimOptions, TrainerOptions
from selfsup.estimation import EstimateOptions, estimate_files
from selfsup.losses import LossOptions, TeacherOptions
from selfsup.network import IterativeLightNet
from selfsup.sequence_loss import SequenceLossOptions

CONFIGS = Path(__file__).parents[1] / "configs"


@pytest.fixture(scope="module")
def cfg():
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose(config_name="train")


def _plain(value):
    return tuple(_plain(v) for v in value) if isinstance(value, list) else value


def _defaults(cls) -> dict:
    out = {}
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            out[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            out[f.name] = f.default_factory()
    return out


@pytest.mark.parametrize("path, node, cls", [
    ("experiment/default.yaml", "loss", LossOptions),  # the loss node lives in the embedded experiment
    ("experiment/default.yaml", "loss.teacher", TeacherOptions),  # the pool teacher's weights (training)
    ("optim/adamw.yaml", None, OptimOptions),
    ("logger/tensorboard.yaml", None, LoggerOptions),
    ("trainer/default.yaml", None, TrainerOptions),  # an experiment may change them: it lists what it changes
    ("experiment/iterative.yaml", "loss", SequenceLossOptions),  # the iterative network's sequence loss
])
def test_a_config_group_holds_its_dataclass_defaults(path, node, cls):
    values = OmegaConf.to_container(OmegaConf.load(CONFIGS / path), resolve=False)
    for key in (node or "").split(".") if node else ():
        values = values[key]
    if cls is LossOptions:
        values = {k: v for k, v in values.items() if k != "teacher"}  # its own node, TeacherOptions
    defaults = _defaults(cls)
    assert set(values) <= set(defaults), f"{path}: keys the dataclass lacks: {set(values) - set(defaults)}"
    for key, value in values.items():
        if isinstance(value, str) and value.startswith("${"):
            continue  # an interpolation (the run folder): no default to compare
        assert _plain(value) == defaults[key], f"{path} {key}: YAML {value!r}, {cls.__name__} {defaults[key]!r}"


def test_the_iterative_model_group_holds_the_networks_defaults():
    values = OmegaConf.to_container(OmegaConf.load(CONFIGS / "model/iterative.yaml"), resolve=False)
    assert values.pop("architecture") == "iterative"
    defaults = {name: p.default for name, p in inspect.signature(IterativeLightNet).parameters.items()}
    assert set(values) == set(defaults), set(values) ^ set(defaults)
    for key, value in values.items():
        assert _plain(value) == defaults[key], f"model/iterative.yaml {key}: YAML {value!r}, code {defaults[key]!r}"


def test_the_estimate_group_is_the_users_dozen_settings_with_the_codes_defaults(cfg):
    values = OmegaConf.to_container(cfg.estimate, resolve=False)
    assert len(values) <= 15, sorted(values)
    options = _defaults(EstimateOptions)
    files = {name: p.default for name, p in inspect.signature(estimate_files).parameters.items()
             if p.default is not inspect.Parameter.empty}
    command = {"input", "output", "batch", "device", "workers", "progress", "depth", "depth_scale", "intrinsics",
               "overwrite", "shard"}
    assert set(values) == (set(options) - {"tuning"}) | command
    for key in set(options) - {"tuning"}:
        assert _plain(values[key]) == options[key], f"estimate.{key}: YAML {values[key]!r}, EstimateOptions {options[key]!r}"
    for key in ("progress", "device", "depth", "depth_scale", "intrinsics", "overwrite", "shard"):  # batch, workers: the command's
        assert values[key] == files[key], f"estimate.{key}: YAML {values[key]!r}, estimate_files {files[key]!r}"


def test_the_track_group_is_the_users_settings_with_the_codes_defaults(cfg):
    from selfsup.tracking import Tracker, track_files

    values = OmegaConf.to_container(cfg.track, resolve=False)
    options = _defaults(EstimateOptions)
    files = {name: p.default for name, p in inspect.signature(track_files).parameters.items()
             if p.default is not inspect.Parameter.empty}
    command = {"input", "output", "refresh", "device", "progress", "depth_scale", "intrinsics", "overwrite"}
    assert set(values) == (set(options) - {"tuning"}) | command
    for key in set(options) - {"tuning"}:
        assert _plain(values[key]) == options[key], f"track.{key}: YAML {values[key]!r}, EstimateOptions {options[key]!r}"
    for key in command - {"input", "output"}:
        assert values[key] == files[key], f"track.{key}: YAML {values[key]!r}, track_files {files[key]!r}"
    assert values["refresh"] == Tracker().refresh


def test_the_scan_group_is_the_users_settings_with_the_codes_defaults(cfg):
    from selfsup.scan import scan_files

    values = OmegaConf.to_container(cfg.scan, resolve=False)
    options = _defaults(EstimateOptions)
    files = {name: p.default for name, p in inspect.signature(scan_files).parameters.items()
             if p.default is not inspect.Parameter.empty}
    command = {"input", "output", "frames_output", "max_frames", "device", "workers", "progress", "depth_scale",
               "intrinsics", "fuse"}
    assert set(values) - command <= set(options) - {"tuning"}, sorted(values)
    for key in set(values) - command:
        assert _plain(values[key]) == options[key], f"scan.{key}: YAML {values[key]!r}, EstimateOptions {options[key]!r}"
    for key in command - {"input", "output", "fuse"}:
        assert values[key] == files[key], f"scan.{key}: YAML {values[key]!r}, scan_files {files[key]!r}"
    assert values["fuse"] == {}  # the fusion's constants: FuseOptions' own defaults



def test_the_adapt_group_holds_the_codes_defaults(cfg):
    from selfsup.adapt import AdaptOptions, FrameOptions, GuardOptions, TeacherOptions

    values = OmegaConf.to_container(cfg.adapt, resolve=False)
    nested = {"frames": FrameOptions, "guards": GuardOptions, "teacher": TeacherOptions}
    command = {"input", "out", "checkpoint", "procedural", "validation_scenes"}  # train.py builds these
    assert set(values) == set(_defaults(AdaptOptions)) | set(nested) | command
    for key, default in _defaults(AdaptOptions).items():
        assert _plain(values[key]) == default, f"adapt.{key}: YAML {values[key]!r}, AdaptOptions {default!r}"
    for node, cls in nested.items():
        assert set(values[node]) == set(_defaults(cls)), node
        for key, default in _defaults(cls).items():
            assert _plain(values[node][key]) == default, f"adapt.{node}.{key}: YAML {values[node][key]!r}, {default!r}"
