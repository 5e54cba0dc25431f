"""Procedural scenes: sampler, exact rendering, degradations, datasets, files."""

import dataclasses
import os
import re
import subprocess
import sys

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from render import GBuffer, Material, PointLights, render
from selfsup.scenes import dataset
from selfsup.scenes.dataset import ProceduralScenes, collate, protocol_specs, render_items, scene_to_item
from selfsup.scenes.degrade import Degradations, degrade
from selfsup.scenes.exact import render_spec, render_specs
from selfsup.scenes.io import read_scene
from selfsup.scenes.sampler import SamplerConfig, Texture, sample_scene, signed_distance
from selfsup.scenes.studio import PANEL_POINTS, drawn_studio_spec, scene_spec

SMALL = SamplerConfig(height=48, width=64, n_lights_probs=(0.5, 0.5))


def _rendered(seed, config=SMALL, samples=2):
    return render_spec(sample_scene(seed, config), samples=samples)


def test_same_seed_same_scene_and_different_seeds_differ():
    a, b, c = _rendered(3).scene, _rendered(3).scene, _rendered(4).scene
    torch.testing.assert_close(a.image, b.image, rtol=0, atol=0)
    torch.testing.assert_close(a.light_pos, b.light_pos, rtol=0, atol=0)
    assert not torch.equal(a.depth, c.depth)


def test_scenes_cast_together_render_exactly_as_each_alone():
    # Seeds with one and two lights, with and without anti-aliased pixels; an object in the dark
    # (its background rays hit nothing) beside rooms with more lights: the padded lights sit at
    # the camera, where those rays' points are, and made its background NaN.
    specs = [sample_scene(seed, SMALL) for seed in range(5)] + [drawn_studio_spec(0, SMALL)]
    assert len({spec.light_position.shape[0] for spec in specs}) == 2
    for samples in (1, 2):
        for alone, together in zip([render_spec(s, samples=samples) for s in specs], render_specs(specs, samples=samples)):
            for name in ("image", "depth", "normals", "kd", "ks", "shininess", "light_intensity"):
                assert torch.equal(getattr(alone.scene, name), getattr(together.scene, name)), name
            assert torch.equal(alone.visibility, together.visibility)
            assert alone.scene.meta == together.scene.meta
    with pytest.raises(ValueError, match="one size"):
        render_specs([specs[0], sample_scene(0, dataclasses.replace(SMALL, height=32))])


def test_a_share_of_objects_in_the_dark_leaves_the_rooms_as_they_were():
    # studio_prob draws from its own stream: a seed that stays a room is the same room.
    mixed = dataclasses.replace(SMALL, studio_prob=0.5)
    specs = [scene_spec(seed, mixed) for seed in range(40)]
    studio = [bool(spec.meta.get("studio")) for spec in specs]
    assert 10 <= sum(studio) <= 30
    for seed, (spec, is_studio) in enumerate(zip(specs, studio)):
        if not is_studio:
            assert torch.equal(spec.light_position, sample_scene(seed, SMALL).light_position)
    frame = render_spec(specs[studio.index(True)], samples=1).scene
    assert bool(torch.isfinite(frame.image).all()) and 0.02 < float((frame.depth > 0).float().mean()) < 0.9
    assert frame.light_pos.shape == (1, 3) and float(frame.image.amax()) > 0
    with pytest.raises(ValueError, match="studio_prob"):
        SamplerConfig(studio_prob=1.5)


