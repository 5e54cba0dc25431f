"""Reflectance the file does not give: the albedo-free fit's driver and per-surface albedo gains.

A file whose kd is one constant says nothing of the albedo (:func:`reflectance_unknown`);
its lights are fitted to the shading's log-differences between neighbours
(:mod:`selfsup.estimation.albedo_free`) by :func:`estimate_albedo_free`.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch
from torch import Tensor

from selfsup.estimation import albedo_free
from selfsup.estimation.count import MIN_RESIDUALS, judged, residual_options
from selfsup.estimation.criterion import Candidate, bic, block_px, fit_row
from selfsup.estimation.intensities import ambient_criterion, evidence, intensities_of
from selfsup.estimation.normals import surface_segments
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.problem import FitProblem, centre_and_size
from selfsup.estimation.vignetting import choose_vignetting, devignetted

__all__ = ["reflectance_unknown", "albedo_free_images", "albedo_free_segments", "estimate_albedo_free",
           "albedo_free_covariance"]

# The bounce of the albedo-free fit (estimate.tuning.albedo_free_bounce): its strength's start
# (log; the bounce maps of albedo relative to its median, bounce_maps) and the LM steps that
# refine it beside the lights.
BOUNCE_START = math.log(0.5)
BOUNCE_ITERATIONS = 8
# A highlight's pixel (left out of the chosen lights' placement): brighter than the diffuse
# model by this many times the fit's Cauchy scale, inside the lights' mirror lobes.
HIGHLIGHT_EXCESS = 2.0


def reflectance_unknown(problem: FitProblem, rel_tol: float = 1e-6) -> Tensor:
    """``(B,)``: the image's kd is one constant on its valid pixels (every channel within
    ``rel_tol`` of its maximum), so it says nothing of the surfaces' albedo."""
    kd = problem.material.kd
    mask = problem.gbuffer.mask[..., None].expand_as(kd)
    hi = torch.where(mask, kd, torch.full_like(kd, -math.inf)).flatten(1, 2).amax(1)  # (B, 3)
    lo = torch.where(mask, kd, torch.full_like(kd, math.inf)).flatten(1, 2).amin(1)
    return ((hi - lo) <= rel_tol * hi.abs().clamp_min(1e-30)).all(1)


def grey_where_unknown(problem: FitProblem, options: EstimateOptions) -> FitProblem:
    """``problem`` with the image of each image whose albedo is unknown (:func:`reflectance_unknown`)
    made grey (its channels' mean in each), where ``tuning.light_colour`` is ``neutral``: intensities
    solved on it are every light's and the ambient's as the image's white, as the albedo-free fit's
    (:func:`intensities_of`). Solved per channel, the network's lamps on DiLiGenT's bear took the
    bear's brown (the weakest channel under a fifth of the strongest in 15 of 24 frames)."""
    unknown = reflectance_unknown(problem)
    if options.tuning.light_colour != "neutral" or not bool(unknown.any()):
        return problem
    grey = problem.image.mean(1, keepdim=True).expand_as(problem.image)
    return replace(problem, image=torch.where(unknown[:, None, None, None], grey, problem.image))


def albedo_free_images(problem: FitProblem, options: EstimateOptions) -> list[bool]:
    # The images estimate_albedo_free fits (method=cnn fits none: the network's slots, settled).
    if options.method == "cnn":
        return [False] * problem.batch
    return albedo_unknown_images(problem, options)


def albedo_unknown_images(problem: FitProblem, options: EstimateOptions) -> list[bool]:
    """Each image's lights are fitted albedo-free (``tuning.reflectance``; with ``auto``, where
    :func:`reflectance_unknown`)."""
    if options.tuning.reflectance == "given":
        return [False] * problem.batch
    if options.tuning.reflectance == "albedo_free":
        return [True] * problem.batch
    return reflectance_unknown(problem).tolist()


