"""The self-supervised loss: re-render the scene from the predicted lights, compare.

No ground-truth light enters :func:`reconstruction_loss` unless the ablation
switch ``supervised_weight`` is above zero.

The image is linear in the light intensities and the ambient term, so for the
predicted light positions the best intensities are solved in closed form
(:mod:`selfsup.linear`) and the photometric error of that re-rendering drives
the positions (variable projection: the network cannot lower the loss by
trading distance for brightness, which otherwise sends lights far away). The
network's own intensity, ambient and presence heads learn from the same fit:

- a slot is *needed* when removing it from the fit raises the photometric error
  by more than ``need_ratio`` of it (and more than ``need_floor``); slot 0 (the
  network's best position hypothesis) is always needed. The count head learns their
  number (cross entropy), so unneeded slots switch off: the network models only what a
  scene needs.
- intensities and ambient learn the closed-form values of the fit with the
  needed slots (log-L1), treated as constants.

Each slot's position hypotheses (:class:`selfsup.model.LightNet`) are scored by the
same robust photometric error: each hypothesis is re-rendered as one more light beside
the slots before it (without cast shadows and every ``hypothesis_stride``-th pixel, for
speed; those slots' intensities and the ambient fitted first, the hypothesis's then, in
closed form, with the scene's albedo), and the scores learn the softmax of the negative
errors (temperature ``hypothesis_temperature`` times the best error). The slots' learned
offsets follow the shadowed photometric error.

Without an albedo (a capture's frames, ``mode=adapt``) the caller gives each pixel's region
of one albedo: each fit then solves the regions' colours beside the intensities and the
ambient (:func:`selfsup.linear.segment_albedo`) and everything else is as above.

The count head learns the number of needed slots (weight ``presence_weight``); the
photometric signal for "is this slot needed" is degenerate where indirect light or
texture looks like a light, so ``count_weight > 0`` adds the generator's true count as
an auxiliary target (the only ground truth the default captures recipe reads).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from render import GBuffer, Material, ShadowedBlinnPhong
from selfsup.linear import basis_images, pseudo_huber, segment_albedo, single_light_costs, solve_intensities
from selfsup.model import LightPrediction, residual_after, scene_frame

__all__ = ["LossOptions", "LossTerms", "SceneBatch", "scene_batch", "reconstruction_loss", "TeacherOptions",
           "teacher_loss"]


@dataclass
class LossOptions:
    """Weights of the loss (mirrors the ``loss`` node of ``configs/experiment``).

    ``robust_scale``: pseudo-Huber width on the exposure-normalised residual
    (quadratic below, linear above: outliers such as unmodelled highlights pull
    with bounded force). ``presence_weight``, ``intensity_weight``: weights of the
    presence and intensity/ambient heads' terms. ``need_ratio``, ``need_floor``:
    when a slot counts as needed (see the module doc). ``supervised_weight``:
    ablation only; 0 (default) keeps the loss free of ground-truth lights.
    ``count_weight``: > 0 adds the true number of lights as the count head's target.
    ``albedo_iterations``: alternations of the albedo-free fit (segments given to
    :func:`reconstruction_loss`; :func:`selfsup.linear.segment_albedo`).
    """

    robust_scale: float = 0.05
    presence_weight: float = 0.05
    intensity_weight: float = 0.05
    need_ratio: float = 0.1
    need_floor: float = 0.006
    hypothesis_weight: float = 0.1
    hypothesis_stride: int = 3
    hypothesis_temperature: float = 0.05
    supervised_weight: float = 0.0
    count_weight: float = 0.0
    albedo_iterations: int = 3

    def __post_init__(self):
        if self.robust_scale <= 0:
            raise ValueError(f"robust_scale must be > 0, got {self.robust_scale}")
        if self.hypothesis_stride < 1 or self.hypothesis_temperature <= 0:
            raise ValueError("hypothesis_stride must be >= 1 and hypothesis_temperature > 0")
        if self.albedo_iterations < 1:
            raise ValueError(f"albedo_iterations must be >= 1, got {self.albedo_iterations}")
        for name in ("presence_weight", "intensity_weight", "need_ratio", "need_floor", "hypothesis_weight",
                     "supervised_weight", "count_weight"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")


@dataclass
class SceneBatch:
    """The renderer's view of a batch: ``image (B, 3, H, W)``, G-buffer, material."""

    image: Tensor
    gbuffer: GBuffer
    material: Material


