"""The CNN, its self-supervised loss and the training framework (issue 4)."""

import json
import os
import shutil
import subprocess

import pytest
import torch
from hydra import compose, initialize_config_dir

from render import GBuffer, Material, PointLights, ShadowedBlinnPhong, light_transport, render
from selfsup.checkpoint import load_checkpoint
from selfsup.checkpoint import load_network
from selfsup.linear import solve_intensities
from selfsup.losses import LossOptions, hypothesis_costs, reconstruction_loss, scene_batch
from selfsup.model import LightNet, scene_frame
from selfsup.scenes.dataset import ProceduralScenes, materialise, sampler_config
from tests.test_readme import ROOT
from train import build_trainer, run

TINY = sampler_config(height=24, width=32, n_lights_probs=[0.5, 0.5])


@pytest.fixture(scope="module")
def pool():
    return materialise(ProceduralScenes(TINY, length=8, base_seed=5, samples=1))


def _cfg(*overrides):
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "configs")):
        return compose(config_name="train", overrides=list(overrides))


def _smoke(tmp_path, *overrides):
    return _cfg("experiment=smoke", f"trainer.out_dir={tmp_path}", "logger.tensorboard=false", *overrides)


def test_network_is_small_counts_and_predicts_every_slot_without_an_albedo(pool):
    network = LightNet(max_lights=3)
    assert sum(p.numel() for p in network.parameters()) <= 10_000_000
    scenes = scene_batch(pool)
    prediction = network(scenes.image, scenes.gbuffer)  # colour and depth alone
    assert prediction.position.shape == (8, 3, 3) and prediction.intensity.shape == (8, 3, 3)
    assert prediction.presence.shape == (8, 3) and prediction.ambient.shape == (8, 3)
    assert prediction.count_logits.shape == (8, 3) and prediction.anchor_logits.shape == (8, 3, 216)
    assert prediction.anchor_position.shape == (8, 3, 216, 3)
    assert torch.isfinite(prediction.position).all() and (prediction.intensity > 0).all()
    assert ((prediction.count >= 1) & (prediction.count <= 3)).all()
    # presence is P(more lights than the slots before): 1, then falling
    assert (prediction.presence[:, 0] == 1).all() and (prediction.presence.diff(dim=1) <= 1e-6).all()
    assert prediction.lights_of(0)[0].shape[0] == int(prediction.count[0])
    # an albedo, where a caller has one, reaches only the cost volumes: the same shapes
    assert network(scenes.image, scenes.gbuffer, scenes.material.kd).position.shape == (8, 3, 3)


def test_count_threshold_calibration_keeps_a_head_from_adding_lights_it_cannot_tell():
    from selfsup.evaluate import calibrate_count_threshold, evaluate_network

    one_light = materialise(ProceduralScenes(sampler_config(height=24, width=32, n_lights_probs=[1.0]), length=6,
                                             base_seed=3, samples=1))
    network = LightNet(max_lights=3)
    with torch.no_grad():  # a head sure of three lights: presence 1, 0.955, 0.91
        network.count_out[-1].weight.zero_()
        network.count_out[-1].bias.copy_(torch.tensor([0.0, 0.0, 3.0]))
    assert all(r["lights_found"] == 3 for r in evaluate_network(network, one_light))
    network.count_threshold, rows = calibrate_count_threshold(network, one_light)
    assert network.count_threshold == 0.99  # the lowest that counts one light
    assert all(r["lights_found"] == 1 and r["count_right"] for r in evaluate_network(network, one_light))
    assert rows == evaluate_network(network, one_light)  # the rows under it, from the same pass
    with pytest.raises(ValueError, match="count_threshold"):
        LightNet(count_threshold=0.0)


def _bumpy_floor(H: int = 48, W: int = 64) -> GBuffer:
    K = torch.tensor([[[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]]])
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    depth = (3.0 - 0.02 * v + 0.2 * torch.sin(u / 7.0) * torch.cos(v / 5.0))[None].float()
    return GBuffer.from_depth(depth, K)


