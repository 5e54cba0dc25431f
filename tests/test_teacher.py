"""The per-frame search as the network's teacher on a training pool (issue 74)."""

import json

import pytest
import torch

from selfsup.engine import DataOptions
from selfsup.losses import scene_batch
from selfsup.model import scene_frame
from selfsup.scenes.dataset import ProceduralScenes, materialise, sampler_config
from selfsup.scenes.degrade import Degradations
from selfsup.teacher import pool_teacher, teacher_cache_path
from tests.test_training import _smoke
from train import build_trainer

ONE_LIGHT = sampler_config(height=24, width=32, n_lights_probs=[1.0])


def test_the_teacher_finds_the_light_of_clean_rooms_reading_no_label(tmp_path):
    # The pool's scenes at twice its grid, searched as captures (albedo withheld): the
    # rooms' one light within a tenth of the scene size. The search is handed no light.
    cache = tmp_path / "teacher.jsonl"
    position, mask, stats = pool_teacher(ONE_LIGHT, Degradations(), 1, 5, 3, 2, cache, scale=2, workers=1)
    truth = materialise(ProceduralScenes(ONE_LIGHT, length=3, base_seed=5, samples=1, max_lights=2))
    assert position.shape == (3, 2, 3) and mask.shape == (3, 2) and stats["searched"] == 3
    assert bool(mask[:, 0].all())
    error = (position[:, 0] - truth["light_pos"][:, 0]).norm(dim=-1) / truth["scene_scale"]
    assert float(error.median()) < 0.1, error


