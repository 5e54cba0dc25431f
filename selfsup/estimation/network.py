"""The network's part in an estimate: its light slots as starts (``cnn+refine``), or as the answer
(``method=cnn``, :func:`network_answer`: the shipped networks' slots settled on the frame by a few LM
steps, the frame's criterion choosing the network and the count)."""

from __future__ import annotations

import functools
import math
from dataclasses import replace

import torch
from torch import Tensor

from selfsup.estimation import albedo_free
from selfsup.estimation.criterion import Candidate, bic, block_px, candidates
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.problem import FitProblem
from selfsup.estimation.reflectance import (albedo_free_segments, albedo_unknown_images, grey_where_unknown,
                                            reflectance_unknown, residual_options)
from selfsup.estimation.solvers import refine

__all__ = ["checkpoints_of", "answer_checkpoints", "start_checkpoint", "cached_network", "network_slots",
           "network_answer", "network_candidates", "settled_slots", "counted", "network_segments"]


def checkpoints_of(options: EstimateOptions) -> tuple[str | None, ...]:
    """Every network ``options`` may load (to load them before any frame): those of
    :func:`answer_checkpoints`, then :func:`start_checkpoint`'s (None: the cost-volume network)."""
    answer = answer_checkpoints(options)
    if options.method == "cnn":
        return answer
    return answer + (start_checkpoint(options),)


def answer_checkpoints(options: EstimateOptions) -> tuple[str | None, ...]:
    """The networks of :func:`network_answer` under ``options``: ``options.checkpoint`` with
    ``method=cnn``, or where it is None the shipped iterative networks, the rooms' and the one
    trained with objects in the dark (:data:`selfsup.checkpoint.ITERATIVE_CHECKPOINT`,
    :data:`~selfsup.checkpoint.STUDIO_CHECKPOINT`; each frame takes the one whose first light settles
    to the lower loss), for ``cnn`` and for ``cnn+refine`` with ``tuning.cnn_start=settled`` (its
    first light where the albedo is unknown); none otherwise."""
    if options.method == "cnn" and options.checkpoint is not None:
        return (options.checkpoint,)
    shipped = options.method == "cnn" or (options.method == "cnn+refine" and options.checkpoint is None
                                          and options.tuning.cnn_start == "settled")
    if not shipped:
        return ()
    from selfsup.checkpoint import ITERATIVE_CHECKPOINT, STUDIO_CHECKPOINT

    return (str(ITERATIVE_CHECKPOINT), str(STUDIO_CHECKPOINT))


def start_checkpoint(options: EstimateOptions) -> str | None:
    """The network whose lights join ``cnn+refine``'s searches (with a file's reflectance, and with
    ``tuning.cnn_start=search``): ``options.checkpoint``, None being the shipped cost-volume network."""
    return options.checkpoint


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


