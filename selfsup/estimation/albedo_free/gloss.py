"""A specular lobe in the albedo-free model, chosen per image: metal and glossy paint.

The albedo-free fit explains the log shading with diffuse light. A glossy object shows its
lamp twice: the diffuse shading, and the lobe around the mirror direction. A sharp highlight
is a few pixels, and :func:`.fit.highlight_pixels` leaves them out; a rough metal (whose
diffuse light is nil) or a broad paint gloss spreads the lobe over much of the object, and the
diffuse-only fit then moves its light towards the lobe, or takes a second light beside the
first to widen the peak. Independent renders of rough gold and aluminium (Mitsuba's GGX
conductors, path traced, through a camera) took two lights in every frame, the first
up to 24.6 degrees off (``benchmarks/results/gloss_cpu2_2026-12-06.md``). A lobe and a light
beside the first explain the same peak, so by default (``tuning.albedo_free_gloss=instead``)
the lobe is tried only where the diffuse fit takes more lights, with one light, and kept where
its criterion is below theirs (not where the black pixels took the second light: a lobe casts
no shadow). That light starts at the one-light fit and at each of the more lights alone: beside
other objects a metal's one diffuse light lands between its lamp and the lobe's peak, where
one of the pair's lights is near the lamp. Rough gold and aluminium then take one light in 10 of 16
frames (``benchmarks/results/gloss_instead_cpu2_2026-12-06.md``; 14 of 16 with the lobe's shape
refined, ``benchmarks/results/gloss_beside_cpu2_2026-12-06.md``), and a frame one light
explains never takes a lobe (tried beside every first light, ``auto``, the matte DiLiGenT
bear's faint sheen took one in 24 of 24 frames and lost 0.6 degrees). Where one light and its
lobe lose, the lobe is tried beside the lights the diffuse fit took (two lamps on a glossy
object); where they win, one light more is searched beside them (a glossy room may have two
lamps), kept only where it is farther from the first than the lobe's width
(``selfsup/estimation/reflectance.py``). Where the diffuse fit keeps one light, a lobe that
outshines it (a metal, a dark glossy paint) is tried from the highlight's mirror direction
(:func:`choose_lone_lobe`, :func:`mirror_start`): such a paint's one diffuse light can land 19
degrees off with no second light paying, and no pair then offers a light near the lamp.

With one paint over the frame (a photographed object) the lobe is one more term of the
shading, its ratio to the diffuse light (``ks / kd``) and its shininess one pair for the
frame: ``S = a + sum_i L_i (D_i + r P_i)``, ``P_i`` the Blinn-Phong lobe of light ``i``
(:func:`render.light_transport`'s specular map) on the side the light reaches. Each
segment's free albedo still divides out, since the lobe is scaled with it (a dielectric's
white lobe over a coloured paint is this to the extent that one paint's level fixes ``r``).
:func:`choose_gloss` tries a grid of both at the first light's position and keeps the lobe
where the criterion prefers it (two parameters more); every later fit of the image (with
``auto``: its second light, the verdict; its intensities) then sees it through the problem's
``gloss``.
"""

from __future__ import annotations

import itertools
import math

import torch
from torch import Tensor

from selfsup.estimation.albedo_free.fit import FINAL_TOLERANCE, refine_positions
from selfsup.estimation.albedo_free.observation import AlbedoFreeFit, observe
from selfsup.estimation.problem import FitProblem, centre_and_size, subsample

__all__ = ["choose_gloss", "choose_coat", "choose_lone_lobe", "fit_lobes", "keep_lobes", "mirror_start", "diffuse_images",
           "gloss_parameters", "lobe_of", "coated_images", "GLOSS_RATIOS", "GLOSS_SHININESS", "GLOSS_PARAMETERS"]

