"""The estimator's driver: a batch of images in, each image's chosen model and every model tried out.

:func:`estimate_batch` sends each image to the fit its reflectance allows (the
image fit with the file's kd, or the albedo-free one of
:mod:`selfsup.estimation.reflectance`). The image fit runs as named stages over the
whole batch, each image judged on its own (:mod:`selfsup.estimation.criterion`):

1. :func:`first_light`: one light searched (network slots and a grid as starts),
   with and without the specular term;
2. :func:`try_coat`: the same with a clear coat on the specular pixels;
3. :func:`grow`: more lights while each pays for itself;
4. :func:`drop_each`: a chosen model of several lights refitted without each light;
5. :func:`flip_coat`: a chosen model of several lights refitted with the other coat;
6. :func:`polish`: the chosen model refined at full resolution.

Candidates are fitted on all pyramid levels but the finest; only the chosen one
descends to it (the finest level costs as much as all the others together).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from render import Material
from selfsup.estimation.criterion import (Candidate, by_model, candidates, fit_row, judged_problem, light_shares,
                                          shadow_gain, specular_images)
from selfsup.estimation.gains import segment_gains
from selfsup.estimation.network import (answer_checkpoints, network_answer, network_candidates, network_slots,
                                        start_checkpoint)
from selfsup.estimation.normals import surface_segments
from selfsup.estimation.options import EstimateOptions, RefineOptions
from selfsup.estimation.prepare import in_file_units, prepare, within_pixels, working_range
from selfsup.estimation.problem import Fit, FitProblem
from selfsup.estimation.records import records
from selfsup.estimation.reflectance import albedo_free_images, albedo_free_segments, estimate_albedo_free
from selfsup.estimation.solvers import refine, search
from selfsup.scenes.io import Scene

__all__ = ["estimate_scene", "estimate_batch", "Selection", "first_light", "try_coat", "grow", "drop_each",
           "flip_coat", "polish", "with_coat"]

Result = tuple[Candidate, list[Candidate]]  # an image's chosen model and every model tried


def with_coat(material: Material, on: list[bool]) -> Material:
    """``material`` with a clear coat on the ks > 0 pixels of the images where ``on``, none elsewhere."""
    if not any(on):
        return dataclasses.replace(material, coat=None)
    chosen = torch.tensor(on, dtype=material.kd.dtype, device=material.kd.device)
    coat = (material.ks.amax(-1, keepdim=True) > 0).to(material.kd.dtype) * chosen[:, None, None, None]
    return dataclasses.replace(material, coat=coat)


@dataclass
class Selection:
    """A batch's model selection in progress, the state the stages pass along.

    ``problem``: the batch (its material carries the coats chosen so far);
    ``searched``: the same under the search's shadow method; ``coarse``: the
    candidates' optimiser settings (every pyramid level but the finest); ``slots``:
    the network's light slots ``(B, K, 3)`` (None for ``method=refine``);
    ``specular_of`` / ``coat_of``: each image's ks > 0 and chosen coat; ``best`` /
    ``tried``: each image's chosen candidate and every one tried.
    """

    problem: FitProblem
    options: EstimateOptions
    searched: FitProblem
    coarse: RefineOptions
    slots: Tensor | None
    specular_of: list[bool]
    coat_of: list[bool]
    best: list[Candidate] = dataclasses.field(default_factory=list)
    tried: list[list[Candidate]] = dataclasses.field(default_factory=list)

    @property
    def everyone(self) -> list[int]:
        return list(range(self.problem.batch))

    @property
    def shiny(self) -> list[int]:
        return [i for i in self.everyone if self.specular_of[i]]

    def index(self, images: list[int]) -> Tensor:
        return torch.tensor(images, dtype=torch.long, device=self.problem.image.device)

    def starts(self, images: list[int]) -> dict:
        """The network's slots of ``images`` and the grid beside them, as a search's starts."""
        if self.slots is None:
            return {}
        tuning = self.options.tuning
        return dict(extra_starts=self.slots[self.index(images)], per_axis=tuning.cnn_grid, starts=tuning.cnn_starts)

    def search_again(self) -> None:
        """``searched`` after the problem's material changed."""
        shadows = self.options.tuning.search_shadows
        self.searched = self.problem if shadows == self.options.shadows else self.problem.with_shadows(shadows)

    def polished(self, images: list[int], fit: Fit, n_lights: int, specular: bool, labels: list[bool]):
        """The search's answer refined and judged under the final shadow model: its
        candidates, the problem of ``images`` and the fit. ``specular`` is the term
        computed, ``labels`` each image's switch (equal where ks > 0)."""
        sub = self.problem.select(self.index(images))
        if self.searched is not self.problem:
            fit = refine(sub, fit.position, replace(self.coarse, specular=specular))
        return candidates(sub, fit, n_lights, labels, self.options), sub, fit

    def refit(self, images: list[int], problem: FitProblem, position: Tensor, n_lights: int, specular: bool
              ) -> list[Candidate]:
        """Candidates of ``images`` refitted on ``problem`` (already selected) from ``position``."""
        fit = refine(problem, position, replace(self.coarse, specular=specular))
        return candidates(problem, fit, n_lights, [specular] * len(images), self.options)

    def positions(self, images: list[int]) -> Tensor:
        """The chosen lights' positions ``(len(images), L, 3)`` (one light count)."""
        return torch.cat([self.best[i].fit.position for i in images])