def scene_batch(batch: dict[str, Tensor]) -> SceneBatch:
    """From a collated batch of :func:`selfsup.scenes.dataset.scene_to_item` dicts.

    Images whose normals are unknown (all zero: sensor depth) get normals estimated
    from the depth, as :meth:`render.GBuffer.from_depth` does for a scene file.
    """
    known = batch["normals"].flatten(1).abs().amax(1) > 0
    if bool(known.all()):
        gbuffer = GBuffer.from_depth(batch["depth"], batch["K"], normals=batch["normals"])
    elif not bool(known.any()):
        gbuffer = GBuffer.from_depth(batch["depth"], batch["K"])
    else:
        given = GBuffer.from_depth(batch["depth"], batch["K"], normals=batch["normals"])
        estimated = GBuffer.from_depth(batch["depth"], batch["K"])
        pick = lambda a, b: torch.where(known.view(-1, *[1] * (a.dim() - 1)), a, b)  # noqa: E731
        gbuffer = GBuffer(pick(given.points, estimated.points), pick(given.normals, estimated.normals),
                          pick(given.mask, estimated.mask))
    material = Material(kd=batch["kd"], ks=batch["ks"], shininess=batch["shininess"])
    return SceneBatch(image=batch["image"].permute(0, 3, 1, 2), gbuffer=gbuffer, material=material)


@dataclass
class LossTerms:
    """``total ()`` and its parts (detached); ``needed (B, K)`` the slots' self-supervised
    presence labels; ``render (B, 3, H, W)`` the re-rendered image of the needed slots
    and ``visibility (B, K, H, W)`` their shadow maps (detached), for logging."""

    total: Tensor
    photometric: Tensor
    hypotheses: Tensor
    presence: Tensor
    intensity: Tensor
    supervised: Tensor
    count: Tensor
    needed: Tensor
    render: Tensor
    visibility: Tensor


def _supervised(prediction: LightPrediction, batch: dict[str, Tensor], size: Tensor) -> Tensor:
    # Ablation: each true light to its nearest slot, relative to the scene size.
    distance = torch.cdist(batch["light_pos"].to(prediction.position), prediction.position).amin(-1)
    mask = batch["light_mask"].to(distance)
    return ((distance / size[:, None]) * mask).sum() / mask.sum().clamp_min(1)


def _robust_cost(model: Tensor, image: Tensor, mask: Tensor, exposure: Tensor, c: float) -> Tensor:
    # Per-image mean pseudo-Huber of the exposure-normalised residual over valid values: (B,).
    residual = (model - image) / exposure[:, None, None, None]
    per_value = pseudo_huber(residual, c) * mask
    return per_value.sum((1, 2, 3)) / mask.sum((1, 2, 3)).clamp_min(1)  # mask holds the 3 channels already


def hypothesis_costs(anchor_position: Tensor, scenes: SceneBatch, exposure: Tensor, falloff, stride: int,
                     robust_scale: float | None = None, before: Tensor | None = None) -> Tensor:
    """Error ``(B, M)`` of each hypothesis ``(B, M, 3)`` as one more light, unshadowed, on
    every ``stride``-th pixel, residuals divided by ``exposure (B,)``
    (:func:`selfsup.linear.single_light_costs`): the only light, or beside the lights
    ``before (B, k, 3)``, whose intensities are fitted first (:func:`selfsup.model.residual_after`)."""
    g, s = scenes.gbuffer, stride
    pixels = (g.points[:, ::s, ::s], g.normals[:, ::s, ::s], g.mask[:, ::s, ::s], scenes.material.kd[:, ::s, ::s],
              scenes.image[:, :, ::s, ::s])
    seen = pixels[-1] if before is None else residual_after(before, *pixels, falloff)
    return single_light_costs(anchor_position, *pixels[:4], seen, exposure, falloff, robust_scale)


