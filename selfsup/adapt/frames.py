"""A user's capture frames as adaptation data: read once, prepared as the estimator prepares them, split.

Each frame goes through what ``mode=estimate`` does before its network sees it (the
working resolution, the working range of values, normals from the depth refitted where
noisy, clipped pixels left out: :func:`selfsup.estimation.prepare.prepare`), so the
network adapts to exactly the inputs it will be given. Its regions of one albedo are
found once (:func:`selfsup.estimation.albedo_free.observe`: smooth surfaces cut by the
image's edges, regions under :data:`~selfsup.estimation.albedo_free.MIN_SEGMENT_PIXELS`
left out): the loss solves each region's colour (:func:`selfsup.linear.segment_albedo`).

A frame that cannot be used (unreadable, no valid depth, black, too little of it in
regions of one albedo) is named with its reason and skipped. The frames are split in
input order into blocks of :attr:`FrameOptions.block` consecutive frames, every
``round(1 / holdout)``-th block held back: neighbouring frames of one video stay on one
side, so the held-back loss measures frames the network did not adapt on.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from render import GBuffer
from selfsup.estimation.albedo_free import observe
from selfsup.estimation.files import estimate_items, failure_reason, record_line
from selfsup.estimation.inputs import iter_inputs, read_item
from selfsup.estimation.jobs import read_records
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.prepare import prepare, within_pixels, working_range

__all__ = ["FrameOptions", "View", "UserFrame", "FrameBatch", "AdaptFrames", "load_frames", "collate_frames", "teach", "mirrored"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameOptions:
    """How the frames are read and split (mirrors ``adapt``'s input keys).

    ``holdout``: share held back (by blocks of ``block`` consecutive frames);
    ``min_region_share``: least share of a frame's valid pixels in regions of one albedo;
    ``loss_stride``: the loss re-renders each frame on blocks of ``loss_stride`` pixels a
    side (:meth:`selfsup.scenes.io.Scene.binned`; the network still sees the frame as
    ``mode=estimate`` gives it): the shadows' cost falls with the pixels;
    ``depth_scale``, ``intrinsics``: as ``estimate.depth_scale`` / ``estimate.intrinsics``.
    """

    holdout: float = 0.2
    block: int = 8
    min_region_share: float = 0.2
    loss_stride: int = 2
    depth_scale: float = 1000.0
    intrinsics: tuple[float, float, float, float] | None = None

    def __post_init__(self):
        if not 0 < self.holdout < 1:
            raise ValueError(f"adapt.frames.holdout must be in (0, 1), got {self.holdout}")
        if self.block < 1 or self.loss_stride < 1:
            raise ValueError(f"adapt.frames.block and adapt.frames.loss_stride must be >= 1, got {self.block} and "
                             f"{self.loss_stride}")
        if not 0 <= self.min_region_share < 1:
            raise ValueError(f"adapt.frames.min_region_share must be in [0, 1), got {self.min_region_share}")


@dataclass
class View:
    """One frame at one resolution: ``image (3, H, W)`` linear, ``points/normals (H, W, 3)``,
    ``mask (H, W)``, ``K (3, 3)``."""

    image: Tensor
    points: Tensor
    normals: Tensor
    mask: Tensor
    K: Tensor

    @staticmethod
    def of(problem) -> "View":
        g = problem.gbuffer
        return View(problem.image[0].float(), g.points[0].float(), g.normals[0].float(), g.mask[0], g.intrinsics[0].float())


@dataclass
class UserFrame:
    """One prepared frame: the ``network``'s view (as ``mode=estimate`` gives it), the
    ``loss``'s (binned by :attr:`FrameOptions.loss_stride`) and its ``labels (h w)`` long
    there: each pixel's region of one albedo, -1 where none (left out of the loss)."""

    id: str
    network: View
    loss: View
    labels: Tensor
    source: object = None  # the input it was read from (a frame of estimate.input's kinds)
    teacher: Tensor | None = None  # (n, 3): the per-frame search's lights (:func:`teach`); (0, 3): none found

    @property
    def size(self) -> tuple[int, int, int, int]:  # the network's (H, W) and the loss's (h, w)
        return tuple(self.network.mask.shape) + tuple(self.loss.mask.shape)


@dataclass
class FrameBatch:
    """Same-sized frames stacked: the network's ``network_image (B, 3, H, W)`` and
    ``network_gbuffer``; the loss's ``image (B, 3, h, w)``, ``gbuffer`` and regions
    ``(labels (B, h w), count)`` (``count``: none), as :func:`selfsup.losses.reconstruction_loss` takes them."""

    ids: list[str]
    network_image: Tensor
    network_gbuffer: GBuffer
    image: Tensor
    gbuffer: GBuffer
    segments: tuple[Tensor, int]
    teacher: Tensor | None = None  # (B, K, 3) the search's lights, padded; None: no frame has them
    teacher_mask: Tensor | None = None  # (B, K) bool: which rows of ``teacher`` are lights


@dataclass
class AdaptFrames:
    """The usable frames, split: ``train`` and ``held`` lists, and ``skipped`` ``{name: reason}``."""

    train: list[UserFrame] = field(default_factory=list)
    held: list[UserFrame] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)


