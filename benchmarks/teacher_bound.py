"""Where a taught network's lights are lost: the teacher, the slot's hypothesis, its cascade.

On the first scenes of a training recipe's pool (the frames the per-frame search taught,
``data.pool.teacher_scenes``; the answers read from the recipe's teacher cache, never
searched here), one-light rooms only, each row says how often a light lands within 0.05 of
the scene size of the true one:

- ``teacher``: the search's own answer (its brightest light), the best the network could
  learn from it;
- ``network`` and ``cost volume alone`` (the learned scores and offsets zeroed): slot 0 of a
  checkpoint, and how often its chosen hypothesis is the one nearest the teacher's light;
- ``oracle hypothesis + cascade``: the hypothesis nearest the teacher's (or the true) light
  handed to the slot's cascade of grey-albedo, unshadowed cost volumes
  (:meth:`selfsup.model.LightNet.refine_anchor`) without the learned offset: what the
  network's design reaches where its classification is perfect.

    python -m benchmarks.teacher_bound --checkpoint outputs/captures_teacher/last.pt [more checkpoints]

Results: benchmarks/results/teacher_bound_<device>_<date>.{md,json}.
"""

from __future__ import annotations

import argparse

import torch

from benchmarks.cnn_eval import cost_volume_only
from benchmarks.common import write_results
from selfsup.checkpoint import load_network
from selfsup.losses import scene_batch
from selfsup.model import SceneFrame, scene_frame
from selfsup.scenes.dataset import ProceduralScenes, materialise
from selfsup.metrics import SUCCESS_THRESHOLD

COLUMNS = ["row", "rooms", "within_0.05_of_truth", "median_error", "within_0.05_of_teacher", "hypothesis_is_teachers"]


def _recipe(experiment: str):
    from hydra import compose, initialize_config_dir

    from train import CONFIGS, build_trainer

    with initialize_config_dir(version_base="1.3", config_dir=str(CONFIGS)):
        cfg = compose(config_name="train", overrides=[f"experiment={experiment}", "trainer.out_dir=/tmp/unused"])
    return build_trainer(cfg)


def _answers(trainer) -> dict[int, list]:
    from selfsup.teacher import read_answers, teacher_cache_path

    p = trainer.pool_options
    cache = teacher_cache_path(p.teacher_cache, trainer.sampler, trainer.degradations, trainer.samples, p.train_seed,
                               p.teacher_scale, p.teacher_method)
    if not cache.exists():
        raise FileNotFoundError(f"no teacher cache {cache}: train the recipe first (it searches its pool once)")
    return read_answers(cache)


def _row(name: str, position: torch.Tensor, truth: torch.Tensor, scale: torch.Tensor, teacher: torch.Tensor,
         chosen_is_teachers: torch.Tensor | None = None) -> dict:
    error = (position - truth).norm(dim=-1) / scale
    row = {"row": name, "rooms": len(error), "within_0.05_of_truth": round(float((error < SUCCESS_THRESHOLD).float().mean()), 3),
           "median_error": round(float(error.median()), 4),
           "within_0.05_of_teacher": round(float(((position - teacher).norm(dim=-1) / scale < SUCCESS_THRESHOLD)
                                                 .float().mean()), 3)}
    if chosen_is_teachers is not None:
        row["hypothesis_is_teachers"] = round(float(chosen_is_teachers.float().mean()), 3)
    return row


@torch.no_grad()
def run(checkpoints: list[str], experiment: str = "captures_taught", scenes: int = 400, write: bool = True):
    trainer = _recipe(experiment)
    answers = _answers(trainer)
    count = min(scenes, trainer.pool_options.teacher_scenes, len(answers))
    pool = materialise(ProceduralScenes(trainer.sampler, trainer.degradations, length=count,
                                        base_seed=trainer.pool_options.train_seed, samples=trainer.samples,
                                        max_lights=trainer.model_config["max_lights"]))
    rooms = [i for i in range(count) if int(pool["light_mask"][i].sum()) == 1 and len(answers.get(i, []))]
    index = torch.tensor(rooms)
    batch = {key: value[index] for key, value in pool.items()}
    scenes_ = scene_batch(batch)
    frame = scene_frame(scenes_.image, scenes_.gbuffer)
    truth, scale = batch["light_pos"][:, 0], batch["scene_scale"]
    teacher = torch.stack([torch.tensor(answers[i], dtype=torch.float32).reshape(-1, 3)[0] for i in rooms])
    rows = [_row("teacher (the search, the frame at the teacher's scale)", teacher, truth, scale, teacher)]
    for checkpoint in checkpoints:
        network, _ = load_network(checkpoint)
        for name, model in ((f"network {checkpoint}, slot 0", network), ("its cost volume alone, slot 0", cost_volume_only(network))):
            prediction = model(scenes_.image, scenes_.gbuffer)
            hypotheses = prediction.anchor_position[:, 0]
            nearest = (hypotheses - teacher[:, None]).norm(dim=-1).argmin(1)
            rows.append(_row(name, prediction.position[:, 0], truth, scale, teacher,
                             prediction.anchor_logits[:, 0].argmax(1) == nearest))
    network, _ = load_network(checkpoints[0])
    pixels = network._evidence_pixels(scenes_.image, scenes_.gbuffer, None)
    for name, light in (("oracle hypothesis nearest the teacher's light + grey cascade", teacher),
                        ("oracle hypothesis nearest the true light + grey cascade", truth)):
        normalised = (light - frame.centre) / frame.size[:, None]
        start = network.anchors[(network.anchors[None] - normalised[:, None]).norm(dim=-1).argmin(1)]
        refined = network.refine_anchor(start, pixels, SceneFrame(frame.centre, frame.size, frame.exposure))
        rows.append(_row(name, frame.centre + frame.size[:, None] * refined, truth, scale, teacher))
    header = (f"Recipe `experiment={experiment}`: the one-light rooms among its pool's first {count} scenes "
              f"(the frames its teacher searched, {trainer.sampler.width}x{trainer.sampler.height} as the network "
              f"sees them; the teacher searched them at {trainer.pool_options.teacher_scale}x). The networks "
              "trained on these frames: their rows are in-sample. The oracle rows use the first checkpoint's "
              "hypothesis grid and cascade (physics only: no learned weight enters them).")
    path = write_results("teacher_bound", torch.device("cpu"), rows, header, COLUMNS) if write else None
    if path is not None:
        with path.open("a") as out:
            out.write(f"\nCommand: `python -m benchmarks.teacher_bound --experiment {experiment} --scenes {scenes} "
                      f"--checkpoint {' '.join(checkpoints)}`\n")
    return rows, path


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", nargs="+", required=True)
    parser.add_argument("--experiment", default="captures_taught")
    parser.add_argument("--scenes", type=int, default=400)
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args(argv)
    rows, path = run(args.checkpoint, args.experiment, args.scenes, not args.no_write)
    for row in rows:
        print(row)
    if path:
        print(path)


if __name__ == "__main__":
    main()