def albedo_free_segments(problem: FitProblem, options: EstimateOptions) -> tuple[Tensor | None, Tensor | None]:
    """Every image's albedo segments ``(B, H, W)`` and smooth surfaces ``(B, H, W)`` as the
    albedo-free fit finds them (:func:`selfsup.estimation.albedo_free.tuned_segments`,
    :func:`selfsup.estimation.normals.surface_segments`); both None where its residuals are pairs."""
    if options.tuning.albedo_free_residuals != "segments":
        return None, None
    g = problem.gbuffer
    geometry = surface_segments(g.points, g.normals, g.mask)
    return albedo_free.tuned_segments(problem, options.tuning, geometry), geometry


def estimate_albedo_free(problem: FitProblem, options: EstimateOptions, slots: Tensor | None = None,
                         sure: Tensor | None = None, segments: tuple[Tensor | None, Tensor | None] | None = None
                         ) -> list[tuple[Candidate, list[Candidate]]]:
    """Lights fitted to the log shading with each albedo segment's mean taken out (or its
    neighbour differences; :mod:`selfsup.estimation.albedo_free`), 1 .. ``max_lights`` while
    :func:`bic` of their Cauchy loss falls (:func:`selfsup.estimation.count.judged`: with
    segments, without the highlights of the lights before, where ``MIN_RESIDUALS`` are left) and each light
    carries ``min_light_share`` of the fitted shading, or while the capture's black pixels need
    one light more (``unlit_evidence``, :func:`selfsup.estimation.unlit.needs_another_light`:
    then the records' criteria may favour the fewer lights); the chosen model's lights then
    refitted with their diffuse light through a clear coat, kept where the criterion prefers it
    (``albedo_free_coat=chosen``, :func:`selfsup.estimation.albedo_free.choose_coat`), and
    placed on its segments merged into classes of one albedo (``albedo_class_rounds``,
    :func:`selfsup.estimation.albedo_free.refine_on_classes`), with the light they cast off
    the surfaces where ``albedo_free_bounce=auto`` and the criterion says it pays (before the
    evidence is judged); intensities and ambient then the fit's own ratios in the image's
    units (:func:`intensities_of`).

    With ``vignetting=auto`` the lens's falloff is chosen with the first light
    (:func:`selfsup.estimation.vignetting.choose_vignetting`); where it is not none, the
    image is estimated again without it and the whole model (its lights, and the falloff's
    one parameter) with the lower criterion on every residual is kept: two lights far apart
    light a room much as one light through a vignetting lens, and a one-light choice took
    a falloff for devset capture 031's second light.

    ``slots (B, K, 3)``: a network's lights in its order (:func:`selfsup.estimation.network.network_slots`);
    the search of ``n`` lights also starts from its first ``n``. ``sure (B,)`` bool: the images
    whose network is sure of its lights (its calibrated confidence, ``tuning.cnn_sure``; every image
    with ``tuning.cnn_start=settled``, the networks' settled answer): its
    first light refined from where it put it (:func:`selfsup.estimation.albedo_free.refine_from`:
    no grid; with ``vignetting=auto`` refined under each lens falloff and the falloff chosen as
    after a search), then one light more searched as elsewhere (its
    first lights one of the starts) but not each light again, the criterion choosing; that search is
    lean (:data:`selfsup.estimation.albedo_free.LEAN_SEARCH`: the network's pair and the split
    starts carry it). ``segments``: :func:`albedo_free_segments` of ``problem`` where a caller found
    them already."""
    # every image's albedo segments (and smooth surfaces), found once
    labels, geometry = albedo_free_segments(problem, options) if segments is None else segments
    results: list = [None] * problem.batch
    sure = torch.zeros(problem.batch, dtype=torch.bool) if sure is None else sure.cpu()
    for flag in (True, False):  # the images whose network is sure: its lights refined; the others searched
        rows = [i for i, s in enumerate(sure.tolist()) if s == flag]
        if rows:
            _estimate_rows(problem, options, labels, geometry, slots, rows, flag, results)
    if slots is not None:
        # Where a sure network's lights led to a model the evidence does not support (no better
        # than the ambient alone), it was wrong: those images, which no search has seen, are
        # searched as without a network and keep whichever answer has the more evidence (on the
        # DiLiGenT ball 4 of 12 frames said "no light" from a sure network's lights). An unsure
        # image's "no light" came from a search already.
        # Judged at the sensor's noise (noise_evidence), as when this check was measured: at the
        # frame's own misfit a wrong light that misses the shading widely still explains some of it.
        doubtful = [i for i in range(problem.batch) if bool(sure[i]) and not (results[i][0].noise_evidence or 0.0) > 0]
        if doubtful:
            before = {i: results[i] for i in doubtful}
            _estimate_rows(problem, options, labels, geometry, None, doubtful, False, results)
            for i, old in before.items():
                if (old[0].noise_evidence or -math.inf) >= (results[i][0].noise_evidence or -math.inf):
                    results[i] = old
    return results