def test_second_slot_finds_the_light_the_first_leaves():
    # Two lights over a bumpy floor, rendered diffuse and unshadowed (the cost volumes'
    # model): slot 1's volume, on what slot 0 leaves, holds the other light near its best.
    H, W = 48, 64
    g = _bumpy_floor(H, W)
    lights = torch.tensor([[[0.8, -0.8, 2.2], [-0.9, -0.6, 3.0]]])
    image = render(g, Material(kd=torch.full((1, H, W, 3), 0.6)),
                   PointLights(position=lights, intensity=torch.tensor([[[4.0] * 3, [2.5] * 3]])),
                   torch.full((1, 3), 0.02), shadows="none").image
    with torch.no_grad():
        prediction = LightNet(max_lights=2).eval()(image, g)
    size = float(scene_frame(image, g).size[0])
    error = torch.cdist(prediction.position[0], lights[0]) / size  # (slots, lights)
    assert float(error.amin(1).max()) < 0.05 and set(error.argmin(1).tolist()) == {0, 1}, error


def test_each_cascade_level_brings_the_cost_volume_closer_to_an_exact_light():
    # A bumpy floor lit by one light, rendered diffuse and unshadowed: exactly the cost
    # volume's model, so each level (a quarter of the last step) must land closer.
    H, W = 48, 64
    g = _bumpy_floor(H, W)
    kd = torch.full((1, H, W, 3), 0.6)
    light = torch.tensor([[[0.4, -0.8, 2.2]]])
    image = render(g, Material(kd=kd), PointLights(position=light, intensity=torch.full((1, 1, 3), 4.0)),
                   torch.full((1, 3), 0.02), shadows="none").image
    frame = scene_frame(image, g)
    truth = (light[0] - frame.centre) / frame.size[:, None]  # normalised, (1, 3)
    errors = []
    for levels in (1, 2, 3):
        network = LightNet(cascade_levels=levels).eval()
        start = network.anchors[(network.anchors - truth).norm(dim=-1).argmin()][None]
        found = network.refine_anchor(start, network._evidence_pixels(image, g, kd), frame)
        errors.append(float((found - truth).norm()))
    assert errors[1] < errors[0] and errors[2] <= errors[1] + 1e-4, errors
    assert errors[1] < LightNet(cascade_levels=2).finest_step, errors
    with pytest.raises(ValueError, match="cascade_levels"):
        LightNet(cascade_levels=0)


def test_network_output_follows_scene_scale_and_exposure(pool):
    # Inputs are normalised: scaling the scene by 3 scales positions by 3 about the
    # camera, and doubling the exposure doubles intensities (inverse square: x 9 for size).
    network = LightNet(max_lights=2).eval()
    scenes = scene_batch(pool)
    g = scenes.gbuffer
    with torch.no_grad():
        base = network(scenes.image, g)
        scaled = network(2 * scenes.image, GBuffer(3 * g.points, g.normals, g.mask))
    # float32 cost volumes of points 3x apart: positions agree to a few 1e-4 of their size
    torch.testing.assert_close(scaled.position, 3 * base.position, rtol=1e-3, atol=2e-3)
    torch.testing.assert_close(scaled.intensity, 18 * base.intensity, rtol=1e-3, atol=1e-6)


def test_hypothesis_costs_match_an_explicit_least_squares_fit(pool):
    scenes = scene_batch({k: v.double() if v.is_floating_point() else v for k, v in pool.items()})
    centre = scene_frame(scenes.image, scenes.gbuffer).centre
    generator = torch.Generator().manual_seed(0)
    hypotheses = centre[:, None] + torch.randn(8, 5, 3, generator=generator, dtype=torch.float64)
    hypotheses[:, :, 1] -= 1.0  # mostly above the scene: the fitted intensities are positive
    fast = hypothesis_costs(hypotheses, scenes, scene_frame(scenes.image, scenes.gbuffer).exposure, "inverse_square",
                            stride=1)
    g, m, image = scenes.gbuffer, scenes.material, scenes.image
    mask = g.mask[:, None].double().expand_as(image)
    exposure = scene_frame(image, g).exposure
    for j in range(5):
        diffuse = light_transport(g, Material(kd=m.kd), hypotheses[:, j:j + 1], shadows="none", specular=False).diffuse
        cols = m.kd.permute(0, 3, 1, 2)[:, :, None] * diffuse[:, None]
        intensity, ambient, model = solve_intensities(cols, m.kd, image, mask, ridge=1e-12)
        explicit = (((model - image) * mask) ** 2).sum((1, 2, 3)) / mask.sum((1, 2, 3)) / exposure**2
        unconstrained = (intensity > 0).all(-1).all(-1) & (ambient > 0).all(-1)
        torch.testing.assert_close(fast[unconstrained, j], explicit[unconstrained], rtol=1e-6, atol=1e-9)
        assert bool((fast[:, j] <= explicit * (1 + 1e-6) + 1e-9).all())  # non-negative optimum: never worse


