"""Fixed-seed sets of scene files and their contact sheet (``mode=generate``)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from selfsup.scenes.dataset import protocol_specs, retain_freed_memory
from selfsup.scenes.degrade import Degradations, degrade
from selfsup.scenes.exact import RenderedScene, render_specs
from selfsup.scenes.io import write_scene
from selfsup.scenes.sampler import SamplerConfig, sample_scene

__all__ = ["generate_set", "contact_sheet", "to_rgb8"]

log = logging.getLogger(__name__)

_BATCH = 16  # scenes ray cast together (render_specs bounds the rays per call itself)


def to_rgb8(x: Tensor) -> np.ndarray:
    """``(H, W, 3)`` values in [0, 1] (clamped) as 8-bit RGB."""
    return (x.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()


def _panels(rendered: RenderedScene, inputs) -> list[np.ndarray]:
    scene = rendered.scene
    valid = (scene.depth > 0)[..., None]
    depth = inputs.depth
    near, far = depth[depth > 0].min(), depth.max()
    depth_vis = torch.where(depth > 0, 1 - (depth - near) / (far - near).clamp_min(1e-6), torch.zeros_like(depth))
    shadow = rendered.visibility.amin(-1) if rendered.visibility.shape[-1] else torch.ones_like(depth)
    return [
        to_rgb8(inputs.image ** (1 / 2.2)),
        to_rgb8(depth_vis[..., None].expand(-1, -1, 3)),
        to_rgb8((0.5 + 0.5 * scene.normals * torch.tensor([1.0, -1.0, -1.0])) * valid),
        to_rgb8(inputs.kd),
        to_rgb8((shadow * valid[..., 0])[..., None].expand(-1, -1, 3)),
    ]


def contact_sheet(rows: list[list[np.ndarray]], path: str | Path) -> None:
    """Write a PNG grid: one row per scene, columns image, depth, normals, albedo, shadow mask."""
    from skimage.io import imsave  # imported here: only this function writes pictures

    gap = 2
    height = max(p.shape[0] for row in rows for p in row)
    lines = []
    for row in rows:
        padded = [np.pad(p, ((0, height - p.shape[0] + gap), (0, gap), (0, 0)), constant_values=255) for p in row]
        lines.append(np.concatenate(padded, 1))
    width = max(line.shape[1] for line in lines)
    sheet = np.concatenate([np.pad(l, ((0, 0), (0, width - l.shape[1]), (0, 0)), constant_values=255) for l in lines], 0)
    imsave(str(path), sheet, check_contrast=False)


class _SetParts(Dataset):
    """Part ``i`` of a set: the scenes ``i * _BATCH ...`` rendered together, degraded and
    written; an item is ``(paths, contact sheet rows)`` of its scenes."""

    def __init__(self, out_dir: Path, total: int, seed: int, sampler: SamplerConfig, degradations: Degradations,
                 samples: int, specs: list | None, sheet_rows: int):
        self.out_dir, self.total, self.seed, self.sampler = out_dir, total, seed, sampler
        self.degradations, self.samples, self.specs, self.sheet_rows = degradations, samples, specs, sheet_rows

    def __len__(self) -> int:
        return -(-self.total // _BATCH)

    def __getitem__(self, part: int) -> tuple[list[Path], list[list[np.ndarray]]]:
        protocol = self.specs is not None
        indices = range(part * _BATCH, min((part + 1) * _BATCH, self.total))
        batch = [self.specs[i] if protocol else sample_scene(self.seed * 1_000_003 + i, self.sampler) for i in indices]
        paths, rows = [], []
        for index, spec, rendered in zip(indices, batch, render_specs(batch, samples=self.samples)):
            inputs = degrade(rendered.scene, self.degradations, spec.seed)
            inputs.meta["id"] = f"{'protocol' if protocol else 'procedural'}_{self.seed}_{index:05d}"
            path = self.out_dir / f"scene_{index:05d}.npz"
            write_scene(path, inputs)
            paths.append(path)
            if index < self.sheet_rows:
                rows.append(_panels(rendered, inputs))
        return paths, rows


def _as_is(item):
    return item


def _start_worker(worker_id: int) -> None:
    retain_freed_memory()  # a process of ours that only renders


def generate_set(out: str, count: int = 100, seed: int = 0, sampler: SamplerConfig | None = None,
                 degradations: Degradations | None = None, samples: int = 2, protocol: bool = False,
                 contact_sheet_rows: int = 6, workers: int = 0, sequence: str | None = None) -> list[Path]:
    """Write ``count`` scene files (or the 9 x 6 protocol set) into ``out``.

    ``sequence`` (a kind of :data:`selfsup.scenes.sequences.SEQUENCE_KINDS`): ``count``
    frames of one sequence instead, ``<out>/frame_<index>.npz`` (for ``mode=track``).

    Files are ``<out>/scene_<index>.npz`` in the format of ``docs/scene-format.md``
    with ground truth; the inputs carry the chosen degradations. With
    ``contact_sheet_rows > 0`` also writes ``<out>/contact_sheet.png``. ``workers``:
    processes that render and write parts of 16 scenes each (0: this process); the
    files are the same whatever the count.
    """
    sampler = sampler or SamplerConfig()
    degradations = degradations or Degradations()
    # Named here, before any directory or scene is made (not as a TypeError or a worker's traceback).
    for key, value, low, meaning in (("generate.count", count, 1, "scene files"),
                                     ("data.samples", samples, 1, "anti-aliasing samples per pixel side"),
                                     ("generate.contact_sheet_rows", contact_sheet_rows, 0, "rows"),
                                     ("generate.workers", workers, 0, "processes; 0: this one")):
        if (key != "generate.count" or not protocol) and (not isinstance(value, int) or isinstance(value, bool)
                                                         or value < low):
            raise ValueError(f"{key} must be an integer >= {low} ({meaning}), got {value!r}")
    out_dir = Path(out)
    if sequence is not None:
        from selfsup.scenes.sequences import render_sequence, write_sequence

        frames = render_sequence(sequence, seed, count, sampler, degradations, samples)
        paths = write_sequence(frames, out_dir)
        log.info("wrote a %s sequence of %d frames to %s", sequence, len(paths), out_dir)
        return paths
    out_dir.mkdir(parents=True, exist_ok=True)
    specs = protocol_specs(sampler, seed=seed + 7000) if protocol else None
    total = len(specs) if protocol else count
    parts = _SetParts(out_dir, total, seed, sampler, degradations, samples, specs, contact_sheet_rows)
    paths, rows = [], []
    # Batch None: each part comes back as it is, in order, from min(workers, parts) processes.
    for part_paths, part_rows in DataLoader(parts, batch_size=None, num_workers=min(workers, len(parts)),
                                            collate_fn=_as_is, worker_init_fn=_start_worker):
        paths.extend(part_paths)
        rows.extend(part_rows)
    if rows:
        contact_sheet(rows, out_dir / "contact_sheet.png")
    log.info("wrote %d scene files to %s", len(paths), out_dir)
    return paths