def _estimate_rows(problem: FitProblem, options: EstimateOptions, labels: Tensor | None, geometry: Tensor | None,
                   slots: Tensor | None, rows: list[int], sure: bool, results: list) -> None:
    # _estimate_split of the images ``rows``, written into ``results``.
    at = torch.tensor(rows, dtype=torch.long, device=problem.image.device)
    part = _estimate_split(problem.select(at), options, None if labels is None else labels[at],
                           None if geometry is None else geometry[at], None if slots is None else slots[at], sure)
    for i, result in zip(rows, part):
        results[i] = result


def _estimate_split(problem: FitProblem, options: EstimateOptions, labels: Tensor | None, geometry: Tensor | None,
                    slots: Tensor | None, sure: bool) -> list[tuple[Candidate, list[Candidate]]]:
    # estimate_albedo_free of images whose network is sure (its lights refined) or not (searched).
    auto = options.tuning.vignetting == "auto"
    results, whole = _fit_albedo_free(problem, options, labels, geometry, auto, slots, sure=sure)
    again = [i for i, (best, _) in enumerate(results) if best.vignetting]
    if again:
        at = torch.tensor(again, dtype=torch.long, device=problem.image.device)
        plain, plain_whole = _fit_albedo_free(problem.select(at), options, None if labels is None else labels[at],
                                              None if geometry is None else geometry[at], False,
                                              None if slots is None else slots[at], sure=sure)
        for j, i in enumerate(again):
            if plain_whole[j] <= whole[i]:
                results[i] = plain[j]
    return results


