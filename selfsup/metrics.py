"""Errors of estimated lights against ground truth, as ``docs/scene-format.md`` defines them.

- position error ``|L_est - L_true| / scene_scale``, estimates and truths paired by
  minimum total distance; an unpaired true or estimated light counts 1.0;
- success: every light of the scene below 0.05;
- angular error: degrees between ``L_est - c`` and ``L_true - c``, ``c`` the
  centroid of the valid points;
- intensity error ``|I_est - I_true| / |I_true|``;
- calibration: the true lights inside the 2-sigma ellipsoid of their paired estimate's
  position covariance (:func:`inside_two_sigma`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["LightErrors", "light_errors", "pair_lights", "inside_two_sigma", "paired_inside_two_sigma", "SUCCESS_THRESHOLD",
           "CHI2_3D_2SIGMA"]

SUCCESS_THRESHOLD = 0.05
CHI2_3D_2SIGMA = 8.03  # the chi-square quantile of 3 degrees of freedom at 95.45% (2 sigma in 1D)


def pair_lights(estimated: Tensor, true: Tensor) -> list[tuple[int, int]]:
    """Pairs ``(est_index, true_index)`` of least total distance; ``(E, 3)``, ``(T, 3)``.

    Exhaustive over assignments (light counts are small: at most 6 here).
    """
    E, T = estimated.shape[0], true.shape[0]
    if E == 0 or T == 0:
        return []
    if max(E, T) > 6:
        raise ValueError(f"pairing supports at most 6 lights a side, got {E} and {T}")
    distance = torch.cdist(estimated.double(), true.double())
    best, best_cost = [], math.inf
    if E <= T:
        for perm in itertools.permutations(range(T), E):
            cost = sum(float(distance[e, t]) for e, t in enumerate(perm))
            if cost < best_cost:
                best, best_cost = list(enumerate(perm)), cost
    else:
        for perm in itertools.permutations(range(E), T):
            cost = sum(float(distance[e, t]) for t, e in enumerate(perm))
            if cost < best_cost:
                best, best_cost = [(e, t) for t, e in enumerate(perm)], cost
    return best


@dataclass(frozen=True)
class LightErrors:
    """Errors of one scene: per true light (unpaired extra estimates appended as 1.0).

    ``position``: list of relative position errors; ``angular``: degrees (paired
    lights only); ``intensity``: relative (paired only); ``success``: all < 0.05;
    ``count_right``: as many estimated lights as true ones.
    """

    position: list[float]
    angular: list[float]
    intensity: list[float]
    success: bool
    count_right: bool


def light_errors(est_pos: Tensor, est_int: Tensor | None, true_pos: Tensor, true_int: Tensor | None,
                 scene_scale: float, centroid: Tensor) -> LightErrors:
    """Errors of estimated lights ``(E, 3)`` against true ones ``(T, 3)``; see the module doc."""
    if scene_scale <= 0:
        raise ValueError(f"scene_scale must be > 0, got {scene_scale}")
    pairs = pair_lights(est_pos, true_pos)
    position, angular, intensity = [], [], []
    for e, t in pairs:
        position.append(float((est_pos[e] - true_pos[t]).norm()) / scene_scale)
        a, b = (est_pos[e] - centroid).double(), (true_pos[t] - centroid).double()
        cos = float((a @ b) / (a.norm() * b.norm()).clamp_min(1e-12))
        angular.append(math.degrees(math.acos(max(-1.0, min(1.0, cos)))))
        if est_int is not None and true_int is not None:
            intensity.append(float((est_int[e] - true_int[t]).norm() / true_int[t].norm().clamp_min(1e-12)))
    unpaired = abs(est_pos.shape[0] - true_pos.shape[0])
    position.extend([1.0] * unpaired)
    return LightErrors(position, angular, intensity, success=bool(position) and max(position) < SUCCESS_THRESHOLD,
                       count_right=est_pos.shape[0] == true_pos.shape[0])


def inside_two_sigma(est_pos: Tensor, est_cov: Tensor, true_pos: Tensor) -> int:
    """How many true lights ``(T, 3)`` fall inside the 2-sigma ellipsoid of the estimate
    they are paired with (:func:`pair_lights`); estimates ``(E, 3)``, their position
    covariances ``(E, 3, 3)``. An unpaired true light is not inside."""
    return sum(inside for _, inside in paired_inside_two_sigma(est_pos, est_cov, true_pos))


def paired_inside_two_sigma(est_pos: Tensor, est_cov: Tensor, true_pos: Tensor) -> list[tuple[float, bool]]:
    """For each true light paired with an estimate (:func:`pair_lights`; shapes as
    :func:`inside_two_sigma`): its distance to that estimate, and whether it lies inside
    the estimate's 2-sigma ellipsoid."""
    out = []
    for e, t in pair_lights(est_pos, true_pos):
        delta = (true_pos[t] - est_pos[e]).double()
        out.append((float(delta.norm()), float(delta @ torch.linalg.pinv(est_cov[e].double()) @ delta) < CHI2_3D_2SIGMA))
    return out
