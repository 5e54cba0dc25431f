"""``mode=adapt``: fine-tune a network on a user's unlabelled capture frames, self-supervised.

Each step re-renders a batch of the user's frames (half of them mirrored) from the
network's lights with the shadowed layer and takes the photometric error as the loss, the
albedo solved per frame in closed form (:func:`selfsup.losses.reconstruction_loss` with the
frames' regions of one albedo: :mod:`selfsup.adapt.frames`), and the per-frame search's
lights, where that error is least over the whole room, teach each slot's hypothesis scores
and position (:mod:`selfsup.teacher`); no light, albedo or count of the user's is
read. What keeps it from going wrong:

- **robust to what the model lacks**: the cost is a pseudo-Huber of the exposure-
  normalised residual (indirect light, highlights and shadows the depth cannot cast pull
  with bounded force); clipped pixels and depth holes are out of the G-buffer's mask;
  regions of one albedo too small to solve are left out; an ambient term takes the
  even part of the indirect light;
- **no forgetting**: every step also takes a batch of procedural scenes of the shipped
  network's recipe with their own loss (their albedo known, their count its auxiliary
  target), and optionally an L2 pull towards the starting weights (``anchor_weight``);
- **no collapse**: a hinge pushes slots out of the surfaces and from behind them
  (:func:`selfsup.adapt.guards.guard_penalty`); each validation measures the held-back
  frames' loss, count and degenerate lights and the procedural validation's error, and a
  checkpoint :func:`selfsup.adapt.guards.refusals` names is never kept;
- **the iterative network** (:class:`selfsup.network.IterativeLightNet`) adapts the same way
  with its own losses at every unrolled step: on the user's frames
  :func:`selfsup.sequence_loss.taught_sequence_loss` (the albedo-free re-render and the
  search's lights), on the procedural scenes :func:`selfsup.sequence_loss.sequence_loss`
  against each scene's re-render minimum, its pool rendered and prepared as its recipe's
  (``experiment=iterative``: twice the grid, prepared as a capture);
- **the best by the held-back loss** among the accepted validations is written to
  ``adapt.out`` as it is found (the starting network if none beats it), so a killed run
  leaves its best; ``<adapt.out>.run/last.pt`` resumes the run exactly (the batches of
  step ``n`` are drawn from ``n`` and the seed).
"""

from __future__ import annotations

import logging
import math
import statistics
import time
from collections import defaultdict
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from torch import Tensor

from render import Material, ShadowedBlinnPhong
from selfsup.adapt.frames import AdaptFrames, FrameOptions, UserFrame, collate_frames, load_frames, mirrored, teach
from selfsup.adapt.guards import GuardOptions, degenerate_lights, guard_penalty, refusals
from selfsup.losses import TeacherOptions, teacher_loss
from selfsup.checkpoint import LIGHTNET_CHECKPOINT, load_checkpoint, load_network, save_network
from selfsup.engine import render_grid
from selfsup.estimation.files import progress_bar
from selfsup.estimation.jobs import locked
from selfsup.evaluate import evaluate_network, summarise
from selfsup.losses import LossOptions, SceneBatch, reconstruction_loss, scene_batch
from selfsup.model import GREY_ALBEDO, LightNet, scene_frame
from selfsup.network import IterativeLightNet
from selfsup.sequence_loss import SequenceLossOptions, pool_minima, sequence_loss, taught_sequence_loss

