"""Where no light reaches: black pixels as evidence of the light count, whatever the albedo.

A capture of direct light alone is black (at 8 bits, 0) wherever no light reaches: in the
cast shadow of every light and on surfaces facing away from all of them. A model of the
lights predicts that set (its *unlit* pixels: direct shading with cast shadows at zero).
Where it predicts unlit pixels that the capture shows lit, some light is missing: a
second light lights the first one's shadows, dimly or not, at any albedo. The albedo-free
fit (:mod:`selfsup.estimation.albedo_free`) cannot see that: its log shading leaves black
pixels out, and each albedo segment's free level absorbs a shadow's brightness.

Indirect light (a room's bounce, a path-traced render) lights every shadow too, so the test
holds only where the capture's darkness *is* the fewer lights' shadow
(:func:`shadow_lit_only`): enough black pixels, most of them predicted unlit. A capture
with indirect light has no black pixel in its shadows and is left to the other criteria.

Measured (ad hoc, docs/decisions.md 2026-11-27): on our Mitsuba direct-light captures the
one-light fit's unlit pixels that are lit were 3-380 in one-light rooms and up to 3,400 in
two-light rooms; path-traced captures have next to no black pixel.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from render.functional import light_transport
from selfsup.estimation.problem import FitProblem
from selfsup.model import brightest_percentile

__all__ = ["dark_pixels", "unlit_pixels", "mismatch", "shadow_lit_only", "unlit_black", "needs_another_light"]

# A pixel is black when its brightest channel is at most this share of the 99th
# percentile of the valid pixels' (8-bit sRGB 0 decodes to 0; 1 is 3e-4 of full scale).
DARK_LEVEL = 0.005
# A model's pixel is unlit when its direct shading is under this share of its median.
UNLIT_LEVEL = 1e-3
# The capture's darkness is the fewer lights' shadow where at least this share of the
# valid pixels is black and predicted unlit, and that is at least DARK_EXPLAINED of
# the black pixels.
MIN_DARK_SHARE = 0.002
DARK_EXPLAINED = 0.5
# One light more is needed where its model's mismatch (:func:`mismatch`) is at most
# MISMATCH_RATIO of the fewer lights' and smaller by at least MISMATCH_GAIN of the
# valid pixels.
MISMATCH_RATIO = 0.7
MISMATCH_GAIN = 0.008
# ... and the model with one light more is itself one of direct light alone: at least
# this share of its unlit pixels is black (where it leaves MIN_DARK_SHARE of the pixels
# unlit or more). A path-traced capture's few black pixels (an open room's walls that
# no bounce reaches) otherwise took a second light for the shadows its indirect light
# fills (ad hoc, 2 of 24 one-light Mitsuba rooms; its unlit pixels 6-52% black, those
# of the two-light direct rooms 64-97%).
UNLIT_BLACK = 0.6


def dark_pixels(image: Tensor, mask: Tensor, level: float = DARK_LEVEL) -> Tensor:
    """``(B, H, W)`` bool: valid pixels whose brightest channel is at most ``level`` x
    the 99th percentile of the valid pixels' brightest channel.

    Args:
        image: ``(B, 3, H, W)`` linear; mask: ``(B, H, W)`` valid pixels.
    """
    top = brightest_percentile(image, mask)  # the network's exposure (selfsup.model.scene_frame)
    return mask & (image.amax(1) <= level * top[:, None, None])


def unlit_pixels(problem: FitProblem, position: Tensor, intensity: Tensor, level: float = UNLIT_LEVEL) -> Tensor:
    """``(B, H, W)`` bool: valid pixels that lights at ``position (B, L, 3)`` of relative
    ``intensity (B, L)`` leave unlit (direct shading with ``problem``'s cast shadows under
    ``level`` x its median over the valid pixels)."""
    diffuse = light_transport(problem.gbuffer, problem.material, position, falloff=problem.falloff,
                              shadows=problem.shadows, shadow_options=problem.shadow_options, specular=False).diffuse
    shading = (intensity[:, :, None, None] * diffuse).sum(1)
    mask = problem.gbuffer.mask
    median = torch.where(mask, shading, torch.full_like(shading, float("nan"))).flatten(1).nanmedian(1).values
    return mask & (shading < level * torch.nan_to_num(median, nan=0.0)[:, None, None])


def _eroded(x: Tensor) -> Tensor:
    # (B, H, W) bool -> the pixels whose 3x3 neighbourhood is all set.
    return -F.max_pool2d(-x[:, None].float(), 3, 1, 1)[:, 0] > 0.5


def mismatch(dark: Tensor, unlit: Tensor, mask: Tensor) -> Tensor:
    """``(B,)`` share of the valid pixels where a model's unlit set and the capture's
    black pixels disagree (predicted unlit but lit, or predicted lit but black), counting
    only pixels whose 3x3 neighbourhood disagrees alike: a shadow edge a pixel off, or
    the speckle of noisy depth, is not a light's footprint."""
    lit = mask & ~dark
    wrong = _eroded(unlit & lit) | _eroded(~unlit & dark & mask)
    return wrong.flatten(1).sum(1) / mask.flatten(1).sum(1).clamp_min(1)