def test_hypothesis_costs_by_chunks_of_images_equal_one_pass_and_carry_gradients(pool, monkeypatch):
    import selfsup.linear

    scenes = scene_batch({k: v.double() if v.is_floating_point() else v for k, v in pool.items()})
    exposure = scene_frame(scenes.image, scenes.gbuffer).exposure
    hypotheses = scene_frame(scenes.image, scenes.gbuffer).centre[:, None] + torch.randn(
        8, 5, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    monkeypatch.setattr(selfsup.linear, "_COST_ELEMENTS_CPU", 1 << 30)  # every image in one pass
    whole = hypothesis_costs(hypotheses, scenes, exposure, "inverse_square", stride=2)
    monkeypatch.setattr(selfsup.linear, "_COST_ELEMENTS_CPU", 1)  # one image per pass
    position = hypotheses.clone().requires_grad_(True)
    chunked = hypothesis_costs(position, scenes, exposure, "inverse_square", stride=2, robust_scale=0.1)
    chunked.sum().backward()
    torch.testing.assert_close(hypothesis_costs(hypotheses, scenes, exposure, "inverse_square", stride=2), whole)
    assert torch.isfinite(position.grad).all() and position.grad.abs().sum() > 0


def test_loss_reads_no_ground_truth_unless_the_ablation_switch_is_on(pool):
    scenes = scene_batch(pool)
    network = LightNet(max_lights=2)
    prediction = network(scenes.image, scenes.gbuffer)
    renderer = ShadowedBlinnPhong(check_finite=False)
    garbage = dict(pool, light_pos=torch.randn_like(pool["light_pos"]) * 50,
                   light_intensity=torch.rand_like(pool["light_intensity"]))
    self_supervised = LossOptions()
    a = reconstruction_loss(prediction, scenes, renderer, self_supervised, pool).total
    b = reconstruction_loss(prediction, scenes, renderer, self_supervised, garbage).total
    c = reconstruction_loss(prediction, scenes, renderer, self_supervised, None).total
    assert a.item() == b.item() == c.item()
    ablation = LossOptions(supervised_weight=1.0)
    assert reconstruction_loss(prediction, scenes, renderer, ablation, pool).total.item() != \
        reconstruction_loss(prediction, scenes, renderer, ablation, garbage).total.item()
    with pytest.raises(ValueError, match="ground-truth"):
        reconstruction_loss(prediction, scenes, renderer, ablation, None)
    counted = LossOptions(count_weight=1.0)  # the auxiliary count reads the true count, nothing else
    truth = reconstruction_loss(prediction, scenes, renderer, counted, pool).total.item()
    assert reconstruction_loss(prediction, scenes, renderer, counted,
                               dict(garbage, light_mask=pool["light_mask"])).total.item() == truth
    one_light = torch.zeros_like(pool["light_mask"])
    one_light[:, 0] = True
    assert reconstruction_loss(prediction, scenes, renderer, counted, dict(pool, light_mask=one_light)).total.item() != truth
    with pytest.raises(ValueError, match="true light count"):
        reconstruction_loss(prediction, scenes, renderer, counted, None)


def test_loss_gradient_reaches_every_trained_head(pool):
    scenes = scene_batch(pool)
    network = LightNet(max_lights=2)
    prediction = network(scenes.image, scenes.gbuffer)
    reconstruction_loss(prediction, scenes, ShadowedBlinnPhong(check_finite=False), LossOptions(count_weight=1.0),
                        pool).total.backward()
    for name in ("slot_out.weight", "anchor_out.weight", "count_out.0.weight", "ambient_out.weight",
                 "backbone.0.0.weight", "slot_embedding"):
        grad = dict(network.named_parameters())[name].grad
        assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0, name


@pytest.mark.parametrize("experiment", sorted(p.stem for p in (ROOT / "configs" / "experiment").glob("*.yaml")))
def test_every_experiment_builds_a_trainer(experiment):
    # What the configs' comments and messages point users to must compose and build.
    trainer = build_trainer(_cfg(f"experiment={experiment}", "trainer.out_dir=x"))
    assert trainer.options.max_steps > 0 and trainer.options.batch_size > 0


def test_config_composes_every_group_and_overrides():
    cfg = _cfg()
    assert cfg.mode == "train"
    for group in ("data", "model", "renderer", "optim", "trainer", "logger", "loss", "eval"):
        assert group in cfg, group
    assert cfg.model.falloff == cfg.renderer.falloff == "inverse_square"
    cfg = _cfg("experiment=smoke", "optim.lr=1e-4", "model.hidden=64", "trainer.out_dir=x")
    assert cfg.trainer.max_steps == 4 and cfg.optim.lr == 1e-4 and cfg.loss.supervised_weight == 0
    trainer = build_trainer(cfg)
    assert trainer.model_config["hidden"] == 64 and trainer.sampler.height == 24
    with pytest.raises(ValueError, match="max_lights=1"):
        build_trainer(_cfg("experiment=smoke", "model.max_lights=1", "trainer.out_dir=x"))
    with pytest.raises(ValueError, match="unknown mode 'fly'"):
        run(_cfg("mode=fly"))
    # Each named before any scene is rendered (several died deep in the first step: step % 0,
    # a zero division, an amin over no anchors).
    for bad in ("trainer.max_minutes=-3", "trainer.threads=-1", "trainer.batch_size=0", "logger.log_every=0",
                "logger.images=-2", "model.input_size=0", "model.hidden=0", "model.anchors_per_axis=0",
                "model.anchor_extent=-1", "model.evidence_points=0", "model.cascade_levels=0"):
        with pytest.raises(ValueError, match=bad.split("=")[0].split(".")[1]):
            build_trainer(_cfg("experiment=smoke", bad, "trainer.out_dir=x"))


def test_a_few_training_steps_lower_the_loss_on_a_tiny_set(tmp_path, pool):
    cfg = _smoke(tmp_path, "data.pool.train_scenes=8", "trainer.batch_size=8", "trainer.max_steps=25",
                 "trainer.val_every=25", "optim.lr=3e-3", "optim.warmup=0.2")
    trainer = build_trainer(cfg)
    scenes = scene_batch(trainer._pool(0, "train"))

    def loss_of(network):
        with torch.no_grad():
            return reconstruction_loss(network(scenes.image, scenes.gbuffer), scenes,
                                       trainer.renderer, trainer.loss).total.item()

    torch.manual_seed(cfg.seed)
    before = loss_of(LightNet(**trainer.model_config))
    result = trainer.fit()
    after = loss_of(load_network(result["last"])[0].train())
    assert result["step"] == 25 and after < 0.8 * before


def test_a_capture_like_batch_trains_without_an_albedo(tmp_path):
    # The captures recipe in miniature: a drawn camera, indirect light, 1-3 lights, the
    # auxiliary count; its steps run and its checkpoint loads safely.
    result = run(_smoke(tmp_path, "experiment=captures", "data.pool.height=24", "data.pool.width=32",
                        "data.pool.train_scenes=8", "data.pool.val_scenes=4", "data.pool.workers=0",
                        "trainer.max_steps=2", "trainer.batch_size=4", "trainer.val_every=2", "trainer.max_minutes=0",
                        "trainer.progress=false", "data.pool.teacher_scenes=2", "data.pool.teacher_scale=1",
                        f"data.pool.teacher_cache={tmp_path / 'teacher'}"))
    assert result["step"] == 2 and result["validation"]["scenes"] == 4
    assert len(list((tmp_path / "teacher").glob("teacher_*.jsonl"))) == 1  # the recipe's teacher searched
    network, state = load_network(result["last"])
    assert network.max_lights == 3 and state["model_config"]["offset_steps"] == 0.25


def test_stop_step_ends_a_run_on_the_full_runs_schedule(tmp_path):
    # Stopped at step 2 of 4, the state is the full run's there: resumed, it ends where a
    # straight run ends.
    stopped = run(_smoke(tmp_path / "a", "trainer.stop_step=2"))
    assert stopped["step"] == 2 and not stopped["stopped_by_time"]
    assert load_checkpoint(stopped["last"])["scheduler"]["total_steps"] == 4
    resumed, straight = run(_smoke(tmp_path / "a")), run(_smoke(tmp_path / "b"))
    assert resumed["step"] == straight["step"] == 4
    a, b = load_checkpoint(resumed["last"]), load_checkpoint(straight["last"])
    for key in a["model"]:
        assert torch.equal(a["model"][key], b["model"][key]), key


def test_resume_continues_exactly_where_the_run_stopped(tmp_path):
    straight = run(_smoke(tmp_path / "a"))
    # Stop after the first step (the time cap), then resume to the end.
    stopped = run(_smoke(tmp_path / "b", "trainer.max_minutes=1e-9"))
    assert stopped["step"] == 1
    resumed = run(_smoke(tmp_path / "b"))
    assert resumed["step"] == 4
    a, b = load_checkpoint(straight["last"]), load_checkpoint(resumed["last"])  # resume checkpoints load safely
    for key in a["model"]:
        assert torch.equal(a["model"][key], b["model"][key]), key
    assert a["optimizer"]["state"][0]["step"] == b["optimizer"]["state"][0]["step"]
    assert json.loads((tmp_path / "b" / "result.json").read_text())["step"] == 4


def test_tensorboard_gets_scalars_and_image_grids(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run(_cfg("experiment=smoke", f"trainer.out_dir={tmp_path}"))
    events = EventAccumulator(str(tmp_path / "tensorboard"))
    events.Reload()
    tags = events.Tags()
    for tag in ("train/total", "train/lr", "train/scenes_per_second", "val/median_position_error",
                "val/success_rate"):
        assert tag in tags["scalars"], tag
    assert "val/input|render|residual|shadow" in tags["images"]


def test_ddp_smoke_run_with_two_gloo_processes(tmp_path):
    if shutil.which("torchrun") is None:
        pytest.skip("torchrun not on PATH")
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    command = ["torchrun", "--standalone", "--nproc_per_node=2", str(ROOT / "train.py"), "experiment=smoke",
               f"trainer.out_dir={tmp_path}", "trainer.device=cpu", "logger.tensorboard=false",
               f"hydra.run.dir={tmp_path}/hydra"]
    done = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads((tmp_path / "result.json").read_text())
    assert result["step"] == 4 and result["validation"]["scenes"] == 8


def test_shipped_checkpoint_loads_small_and_within_budget():
    from selfsup.checkpoint import DEFAULT_CHECKPOINT

    if not DEFAULT_CHECKPOINT.is_file():
        pytest.fail(f"the shipped checkpoint {DEFAULT_CHECKPOINT} is missing")
    assert DEFAULT_CHECKPOINT.stat().st_size <= 40 * 2**20  # issue 62: at most 40 MB, 10 M parameters
    network, state = load_network()
    assert sum(p.numel() for p in network.parameters()) <= 10_000_000
    # Its provenance: experiment=captures stopped at step 5000, validated on 300 capture-like scenes.
    assert state["step"] == 5000 and state["metrics"]["scenes"] == 300 and "experiment=captures" in state["recipe"]
    assert state["model_config"]["max_lights"] == 3


def test_missing_checkpoint_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        load_network(tmp_path / "nope.pt")
    torch.save({"weights": 1}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="not a LightNet checkpoint"):
        load_network(tmp_path / "bad.pt")


def test_exposure_is_the_99th_percentile_of_valid_pixels():
    generator = torch.Generator().manual_seed(1)
    image = torch.rand(2, 3, 20, 30, generator=generator)
    depth = torch.rand(2, 20, 30, generator=generator) + 1
    depth[0, :5] = 0  # invalid pixels must not count
    K = torch.tensor([[20.0, 0, 15], [0, 20.0, 10], [0, 0, 1]]).expand(2, 3, 3)
    g = GBuffer.from_depth(depth, K)
    brightest = image.amax(1).flatten(1)
    expected = torch.nanquantile(torch.where(g.mask.flatten(1), brightest, torch.nan), 0.99, dim=1)
    torch.testing.assert_close(scene_frame(image, g).exposure, expected, rtol=0, atol=0)
