"""Self-supervised training of the light networks (:class:`selfsup.model.LightNet`,
:class:`selfsup.network.IterativeLightNet`): loop, checkpoints, logging, DDP.

The loop is plain PyTorch. What it guarantees:

- **reproducible data**: procedural scenes are rendered into a pool
  (:func:`selfsup.scenes.dataset.materialise`) from seeds, refreshed with new
  seeds every ``refresh_epochs`` epochs; the order of epoch ``e`` is a
  permutation seeded by ``seed`` and ``e``. Step ``n`` therefore always sees the
  same batch, which is what makes resume exact;
- **checkpoints**: ``last.pt`` at every validation (model, optimiser, schedule,
  step, RNG states, the composed config) and ``best.pt`` when the validation
  median position error improves; ``resume=auto`` continues from ``last.pt``;
- **distributed**: launched by ``torchrun``, each process takes its share of
  every global batch and DDP averages the gradients (NCCL on GPUs, gloo on CPU);
  rank 0 validates, logs and writes checkpoints;
- **mixed precision** (bfloat16 autocast of the network) on CUDA when ``amp``;
  the renderer and the loss always run in float32;
- **the iterative network** (``model.architecture=iterative``) learns from
  :func:`selfsup.sequence_loss.sequence_loss`; its training pool carries each scene's
  re-render minimum (:func:`selfsup.sequence_loss.rerender_minimum`, found once per pool);
- **frames as captures**: with ``data.pool.render_scale > 1`` the pools are rendered at that
  many times their grid and handed to ``prepare_pool`` (``train.py`` gives the estimator's
  :func:`selfsup.estimation.prepare.prepared_pool`), which prepares them as a capture's
  frames and pools them to the grid;
- **logging**: TensorBoard scalars (loss terms, learning rate, scenes/s,
  validation metrics) and image grids (input, re-render, residual, shadow mask),
  and a progress bar.

Ground-truth lights are read only by validation and by the loss's ablation switch.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.distributed as dist
from torch import Tensor

from render import ShadowedBlinnPhong
from selfsup.checkpoint import build_network, load_checkpoint, save_network
from selfsup.evaluate import calibrate_confidence, calibrate_count_threshold, summarise
from selfsup.losses import LossOptions, TeacherOptions, reconstruction_loss, scene_batch, teacher_loss
from selfsup.model import LightNet, LightPrediction, scene_frame
from selfsup.network import IterativePrediction
from selfsup.sequence_loss import SequenceLossOptions, pool_minima, sequence_loss

__all__ = ["DataOptions", "OptimOptions", "TrainerOptions", "LoggerOptions", "Trainer", "render_grid"]

log = logging.getLogger(__name__)



@dataclass
class DataOptions:
    """Scene pools (mirrors ``data.pool``): counts, seeds, refresh period, render workers."""

    train_scenes: int = 1500
    val_scenes: int = 150
    train_seed: int = 1
    val_seed: int = 2
    refresh_epochs: int = 0  # 0: one pool for the whole run
    workers: int = 2
    albedo_share: float = 0.0  # share of training steps whose cost volumes see the scenes' albedo
    # The per-frame search as teacher (selfsup.teacher.PoolTeacher, which train.py builds from
    # these): on the first teacher_scenes of each training pool, rendered again at
    # teacher_scale x its grid and searched with teacher_method, cached under teacher_cache.
    teacher_scenes: int = 0
    teacher_scale: int = 2
    teacher_method: str = "refine"
    teacher_cache: str = "data/teacher"
    render_scale: int = 1  # > 1: pools rendered at this many times their grid, prepared as captures, pooled back

    def __post_init__(self):
        if not (isinstance(self.render_scale, int) and self.render_scale >= 1):
            raise ValueError(f"data.pool.render_scale must be an integer >= 1, got {self.render_scale!r}")
        if not 0 <= self.teacher_scenes <= self.train_scenes or self.teacher_scale < 1:
            raise ValueError(f"data.pool.teacher_scenes must be in [0, train_scenes={self.train_scenes}] and "
                             f"teacher_scale >= 1, got {self.teacher_scenes} and {self.teacher_scale}")
        if self.teacher_method not in ("refine", "cnn+refine"):
            raise ValueError(f"data.pool.teacher_method must be 'refine' or 'cnn+refine' (the search; 'cnn' would "
                             f"teach the network its own answers), got {self.teacher_method!r}")
        if not 0 <= self.albedo_share <= 1:
            raise ValueError(f"data.pool.albedo_share must be in [0, 1], got {self.albedo_share}")
        if self.train_scenes < 1 or self.val_scenes < 1:
            raise ValueError(f"train_scenes and val_scenes must be >= 1, got {self.train_scenes}, {self.val_scenes}")
        if self.refresh_epochs < 0 or self.workers < 0:
            raise ValueError("refresh_epochs and workers must be >= 0")


@dataclass
class OptimOptions:
    """AdamW with a one-cycle learning rate (mirrors the ``optim`` group)."""

    lr: float = 1e-3
    weight_decay: float = 1e-4
    betas: tuple[float, float] = (0.9, 0.999)
    warmup: float = 0.1  # share of the steps spent rising to lr
    grad_clip: float = 1.0  # 0: off

    def __post_init__(self):
        if not self.lr > 0 or not 0 <= self.warmup < 1 or self.grad_clip < 0 or self.weight_decay < 0:
            raise ValueError(f"bad optimiser options: {self}")


@dataclass
class TrainerOptions:
    """How long and where (mirrors the ``trainer`` group)."""

    max_steps: int = 900
    batch_size: int = 32  # global: split over the processes
    val_every: int = 100
    max_minutes: float = 0.0  # >0: stop (and checkpoint) after this wall time
    stop_step: int = 0  # >0: stop (and checkpoint) at this step, the schedule still max_steps' (a run reproduced to a step)
    amp: bool = True  # bfloat16 autocast of the network, CUDA only
    device: str = "auto"  # auto | cpu | cuda
    out_dir: str = "runs/default"
    resume: str = "auto"  # auto (last.pt of out_dir if any) | never | a checkpoint path
    init: str | None = None  # a fresh run's starting weights (a LightNet checkpoint); its own optimiser and schedule
    progress: bool = True
    threads: int = 0  # >0: torch.set_num_threads on CPU

    def __post_init__(self):
        if self.max_steps < 1 or self.batch_size < 1 or self.val_every < 1:
            raise ValueError(f"max_steps, batch_size and val_every must be >= 1: {self}")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"device must be auto, cpu or cuda, got {self.device!r}")
        if self.stop_step < 0:
            raise ValueError(f"trainer.stop_step must be >= 0 (0: none), got {self.stop_step}")
        if not self.max_minutes >= 0 or self.threads < 0:  # -3 minutes read as no cap, silently
            raise ValueError(f"trainer.max_minutes must be >= 0 (0: no cap) and trainer.threads >= 0 (0: torch's "
                             f"default), got {self.max_minutes} and {self.threads}")


@dataclass
class LoggerOptions:
    """TensorBoard (mirrors the ``logger`` group)."""

    tensorboard: bool = True
    log_every: int = 10
    image_every: int = 1  # image grids every n-th validation; 0: never
    images: int = 4

    def __post_init__(self):
        if self.log_every < 1 or self.image_every < 0 or self.images < 1:  # log_every=0 died in step % 0
            raise ValueError(f"logger.log_every and logger.images must be >= 1 and logger.image_every >= 0 (0: never), "
                             f"got {self.log_every}, {self.images} and {self.image_every}")


@dataclass
class _Dist:
    rank: int = 0
    world: int = 1
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @property
    def main(self) -> bool:
        return self.rank == 0


def taught_minima(pool: dict[str, Tensor]) -> dict[str, Tensor]:
    """The iterative network's targets where the per-frame search taught the pool: on each scene
    where the search found lights (``teacher_mask`` ``(N, K)``, brightest first), its lights and
    their count take the re-render minimum's place (``target_pos (N, K, 3)``, ``target_needed
    (N, K)``); elsewhere the minimum stays. On 180 two-light training rooms of
    ``experiment=iterative`` the search put a second light within 0.05 of a true second lamp in
    39, the minimum in 29 (docs/decisions.md, 2026-12-08)."""
    found = pool["teacher_mask"].any(1)
    K = pool["target_pos"].shape[1]
    taught_pos, taught_mask = pool["teacher_pos"][:, :K], pool["teacher_mask"][:, :K]
    # A slot the search left empty keeps the minimum's place (not needed), never the origin.
    taught_pos = torch.where(taught_mask[..., None], taught_pos, pool["target_pos"])
    return {"target_pos": torch.where(found[:, None, None], taught_pos, pool["target_pos"]),
            "target_needed": torch.where(found[:, None], taught_mask, pool["target_needed"])}


def _setup_distributed(device: str) -> _Dist:
    use_cuda = device == "cuda" or (device == "auto" and torch.cuda.is_available())
    if device == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("trainer.device=cuda but no CUDA device is available")
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return _Dist(device=torch.device("cuda" if use_cuda else "cpu"))
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if not dist.is_initialized():
        dist.init_process_group("nccl" if use_cuda else "gloo")
    if use_cuda:
        torch.cuda.set_device(local)
    return _Dist(rank=dist.get_rank(), world=dist.get_world_size(),
                 device=torch.device(f"cuda:{local}" if use_cuda else "cpu"))


def _float32(prediction: LightPrediction) -> LightPrediction:
    return dataclasses.replace(prediction, **{f.name: getattr(prediction, f.name).float() for f in dataclasses.fields(prediction)
                                              if isinstance(getattr(prediction, f.name), Tensor)})


def _display(image: Tensor, exposure: Tensor) -> Tensor:
    # (B, 3, H, W) linear -> [0, 1] gamma-encoded for the image grid.
    return (image / exposure[:, None, None, None]).clamp(0, 1) ** (1 / 2.2)


class Trainer:
    """Trains a :class:`LightNet` on procedural scenes; see the module doc.

    Args:
        model_config: keyword arguments of the network (:func:`selfsup.checkpoint.build_network`).
        sampler, degradations, samples: procedural scene options (the ``data`` group).
        pool: :class:`DataOptions`; optim: :class:`OptimOptions`; trainer:
        :class:`TrainerOptions`; logger: :class:`LoggerOptions`; loss: :class:`LossOptions`.
        teacher: the weights of the teacher's terms on the pool scenes it searched
            (:class:`selfsup.losses.TeacherOptions`; read where ``pool.teacher_scenes > 0``).
        teacher_search: ``base_seed -> (position (n, K, 3), mask (n, K))``, the teacher's
            lights on a pool's first ``n = pool.teacher_scenes`` scenes
            (:class:`selfsup.teacher.PoolTeacher`); needed where ``pool.teacher_scenes > 0``.
        renderer: the shadowed renderer the loss re-renders with.
        prepare_pool: ``(pool, long_side) -> pool``, the frames of a pool rendered at
            ``pool.render_scale`` prepared as captures and pooled to the grid (needed where
            ``render_scale > 1``).
        seed: initialisation and data order.
        config: the composed config, stored in checkpoints for the record.
    """

    def __init__(self, model_config: dict, sampler, degradations, samples: int, pool: DataOptions,
                 optim: OptimOptions, trainer: TrainerOptions, logger: LoggerOptions, loss: LossOptions,
                 renderer: ShadowedBlinnPhong, seed: int = 0, config: dict | None = None,
                 teacher: TeacherOptions | None = None, teacher_search=None, prepare_pool=None):
        self.model_config = dict(model_config)
        with torch.device("meta"):  # a bad model setting is named now, before any scene is rendered (no weights made)
            self.iterative = not isinstance(build_network(self.model_config), LightNet)
        if self.iterative != isinstance(loss, SequenceLossOptions):
            raise ValueError("the iterative network (model.architecture=iterative) learns from the sequence loss's "
                             "options (selfsup.sequence_loss.SequenceLossOptions) and LightNet from LossOptions: the "
                             "experiment's loss node does not fit the model")
        if pool.render_scale > 1 and prepare_pool is None:
            raise ValueError("data.pool.render_scale > 1 needs prepare_pool (train.py gives the estimator's)")
        self.prepare_pool = prepare_pool
        self.sampler, self.degradations, self.samples = sampler, degradations, samples
        self.pool_options, self.optim, self.options, self.logger, self.loss = pool, optim, trainer, logger, loss
        self.renderer = renderer
        self.teacher = teacher or TeacherOptions()
        if pool.teacher_scenes and teacher_search is None:
            raise ValueError("data.pool.teacher_scenes > 0 needs a teacher_search (selfsup.teacher.PoolTeacher; "
                             "train.py builds it)")
        self.teacher_search = teacher_search
        self.seed = seed
        self.config = config or {}
        self.out_dir = Path(trainer.out_dir)
        self._pools: dict[int, dict[str, Tensor]] = {}

    # -- data ---------------------------------------------------------------
    def _pool(self, generation: int, which: str) -> dict[str, Tensor]:
        from selfsup.scenes.dataset import ProceduralScenes, materialise

        key = -1 if which == "val" else generation
        if key not in self._pools:
            if which == "train":
                self._pools = {k: v for k, v in self._pools.items() if k == -1}  # keep one train pool in memory
            count = self.pool_options.val_scenes if which == "val" else self.pool_options.train_scenes
            base = self.pool_options.val_seed if which == "val" else self.pool_options.train_seed + 1000 * generation
            scale = self.pool_options.render_scale
            sampler = dataclasses.replace(self.sampler, height=self.sampler.height * scale, width=self.sampler.width * scale)
            dataset = ProceduralScenes(sampler, self.degradations, length=count, base_seed=base,
                                       samples=self.samples,
                                       max_lights=max(self.model_config.get("max_lights", 2), len(sampler.n_lights_probs)))
            started = time.perf_counter()
            self._pools[key] = materialise(dataset, workers=self.pool_options.workers, progress=self.options.progress)
            if scale > 1:
                self._pools[key] = self.prepare_pool(self._pools[key], max(self.sampler.height, self.sampler.width))
            log.info("rendered %d %s scenes in %.1f s", count, which, time.perf_counter() - started)
            if which == "train" and self.iterative:
                self._pools[key].update(self._minima(self._pools[key]))
            if which == "train" and self.pool_options.teacher_scenes:
                self._pools[key].update(self._taught(base, count))
                if self.iterative:
                    self._pools[key].update(taught_minima(self._pools[key]))
        return self._pools[key]

    def _minima(self, pool: dict[str, Tensor]) -> dict[str, Tensor]:
        """Each training scene's re-render minimum (:func:`selfsup.sequence_loss.pool_minima`), found once."""
        started = time.perf_counter()
        minima = pool_minima(pool, self.model_config.get("max_lights", 2), self.loss)
        log.info("re-render minima of %d scenes in %.1f s", pool["image"].shape[0], time.perf_counter() - started)
        return minima

    def _taught(self, base_seed: int, count: int) -> dict[str, Tensor]:
        """``teacher_pos (count, K, 3)`` and ``teacher_mask (count, K)`` of a training pool:
        the search's lights on its first ``teacher_scenes`` scenes, none after them."""
        position, mask = self.teacher_search(base_seed)
        padded = torch.zeros(count, *position.shape[1:]), torch.zeros(count, *mask.shape[1:], dtype=torch.bool)
        padded[0][:len(position)], padded[1][:len(mask)] = position, mask
        return {"teacher_pos": padded[0], "teacher_mask": padded[1]}

    def _steps_per_epoch(self) -> int:
        return max(1, self.pool_options.train_scenes // self.options.batch_size)

    def batch_indices(self, step: int, rank: int = 0, world: int = 1) -> tuple[int, Tensor]:
        """``(pool generation, indices of this process's share)`` of global step ``step``."""
        per_epoch = self._steps_per_epoch()
        epoch, within = divmod(step, per_epoch)
        refresh = self.pool_options.refresh_epochs
        generation = epoch // refresh if refresh else 0
        order = torch.randperm(self.pool_options.train_scenes,
                               generator=torch.Generator().manual_seed(self.seed * 100_003 + epoch))
        batch = order[within * self.options.batch_size:(within + 1) * self.options.batch_size]
        return generation, batch[rank::world]

    # -- checkpoints ------------------------------------------------------------
    def _checkpoint_extra(self, optimiser, schedule, step: int, best: float) -> dict:
        rng = {"torch": torch.get_rng_state()}
        if torch.cuda.is_available():
            rng["cuda"] = torch.cuda.get_rng_state_all()
        return {"optimizer": optimiser.state_dict(), "scheduler": schedule.state_dict(), "step": step,
                "best": best, "rng": rng, "config": self.config}

    def _resume_path(self) -> Path | None:
        resume = self.options.resume
        if resume == "never":
            return None
        if resume == "auto":
            path = self.out_dir / "last.pt"
            return path if path.is_file() else None
        path = Path(resume)
        if not path.is_file():
            raise FileNotFoundError(f"trainer.resume: no checkpoint at {path}")
        return path

    # -- the loop -----------------------------------------------------------------
    def _loss(self, prediction: LightPrediction, scenes, renderer, batch: dict[str, Tensor]):
        """``(terms, total, teacher parts)`` of one batch: the reconstruction loss, plus the
        teacher's terms where the batch holds frames the search taught."""
        if isinstance(prediction, IterativePrediction):
            terms = sequence_loss(prediction, scenes, renderer, batch["target_pos"], batch["target_needed"], self.loss)
            return terms, terms.total, {}
        terms = reconstruction_loss(prediction, scenes, renderer, self.loss, batch)
        if "teacher_mask" not in batch:
            return terms, terms.total, {}
        size = scene_frame(scenes.image, scenes.gbuffer).size
        teaching, taught = teacher_loss(prediction, batch["teacher_pos"], batch["teacher_mask"], size, self.teacher)
        return terms, terms.total + teaching, taught

    def _search_once(self, ctx: _Dist, step: int) -> None:
        # Under DDP with a teacher, rank 0 searches (and caches) the pool; the others read the cache.
        if self.pool_options.teacher_scenes and ctx.world > 1:
            if ctx.main:
                self._pool(self.batch_indices(step)[0], "train")
            dist.barrier()

    def fit(self) -> dict:
        """Train to ``max_steps`` (or ``max_minutes``); returns the final validation summary,
        the step reached and the checkpoint paths."""
        from tqdm import tqdm

        ctx = _setup_distributed(self.options.device)
        if self.options.threads > 0 and ctx.device.type == "cpu":
            torch.set_num_threads(self.options.threads)
        if self.options.batch_size < ctx.world:
            raise ValueError(f"batch_size {self.options.batch_size} is smaller than the {ctx.world} processes")
        torch.manual_seed(self.seed)
        network = build_network(self.model_config).to(ctx.device)
        model = network
        if ctx.world > 1:
            model = torch.nn.parallel.DistributedDataParallel(network, device_ids=[ctx.device.index] if ctx.device.type == "cuda" else None)
        optimiser = torch.optim.AdamW(network.parameters(), lr=self.optim.lr, betas=tuple(self.optim.betas),
                                      weight_decay=self.optim.weight_decay)
        schedule = torch.optim.lr_scheduler.OneCycleLR(optimiser, self.optim.lr, total_steps=self.options.max_steps,
                                                       pct_start=max(self.optim.warmup, 1e-3))
        step, best = self._resume(network, optimiser, schedule, ctx)
        renderer = self.renderer.to(ctx.device)
        writer = None
        if ctx.main and self.logger.tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            writer = SummaryWriter(str(self.out_dir / "tensorboard"), purge_step=step)
        val_pool = self._pool(0, "val") if ctx.main else None
        self._search_once(ctx, step)
        amp = self.options.amp and ctx.device.type == "cuda"
        started = time.perf_counter()
        window_start, window_scenes = started, 0
        summary, stop, at_stop_step = {}, False, False
        bar = tqdm(total=self.options.max_steps, initial=step, disable=not (ctx.main and self.options.progress),
                   desc="train", unit="step")
        try:
            while step < self.options.max_steps and not stop:
                generation, indices = self.batch_indices(step, ctx.rank, ctx.world)
                pool = self._pool(generation, "train")
                batch = {key: value[indices].to(ctx.device, non_blocking=True) for key, value in pool.items()}
                scenes = scene_batch(batch)
                # The network needs no albedo; a share of the steps lets its cost volumes see the
                # true one, as a caller with a scene file's albedo may (the step decides: resume stays exact).
                albedo = self.pool_options.albedo_share > 0 and float(torch.rand(
                    (), generator=torch.Generator().manual_seed(self.seed * 7919 + step))) < self.pool_options.albedo_share
                with torch.autocast(ctx.device.type, dtype=torch.bfloat16, enabled=amp):
                    prediction = model(scenes.image, scenes.gbuffer, scenes.material.kd if albedo else None)
                terms, total, taught = self._loss(_float32(prediction), scenes, renderer, batch)
                if not torch.isfinite(total):
                    raise FloatingPointError(f"non-finite loss at step {step}: {total.item()}")
                optimiser.zero_grad(set_to_none=True)
                total.backward()
                if self.optim.grad_clip > 0:
                    torch.nn.utils.clip_grad_norm_(network.parameters(), self.optim.grad_clip)
                optimiser.step()
                schedule.step()
                step += 1
                window_scenes += int(indices.numel()) * ctx.world
                bar.update(1)
                if writer is not None and (step % self.logger.log_every == 0 or step == 1):
                    now = time.perf_counter()
                    _log_terms(writer, terms, schedule.get_last_lr()[0], window_scenes / max(now - window_start, 1e-9),
                               step)
                    for name, value in taught.items():
                        writer.add_scalar(f"loss/{name}", value, step)
                    window_start, window_scenes = now, 0
                    bar.set_postfix(loss=f"{float(total.detach()):.4f}")
                if self.options.max_minutes > 0:
                    stop = self._agree((time.perf_counter() - started) / 60 > self.options.max_minutes, ctx)
                at_stop_step = bool(self.options.stop_step) and step >= self.options.stop_step
                stop = stop or at_stop_step  # every process reaches the same step
                if step % self.options.val_every == 0 or step == self.options.max_steps or stop:
                    if ctx.main:
                        summary = self._validate(network, val_pool, renderer, writer, step)
                        improved = summary["median_position_error"] < best
                        best = min(best, summary["median_position_error"])
                        extra = self._checkpoint_extra(optimiser, schedule, step, best)
                        save_network(self.out_dir / "last.pt", network, self.model_config, summary, extra)
                        if improved:
                            save_network(self.out_dir / "best.pt", network, self.model_config, summary, extra)
                        bar.write(f"step {step}: " + ", ".join(f"{k} {v:.4g}" for k, v in summary.items()))
                    if ctx.world > 1:
                        dist.barrier()
        finally:
            bar.close()
            if writer is not None:
                writer.close()
        if stop and ctx.main:
            reason = f"trainer.stop_step={self.options.stop_step}" if at_stop_step else f"trainer.max_minutes={self.options.max_minutes}"
            log.warning("stopped at step %d of %d: %s reached", step, self.options.max_steps, reason)
        result = {"step": step, "minutes": (time.perf_counter() - started) / 60, "validation": summary,
                  "last": str(self.out_dir / "last.pt"), "best": str(self.out_dir / "best.pt"),
                  "max_steps": self.options.max_steps, "max_minutes": self.options.max_minutes,
                  "stopped_by_time": bool(stop) and not at_stop_step,
                  "stop_step": self.options.stop_step}
        if ctx.main:
            (self.out_dir / "result.json").write_text(json.dumps(result, indent=2))
        return result

    def _resume(self, network: torch.nn.Module, optimiser: torch.optim.Optimizer,
                schedule: torch.optim.lr_scheduler.LRScheduler, ctx: _Dist) -> tuple[int, float]:
        """The step and best validation error to go on from: a checkpoint's (its weights,
        optimiser, schedule and random state restored), or a fresh start's (0, inf)."""
        resume = self._resume_path()
        if resume is None:
            if self.options.init:  # fine-tuning: the weights only, of the model config's shapes
                state = load_checkpoint(self.options.init, map_location=ctx.device)
                if not isinstance(state, dict) or "model" not in state:
                    raise ValueError(f"trainer.init={self.options.init} is not a LightNet checkpoint (no 'model')")
                try:
                    network.load_state_dict(state["model"])
                except RuntimeError as error:
                    reason = next((line.strip() for line in str(error).splitlines()[1:] if line.strip()), str(error))
                    raise ValueError(f"trainer.init={self.options.init}: its weights do not fit model "
                                     f"{self.model_config} ({reason})") from None
                if ctx.main:
                    log.info("started from the weights of %s", self.options.init)
            return 0, math.inf
        state = load_checkpoint(resume, map_location=ctx.device)
        network.load_state_dict(state["model"])
        optimiser.load_state_dict(state["optimizer"])
        schedule.load_state_dict(state["scheduler"])
        torch.set_rng_state(state["rng"]["torch"].cpu())
        if "cuda" in state["rng"] and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(state["rng"]["cuda"])
        if ctx.main:
            log.info("resumed from %s at step %d", resume, int(state["step"]))
        return int(state["step"]), float(state["best"])

    @staticmethod
    def _agree(flag: bool, ctx: _Dist) -> bool:
        # Every process must stop at the same step, or DDP would wait forever.
        if ctx.world == 1:
            return flag
        value = torch.tensor([float(flag)], device=ctx.device)
        dist.all_reduce(value, op=dist.ReduceOp.MAX)
        return bool(value.item() > 0)

    def _validate(self, network: torch.nn.Module, pool: dict[str, Tensor], renderer, writer, step: int) -> dict:
        # The count's threshold, calibrated on the validation scenes, goes with the checkpoint.
        network.count_threshold, rows = calibrate_count_threshold(network, pool)
        self.model_config["count_threshold"] = network.count_threshold
        summary = summarise(rows)
        summary["count_threshold"] = network.count_threshold
        if self.iterative:  # the confidence's logistic model, fitted on the same scenes, goes with the checkpoint
            network.confidence_weights, placed = calibrate_confidence(network, pool)
            self.model_config["confidence_weights"] = list(network.confidence_weights)
            summary["slot0_placed"] = placed
        if writer is not None:
            for name, value in summary.items():
                writer.add_scalar(f"val/{name}", value, step)
            every = self.logger.image_every
            if every and (step // self.options.val_every) % every == 0:
                writer.add_image("val/input|render|residual|shadow", self._grid(network, pool, renderer), step)
        return summary

    @torch.no_grad()
    def _grid(self, network: torch.nn.Module, pool: dict[str, Tensor], renderer) -> Tensor:
        """``(3, n H, 4 W)``: per scene, input, re-render, |residual| and slot 0's shadow mask."""
        device = next(network.parameters()).device
        batch = {key: value[: self.logger.images].to(device) for key, value in pool.items()}
        scenes = scene_batch(batch)
        network.eval()
        prediction = network(scenes.image, scenes.gbuffer)
        network.train()
        if isinstance(prediction, IterativePrediction):
            return render_grid(scenes.image, *_final_render(prediction, scenes, renderer),
                               scene_frame(scenes.image, scenes.gbuffer).exposure)
        terms = reconstruction_loss(prediction, scenes, renderer, self.loss, batch)
        return render_grid(scenes.image, terms.render, terms.visibility, scene_frame(scenes.image, scenes.gbuffer).exposure)


def _final_render(prediction: IterativePrediction, scenes, renderer) -> tuple[Tensor, Tensor]:
    # The last step's counted lights re-rendered with the scene's albedo: (render, visibility).
    from selfsup.sequence_loss import _robust_fit

    counted = (torch.arange(prediction.position.shape[1]) < prediction.count[:, None]).to(scenes.image.dtype)
    transport = renderer.transport(scenes.gbuffer, scenes.material, prediction.position)
    _, model, _ = _robust_fit(scenes, transport, counted, 0.05, prediction.grid.frame.exposure)
    visibility = transport.visibility if transport.visibility is not None else torch.ones_like(transport.diffuse)
    return model, visibility


def render_grid(image: Tensor, render: Tensor, visibility: Tensor, exposure: Tensor) -> Tensor:
    """``(3, n H, 4 W)`` for TensorBoard: per image ``(n, 3, H, W)``, the input, its re-render
    ``render``, 4 x the |residual| (each divided by ``exposure (n,)``, gamma-encoded) and
    slot 0's shadow mask of ``visibility (n, K, H, W)``."""
    shadow = visibility[:, :1].expand(-1, 3, -1, -1)
    tiles = [_display(image, exposure), _display(render, exposure), _display((render - image).abs() * 4, exposure),
             shadow.clamp(0, 1)]
    rows = torch.cat(tiles, 3)  # (n, 3, H, 4W)
    return rows.permute(1, 0, 2, 3).reshape(3, -1, rows.shape[-1]).cpu()


def _log_terms(writer, terms, lr: float, scenes_per_second: float, step: int) -> None:
    """One training step's loss terms, needed lights, learning rate and speed to TensorBoard."""
    for name in ("total", "photometric", "hypotheses", "presence", "intensity", "supervised", "count", "position",
                 "votes"):
        if hasattr(terms, name):
            writer.add_scalar(f"train/{name}", float(getattr(terms, name).detach()), step)
    if hasattr(terms, "needed"):
        writer.add_scalar("train/needed_lights", float(terms.needed.float().sum(1).mean()), step)
    writer.add_scalar("train/lr", lr, step)
    writer.add_scalar("train/scenes_per_second", scenes_per_second, step)
