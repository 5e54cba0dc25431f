"""Scenes and error measures shared by the estimator's tests."""

import dataclasses

from selfsup.metrics import light_errors
from selfsup.scenes.exact import render_spec
from selfsup.scenes.io import write_scene
from selfsup.scenes.sampler import SamplerConfig, sample_scene

SMALL = SamplerConfig(height=48, width=64, specular_prob=0.0, ambient_zero_prob=1.0)

MEDIUM = dataclasses.replace(SMALL, height=96, width=128)  # the grid search works at stride 4: keep 24x32 there

def _scene(seed, n_lights=1, config=SMALL):
    return render_spec(sample_scene(seed, config, n_lights=n_lights), samples=1).scene

def _rel_error(position, scene):
    return float((position - scene.light_pos).norm(dim=-1).max() / scene.scene_scale)

def _rel_error_paired(position, scene):
    return max(light_errors(position, None, scene.light_pos, None, float(scene.scene_scale),
                            scene.light_pos.mean(0)).position)


def _written(folder, seed, config):
    path = folder / "written" / f"{seed}.npz"
    path.parent.mkdir(exist_ok=True)
    write_scene(path, _scene(seed, config=config))
    return path
