"""Frame sequences with exact truth: each kind changes what it says and nothing else."""

import pytest
import torch

from selfsup.scenes.sampler import SamplerConfig, signed_distance
from selfsup.scenes.sequences import SEQUENCE_KINDS, render_sequence, sequence_specs, write_sequence

SMALL = SamplerConfig(height=30, width=40)


def test_a_moving_light_moves_along_a_path_clear_of_every_surface():
    specs = sequence_specs("moving_light", 3, frames=8, config=SMALL)
    positions = torch.stack([s.light_position[0] for s in specs])
    steps = (positions[1:] - positions[:-1]).norm(dim=-1)
    assert bool((steps > 0).all()) and float(steps.max() / steps.min()) < 1.01  # even steps
    assert bool((signed_distance(specs[0].prims, positions) > SMALL.light_margin * 0.99).all())
    assert all(torch.equal(s.prims.boxes, specs[0].prims.boxes) for s in specs)  # the scene stands still


def test_a_moving_camera_moves_the_scene_and_its_light_rigidly():
    specs = sequence_specs("moving_camera", 3, frames=5, config=SMALL)
    first, last = specs[0], specs[-1]
    assert not torch.allclose(first.light_position, last.light_position)
    for spec in (first, last):  # the light's distance to the floor plane is the same in every frame
        floor = spec.prims.planes[0]
        height = float(((spec.light_position[0] - floor[:3]) * floor[3:6]).sum())
        assert height == pytest.approx(float(((first.light_position[0] - first.prims.planes[0, :3])
                                              * first.prims.planes[0, 3:6]).sum()), rel=1e-4)


def test_the_switch_turns_the_second_light_on_then_off():
    counts = [s.light_position.shape[0] for s in sequence_specs("switch", 3, frames=9, config=SMALL)]
    assert counts == [1, 1, 1, 2, 2, 2, 1, 1, 1]


def test_rendered_frames_carry_their_truth_and_are_written_in_order(tmp_path):
    scenes = render_sequence("two_lights", 4, frames=3, config=SMALL)
    assert [s.id for s in scenes] == ["two_lights_4_000", "two_lights_4_001", "two_lights_4_002"]
    assert all(s.light_pos.shape == (2, 3) for s in scenes)
    assert not torch.equal(scenes[0].light_pos[0], scenes[2].light_pos[0])
    assert torch.equal(scenes[0].light_pos[1], scenes[2].light_pos[1])  # the second light stands still
    paths = write_sequence(scenes, tmp_path)
    assert [p.name for p in paths] == ["frame_000.npz", "frame_001.npz", "frame_002.npz"]


def test_bad_sequence_requests_are_named():
    with pytest.raises(ValueError, match="unknown sequence kind 'dance'"):
        sequence_specs("dance", 0)
    with pytest.raises(ValueError, match="at least 2 frames"):
        sequence_specs("static", 0, frames=1)
    assert set(SEQUENCE_KINDS) == {"static", "moving_light", "moving_camera", "switch", "two_lights"}


def test_mode_generate_writes_a_sequence(tmp_path):
    from selfsup.scenes.generate import generate_set
    from selfsup.scenes.io import read_scene

    paths = generate_set(str(tmp_path), count=3, seed=5, sampler=SMALL, sequence="moving_light")
    assert [p.name for p in paths] == ["frame_000.npz", "frame_001.npz", "frame_002.npz"]
    first, last = read_scene(paths[0]), read_scene(paths[-1])
    assert not torch.equal(first.light_pos, last.light_pos) and torch.equal(first.depth, last.depth)