__all__ = ["AdaptOptions", "Procedural", "adapt_files"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class AdaptOptions:
    """The run (mirrors ``configs/adapt``): ``steps`` of ``batch`` user frames and
    ``procedural_batch`` procedural scenes (0: none; ``procedural_albedo_share`` of the steps
    let their cost volumes see the albedo, as the shipped network learned), AdamW at ``lr`` with a one-cycle
    schedule (``warmup`` share rising), gradients clipped at ``grad_clip``; validation every
    ``val_every`` steps; ``anchor_weight``: L2 pull to the starting weights (summed squares);
    ``guard_weight``: weight of the surface hinge; ``mirror``: each frame of a batch mirrored
    left to right at random (:func:`selfsup.adapt.frames.mirrored`)."""

    steps: int = 600
    batch: int = 8
    lr: float = 1e-4
    weight_decay: float = 1e-4
    warmup: float = 0.1
    grad_clip: float = 1.0
    val_every: int = 100
    procedural_batch: int = 8
    procedural_count_weight: float = 1.0
    procedural_albedo_share: float = 0.25
    anchor_weight: float = 0.05
    guard_weight: float = 1.0
    mirror: bool = True
    device: str = "auto"
    threads: int = 0
    progress: bool = True
    tensorboard: bool = True
    images: int = 4
    resume: str = "auto"
    seed: int = 0

    def __post_init__(self):
        if self.steps < 1 or self.batch < 1 or self.val_every < 1 or self.images < 1:
            raise ValueError(f"adapt.steps, adapt.batch, adapt.val_every and adapt.images must be >= 1: {self}")
        if not self.lr > 0 or not 0 <= self.warmup < 1 or self.grad_clip < 0 or self.weight_decay < 0:
            raise ValueError(f"adapt.lr must be > 0, adapt.warmup in [0, 1), adapt.grad_clip and adapt.weight_decay >= 0: "
                             f"{self.lr}, {self.warmup}, {self.grad_clip}, {self.weight_decay}")
        if not 0 <= self.procedural_albedo_share <= 1:
            raise ValueError(f"adapt.procedural_albedo_share must be in [0, 1], got {self.procedural_albedo_share}")
        for name in ("procedural_batch", "procedural_count_weight", "anchor_weight", "guard_weight", "threads"):
            if getattr(self, name) < 0:
                raise ValueError(f"adapt.{name} must be >= 0, got {getattr(self, name)}")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"adapt.device must be auto, cpu or cuda, got {self.device!r}")
        if self.resume not in ("auto", "never"):
            raise ValueError(f"adapt.resume must be auto (go on from <adapt.out>.run/last.pt if there) or never, "
                             f"got {self.resume!r}")


@dataclass(frozen=True)
class Procedural:
    """The procedural scenes: ``sampler``/``degradations``/``samples`` and ``scenes`` of the
    mixed-in pool (the shipped network's recipe), and of the validation set
    (``validation_*``, scored as ``mode=eval``'s true-reflectance set: the network's cost
    volumes see the albedo)."""

    sampler: object
    degradations: object
    samples: int
    scenes: int
    validation_sampler: object
    validation_degradations: object
    validation_samples: int
    validation_scenes: int
    seed: int = 4000


def _device(name: str) -> torch.device:
    if name == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("adapt.device=cuda but no CUDA device is available")
    return torch.device("cuda" if name == "cuda" or (name == "auto" and torch.cuda.is_available()) else "cpu")