# The grid of lobes tried (ratio of the lobe's peak to the diffuse light, Blinn-Phong
# shininess): from a paint's broad sheen to a metal whose diffuse light is nil, and from a
# rough lobe (GGX alpha 0.45) to a fairly sharp one (alpha 0.16; a sharper highlight is a few
# pixels, left out as such). Ad hoc, 2026-12-06, on the Mitsuba studio objects: rough gold
# (alpha 0.25, Blinn-Phong 30) chose (10, 10) in 8 of 8 frames on a 6 x 5 grid.
GLOSS_RATIOS = (0.3, 1.0, 3.0, 10.0, 30.0)
GLOSS_SHININESS = (4.0, 12.0, 40.0, 120.0)
GLOSS_STRIDE = 4  # the grid is tried at every fourth pixel (every second: the same lobes chosen on
# 24 Mitsuba metal frames, one frame fewer of sharp gold taking one, at 2.2 times the time)
GLOSS_ITERATIONS = (8, 12)  # LM steps of every lobe of the grid, then of the best at full resolution
GLOSS_PARAMETERS = 2  # the ratio and the shininess, counted by the criterion
# The coat's choice, counted by the criterion where it is chosen (choose_coat). Priced at 0, rooms
# whose paint is mostly matte took a coat that fitted a little better: eight capture sets 176 -> 172
# successes, 67 -> 64 counts; at 1, 175 and 67 (ad hoc, 2026-12-07: coat_albedo_free_cpu1_2026-12-07.md).
COAT_PARAMETERS = 1
# Each start's best lobe of the grid is then refined on the 8 lobes about it, each round at half
# the last step (in log; the grid's is a factor of about 3.2 in both): the grid alone is too
# coarse for a lobe between its shininesses (our renderer's rough gold-like paint, Blinn-Phong 8
# beside a box and a cylinder: two lights, 9.8 degrees off, on the grid; one and its lobe, 1.0,
# refined twice; Mitsuba's aluminium one light in 7 of 8 frames, 4 on the grid). Refined, the lobe
# also takes a pair's place in the tracking benchmark's glossy room lit by two lamps, whose dim
# second lamp does not pay beside it even started from the truth (benchmarks/results/
# gloss_beside_cpu2_2026-12-06.md).
GLOSS_REFINE_ROUNDS = 2
# A start within this share of the scene size of an earlier one is the same start (a two-light
# fit's brighter light is often where the one-light fit was): left out of the grid.
SAME_START = 0.05
# A lobe beside one light (:func:`choose_lone_lobe`) only where it outshines the diffuse light
# (its ratio at least this): a metal or a dark glossy paint, whose one diffuse light lands between
# the lamp and the lobe's peak. A paint's sheen stays with the highlight left out: the DiLiGenT
# bear's lobe fits at 0.4-0.56 and our generator's white gloss at 0.71-0.75 (its light within a
# degree without it); our gold-like paint at 10 (truth 8). Ad hoc, 2026-12-07 (docs/decisions.md).
LONE_LOBE_RATIO = 1.0
# The screen before it: these lobes at every SCREEN_STRIDE-th pixel, SCREEN_ITERATIONS LM steps
# from the highlight's mirror; the grid is tried only where one of them has a lower loss than the
# diffuse light there (3 of 34 one-light Mitsuba rooms, 1 of 12 bear frames, no ball frame).
SCREEN_LOBES = ((3.0, 12.0), (10.0, 12.0), (30.0, 12.0))
SCREEN_STRIDE = 8
SCREEN_ITERATIONS = 5
# The highlight of :func:`mirror_start`: the brightest MIRROR_QUANTILE of the pixels whose normal
# faces the camera (cosine above MIRROR_FACING; a depth map's normals at an outline are not a
# highlight's), and the light at least MIRROR_DISTANCE scene sizes from it (a lobe fitted from a
# light as near as the diffuse fit's, a third of a metre from the dark-metal sphere, stayed there).
MIRROR_QUANTILE = 0.9
MIRROR_FACING = 0.3
MIRROR_DISTANCE = 1.0


def choose_gloss(problem: FitProblem, found: AlbedoFreeFit, labels: Tensor | None, robust_scale: float,
                 criterion, residuals: str = "segments", against: list[float] | None = None,
                 starts: list[AlbedoFreeFit] = (), shapes: Tensor | None = None) -> tuple[FitProblem, AlbedoFreeFit]:
    """Each image's specular lobe, or none: the best of :func:`fit_lobes` kept where its
    ``criterion(fit, extra)`` (a list per image; lower is better; :data:`GLOSS_PARAMETERS`
    more) is below the diffuse fit's (``found``'s), and below ``against`` (a criterion per
    image, e.g. of the diffuse fit with more lights) where given (:func:`keep_lobes`).
    Returns the problem with its ``gloss (B, 2)`` (a ratio of 0 where none was kept; None
    where no image kept one) and each image's fit, with or without it. The other arguments:
    as :func:`fit_lobes`."""
    gloss, fitted, values = fit_lobes(problem, found, labels, robust_scale, criterion, residuals, starts, shapes)
    return keep_lobes(problem, found, gloss, fitted, values, criterion, against)


