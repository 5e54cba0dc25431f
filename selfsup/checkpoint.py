"""LightNet checkpoints: one file holds the network's constructor arguments and weights.

The shipped checkpoint (``selfsup/checkpoints/lightnet.pt``) is what ``mode=eval``
and ``estimate.method=cnn|cnn+refine`` use when no other is named; training
checkpoints (``last.pt``, ``best.pt``) add the optimiser, schedule, step and RNG
states for resuming.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from selfsup.model import LightNet

__all__ = ["DEFAULT_CHECKPOINT", "LIGHTNET_CHECKPOINT", "ITERATIVE_CHECKPOINT", "save_network", "load_network", "load_checkpoint", "build_network", "ARCHITECTURES"]

# model_config["architecture"]: the network a config builds (absent: the cost-volume LightNet).
ARCHITECTURES = ("lightnet", "iterative")


def build_network(model_config: dict):
    """The network of a model config: :class:`selfsup.model.LightNet` (``architecture``
    ``lightnet`` or absent) or :class:`selfsup.network.IterativeLightNet` (``iterative``)."""
    config = dict(model_config)
    architecture = config.pop("architecture", "lightnet")
    if architecture not in ARCHITECTURES:
        raise ValueError(f"model.architecture must be one of {ARCHITECTURES}, got {architecture!r}")
    if "widths" in config:
        config["widths"] = tuple(config["widths"])
    if architecture == "iterative":
        from selfsup.network import IterativeLightNet

        return IterativeLightNet(**config)
    return LightNet(**config)

LIGHTNET_CHECKPOINT = Path(__file__).parent / "checkpoints" / "lightnet.pt"  # the cost-volume network; mode=adapt's start
# The iterative network (selfsup.network), `python train.py experiment=iterative`'s run (stopped at its
# 85-minute cap, step 2503): one of estimate.method=cnn's two networks (docs/training.md); as
# cnn+refine's start it lost a frame in two capture sets, so that start stays the cost-volume network.
ITERATIVE_CHECKPOINT = Path(__file__).parent / "checkpoints" / "iterative.pt"
# The same network fine-tuned with objects photographed in the dark (`experiment=iterative_studio`):
# beside the rooms' one in estimate.method=cnn, each frame taking whichever settles to the lower loss.
STUDIO_CHECKPOINT = Path(__file__).parent / "checkpoints" / "iterative_studio.pt"
DEFAULT_CHECKPOINT = LIGHTNET_CHECKPOINT  # what cnn+refine and mode=eval load when none is named
# 2: the network of colour and depth alone (no albedo channel), counting its lights (issue 62).
CHECKPOINT_FORMAT = 2


def save_network(path: str | Path, network: LightNet, model_config: dict, metrics: dict | None = None,
                 extra: dict | None = None) -> Path:
    """Write a checkpoint (atomically: a crash never leaves a half-written file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {"format": CHECKPOINT_FORMAT, "model_config": model_config, "model": network.state_dict(),
             "metrics": metrics or {}, **(extra or {})}
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)
    return path


def load_checkpoint(path: str | Path, map_location="cpu") -> dict:
    """A checkpoint's contents, read with ``weights_only=True``: tensors, numbers, strings
    and containers of them, never arbitrary objects, so that a checkpoint from someone
    else cannot run code here. A file that needs more is refused with the reason.

    Raises:
        ValueError: the file needs arbitrary unpickling, or is no torch checkpoint.
    """
    import pickle

    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as error:
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise ValueError(f"{path}: refused: it holds objects other than tensors, numbers, strings and containers "
                         f"of them, and unpickling them could run code from the file ({reason})") from None
    except (RuntimeError, EOFError, OSError) as error:
        raise ValueError(f"{path} is not a readable torch checkpoint ({type(error).__name__}: {error})") from None


def load_network(path: str | Path | None = None, map_location="cpu") -> tuple[torch.nn.Module, dict]:
    """``(network in eval mode, checkpoint dict)``; ``path`` None: the shipped checkpoint."""
    path = Path(path) if path is not None else DEFAULT_CHECKPOINT
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}" + (
            " (the shipped one: train it with `python train.py`, see docs/training.md)" if path == DEFAULT_CHECKPOINT else ""))
    state = load_checkpoint(path, map_location)
    if not isinstance(state, dict) or "model" not in state or "model_config" not in state:
        raise ValueError(f"{path} is not a LightNet checkpoint (needs 'model' and 'model_config')")
    if state.get("format", 1) != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} holds a LightNet of checkpoint format {state.get('format', 1)}; this version reads "
                         f"format {CHECKPOINT_FORMAT} (the network of colour and depth alone that counts its lights): "
                         "train one with `python train.py` (docs/training.md)")
    network = build_network(state["model_config"])
    network.load_state_dict(state["model"])
    return network.eval(), state
