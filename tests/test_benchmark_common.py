import json

import torch

from benchmarks import common


def test_cpu_results_carry_the_machine_reference(tmp_path, monkeypatch):
    monkeypatch.setattr(common, "RESULTS", tmp_path)
    threads = torch.get_num_threads()
    md = common.write_results("probe", torch.device("cpu"), [{"a": 1}], "header", ["a"])
    assert torch.get_num_threads() == threads  # the reference's one-thread pass restores the threads
    reference = json.loads(md.with_suffix(".json").read_text())["meta"]["machine_reference"]
    assert 0 < reference["elementwise_ns"] < 100 and reference["matmul_gflops"] > 0
    assert reference["threads"] == threads
    text = md.read_text()
    assert f"{reference['elementwise_ns']} ns per element" in text and "| 1 |" in text


def test_a_rerun_of_the_same_day_keeps_the_earlier_results(tmp_path, monkeypatch):
    monkeypatch.setattr(common, "RESULTS", tmp_path)
    monkeypatch.setattr(common, "machine_reference", lambda: {"elementwise_ns": 1.0, "matmul_gflops": 1.0, "threads": 1})
    first = common.write_results("probe", torch.device("cpu"), [{"a": 1}], "header", ["a"])
    second = common.write_results("probe", torch.device("cpu"), [{"a": 2}], "header", ["a"])
    third = common.write_results("probe", torch.device("cpu"), [{"a": 3}], "header", ["a"])
    assert first != second != third and second.stem == f"{first.stem}_2" and third.stem == f"{first.stem}_3"
    assert "| 1 |" in first.read_text() and "| 2 |" in second.read_text()
    assert json.loads(first.with_suffix(".json").read_text())["rows"] == [{"a": 1}]


def test_indirect_field_recovers_a_known_indirect_irradiance():
    # gi = direct + kd * E(x): E constant gives no variation; E a ramp across the image varies
    # between blocks, by the ramp's own relative spread.
    import dataclasses

    from benchmarks.indirect_field import block_irradiance
    from selfsup.scenes.exact import render_spec
    from selfsup.scenes.sampler import SamplerConfig, sample_scene

    direct = render_spec(sample_scene(3, SamplerConfig(height=48, width=64)), samples=1).scene
    kd = direct.kd.clamp_min(0.1)  # every pixel usable
    direct = dataclasses.replace(direct, kd=kd)
    constant = dataclasses.replace(direct, image=direct.image + 0.2 * kd)
    irradiance, centre = block_irradiance(direct, constant, 16)
    assert irradiance.shape[0] == centre.shape[0] > 4
    torch.testing.assert_close(irradiance, torch.full_like(irradiance, 0.2))
    ramp = torch.linspace(0.1, 0.3, 64, dtype=kd.dtype).expand(48, 64)[..., None]
    irradiance, _ = block_irradiance(direct, dataclasses.replace(direct, image=direct.image + ramp * kd), 16)
    block_means = ramp[0, :, 0].reshape(4, 16).mean(-1).double()
    torch.testing.assert_close(irradiance.reshape(-1, 4), block_means.expand(3, 4), rtol=1e-5, atol=1e-6)


def test_room_agreement_counts_each_light_against_its_own_exact_shadows():
    # A method scored against its own shadows misses and adds nothing; the same shadows
    # with the lights swapped (or the classes flipped) do not: the bookkeeping of light
    # order, layout and classes is what the rooms' table rests on.
    from benchmarks.shadow_accuracy import room_agreement, setting_agreement
    from render.shadows import shadow_visibility
    from render.types import GBuffer
    from selfsup.scenes.exact import render_spec
    from selfsup.scenes.sampler import SamplerConfig, sample_scene

    scene = render_spec(sample_scene(5, SamplerConfig(height=48, width=64, n_lights_probs=(0.0, 1.0))), samples=1).scene
    g = GBuffer.from_depth(scene.depth[None], scene.K[None], scene.normals[None])
    own = shadow_visibility("epipolar", g.points, g.mask, g.intrinsics, scene.light_pos[None].to(g.points.dtype))[0]
    counts = room_agreement(scene, own.permute(1, 2, 0), methods=("epipolar",))
    assert counts["shadowed"] > 0 and counts["epipolar_missed"] == 0 and counts["epipolar_extra"] == 0
    swapped = room_agreement(scene, own.flip(0).permute(1, 2, 0), methods=("epipolar",))
    assert swapped["epipolar_missed"] + swapped["epipolar_extra"] > 0
    flipped = room_agreement(scene, (1 - own).permute(1, 2, 0), methods=("epipolar",))
    assert flipped["epipolar_missed"] == flipped["shadowed"] > 0
    # No shadows at all: every exactly shadowed pixel missed, none added.
    bare = setting_agreement(scene, own.permute(1, 2, 0), {"bare": ("none", None)})
    assert bare["bare_missed"] == bare["shadowed"] > 0 and bare["bare_extra"] == 0


def test_the_devset_score_gives_each_scene_its_worst_relative_intensity_error(tmp_path):
    # A record with the true positions and one light 10% too bright, another 20% too dim
    # in a two-light scene: position error 0, intensity error 0.2 (the worst paired light).
    from benchmarks.devset_estimate import score
    from selfsup.scenes.exact import render_spec
    from selfsup.scenes.io import write_scene
    from selfsup.scenes.sampler import SamplerConfig, sample_scene

    scene = render_spec(sample_scene(5, SamplerConfig(height=24, width=32, n_lights_probs=(0.0, 1.0))), samples=1).scene
    scene.meta["id"] = "probe"
    write_scene(tmp_path / "probe.npz", scene)
    lights = [{"position": p.tolist(), "intensity": (i * f).tolist(), "position_cov": torch.eye(3).tolist()}
              for p, i, f in zip(scene.light_pos, scene.light_intensity, (1.1, 0.8))]
    (tmp_path / "lights.jsonl").write_text(json.dumps({"id": "probe", "lights": lights, "seconds": 0.1}) + "\n")
    (row,) = score(tmp_path, tmp_path / "lights.jsonl")
    assert row["found"] == row["true"] == 2 and max(row["position"]) == 0.0
    assert sorted(row["intensity"]) == [0.1, 0.2]
