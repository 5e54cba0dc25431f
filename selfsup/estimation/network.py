"""The network's part in an estimate: its light slots as starts, or as the answer (``method=cnn``)."""

from __future__ import annotations

import functools
from dataclasses import replace

import torch
from torch import Tensor

from selfsup.estimation.criterion import Candidate, candidates
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.problem import FitProblem
from selfsup.estimation.reflectance import grey_where_unknown, reflectance_unknown
from selfsup.estimation.solvers import refine

__all__ = ["cached_network", "network_slots", "network_candidates"]


@functools.lru_cache(maxsize=4)
def cached_network(checkpoint: str | None, device: str = "cpu"):
    from selfsup.checkpoint import load_network

    return load_network(checkpoint, map_location=device)[0].to(device)


@torch.no_grad()
def network_slots(problem: FitProblem, checkpoint: str | None = None, with_confidence: bool = False):
    """The network's light slots: positions ``(B, K, 3)`` in the network's order and which
    of them it counts ``(B, K)`` bool (its count's first slots); with ``with_confidence`` also
    its calibrated confidence ``(B,)`` that its first slot is a light (zeros for a network
    without one). The network needs no albedo: its cost volumes see the problem's only where
    the file gives one (not one constant, :func:`reflectance_unknown`)."""
    network = cached_network(checkpoint, str(problem.image.device))
    image, g, kd = problem.image.float(), problem.gbuffer, problem.material.kd.float()
    known = ~reflectance_unknown(problem)
    prediction = network(image, g, kd if bool(known.all()) else None)
    position, count = prediction.position, prediction.count
    if bool(known.any()) and not bool(known.all()):  # a mixed batch: the albedo where it is known
        given = network(image, g, kd)
        position = torch.where(known[:, None, None], given.position, position)
        count = torch.where(known, given.count, count)
    present = torch.arange(position.shape[1], device=count.device) < count[:, None]
    if with_confidence:
        confidence = getattr(prediction, "confidence", None)
        if confidence is None or not (bool(known.all()) or not bool(known.any())):
            confidence = torch.zeros(position.shape[0], device=position.device)  # a mixed batch: searched
        return position.to(problem.image.dtype), present, confidence
    return position.to(problem.image.dtype), present


def network_candidates(problem: FitProblem, slots: Tensor, present: Tensor, specular_of: list[bool],
                        options: EstimateOptions) -> list[tuple[Candidate, list[Candidate]]]:
    # The network's counted slots (at least one); refine with no iterations solves
    # their intensities and ambient and evaluates the fit.
    problem = grey_where_unknown(problem, options)  # the lights the image's white where the albedo is unknown
    keep = present.sum(1).clamp(1, options.max_lights).tolist()
    chosen: list[Candidate | None] = [None] * problem.batch
    for n_lights in sorted(set(keep)):
        group = [i for i, k in enumerate(keep) if k == n_lights]
        at = torch.tensor(group, dtype=torch.long, device=slots.device)
        labels = [specular_of[i] for i in group]
        sub = problem.select(at)
        solve = replace(options.tuning.refine, specular=any(labels), max_iters=(0,), strides=(1,))
        fit = refine(sub, slots[at, :n_lights], solve)
        for i, c in zip(group, candidates(sub, fit, n_lights, labels, options)):
            chosen[i] = c
    return [(c, [c]) for c in chosen]