def choose_coat(problem: FitProblem, found: AlbedoFreeFit, labels: Tensor | None, robust_scale: float,
                criterion, residuals: str = "segments", always: bool = False) -> tuple[FitProblem, AlbedoFreeFit]:
    """Each image's diffuse light through a clear coat, or not: ``found``'s lights refined with
    the coat on every pixel (:mod:`render.coat`: a dielectric's transmission in and out, which
    dims the diffuse light towards grazing angles as glossy paint and plastic do), kept where
    ``criterion(fit, extra)`` (a list per image, lower is better) is below ``found``'s, the coat's
    choice one parameter more (:data:`COAT_PARAMETERS`; its index and roughness are fixed), or
    everywhere with ``always``. Returns the
    problem with its coat (``material.coat (B, H, W, 1)``, 0 where none; unchanged where no image
    keeps one) and each image's fit. ``labels``, ``robust_scale``, ``residuals``: as :func:`observe`."""
    B, H, W = problem.gbuffer.mask.shape
    every = problem.image.new_ones(B, H, W, 1)
    seen = observe(problem.with_coat(every), robust_scale, residuals=residuals, labels=labels)
    fitted = refine_positions(seen, found.position, found.log_weight, GLOSS_ITERATIONS[1], FINAL_TOLERANCE,
                              log_bounce=found.log_bounce)
    take = [True] * B if always else [c < p for p, c in zip(criterion(found), criterion(fitted, [COAT_PARAMETERS] * B))]
    if not any(take):
        return problem, found
    take = torch.tensor(take, device=problem.image.device)
    return problem.with_coat(every * take[:, None, None, None]), found.chosen(take, fitted)


def fit_lobes(problem: FitProblem, found: AlbedoFreeFit, labels: Tensor | None, robust_scale: float,
              criterion, residuals: str = "segments", starts: list[AlbedoFreeFit] = (),
              shapes: Tensor | None = None, min_ratio: float = 0.0) -> tuple[Tensor, AlbedoFreeFit, list[float]]:
    """Each image's best specular lobe: every lobe of :data:`GLOSS_RATIOS` x
    :data:`GLOSS_SHININESS` (and of ``shapes (B, K, 2)``, ratios and shininesses of each
    image's own) refined from ``found`` (a fit of ``problem``, its lights held in number; and
    from each fit of as many lights in ``starts``, other places they may start, unless
    :data:`SAME_START` of the scene size from an earlier one in every image) at
    :data:`GLOSS_STRIDE`; each start's best lobe refined about it (:data:`GLOSS_REFINE_ROUNDS`)
    and at full resolution, and the one of lowest ``criterion(fit, extra)`` kept. Returns its
    ``gloss (B, 2)``, its fit and its criterion (a list per image). ``labels``,
    ``robust_scale``, ``residuals``: as :func:`observe`. ``min_ratio``: the grid's ratios below it
    are left out."""
    B = problem.batch
    ratios = [r for r in GLOSS_RATIOS if r >= min_ratio]
    grid = torch.tensor(list(itertools.product(ratios, GLOSS_SHININESS)), dtype=problem.image.dtype,
                        device=problem.image.device)[None].expand(B, -1, -1)  # (B, G, 2)
    shapes = grid if shapes is None else torch.cat([grid, shapes.to(grid)], 1)
    fits = [found]
    _, size = centre_and_size(problem)
    for start in starts:  # each start unless every image has it already
        apart = torch.stack([(start.position - f.position).norm(dim=-1).amax(1) for f in fits]).amin(0)
        if bool((apart > SAME_START * size).any()):
            fits.append(start)
    G = shapes.shape[1]
    S = len(fits)
    tries = S * G  # each image's grid: every lobe from every start
    rows = torch.arange(B, device=problem.image.device).repeat_interleave(tries)
    L = found.position.shape[1]
    position = torch.stack([f.position for f in fits], 1)[:, :, None].expand(-1, -1, G, -1, -1).reshape(B * tries, L, 3)
    log_weight = torch.stack([f.log_weight for f in fits], 1)[:, :, None].expand(-1, -1, G, -1).reshape(B * tries, -1)
    combos = shapes[:, None].expand(-1, S, -1, -1).reshape(B * S, G, 2)  # each start's lobes
    tiled = subsample(problem.select(rows).with_gloss(combos.reshape(-1, 2)), GLOSS_STRIDE)
    coarse_labels = None if labels is None else labels[rows][:, ::GLOSS_STRIDE, ::GLOSS_STRIDE]
    seen = observe(tiled, robust_scale, residuals=residuals, labels=coarse_labels)
    tried = refine_positions(seen, position, log_weight, GLOSS_ITERATIONS[0])
    # Each start's best lobe of the grid, refined about it and at full resolution; each image
    # keeps the start whose lobe has the lowest criterion.
    best = tried.loss.view(B * S, G).argmin(1)  # (B S,)
    pick = torch.arange(B * S, device=best.device) * G + best
    gloss = combos[torch.arange(B * S, device=best.device), best]  # (B S, 2)
    coarse = AlbedoFreeFit.rows([(tried, int(r)) for r in pick])  # the grid's best fits
    each = torch.arange(B, device=best.device).repeat_interleave(S)
    images, each_labels = problem.select(each), None if labels is None else labels[each]
    gloss, coarse = _refined_lobes(images, gloss, coarse, each_labels, robust_scale, residuals)
    full = observe(images.with_gloss(gloss), robust_scale, residuals=residuals, labels=each_labels)
    fitted = refine_positions(full, coarse.position, coarse.log_weight, GLOSS_ITERATIONS[1], FINAL_TOLERANCE)
    values = criterion(fitted, [GLOSS_PARAMETERS] * (B * S))
    kept = [b * S + min(range(S), key=lambda k: values[b * S + k]) for b in range(B)]
    return gloss[kept], AlbedoFreeFit.rows([(fitted, r) for r in kept]), [values[r] for r in kept]


