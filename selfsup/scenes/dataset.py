"""Procedural scenes as torch datasets and as fixed-seed sets of scene files.

- :class:`ProceduralScenes`: an on-the-fly map-style dataset. Item ``i`` is drawn
  from seed ``base_seed * 1_000_003 + i`` alone, so any worker, in any order,
  returns the same item (worker-safe, reproducible).
- :func:`protocol_specs`: the paper's protocol set, 9 scenes x 6 light positions
  spread around each scene.
- :func:`scene_to_item` / :func:`collate`: one scene as a dict of tensors, lights
  padded to a fixed count with a mask, so that batches stack.
"""

from __future__ import annotations

import ctypes
import dataclasses
import os

import torch
from torch import Tensor
from torch.utils.data import Dataset, default_collate, get_worker_info

from selfsup.scenes.degrade import Degradations, degrade
from selfsup.scenes.exact import RenderedScene, render_specs
from selfsup.scenes.io import Scene
from selfsup.scenes.sampler import SamplerConfig, SceneSpec, sample_scene
from selfsup.scenes.studio import scene_spec

__all__ = ["ProceduralScenes", "sampler_config", "scene_to_item", "area_truth", "collate", "materialise", "protocol_specs",
           "PROTOCOL_LIGHTS", "render_item", "render_items", "retain_freed_memory"]

# Room-normalised light positions (x across, y up, z into the room, in [0, 1]) of the
# protocol set: front/back x left/right high, and two in the middle at two heights.
PROTOCOL_LIGHTS = torch.tensor([
    [0.1, 0.9, 0.15], [0.9, 0.9, 0.15], [0.1, 0.8, 0.85], [0.9, 0.8, 0.85], [0.5, 0.95, 0.5], [0.55, 0.45, 0.35],
])


def protocol_specs(config: SamplerConfig, seed: int = 7000, scenes: int = 9) -> list[SceneSpec]:
    """``scenes`` fixed scenes x 6 light positions (:data:`PROTOCOL_LIGHTS`), one light each.

    A light position that would fall inside an object moves up or towards the
    room centre until it is clear (the scene is resampled if none is).
    """
    specs = []
    scene_seed = seed
    while len(specs) < scenes * len(PROTOCOL_LIGHTS):
        batch = []
        for light in PROTOCOL_LIGHTS:
            for shrink in (0.0, 0.15, 0.3, 0.45):
                moved = light + shrink * (torch.tensor([0.5, 1.0, 0.5]) - light)
                try:
                    batch.append(sample_scene(scene_seed, config, n_lights=1, light_position_world=moved[None]))
                    break
                except ValueError:
                    continue
        if len(batch) == len(PROTOCOL_LIGHTS):
            for index, spec in enumerate(batch):
                spec.seed = scene_seed * 10 + index
                spec.meta["protocol"] = {"scene_seed": scene_seed, "light_index": index}
            specs.extend(batch)
        scene_seed += 1
    return specs


def scene_to_item(scene: Scene, max_lights: int) -> dict[str, Tensor]:
    """One scene as tensors (no batch axis); lights padded to ``max_lights``.

    Keys: ``image (H, W, 3)``, ``depth (H, W)``, ``K (3, 3)``, ``kd (H, W, 3)``,
    ``ks (H, W, 1)``, ``shininess (H, W)``, ``normals (H, W, 3)`` (zeros when
    unknown), ``ambient (3,)`` with ``ambient_known ()``, ``light_pos (max_lights, 3)``,
    ``light_intensity (max_lights, 3)``, ``light_mask (max_lights,)``, ``scene_scale ()``.
    """
    H, W = scene.depth.shape
    n = 0 if scene.light_pos is None else scene.light_pos.shape[0]
    if n > max_lights:
        raise ValueError(f"scene {scene.id} has {n} lights, more than max_lights={max_lights}")
    light_pos = torch.zeros(max_lights, 3)
    light_intensity = torch.zeros(max_lights, 3)
    if n:
        light_pos[:n], light_intensity[:n] = scene.light_pos, scene.light_intensity
    shininess = scene.shininess if scene.shininess.dim() == 2 else scene.shininess.expand(H, W)
    ks = torch.zeros(H, W, 1) if scene.ks is None else scene.ks
    return {
        "image": scene.image, "depth": scene.depth, "K": scene.K, "kd": scene.kd,
        "ks": ks, "shininess": shininess,
        "normals": torch.zeros(H, W, 3) if scene.normals is None else scene.normals,
        "ambient": torch.zeros(3) if scene.ambient is None else scene.ambient,
        "ambient_known": torch.tensor(scene.ambient is not None),
        "light_pos": light_pos, "light_intensity": light_intensity,
        "light_mask": torch.arange(max_lights) < n,
        "scene_scale": torch.tensor(0.0) if scene.scene_scale is None else scene.scene_scale,
    }