def _fit_albedo_free(problem: FitProblem, options: EstimateOptions, labels: Tensor | None, geometry: Tensor | None,
                     vignetting: bool, slots: Tensor | None = None, sure: bool = False
                     ) -> tuple[list[tuple[Candidate, list[Candidate]]], list[float]]:
    # estimate_albedo_free's results, with the lens's falloff chosen (vignetting) or none, and
    # each image's criterion of its whole chosen model on every residual.
    B, device = problem.batch, problem.image.device
    block = block_px(options, problem.image.shape[-1], albedo_free=True)

    def criterion(fit: albedo_free.AlbedoFreeFit, extra: list[int] | None = None) -> list[float]:
        # The BIC of each image's fit: its position and a contrast per light (the ambient's for
        # the first), the bounce's strength where it has one, and ``extra`` parameters (a
        # lens's vignetting).
        n_params = 4 * fit.position.shape[1]
        extra = extra or [0] * fit.position.shape[0]
        extra = [more + int(b) for more, b in zip(extra, fit.bounced().tolist())]
        # An image without residuals has no criterion (MIN_RESIDUALS names it below).
        return [bic(loss, int(pairs), n_params + more, block) if pairs >= 1 else math.inf
                for loss, pairs, more in zip(fit.loss.tolist(), fit.pairs.tolist(), extra)]

    def with_bounce(every: albedo_free.LogShading, fit: albedo_free.AlbedoFreeFit) -> albedo_free.AlbedoFreeFit:
        # Each image's fit or the same lights with the bounce of the light they cast off the
        # surfaces (its strength one more parameter), whichever the criterion prefers, on the
        # observation ``every`` (its segments, every residual).
        if options.tuning.albedo_free_bounce == "never" or every.gbuffer.intrinsics is None:
            return fit
        start = torch.full_like(fit.loss, BOUNCE_START)
        bounced = albedo_free.refine_positions(every, fit.position, fit.log_weight, BOUNCE_ITERATIONS, log_bounce=start)
        plain = fit if fit.log_bounce is None else albedo_free.AlbedoFreeFit(fit.position, fit.log_weight, fit.loss,
                                                                          fit.pairs)
        take = torch.tensor([b < a for a, b in zip(criterion(plain), criterion(bounced))], device=fit.loss.device)
        return plain.chosen(take, bounced)

    search_kwargs = dict(robust_scale=options.tuning.albedo_free_scale, **residual_options(options))

    def network_starts(rows: Tensor | None, n_lights: int) -> dict:
        # The network's first n lights as one more start of a search of n (None: no network).
        if slots is None or n_lights > slots.shape[1]:
            return {}
        chosen = slots if rows is None else slots[rows]
        return dict(extra_starts=chosen[:, None, :n_lights])

    if sure and vignetting:  # the network's first light refined under each lens falloff, no grid
        corner_loss, found = choose_vignetting(problem, labels, criterion, search_kwargs, position=slots[:, :1])
        problem = devignetted(problem, corner_loss)
    elif sure:  # the network's first light refined, no grid
        corner_loss = problem.image.new_zeros(B)
        found = albedo_free.refine_from(problem, slots[:, :1], labels=labels, **search_kwargs)
    elif vignetting:
        corner_loss, found = choose_vignetting(problem, labels, criterion, search_kwargs, network_starts(None, 1))
        problem = devignetted(problem, corner_loss)  # every fit below sees the image with the lens's falloff taken out
    else:
        corner_loss = problem.image.new_zeros(B)
        found = albedo_free.search(problem, 1, labels=labels, **search_kwargs, **network_starts(None, 1))
    pairs = found.pairs.tolist()
    if min(pairs) < MIN_RESIDUALS:
        raise ValueError(f"kd is one constant, so the lights are fitted albedo-free, but image {pairs.index(min(pairs))} "
                         f"has {min(pairs)} usable residuals (lit pixels of albedo segments, or pairs of neighbouring "
                         f"pixels with kd > 0 and light; at least {MIN_RESIDUALS} needed)")
    if options.tuning.albedo_free_coat in ("auto", "always"):  # glossy paint and plastic: the diffuse light through a coat
        problem, found = albedo_free.choose_coat(problem, found, labels, search_kwargs["robust_scale"], criterion,
                                                 search_kwargs["residuals"], options.tuning.albedo_free_coat == "always")
    if options.tuning.albedo_free_gloss == "auto" and labels is not None:
        # Metal and glossy paint: a specular lobe beside the diffuse light, where it pays.
        problem, found = albedo_free.choose_gloss(problem, found, labels, options.tuning.albedo_free_scale, criterion)

    best = [(found, i, c) for i, c in enumerate(criterion(found))]  # (fit, row, criterion) per image
    tried = [[(1, c)] for _, _, c in best]
    growing = list(range(B))
    by_shadows = [False] * B  # each image's last light taken by its black pixels, not the criterion
    for n_lights in range(2, options.max_lights + 1):
        if not growing or (sure and n_lights > slots.shape[1]):
            break
        at = torch.tensor(growing, dtype=torch.long, device=device)
        before = albedo_free.AlbedoFreeFit.rows([best[i][:2] for i in growing])
        sub = problem.select(at)
        kwargs = dict(robust_scale=options.tuning.albedo_free_scale, labels=None if labels is None else labels[at],
                      **residual_options(options))
        if sure:  # one light more searched beside the network's first, its first n lights one of the starts
            more = albedo_free.search(sub, n_lights, fixed=before, **kwargs, **network_starts(at, n_lights),
                                      **albedo_free.LEAN_SEARCH)
        else:
            more = albedo_free.search_each(sub, albedo_free.search(sub, n_lights, fixed=before, **kwargs,
                                                                   **network_starts(at, n_lights)), **kwargs)
        taken, shadows, fewer_value, more_value = judged(sub, before, more, [best[i][2] for i in growing],
                                                         kwargs["labels"], options, criterion,
                                                         None if geometry is None else geometry[at])
        still = []
        for j, (i, c) in enumerate(zip(growing, more_value)):
            tried[i][-1] = (n_lights - 1, fewer_value[j])  # the records keep the values compared
            tried[i].append((n_lights, c))
            if taken[j]:
                best[i] = (more, j, c)
                by_shadows[i] = shadows[j]
                still.append(i)
        growing = still
    if options.tuning.albedo_free_gloss == "instead" and labels is not None:
        problem = _lobe_instead(problem, found, labels, options, criterion, best, by_shadows, tried, geometry,
                                from_mirror=sure)
    return _chosen_candidates(problem, labels, geometry, options, best, tried, corner_loss, criterion, with_bounce)