def keep_lobes(problem: FitProblem, found: AlbedoFreeFit, gloss: Tensor, fitted: AlbedoFreeFit, values: list[float],
               criterion, against: list[float] | None = None) -> tuple[FitProblem, AlbedoFreeFit]:
    """Each image's lobe ``gloss (B, 2)`` and its fit (criterion ``values``, from
    :func:`fit_lobes`) kept where below ``found``'s criterion and ``against`` (where given):
    as :func:`choose_gloss` returns them."""
    plain = criterion(found)
    if against is not None:
        plain = [min(p, a) for p, a in zip(plain, against)]
    take = torch.tensor([c < p for p, c in zip(plain, values)], device=problem.image.device)
    if not bool(take.any()):
        return problem, found
    gloss = torch.where(take[:, None], gloss, torch.zeros_like(gloss))
    return problem.with_gloss(gloss), found.chosen(take, fitted)


def _refined_lobes(problem: FitProblem, gloss: Tensor, fit: AlbedoFreeFit, labels: Tensor | None, robust_scale: float,
                   residuals: str) -> tuple[Tensor, AlbedoFreeFit]:
    # Each image's lobe ``gloss (B, 2)`` and its fit at GLOSS_STRIDE, refined for
    # GLOSS_REFINE_ROUNDS rounds: the 8 lobes about it at the round's step (in log) refined as
    # the grid's were, the lowest loss kept (the lobe itself where none is lower).
    if GLOSS_REFINE_ROUNDS == 0:  # off: no 8-fold copies of the labels for nothing
        return gloss, fit
    B = problem.batch
    step = torch.tensor([math.log(GLOSS_RATIOS[-1] / GLOSS_RATIOS[0]) / (len(GLOSS_RATIOS) - 1),
                         math.log(GLOSS_SHININESS[-1] / GLOSS_SHININESS[0]) / (len(GLOSS_SHININESS) - 1)],
                        dtype=gloss.dtype, device=gloss.device)
    around = torch.tensor([(a, b) for a in (-1.0, 0.0, 1.0) for b in (-1.0, 0.0, 1.0) if (a, b) != (0.0, 0.0)],
                          dtype=gloss.dtype, device=gloss.device)  # (8, 2)
    rows = torch.arange(B, device=gloss.device).repeat_interleave(len(around))
    coarse_labels = None if labels is None else labels[rows][:, ::GLOSS_STRIDE, ::GLOSS_STRIDE]
    for _ in range(GLOSS_REFINE_ROUNDS):
        step = step / 2
        lobes = gloss[:, None] * (around * step).exp()  # (B, 8, 2)
        seen = observe(subsample(problem.select(rows).with_gloss(lobes.reshape(-1, 2)), GLOSS_STRIDE), robust_scale,
                       residuals=residuals, labels=coarse_labels)
        tried = refine_positions(seen, fit.position[rows], fit.log_weight[rows], GLOSS_ITERATIONS[0])
        loss, best = tried.loss.view(B, len(around)).min(1)
        better = loss < fit.loss
        pick = torch.arange(B, device=best.device) * len(around) + best
        gloss = torch.where(better[:, None], lobes[torch.arange(B, device=best.device), best], gloss)
        fit = fit.chosen(better, AlbedoFreeFit.rows([(tried, int(r)) for r in pick]))
    return gloss, fit