def collate(items: list[dict[str, Tensor]]) -> dict[str, Tensor]:
    """Stack items (all of one resolution) along a new batch axis: ``{key: (N, ...)}``.

    torch's ``default_collate`` does the stacking: inside a DataLoader worker it
    stacks straight into shared memory, so handing the batch (25 MB at 32 scenes
    of 128x128) to the main process copies nothing more in the worker.
    """
    return default_collate(items)


def render_item(seed: int, sampler: SamplerConfig, degradations: Degradations, samples: int) -> tuple[RenderedScene, Scene]:
    """Sample, render and degrade one scene: ``(exact render, degraded inputs)``."""
    return render_items([seed], sampler, degradations, samples)[0]


def render_items(seeds: list[int], sampler: SamplerConfig, degradations: Degradations,
                 samples: int) -> list[tuple[RenderedScene, Scene]]:
    """:func:`render_item` of each seed, ray cast together: the same results, several
    times faster per scene (see :func:`selfsup.scenes.exact.render_specs`). Each seed's scene is
    :func:`selfsup.scenes.studio.scene_spec`'s: a room, or an object in the dark where
    ``sampler.studio_prob`` draws one. Rooms lit by panels (``sampler.panel_prob``: 16 points
    a light) are cast apart from the others, whose lights would be padded to theirs."""
    specs = [scene_spec(seed, sampler) for seed in seeds]
    rendered: list[RenderedScene | None] = [None] * len(specs)
    for area in (False, True):
        rows = [i for i, spec in enumerate(specs) if ("area_lights" in spec.meta) == area]
        for i, r in zip(rows, render_specs([specs[i] for i in rows], samples=samples)):
            rendered[i] = r
    return [(r, area_truth(degrade(r.scene, degradations, seed, r.visibility))) for r, seed in zip(rendered, seeds)]


def area_truth(scene: Scene) -> Scene:
    """``scene`` with its area lights (``meta["area_lights"]["centres"]``: the ceiling panels
    of :func:`selfsup.scenes.studio.scene_spec`) reported as one light each: at its centre,
    its points' intensities summed. Rendered (and degraded) first: the image is the panels'."""
    area = scene.meta.get("area_lights") or {}
    if "centres" not in area or scene.light_pos is None:
        return scene
    centres = torch.tensor(area["centres"], dtype=scene.light_pos.dtype)
    intensity = scene.light_intensity.reshape(len(centres), -1, scene.light_intensity.shape[-1]).sum(1)
    return dataclasses.replace(scene, light_pos=centres, light_intensity=intensity)


# glibc's mallopt(3) parameter M_TOP_PAD: how much free memory at the top of the heap
# malloc keeps when it trims, and adds when it grows.
_M_TOP_PAD = -2
_RETAINED_BYTES = 256 * 2**20
_retaining = {"pid": None}


