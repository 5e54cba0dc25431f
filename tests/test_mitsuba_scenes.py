"""benchmarks/mitsuba_scenes.py: its sensor model, and (where Mitsuba 3 is installed)
that Mitsuba's images of a sampled scene agree with our exact renderer's."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from benchmarks.mitsuba_scenes import _plane_normals, _sensor_noise


def _slanted_plane(H=30, W=40, f=40.0):
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]])
    normal = np.array([0.0, -0.6, -0.8])  # faces the camera
    v, u = np.mgrid[0:H, 0:W].astype(float)
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    depth = 3.0 / (rays @ -normal)  # the plane n.X = -3
    return depth, np.broadcast_to(normal, (H, W, 3)).copy(), K, rays


def test_plane_normals_of_a_plane_are_its_normal_facing_the_camera():
    depth, normal, _, rays = _slanted_plane()
    valid = np.ones(depth.shape, bool)
    valid[5, 5] = False
    n = _plane_normals(depth[..., None] * rays, valid)
    assert np.allclose(n[valid], normal[valid], atol=1e-6)
    assert np.all(n[5, 5] == 0)


def test_sensor_noise_follows_the_devset_model():
    depth, normal, K, _ = _slanted_plane(120, 160, 140.0)
    image = np.full(depth.shape + (3,), 0.4)
    noisy, z, normals, _ = _sensor_noise(image, depth, normal, K, np.random.default_rng(0))
    kept = z > 0
    assert 0.95 < kept.mean() < 0.99  # 2% random holes, no jumps or grazing views on this plane
    sigma = 0.0012 * depth**2 + 0.002
    assert 0.9 < np.std(((z - depth) / sigma)[kept]) < 1.1
    assert np.all(np.abs(np.round(z[kept] * 1000) - z[kept] * 1000) < 1e-6)  # 1 mm steps
    expected = math.sqrt(1.44e-4 * 0.4 * 0.4 + (0.006 * 0.4) ** 2)
    assert abs(np.std(noisy - image) / expected - 1) < 0.05
    angles = np.degrees(np.arccos(np.clip(np.sum(normals[kept] * normal[kept], -1), -1, 1)))
    assert 0.5 < np.median(angles) < 20  # refitted to the noisy depth: noisy, but planes


def test_mitsuba_direct_light_matches_the_exact_renderer():
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    from benchmarks.mitsuba_scenes import render_variants
    from selfsup.scenes.exact import render_spec
    from selfsup.scenes.sampler import SamplerConfig, sample_scene

    spec = sample_scene(5, SamplerConfig(height=30, width=40), n_lights=1)
    m = spec.materials  # uniform matte albedo: the two renderers' models coincide
    spec = dataclasses.replace(spec, ambient_relative=torch.zeros(3), materials=dataclasses.replace(
        m, texture=torch.zeros_like(m.texture), ks=torch.zeros_like(m.ks)))
    ours = render_spec(spec).scene
    theirs = render_variants(spec, "check")["direct"]
    assert torch.equal(theirs.depth > 0, ours.depth > 0)
    valid = ours.depth > 0
    assert (theirs.depth - ours.depth)[valid].abs().max() < 1e-3
    assert (theirs.normals * ours.normals).sum(-1)[valid].min() > 0.999
    # Images relative to their own light intensities (the exposures differ slightly).
    a = theirs.image / theirs.light_intensity[0]
    b = ours.image / ours.light_intensity[0]
    assert ((a - b).abs().amax(-1)[valid] / b.amax(-1)[valid].clamp_min(1e-3)).median() < 0.01


def test_a_closed_room_leaves_no_pixel_open():
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    from benchmarks.mitsuba_scenes import render_variants
    from selfsup.scenes.sampler import SamplerConfig, sample_scene

    spec = sample_scene(7000 * 1_000_003, SamplerConfig(height=30, width=40), n_lights=1)  # the set's scene 0
    open_room = render_variants(spec, "open")["direct"]
    closed = render_variants(spec, "closed", closed=True)
    assert (open_room.depth == 0).any()  # this scene looks past a wall's edge
    assert (closed["direct"].depth > 0).all()
    assert closed["gi"].image.mean() > closed["direct"].image.mean()  # the closing walls reflect


def test_the_mitsuba_studio_cup_shows_its_inside_to_the_camera():
    # benchmarks/mitsuba_studio.py's cup: an open tube on a bottom, tilted towards the camera, so the
    # inside (deeper than the front rim by about a diameter) is in view and lit by a lamp in front.
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    from benchmarks.mitsuba_studio import CUP_RADIUS, render
    from selfsup.scenes.studio import sphere_centre, studio_spec

    spec = studio_spec((0.1, -0.1, -0.99), others=False, width=40, height=30)
    image, depth = render(spec, "cup", "matte", "direct", spp=4)
    seen = depth > 0
    assert 0.1 < float(seen.float().mean()) < 0.6
    centre = float(sphere_centre(spec)[2])
    assert float(depth[seen].min()) < centre - 0.5 * CUP_RADIUS  # the front of the tube
    assert float(depth[seen].max()) > centre + 0.5 * CUP_RADIUS  # the inside's far wall and bottom
    assert float(image[~seen].mean()) < 0.05 * float(image[seen].mean())  # lit, in the dark (edge pixels partly)