def reconstruction_loss(prediction: LightPrediction, scenes: SceneBatch, renderer: ShadowedBlinnPhong,
                        options: LossOptions, batch: dict[str, Tensor] | None = None,
                        segments: tuple[Tensor, int] | None = None) -> LossTerms:
    """Robust photometric error of the re-rendered scene, plus the heads' terms.

    Args:
        prediction: the network's output for the batch (K slots).
        scenes: what the renderer needs (image, G-buffer, material).
        renderer: the shadowed Blinn-Phong layer (shadows on for training); its
            per-light transport maps are what the closed-form fit combines.
        options: weights.
        batch: the collated batch; read only for the ``supervised_weight`` ablation.
        segments: albedo-free (a capture's unknown albedo): ``(labels (B, H W) long,
            count)``, each pixel's region of one albedo (``count``: none, left out of the
            fit and the error). Each fit solves each region's colour beside the
            intensities and the ambient (:func:`selfsup.linear.segment_albedo`, diffuse
            only: highlights are the robust cost's outliers) and ``scenes.material`` is not
            read for the albedo. None: the material's albedo is the scene's.
    """
    g, m, image = scenes.gbuffer, scenes.material, scenes.image
    transport = renderer.transport(g, m, prediction.position)
    mask = g.mask[:, None].to(image.dtype).expand_as(image)
    if segments is not None:
        labels, count = segments
        mask = mask * (labels < count).view(g.mask.shape)[:, None].to(image.dtype)
    frame = scene_frame(image, g)
    B, K = prediction.presence.shape
    given = basis_images(m.kd, m.ks, transport.diffuse, transport.specular) if segments is None else None

    def fit(on: Tensor):
        if segments is None:
            kd, cols = m.kd, given
        else:
            kd = segment_albedo(transport.diffuse.detach() * on[:, :, None, None], image, mask, labels, count,
                                options.albedo_iterations)
            cols = basis_images(kd, None, transport.diffuse, None)
        intensity, ambient, model = solve_intensities(cols * on[:, None, :, None, None], kd, image, mask, ridge=1e-6)
        return intensity, ambient, model * mask, _robust_cost(model * mask, image, mask, frame.exposure, options.robust_scale), kd

    everything = torch.ones(B, K, dtype=image.dtype, device=image.device)
    _, _, _, cost_all, kd_all = fit(everything)
    with torch.no_grad():  # which slots the image needs: the error without each one
        rise = torch.stack([fit(everything - F.one_hot(torch.tensor(k), K).to(everything))[3] for k in range(K)], 1)
        rise = rise - cost_all[:, None]
        needed = rise > torch.maximum(options.need_ratio * cost_all, torch.full_like(cost_all, options.need_floor))[:, None]
        needed[:, 0] = True
    intensity, ambient, model, cost_needed, _ = fit(needed.to(image.dtype))
    photometric = 0.5 * (cost_all.mean() + cost_needed.mean())
    if segments is not None:  # the hypotheses are scored on the pixels that count, with the albedo solved
        scenes = SceneBatch(image, replace(g, mask=mask[:, 0] > 0), Material(kd=kd_all))

    hypotheses = torch.zeros((), dtype=image.dtype, device=image.device)
    for k in range(K):
        with torch.no_grad():
            costs = hypothesis_costs(prediction.anchor_position[:, k].detach(), scenes, frame.exposure, renderer.falloff,
                                     options.hypothesis_stride, options.robust_scale,
                                     prediction.position[:, :k].detach() if k else None)
            best = costs.amin(1, keepdim=True)
            target = torch.softmax(-(costs - best) / (options.hypothesis_temperature * best.clamp_min(1e-8)), 1)
        hypotheses = hypotheses - (target * torch.log_softmax(prediction.anchor_logits[:, k], 1)).sum(1).mean() / K

    presence = F.cross_entropy(prediction.count_logits, needed[:, 1:].sum(1))  # count label: 1 + the needed others
    count = torch.zeros((), dtype=image.dtype, device=image.device)
    if options.count_weight > 0:
        if batch is None or "light_mask" not in batch:
            raise ValueError("count_weight > 0 needs the batch's true light count (light_mask)")
        true_count = batch["light_mask"].sum(1).clamp(1, K) - 1
        count = F.cross_entropy(prediction.count_logits, true_count.to(prediction.count_logits.device))
    s = frame.exposure
    target_int = intensity.detach().clamp_min(1e-6 * s[:, None, None] * frame.size[:, None, None] ** 2)
    log_error = (prediction.intensity.clamp_min(1e-12).log() - target_int.log()).abs().mean(-1)
    intensity_term = (log_error * needed).sum() / needed.sum().clamp_min(1)
    intensity_term = intensity_term + ((prediction.ambient - ambient.detach()).abs() / s[:, None]).mean()

    supervised = torch.zeros((), dtype=image.dtype, device=image.device)
    if options.supervised_weight > 0:
        if batch is None or "light_pos" not in batch:
            raise ValueError("supervised_weight > 0 needs the batch's ground-truth lights")
        supervised = _supervised(prediction, batch, frame.size)
    total = (photometric + options.hypothesis_weight * hypotheses + options.presence_weight * presence + options.intensity_weight * intensity_term
             + options.supervised_weight * supervised + options.count_weight * count)
    visibility = transport.visibility if transport.visibility is not None else torch.ones_like(transport.diffuse)
    return LossTerms(total=total, photometric=photometric.detach(), hypotheses=hypotheses.detach(),
                     presence=presence.detach(),
                     intensity=intensity_term.detach(), supervised=supervised.detach(), count=count.detach(), needed=needed,
                     render=model.detach(), visibility=visibility.detach())