def _lobe_instead(problem: FitProblem, found: albedo_free.AlbedoFreeFit, labels: Tensor, options: EstimateOptions,
                  criterion, best: list, by_shadows: list[bool], tried: list[list[tuple]],
                  geometry: Tensor | None = None, from_mirror: bool = False) -> FitProblem:
    # Where the diffuse fit took more than one light, one light with a specular lobe in their place
    # (:func:`albedo_free.choose_gloss`), where its criterion on every residual is below theirs: a broad lobe is a
    # second peak that a light beside the first also makes. Its light starts at the one-light fit ``found`` and at
    # each of the more lights alone (a metal's one diffuse light lands between its lamp and the lobe's peak, one
    # of the pair's near the lamp). Not where the black pixels took the last light (``by_shadows``): a lobe casts
    # no shadow. Beside a lobe that replaced lights, one light more is searched and judged as any second light
    # (:func:`_light_beside_lobe`): a glossy room may have two lamps. Where one light and its lobe lose, the lobe
    # is tried beside the lights the diffuse fit took (two lamps on a glossy object: the diffuse pair lands 16-21
    # degrees off both, each light between a lamp and a highlight). Where it kept one light, a lobe that outshines
    # it (:func:`albedo_free.choose_lone_lobe`). ``from_mirror``: the pairs' lobes start at the highlight's mirror
    # too (a lean pair has no light near a metal's lamp). ``best`` and ``tried`` are updated in place (the lobe's
    # models join ``tried`` as ``(n, criterion, True)``); returns the problem with each image's lobe.
    scale, residuals = options.tuning.albedo_free_scale, options.tuning.albedo_free_residuals
    gloss = problem.image.new_zeros(problem.batch, 2)
    counts = [best[i][0].position.shape[1] for i in range(problem.batch)]
    for n_lights in sorted({n for n, shadows in zip(counts, by_shadows) if n > 1 and not shadows}):
        more = [i for i in range(problem.batch) if counts[i] == n_lights and not by_shadows[i]]
        several = albedo_free.AlbedoFreeFit.rows([best[i][:2] for i in more])
        at, alone = _rows_of(problem, found, more)  # their one-light fits
        sub = problem.select(at)
        starts = [several.only(k) for k in range(n_lights)]
        if from_mirror:
            starts.append(albedo_free.mirror_start(sub, alone, labels[at], scale, residuals))
        shapes, fitted, fitted_values = albedo_free.fit_lobes(sub, alone, labels[at], scale, criterion, starts=starts)
        lobed_problem, lobed = albedo_free.keep_lobes(sub, alone, shapes, fitted, fitted_values, criterion,
                                                      against=criterion(several))
        took = _taken_lobes(lobed_problem, lobed, more, 1, criterion, best, tried, gloss)
        if took:
            _light_beside_lobe(lobed_problem, lobed, several, took, [more[j] for j in took], labels[at], options,
                               criterion, best, tried, None if geometry is None else geometry[at])
        rest = [j for j in range(len(more)) if j not in took]
        if rest:  # the lobe beside the lights they have (two lamps on a glossy object); the one light's shape too
            beside = torch.tensor(rest, dtype=torch.long, device=problem.image.device)
            lobed_problem, lobed = albedo_free.choose_gloss(
                sub.select(beside), albedo_free.AlbedoFreeFit.rows([(several, j) for j in rest]),
                labels[at[beside]], scale, criterion, shapes=shapes[beside, None])
            _taken_lobes(lobed_problem, lobed, [more[j] for j in rest], n_lights, criterion, best, tried, gloss)
    ones = [i for i in range(problem.batch) if counts[i] == 1]
    if from_mirror and ones:  # a sure network's light no better than the ambient alone is a wrong light, not
        # a lamp beside a lobe: the search without a network follows (estimate_albedo_free) and tries the lobe
        at, alone = _rows_of(problem, found, ones)
        every = albedo_free.observe(problem.select(at), scale, labels=labels[at], **residual_options(options))
        unlit = ambient_criterion(every, alone, block_px(options, problem.image.shape[-1], albedo_free=True))
        ones = [i for i, u, c in zip(ones, unlit, criterion(alone)) if c < u]
    if ones:
        at, alone = _rows_of(problem, found, ones)
        lobed_problem, lobed = albedo_free.choose_lone_lobe(problem.select(at), alone, labels[at], scale, criterion,
                                                            residuals)
        _taken_lobes(lobed_problem, lobed, ones, 1, criterion, best, tried, gloss)
    return problem.with_gloss(gloss) if bool((gloss[:, 0] > 0).any()) else problem