def choose_lone_lobe(problem: FitProblem, found: AlbedoFreeFit, labels: Tensor | None, robust_scale: float,
                     criterion, residuals: str = "segments") -> tuple[FitProblem, AlbedoFreeFit]:
    """Each one-light image's lobe that outshines its diffuse light (ratio at least
    :data:`LONE_LOBE_RATIO`), or none: its light started at the highlight's mirror
    (:func:`mirror_start`), screened (:func:`_lobe_screen`), then the grid's lobes of that ratio
    or more fitted (:func:`fit_lobes`) and kept where the criterion prefers them to ``found``
    (one light, diffuse). Returns as :func:`choose_gloss`. The diffuse fit's light is no start:
    on a lobe-dominated paint it lies between the lamp and the highlight (our gold-like paint,
    18.7 degrees off), and a lobe fitted from there stays near it."""
    if found.position.shape[1] != 1:
        raise ValueError(f"choose_lone_lobe fits a lobe beside one light, got {found.position.shape[1]}")
    start = mirror_start(problem, found, labels, robust_scale, residuals)
    passed = _lobe_screen(problem, found, start, labels, robust_scale, residuals)
    if not bool(passed.any()):
        return problem, found
    at = passed.nonzero()[:, 0]
    sub = problem.select(at)
    shapes, fitted, values = fit_lobes(sub, AlbedoFreeFit.rows([(start, int(i)) for i in at]),
                                       None if labels is None else labels[at], robust_scale, criterion, residuals,
                                       min_ratio=LONE_LOBE_RATIO)
    # The refinement about the grid may take a lobe below the ratio: not kept.
    values = [v if ratio >= LONE_LOBE_RATIO else math.inf for v, ratio in zip(values, shapes[:, 0].tolist())]
    # Every image: a lobe where screened, fitted and kept; none elsewhere.
    gloss = problem.image.new_zeros(problem.batch, 2)
    gloss[at] = shapes.to(gloss)
    every = [math.inf] * problem.batch
    for j, i in enumerate(at.tolist()):
        every[i] = values[j]
    return keep_lobes(problem, found, gloss, _scattered(found, fitted, at), every, criterion)


def _scattered(like: AlbedoFreeFit, part: AlbedoFreeFit, at: Tensor) -> AlbedoFreeFit:
    # ``like`` with its rows ``at`` replaced by ``part``'s rows in turn.
    rows = [(like, i) for i in range(like.position.shape[0])]
    for j, i in enumerate(at.tolist()):
        rows[i] = (part, j)
    return AlbedoFreeFit.rows(rows)


def _lobe_screen(problem: FitProblem, found: AlbedoFreeFit, start: AlbedoFreeFit, labels: Tensor | None,
                 robust_scale: float, residuals: str) -> Tensor:
    """``(B,)`` bool: whether one of :data:`SCREEN_LOBES`, its light refined from ``start`` by
    :data:`SCREEN_ITERATIONS` LM steps at every :data:`SCREEN_STRIDE`-th pixel, has a lower loss
    there than ``found`` (diffuse) as it stands."""
    B, K, s = problem.batch, len(SCREEN_LOBES), SCREEN_STRIDE
    lobes = problem.image.new_tensor(SCREEN_LOBES).repeat(B, 1)  # (B K, 2)
    rows = torch.arange(B, device=problem.image.device).repeat_interleave(K)
    coarse = None if labels is None else labels[:, ::s, ::s]
    glossy = observe(subsample(problem.select(rows).with_gloss(lobes), s), robust_scale, residuals=residuals,
                     labels=None if coarse is None else coarse[rows])
    tried = refine_positions(glossy, start.position[rows], start.log_weight[rows], SCREEN_ITERATIONS)
    plain = observe(subsample(problem, s), robust_scale, residuals=residuals, labels=coarse)
    diffuse = refine_positions(plain, found.position, found.log_weight, 0)
    return tried.loss.view(B, K).amin(1) < diffuse.loss