class _Run:
    """One adaptation's state: the network, its starting weights, the data, the optimiser."""

    def __init__(self, network: LightNet, frames: AdaptFrames, procedural: Procedural, options: AdaptOptions,
                 loss: LossOptions, guards: GuardOptions, teacher: TeacherOptions, renderer: ShadowedBlinnPhong,
                 device: torch.device):
        from selfsup.scenes.dataset import ProceduralScenes, materialise

        self.network, self.frames, self.options, self.loss, self.guards = network, frames, options, loss, guards
        self.teacher = teacher
        self.device, self.renderer = device, renderer.to(device)
        self.start_weights = [p.detach().clone() for p in network.parameters()]
        self.groups: dict[tuple[int, ...], list[UserFrame]] = defaultdict(list)  # by UserFrame.size
        for frame in frames.train:
            self.groups[frame.size].append(frame)
        self.procedural_loss = replace(loss, count_weight=options.procedural_count_weight)
        self.iterative = isinstance(network, IterativeLightNet)
        # The iterative network's terms: its recipe's (configs/experiment/iterative.yaml's loss node).
        self.sequence = SequenceLossOptions(robust_scale=loss.robust_scale)
        K = network.max_lights
        self.pool = None
        if options.procedural_batch:
            self.pool = self._procedural_pool(procedural, K)
        self.validation = materialise(ProceduralScenes(procedural.validation_sampler, procedural.validation_degradations,
                                                       length=procedural.validation_scenes, base_seed=9000,
                                                       samples=procedural.validation_samples, max_lights=K),
                                      workers=0, progress=False)

    def _procedural_pool(self, procedural: Procedural, slots: int) -> dict[str, Tensor]:
        # The mixed-in scenes, as the network learned them: the cost-volume network's at the
        # sampler's size; the iterative one's rendered at twice it, prepared as a capture and
        # pooled onto its grid, with each scene's re-render minimum (found once, here).
        from selfsup.estimation.prepare import prepared_pool
        from selfsup.scenes.dataset import ProceduralScenes, materialise

        sampler = procedural.sampler
        lights = max(slots, len(sampler.n_lights_probs))
        if not self.iterative:
            return materialise(ProceduralScenes(sampler, procedural.degradations, length=procedural.scenes,
                                                base_seed=procedural.seed, samples=procedural.samples, max_lights=slots),
                               workers=0, progress=False)
        fine = replace(sampler, height=2 * sampler.height, width=2 * sampler.width)
        pool = materialise(ProceduralScenes(fine, procedural.degradations, length=procedural.scenes,
                                            base_seed=procedural.seed, samples=procedural.samples, max_lights=lights),
                           workers=0, progress=False)
        pool = prepared_pool(pool, max(sampler.height, sampler.width))
        return {**pool, **pool_minima(pool, slots, self.sequence)}

    def user_batch(self, step: int):
        """Step ``step``'s frames: a size group drawn by its share of the frames, then
        ``batch`` of its frames (all of a smaller group), from the step and the seed."""
        generator = torch.Generator().manual_seed(self.options.seed * 100_003 + step)
        sizes = sorted(self.groups)
        weights = torch.tensor([len(self.groups[s]) for s in sizes], dtype=torch.float64)
        group = self.groups[sizes[int(torch.multinomial(weights, 1, generator=generator))]]
        picked = torch.randperm(len(group), generator=generator)[: self.options.batch].tolist()
        batch = collate_frames([group[i] for i in picked], self.device, self.network.max_lights)
        if self.options.mirror:
            batch = mirrored(batch, (torch.rand(len(picked), generator=generator) < 0.5).to(self.device))
        return batch

    def procedural_batch(self, step: int) -> dict[str, Tensor]:
        generator = torch.Generator().manual_seed(self.options.seed * 7_919 + step)
        index = torch.randperm(self.pool["image"].shape[0], generator=generator)[: self.options.procedural_batch]
        return {key: value[index].to(self.device) for key, value in self.pool.items()}

    def user_terms(self, batch):
        """The user frames' loss ``()`` of a :class:`FrameBatch` (the albedo-free re-render's
        terms and the teacher's), its parts, the re-render's terms, the prediction and the
        frames' :class:`~selfsup.model.SceneFrame`."""
        prediction = self.network(batch.network_image, batch.network_gbuffer, None)
        frame = scene_frame(batch.image, batch.gbuffer)
        if self.iterative:
            terms = taught_sequence_loss(prediction, batch.image, batch.gbuffer, batch.segments, self.renderer,
                                         self.sequence, self.teacher, batch.teacher, batch.teacher_mask)
            parts = {"photometric": float(terms.photometric)}
            if batch.teacher is not None:
                parts.update(teacher_position=float(terms.position), teacher_count=float(terms.presence))
            return terms.total, parts, terms, prediction, frame
        scenes = SceneBatch(batch.image, batch.gbuffer, Material(kd=torch.full((*batch.image.shape[:1],
                                                                                 *batch.image.shape[2:], 3), GREY_ALBEDO,
                                                                                device=batch.image.device)))
        terms = reconstruction_loss(prediction, scenes, self.renderer, self.loss, segments=batch.segments)
        total, parts = terms.total, {"photometric": float(terms.photometric)}
        if batch.teacher is not None:
            taught, taught_parts = teacher_loss(prediction, batch.teacher, batch.teacher_mask, frame.size, self.teacher)
            total, parts = total + taught, {**parts, **taught_parts}
        return total, parts, terms, prediction, frame

    def step_loss(self, step: int) -> tuple[Tensor, dict[str, float]]:
        batch = self.user_batch(step)
        user, parts, _, prediction, frame = self.user_terms(batch)
        guard = guard_penalty(prediction.position, batch.gbuffer, frame.size, self.guards)
        total = user + self.options.guard_weight * guard
        parts = {"user": float(user.detach()), **parts, "guard": float(guard.detach())}
        if self.pool is not None:
            pool = self.procedural_batch(step)
            scenes = scene_batch(pool)
            if self.iterative:  # its own recipe's terms (it reads no albedo)
                terms = sequence_loss(self.network(scenes.image, scenes.gbuffer), scenes, self.renderer,
                                      pool["target_pos"], pool["target_needed"], self.sequence)
                total = total + terms.total
                parts["procedural"] = float(terms.total.detach())
            else:
                total, parts = self._procedural_lightnet(step, pool, scenes, total, parts)
        if self.options.anchor_weight > 0:
            anchor = sum(((p - p0) ** 2).sum() for p, p0 in zip(self.network.parameters(), self.start_weights))
            total = total + self.options.anchor_weight * anchor
            parts["anchor"] = float(anchor.detach())
        if not torch.isfinite(total):
            raise FloatingPointError(f"non-finite adaptation loss at step {step}: {parts}")
        return total, parts

    def _procedural_lightnet(self, step: int, pool: dict[str, Tensor], scenes: SceneBatch, total: Tensor,
                             parts: dict[str, float]) -> tuple[Tensor, dict[str, float]]:
        # The cost-volume network's procedural terms: as the shipped network learned, a share of
        # the steps' cost volumes see the albedo, and the count head reads the true count.
        albedo = float(torch.rand((), generator=torch.Generator().manual_seed(self.options.seed * 7_919 + step))
                       ) < self.options.procedural_albedo_share
        prediction = self.network(scenes.image, scenes.gbuffer, scenes.material.kd if albedo else None)
        procedural = reconstruction_loss(prediction, scenes, self.renderer, self.procedural_loss, pool)
        parts["procedural"] = float(procedural.total.detach())
        return total + procedural.total, parts

    @torch.no_grad()
    def validate(self) -> tuple[dict, Tensor | None]:
        """Held-back loss, mean count, degenerate share; the procedural validation's
        median position error and success; and the first held frames' image grid."""
        was = self.network.training
        self.network.eval()
        losses, photometric, counts, degenerate, grid = [], [], [], [], None
        by_size: dict[tuple[int, ...], list[UserFrame]] = defaultdict(list)
        for frame in self.frames.held:
            by_size[frame.size].append(frame)
        for size in sorted(by_size):
            group = by_size[size]
            for start in range(0, len(group), self.options.batch):
                batch = collate_frames(group[start:start + self.options.batch], self.device, self.network.max_lights)
                user, parts, terms, prediction, frame = self.user_terms(batch)
                losses += [float(user)] * len(batch.ids)
                photometric += [parts["photometric"]] * len(batch.ids)
                count = prediction.count
                counted = torch.arange(prediction.position.shape[1], device=count.device) < count[:, None]
                bad = degenerate_lights(prediction.position, batch.gbuffer, frame.size, self.guards)
                counts += count.tolist()
                degenerate += (bad & counted).any(1).tolist()
                if grid is None:
                    n = self.options.images
                    grid = render_grid(batch.image[:n], terms.render[:n], terms.visibility[:n], frame.exposure[:n])
        procedural = summarise(evaluate_network(self.network, self.validation, albedo=True))
        self.network.train(was)
        return {"held_loss": statistics.fmean(losses), "held_photometric": statistics.fmean(photometric),
                "mean_count": statistics.fmean(counts),
                "degenerate_share": statistics.fmean(float(d) for d in degenerate),
                "procedural_median_error": procedural["median_position_error"],
                "procedural_success": procedural["success_rate"]}, grid