def _taken_lobes(lobed_problem: FitProblem, lobed: albedo_free.AlbedoFreeFit, images: list[int], n_lights: int,
                 criterion, best: list, tried: list[list[tuple]], gloss: Tensor) -> list[int]:
    # The rows of ``lobed_problem`` (images ``images``) that kept a lobe (ratio > 0): each
    # image's ``best`` becomes its row of ``lobed`` (n_lights lights and the lobe), ``tried``
    # gains it and ``gloss (B, 2)`` its lobe, in place. Returns those rows.
    if lobed_problem.gloss is None:
        return []
    took = [j for j, ratio in enumerate(lobed_problem.gloss[:, 0].tolist()) if ratio > 0]
    values = criterion(lobed, [albedo_free.GLOSS_PARAMETERS] * len(images))
    for j in took:
        best[images[j]] = (lobed, j, values[j])
        tried[images[j]].append((n_lights, values[j], True))
        gloss[images[j]] = lobed_problem.gloss[j]
    return took


def _light_beside_lobe(problem: FitProblem, lobed: albedo_free.AlbedoFreeFit, several: albedo_free.AlbedoFreeFit,
                       rows: list[int], images: list[int], labels: Tensor, options: EstimateOptions, criterion,
                       best: list, tried: list[list[tuple]], geometry: Tensor | None) -> None:
    # Rows ``rows`` of ``problem`` (with its lobes; images ``images`` of ``best``) took one light
    # and its lobe (``lobed``) in the place of the lights of ``several``: one light more searched
    # beside it (the lobe on both), also from the lobe's light beside each light it replaced (and
    # the replaced pair itself), taken where :func:`selfsup.estimation.count.judged` takes it and the two lights are
    # resolved (:func:`_resolved_beside_lobe`). The two models differ by a light only, so they are
    # judged without the lobe's parameters; the records keep them with.
    at = torch.tensor(rows, dtype=torch.long, device=problem.image.device)
    sub, replaced = problem.select(at), several.position[at]  # replaced (R, n, 3)
    before = albedo_free.AlbedoFreeFit.rows([(lobed, j) for j in rows])
    starts = [torch.stack([before.position[:, 0], replaced[:, k]], 1) for k in range(replaced.shape[1])]
    starts += [replaced] if replaced.shape[1] == 2 else []
    kwargs = dict(robust_scale=options.tuning.albedo_free_scale, labels=labels[at], **residual_options(options))
    more = albedo_free.search(sub, 2, fixed=before, starts=4 + len(starts), extra_starts=torch.stack(starts, 1),
                              **kwargs)
    more = albedo_free.search_each(sub, more, **kwargs)
    taken, _, _, _ = judged(sub, before, more, criterion(before), kwargs["labels"], options, criterion,
                            None if geometry is None else geometry[at])
    apart = _resolved_beside_lobe(sub, more).tolist()
    taken = [t and a for t, a in zip(taken, apart)]
    values = criterion(more, [albedo_free.GLOSS_PARAMETERS] * len(rows))
    for j, i in enumerate(images):
        tried[i].append((2, values[j], True))
        if taken[j]:
            best[i] = (more, j, values[j])