# -- the per-frame search as teacher (selfsup.teacher finds its lights) --------------
@dataclass(frozen=True)
class TeacherOptions:
    """Weights of the teacher's terms (mirrors ``adapt.teacher`` and ``loss.teacher``): ``position`` (pseudo-Huber of
    the slot-to-light distance over the scene size, width ``scale``), ``anchors`` (cross
    entropy of the hypothesis scores against a Gaussian of width ``anchor_width`` of the scene
    size about the light), ``count`` (cross entropy of the count head against the lights found;
    0 by default: at 0.5 the adapted network stopped counting second lights, 25% -> 3% of the
    two-light test rooms, benchmarks/results/adapt_teacher_count_cpu2_2026-11-29.md). All 0:
    the photometric loss alone."""

    position: float = 1.0
    anchors: float = 0.1
    count: float = 0.0
    scale: float = 0.02
    anchor_width: float = 0.05

    def __post_init__(self):
        for name in ("position", "anchors", "count"):
            if getattr(self, name) < 0:
                raise ValueError(f"teacher.{name} (adapt.teacher, loss.teacher) must be >= 0, got {getattr(self, name)}")
        if self.scale <= 0 or self.anchor_width <= 0:
            raise ValueError("teacher.scale and teacher.anchor_width (adapt.teacher, loss.teacher) must be > 0")


def _assignment(position: Tensor, teacher: Tensor, mask: Tensor) -> Tensor:
    """``(B, K)`` long: the slot each teacher row goes to (a permutation of the slots, the one
    of least summed distance over the rows that are lights)."""
    B, K, _ = position.shape
    distance = torch.cdist(teacher, position.detach())  # (B, K rows, K slots)
    orders = torch.tensor(list(itertools.permutations(range(K))), device=position.device)  # (P, K)
    cost = (distance[:, torch.arange(K, device=position.device)[None], orders] * mask[:, None]).sum(-1)  # (B, P)
    return orders[cost.argmin(1)]


def teacher_loss(prediction: LightPrediction, teacher: Tensor, mask: Tensor, size: Tensor,
                 options: TeacherOptions) -> tuple[Tensor, dict[str, float]]:
    """``()`` loss of ``prediction`` against the teacher's lights ``teacher (B, K, 3)`` (rows of
    ``mask (B, K)``; an image without any is left out) and its parts; ``size (B,)`` the scenes' sizes."""
    zero = prediction.position.new_zeros(())
    has = mask.any(1)
    if not bool(has.any()):
        return zero, {}
    position, anchors, logits = prediction.position[has], prediction.anchor_position[has], prediction.anchor_logits[has]
    teacher, mask, size = teacher[has].to(position), mask[has], size[has].to(position)
    slot = _assignment(position, teacher, mask)  # (b, K)
    rows = torch.arange(len(slot), device=slot.device)[:, None]
    placed = position[rows, slot]  # (b, K, 3): the slot of each teacher row
    distance = (placed - teacher).norm(dim=-1) / size[:, None]
    weight = mask.to(position.dtype)
    position_term = (pseudo_huber(distance, options.scale) * weight).sum() / weight.sum()
    # Each assigned slot's hypotheses: a Gaussian about the teacher's light.
    spread = (anchors[rows, slot].detach() - teacher[:, :, None]).norm(dim=-1) / size[:, None, None]  # (b, K, M)
    target = torch.softmax(-0.5 * (spread / options.anchor_width) ** 2, -1)
    anchor_term = -((target * torch.log_softmax(logits[rows, slot], -1)).sum(-1) * weight).sum() / weight.sum()
    count_term = F.cross_entropy(prediction.count_logits[has], mask.sum(1) - 1)
    total = options.position * position_term + options.anchors * anchor_term + options.count * count_term
    return total, {"teacher_position": float(position_term.detach()), "teacher_anchors": float(anchor_term.detach()),
                   "teacher_count": float(count_term.detach())}