def adapt_files(input: str | list[str], out: str | Path, checkpoint: str | None = None,
                options: AdaptOptions | None = None, frame_options: FrameOptions | None = None,
                guards: GuardOptions | None = None, loss: LossOptions | None = None,
                renderer: ShadowedBlinnPhong | None = None, procedural: Procedural | None = None,
                teacher: TeacherOptions | None = None) -> dict:
    """Adapt the network of ``checkpoint`` (None: the shipped one) on the frames of ``input``
    (a folder, a list file, or a list of them) and write the best accepted weights to
    ``out``; returns the summary (also logged as one line). See the module doc."""
    options, frame_options = options or AdaptOptions(), frame_options or FrameOptions()
    guards, loss, teacher = guards or GuardOptions(), loss or LossOptions(), teacher or TeacherOptions()
    renderer = renderer or ShadowedBlinnPhong(check_finite=False)
    out = Path(out)
    if out.suffix != ".pt":
        raise ValueError(f"adapt.out must name a .pt checkpoint file, got {out}")
    if procedural is None:
        raise ValueError("adapt_files needs the procedural scenes' settings (train.py builds them from configs/adapt)")
    inputs = input if isinstance(input, list) else [input]
    for source in inputs:  # named before <out>.run is made
        if not Path(source).exists():
            raise FileNotFoundError(f"adapt.input {source} does not exist")
    work = Path(f"{out}.run")
    with locked(work / "lock"):
        return _adapt(inputs, out, checkpoint, options, frame_options, guards,
                      loss, teacher, renderer, procedural, work)


