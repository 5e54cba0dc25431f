"""Ground-truth accuracy and speed of the light-estimation CNN alone (``mode=eval``).

Targets (issue 4), on the fixed-seed procedural test set with true reflectance:
median position error <= 0.05 of the scene size, median angular error <= 5
degrees; inference <= 5 ms per 128x128 image at batch 16 on the 2-core CPU
(issue 62: <= 10 ms per 160x120 image at batch 1, no albedo). The degraded sets
(reflectance noise m, sensor depth noise), the capture-like sets (a drawn camera,
indirect light: the network sees no albedo there, as with a capture) and directories
of scene files (e.g. the Mitsuba devset) are reported as measured. Where a set's
scenes give their albedo (every set but the camera's, and scene files), the network's
cost volumes see it, as ``mode=estimate`` lets them for a scene file.

    python train.py mode=eval                      # the shipped checkpoint
    python train.py mode=eval eval.checkpoint=outputs/.../best.pt eval.scenes=50

Results: benchmarks/results/cnn_eval_<device>_<date>.{md,json}.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import torch

from benchmarks.common import timed, write_results
from render.shadows import ShadowMethod
from selfsup.checkpoint import load_network
from selfsup.estimation.prepare import prepared_pool
from selfsup.evaluate import evaluate_network, summarise
from selfsup.losses import scene_batch
from selfsup.network import IterativeLightNet
from selfsup.scenes.dataset import ProceduralScenes, collate, materialise, sampler_config, scene_to_item
from selfsup.scenes.degrade import Degradations

log = logging.getLogger(__name__)

COLUMNS = ["set", "scenes", "median_position_error", "median_angular_error", "mean_angular_error", "success_rate",
           "count_accuracy", "one_light_success", "two_light_right_count", "three_light_right_count", "ms_per_image"]


def _file_pool_rows(network, directory: str, device) -> list[dict]:
    from selfsup.estimation.files import scene_files
    from selfsup.scenes.io import read_scene

    rows = []
    for path in scene_files(directory):
        scene = read_scene(path)
        if scene.light_pos is None or scene.scene_scale is None:
            raise ValueError(f"{path}: eval needs ground-truth lights and scene_scale")
        item = scene_to_item(scene, max(network.max_lights, scene.light_pos.shape[0]))
        rows.extend(evaluate_network(network, collate([item]), batch_size=1, albedo=True))
    return rows


def inference_ms(network, device, height: int = 128, width: int = 128, batch: int = 16) -> float:
    """Milliseconds per image of the network's forward pass (inputs already built, no albedo)."""
    sampler = sampler_config(height=height, width=width)
    pool = materialise(ProceduralScenes(sampler, length=batch, base_seed=77, samples=1))
    scenes = scene_batch({k: v.to(device) for k, v in pool.items()})
    with torch.no_grad():
        seconds = timed(lambda: network(scenes.image, scenes.gbuffer), device)
    return 1000 * seconds / batch


def cost_volume_only(network):
    """A copy of ``network`` whose lights come from its cost volumes alone: the learned
    anchor scores and the slots' learned offsets are zero (the count is unchanged)."""
    import copy

    plain = copy.deepcopy(network)
    with torch.no_grad():
        plain.anchor_out.weight.zero_()
        plain.anchor_out.bias.zero_()
        plain.slot_out.weight[:3].zero_()
        plain.slot_out.bias[:3].zero_()
    return plain


def iterative_ablations(network) -> dict:
    """Copies of an iterative network with one part off each: ``the physics alone`` (a grey
    cost volume's best as the init, every pair weighted 1, the damping fixed at 0.1, no
    presence change: nothing learned places a light), ``no re-render read`` (the update block
    sees zeros for the residual, shadows and shares), ``no shadows`` (the re-render without
    cast shadows), ``votes alone`` (T = 0)."""
    import copy

    def changed(**attributes):
        other = copy.deepcopy(network)
        for name, value in attributes.items():
            setattr(other, name, value)
        return other

    physics = changed(init="volume")
    with torch.no_grad():
        physics.update.weights_out.weight.zero_()
        physics.update.weights_out.bias.fill_(30.0)  # sigmoid(30) = 1: every pair counts
        physics.update.damping_out.weight.zero_()
        physics.update.damping_out.bias.fill_(math.log(math.expm1(0.1)))  # softplus^-1(0.1)
        physics.update.slot_out[-1].weight.zero_()
        physics.update.slot_out[-1].bias.zero_()
    blind = copy.deepcopy(network)
    blind.update.use_render = False
    return {"the physics alone (grey volume, unweighted Gauss-Newton)": physics, "no re-render read": blind,
            "no shadows in the re-render": changed(shadows=ShadowMethod.NONE, shadow_options=None),
            "votes alone (T = 0)": changed(steps=0)}