def retain_freed_memory(nbytes: int = _RETAINED_BYTES) -> bool:
    """Let this process keep up to ``nbytes`` of freed heap (glibc's ``M_TOP_PAD``)
    instead of handing it back to the system at every large free.

    Ray casting a batch allocates and frees arrays of megabytes by the hundred. By
    default glibc returns the heap's freed top at once, and the next arrays pay for
    their pages again (a page fault on each first touch): 7% of the generator's
    time through a 2-worker DataLoader at 32 scenes of 128x128 on the 2-core CPU,
    6-15% in one process, the peak memory unchanged.
    :class:`ProceduralScenes` calls this in DataLoader workers (processes that only
    render), and ``train.py`` for its own process; a library call changes nothing
    else of the caller's process. Returns whether it took effect (False without glibc).
    """
    if _retaining["pid"] == os.getpid():
        return True
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError, TypeError):  # not glibc (macOS, Windows)
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    if not mallopt(_M_TOP_PAD, int(nbytes)):
        return False
    _retaining["pid"] = os.getpid()
    return True


class ProceduralScenes(Dataset):
    """On-the-fly procedural scenes (map-style, ``length`` items).

    Args:
        sampler: scene distributions; its height/width fix the resolution.
        degradations: applied to the inputs, never to the ground truth.
        length: number of items.
        base_seed: item ``i`` uses seed ``base_seed * 1_000_003 + i``.
        samples: anti-aliasing samples per pixel side.
        max_lights: lights are padded to this count.
    """

    def __init__(self, sampler: SamplerConfig, degradations: Degradations | None = None, length: int = 1000,
                 base_seed: int = 0, samples: int = 2, max_lights: int | None = None):
        if length < 1:
            raise ValueError(f"length must be >= 1, got {length}")
        if samples < 1:  # named here, not in the first worker that renders
            raise ValueError(f"samples must be >= 1 (anti-aliasing samples per pixel side), got {samples}")
        self.sampler = sampler
        self.degradations = degradations or Degradations()
        self.length = length
        self.base_seed = base_seed
        self.samples = samples
        self.max_lights = max_lights or len(sampler.n_lights_probs)

    def __len__(self) -> int:
        return self.length

    def seed_of(self, index: int) -> int:
        return self.base_seed * 1_000_003 + index

    def __getitem__(self, index: int) -> dict[str, Tensor]:
        return self.__getitems__([index])[0]

    def __getitems__(self, indices: list[int]) -> list[dict[str, Tensor]]:
        """Items ``indices``, rendered together (a DataLoader fetches its batches so)."""
        for index in indices:
            if not 0 <= index < self.length:
                raise IndexError(f"index {index} out of range for {self.length} scenes")
        if get_worker_info() is not None:  # a DataLoader worker: a process of ours
            retain_freed_memory()
        rendered = render_items([self.seed_of(i) for i in indices], self.sampler, self.degradations, self.samples)
        return [scene_to_item(scene, self.max_lights) for _, scene in rendered]


def sampler_config(**kwargs) -> SamplerConfig:
    """:class:`SamplerConfig` from plain config values (lists become tuples)."""
    fields = {f.name for f in dataclasses.fields(SamplerConfig)}
    unknown = set(kwargs) - fields
    if unknown:
        raise ValueError(f"unknown sampler option(s) {sorted(unknown)}; known: {sorted(fields)}")
    return SamplerConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in kwargs.items()})


def materialise(dataset: Dataset, workers: int = 0, batch_size: int = 32, progress: bool = False) -> dict[str, Tensor]:
    """Every item of ``dataset`` rendered once and stacked: ``{key: (N, ...)}``.

    Training reuses a pool of procedural scenes for several epochs instead of
    ray casting each one again; ``workers`` processes render in parallel.
    """
    from torch.utils.data import DataLoader
    from tqdm import tqdm

    loader = DataLoader(dataset, batch_size=batch_size, num_workers=workers, collate_fn=collate)
    parts = [batch for batch in tqdm(loader, desc="rendering scenes", disable=not progress, unit="batch")]
    return {key: torch.cat([part[key] for part in parts]) for key in parts[0]}