def _resolved_beside_lobe(problem: FitProblem, fit: albedo_free.AlbedoFreeFit) -> Tensor:
    """``(B,)`` bool: whether the two lights of ``fit`` lie farther apart, seen from the
    scene's centre, than the half-width at half maximum of ``problem``'s lobe (Blinn-Phong
    ``s``: ``acos(2 ** (-1 / s))`` in the half vector's angle; a light moved by twice that
    moves the peak by it). Closer, the pair is one lamp whose lobe has another shape than
    Blinn-Phong's (Mitsuba's GGX gold and aluminium took a second light 6-9 degrees from the
    first, beside a lobe 17-23 degrees wide), not two lamps."""
    centre, _ = centre_and_size(problem)
    seen = torch.nn.functional.normalize(fit.position - centre[:, None], dim=-1)  # (B, 2, 3)
    cosine = (seen[:, 0] * seen[:, 1]).sum(-1).clamp(-1.0, 1.0)
    half_width = torch.acos(torch.exp2(-1.0 / problem.gloss[:, 1].clamp_min(1e-3)))
    return torch.acos(cosine) > half_width


def _chosen_candidates(problem: FitProblem, labels: Tensor | None, geometry: Tensor | None, options: EstimateOptions,
                       best: list, tried: list[list[tuple[int, float]]], corner_loss: Tensor, criterion,
                       with_bounce=None) -> tuple[list[tuple[Candidate, list[Candidate]]], list[float]]:
    # Each image's chosen fit ``best[i] = (fit, row, criterion)`` as a candidate (through a coat
    # where ``criterion(fit, extra)`` prefers it, refined on its albedo classes, its intensities and
    # covariance), the models ``tried[i]`` beside it, and the criterion of the whole model on every
    # residual; one batched pass per light count.
    B, device = problem.batch, problem.image.device
    block = block_px(options, problem.image.shape[-1], albedo_free=True)
    results: list = [None] * B
    whole = [math.inf] * B
    counts = [best[i][0].position.shape[1] for i in range(B)]
    for n_lights in sorted(set(counts)):  # one batched solve and covariance per light count
        group = [i for i in range(B) if counts[i] == n_lights]
        chosen = albedo_free.AlbedoFreeFit.rows([best[i][:2] for i in group])
        rows = torch.tensor(group, dtype=torch.long, device=device)
        sub = problem.select(rows)
        segments = None if labels is None else labels[rows]
        if options.tuning.albedo_free_coat == "chosen":  # the chosen lights' diffuse light through a coat, where it pays
            sub, chosen = albedo_free.choose_coat(sub, chosen, segments, options.tuning.albedo_free_scale, criterion,
                                                  options.tuning.albedo_free_residuals)
        # The chosen model against the model without lights on every residual: how much its lights explain.
        # (The chosen fit's own loss is its loss on every residual: the searches end on this observation.)
        every = albedo_free.observe(sub, options.tuning.albedo_free_scale, labels=segments, **residual_options(options))
        if with_bounce is not None:
            chosen = with_bounce(every, chosen)
        losses, counted = chosen.loss.tolist(), chosen.pairs.tolist()
        # The model's own parameters: a position and a contrast per light, the bounce's strength, the lobe's
        # two, the coat's choice.
        bounced = chosen.bounced().tolist()
        own = [4 * n_lights + int(b) + g for b, g in zip(bounced, albedo_free.gloss_parameters(sub))]
        # The lights' evidence under the sensor's noise or, where larger, under the frame's own misfit.
        at_noise = evidence(every, chosen, own, block, 0.0)
        support = at_noise if options.tuning.evidence_spread == 0 else [
            max(a, b) for a, b in zip(at_noise, evidence(every, chosen, own, block, options.tuning.evidence_spread))]
        for i, loss, pairs, k in zip(group, losses, counted, own):
            whole[i] = bic(loss, pairs, k + int(bool(corner_loss[i] > 0)), block)
        highlight = torch.zeros_like(sub.gbuffer.mask)
        if segments is not None and options.tuning.highlights == "leave_out" and options.tuning.albedo_free_lobe_deg > 0:
            # The diffuse-only fit cannot explain a glossy surface's highlight: its pixels (in the
            # lights' mirror lobes, clearly brighter than the model) are left out of the placement.
            highlight = albedo_free.highlight_pixels(every, chosen, options.tuning.albedo_free_lobe_deg,
                                                     HIGHLIGHT_EXCESS) & albedo_free.diffuse_images(sub)[:, None, None]
            segments = torch.where(highlight, -1, segments)
        if segments is not None and options.tuning.albedo_class_rounds > 0:
            # The chosen model's lights placed on its segments merged into classes of one albedo.
            chosen, observed = albedo_free.refine_on_classes(
                sub, segments, chosen, options.tuning.albedo_free_scale, options.tuning.albedo_class_rounds,
                level_tolerance=options.tuning.albedo_class_level, chroma_tolerance=options.tuning.albedo_class_chroma,
                geometry=geometry[rows])
        else:
            observed = every
        fit, bounce_share = intensities_of(sub, chosen, options, observed)
        cov = albedo_free_covariance(observed, chosen, sub, options).cpu()
        coats = albedo_free.coated_images(sub).tolist()
        for j, i in enumerate(group):
            candidate = Candidate(fit_row(fit, j), n_lights, False, best[i][2], cov[j], "albedo_free",
                                  evidence=support[j], noise_evidence=at_noise[j],
                                  vignetting=round(float(corner_loss[i]), 3),
                                  highlight_pixels=int(highlight[j].sum()),
                                  bounce_share=round(float(bounce_share[j]), 4) if bounced[j] else None,
                                  gloss=albedo_free.lobe_of(sub, j), coat=coats[j])
            # The records keep the tried models' counts and criteria only.
            # (n, value) of the diffuse models, (n, value, True) of one with a specular lobe.
            others = [Candidate(candidate.fit, n, bool(lobe), value, None, "albedo_free") for n, value, *lobe in tried[i]]
            results[i] = (candidate, others)
    return results, whole