def first_light(run: Selection) -> None:
    """One light searched for every image (with the specular term wherever any image has
    ks), then, for the images with ks, the same light refined without it."""
    everyone, any_specular = run.everyone, any(run.specular_of)
    # Where ks is zero the specular term adds nothing: one search serves the whole batch.
    first = search(run.searched, 1, replace(run.coarse, specular=any_specular), **run.starts(everyone))
    run.tried = [[c] for c in run.polished(everyone, first, 1, any_specular, run.specular_of)[0]]
    shiny = run.shiny
    if shiny:
        at = run.index(shiny)
        unspecular = refine(run.searched.select(at), first.position[at], replace(run.coarse, specular=False))
        for i, c in zip(shiny, run.polished(shiny, unspecular, 1, False, [False] * len(shiny))[0]):
            run.tried[i].append(c)
    run.best = [min(t, key=lambda c: c.criterion) for t in run.tried]


def try_coat(run: Selection) -> None:
    """``coat=always``: every candidate of an image with ks wears the coat. ``auto``: the
    one-light model again with a coat on the specular pixels, from the bare fit's light;
    every later model of the images where it wins keeps the coat."""
    coat = run.options.tuning.coat
    if coat == "always":
        run.best = [replace(c, coat=run.coat_of[i]) for i, c in enumerate(run.best)]
        run.tried = [[replace(c, coat=run.coat_of[i]) for c in t] for i, t in enumerate(run.tried)]
        return
    shiny = run.shiny
    if coat != "auto" or not shiny:
        return
    trial = run.problem.with_material(with_coat(run.problem.material, [i in shiny for i in run.everyone]))
    for specular in (False, True):
        group = [i for i in shiny if run.best[i].specular == specular]
        if not group:
            continue
        for i, c in zip(group, run.refit(group, trial.select(run.index(group)), run.positions(group), 1, specular)):
            c = replace(c, coat=True)
            run.tried[i].append(c)
            if c.criterion < run.best[i].criterion:
                run.best[i] = c
                run.coat_of[i] = True
    if any(run.coat_of):
        run.problem.material = with_coat(run.problem.material, run.coat_of)
        run.search_again()


def _keeps(run: Selection, i: int, c: Candidate, pays: bool, share: float, gain: float) -> bool:
    # Whether image i takes candidate c of one more light. A light that does not pay for
    # itself: more would not either. A weak one needs more evidence: its own cast shadows
    # in the image, or paying for its parameters weak_light_penalty times.
    tuning = run.options.tuning
    shown = gain >= tuning.weak_light_shadow_gain
    extra = (tuning.weak_light_penalty - 1) * 6 * math.log(c.samples)  # 6: its position and intensity
    strong = (tuning.weak_light_penalty > 0 and share >= tuning.weak_light_min_share
              and c.criterion + extra < run.best[i].criterion)
    return pays and (share >= tuning.min_light_share or shown or strong)


def grow(run: Selection) -> None:
    """Lights added one at a time (2 .. ``max_lights``), searched beside the chosen ones,
    while each added light pays for itself (:func:`_keeps`)."""
    tuning = run.options.tuning
    growing = run.everyone
    for n_lights in range(2, run.options.max_lights + 1):
        still = []
        for specular in (False, True):
            group = [i for i in growing if run.best[i].specular == specular]
            if not group:
                continue
            more = search(run.searched.select(run.index(group)), n_lights, replace(run.coarse, specular=specular),
                          fixed=run.positions(group), **run.starts(group))
            found, sub, fit = run.polished(group, more, n_lights, specular, [specular] * len(group))
            per_light = light_shares(sub, fit, specular)
            shares = per_light.amin(-1).tolist()
            pays = [c.criterion < run.best[i].criterion for i, c in zip(group, found)]
            weak = [j for j, (p, share) in enumerate(zip(pays, shares))
                    if p and tuning.weak_light_min_share <= share < tuning.min_light_share]
            gains = {}
            if weak and tuning.weak_light_shadow_gain > 0:
                at = run.index(weak)
                gains = dict(zip(weak, shadow_gain(sub.select(at), fit.position[at], per_light[at].argmin(-1),
                                                   specular, tuning.refine).tolist()))
            for j, (i, c, share) in enumerate(zip(group, found, shares)):
                c = replace(c, coat=run.coat_of[i])
                run.tried[i].append(c)
                if _keeps(run, i, c, pays[j], share, gains.get(j, -math.inf)):
                    run.best[i] = c
                    still.append(i)
        growing = sorted(still)


