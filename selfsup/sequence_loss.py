"""How :class:`selfsup.network.IterativeLightNet` learns: the re-render loss at every step.

No light label is read. Two things come from the re-render loss with the scene's albedo
(which a training scene has; the network never sees it):

- :func:`rerender_minimum`, once per training pool: each scene's lights where that loss is
  least, found by search (a cost volume of the one-light fit over the scene, a cascade
  about its best, then Gauss-Newton steps with cast shadows; a second light on what the
  first leaves, kept where it lowers the loss by ``need_ratio``). The network's steps
  cannot search (they move from where they are); these minima tell them where the loss's
  global minimum lies, as a teacher would, at the cost of a few renders per scene.
- :func:`sequence_loss`, every step: for the init and each update step (weighed
  ``gamma^(T - t)``, later steps more, as RAFT's sequence loss): the robust re-render error
  through the shadowed layer of the step's lights (intensities and ambient in closed form),
  the pseudo-Huber distance of each needed slot to its minimum, the presences against the
  slots the minimum needs, and at the init each vote's angle to its slot's minimum.

A user's captures (``mode=adapt``) have no albedo: :func:`taught_sequence_loss` re-renders
each step with each region's albedo solved in closed form beside the intensities, and the
per-frame search's lights take the minimum's place.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from render import EpipolarShadowOptions, ShadowedBlinnPhong
from render import Material
from selfsup.linear import basis_images, pseudo_huber, segment_albedo, single_light_costs, solve_intensities
from selfsup.losses import SceneBatch, TeacherOptions, _robust_cost, scene_batch
from selfsup.model import GREY_ALBEDO, residual_after, scene_frame
from selfsup.network import IterativePrediction
from selfsup.network.grid import work_grid
from selfsup.network.physics import LightState, gauss_newton_step, rerender

__all__ = ["SequenceLossOptions", "SequenceTerms", "rerender_minimum", "pool_minima", "sequence_loss",
           "taught_sequence_loss", "UNBOUNDED"]

# The epipolar shadows' unbounded solid (everything behind the visible surface): a third of the
# bounded default's cost, the training renderer's setting (configs/renderer/shadowed.yaml).
UNBOUNDED = EpipolarShadowOptions(scene_thickness=None)
# A split start's two lights lie this far (scene sizes) either side of the one light's place.
SPLIT = 0.15


@dataclass(frozen=True)
class SequenceLossOptions:
    """Weights of :func:`sequence_loss` (mirrors the experiment's ``loss`` node).

    ``gamma``: step ``t`` of ``T`` weighs ``gamma^(T - t)``. ``photometric``: the robust
    re-render error (pseudo-Huber of the exposure-normalised residual at ``robust_scale``).
    ``position``: pseudo-Huber of each needed slot's distance to the re-render loss's
    minimum over the scene size, at ``position_scale``. ``presence``: binary cross entropy
    of slots 1.. against the minimum's needed slots. ``votes``: ``1 - cos`` of each vote's
    direction to its slot's minimum (the init's vote field). ``need_ratio``: a second light
    is needed where it lowers the minimum's loss by this share.
    """

    gamma: float = 0.8
    photometric: float = 1.0
    robust_scale: float = 0.05
    position: float = 1.0
    position_scale: float = 0.02
    presence: float = 0.1
    votes: float = 0.1
    need_ratio: float = 0.1

    def __post_init__(self):
        if not 0 < self.gamma <= 1:
            raise ValueError(f"loss.gamma must be in (0, 1], got {self.gamma}")
        for name in ("photometric", "position", "presence", "votes", "need_ratio"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"loss.{name} must be >= 0, got {getattr(self, name)}")
        if not (self.robust_scale > 0 and self.position_scale > 0):
            raise ValueError("loss.robust_scale and loss.position_scale must be > 0")


@dataclass
class SequenceTerms:
    """``total ()`` and its parts (detached), and the final step's ``render (B, 3, H, W)``
    and ``visibility (B, K, H, W)`` for logging."""

    total: Tensor
    photometric: Tensor
    position: Tensor
    presence: Tensor
    votes: Tensor
    render: Tensor
    visibility: Tensor


def _robust_fit(scenes: SceneBatch, transport, on: Tensor, robust_scale: float, exposure: Tensor):
    # Closed-form intensities of the lights ``on (B, K)`` with the scene's albedo: (cost (B,), model
    # image, each light's share (B, K) of the model's light on the valid pixels).
    m, image = scenes.material, scenes.image
    cols = basis_images(m.kd, m.ks, transport.diffuse, transport.specular) * on[:, None, :, None, None]
    mask = scenes.gbuffer.mask[:, None].to(image.dtype).expand_as(image)
    intensity, _, model = solve_intensities(cols, m.kd, image, mask, ridge=1e-6)
    residual = (model - image) / exposure[:, None, None, None]
    cost = (pseudo_huber(residual, robust_scale) * mask).sum((1, 2, 3)) / mask.sum((1, 2, 3)).clamp_min(1)
    light = (cols * mask[:, :, None]).sum((3, 4)) * intensity.transpose(1, 2)  # (B, 3, K)
    share = light.sum(1) / light.sum((1, 2)).clamp_min(1e-30)[:, None]
    return cost, model * mask, share


def _cascade(scenes: SceneBatch, image: Tensor, centre: Tensor, size: Tensor, exposure: Tensor) -> Tensor:
    # The best of a 6^3 grid over +-0.75 scene sizes, then twice of a 5^3 grid at a quarter of
    # the step about it: (B, 3) metres, the one-light fit's error with the scene's albedo.
    g, kd = scenes.gbuffer, scenes.material.kd
    dtype, device = image.dtype, image.device
    axis = torch.linspace(-0.75, 0.75, 6, dtype=dtype, device=device)
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(1, -1, 3)
    fine = torch.arange(-2.0, 3.0, dtype=dtype, device=device)
    fine = torch.stack(torch.meshgrid(fine, fine, fine, indexing="ij"), -1).reshape(1, -1, 3)
    rows = torch.arange(len(image), device=device)
    best, step = None, 0.3
    for level in range(3):
        hypotheses = grid.expand(len(image), -1, -1) if level == 0 else best[:, None] + step * fine
        metres = centre[:, None] + size[:, None, None] * hypotheses
        # Squared errors (sums over pixels alone, several times faster than a robust cost):
        # the Gauss-Newton steps after the cascade are robust.
        costs = single_light_costs(metres, g.points, g.normals, g.mask, kd, image, exposure, "inverse_square")
        best = hypotheses[rows, costs.argmin(1)]
        step = step / 4
    return centre + size[:, None] * best


@torch.no_grad()
def rerender_minimum(scenes: SceneBatch, max_lights: int, options: SequenceLossOptions = SequenceLossOptions(),
                     steps: int = 8, shadow_options=UNBOUNDED, split: bool = False) -> tuple[Tensor, Tensor]:
    """Each scene's lights where the re-render loss with its albedo is least (see the module doc).

    Returns:
        ``position (B, K, 3)`` metres (slot 0 the brightest light's; slot ``k`` on what
        the slots before leave) and ``needed (B, K)`` bool (slot 0 always).
    """
    g, image = scenes.gbuffer, scenes.image
    grid = work_grid(image, g, max(g.mask.shape[1:]))  # the scene's own grid: its centre, size and exposure
    frame = grid.frame
    kd = scenes.material.kd
    B = image.shape[0]
    # The log shading with the albedo divided out, channel by channel (white balance cancels).
    lit = g.mask & (kd.amin(-1) > 1e-3) & (image.amax(1) < 0.99 * image.flatten(1).amax(1)[:, None, None])
    grey = (image / kd.permute(0, 3, 1, 2).clamp_min(1e-3)).mean(1) / frame.exposure[:, None, None]
    observed, usable = grey.clamp_min(1e-4).log(), lit & (grey > 1e-4)
    uniform = torch.ones(B, 4, *g.mask.shape[1:], dtype=image.dtype, device=image.device)
    damping = torch.full((B,), 0.01, dtype=image.dtype, device=image.device)

    def refine(position: Tensor) -> Tensor:
        k = position.shape[1]
        state = LightState(grid.normalised(position), image.new_zeros(B, k), image.new_full((B,), -1.0),
                           image.new_ones(B, k), image.new_zeros(B))
        for _ in range(steps):
            render = rerender(grid, state, shadow_options=shadow_options)
            state, _ = gauss_newton_step(state, observed, usable, render, uniform, damping)
        return grid.metres(state.position)

    first = refine(_cascade(scenes, image, frame.centre, frame.size, frame.exposure)[:, None])
    positions, needed = first, torch.ones(B, 1, dtype=torch.bool, device=image.device)
    if max_lights > 1:
        renderer = ShadowedBlinnPhong(check_finite=False, shadow_options=shadow_options)

        def fitted(position: Tensor):  # (cost, share) of the lights with the scene's albedo, shadows
            on = image.new_ones(B, position.shape[1])
            cost, _, share = _robust_fit(scenes, renderer.transport(g, scenes.material, position), on,
                                         options.robust_scale, frame.exposure)
            return cost, share

        one_cost, _ = fitted(first)
        # Pairs refined together, the one of least cost kept, the brighter first: a second light
        # on what the first leaves, and with ``split`` the first split in two along each axis (a
        # light placed between two lamps: the estimator's split starts). Off: on 256 training
        # rooms the split pairs lowered the cost by need_ratio in 61% of one-light rooms (25%
        # without) and 67% of two-light ones (33%), at four times the time.
        left = residual_after(first, g.points, g.normals, g.mask, kd, image, "inverse_square")
        pairs = [torch.stack([first[:, 0], _cascade(scenes, left, frame.centre, frame.size, frame.exposure)], 1)]
        for axis in range(3 if split else 0):
            offset = torch.zeros(B, 3, dtype=image.dtype, device=image.device)
            offset[:, axis] = SPLIT * frame.size
            pairs.append(torch.stack([first[:, 0] + offset, first[:, 0] - offset], 1))
        both, two_cost, share = None, None, None
        for pair in pairs:
            pair = refine(pair)
            cost, pair_share = fitted(pair)
            take = cost < two_cost if both is not None else torch.ones_like(cost, dtype=torch.bool)
            both = pair if both is None else torch.where(take[:, None, None], pair, both)
            two_cost = cost if two_cost is None else torch.where(take, cost, two_cost)
            share = pair_share if share is None else torch.where(take[:, None], pair_share, share)
        both = torch.where((share[:, 1] > share[:, 0])[:, None, None], both.flip(1), both)
        two = (one_cost - two_cost) > options.need_ratio * two_cost
        positions = torch.where(two[:, None, None], both, torch.cat([first, both[:, 1:]], 1))
        needed = torch.stack([torch.ones_like(two), two], 1)
        if max_lights > 2:  # slots beyond two are never needed here
            pad = max_lights - 2
            positions = torch.cat([positions, positions[:, -1:].expand(-1, pad, -1)], 1)
            needed = torch.cat([needed, torch.zeros(B, pad, dtype=torch.bool, device=image.device)], 1)
    return positions, needed


def pool_minima(pool: dict[str, Tensor], max_lights: int, options: SequenceLossOptions = SequenceLossOptions(),
                batch: int = 64) -> dict[str, Tensor]:
    """``target_pos (N, K, 3)`` and ``target_needed (N, K)``: :func:`rerender_minimum` of every
    scene of a pool (stacked items of :func:`selfsup.scenes.dataset.scene_to_item`), ``batch`` at a time."""
    parts = [rerender_minimum(scene_batch({k: v[i:i + batch] for k, v in pool.items()}), max_lights, options)
             for i in range(0, pool["image"].shape[0], batch)]
    return {"target_pos": torch.cat([p for p, _ in parts]), "target_needed": torch.cat([n for _, n in parts])}


def _vote_term(prediction: IterativePrediction, target: Tensor, needed: Tensor) -> Tensor:
    # 1 - cos of each valid cell's vote and its direction to the slot's minimum, over needed slots.
    direction, _ = prediction.votes
    grid = prediction.grid
    points = (grid.gbuffer.points - grid.frame.centre[:, None, None]) / grid.frame.size[:, None, None, None]
    goal = F.normalize(grid.normalised(target)[:, :, None, None] - points[:, None], dim=-1, eps=1e-6)  # (B, K, h, w, 3)
    weight = grid.gbuffer.mask[:, None].to(direction.dtype) * needed[:, :, None, None].to(direction.dtype)
    return ((1 - (direction * goal).sum(-1)) * weight).sum() / weight.sum().clamp_min(1)


def sequence_loss(prediction: IterativePrediction, scenes: SceneBatch, renderer: ShadowedBlinnPhong, target: Tensor,
                  needed: Tensor, options: SequenceLossOptions) -> SequenceTerms:
    """The loss of every step of ``prediction`` (see the module doc).

    Args:
        prediction: the network's output with its steps.
        scenes: the batch (the scene's albedo is read here, for the re-render, not by the network).
        renderer: the shadowed layer the re-render goes through.
        target, needed: :func:`rerender_minimum` of the batch, ``(B, K, 3)`` and ``(B, K)``.
    """
    g = scenes.gbuffer
    frame = prediction.grid.frame
    on = needed.to(scenes.image.dtype)
    T = len(prediction.steps) - 1
    zero = scenes.image.new_zeros(())
    photometric, position, presence = zero, zero, zero
    model, visibility = None, None
    for t, step in enumerate(prediction.steps):
        weight = options.gamma ** (T - t)
        if options.photometric > 0:
            transport = renderer.transport(g, scenes.material, step.position)
            cost, model, _ = _robust_fit(scenes, transport, on, options.robust_scale, frame.exposure)
            photometric = photometric + weight * cost.mean()
            visibility = transport.visibility
        distance = (step.position - target).norm(dim=-1) / frame.size[:, None]
        position = position + weight * (pseudo_huber(distance, options.position_scale) * on).sum() / on.sum()
        if step.logits.shape[1] > 1:
            presence = presence + weight * F.binary_cross_entropy_with_logits(step.logits[:, 1:], on[:, 1:])
    votes = _vote_term(prediction, target, needed) if prediction.votes is not None else zero
    total = (options.photometric * photometric + options.position * position + options.presence * presence
             + options.votes * votes)
    if model is None:
        model = torch.zeros_like(scenes.image)
    if visibility is None:
        visibility = torch.ones_like(g.mask[:, None].expand(-1, target.shape[1], -1, -1), dtype=scenes.image.dtype)
    return SequenceTerms(total, photometric.detach(), position.detach(), presence.detach(), votes.detach(),
                         model.detach(), visibility.detach())


def taught_sequence_loss(prediction: IterativePrediction, image: Tensor, gbuffer, segments: tuple[Tensor, int],
                         renderer: ShadowedBlinnPhong, options: SequenceLossOptions, teacher: TeacherOptions,
                         taught: Tensor | None = None, taught_mask: Tensor | None = None) -> SequenceTerms:
    """The loss of every step of ``prediction`` on frames without albedo (a user's captures).

    For the init and each update step (weighed ``gamma^(T - t)``): the robust re-render error
    through the shadowed layer, each region's albedo solved in closed form beside the
    intensities and the ambient (:func:`selfsup.linear.segment_albedo`, diffuse only, as the
    cost-volume network's adaptation loss); the pseudo-Huber distance of slot ``k`` to the
    per-frame search's ``k``-th light (brightest first) over the scene size, at
    ``teacher.scale``; and, weighed ``teacher.count``, the presences against the lights the
    search found. The lights switched on in the re-render are the search's where it found
    some, else the network's own count.

    Args:
        prediction: the network's output on the frames (its view may be finer than the loss's).
        image: ``(B, 3, h, w)`` linear colour of the loss's view; ``gbuffer`` its G-buffer
            (same camera frame, metres).
        segments: ``(labels (B, h w) long, count)``: each pixel's region of one albedo
            (``count``: none, left out).
        taught, taught_mask: the search's lights ``(B, K, 3)`` and which are lights ``(B, K)``
            (None: no frame has any).
    """
    labels, count = segments
    frame = scene_frame(image, gbuffer)
    B, K = prediction.presence.shape
    mask = gbuffer.mask[:, None].to(image.dtype).expand_as(image) * (labels < count).view(gbuffer.mask.shape)[:, None]
    material = Material(kd=torch.full((B, *gbuffer.mask.shape[1:], 3), GREY_ALBEDO, dtype=image.dtype,
                                      device=image.device))
    on = (torch.arange(K, device=image.device) < prediction.count[:, None]).to(image.dtype)  # the network's count
    has = torch.zeros(B, dtype=torch.bool, device=image.device)
    if taught_mask is not None:  # where the search found lights, its count
        has = taught_mask.any(1)
        on = torch.where(has[:, None], taught_mask.to(image.dtype), on)
    T = len(prediction.steps) - 1
    zero = image.new_zeros(())
    photometric, position, presence = zero, zero, zero
    model, visibility = None, None
    for t, step in enumerate(prediction.steps):
        weight = options.gamma ** (T - t)
        transport = renderer.transport(gbuffer, material, step.position)
        kd = segment_albedo(transport.diffuse.detach() * on[:, :, None, None], image, mask, labels, count)
        cols = basis_images(kd, None, transport.diffuse, None) * on[:, None, :, None, None]
        _, _, model = solve_intensities(cols, kd, image, mask, ridge=1e-6)
        model = model * mask
        cost = _robust_cost(model, image, mask, frame.exposure, options.robust_scale)
        photometric = photometric + weight * cost.mean()
        visibility = transport.visibility
        if bool(has.any()):
            rows = taught_mask[has].to(image.dtype)
            distance = (step.position[has] - taught[has]).norm(dim=-1) / frame.size[has, None]
            position = position + weight * (pseudo_huber(distance, teacher.scale) * rows).sum() / rows.sum()
            if K > 1:
                presence = presence + weight * F.binary_cross_entropy_with_logits(step.logits[has, 1:], rows[:, 1:])
    total = options.photometric * photometric + teacher.position * position + teacher.count * presence
    return SequenceTerms(total, photometric.detach(), position.detach(), presence.detach(), zero, model.detach(),
                         visibility.detach())
