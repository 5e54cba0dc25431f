"""A constant-velocity Kalman filter of one light's position, and the pairing of lights to tracks.

The state is the light's position and its velocity per frame (metres, the camera's
frame); the process noise is a white acceleration of standard deviation ``q`` metres
per frame squared (the discrete white-noise acceleration model); a measurement is a
position with its covariance (the estimator's, :mod:`selfsup.estimation.uncertainty`).
A still light's filtered position then averages its measurements' noise away, and a
light moving steadily is followed without lag.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["LightState", "start_state", "predict", "update", "pair_lights", "moved"]


@dataclass
class LightState:
    """One tracked light: ``mean (6,)`` position then velocity per frame, ``cov (6, 6)``, float64."""

    mean: Tensor
    cov: Tensor

    @property
    def position(self) -> Tensor:
        return self.mean[:3]

    @property
    def position_cov(self) -> Tensor:
        return self.cov[:3, :3]


def start_state(position: Tensor, position_cov: Tensor, velocity_std: float) -> LightState:
    """A new track at a measured ``position (3,)`` with covariance ``(3, 3)``, still, its
    velocity unknown to ``velocity_std`` metres per frame."""
    mean = torch.cat([position.double(), torch.zeros(3, dtype=torch.float64)])
    cov = torch.zeros(6, 6, dtype=torch.float64)
    cov[:3, :3] = position_cov.double()
    cov[3:, 3:] = torch.eye(3, dtype=torch.float64) * velocity_std**2
    return LightState(mean, cov)


def _transition() -> Tensor:
    F = torch.eye(6, dtype=torch.float64)
    F[:3, 3:] = torch.eye(3, dtype=torch.float64)
    return F


def predict(state: LightState, acceleration_std: float) -> LightState:
    """The state one frame later: ``p + v``, its covariance grown by the process noise."""
    F = _transition()
    eye = torch.eye(3, dtype=torch.float64)
    q = acceleration_std**2
    Q = torch.cat([torch.cat([eye / 4, eye / 2], 1), torch.cat([eye / 2, eye], 1)]) * q
    return LightState(F @ state.mean, F @ state.cov @ F.T + Q)


def update(state: LightState, position: Tensor, position_cov: Tensor) -> LightState:
    """The state given a measured ``position (3,)`` with covariance ``(3, 3)`` (Joseph form,
    so the covariance stays symmetric and positive)."""
    H = torch.cat([torch.eye(3, dtype=torch.float64), torch.zeros(3, 3, dtype=torch.float64)], 1)
    R = position_cov.double()
    S = H @ state.cov @ H.T + R
    gain = torch.linalg.solve(S, H @ state.cov).T  # (6, 3): P H^T S^-1, S and P symmetric
    innovation = position.double() - H @ state.mean
    keep = torch.eye(6, dtype=torch.float64) - gain @ H
    cov = keep @ state.cov @ keep.T + gain @ R @ gain.T
    return LightState(state.mean + gain @ innovation, (cov + cov.T) / 2)


def moved(state: LightState, rotation: Tensor, translation: Tensor) -> LightState:
    """The state seen from a camera that moved: ``rotation (3, 3)`` and ``translation (3,)``
    take a point of the old camera's frame to the new one's (``x' = R x + t``); the velocity
    and every covariance block turn with ``R`` (a still light stays still in the room)."""
    R = rotation.double()
    turn = torch.zeros(6, 6, dtype=torch.float64)
    turn[:3, :3] = R
    turn[3:, 3:] = R
    mean = turn @ state.mean
    mean[:3] += translation.double()
    return LightState(mean, turn @ state.cov @ turn.T)


def pair_lights(tracked: Tensor, found: Tensor, radius: float) -> list[int | None]:
    """For each found light ``(M, 3)``, the tracked light ``(N, 3)`` it continues, or None:
    the pairing of least summed distance (every assignment tried: a scene holds few
    lights), pairs farther apart than ``radius`` cut."""
    M, N = found.shape[0], tracked.shape[0]
    if M == 0 or N == 0:
        return [None] * M
    distance = torch.cdist(found.double(), tracked.double())  # (M, N)
    best, best_cost = None, float("inf")
    k = min(M, N)
    for rows in itertools.combinations(range(M), k):
        for cols in itertools.permutations(range(N), k):
            cost = float(sum(distance[r, c] for r, c in zip(rows, cols)))
            if cost < best_cost:
                best, best_cost = dict(zip(rows, cols)), cost
    return [best[m] if m in best and float(distance[m, best[m]]) <= radius else None for m in range(M)]
