"""selfsup/indirect.py: the first bounce between visible surfaces, and its use in model selection."""

import dataclasses
import math

import pytest
import torch

from render import GBuffer
from selfsup.estimation.options import EstimateOptions, Tuning
from selfsup.estimation.stages import estimate_scene
from selfsup.scenes.indirect import bounce_gain, indirect_columns, one_bounce
from selfsup.scenes.exact import render_spec
from selfsup.scenes.sampler import SamplerConfig, sample_scene


def _corner(H=12, W=16, f=12.0, dtype=torch.float64):
    """A floor (y = 1, normal up: -y in the camera frame) meeting a back wall (z = 4)."""
    K = torch.tensor([[[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]]], dtype=dtype)
    v, u = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")
    rays = torch.stack([(u - (W - 1) / 2) / f, (v - (H - 1) / 2) / f, torch.ones_like(u)], -1)
    floor_t = torch.where(rays[..., 1] > 0, 1 / rays[..., 1].clamp_min(1e-9), torch.full_like(u, 1e9))
    floor = floor_t < 4 / rays[..., 2]
    depth = torch.where(floor, floor_t, 4 / rays[..., 2])
    up, back = torch.tensor([0.0, -1, 0], dtype=dtype), torch.tensor([0.0, 0, -1], dtype=dtype)
    normals = torch.where(floor[..., None], up, back)
    return GBuffer.from_depth(depth[None], K, normals=normals[None]), floor


def test_one_bounce_matches_the_sum_over_patches_written_out():
    g, floor = _corner()
    kd = torch.rand(1, 12, 16, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    diffuse = torch.rand(1, 2, 12, 16, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    got = one_bounce(g, kd, diffuse, patch_px=1, target_px=1)[0]
    pts, nrm, f = g.points[0].reshape(-1, 3), g.normals[0].reshape(-1, 3), 12.0
    expected = torch.zeros(3, 2, 12 * 16, dtype=torch.float64)
    for x in range(12 * 16):
        for p in range(12 * 16):
            d = pts[p] - pts[x]
            r2 = float(d @ d)
            cos_view = max(float(nrm[p] @ -pts[p] / pts[p].norm()), 0.2)
            area = (float(pts[p, 2]) / f) ** 2 / cos_view
            if r2 == 0:
                continue
            r = math.sqrt(r2)
            form = max(float(nrm[x] @ d) / r, 0) * max(float(nrm[p] @ -d) / r, 0) * area / (math.pi * max(r2, area))
            expected[:, :, x] += form * kd[0].reshape(-1, 3)[p][:, None] * diffuse[0].reshape(2, -1)[:, p]
    assert torch.allclose(got.reshape(3, 2, -1), expected, rtol=1e-6, atol=1e-12)


def test_a_plane_lights_nothing_of_itself_and_a_lit_floor_lights_the_wall():
    g, floor = _corner(60, 80, 60.0, torch.float32)
    kd = torch.full((1, 60, 80, 3), 0.5)
    lit_floor = floor.float()[None, None]
    bounce = one_bounce(g, kd, lit_floor)[0, :, 0]
    wall = ~floor
    wall[:, :2] = wall[:, -2:] = False  # interpolation borders
    inner_floor = floor.clone()
    inner_floor[floor.nonzero()[:, 0].min() : floor.nonzero()[:, 0].min() + 12] = False  # off the corner's interpolation band
    assert inner_floor.sum() > 100 and bounce[:, inner_floor].abs().max() < 1e-6
    assert bounce[:, wall].min() > 0
    assert torch.allclose(one_bounce(g, kd, 2 * lit_floor)[0, :, 0], 2 * bounce)  # linear in the light


def test_missing_pixels_give_finite_zeros():
    g, _ = _corner(24, 32, 24.0, torch.float32)
    mask = g.mask.clone()
    mask[0, 3:9, 4:12] = False
    points = torch.where(mask[..., None], g.points, torch.full_like(g.points, float("nan")))
    g = GBuffer(points=points, normals=g.normals, mask=mask, intrinsics=g.intrinsics)
    kd = torch.full((1, 24, 32, 3), 0.5)
    bounce = indirect_columns(g, kd, torch.ones(1, 1, 24, 32))
    assert torch.isfinite(bounce).all() and bounce[0, :, 0][:, ~mask[0]].abs().max() == 0


def test_bounce_gain_is_the_series_of_the_mean_albedo():
    kd = torch.tensor([0.0, 0.5, 0.95]).expand(1, 4, 4, 3)
    gain = bounce_gain(kd, torch.ones(1, 4, 4, dtype=torch.bool))
    assert torch.allclose(gain, torch.tensor([[1.0, 2.0, 5.0]]))  # the last capped at mean albedo 0.8


def test_indirect_judges_only_files_without_ambient():
    config = SamplerConfig(height=48, width=64, specular_prob=0.0, ambient_zero_prob=1.0)
    scene = render_spec(sample_scene(3, config, n_lights=1), samples=1).scene

    def criteria(s, indirect):
        return [c["criterion"] for c in estimate_scene(s, EstimateOptions(tuning=Tuning(indirect=indirect)))["candidates"]]

    assert criteria(scene, "auto") == criteria(scene, "never")  # the ambient is given: nothing unaccounted for
    unknown = dataclasses.replace(scene, ambient=None)
    assert criteria(unknown, "auto") != criteria(unknown, "never")
    with pytest.raises(ValueError, match="indirect"):
        EstimateOptions(tuning=Tuning(indirect="sometimes"))


def test_a_problem_keeps_its_indirect_switch_and_medians_through_selections():
    from selfsup.estimation.prepare import prepare
    from selfsup.estimation.problem import FitProblem

    config = SamplerConfig(height=24, width=32, specular_prob=0.0, ambient_zero_prob=1.0)
    scenes = [dataclasses.replace(render_spec(sample_scene(s, config), samples=1).scene, ambient=None) for s in (1, 2)]
    problem = prepare(scenes, EstimateOptions())
    median = problem.median_observed()
    bounced = problem.with_indirect()
    assert bounced.indirect and not problem.indirect and bounced._median is median
    assert bounced.select(torch.tensor([1])).indirect
    assert FitProblem.cat([bounced.select(torch.tensor([0])), bounced.select(torch.tensor([1]))]).indirect