def drop_each(run: Selection) -> None:
    """A chosen model of several lights refitted without each of its lights in turn, from
    the others' positions: the fit of fewer lights can stop where the criterion (which
    sees cast shadows) judges it poorly, and a light then pays for itself against that
    stop alone. The criterion alone decides: fewer lights need no extra evidence."""
    for (n_lights, specular), group in by_model(run.best).items():
        if n_lights < 2:
            continue
        positions = run.positions(group)  # (G, n, 3)
        rest = torch.cat([torch.cat([positions[:, :k], positions[:, k + 1:]], 1) for k in range(n_lights)])
        images = group * n_lights  # light k dropped from every image of the group, then k + 1
        for i, c in zip(images, run.refit(images, run.problem.select(run.index(images)), rest, n_lights - 1,
                                          specular)):
            c = replace(c, coat=run.coat_of[i])
            run.tried[i].append(c)
            if c.criterion < run.best[i].criterion:
                run.best[i] = c


def flip_coat(run: Selection) -> None:
    """``coat=auto``: a two-light scene's one-light fit chooses the coat unreliably (the
    missing light weighs more than the coat): its chosen model is refitted with the other
    setting from its own lights, and the better of the two kept."""
    shiny = run.shiny
    if run.options.tuning.coat != "auto" or not shiny:
        return
    flipped = [i for i in shiny if run.best[i].n_lights > 1]
    trial = run.problem.with_material(
        with_coat(run.problem.material, [i in flipped and not run.coat_of[i] for i in run.everyone]))
    for (n_lights, specular), group in by_model([run.best[i] for i in flipped]).items():
        images = [flipped[j] for j in group]
        for i, c in zip(images, run.refit(images, trial.select(run.index(images)), run.positions(images), n_lights,
                                          specular)):
            c = replace(c, coat=not run.coat_of[i])
            run.tried[i].append(c)
            if c.criterion < run.best[i].criterion:
                run.best[i] = c
                run.coat_of[i] = c.coat
    run.problem.material = with_coat(run.problem.material, run.coat_of)


def polish(run: Selection) -> None:
    """The chosen models refined at full resolution with the final robust scale; each
    keeps the criterion it was chosen by."""
    tuning = run.options.tuning
    if len(tuning.refine.strides) == 1 and tuning.final_robust_scale == tuning.refine.robust_scale:
        return
    for (n_lights, specular), group in by_model(run.best).items():
        finest = replace(tuning.refine, specular=specular, strides=tuning.refine.strides[-1:],
                         max_iters=tuning.refine.max_iters[-1:], robust_scale=tuning.final_robust_scale)
        fit = refine(run.problem.select(run.index(group)), run.positions(group), finest)
        for j, i in enumerate(group):
            run.best[i] = replace(run.best[i], fit=fit_row(fit, j))


STAGES = (first_light, try_coat, grow, drop_each, flip_coat, polish)


def _start(problem: FitProblem, options: EstimateOptions) -> Selection:
    # The selection's state before the first stage: scales found once, coats set, the
    # network's slots, the candidates' (coarse) optimiser settings.
    tuning = options.tuning
    if tuning.refine.robust:
        problem.median_observed()  # the robust scale, found once: every selection below keeps its rows
        problem.noise_level()  # and the scale's floor, likewise
        judged_problem(problem, options)  # and the criterion's subsample's, likewise
    specular_of = specular_images(problem).tolist()
    coat_of = [tuning.coat == "always" and spec for spec in specular_of]  # auto adds the images the coat wins
    if any(coat_of) or problem.material.coat is not None:
        # Exactly these coats: a pass of reflectance_gains starts bare of the coats the last one chose.
        problem.material = with_coat(problem.material, coat_of)
    levels = len(tuning.refine.strides)
    coarse = replace(tuning.refine, strides=tuning.refine.strides[: max(levels - 1, 1)],
                     max_iters=tuning.refine.max_iters[: max(levels - 1, 1)])
    run = Selection(problem, options, problem, coarse, None, specular_of, coat_of)
    run.search_again()
    return run


def _estimate_once(problem: FitProblem, options: EstimateOptions) -> list[Result]:
    # The image fit with the problem's reflectance: the stages in turn, or the network alone.
    run = _start(problem, options)
    if options.method == "cnn":
        run.slots, count = network_answer(problem, options)
        return [(replace(best, coat=run.coat_of[i]), [replace(c, coat=run.coat_of[i]) for c in tried])
                for i, (best, tried) in enumerate(network_candidates(problem, run.slots, count,
                                                                     run.specular_of, options))]
    if options.method != "refine":
        run.slots, _ = network_slots(problem, start_checkpoint(options))
    for stage in STAGES:
        stage(run)
    return [(run.best[i], run.tried[i]) for i in run.everyone]


