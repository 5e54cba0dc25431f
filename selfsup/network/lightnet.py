"""The network that re-renders what it predicts: an init and T update steps (RAFT's shape).

:class:`IterativeLightNet` needs what a camera gives (linear colour, a G-buffer with
intrinsics; no albedo). It works on the frame's working grid (:mod:`selfsup.network.grid`):

1. the encoder (:mod:`selfsup.network.encoder`) computes features once;
2. the init: each slot's light is where its vote field's rays meet
   (:mod:`selfsup.network.votes`; ``init="votes"``), or the best of a grey, unshadowed
   cost volume's hypotheses (``init="volume"``, the physics alone, for the ablation);
   a small head gives the first presences, relative intensities and ambient;
3. ``steps`` update steps (:mod:`selfsup.network.update`): re-render with cast shadows,
   weigh the pixels, take the weighted Gauss-Newton step, update the presences.

Every step's lights are returned, so that a loss can weigh the sequence. Between steps the
lights are detached (as RAFT detaches its flow): each step's gradient reaches the weights
of that step's update through its Gauss-Newton solve, not the steps before it.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from render import GBuffer
from render.shadows import ShadowMethod, default_options
from selfsup.linear import basis_images, single_light_costs, solve_intensities
from selfsup.model import GREY_ALBEDO
from selfsup.network.encoder import Encoder
from selfsup.network.grid import WorkGrid, grey_log, work_grid
from selfsup.network.physics import LOG_GAIN_RANGE, LightState, rerender
from selfsup.network.update import UpdateBlock
from selfsup.network.votes import VoteHead, meeting_point

__all__ = ["IterativeLightNet", "IterativePrediction", "StepLights", "INITS", "confidence_features"]

INITS = ("votes", "volume")


@dataclass
class StepLights:
    """One step's lights: ``position (B, K, 3)`` metres, ``logits (B, K)`` of presence
    (slot 0's unused), ``state`` (scene units), ``weights (B, 4, h, w)`` or None (the init)."""

    position: Tensor
    logits: Tensor
    state: LightState
    weights: Tensor | None = None


@dataclass
class IterativePrediction:
    """What :class:`IterativeLightNet` predicts for a batch of K slots.

    Attributes:
        position: ``(B, K, 3)`` metres, the last step's.
        presence: ``(B, K)``: slot 0's is 1; the others' the probability that the room
            has that light.
        steps: the init and every update's :class:`StepLights`.
        grid: the working grid.
        closing: what :attr:`intensity` and :attr:`ambient` are solved by, on their first read
            (a re-render with the last lights' shadows, 7% of a forward at batch 1 on the CPU;
            the estimator reads positions and counts only).
        votes: ``(direction (B, K, h, w, 3), weight (B, K, h, w))`` or None (``init="volume"``).
        count_threshold: a slot ``k >= 1`` counts where it and every slot before it reach it.
        confidence: ``(B,)`` in (0, 1): the calibrated probability that slot 0 lies within 0.05
            of the scene size of a light (:func:`confidence_features` through the network's
            ``confidence_weights``, fitted on validation scenes; 0.5 before).
    """

    position: Tensor
    presence: Tensor
    steps: list[StepLights]
    grid: WorkGrid
    closing: Callable[[], tuple[Tensor, Tensor]] = field(repr=False)
    votes: tuple[Tensor, Tensor] | None = None
    count_threshold: float = 0.5
    confidence: Tensor | None = None

    @functools.cached_property
    def _closed(self) -> tuple[Tensor, Tensor]:
        return self.closing()

    @property
    def intensity(self) -> Tensor:
        """``(B, K, 3)`` of a grey (0.5) albedo, the image's units, solved in closed form on the
        grid with the last step's shadows (on first read)."""
        return self._closed[0]

    @property
    def ambient(self) -> Tensor:
        """``(B, 3)``, solved with :attr:`intensity`."""
        return self._closed[1]

    @property
    def count(self) -> Tensor:
        """``(B,)`` long: 1 + the leading slots after the first whose presence reaches the threshold."""
        counted = (self.presence[:, 1:] >= self.count_threshold).long().cumprod(1)
        return 1 + counted.sum(1)

    def lights_of(self, index: int) -> tuple[Tensor, Tensor]:
        """Positions and intensities ``(n, 3)`` of image ``index``'s first ``n = count`` slots."""
        n = int(self.count[index])
        return self.position[index, :n], self.intensity[index, :n]


def confidence_features(steps: list[StepLights]) -> Tensor:
    """``(B, 3)``: 1, the log distance (scene units) from slot 0's init to its last step, and
    the log length of its last step: where the votes and the re-render agree and the steps
    have settled, slot 0 is likely right (the logistic model of :attr:`IterativePrediction.confidence`)."""
    first, last = steps[0].state.position[:, 0], steps[-1].state.position[:, 0]
    before = steps[-2].state.position[:, 0] if len(steps) > 1 else first
    agreement = (last - first).norm(dim=-1).detach()
    move = (last - before).norm(dim=-1).detach()
    return torch.stack([torch.ones_like(move), torch.log(agreement + 1e-3), torch.log(move + 1e-4)], 1)


class IterativeLightNet(nn.Module):
    """Point lights from colour and depth, placed by re-rendering them (see the module doc).

    Args:
        max_lights: slots K.
        long_side: the working grid's longer side, in cells.
        widths, global_width: the encoder's (:class:`selfsup.network.encoder.Encoder`).
        update_width: the update block's channels.
        steps: update steps T (0: the init alone).
        init: ``votes`` or ``volume`` (:data:`INITS`).
        shadows: the re-render's cast shadows (``epipolar`` or ``none``, an ablation).
        use_render: False: the update reads no re-render (an ablation).
        count_threshold: see :class:`IterativePrediction` (calibrated on validation scenes).
        confidence_weights: the logistic model of :attr:`IterativePrediction.confidence` on
            :func:`confidence_features` (fitted on validation scenes; zeros: 0.5 everywhere).
        shadow_thickness: the epipolar solid behind each cell, of the scene size (None: unbounded,
            everything behind the surface; the layer's default is 0.03, three times the cost).

    ``forward(image (B, 3, H, W), gbuffer (with intrinsics), kd=None, steps=None) ->
    IterativePrediction``; ``kd`` is accepted and ignored (the network needs no albedo).
    """

    def __init__(self, max_lights: int = 2, long_side: int = 64, widths: tuple[int, ...] = (32, 48, 64, 96),
                 global_width: int = 128, update_width: int = 48, steps: int = 3, init: str = "votes",
                 shadows: str = "epipolar", use_render: bool = True, count_threshold: float = 0.5,
                 shadow_thickness: float | None = None,
                 confidence_weights: tuple[float, float, float] = (0.0, 0.0, 0.0)):
        super().__init__()
        if max_lights < 1 or long_side < 8 or steps < 0:
            raise ValueError(f"max_lights must be >= 1, long_side >= 8 and steps >= 0, got {max_lights}, {long_side} "
                             f"and {steps}")
        if init not in INITS:
            raise ValueError(f"init must be one of {INITS}, got {init!r}")
        if shadows not in ("epipolar", "none"):
            raise ValueError(f"shadows must be 'epipolar' or 'none', got {shadows!r}")
        if not 0 < count_threshold <= 1:
            raise ValueError(f"count_threshold must be in (0, 1], got {count_threshold}")
        self.max_lights, self.long_side, self.steps, self.init = max_lights, long_side, steps, init
        self.shadows = ShadowMethod(shadows)
        # The epipolar solid behind each cell: None, unbounded (a third of the bounded one's cost).
        self.shadow_options = default_options(self.shadows, scene_thickness=shadow_thickness) \
            if self.shadows is ShadowMethod.EPIPOLAR else None
        self.count_threshold = float(count_threshold)
        if len(confidence_weights) != 3:
            raise ValueError(f"confidence_weights must be 3 numbers, got {confidence_weights!r}")
        self.confidence_weights = tuple(float(w) for w in confidence_weights)
        self.encoder = Encoder(tuple(widths), global_width)
        self.votes = VoteHead(self.encoder.channels, max_lights)
        self.first = nn.Linear(global_width, 2 * max_lights)  # presence logits, log gains (slots 1..), log ambient
        with torch.no_grad():
            self.first.weight.mul_(0.1)
            self.first.bias.zero_()
            self.first.bias[2 * max_lights - 1] = -1.0
        self.update = UpdateBlock(self.encoder.channels, global_width, max_lights, update_width, use_render)

    def _volume_init(self, grid: WorkGrid, observed: Tensor) -> Tensor:
        # Each slot's best hypothesis of a grey unshadowed cost volume (a 6^3 grid over +-0.75
        # scene sizes), slot k on what slots 0..k-1 leave: (B, K, 3) scene units, no gradient.
        from selfsup.model import residual_after

        with torch.no_grad():
            axis = torch.linspace(-0.75, 0.75, 6, dtype=grid.image.dtype, device=grid.image.device)
            anchors = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(1, -1, 3)
            g = grid.gbuffer
            kd = torch.full_like(g.points, GREY_ALBEDO)
            B = grid.image.shape[0]
            chosen, image = [], grid.image
            for k in range(self.max_lights):
                if k:
                    image = residual_after(grid.metres(torch.stack(chosen, 1)), g.points, g.normals, g.mask, kd,
                                           grid.image, "inverse_square")
                costs = single_light_costs(grid.metres(anchors.expand(B, -1, -1)), g.points, g.normals, g.mask, kd,
                                           image, grid.frame.exposure, "inverse_square")
                chosen.append(anchors[0, costs.argmin(1)])
            return torch.stack(chosen, 1)

    def forward(self, image: Tensor, gbuffer: GBuffer, kd: Tensor | None = None, steps: int | None = None
                ) -> IterativePrediction:
        steps = self.steps if steps is None else steps
        grid = work_grid(image, gbuffer, self.long_side)
        features, global_features = self.encoder(grid)
        observed, usable = grey_log(grid.image, grid.gbuffer.mask, grid.frame.exposure)
        K = self.max_lights
        first = self.first(global_features).float()
        logits = torch.cat([first.new_zeros(len(first), 1), first[:, : K - 1]], 1)
        log_gain = torch.cat([first.new_zeros(len(first), 1), first[:, K - 1 : 2 * K - 2].clamp(*LOG_GAIN_RANGE)], 1)
        votes = None
        points = (grid.gbuffer.points - grid.frame.centre[:, None, None]) / grid.frame.size[:, None, None, None]
        if self.init == "votes":
            direction, weight = self.votes(features, grid.gbuffer.mask)
            votes = (direction.float(), weight.float())
            position = meeting_point(points.float(), *votes)
        else:
            position = self._volume_init(grid, observed)
        presence = torch.cat([torch.ones_like(logits[:, :1]), torch.sigmoid(logits[:, 1:])], 1)
        state = LightState(position, log_gain, first[:, -1], presence, torch.zeros_like(first[:, -1]))
        history = [StepLights(grid.metres(position), logits, state)]
        for _ in range(steps):
            state = state.detach()
            render = rerender(grid, state, self.shadows, self.shadow_options)
            state, logits, weights, _ = self.update(grid, features, global_features, observed, usable, state, render,
                                                    logits.detach())
            history.append(StepLights(grid.metres(state.position), logits, state, weights))
        weights = torch.tensor(self.confidence_weights, dtype=position.dtype, device=position.device)
        confidence = torch.sigmoid(confidence_features(history) @ weights)
        closing = functools.partial(self._intensities, grid, state.detach())
        return IterativePrediction(history[-1].position, state.presence, history, grid, closing, votes,
                                   self.count_threshold, confidence)

    @torch.no_grad()
    def _intensities(self, grid: WorkGrid, state: LightState) -> tuple[Tensor, Tensor]:
        # Closed-form intensities (B, K, 3) and ambient (B, 3) of a grey albedo, the last state's shadows.
        render = rerender(grid, state.detach(), self.shadows, self.shadow_options, jacobian=False)
        transport = render.transport / grid.frame.size[:, None, None, None] ** 2  # scene units -> metres
        kd = torch.full_like(grid.gbuffer.points, GREY_ALBEDO)
        weights = grid.gbuffer.mask[:, None].to(grid.image.dtype).expand_as(grid.image)
        intensity, ambient, _ = solve_intensities(basis_images(kd, None, transport, None), kd, grid.image, weights,
                                                  ridge=1e-6)
        return intensity, ambient
