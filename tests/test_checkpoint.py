"""Checkpoints load with weights_only: a file that needs arbitrary unpickling is refused."""

import collections

import pytest
import torch

from selfsup.checkpoint import DEFAULT_CHECKPOINT, load_checkpoint, load_network


class _Payload:
    """Stands for any object a checkpoint from elsewhere could carry (its unpickling runs code)."""


def test_the_shipped_checkpoint_loads_with_weights_only():
    state = load_checkpoint(DEFAULT_CHECKPOINT)
    assert {"model", "model_config"} <= set(state)
    network, _ = load_network()
    assert not network.training


def test_a_checkpoint_holding_an_arbitrary_object_is_refused_with_the_reason(tmp_path):
    state = load_checkpoint(DEFAULT_CHECKPOINT)
    state["extra"] = _Payload()
    path = tmp_path / "foreign.pt"
    torch.save(state, path)
    with pytest.raises(ValueError, match="refused: it holds objects other than tensors.*could run code"):
        load_checkpoint(path)
    with pytest.raises(ValueError, match="refused"):
        load_network(path)


def test_a_file_that_is_no_checkpoint_is_named(tmp_path):
    path = tmp_path / "notes.pt"
    path.write_text("not a checkpoint")
    with pytest.raises(ValueError, match="notes.pt is not a readable torch checkpoint|refused"):
        load_checkpoint(path)


def test_plain_containers_load(tmp_path):
    path = tmp_path / "plain.pt"
    torch.save({"a": [1, 2.5, "x"], "b": collections.OrderedDict(w=torch.ones(2))}, path)
    assert load_checkpoint(path)["a"] == [1, 2.5, "x"]


def test_a_checkpoint_of_the_network_before_camera_inputs_is_named(tmp_path):
    # Format 1 networks read an albedo channel and had two slots: the message says what to do.
    state = load_checkpoint(DEFAULT_CHECKPOINT)
    state["format"] = 1
    path = tmp_path / "old.pt"
    torch.save(state, path)
    with pytest.raises(ValueError, match="format 1.*reads format 2.*python train.py"):
        load_network(path)
