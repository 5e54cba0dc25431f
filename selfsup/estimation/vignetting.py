"""A lens's vignetting, chosen per frame with the first light: what cameras do to the shading.

A lens passes less light to the image's corners than to its centre (the ``cos^4`` law of
a simple lens, and more where its barrel cuts the beam); phones correct most of it, webcams
and depth cameras' colour sensors often do not. To a fit that models only the lights,
the brighter centre looks like a light near the camera: through 30% vignetting at the
corners our procedural captures' one-light success fell from 92% to 50% (every other
camera reality alone cost at most two of 12 frames; ``benchmarks.captures realities``,
docs/decisions.md 2026-11-28), and real Kinect and RealSense frames took lights at the
camera's height, 0.4-1.5 m from it.

:func:`falloff` is the radial factor ``(1 + a r^2)^-2`` (the ``cos^4`` law's shape, ``r`` the
distance from the principal point in focal lengths), its strength given as the share of
light the image's corners lose. :func:`choose_vignetting` fits the first light through each
strength of :data:`SHARES` (one albedo-free search over all of them, the image divided by
the falloff) and keeps, per image, the one the criterion prefers (one parameter more than
none); the rest of the estimate sees the image with it divided out.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from selfsup.estimation import albedo_free
from selfsup.estimation.problem import FitProblem
from selfsup.scenes.camera import lens_falloff as falloff  # the camera model's lens, the one formula

__all__ = ["falloff", "devignetted", "choose_vignetting", "SHARES"]

# The corner losses tried: none, and a lens's usual range (consumer RGB-D colour cameras
# lose 20-50% of the light at the corners without correction).
SHARES = (0.0, 0.25, 0.5)
FULL_ITERATIONS = 15  # the chosen strength's first light at full resolution, as albedo_free.search ends
# Each strength's search: this many starts of this many LM steps, the grid ranked on every
# CHOICE_RANK_STRIDE-th pixel (albedo_free.search's defaults: 4, 15 and 4, which chose as
# well on the 108 camera-realities frames: 67, 68 and 70 successes as each was cheapened in
# turn; ad hoc, 2026-11-28).
CHOICE_STARTS = 2
CHOICE_ITERATIONS = 10
CHOICE_RANK_STRIDE = 8


def devignetted(problem: FitProblem, corner_share: Tensor) -> FitProblem:
    """``problem`` with its image divided by :func:`falloff` of ``corner_share (B,)``; the
    robust scales found before are kept (fits of every strength are judged alike)."""
    H, W = problem.image.shape[-2:]
    factor = falloff(problem.gbuffer.intrinsics, H, W, corner_share)[:, None]  # (B, 1, H, W)
    return problem._changed(image=problem.image / factor)


def _interpolated(values: Tensor, choice: Tensor) -> Tensor:
    # (B,) strengths: where the best of SHARES (values (S, B), choice (B,)) has a neighbour on
    # each side, the minimum of the parabola through the three; else the best itself. The
    # grid's steps are coarse beside a lens's strength (a 0.3 lens fitted at 0.2 or 0.4 lost
    # a third of its frames).
    grid = torch.tensor(SHARES, dtype=values.dtype)
    out = grid[choice].clone()
    for i, k in enumerate(choice.tolist()):
        if 0 < k < len(SHARES) - 1:
            (x0, x1, x2), (y0, y1, y2) = grid[k - 1 : k + 2].tolist(), values[k - 1 : k + 2, i].tolist()
            bend = y0 - 2 * y1 + y2  # > 0: y1 is the lowest of three on equal steps
            if bend > 0:
                out[i] = min(max(x1 - (x1 - x0) * (y2 - y0) / (2 * bend), x0), x2)
    return out


def choose_vignetting(problem: FitProblem, labels: Tensor | None, criterion, search_kwargs: dict,
                      starts: dict | None = None, position: Tensor | None = None
                      ) -> tuple[Tensor, albedo_free.AlbedoFreeFit]:
    """Each image's corner loss ``(B,)`` of :data:`SHARES` and its first light's fit.

    The first light is searched through every strength at once (the images side by side);
    ``criterion(fit, extra_params)`` gives each image's value of a fit (lower is better),
    a strength other than none paying for one parameter. A problem without intrinsics
    keeps none, and so does a crop of its frame (``problem.cropped``: an object in the dark,
    the frame's corners out of view, where the falloff's strength was a free knob chosen at
    its limit in half the DiLiGenT ball's frames). ``starts``:
    :func:`selfsup.estimation.albedo_free.search`'s ``extra_starts`` (a network's first light), or none.
    ``position (B, 1, 3)``: a sure network's first light, refined under each strength
    (:func:`selfsup.estimation.albedo_free.refine_from`) in place of the search."""
    B = problem.batch

    def first_light(p: FitProblem, at: Tensor | None, **kwargs) -> albedo_free.AlbedoFreeFit:
        if position is None:
            return albedo_free.search(p, 1, labels=at, **kwargs, **search_kwargs)
        kept = {k: v for k, v in kwargs.items() if k == "iterations"}
        return albedo_free.refine_from(p, position.repeat(p.batch // B, 1, 1), labels=at, **kept, **search_kwargs)

    problem.median_observed(), problem.noise_level()  # the scales, found once on the image as given
    cropped = torch.zeros(B, dtype=torch.bool, device=problem.image.device) if problem.cropped is None else problem.cropped
    if problem.gbuffer.intrinsics is None or bool(cropped.all()):
        shares = problem.image.new_zeros(B)
        return shares, first_light(problem, labels, **(starts or {}))
    # Each strength's first light on every pixel (the scales of the image as given: the loss of
    # each strength on one scale; every 2nd pixel lost 3 of 67 successes on the 108 camera-
    # realities frames, ad hoc, 2026-11-28), without the search's last steps, which only the
    # chosen one takes at full resolution (FULL_ITERATIONS).
    tried = [devignetted(problem, torch.full((B,), share, dtype=problem.image.dtype, device=problem.image.device))
             for share in SHARES]
    together = FitProblem.cat(tried)
    together._median = torch.cat([problem._median] * len(SHARES))
    together._noise = torch.cat([problem._noise] * len(SHARES))
    at = None if labels is None else labels.repeat(len(SHARES), 1, 1)
    extra = {k: v.repeat(len(SHARES), *[1] * (v.dim() - 1)) for k, v in (starts or {}).items()}
    fit = first_light(together, at, starts=CHOICE_STARTS, iterations=(CHOICE_ITERATIONS, 0),
                      rank_stride=CHOICE_RANK_STRIDE, **extra)
    values = torch.tensor([criterion(fit, [0 if share == 0 else 1 for share in SHARES for _ in range(B)])],
                          dtype=torch.float64).view(len(SHARES), B)
    values[1:, cropped.cpu()] = math.inf  # a crop keeps none
    choice = values.argmin(0)  # (B,)
    shares = _interpolated(values, choice).to(problem.image)
    picked = albedo_free.AlbedoFreeFit.rows([(fit, int(k) * B + i) for i, k in enumerate(choice.tolist())])
    chosen = devignetted(problem, shares)
    full = albedo_free.observe(chosen, search_kwargs.get("robust_scale", 0.02), labels=labels,
                               **{k: v for k, v in search_kwargs.items() if k in ("residuals", "segment_scale")})
    fit = albedo_free.refine_positions(full, picked.position, picked.log_weight, FULL_ITERATIONS,
                                       albedo_free.FINAL_TOLERANCE)
    return shares, fit