def test_the_teachers_answers_are_read_back_and_a_torn_line_is_searched_again(tmp_path):
    cache = tmp_path / "teacher.jsonl"
    first = pool_teacher(ONE_LIGHT, Degradations(), 1, 5, 2, 2, cache, scale=1, workers=1)
    lines = cache.read_text().splitlines()
    assert len(lines) == 2 and {json.loads(line)["index"] for line in lines} == {0, 1}
    again = pool_teacher(ONE_LIGHT, Degradations(), 1, 5, 2, 2, cache, scale=1, workers=1)
    assert again[2]["searched"] == 0 and torch.equal(again[0], first[0]) and torch.equal(again[1], first[1])
    cache.write_text(lines[0] + "\n" + lines[1][: len(lines[1]) // 2])  # a killed run's last line
    torn = pool_teacher(ONE_LIGHT, Degradations(), 1, 5, 2, 2, cache, scale=1, workers=1)
    assert torn[2]["searched"] == 1 and torch.allclose(torn[0], first[0])
    mended = pool_teacher(ONE_LIGHT, Degradations(), 1, 5, 2, 2, cache, scale=1, workers=1)
    assert mended[2]["searched"] == 0 and len(cache.read_text().splitlines()) == 2  # the torn line was cut off


def test_the_teacher_takes_rooms_with_more_lights_than_its_slots(tmp_path):
    # The iterative recipe's pools hold three-light rooms and two slots: the teacher searched
    # them as the trainer's pool holds them (it refused them with "more than max_lights").
    three = sampler_config(height=24, width=32, n_lights_probs=[0.0, 0.0, 1.0])
    position, mask, _ = pool_teacher(three, Degradations(), 1, 5, 1, 2, tmp_path / "teacher.jsonl", scale=1, workers=1)
    assert position.shape == (1, 2, 3) and mask.shape == (1, 2)


def test_the_cache_is_named_by_everything_that_changes_the_answers(tmp_path):
    base = teacher_cache_path(tmp_path, ONE_LIGHT, Degradations(), 1, 5, 2, "refine")
    assert base == teacher_cache_path(tmp_path, ONE_LIGHT, Degradations(), 1, 5, 2, "refine")
    changed = [teacher_cache_path(tmp_path, ONE_LIGHT, Degradations(camera=True), 1, 5, 2, "refine"),
               teacher_cache_path(tmp_path, ONE_LIGHT, Degradations(), 2, 5, 2, "refine"),
               teacher_cache_path(tmp_path, ONE_LIGHT, Degradations(), 1, 6, 2, "refine"),
               teacher_cache_path(tmp_path, ONE_LIGHT, Degradations(), 1, 5, 1, "refine"),
               teacher_cache_path(tmp_path, ONE_LIGHT, Degradations(), 1, 5, 2, "cnn+refine"),
               teacher_cache_path(tmp_path, sampler_config(height=24, width=32, n_lights_probs=[0.5, 0.5]),
                                  Degradations(), 1, 5, 2, "refine")]
    assert len({base, *changed}) == 7


def test_the_trainer_teaches_the_pools_first_scenes_and_the_teacher_moves_the_scores(tmp_path):
    cfg = _smoke(tmp_path, "data.pool.teacher_scenes=3", "data.pool.teacher_scale=1",
                 f"data.pool.teacher_cache={tmp_path / 'cache'}")
    trainer = build_trainer(cfg)
    pool = trainer._pool(0, "train")
    position, mask = trainer.teacher_search(trainer.pool_options.train_seed)  # read back from its cache
    assert torch.equal(pool["teacher_mask"][:3], mask) and torch.equal(pool["teacher_pos"][:3], position)
    assert mask.any() and not pool["teacher_mask"][3:].any()
    assert pool["teacher_pos"].shape == (*pool["light_pos"].shape,)
    from selfsup.model import LightNet
    from selfsup.losses import teacher_loss

    torch.manual_seed(0)
    network = LightNet(**trainer.model_config)
    batch = {key: value[:4] for key, value in pool.items()}
    scenes = scene_batch(batch)
    prediction = network(scenes.image, scenes.gbuffer)
    total, parts = teacher_loss(prediction, batch["teacher_pos"], batch["teacher_mask"],
                                scene_frame(scenes.image, scenes.gbuffer).size, trainer.teacher)
    total.backward()
    assert parts["teacher_anchors"] > 0 and network.anchor_out.weight.grad.abs().sum() > 0
    assert network.slot_out.weight.grad[:3].abs().sum() > 0  # the offsets follow the teacher's positions
    result = trainer.fit()  # the loop runs with the teacher's term
    assert result["step"] == 4


@pytest.mark.parametrize("bad", [dict(teacher_scenes=-1), dict(teacher_scenes=20), dict(teacher_scale=0),
                                 dict(teacher_method="cnn")])
def test_bad_teacher_settings_are_named(bad):
    with pytest.raises(ValueError, match="teacher"):
        DataOptions(train_scenes=16, **bad)


def test_a_trainer_told_to_teach_without_a_search_says_so(tmp_path):
    cfg = _smoke(tmp_path, "data.pool.teacher_scenes=3")
    trainer = build_trainer(cfg)
    with pytest.raises(ValueError, match="teacher_search"):
        type(trainer)(trainer.model_config, trainer.sampler, trainer.degradations, trainer.samples,
                      trainer.pool_options, trainer.optim, trainer.options, trainer.logger, trainer.loss,
                      trainer.renderer)


def test_a_run_may_start_from_a_checkpoints_weights_and_a_mismatch_is_named(tmp_path):
    from selfsup.checkpoint import load_checkpoint
    from train import run

    first = run(_smoke(tmp_path / "a"))
    tuned = run(_smoke(tmp_path / "b", f"trainer.init={first['last']}", "trainer.max_steps=1", "optim.lr=1e-12"))
    a, b = load_checkpoint(first["last"])["model"], load_checkpoint(tuned["last"])["model"]
    assert tuned["step"] == 1 and all(torch.allclose(a[k], b[k], atol=1e-6) for k in a)
    with pytest.raises(ValueError, match="do not fit"):
        run(_smoke(tmp_path / "c", f"trainer.init={first['last']}", "model.hidden=32"))


def test_the_search_takes_the_minimums_place_where_it_found_lights():
    from selfsup.engine import taught_minima

    minimum = torch.arange(18, dtype=torch.float32).reshape(3, 2, 3)
    needed = torch.tensor([[True, True], [True, False], [True, True]])
    searched = -torch.ones(3, 2, 3)
    found = torch.tensor([[True, True], [True, False], [False, False]])  # a pair, one light, none
    out = taught_minima({"target_pos": minimum, "target_needed": needed, "teacher_pos": searched,
                         "teacher_mask": found})
    assert torch.equal(out["target_pos"][0], searched[0]) and out["target_needed"][0].all()
    assert torch.equal(out["target_pos"][1, 0], searched[1, 0]) and torch.equal(out["target_pos"][1, 1], minimum[1, 1])
    assert out["target_needed"][1].tolist() == [True, False]  # the search's count, not the minimum's
    assert torch.equal(out["target_pos"][2], minimum[2]) and out["target_needed"][2].all()  # no light: the minimum


def test_the_taught_iterative_recipe_takes_the_searchs_lights_as_targets(tmp_path):
    # experiment=iterative_taught in miniature: the pool's rooms searched once, their lights the slots' targets.
    from tests.test_training import _cfg

    cfg = _cfg("experiment=iterative_taught", f"trainer.out_dir={tmp_path}", "logger.tensorboard=false",
               "data.pool.height=24", "data.pool.width=32", "data.pool.train_scenes=4", "data.pool.teacher_scenes=4",
               "data.pool.teacher_scale=1", f"data.pool.teacher_cache={tmp_path / 'cache'}", "data.pool.val_scenes=2",
               "data.pool.workers=0", "trainer.init=null", "trainer.progress=false", "model.long_side=32",
               "model.widths=[8,16,16]", "model.global_width=16", "model.update_width=8")
    pool = build_trainer(cfg)._pool(0, "train")
    found = pool["teacher_mask"].any(1)
    assert found.any()
    assert torch.equal(pool["target_needed"][found], pool["teacher_mask"][found])
    taught = pool["teacher_mask"]
    assert torch.equal(pool["target_pos"][taught], pool["teacher_pos"][taught])
