"""The light-estimation CNN: colour + depth in, point lights counted and placed, ambient out.

A plain ``nn.Module`` that knows nothing of training. It needs what a camera gives: a
linear colour image (any exposure and white balance) and a G-buffer from the depth; no
albedo. Every input is normalised per image, so that no resolution, aspect ratio,
intrinsics, exposure or scene size is assumed:

- the image is divided by its exposure ``s`` (99th percentile of the valid
  pixels' brightest channel);
- points are expressed relative to the centroid ``c`` of the valid points, in
  units of the scene size ``r`` (diagonal of their bounding box);
- all maps are resampled (mask-weighted area averages) to a fixed
  ``input_size x input_size`` grid.

Each light slot is chosen among M hypotheses: a fixed grid of anchors in the
normalised frame, each with a score; the best-scored hypothesis is the slot's
position. Scoring hypotheses is a classification over space, which learns far more
reliably than regressing a position through a photometric loss with local minima.
Like the cost volume of a stereo network, the scores start from physics: each
anchor's photometric error as one more light (diffuse, unshadowed, its intensity and
the ambient in closed form, :func:`selfsup.linear.single_light_costs`, on a coarse
pixel grid) is an input of the head and a prior on the scores. Slot 0's volume
explains the image; slot ``k``'s explains what slots ``0 .. k-1`` leave (their
intensities fitted in closed form: matching pursuit). Without an albedo the volumes
take a grey one; where a caller has the true albedo (a scene file) it may pass it, and
only the volumes use it. The network learns what the simple model misses (texture,
shadows, highlights, indirect light). How far each volume's best hypothesis lowers the
error is what the count head reads, beside the image features: it says how many of
the K slots the room has (1 .. K). Outputs are mapped back: light positions are
``c + r * p`` with ``p`` the network's normalised position; intensities are ``exp(q) * s``
times ``r^2`` under inverse-square falloff (the light must be brighter the farther it
is); the ambient term is ``softplus(a) * s``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from render.functional import light_transport
from render.shading import Falloff
from render.types import GBuffer, Material
from selfsup.linear import basis_images, single_light_costs, solve_intensities

__all__ = ["LightNet", "LightPrediction", "SceneFrame", "scene_frame", "brightest_percentile", "network_inputs",
           "residual_after"]

IN_CHANNELS = 10
GREY_ALBEDO = 0.5  # the cost volumes' albedo where none is given (a capture's convention)


@dataclass
class LightPrediction:
    """What :class:`LightNet` predicts for a batch of K slots and M hypotheses a slot.

    Attributes:
        position: ``(B, K, 3)`` camera-frame metres, one row per slot.
        intensity: ``(B, K, 3)`` in the units of the image model (not yet gated).
        presence: ``(B, K)`` in (0, 1): the probability that the room has more than ``k``
            lights (the count head's); slot 0 is always present (1).
        ambient: ``(B, 3)``.
        count_logits: ``(B, K)``: scores of 1 .. K lights.
        count_threshold: a slot ``k >= 1`` counts where ``presence[k]`` reaches it
            (:attr:`LightNet.count_threshold`, calibrated on validation scenes).
        anchor_logits: ``(B, K, M)`` scores of each slot's position hypotheses.
        anchor_position: ``(B, K, M, 3)`` metres: the hypotheses (anchors moved to the
            vertex of their cost parabola); each slot refines its best-scored one.
    """

    position: Tensor
    intensity: Tensor
    presence: Tensor
    ambient: Tensor
    count_logits: Tensor
    anchor_logits: Tensor
    anchor_position: Tensor
    count_threshold: float = 0.5

    @property
    def count(self) -> Tensor:
        """``(B,)`` long: the number of lights, 1 .. K: one, and each slot after it whose
        presence reaches :attr:`count_threshold` (presence falls from slot to slot)."""
        return 1 + (self.presence[:, 1:] >= self.count_threshold).sum(1)

    def lights_of(self, index: int) -> tuple[Tensor, Tensor]:
        """Positions and intensities ``(n, 3)`` of image ``index``'s first ``n`` slots, ``n``
        its :attr:`count`."""
        n = int(self.count[index])
        return self.position[index, :n], self.intensity[index, :n]


@dataclass
class SceneFrame:
    """Per-image normalisation: ``centre (B, 3)``, ``size (B,)`` metres, ``exposure (B,)``."""

    centre: Tensor
    size: Tensor
    exposure: Tensor


def scene_frame(image: Tensor, gbuffer: GBuffer) -> SceneFrame:
    """Centroid and bounding-box diagonal of the valid points, and the image exposure.

    Args:
        image: ``(B, 3, H, W)`` linear RGB.
        gbuffer: the view's G-buffer; its mask must hold at least one pixel per image.
    """
    mask = gbuffer.mask
    count = mask.flatten(1).sum(1)
    if bool((count == 0).any()):
        raise ValueError(f"image(s) {(count == 0).nonzero().flatten().tolist()} have no valid pixel")
    centre, lo, hi = gbuffer.extent()
    size = (hi - lo).norm(dim=-1).clamp_min(1e-6)
    return SceneFrame(centre=centre, size=size, exposure=brightest_percentile(image, mask).clamp_min(1e-8))


def brightest_percentile(image: Tensor, mask: Tensor, q: float = 0.99) -> Tensor:
    """``(B,)``: the ``q`` quantile of the valid pixels' brightest channel of ``image
    (B, 3, H, W)`` over ``mask (B, H, W)``, linearly interpolated between order statistics
    (as :func:`torch.nanquantile`), from the top ``1 - q`` alone (topk, not a sort); 0 for
    an image without a valid pixel."""
    count = mask.flatten(1).sum(1)
    brightest = image.amax(1).flatten(1)
    brightest = torch.where(mask.flatten(1), brightest, torch.full_like(brightest, float("-inf")))
    last = (count - 1).clamp_min(0)
    position = q * last.to(image.dtype)
    below = position.floor().long()
    above = torch.minimum(below + 1, last)
    low_rank, high_rank = last - below, last - above  # ranks from the top
    top = brightest.topk(int(low_rank.max()) + 1, dim=1).values
    low, high = top.gather(1, low_rank[:, None])[:, 0], top.gather(1, high_rank[:, None])[:, 0]
    value = low + (high - low) * (position - below.to(image.dtype))
    return torch.where(count > 0, value, torch.zeros_like(value))


def _average_to(x: Tensor, size: int) -> Tensor:
    """``adaptive_avg_pool2d(x, size)``; by fixed windows where they tile the image
    (the same windows, 25% faster on CPU; identical for 2x2 and 4x4)."""
    H, W = x.shape[-2:]
    if H % size or W % size:
        return F.adaptive_avg_pool2d(x, size)
    return F.avg_pool2d(x, (H // size, W // size))


def network_inputs(image: Tensor, gbuffer: GBuffer, frame: SceneFrame, size: int) -> Tensor:
    """The normalised ``(B, 10, size, size)`` input of :class:`LightNet`.

    Channels: image / s (3, clamped to [0, 4]), normalised points (3), normals (3), mask
    (1); invalid pixels hold zeros, and the resampling averages valid pixels only.
    """
    B, _, H, W = image.shape
    mask = gbuffer.mask[:, None].to(image.dtype)
    s = frame.exposure[:, None, None, None]
    # Written channel-last, where the sources (channel-last G-buffer maps) are read in
    # order and the 2x2 average pooling runs 2-3x faster on the CPU than channel-first.
    maps = torch.empty(B, 9, H, W, dtype=image.dtype, device=image.device, memory_format=torch.channels_last)
    torch.div(image, s, out=maps[:, 0:3]).clamp_(0, 4)
    points = maps[:, 3:6].permute(0, 2, 3, 1)
    torch.sub(gbuffer.points, frame.centre[:, None, None], out=points).div_(frame.size[:, None, None, None])
    maps[:, 6:9] = gbuffer.normals.permute(0, 3, 1, 2)
    maps = torch.where(gbuffer.mask[:, None], maps, 0.0)  # one pass; invalid pixels may hold non-finite points
    pooled = _average_to(maps, size)
    coverage = _average_to(mask, size)
    return torch.cat([pooled / coverage.clamp_min(1e-6) * (coverage > 0), coverage], 1)


def _parabola_vertex(cost: Tensor, per_axis: int) -> Tensor:
    """Per anchor of an ``per_axis^3`` grid (``cost (B, M)``, x-major), the offset in grid
    steps ``(B, M, 3)`` of the minimum of the parabola through it and its two neighbours
    along each axis; 0 where the parabola does not open upwards; within +-0.5."""
    grid = cost.view(-1, per_axis, per_axis, per_axis)
    shifts = []
    for axis in (1, 2, 3):
        before = torch.cat([grid.narrow(axis, 0, 1), grid.narrow(axis, 0, per_axis - 1)], axis)
        after = torch.cat([grid.narrow(axis, 1, per_axis - 1), grid.narrow(axis, per_axis - 1, 1)], axis)
        curvature = before - 2 * grid + after
        vertex = 0.5 * (before - after) / curvature.clamp_min(1e-12)
        shifts.append(torch.where(curvature > 1e-12, vertex.clamp(-0.5, 0.5), torch.zeros_like(vertex)))
    return torch.stack(shifts, -1).reshape(cost.shape[0], -1, 3)


def _block(cin: int, cout: int, stride: int) -> nn.Sequential:
    groups = 8 if cout % 8 == 0 else 1
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.GroupNorm(groups, cout), nn.SiLU(),
        nn.Conv2d(cout, cout, 3, 1, 1, bias=False), nn.GroupNorm(groups, cout), nn.SiLU(),
    )


class LightNet(nn.Module):
    """Small CNN that counts up to ``max_lights`` point lights, places them, and gives the ambient.

    Args:
        max_lights: slots K; each has a position, an RGB intensity; the count head says
            how many of them the room has.
        input_size: side of the square grid the inputs are resampled to.
        widths: channels of the stride-2 stages (each halves the grid).
        hidden: width of the fully connected head.
        anchors_per_axis, anchor_extent: each slot's hypotheses, a grid of
            ``anchors_per_axis^3`` points spanning ``+-anchor_extent`` scene sizes.
        falloff: the image model's falloff; sets how intensity scales with size.
        evidence_points: the anchors' photometric errors are measured on about
            this many pixels along the shorter image side.
        cascade_levels: finer cost volumes around each slot's chosen anchor, each a 5^3
            grid at a quarter of the previous step (1: quarter steps; 2: sixteenths).
            Each level costs 125 more hypotheses a slot on the evidence pixels.
        offset_steps: how far each slot's learned offset may move it from the cascade's
            best, in anchor steps (0.0625: the finest step of two levels).
        count_threshold: the presence a slot after the first needs to count (0.5: the
            count head's median; training calibrates it on its validation scenes,
            :func:`selfsup.evaluate.calibrate_count_threshold`, and the checkpoint keeps it).

    ``forward(image (B, 3, H, W), gbuffer, kd (B, H, W, 3) or None) -> LightPrediction``.
    """

    def __init__(self, max_lights: int = 3, input_size: int = 64, widths: tuple[int, ...] = (32, 48, 64, 96, 128),
                 hidden: int = 256, anchors_per_axis: int = 6, anchor_extent: float = 0.75,
                 falloff: Falloff | str = Falloff.INVERSE_SQUARE, evidence_points: int = 16, cascade_levels: int = 2,
                 offset_steps: float = 0.0625, count_threshold: float = 0.5):
        super().__init__()
        if not offset_steps >= 0:
            raise ValueError(f"offset_steps must be >= 0, got {offset_steps}")
        if not 0 < count_threshold <= 1:
            raise ValueError(f"count_threshold must be in (0, 1], got {count_threshold}")
        self.count_threshold = float(count_threshold)
        if max_lights < 1:
            raise ValueError(f"max_lights must be >= 1, got {max_lights}")
        if cascade_levels < 1:
            raise ValueError(f"cascade_levels must be >= 1, got {cascade_levels}")
        if input_size < 2 ** len(widths) or input_size % 2 ** len(widths):
            raise ValueError(f"input_size {input_size} must be a positive multiple of 2^{len(widths)} "
                             "(one halving per stage)")
        if min(widths, default=1) < 1 or hidden < 1:
            raise ValueError(f"widths and hidden must be >= 1 channels, got {list(widths)} and {hidden}")
        if anchors_per_axis < 2 or not anchor_extent > 0 or evidence_points < 1:
            raise ValueError(f"anchors_per_axis must be >= 2, anchor_extent > 0 and evidence_points >= 1, got "
                             f"{anchors_per_axis}, {anchor_extent} and {evidence_points}")
        self.max_lights = max_lights
        self.input_size = input_size
        self.falloff = Falloff(falloff)
        self.evidence_points = evidence_points
        self.cascade_levels = cascade_levels
        stages, cin = [], IN_CHANNELS
        for width in widths:
            stages.append(_block(cin, width, 2))
            cin = width
        self.backbone = nn.Sequential(*stages)
        cells = (input_size // 2 ** len(widths)) ** 2
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(cin * cells, hidden), nn.SiLU(), nn.Linear(hidden, hidden), nn.SiLU())
        axis = torch.linspace(-anchor_extent, anchor_extent, anchors_per_axis)
        grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
        self.register_buffer("anchors", grid, persistent=False)
        self.anchors_per_axis = anchors_per_axis
        fine = torch.arange(-2.0, 3.0)
        self.register_buffer("fine_grid", torch.stack(torch.meshgrid(fine, fine, fine, indexing="ij"), -1).reshape(-1, 3),
                             persistent=False)
        self.anchor_step = 2 * anchor_extent / max(anchors_per_axis - 1, 1)
        self.finest_step = self.anchor_step * 0.25**cascade_levels  # the finest cascade level's grid step
        self.offset_reach = self.anchor_step * offset_steps  # each slot's learned offset stays within it
        anchors = grid.shape[0]
        self.evidence_in = nn.Sequential(nn.Linear(anchors, hidden), nn.SiLU())
        self.slot_embedding = nn.Parameter(torch.zeros(max_lights, hidden))
        # Prior logits: -20 x the relative excess error (fixed: the learned scores add to it).
        self.register_buffer("evidence_weight", torch.tensor(20.0), persistent=False)
        self.slot_out = nn.Linear(2 * hidden, 6)  # offset (3) and log intensity (3) of a slot
        self.anchor_out = nn.Linear(2 * hidden, anchors)
        # The count reads the image features and how much each volume's best lowers the error.
        self.count_out = nn.Sequential(nn.Linear(hidden + 2 * max(max_lights - 1, 1), hidden), nn.SiLU(),
                                       nn.Linear(hidden, max_lights))
        self.ambient_out = nn.Linear(hidden, 3)
        with torch.no_grad():  # learned scores start at zero: the physics prior decides at first
            self.anchor_out.weight.zero_()
            self.anchor_out.bias.zero_()
            self.slot_out.weight.mul_(0.1)
            self.slot_out.bias.zero_()
            self.slot_out.weight[:3].zero_()  # offsets start at zero

    def _evidence_pixels(self, image: Tensor, gbuffer: GBuffer, kd: Tensor | None) -> tuple[Tensor, ...]:
        """Every ``step``-th pixel's points, normals, mask, albedo and colour (float32)."""
        step = max(1, round(min(image.shape[-2:]) / self.evidence_points))
        g = gbuffer
        points, normals, mask = g.points[:, ::step, ::step].float(), g.normals[:, ::step, ::step].float(), g.mask[:, ::step, ::step]
        colour = image[:, :, ::step, ::step].float()
        albedo = torch.full_like(points, GREY_ALBEDO) if kd is None else kd[:, ::step, ::step].float()
        return points, normals, mask, albedo, colour

    @torch.no_grad()
    def photometric_costs(self, normalised: Tensor, pixels: tuple[Tensor, ...], frame: SceneFrame) -> Tensor:
        """``(B, M)`` photometric error of one more light at normalised positions ``(B|1, M, 3)``
        on ``pixels`` (:meth:`_evidence_pixels`, the colour perhaps a residual)."""
        points, normals, mask, albedo, colour = pixels
        position = frame.centre[:, None] + frame.size[:, None, None] * normalised.to(frame.centre)
        with torch.autocast(colour.device.type, enabled=False):  # sums of many small terms: keep float32
            return single_light_costs(position.float(), points, normals, mask, albedo, colour,
                                      frame.exposure.float(), self.falloff)

    def refine_anchor(self, centre: Tensor, pixels: tuple[Tensor, ...], frame: SceneFrame) -> Tensor:
        """Cascade: ``cascade_levels`` times, the best of a 5^3 grid at a quarter of the
        previous step around ``centre (B, 3)`` (normalised), moved to its parabola
        vertex; ``(B, 3)``, no gradient."""
        rows = torch.arange(centre.shape[0], device=centre.device)
        step = self.anchor_step
        for _ in range(self.cascade_levels):
            step = 0.25 * step
            fine = centre[:, None] + step * self.fine_grid.to(centre)  # (B, 125, 3)
            costs = self.photometric_costs(fine, pixels, frame)
            shift = _parabola_vertex(costs, 5)
            pick = costs.argmin(1)
            centre = fine[rows, pick] + step * shift[rows, pick]
        return centre.detach()

    def forward(self, image: Tensor, gbuffer: GBuffer, kd: Tensor | None = None) -> LightPrediction:
        frame = scene_frame(image, gbuffer)
        features = self.head(self.backbone(network_inputs(image, gbuffer, frame, self.input_size)))
        pixels = self._evidence_pixels(image, gbuffer, kd)
        positions, offsets, logits, hypotheses, best_costs = [], [], [], [], []
        for k in range(self.max_lights):
            at = pixels
            if k:  # what the slots before leave
                at = (*pixels[:4], residual_after(torch.stack(positions, 1).detach(), *pixels, self.falloff))
            costs = self.photometric_costs(self.anchors[None], at, frame)
            best = costs.amin(1, keepdim=True).clamp_min(1e-12)
            best_costs.append(best[:, 0])
            evidence = -(costs / best - 1).clamp(0, 10).to(features.dtype)
            slot = torch.cat([features + self.slot_embedding[k], self.evidence_in(evidence)], 1)
            anchor_logits = self.anchor_out(slot) + self.evidence_weight * evidence
            # Each anchor moves to the vertex of the parabola through its neighbours' errors
            # (sub-grid refinement, as in stereo matching).
            shift = _parabola_vertex(costs.float(), self.anchors_per_axis).to(features.dtype)
            hypotheses.append(self.anchors + self.anchor_step * shift)
            chosen = anchor_logits.argmax(1)
            # The chosen anchor refined on finer cost volumes around it (a cascade, as in
            # multi-view stereo networks), plus a learned offset within offset_reach.
            raw = self.slot_out(slot)
            normalised = self.refine_anchor(self.anchors[chosen], at, frame) + self.offset_reach * torch.tanh(raw[:, :3])
            positions.append(frame.centre + frame.size[:, None] * normalised)
            offsets.append(raw[:, 3:])
            logits.append(anchor_logits)
        best_costs = torch.stack(best_costs, 1).clamp_min(1e-12)
        if self.max_lights > 1:  # how much each slot's best lowers the error: on the last slot's, and on slot 0's
            ratios = torch.cat([best_costs[:, 1:] / best_costs[:, :-1], best_costs[:, 1:] / best_costs[:, :1]], 1).log()
        else:
            ratios = best_costs.new_zeros(len(image), 2)
        count_in = torch.cat([features, ratios.to(features.dtype)], 1)
        count_logits = self.count_out(count_in)
        more_than = 1 - torch.softmax(count_logits.float(), 1).cumsum(1)  # P(count > k + 1)
        presence = torch.cat([torch.ones_like(more_than[:, :1]), more_than[:, :-1]], 1).clamp(0, 1).to(features.dtype)
        unit = frame.exposure if self.falloff == Falloff.NONE else frame.exposure * frame.size**2
        intensity = torch.exp(torch.stack(offsets, 1).clamp(-12, 12)) * unit[:, None, None]
        ambient = F.softplus(self.ambient_out(features)) * frame.exposure[:, None] * 0.1
        anchor_position = frame.centre[:, None, None] + frame.size[:, None, None, None] * torch.stack(hypotheses, 1)
        return LightPrediction(position=torch.stack(positions, 1), intensity=intensity, presence=presence,
                               ambient=ambient, count_logits=count_logits, anchor_logits=torch.stack(logits, 1),
                               anchor_position=anchor_position, count_threshold=self.count_threshold)


@torch.no_grad()
def residual_after(position: Tensor, points: Tensor, normals: Tensor, mask: Tensor, kd: Tensor, image: Tensor,
                   falloff: Falloff) -> Tensor:
    """``(B, 3, H, W)``: ``image`` less the diffuse, unshadowed light of ``position (B, k, 3)``
    metres at their least-squares intensities (fitted with an ambient, which stays in).

    Args:
        points, normals: ``(B, H, W, 3)``; mask ``(B, H, W)``; kd ``(B, H, W, 3)``; image ``(B, 3, H, W)``.
    """
    diffuse = light_transport(GBuffer(points, normals, mask), Material(kd=kd), position, falloff=falloff,
                              shadows="none", specular=False).diffuse
    cols = basis_images(kd, None, diffuse, None)
    weights = mask[:, None].to(image.dtype).expand_as(image)
    intensity, _, _ = solve_intensities(cols, kd, image, weights, ridge=1e-6)
    return image - (cols * intensity.transpose(1, 2)[..., None, None]).sum(2)