class _Settles:
    """The settles of one set of slots ``(B, K, 3)``, each light count once: ``of(n)`` is
    :func:`_settled` of every image's first ``n`` (settled slots, loss, residuals, weakest share)."""

    def __init__(self, problem: FitProblem, slots: Tensor, options: EstimateOptions, labels: Tensor | None):
        self.problem, self.slots, self.options, self.labels = problem, slots, options, labels
        self.done: dict[int, tuple[Tensor, Tensor, Tensor, Tensor]] = {}

    def of(self, n: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        if n not in self.done:
            self.done[n] = _settled(self.problem, self.slots, [n] * self.problem.batch, self.options, self.labels)
        return self.done[n]


def network_answer(problem: FitProblem, options: EstimateOptions, labels: Tensor | None = None
                   ) -> tuple[Tensor, list[int]]:
    """``method=cnn``'s lights: slots ``(B, K, 3)``, each image's first ``count[i]`` settled on the
    frame (:func:`settled_slots`), and that count (:func:`counted`). The slots are its one network's,
    or of several (:func:`answer_checkpoints`) each image's whose first slot, settled as one light,
    explains the frame with the lower loss. On the DiLiGenT ball, bear and cat the network trained
    in the dark was taken in every frame (1.9, 1.7, 10.8 degrees, where the rooms' network alone gave
    3.4, 2.5, 26.5); on one-light Mitsuba and procedural captures the choice placed as many lamps as
    the rooms' network alone, within one frame a set (docs/decisions.md, 2026-12-07). ``labels``:
    the images' albedo segments (:func:`network_segments`), where known."""
    if labels is None:
        labels = network_segments(problem, options)
    answers = [network_slots(problem, path) for path in answer_checkpoints(options)]
    if len({slots.shape[1] for slots, _ in answers}) != 1:
        raise ValueError(f"the networks of estimate.method=cnn must have as many slots, got "
                         f"{[slots.shape[1] for slots, _ in answers]}")
    settles = [_Settles(problem, slots, options, labels) for slots, _ in answers]
    if len(answers) == 1:
        (slots, present), chosen = answers[0], settles[0]
    else:
        losses = torch.stack([each.of(1)[1] for each in settles], 1)
        pick = losses.nan_to_num(nan=math.inf).argmin(1)
        rows = torch.arange(problem.batch, device=pick.device)
        slots = torch.stack([slots for slots, _ in answers], 1)[rows, pick]
        present = torch.stack([present for _, present in answers], 1)[rows, pick]
        chosen = _Settles(problem, slots, options, labels)
        chosen.done[1] = tuple(torch.stack([each.of(1)[j] for each in settles], 1)[rows, pick] for j in range(4))
    count = counted(problem, slots, present, options, labels, chosen)
    settled = slots.clone()
    for n in sorted(set(count)):
        at = torch.tensor([i for i, k in enumerate(count) if k == n], dtype=torch.long, device=slots.device)
        settled[at] = chosen.of(n)[0][at]
    return settled, count


def settled_slots(problem: FitProblem, slots: Tensor, keep: list[int], options: EstimateOptions,
                  labels: Tensor | None = None) -> Tensor:
    """``slots (B, K, 3)`` with each image's first ``keep[i]`` settled on the frame by
    ``tuning.cnn_settle`` LM steps at every ``tuning.cnn_settle_stride``-th pixel, no search:
    where the albedo is unknown (:func:`albedo_unknown_images`) albedo-free on the frame's albedo
    segments (:func:`selfsup.estimation.albedo_free.refine_from`), else as the file's reflectance
    says (without its specular term). The iterative network's first slot lies in its lamp's basin in
    nearly every one-light capture, but its 64-cell steps stop a few centimetres short: settled by 5
    steps at half resolution, one-light Mitsuba and procedural captures went from 11-20 to 21-24 of
    24 placed within 0.05 of the scene, for about 25 ms and the segments' 50 ms a frame
    (docs/decisions.md, 2026-12-07). ``labels``: as :func:`network_answer`."""
    return _settled(problem, slots, keep, options, network_segments(problem, options) if labels is None else labels)[0]


def _settled(problem: FitProblem, slots: Tensor, keep: list[int], options: EstimateOptions,
             labels: Tensor | None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    # settled_slots, and each image's loss (B,) there, the residuals it sums (B,) (the albedo-free
    # fit's, or the robust cost and valid values with the file's reflectance; NaN with cnn_settle=0)
    # and its weakest light's share of the fitted shading (B,) (albedo-free only; 1 elsewhere).
    # ``labels``: :func:`network_segments` of every image (None: the fit uses no segments).
    steps, stride = options.tuning.cnn_settle, options.tuning.cnn_settle_stride
    loss = torch.full((problem.batch,), math.nan, dtype=problem.image.dtype, device=problem.image.device)
    pairs = torch.zeros(problem.batch, dtype=torch.long, device=problem.image.device)
    share = torch.ones_like(loss)
    if steps == 0:
        return slots, loss, pairs, share
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
                fit = albedo_free.refine_from(sub, start, robust_scale=options.tuning.albedo_free_scale,
                                              labels=None if labels is None else labels[at], iterations=(steps, 0),
                                              start_stride=stride, **residual_options(options))
                loss[at], pairs[at] = fit.loss.to(loss), fit.pairs.to(pairs)
                share[at] = albedo_free.light_shares(sub, fit).amin(1).to(share)
            else:
                fit = refine(sub, start, replace(options.tuning.refine, specular=False, max_iters=(steps,),
                                                 strides=(stride,)))
                loss[at], pairs[at] = fit.cost.to(loss), fit.n.to(pairs)
            settled[at, :n_lights] = fit.position.to(settled)
    return settled, loss, pairs, share


def network_segments(problem: FitProblem, options: EstimateOptions) -> Tensor | None:
    """Every image's albedo segments ``(B, H, W)`` as the albedo-free fit finds them, for the
    settle; None where no image's albedo is unknown or the fit uses pairs."""
    if not any(albedo_unknown_images(problem, options)):
        return None
    return albedo_free_segments(problem, options)[0]


def counted(problem: FitProblem, slots: Tensor, present: Tensor, options: EstimateOptions,
            labels: Tensor | None = None, settles: _Settles | None = None) -> list[int]:
    """How many of each image's slots ``method=cnn`` keeps: with ``tuning.cnn_count=criterion``, where
    the albedo is unknown, the ``n`` (1 .. K, at most ``max_lights``) whose first ``n`` slots, settled
    (:func:`settled_slots`), give the albedo-free fit's lowest :func:`bic` (four parameters a light,
    the estimator's blocks) with each light carrying ``tuning.min_light_share`` of the fitted shading:
    the frame's evidence in place of the network's presences (which told one-light rooms from
    two-light ones no better than chance, docs/training.md); elsewhere, and with ``network``, its
    presences' count (:attr:`selfsup.network.IterativePrediction.count`). ``labels``: as
    :func:`network_answer`; ``settles``: these slots' settles done so far."""
    keep = present.sum(1).clamp(1, options.max_lights).tolist()
    top = min(slots.shape[1], options.max_lights)
    unknown = albedo_unknown_images(problem, options)
    if options.tuning.cnn_count != "criterion" or options.tuning.cnn_settle == 0 or top < 2 or not any(unknown):
        return keep
    if settles is None:
        settles = _Settles(problem, slots, options, network_segments(problem, options) if labels is None else labels)
    block = block_px(options, problem.image.shape[-1], albedo_free=True)
    values = []
    for n in range(1, top + 1):
        _, loss, pairs, share = settles.of(n)
        values.append([bic(l, int(p), 4 * n, block) if p >= 1 and (n == 1 or w >= options.tuning.min_light_share)
                       else math.inf for l, p, w in zip(loss.tolist(), pairs.tolist(), share.tolist())])
    return [min(range(top), key=lambda n: values[n][i]) + 1 if u else k for i, (k, u) in enumerate(zip(keep, unknown))]


def network_candidates(problem: FitProblem, slots: Tensor, count: list[int], specular_of: list[bool],
                       options: EstimateOptions) -> list[tuple[Candidate, list[Candidate]]]:
    # The first count[i] of each image's slots (network_answer's); refine with no iterations solves
    # their intensities and ambient and evaluates the fit.
    problem = grey_where_unknown(problem, options)  # the lights the image's white where the albedo is unknown
    chosen: list[Candidate | None] = [None] * problem.batch
    for n_lights in sorted(set(count)):
        group = [i for i, k in enumerate(count) if k == n_lights]
        at = torch.tensor(group, dtype=torch.long, device=slots.device)
        labels = [specular_of[i] for i in group]
        sub = problem.select(at)
        solve = replace(options.tuning.refine, specular=any(labels), max_iters=(0,), strides=(1,))
        fit = refine(sub, slots[at, :n_lights], solve)
        for i, c in zip(group, candidates(sub, fit, n_lights, labels, options)):
            chosen[i] = c
    return [(c, [c]) for c in chosen]