def _prepared(item, estimate: EstimateOptions, options: FrameOptions) -> UserFrame:
    # One input as a UserFrame; raises with the reason it cannot be used.
    scene, _ = working_range(within_pixels(read_item(item), estimate))
    problem = prepare([scene], estimate)
    coarse = prepare([scene.binned(options.loss_stride)], estimate) if options.loss_stride > 1 else problem
    observed = observe(coarse)
    usable = observed.pairs[0]
    share = float(usable.sum()) / max(int(coarse.gbuffer.mask.sum()), 1)
    if share < options.min_region_share:
        raise ValueError(f"only {share:.0%} of its valid pixels lie in regions of one albedo large enough to solve "
                         f"(adapt.frames.min_region_share={options.min_region_share}): too noisy or too fragmented "
                         "a frame")
    labels = torch.where(usable, observed.segments[0], torch.full_like(observed.segments[0], -1))
    return UserFrame(scene.id, View.of(problem), View.of(coarse), labels, item)


def load_frames(inputs: list[str | Path], options: FrameOptions, estimate: EstimateOptions | None = None,
                progress=None) -> AdaptFrames:
    """The usable frames of ``inputs`` (each what ``estimate.input`` takes: a capture
    folder, a folder of them, a list file, scene files), split as the module says.

    Raises:
        FileNotFoundError: an input that does not exist or holds no frames.
        ValueError: too few usable frames to hold some back (at least 2 needed).
    """
    estimate = estimate or EstimateOptions()
    frames: list[UserFrame] = []
    skipped: dict[str, str] = {}
    for source in inputs:
        for item in iter_inputs(source, depth_scale=options.depth_scale, intrinsics=options.intrinsics,
                                key="adapt.input", nested=True):
            try:
                frames.append(_prepared(item, estimate, options))
            except Exception as error:  # noqa: BLE001 - any frame's failure is named, never the run's
                skipped[str(item)] = failure_reason(error)
                log.warning("skipped %s: %s", item, skipped[str(item)])
            if progress is not None:
                progress.update(1)
    if len(frames) < 2:
        raise ValueError(f"adapt.input holds {len(frames)} usable frame(s) ({len(skipped)} skipped): adaptation "
                         "needs at least 2, one of them held back")
    every = max(2, round(1 / options.holdout))
    held_block = [(i // options.block) % every == every - 1 for i in range(len(frames))]
    if not any(held_block):  # fewer frames than blocks to the first held one: the last block
        last = (len(frames) - 1) // options.block
        held_block = [i // options.block == last for i in range(len(frames))]
    if all(held_block):
        held_block[0] = False
    split = AdaptFrames(skipped=skipped)
    for frame, held in zip(frames, held_block):
        (split.held if held else split.train).append(frame)
    return split


def mirrored(batch: FrameBatch, which: Tensor) -> FrameBatch:
    """``batch`` with the frames ``which (B,)`` bool mirrored left to right: their images,
    G-buffers (x negated, the principal point mirrored), regions and teachers' lights (x
    negated). A mirrored room is a room: the same physics, a view the captures lack."""
    def pick(flipped: Tensor, original: Tensor) -> Tensor:
        return torch.where(which.view(-1, *[1] * (original.dim() - 1)), flipped, original)

    def gbuffer(g: GBuffer) -> GBuffer:
        sign = torch.tensor([-1.0, 1.0, 1.0], dtype=g.points.dtype, device=g.points.device)
        K = g.intrinsics.clone()
        K[:, 0, 2] = g.mask.shape[2] - 1 - K[:, 0, 2]
        return GBuffer(pick(g.points.flip(2) * sign, g.points), pick(g.normals.flip(2) * sign, g.normals),
                       pick(g.mask.flip(2), g.mask), intrinsics=pick(K, g.intrinsics))

    labels, count = batch.segments
    h, w = batch.gbuffer.mask.shape[1:]
    labels = pick(labels.view(-1, h, w).flip(2).reshape(labels.shape), labels)
    teacher = batch.teacher
    if teacher is not None:
        teacher = pick(teacher * torch.tensor([-1.0, 1.0, 1.0], dtype=teacher.dtype, device=teacher.device), teacher)
    return FrameBatch(batch.ids, pick(batch.network_image.flip(3), batch.network_image), gbuffer(batch.network_gbuffer),
                      pick(batch.image.flip(3), batch.image), gbuffer(batch.gbuffer), (labels, count), teacher,
                      batch.teacher_mask)


def teach(frames: list[UserFrame], checkpoint: str | None, cache: Path, device: str = "cpu") -> int:
    """Each frame's lights as the estimator's per-frame search finds them (``mode=estimate``'s
    defaults with the network of ``checkpoint``: the albedo-free fit of each region's
    level, a search, robust refinement and model selection; no truth), into
    ``frame.teacher``; a frame where it finds no light gets none (0 rows). The records are
    kept in ``cache`` (JSON Lines) and read back instead of searched again. Returns how
    many frames have lights."""
    known = {str(record["id"]): record for record in read_records(cache)}  # a killed run's torn line: redone
    missing = [frame for frame in frames if frame.id not in known]
    if missing:
        options = EstimateOptions(checkpoint=checkpoint)
        with cache.open("a") as out:
            for frame, (_, record, reason) in zip(missing, estimate_items([f.source for f in missing], options,
                                                                           device=device)):
                if record is None:
                    log.warning("the search failed on %s (%s): no lights to teach there", frame.id, reason)
                lights = [{"position": light["position"]} for light in (record or {"lights": []})["lights"]]
                known[frame.id] = {"id": frame.id, "lights": lights}
                out.write(record_line(known[frame.id]) + "\n")
    for frame in frames:
        frame.teacher = torch.tensor([light["position"] for light in known[frame.id]["lights"]],
                                     dtype=torch.float32).reshape(-1, 3)
    return sum(len(frame.teacher) > 0 for frame in frames)


def collate_frames(frames: list[UserFrame], device=None, slots: int = 0) -> FrameBatch:
    """Stack same-sized ``frames`` into a :class:`FrameBatch` on ``device``, their teachers'
    lights padded to ``slots`` (0: left out)."""
    sizes = {frame.size for frame in frames}
    if len(sizes) != 1:
        raise ValueError(f"frames of one batch must share a size, got {sorted(sizes)}")
    labels = torch.stack([frame.labels for frame in frames])
    count = int(labels.max()) + 1
    labels = torch.where(labels < 0, torch.full_like(labels, count), labels)

    def stacked(view: str) -> tuple[Tensor, GBuffer]:
        def stack(name: str) -> Tensor:
            return torch.stack([getattr(getattr(frame, view), name) for frame in frames]).to(device)

        return stack("image"), GBuffer(stack("points"), stack("normals"), stack("mask"), intrinsics=stack("K"))

    batch = FrameBatch([frame.id for frame in frames], *stacked("network"), *stacked("loss"), (labels.to(device), count))
    if slots and any(frame.teacher is not None for frame in frames):
        batch.teacher = torch.zeros(len(frames), slots, 3)
        batch.teacher_mask = torch.zeros(len(frames), slots, dtype=torch.bool)
        for i, frame in enumerate(frames):
            if frame.teacher is not None:
                n = min(len(frame.teacher), slots)
                batch.teacher[i, :n] = frame.teacher[:n]
                batch.teacher_mask[i, :n] = True
        batch.teacher, batch.teacher_mask = batch.teacher.to(device), batch.teacher_mask.to(device)
    return batch
