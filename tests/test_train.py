import pytest
from hydra import compose, initialize_config_dir

from tests.test_readme import ROOT
from train import run


def _cfg(*overrides):
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "configs")):
        return compose(config_name="train", overrides=list(overrides))


def test_benchmark_mode_runs_the_shadow_benchmark_shrunk():
    rows, path = run(_cfg("mode=benchmark", "benchmark.height=30", "benchmark.width=40", "benchmark.write=false"))
    assert path is None and rows[-1]["light"] == "**mean**"
    assert 0.8 < rows[-1]["epipolar_agree"] <= 1.0


def test_unknown_mode_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown mode 'fly'"):
        run(_cfg("mode=fly"))