def _rows_of(problem: FitProblem, fit: albedo_free.AlbedoFreeFit, images: list[int]
             ) -> tuple[Tensor, albedo_free.AlbedoFreeFit]:
    # ``images`` as an index tensor on the problem's device, and ``fit``'s rows of them.
    return (torch.tensor(images, dtype=torch.long, device=problem.image.device),
            albedo_free.AlbedoFreeFit.rows([(fit, i) for i in images]))


def albedo_free_covariance(observed: albedo_free.LogShading, fit: albedo_free.AlbedoFreeFit, problem: FitProblem,
                           options: EstimateOptions) -> Tensor:
    """:func:`selfsup.estimation.albedo_free.position_covariance` ``(B, L, 3, 3)`` of ``fit``
    to ``observed`` (the log shading of ``problem``) under ``options``: the criterion's block,
    the indirect field and, where set, the refitted normals' tilt. The estimator's answer
    and the tracker's warm steps take it alike."""
    tuning = options.tuning
    return albedo_free.position_covariance(observed, fit, block_px=block_px(options, problem.image.shape[-1], albedo_free=True),
                                           indirect_variation=tuning.indirect_variation,
                                           indirect_length=tuning.indirect_length,
                                           normal_tilt=problem.normal_tilt if tuning.normal_error else None)