def run(checkpoint: str | None = None, sets: dict | None = None, files: dict | None = None, scenes: int = 200,
        seed: int = 9000, height: int = 120, width: int = 160, samples: int = 2,
        n_lights_probs: tuple = (0.75, 0.25), workers: int = 2, device: str = "auto", write: bool = False):
    """Evaluate ``checkpoint`` (None: the shipped one) on each procedural set in
    ``sets`` (name -> Degradations fields) and each directory in ``files``
    (name -> path). Returns ``(rows, results path or None)``."""
    device = torch.device("cuda" if device == "auto" and torch.cuda.is_available() else
                          ("cpu" if device == "auto" else device))
    network, state = load_network(checkpoint, map_location=device)
    network.to(device)
    speed = inference_ms(network, device)
    speed_one = inference_ms(network, device, 120, 160, 1)
    rows = []
    for name, fields in (sets or {"true reflectance": {}}).items():
        fields = dict(fields or {})
        probs = list(fields.pop("n_lights_probs", n_lights_probs))  # a set may draw its own light counts
        degradations = Degradations(**fields)
        albedo = not degradations.camera  # a capture gives no albedo
        pool = materialise(ProceduralScenes(sampler_config(height=height, width=width, n_lights_probs=probs),
                                            degradations, length=scenes, base_seed=seed, samples=samples,
                                            max_lights=max(network.max_lights, len(probs))), workers=workers)
        iterative = isinstance(network, IterativeLightNet)
        if iterative and degradations.camera:  # as the estimator reads a capture: normals refitted, clipped pixels out
            pool = prepared_pool(pool, max(height, width))
        started = time.perf_counter()
        summary = summarise(evaluate_network(network, pool, albedo=albedo))
        rows.append({"set": name, **_rounded(summary),
                     "ms_per_image": round(1000 * (time.perf_counter() - started) / scenes, 2)})
        # The ablations on every set: what each part is worth.
        others = iterative_ablations(network) if iterative else {
            "cost volume alone (learned scores and offset zeroed)": cost_volume_only(network)}
        for part, other in others.items():
            rows.append({"set": f"{name}, {part}", **_rounded(summarise(evaluate_network(other, pool, albedo=albedo)))})
    for name, directory in (files or {}).items():
        if not Path(directory).exists():
            log.warning("eval set %r skipped: no directory %s", name, directory)
            continue
        started = time.perf_counter()
        per_scene = _file_pool_rows(network, directory, device)
        rows.append({"set": name, **_rounded(summarise(per_scene)),
                     "ms_per_image": round(1000 * (time.perf_counter() - started) / len(per_scene), 2)})
    rows.append({"set": "inference only, 128x128, batch 16", "ms_per_image": round(speed, 2)})
    rows.append({"set": "inference only, 160x120, batch 1", "ms_per_image": round(speed_one, 2)})
    path = None
    if write:
        trained = state.get("metrics", {})
        header = (f"Checkpoint: {checkpoint or 'shipped (selfsup/checkpoints/lightnet.pt)'}; "
                  f"{sum(p.numel() for p in network.parameters())} parameters; its validation at save: "
                  f"{ {k: round(v, 4) for k, v in trained.items()} }. Procedural sets: {scenes} scenes each, "
                  f"seed {seed}, {width}x{height}, {samples}x{samples} AA, P(lights) {list(n_lights_probs)}. "
                  "Errors as in scene-format.md (position: worst light per scene, of the scene size; "
                  "angular: degrees about the centroid); ms_per_image of a set includes input preparation and "
                  "scoring.")
        path = write_results("cnn_eval", device, rows, header, COLUMNS)
    return rows, path


def _rounded(summary: dict) -> dict:
    return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in summary.items()}


__all__ = ["run", "inference_ms", "cost_volume_only", "iterative_ablations"]