def shadow_lit_only(dark: Tensor, unlit: Tensor, mask: Tensor) -> Tensor:
    """``(B,)`` bool: the capture's black pixels are the shadows of ``unlit``'s model (at
    least :data:`MIN_DARK_SHARE` of the valid pixels black and predicted unlit, and that
    :data:`DARK_EXPLAINED` of the black pixels), so no indirect light lights its shadows."""
    explained = (dark & unlit).flatten(1).sum(1)
    valid = mask.flatten(1).sum(1).clamp_min(1)
    return (explained >= MIN_DARK_SHARE * valid) & (explained >= DARK_EXPLAINED * dark.flatten(1).sum(1))


def unlit_black(dark: Tensor, unlit: Tensor, mask: Tensor) -> Tensor:
    """``(B,)`` bool: at least :data:`UNLIT_BLACK` of a model's unlit pixels are black (or
    it leaves fewer than :data:`MIN_DARK_SHARE` of the valid pixels unlit): a model of
    direct light alone, as the capture is."""
    unlit_count = unlit.flatten(1).sum(1)
    return ((dark & unlit).flatten(1).sum(1) >= UNLIT_BLACK * unlit_count) | (
        unlit_count < MIN_DARK_SHARE * mask.flatten(1).sum(1))


def needs_another_light(problem: FitProblem, fewer: tuple[Tensor, Tensor], more: tuple[Tensor, Tensor]) -> Tensor:
    """``(B,)`` bool: the black pixels of ``problem``'s capture say that the model of one
    light more is needed: its shadows are the capture's darkness (:func:`shadow_lit_only`
    of the fewer lights' model), the model with one light more disagrees with the
    black pixels on :data:`MISMATCH_RATIO` of the pixels or fewer, :data:`MISMATCH_GAIN`
    of them less at least, and its own unlit pixels are black (:data:`UNLIT_BLACK`).

    Args:
        problem: the images, with the cast shadows to judge by (``problem.shadows``).
        fewer, more: each model's positions ``(B, L, 3)`` and relative intensities ``(B, L)``.
    """
    mask = problem.gbuffer.mask
    dark = dark_pixels(problem.image, mask)
    needed = torch.zeros(problem.batch, dtype=torch.bool, device=mask.device)
    # Only images black on MIN_DARK_SHARE of their pixels can pass shadow_lit_only: the
    # others (a capture with indirect light) cast no shadows here.
    maybe = (dark.flatten(1).sum(1) >= MIN_DARK_SHARE * mask.flatten(1).sum(1)).nonzero()[:, 0]
    if not maybe.numel():
        return needed
    problem, dark, mask = problem.select(maybe), dark[maybe], mask[maybe]
    unlit_fewer = unlit_pixels(problem, *(x[maybe] for x in fewer))
    unlit_more = unlit_pixels(problem, *(x[maybe] for x in more))
    before, after = mismatch(dark, unlit_fewer, mask), mismatch(dark, unlit_more, mask)
    needed[maybe] = (shadow_lit_only(dark, unlit_fewer, mask) & unlit_black(dark, unlit_more, mask)
                     & (after <= MISMATCH_RATIO * before) & (before - after >= MISMATCH_GAIN))
    return needed