def test_a_share_of_rooms_lit_by_ceiling_panels_reports_their_centres():
    # panel_prob draws from its own stream: a seed that stays lit by points is the same room;
    # a panel's room is rendered from its grid of points and reported as one light at its centre.
    mixed = dataclasses.replace(SMALL, panel_prob=0.5, n_lights_probs=(0.5, 0.5))
    specs = [scene_spec(seed, mixed) for seed in range(20)]
    panel = ["area_lights" in spec.meta for spec in specs]
    assert 4 <= sum(panel) <= 16
    for seed, (spec, is_panel) in enumerate(zip(specs, panel)):
        point = sample_scene(seed, dataclasses.replace(mixed, panel_prob=0.0))
        if not is_panel:
            assert torch.equal(spec.light_position, point.light_position)
        else:
            n = point.light_position.shape[0]
            assert spec.light_position.shape[0] == n * PANEL_POINTS ** 2
    seeds = [seed for seed, is_panel in enumerate(panel) if is_panel][:2]
    for (rendered, scene), seed in zip(render_items(seeds, mixed, Degradations(indirect=1.0), 1), seeds):
        centres = torch.tensor(specs[seed].meta["area_lights"]["centres"])
        assert torch.allclose(scene.light_pos, centres) and scene.light_intensity.shape == centres.shape
        assert torch.allclose(scene.light_intensity.sum(0), rendered.scene.light_intensity.sum(0))
        assert bool(torch.isfinite(scene.image).all()) and float(scene.image.amax()) > 0
        item = scene_to_item(scene, 2)
        assert int(item["light_mask"].sum()) == centres.shape[0]
    with pytest.raises(ValueError, match="panel_prob"):
        SamplerConfig(panel_prob=-0.1)


def test_dataset_batches_equal_its_items():
    data = ProceduralScenes(SMALL, length=4, base_seed=5)
    for item, one in zip(data.__getitems__([2, 0, 3]), (data[2], data[0], data[3])):
        for key in item:
            assert torch.equal(item[key], one[key]), key
    with pytest.raises(IndexError):
        data.__getitems__([0, 4])
    with pytest.raises(ValueError, match="samples must be >= 1"):  # it died in the first worker that rendered
        ProceduralScenes(SMALL, length=4, samples=0)


@pytest.mark.parametrize("seed", range(4))
def test_depth_reprojects_onto_the_surfaces_and_normals_face_the_camera(seed):
    spec = sample_scene(seed, SMALL)
    scene = render_spec(spec, samples=1).scene
    gbuffer = GBuffer.from_depth(scene.depth[None], scene.K[None], scene.normals[None])
    points = gbuffer.points[0][gbuffer.mask[0]].double()
    distance = signed_distance(spec.prims.to(torch.float64), points).abs()
    assert distance.max() < 1e-4 * points.norm(dim=-1).max()
    normals = scene.normals[gbuffer.mask[0]].double()
    assert ((normals * -points).sum(-1) > 0).all()
    torch.testing.assert_close(normals.norm(dim=-1), torch.ones(len(normals), dtype=torch.float64))


def test_lights_keep_the_margin_from_every_surface():
    config = dataclasses.replace(SMALL, n_objects=(6, 8), light_margin=0.4)
    for seed in range(20):
        spec = sample_scene(seed, config)
        distance = signed_distance(spec.prims.to(torch.float64), spec.light_position.double())
        assert (distance > 0.4 - 1e-4).all(), (seed, distance)


