"""The network's part in an estimate: its light slots as starts, or as the answer (``method=cnn``,
its counted slots settled on the frame by a few LM steps)."""

from __future__ import annotations

import functools
from dataclasses import replace

import torch
from torch import Tensor

from selfsup.estimation import albedo_free
from selfsup.estimation.criterion import Candidate, candidates
from selfsup.estimation.normals import surface_segments
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.problem import FitProblem
from selfsup.estimation.reflectance import albedo_unknown_images, grey_where_unknown, reflectance_unknown, residual_options
from selfsup.estimation.solvers import refine

__all__ = ["checkpoint_of", "cached_network", "network_slots", "network_candidates", "settled_slots"]


def checkpoint_of(options: EstimateOptions) -> str | None:
    """The network ``options`` loads: ``options.checkpoint``, or where it is None the shipped one of
    its method: the iterative network for ``cnn`` (:data:`selfsup.checkpoint.ITERATIVE_CHECKPOINT`:
    settled, it places one-light rooms' lamps in 88-92% of capture frames where the cost-volume
    network placed 71-88%), the cost-volume network as ``cnn+refine``'s start (None)."""
    if options.checkpoint is not None or options.method != "cnn":
        return options.checkpoint
    from selfsup.checkpoint import ITERATIVE_CHECKPOINT

    return str(ITERATIVE_CHECKPOINT)


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


def settled_slots(problem: FitProblem, slots: Tensor, keep: list[int], options: EstimateOptions) -> Tensor:
    """``slots (B, K, 3)`` with each image's first ``keep[i]`` settled on the frame by
    ``tuning.cnn_settle`` LM steps at every ``tuning.cnn_settle_stride``-th pixel, no search:
    where the albedo is unknown (:func:`albedo_unknown_images`) albedo-free on the frame's albedo
    segments (:func:`selfsup.estimation.albedo_free.refine_from`), else as the file's reflectance
    says (without its specular term). The iterative network's first slot lies in its lamp's basin in
    nearly every one-light capture, but its 64-cell steps stop a few centimetres short: settled by 5
    steps at half resolution, one-light Mitsuba and procedural captures went from 11-20 to 21-24 of
    24 placed within 0.05 of the scene, for about 25 ms and the segments' 50 ms a frame
    (docs/decisions.md, 2026-12-07)."""
    steps, stride = options.tuning.cnn_settle, options.tuning.cnn_settle_stride
    if steps == 0:
        return slots
    settled = slots.clone()
    unknown = albedo_unknown_images(problem, options)
    for n_lights in sorted(set(keep)):
        for free in (True, False):
            group = [i for i, (k, u) in enumerate(zip(keep, unknown)) if k == n_lights and u == free]
            if not group:
                continue
            at = torch.tensor(group, dtype=torch.long, device=slots.device)
            sub, start = problem.select(at), slots[at, :n_lights]
            if free:
                labels = None
                if options.tuning.albedo_free_residuals == "segments":
                    g = sub.gbuffer
                    labels = albedo_free.tuned_segments(sub, options.tuning, surface_segments(g.points, g.normals, g.mask))
                fit = albedo_free.refine_from(sub, start, robust_scale=options.tuning.albedo_free_scale, labels=labels,
                                              iterations=(steps, 0), start_stride=stride, **residual_options(options))
            else:
                fit = refine(sub, start, replace(options.tuning.refine, specular=False, max_iters=(steps,),
                                                 strides=(stride,)))
            settled[at, :n_lights] = fit.position.to(settled)
    return settled


def network_candidates(problem: FitProblem, slots: Tensor, present: Tensor, specular_of: list[bool],
                        options: EstimateOptions) -> list[tuple[Candidate, list[Candidate]]]:
    # The network's counted slots (at least one), settled (settled_slots); refine with no
    # iterations solves their intensities and ambient and evaluates the fit.
    keep = present.sum(1).clamp(1, options.max_lights).tolist()
    slots = settled_slots(problem, slots, keep, options)
    problem = grey_where_unknown(problem, options)  # the lights the image's white where the albedo is unknown
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
