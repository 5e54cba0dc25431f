"""Ground-truth metrics of a light-estimation network on a pool of scenes.

Training never sees these numbers through its loss; validation and ``mode=eval``
report them (definitions in :mod:`selfsup.metrics` and ``docs/scene-format.md``).
"""

from __future__ import annotations

import statistics

import torch
from torch import Tensor

from selfsup.losses import scene_batch
from selfsup.metrics import SUCCESS_THRESHOLD, light_errors
from selfsup.model import LightNet, scene_frame

__all__ = ["evaluate_network", "summarise", "calibrate_count_threshold", "calibrate_confidence", "fit_logistic",
           "COUNT_THRESHOLDS"]

# The presence thresholds calibration chooses from.
COUNT_THRESHOLDS = (0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.99, 1.0)


def summarise(rows: list[dict]) -> dict[str, float]:
    """Medians and rates over per-scene rows of :func:`evaluate_network`."""
    if not rows:
        raise ValueError("no scenes to summarise")
    by_count = {}
    for n, name in ((1, "one_light_success"), (2, "two_light_right_count"), (3, "three_light_right_count")):
        these = [r for r in rows if r.get("lights_true") == n]
        if these:  # per room size: placed (one light), counted (two and three)
            by_count[name] = statistics.fmean(float(r["success"] if n == 1 else r["count_right"]) for r in these)
    return {
        "scenes": len(rows),
        "median_position_error": statistics.median(r["position_error"] for r in rows),
        "mean_position_error": statistics.fmean(r["position_error"] for r in rows),
        "median_angular_error": statistics.median(r["angular_error"] for r in rows),
        "mean_angular_error": statistics.fmean(r["angular_error"] for r in rows),
        "success_rate": statistics.fmean(float(r["success"]) for r in rows),
        "count_accuracy": statistics.fmean(float(r["count_right"]) for r in rows),
        **by_count,
    }


@torch.no_grad()
def evaluate_network(network: LightNet, pool: dict[str, Tensor], batch_size: int = 64,
                     albedo: bool = False) -> list[dict]:
    """One row per scene of ``pool`` (stacked items with ground truth): the worst
    light's ``position_error`` (an unpaired light counts 1.0), the median
    ``angular_error`` of the paired lights (180 when none), ``success``, ``count_right``.
    The network's count says how many of its slots are lights; ``albedo``: its cost
    volumes see the pool's albedo (as for a scene file that gives it), else none.

    The network runs in eval mode on its own device; the pool may live anywhere.
    """
    return _rows_by_threshold(network, pool, (network.count_threshold,), batch_size, albedo)[0]


def _rows_by_threshold(network: LightNet, pool: dict[str, Tensor], thresholds: tuple[float, ...], batch_size: int,
                       albedo: bool) -> list[list[dict]]:
    # evaluate_network's rows under each count threshold, from one pass of the network.
    was_training = network.training
    network.eval()
    device = next(network.parameters()).device
    rows: list[list[dict]] = [[] for _ in thresholds]
    try:
        for start in range(0, pool["image"].shape[0], batch_size):
            batch = {key: value[start:start + batch_size].to(device) for key, value in pool.items()}
            scenes = scene_batch(batch)
            prediction = network(scenes.image, scenes.gbuffer, scenes.material.kd if albedo else None)
            centre = scene_frame(scenes.image, scenes.gbuffer).centre
            for t, threshold in enumerate(thresholds):
                prediction.count_threshold = threshold
                for i in range(scenes.image.shape[0]):
                    rows[t].append(_scene_row(prediction, i, batch, centre[i]))
    finally:
        network.train(was_training)
    return rows


def _scene_row(prediction, i: int, batch: dict[str, Tensor], centre: Tensor) -> dict:
    position, intensity = prediction.lights_of(i)
    truth = batch["light_mask"][i]
    errors = light_errors(position.float().cpu(), intensity.float().cpu(), batch["light_pos"][i][truth].cpu(),
                          batch["light_intensity"][i][truth].cpu(), float(batch["scene_scale"][i]), centre.float().cpu())
    return {"position_error": max(errors.position),
            "angular_error": statistics.median(errors.angular) if errors.angular else 180.0,
            "success": max(errors.position) < SUCCESS_THRESHOLD, "count_right": errors.count_right,
            "lights_true": int(truth.sum()), "lights_found": int(position.shape[0])}


@torch.no_grad()
def calibrate_count_threshold(network: LightNet, pool: dict[str, Tensor], batch_size: int = 64,
                              albedo: bool = False) -> tuple[float, list[dict]]:
    """The presence threshold of :data:`COUNT_THRESHOLDS` under which most of ``pool``'s
    scenes succeed (every light within 0.05 of the scene size, the count right), then most
    are counted right; the lowest of equals; and :func:`evaluate_network`'s rows under it
    (one pass of the network for both). A slot the network counts but cannot place costs a
    scene its success: a count head that tells the scenes' counts apart no better than it
    places their lights gets a threshold that adds few lights."""
    rows = _rows_by_threshold(network, pool, COUNT_THRESHOLDS, batch_size, albedo)
    score = [(sum(r["success"] for r in these), sum(r["count_right"] for r in these)) for these in rows]
    best = max(range(len(score)), key=lambda i: (score[i], -i))
    return COUNT_THRESHOLDS[best], rows[best]


@torch.no_grad()
def calibrate_confidence(network, pool: dict[str, Tensor], batch_size: int = 64, ridge: float = 1e-2
                         ) -> tuple[tuple[float, float, float], float]:
    """The logistic model of an iterative network's confidence
    (:func:`selfsup.network.lightnet.confidence_features`) fitted on ``pool``'s scenes to
    whether slot 0 lands within 0.05 of the scene size of a true light (Newton's method on the
    ridge-penalised log likelihood); and the share of scenes where it does."""
    from selfsup.network.lightnet import confidence_features

    was_training = network.training
    network.eval()
    device = next(network.parameters()).device
    features, hits = [], []
    try:
        for start in range(0, pool["image"].shape[0], batch_size):
            batch = {key: value[start:start + batch_size].to(device) for key, value in pool.items()}
            scenes = scene_batch(batch)
            prediction = network(scenes.image, scenes.gbuffer)
            distance = (prediction.position[:, :1] - batch["light_pos"]).norm(dim=-1)  # (B, lights)
            distance = torch.where(batch["light_mask"], distance, torch.full_like(distance, float("inf")))
            hits.append((distance.amin(1) < SUCCESS_THRESHOLD * batch["scene_scale"]).double().cpu())
            features.append(confidence_features(prediction.steps).double().cpu())
    finally:
        network.train(was_training)
    x, y = torch.cat(features), torch.cat(hits)
    return tuple(float(v) for v in fit_logistic(x, y, ridge)), float(y.mean())


def fit_logistic(x: Tensor, y: Tensor, ridge: float = 1e-2, iterations: int = 25) -> Tensor:
    """Weights ``(F,)`` of ``P(y = 1) = sigmoid(x @ w)`` for features ``x (N, F)`` and labels
    ``y (N,)`` in {0, 1}: Newton's method on the log likelihood with an L2 ``ridge`` (which
    keeps separable data finite)."""
    x, y = x.double(), y.double()
    w = torch.zeros(x.shape[1], dtype=torch.float64)
    eye = torch.eye(x.shape[1], dtype=torch.float64)
    for _ in range(iterations):
        p = torch.sigmoid(x @ w)
        gradient = x.T @ (p - y) + ridge * w
        hessian = (x * (p * (1 - p))[:, None]).T @ x + ridge * eye
        w = w - torch.linalg.solve(hessian, gradient)
    return w