def test_typical_scene_has_at_least_5_percent_shadow():
    shares = [float((_rendered(seed, samples=1).visibility < 0.5).any(-1).float().mean()) for seed in range(12)]
    assert sorted(shares)[len(shares) // 2] >= 0.05, shares


@pytest.mark.parametrize("seed", [0, 1])
def test_exact_renderer_agrees_with_render_layer_without_occluders(seed):
    config = dataclasses.replace(SMALL, n_objects=(0, 0), ambient_zero_prob=0.0)
    scene = _rendered(seed, config, samples=1).scene
    gbuffer = GBuffer.from_depth(scene.depth[None].double(), scene.K[None].double(), scene.normals[None].double())
    material = Material(kd=scene.kd[None].double(), ks=scene.ks[None].double(), shininess=scene.shininess[None].double())
    lights = PointLights(position=scene.light_pos[None].double(), intensity=scene.light_intensity[None].double())
    out = render(gbuffer, material, lights, scene.ambient[None].double(), shadows="none")
    ours = out.image[0].permute(1, 2, 0)
    rel = (ours - scene.image.double()).abs() / scene.image.double().clamp_min(1e-3)
    assert rel.max() < 1e-4


def test_batched_quantiles_equal_torch_quantile_of_each_rows_valid_values():
    from selfsup.scenes.exact import _quantiles

    gen = torch.Generator().manual_seed(3)
    values = torch.rand(5, 300, generator=gen)
    valid = torch.rand(5, 300, generator=gen) < torch.tensor([[0.9], [0.5], [0.02], [1.0], [0.0]])
    got = _quantiles(values, valid, 0.99)
    for row in range(4):
        torch.testing.assert_close(got[row], torch.quantile(values[row][valid[row]], 0.99), rtol=0, atol=1e-6)
    assert got[4] == 0  # no valid value


def test_antialiasing_averages_edges_only():
    spec = sample_scene(1, SMALL)
    sharp, smooth = render_spec(spec, samples=1).scene, render_spec(spec, samples=3).scene
    changed = (sharp.image - smooth.image).abs().amax(-1) > 1e-5
    assert 0 < smooth.meta["aa_pixels"] < SMALL.height * SMALL.width
    assert changed.float().mean() <= smooth.meta["aa_pixels"] / (SMALL.height * SMALL.width) + 1e-6
    torch.testing.assert_close(sharp.depth, smooth.depth)


def test_edge_keys_flag_the_pixels_the_value_ranges_flag():
    # _edges compares one integer key and one set of albedo classes per pixel; the
    # definition is the range over the 3x3 neighbourhood of the primitive, of each light's
    # visibility and of each channel of the patterned albedo (0 off patterns and off the
    # surface): any change, or over 0.02. Random maps with small regions and thin stripes.
    from selfsup.scenes.exact import _albedo_jumps, _edges, material_rows, neighbourhood_max
    from selfsup.scenes.sampler import Materials

    generator = torch.Generator().manual_seed(0)
    B, H, W, L, P = 3, 24, 32, 2, 4
    base = torch.rand(P, 3, generator=generator)
    alt = base.clone()
    alt[0] += 0.01  # a jump below the threshold
    alt[1:] *= 0.4
    materials = Materials(kd_base=base, kd_alt=alt, texture=torch.tensor([1, 2, 1, 0]), texture_scale=torch.ones(P),
                          texture_dir=torch.ones(P, 3), ks=torch.zeros(P), shininess=torch.ones(P))
    rows = material_rows(materials)

    def blocky(high, cells):
        return torch.randint(0, high, (B, H // cells, W // cells), generator=generator).repeat_interleave(
            cells, 1).repeat_interleave(cells, 2)

    local = blocky(P, 4)
    visibility = torch.stack([blocky(2, 8), blocky(2, 2)]).float()
    side = torch.randint(0, 2, (B, H, W), generator=generator)
    valid = torch.rand(B, H, W, generator=generator) > 0.05
    patterned = valid & (materials.texture[local] != 0)
    albedo_class = (patterned * (1 + side)).to(torch.uint8)
    kd = alt[local] + side[..., None] * (base[local] - alt[local])
    kd = (kd * patterned[..., None]).permute(3, 0, 1, 2)
    geometry, albedo = _edges(local, visibility, albedo_class, _albedo_jumps(rows)[local])

    stack = torch.cat([local.float()[None], visibility, kd])
    change = neighbourhood_max(stack) + neighbourhood_max(-stack)
    expected_geometry = (change[: 1 + L] > 0).any(0)
    assert torch.equal(geometry, expected_geometry)
    assert torch.equal(albedo, (change[-3:] > 0.02).any(0) & ~expected_geometry)
    assert 0 < albedo.sum() and 0 < geometry.sum() < geometry.numel()


@pytest.mark.parametrize("seed", [1, 5])
def test_adaptive_antialiasing_matches_four_shifted_renders(seed):
    # The 2x2 samples of a pixel are the centre samples of renders whose principal point
    # moves by a quarter pixel: their mean is brute-force supersampling. The adaptive
    # render (full trace at primitive and shadow edges, the centre's primitive alone at
    # checker and stripe edges, the centre sample elsewhere) must match it; fractal
    # albedo, which it point-samples (see render_specs), is swapped for uniform.
    spec = sample_scene(seed, dataclasses.replace(SMALL, n_lights_probs=(1.0,)))
    texture = torch.where(spec.materials.texture == Texture.NOISE, Texture.UNIFORM, spec.materials.texture)
    spec = dataclasses.replace(spec, materials=dataclasses.replace(spec.materials, texture=texture))

    def unit_exposure(scene):
        return scene.image.double() * float(spec.light_relative_intensity[0, 0] / scene.light_intensity[0, 0])

    adaptive = unit_exposure(render_spec(spec, samples=2).scene)
    shots = []
    for dy in (-0.25, 0.25):
        for dx in (-0.25, 0.25):
            K = spec.K.clone()
            K[0, 2] -= dx
            K[1, 2] -= dy
            shots.append(unit_exposure(render_spec(dataclasses.replace(spec, K=K), samples=1).scene))
    brute = torch.stack(shots).mean(0)
    off = ((adaptive - brute).abs() / brute.clamp_min(1e-3)).amax(-1) > 1e-2
    assert off.double().mean() < 0.01  # measured 2026-11-23: 0.3% and 0.8% of pixels


def _fields(scene):
    return {f.name: getattr(scene, f.name) for f in dataclasses.fields(scene) if f.name != "meta"}


@pytest.mark.parametrize("switch, changed", [
    (dict(reflectance="half"), {"kd", "ks"}),
    (dict(reflectance="noise", reflectance_noise=0.2), {"kd"}),
    (dict(depth_noise=0.003), {"depth", "normals"}),
    (dict(depth_quantisation=0.002), {"depth", "normals"}),
    (dict(edge_hole_jump=0.05), {"depth", "normals"}),
    (dict(random_holes=0.05), {"depth", "normals"}),
    (dict(image_noise=0.01), {"image"}),
    (dict(ambient="unknown"), {"ambient"}),
    (dict(ambient="wrong", wrong_ambient_factor=3.0), {"ambient"}),
])
def test_each_degradation_changes_only_what_it_should(switch, changed):
    config = dataclasses.replace(SMALL, ambient_zero_prob=0.0)
    clean = _rendered(2, config, samples=1).scene
    before = {k: (v.clone() if v is not None else None) for k, v in _fields(clean).items()}
    noisy = degrade(clean, Degradations(**switch), seed=5)
    for key, value in _fields(noisy).items():
        same = (value is None and before[key] is None) or (
            value is not None and before[key] is not None and torch.equal(value, before[key]))
        assert same != (key in changed), key
    for key, value in _fields(clean).items():  # the ground truth scene is untouched
        assert (value is None and before[key] is None) or torch.equal(value, before[key])


def test_indirect_light_adds_the_rooms_bounces_and_needs_the_visibility():
    rendered = _rendered(2, dataclasses.replace(SMALL, ambient_zero_prob=0.0), samples=1)
    clean = rendered.scene
    lit = degrade(clean, Degradations(indirect=2.0), seed=5, visibility=rendered.visibility)
    valid = clean.depth > 0
    added = (lit.image - clean.image)[valid]
    strength = lit.meta["indirect_strength"]
    assert 0 < strength <= 2.0 and (added >= 0).all() and float(added.mean()) > 0.01 * float(clean.image[valid].mean())
    changed = {k for k, v in _fields(lit).items() if not (v is None or torch.equal(v, _fields(clean)[k]))}
    assert changed == {"image"}  # the truth (lights, albedo, depth) is what it was
    with pytest.raises(ValueError, match="visibility"):
        degrade(clean, Degradations(indirect=1.0), seed=5)


def test_a_drawn_camera_gives_what_the_capture_reader_gives():
    from selfsup.scenes.capture import srgb_to_linear

    rendered = _rendered(3, SMALL, samples=1)
    clean = rendered.scene
    captured = degrade(clean, Degradations(camera=True), seed=7)
    codes = torch.from_numpy(srgb_to_linear(np.arange(256) / 255)).float()
    image = captured.image.flatten()
    nearest = (image[:, None] - codes[None]).abs().amin(1)
    assert float(nearest.max()) < 1e-6  # 8-bit sRGB codes, read back to linear
    depth = captured.depth[captured.depth > 0]
    torch.testing.assert_close(depth * 1000, (depth * 1000).round(), rtol=0, atol=1e-3)  # millimetres
    assert captured.normals is None and captured.ambient is None  # a camera gives neither
    assert (captured.depth == 0).sum() >= (clean.depth == 0).sum()  # the sensor's holes
    ratio = captured.light_intensity / clean.light_intensity  # exposure times the white balance's gains
    assert torch.isfinite(ratio).all() and (ratio > 0).all()
    torch.testing.assert_close(ratio, ratio[:1].expand_as(ratio))  # one camera for every light
    assert torch.equal(captured.kd, clean.kd) and torch.equal(captured.light_pos, clean.light_pos)
    again = degrade(clean, Degradations(camera=True), seed=7)
    assert torch.equal(again.image, captured.image) and torch.equal(again.depth, captured.depth)


def test_light_power_range_draws_dim_lights_and_its_default_draws_as_before():
    # The default (1/3, 1) draws the numbers the sampler drew before the setting existed.
    same = sample_scene(11, dataclasses.replace(SMALL, light_power_range=(1 / 3, 1.0)))
    torch.testing.assert_close(sample_scene(11, SMALL).light_relative_intensity, same.light_relative_intensity,
                               rtol=0, atol=0)
    dim = SamplerConfig(height=8, width=8, n_lights_probs=(0.0, 1.0), light_power_range=(0.1, 1.0))
    ratios = []
    for seed in range(40):
        spec = sample_scene(seed, dim)
        power = spec.light_relative_intensity.mean(-1) / spec.light_position.norm(dim=-1) ** 2
        ratios.append(float(power.min() / power.max()))
    assert min(ratios) < 1 / 3 and min(ratios) >= 0.1 * 0.75  # the tint moves a channel by 25% at most
    with pytest.raises(ValueError, match="light_power_range"):
        SamplerConfig(light_power_range=(0.0, 1.0))


def test_bad_degradation_values_are_named():
    with pytest.raises(ValueError, match="reflectance"):
        Degradations(reflectance="wrong")
    with pytest.raises(ValueError, match="random_holes"):
        Degradations(random_holes=1.5)


def test_dataset_is_reproducible_and_worker_safe():
    data = ProceduralScenes(SMALL, length=4, base_seed=1, samples=1)
    direct = collate([data[i] for i in range(4)])
    loaded = next(iter(DataLoader(data, batch_size=4, num_workers=2, collate_fn=collate)))
    for key in direct:
        torch.testing.assert_close(direct[key], loaded[key], rtol=0, atol=0)
    assert direct["light_mask"].shape == (4, 2)
    with pytest.raises(IndexError):
        data[4]


class _ReportsRetention(ProceduralScenes):
    # Each item says whether the process that rendered it keeps its freed memory.
    def __getitems__(self, indices):
        items = super().__getitems__(indices)
        for item in items:
            item["retains"] = torch.tensor(dataset._retaining["pid"] == os.getpid())
        return items


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_dataloader_workers_keep_their_freed_memory_and_the_caller_is_left_alone(monkeypatch):
    monkeypatch.setitem(dataset._retaining, "pid", None)  # whatever this test process did before
    data = _ReportsRetention(SMALL, length=2, base_seed=1, samples=1)
    loaded = next(iter(DataLoader(data, batch_size=1, num_workers=2, collate_fn=collate)))
    assert loaded["retains"].all()
    assert not data[0]["retains"] and dataset._retaining["pid"] is None  # rendered here: left alone
    assert dataset.retain_freed_memory() and dataset._retaining["pid"] == os.getpid()


def test_rendering_a_scene_imports_no_sympy():
    # Each DataLoader worker would pay the import (half a second) before its first
    # batch; torch.broadcast_shapes, for one, imports it on its first call.
    code = ("import sys; from selfsup.scenes.dataset import render_items; "
            "from selfsup.scenes.sampler import SamplerConfig; from selfsup.scenes.degrade import Degradations; "
            "render_items([0, 1], SamplerConfig(height=24, width=32), Degradations(), 2); "
            "print('sympy' in sys.modules)")
    ran = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert ran.returncode == 0, ran.stderr
    assert ran.stdout.strip() == "False"


def test_protocol_set_is_9_scenes_by_6_lights():
    specs = protocol_specs(dataclasses.replace(SMALL, n_lights_probs=(1.0,)))
    assert len(specs) == 54
    seeds = [s.meta["protocol"]["scene_seed"] for s in specs]
    assert len(set(seeds)) == 9 and all(seeds.count(s) == 6 for s in set(seeds))
    assert all(s.light_position.shape == (1, 3) for s in specs)


def test_generate_mode_writes_readable_files_and_contact_sheet(tmp_path):
    from hydra import compose, initialize_config_dir

    import train

    with initialize_config_dir(version_base="1.3", config_dir=str(train.__file__).rsplit("/", 1)[0] + "/configs"):
        cfg = compose("train", overrides=[
            "mode=generate", f"generate.out={tmp_path}", "generate.count=3",
            "data.sampler.height=24", "data.sampler.width=32", "generate.contact_sheet_rows=2",
        ])
    paths = train.run(cfg)
    assert len(paths) == 3 and (tmp_path / "contact_sheet.png").stat().st_size > 0
    scene = read_scene(paths[0])
    assert scene.image.shape == (24, 32, 3) and scene.light_pos.shape == (1, 3) and float(scene.scene_scale) > 0


def test_generate_set_writes_the_same_files_from_worker_processes(tmp_path):
    from selfsup.scenes.generate import generate_set

    tiny = dataclasses.replace(SMALL, height=12, width=16)
    alone = generate_set(str(tmp_path / "alone"), count=18, sampler=tiny, contact_sheet_rows=0, workers=0)
    spread = generate_set(str(tmp_path / "spread"), count=18, sampler=tiny, contact_sheet_rows=0, workers=2)
    assert [p.name for p in alone] == [p.name for p in spread] == [f"scene_{i:05d}.npz" for i in range(18)]
    for a, b in zip(alone, spread):
        with np.load(a) as x, np.load(b) as y:
            assert x.files == y.files and all(np.array_equal(x[k], y[k]) for k in x.files)
    for bad, message in ((dict(workers=-1), "generate.workers"), (dict(count=2.5), "generate.count"),
                         (dict(count=0), "generate.count"), (dict(samples=0), "data.samples"),
                         (dict(contact_sheet_rows=-1), "generate.contact_sheet_rows")):
        with pytest.raises(ValueError, match=message):
            generate_set(str(tmp_path / "bad"), **{"count": 1, "sampler": tiny, **bad})
    assert not (tmp_path / "bad").exists()


def test_generate_speed_benchmark_reports_the_median_loader_run_and_its_range():
    from benchmarks.generate_speed import run

    rows = run(count=2, batch=2, workers=1, loader_count=6, loader_runs=3, write=False)
    loader = [row for row in rows if row["how"].startswith("DataLoader")]
    assert len(loader) == 2 and all(row["runs"] == 3 for row in loader)
    for row in loader:
        low, high = map(float, row["range_scenes_per_s"].split("-"))
        assert low <= row["scenes_per_s"] <= high
    assert all(row["scenes_per_s"] > 0 for row in rows)


@pytest.mark.parametrize("change, message", [
    (dict(n_lights_probs=(0.0, 0.0)), "n_lights_probs must be finite, >= 0 and not all 0"),
    (dict(n_lights_probs=(1.0, -0.5)), "n_lights_probs"),
    (dict(height=0), "height and width must be integers >= 1"),
    (dict(room_width=(5.0, 3.0)), "room_width must be a range"),
    (dict(fov_x_deg=(50.0, 190.0)), "fov_x_deg must be a range"),
    (dict(scale_range=(0.0, 1.0)), "scale_range must be a range"),
    (dict(n_objects=(3, 1)), "n_objects must be a range"),
    (dict(specular_prob=1.5), "specular_prob must be a probability"),
    (dict(light_margin=-0.1), "light_margin must be >= 0"),
])
def test_bad_sampler_settings_are_named(change, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        dataclasses.replace(SamplerConfig(), **change)