def _start_network(checkpoint: str | None, device: torch.device) -> tuple[LightNet | IterativeLightNet, dict]:
    # The network adaptation starts from (either architecture; load_network names an unknown one).
    network, state = load_network(checkpoint or LIGHTNET_CHECKPOINT, map_location=device)
    return network.to(device).train(), state


def _adapt(inputs: list, out: Path, checkpoint: str | None, options: AdaptOptions, frame_options: FrameOptions,
           guards: GuardOptions, loss: LossOptions, teacher: TeacherOptions, renderer: ShadowedBlinnPhong,
           procedural: Procedural, work: Path) -> dict:
    started = time.perf_counter()
    device = _device(options.device)
    if options.threads and device.type == "cpu":
        torch.set_num_threads(options.threads)
    network, state = _start_network(checkpoint, device)
    bar, printing = progress_bar(None, "read", "frame", options.progress)
    quiet = logging.getLogger("selfsup.estimation.prepare")  # "N clipped pixels left out" of each frame, twice
    level = quiet.level
    quiet.setLevel(max(quiet.getEffectiveLevel(), logging.WARNING))
    try:
        with printing:
            frames = load_frames(inputs, frame_options, progress=bar)
        if bar is not None:
            bar.close()
        log.info("%d frames to adapt on, %d held back, %d skipped", len(frames.train), len(frames.held),
                 len(frames.skipped))
        if teacher.position or teacher.anchors or teacher.count:
            searched = time.perf_counter()
            found = teach(frames.train + frames.held, checkpoint, work / "teacher.jsonl", str(device))
            log.info("the per-frame search found lights in %d of %d frames (%.0f s; %s)", found,
                     len(frames.train) + len(frames.held), time.perf_counter() - searched, work / "teacher.jsonl")
    finally:
        quiet.setLevel(level)
    torch.manual_seed(options.seed)
    run = _Run(network, frames, procedural, options, loss, guards, teacher, renderer, device)
    optimiser = torch.optim.AdamW(network.parameters(), lr=options.lr, weight_decay=options.weight_decay)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimiser, options.lr, total_steps=options.steps,
                                                   pct_start=max(options.warmup, 1e-3))
    step, start, best, accepted = 0, None, math.inf, 0
    if options.resume == "auto" and (work / "last.pt").is_file():
        saved = load_checkpoint(work / "last.pt", map_location=device)
        if saved["scheduler"]["total_steps"] != options.steps:
            raise ValueError(f"adapt.steps={options.steps} but the run in {work} was started with "
                             f"{saved['scheduler']['total_steps']}: resume it with the same steps, or start over "
                             "with adapt.resume=never")
        network.load_state_dict(saved["model"])
        optimiser.load_state_dict(saved["optimizer"])
        schedule.load_state_dict(saved["scheduler"])
        step, start, best, accepted = int(saved["step"]), saved["start"], float(saved["best"]), int(saved["accepted"])
        run.start_weights = [saved["start_weights"][i].to(device) for i in range(len(run.start_weights))]
        log.info("resumed from %s at step %d", work / "last.pt", step)
    writer = None
    if options.tensorboard:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(work / "tensorboard"), purge_step=step)
    config = dict(state["model_config"])
    if start is None:
        start, grid = run.validate()
        best = start["held_loss"]
        save_network(out, network, config, {"adapted": False, **start}, {"adapted_from": str(checkpoint or "shipped")})
        if writer is not None:
            _log_validation(writer, start, grid, 0, "before")
    bar, printing = progress_bar(options.steps, "adapt", "step", options.progress)
    if bar is not None:
        bar.update(step)
    last = dict(start)
    with printing:
        while step < options.steps:
            total, parts = run.step_loss(step)
            optimiser.zero_grad(set_to_none=True)
            total.backward()
            if options.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(network.parameters(), options.grad_clip)
            optimiser.step()
            schedule.step()
            step += 1
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{parts['user']:.4f}")
            if writer is not None:
                for name, value in parts.items():
                    writer.add_scalar(f"adapt/{name}", value, step)
            if step % options.val_every == 0 or step == options.steps:
                last, grid = run.validate()
                reasons = refusals(start, last, guards)
                if writer is not None:
                    _log_validation(writer, last, grid, step, "after")
                if reasons:
                    log.warning("step %d refused: %s", step, "; ".join(reasons))
                elif last["held_loss"] < best:
                    best, accepted = last["held_loss"], step
                    save_network(out, network, config, {"adapted": True, "step": step, **last},
                                 {"adapted_from": str(checkpoint or "shipped"), "before": start})
                log.info("step %d: %s", step, ", ".join(f"{k} {v:.4g}" for k, v in last.items()))
                save_network(work / "last.pt", network, config, last,
                             {"optimizer": optimiser.state_dict(), "scheduler": schedule.state_dict(), "step": step,
                              "start": start, "best": best, "accepted": accepted,
                              "start_weights": run.start_weights})
    if bar is not None:
        bar.close()
    if writer is not None:
        writer.close()
    return _summary(frames, start, best, accepted, out, step, (time.perf_counter() - started) / 60)


