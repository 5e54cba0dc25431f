"""The JSON-ready records of an estimate (``docs/scene-format.md``, "Estimation output")."""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from selfsup.estimation.criterion import Candidate, block_px, by_model, criterion_light, stacked_fits
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.problem import Fit, FitProblem, solve_at, transport_maps
from selfsup.estimation.reflectance import grey_where_unknown
from selfsup.estimation.uncertainty import position_covariance

__all__ = ["records", "surface_shares"]


def records(ids: list[str], problem: FitProblem, results: list[tuple[Candidate, list[Candidate]]],
            options: EstimateOptions) -> list[dict]:
    """The JSON-ready records (no ``seconds``) of :func:`estimate_batch`'s results, with
    each light's position covariance (one batched call per light count and switch).

    Where the file leaves light unaccounted for (no ambient) and ``options.tuning.indirect``
    is ``auto``, the reported intensities and ambient are solved again at the chosen
    positions with the light the criterion models (each light's indirect light and
    its cast shadows, :func:`judged_problem`, at every pixel): the fit's own, without
    them, take indirect light for light of the lamps. On the path-traced files the
    median worst intensity error fell, devset gi 0.114 -> 0.102, Mitsuba rooms 0.158
    -> 0.107 and 0.538 -> 0.439 (benchmarks/results/estimation_measurements.md, "Intensities under indirect light"); the
    positions and covariances stay the fit's."""
    covariances: list[Tensor | None] = [best.covariance for best, _ in results]
    lit: list[tuple[Tensor, Tensor] | None] = [None] * len(results)
    resolve = options.tuning.indirect == "auto" and problem.ambient is None and problem.gbuffer.intrinsics is not None
    own = [i for i, c in enumerate(covariances) if c is None]
    for (n_lights, specular), indices in by_model([results[i][0] for i in own]).items():
        group = [own[j] for j in indices]
        at = torch.tensor(group, dtype=torch.long, device=problem.image.device)
        fit = stacked_fits([results[i][0].fit for i in group])
        block = block_px(options, problem.image.shape[-1])
        cov = position_covariance(problem.select(at), fit, replace(options.tuning.refine, specular=specular),
                                  correlation_px=float(block**2), albedo_error=options.tuning.albedo_error,
                                  albedo_block_px=block, indirect_variation=options.tuning.indirect_variation,
                                  indirect_length=options.tuning.indirect_length,
                                  normal_error=options.tuning.normal_error).cpu()
        if resolve:
            final = replace(options.tuning.refine, specular=specular, robust_scale=options.tuning.final_robust_scale)
            # On the grey image where the albedo is unknown and the lights neutral (the lights the image's white).
            judged = criterion_light(grey_where_unknown(problem.select(at), options), options)
            _, intensity, ambient, *_ = solve_at(judged, fit.position, final)
        for j, i in enumerate(group):
            covariances[i] = cov[j]
            if resolve:
                lit[i] = intensity[j : j + 1], ambient[j : j + 1]
    shares: list[tuple[Tensor, Tensor] | None] = [None] * len(results)  # (share, mean shading) per record
    for _, group in by_model([replace(best, specular=False) for best, _ in results]).items():
        at = torch.tensor(group, dtype=torch.long, device=problem.image.device)
        fits = [results[i][0].fit if lit[i] is None else replace(results[i][0].fit, intensity=lit[i][0], ambient=lit[i][1])
                for i in group]
        share, mean_diffuse = surface_shares(problem.select(at), stacked_fits(fits), options)
        for j, i in enumerate(group):
            shares[i] = (share[j].cpu(), mean_diffuse[j].cpu())
    return [_record(scene_id, best, tried, cov, share, options.tuning.min_found_share, solved,
                    options.tuning.weak_light_min_share)
            for scene_id, (best, tried), cov, share, solved in zip(ids, results, covariances, shares, lit)]