def mirror_start(problem: FitProblem, found: AlbedoFreeFit, labels: Tensor | None, robust_scale: float,
                 residuals: str = "segments") -> AlbedoFreeFit:
    """``found`` with its first light moved to the mirror of the frame's highlight: where a
    surface shows its lamp's lobe, the lamp lies along the view ray reflected about the normal.
    The highlight is the :data:`MIRROR_QUANTILE` brightest of the valid pixels facing the camera
    (brightness against each segment's level: one paint's brightest patch, not a white wall), its
    normal, view direction and point their brightness-weighted means; the light stands as far from
    that point as ``found``'s first light, at least :data:`MIRROR_DISTANCE` scene sizes. On our
    generator's dark metal beside a box and a cylinder, where the diffuse light lands 12-18
    degrees off, this start lies within 0.8-2.5 degrees of the lamp. Images without such pixels
    (or without segments) keep ``found``'s light; the weights, loss and pairs are ``found``'s."""
    seen = observe(problem, robust_scale, residuals=residuals, labels=labels)
    if seen.segments is None:
        return found
    log_shading = seen.log_shading.flatten(1)  # (B, P)
    points, normals = problem.gbuffer.points.flatten(1, 2), problem.gbuffer.normals.flatten(1, 2)  # (B, P, 3)
    toward_camera = torch.nn.functional.normalize(-points, dim=-1)
    facing = seen.pairs & ((normals * toward_camera).sum(-1) > MIRROR_FACING)
    bright = torch.where(facing, log_shading - seen.offsets(log_shading), torch.zeros_like(log_shading)).clamp_min(0)
    weight = torch.zeros_like(bright)
    for b in range(problem.batch):  # each image's own brightest share
        lit = bright[b][bright[b] > 0]
        if lit.numel() >= 10:
            weight[b] = torch.where(bright[b] >= torch.quantile(lit, MIRROR_QUANTILE), bright[b], 0.0)
    total = weight.sum(1, keepdim=True)  # (B, 1)

    def mean(x: Tensor) -> Tensor:  # (B, P, 3) -> (B, 3), brightness-weighted
        return (x * weight[..., None]).sum(1) / total.clamp_min(1e-30)

    normal = torch.nn.functional.normalize(mean(normals), dim=-1)
    view = torch.nn.functional.normalize(mean(toward_camera), dim=-1)
    point = mean(points)
    mirror = 2 * (normal * view).sum(-1, keepdim=True) * normal - view  # (B, 3)
    _, size = centre_and_size(problem)
    distance = torch.maximum((found.position[:, 0] - point).norm(dim=-1, keepdim=True), MIRROR_DISTANCE * size[:, None])
    position = found.position.clone()
    position[:, 0] = torch.where(total > 0, point + distance * mirror, found.position[:, 0])
    return AlbedoFreeFit(position, found.log_weight, found.loss, found.pairs)


def diffuse_images(problem: FitProblem) -> Tensor:
    """``(B,)`` bool: the images whose albedo-free model has no specular lobe."""
    if problem.gloss is None:
        return torch.ones(problem.batch, dtype=torch.bool, device=problem.image.device)
    return ~(problem.gloss[:, 0] > 0)


def gloss_parameters(problem: FitProblem) -> list[int]:
    """Each image's parameters of its albedo-free glossy terms: its specular lobe's two
    (:attr:`FitProblem.gloss`) and its coat's choice (:data:`COAT_PARAMETERS`, :func:`coated_images`), where it
    has them."""
    return [(0 if diffuse else GLOSS_PARAMETERS) + COAT_PARAMETERS * coat
            for diffuse, coat in zip(diffuse_images(problem).tolist(), coated_images(problem).tolist())]


def coated_images(problem: FitProblem) -> Tensor:
    """``(B,)`` bool: the images whose diffuse light goes through a clear coat (:func:`choose_coat`)."""
    if problem.material.coat is None:
        return torch.zeros(problem.batch, dtype=torch.bool, device=problem.image.device)
    return problem.material.coat.flatten(1).amax(1) > 0


def lobe_of(problem: FitProblem, row: int) -> tuple[float, float] | None:
    """Image ``row``'s albedo-free specular lobe ``(ratio, shininess)``, or None (diffuse only)."""
    if problem.gloss is None or not float(problem.gloss[row, 0]) > 0:
        return None
    ratio, shininess = problem.gloss[row].tolist()
    return round(ratio, 4), round(shininess, 2)