def _log_validation(writer, values: dict, grid: Tensor | None, step: int, which: str) -> None:
    for name, value in values.items():
        writer.add_scalar(f"held/{name}", value, step)
    if grid is not None:
        writer.add_image(f"held/{which}: input|render|residual|shadow", grid, step)


def _summary(frames: AdaptFrames, start: dict, best: float, accepted: int, out: Path, steps: int,
             minutes: float) -> dict:
    kept = load_checkpoint(out)["metrics"]
    change = best / start["held_loss"] - 1 if start["held_loss"] > 0 else 0.0
    line = (f"adapted on {len(frames.train)} frames ({len(frames.held)} held back, {len(frames.skipped)} skipped) in "
            f"{minutes:.1f} min, {steps} steps: held-back loss {start['held_loss']:.4f} -> {best:.4f} ({change:+.0%}), "
            f"procedural median position error {start['procedural_median_error']:.4f} -> "
            f"{kept['procedural_median_error']:.4f}; " + (f"the weights of step {accepted} in {out}" if accepted else
                                                          f"no step beat the start: {out} holds the starting network"))
    log.info("%s", line)
    return {"line": line, "frames": len(frames.train), "held": len(frames.held), "skipped": dict(frames.skipped),
            "before": start, "after": kept, "accepted_step": accepted, "steps": steps, "minutes": minutes,
            "checkpoint": str(out)}