def surface_shares(problem: FitProblem, fit: Fit, options: EstimateOptions) -> tuple[Tensor, Tensor]:
    """Each light's share ``(B, L)`` of the light on the visible surfaces: its grey
    intensity times its diffuse shading with the criterion's cast shadows, summed over
    the valid pixels, over that of every light and the ambient (albedo and highlights
    left out: what a lamp gives a surface, not what the camera sees of it); and each
    light's mean unit shading there ``(B, L)``."""
    judged = criterion_light(problem, options).with_indirect(False)
    diffuse, _ = transport_maps(judged, fit.position, False)  # (B, L, H, W)
    mask = problem.gbuffer.mask[:, None].to(diffuse.dtype)
    pixels = mask.flatten(1).sum(1).clamp_min(1)  # (B,)
    mean_diffuse = (diffuse * mask).flatten(2).sum(2) / pixels[:, None]  # (B, L)
    direct = fit.intensity.mean(-1) * mean_diffuse  # (B, L) per pixel
    return direct / (direct.sum(1) + fit.ambient.mean(-1)).clamp_min(1e-30)[:, None], mean_diffuse


def _record(scene_id: str, best: Candidate, tried: list[Candidate], cov: Tensor, shares: tuple[Tensor, Tensor],
            min_found_share: float, solved: tuple[Tensor, Tensor] | None = None, faint_share: float = 0.0) -> dict:
    # cov: (L, 3, 3) position covariance of the chosen model's lights; shares: (L,) each
    # light's share of the surfaces' light and (L,) its mean unit shading there
    # (surface_shares); solved: the intensities (1, L, 3) and ambient (1, 3) to report
    # instead of the fit's; faint_share: a light under this share beside found ones is not presented.
    share, mean_diffuse = shares
    std = cov.diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt()
    fit = best.fit if solved is None else replace(best.fit, intensity=solved[0], ambient=solved[1])
    # Brightest light first (summed RGB intensity): the same scene gives the same record
    # whichever start each light was found from.
    order = fit.intensity[0].sum(-1).cpu().argsort(descending=True, stable=True).tolist()
    lights = [
        {"position": fit.position[0, i].tolist(), "intensity": fit.intensity[0, i].tolist(),
         "position_std": std[i].tolist(), "position_cov": cov[i].tolist(), "share": round(float(share[i]), 4)}
        for i in order
    ]
    ambient = fit.ambient[0].tolist()
    # A light that explains almost nothing is not presented as one: the brightest must give
    # min_found_share of the surfaces' light, and the lights must beat the ambient alone.
    found = bool(lights) and float(share.max()) >= min_found_share and (best.evidence is None or best.evidence > 0)
    # Nor is a light beside them that gives the surfaces almost none of their light (under
    # faint_share, with the cast shadows): a lamp the geometry hides from nearly every visible
    # surface, placed there by a fit without shadows (a one-light procedural room's second light,
    # 0.46% of the light; benchmarks/results/faint_lights_presented_cpu1_2026-12-08.md).
    hidden = [k for k, i in enumerate(order) if not found or float(share[i]) < faint_share]
    shown = [k for k in range(len(order)) if k not in hidden]
    unsupported = [lights[k] for k in hidden]
    if hidden:
        # Their light becomes the ambient's: as much light on the surfaces, without direction.
        rows = [order[k] for k in hidden]
        given = fit.intensity[0, rows] * mean_diffuse.to(fit.intensity)[rows, None]  # (hidden, 3) on the surfaces
        ambient = (fit.ambient[0] + given.sum(0)).tolist()
        lights = [lights[k] for k in shown]
    return {
        "id": scene_id, "lights": lights, "ambient": ambient, "light_found": found,
        "direct_share": round(float(share[[order[k] for k in shown]].sum()), 4) if found else 0.0,
        "evidence": None if best.evidence is None else round(best.evidence, 3),
        "unsupported_lights": unsupported, "vignetting": best.vignetting, "highlight_pixels": best.highlight_pixels,
        "bounce_share": best.bounce_share,
        "gloss": None if best.gloss is None else {"ratio": best.gloss[0], "shininess": best.gloss[1]},
        "specular": best.specular, "coat": best.coat, "reflectance": best.reflectance,
        "candidates": [{"n_lights": c.n_lights, "specular": c.specular, "coat": c.coat, "criterion": round(c.criterion, 3)}
                       for c in tried],
    }
