"""The light network that re-renders its own guess (RAFT's layout: grid, encoder, votes,
physics, update, lightnet); see :mod:`selfsup.network.lightnet`."""

from selfsup.network.lightnet import IterativeLightNet, IterativePrediction, StepLights

__all__ = ["IterativeLightNet", "IterativePrediction", "StepLights"]