def estimate_batch(problem: FitProblem, options: EstimateOptions) -> list[Result]:
    """Estimate the lights of a batch of same-sized images; each image's chosen model
    and every model tried (see :func:`estimate_scene`).

    Every step runs on the whole batch (the searches over ``B x candidates``
    images), so a GPU is filled; each image is judged on its own and gets the
    answer it would get alone (with ``tuning.cnn_start=settled`` up to the networks' float32 batch
    noise, about 1e-5 m, which moved where the LM stops by a fifth of the answer's uncertainty).

    With ``options.tuning.reflectance_gains`` rounds, each round rescales the albedo of every
    smooth surface (:func:`selfsup.estimation.normals.surface_segments`) by :func:`segment_gains`
    of the last round's chosen fit and estimates again; ``problem.material`` is then
    replaced by the last albedo, which the records' covariances need.

    Images whose reflectance is fitted albedo-free (``options.tuning.reflectance``,
    :func:`reflectance_unknown`) go to :func:`estimate_albedo_free` instead.
    """
    free = albedo_free_images(problem, options)
    if any(free):
        results: list = [None] * problem.batch
        for flag, fit_images in ((True, _albedo_free_with_network), (False, estimate_given)):
            rows = [i for i, f in enumerate(free) if f == flag]
            if not rows:
                continue
            at = torch.tensor(rows, dtype=torch.long, device=problem.image.device)
            sub = problem.select(at)
            for i, result in zip(rows, fit_images(sub, options)):
                results[i] = result
            if not flag and options.tuning.reflectance_gains:  # the records' covariances need the rescaled albedo
                problem.material = dataclasses.replace(problem.material,
                                                       kd=problem.material.kd.index_put((at,), sub.material.kd))
        return results
    return estimate_given(problem, options)


def _albedo_free_with_network(problem: FitProblem, options: EstimateOptions) -> list[Result]:
    # The albedo-free fit. With cnn+refine and tuning.cnn_start=settled, method=cnn's answer (the
    # shipped networks' lights settled and picked on the frame) is every image's sure start: its
    # first light refined with no grid, one light more searched beside it. Otherwise the network's
    # lights join the searches' starts, or where it is sure (its confidence reaches tuning.cnn_sure)
    # are refined without a search.
    if options.method != "cnn+refine":
        return estimate_albedo_free(problem, options)
    if answer_checkpoints(options):
        segments = albedo_free_segments(problem, options)
        slots, _ = network_answer(problem, options, segments[0])
        sure = torch.ones(problem.batch, dtype=torch.bool, device=problem.image.device)
        return estimate_albedo_free(problem, options, slots, sure, segments)
    slots, _, confidence = network_slots(problem, start_checkpoint(options), with_confidence=True)
    return estimate_albedo_free(problem, options, slots, confidence >= options.tuning.cnn_sure)


def estimate_given(problem: FitProblem, options: EstimateOptions) -> list[Result]:
    # The image fit with the file's reflectance (and its reflectance_gains rounds).
    results = _estimate_once(problem, options)
    if options.tuning.reflectance_gains:
        g = problem.gbuffer
        segments = surface_segments(g.points, g.normals, g.mask)
        for _ in range(options.tuning.reflectance_gains):
            model = torch.cat([best.fit.model for best, _ in results])
            kd = problem.material.kd * segment_gains(problem.image, model, segments)
            problem.material = dataclasses.replace(problem.material, kd=kd)
            results = _estimate_once(problem, options)
    return results


def estimate_scene(scene: Scene, options: EstimateOptions, device: str | torch.device = "cpu") -> dict:
    """Estimate the lights of one scene on ``device``; returns the JSON-ready record (no ``seconds``).

    Models tried: one light (searched with the specular term if the file has ks),
    the same light refined without it, then more lights with the better of the two
    while each added light lowers :func:`bic` and carries at least
    ``min_light_share`` of the rendered direct light. Searches run with
    ``search_shadows``; each model found is refined with ``shadows`` before it is
    judged. With ``cnn+refine`` the network's slots join the grid's best
    candidates as starts of every search; ``cnn`` searches nothing: the networks' slots are settled
    and counted on the frame (:func:`selfsup.estimation.network.network_answer`).
    :func:`estimate_batch` does the work; batches of scenes go there.
    """
    scene, factor = working_range(within_pixels(scene, options))
    problem = prepare([scene], options, torch.device(device))
    return in_file_units(records([scene.id], problem, estimate_batch(problem, options), options)[0], factor)
