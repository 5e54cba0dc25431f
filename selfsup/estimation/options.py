"""The estimator's settings: what a user chooses, and the tuned constants.

:class:`EstimateOptions` holds the user's choices (``configs/estimate/default.yaml``
shows them with the file and process settings of ``mode=estimate``); everything
measured and tuned lives in the frozen :class:`Tuning` (its optimiser part in
:class:`RefineOptions`), whose defaults are written here alone. What each constant
does, and the measurements behind it: ``docs/estimation.md``, "Tuning".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

from render.shadows import ShadowMethod

__all__ = ["EstimateOptions", "Tuning", "RefineOptions", "METHODS", "SHADOW_METHODS"]

METHODS = ("cnn+refine", "cnn", "refine")
SHADOW_METHODS = tuple(m.value for m in ShadowMethod)
NORMAL_SMOOTHING = ("auto", "always", "never")
REFLECTANCE = ("auto", "given", "albedo_free")
INDIRECT = ("auto", "never")
COAT = ("auto", "never", "always")
ALBEDO_FREE_COAT = ("chosen", "auto", "never", "always")
ALBEDO_FREE_RESIDUALS = ("segments", "pairs")
LIGHT_COLOUR = ("neutral", "shared", "free")
VIGNETTING = ("auto", "none")
HIGHLIGHTS = ("leave_out", "keep")
ALBEDO_FREE_BOUNCE = ("auto", "never")
ALBEDO_FREE_GLOSS = ("auto", "instead", "never")
ALBEDO_FREE_COUNT = ("segments", "classes", "either")
CNN_COUNT = ("criterion", "network")
CNN_START = ("settled", "search")
REFINE_METHODS = ("lm", "adam", "gd")


@dataclass(frozen=True)
class RefineOptions:
    """Optimiser settings of the light refinement (:func:`selfsup.estimation.solvers.refine`).

    ``method``: ``lm`` | ``adam`` | ``gd`` (the paper's: rate 0.02, stop at a relative
    change of 1e-4). ``max_iters`` per pyramid level, ``strides``: coarse-to-fine pixel
    strides. ``tol``: stop when the relative cost decrease of an accepted step falls
    below it; ``step_tol`` (``lm``): or when a step moves every light less than this, in
    scene sizes. ``robust``: Cauchy IRLS with scale ``robust_scale`` x the median observed
    value, at least ``robust_noise_floor`` x the image's noise level
    (:meth:`~selfsup.estimation.problem.FitProblem.noise_level`); ``irls_passes``:
    reweighting passes solving the intensities and ambient at fixed positions.
    ``fd_step``: forward-difference step of the shadow Jacobian, in scene sizes.
    ``learning_rate``: adam / gd. ``specular``: whether the specular term is computed.
    """

    method: str = "lm"
    max_iters: tuple[int, ...] = (30, 10)
    strides: tuple[int, ...] = (4, 1)
    tol: float = 1e-4
    step_tol: float = 1e-4
    robust: bool = True
    robust_scale: float = 0.2
    robust_noise_floor: float = 1.0
    irls_passes: int = 4
    fd_step: float = 1e-3
    learning_rate: float = 0.02
    specular: bool = True

    def __post_init__(self):
        object.__setattr__(self, "max_iters", tuple(self.max_iters))
        object.__setattr__(self, "strides", tuple(self.strides))
        if self.method not in REFINE_METHODS:
            raise ValueError(f"method must be lm, adam or gd, got {self.method!r}")
        if len(self.max_iters) != len(self.strides):
            raise ValueError(f"max_iters {self.max_iters} and strides {self.strides} must have the same length")
        if not self.strides or any(s < 1 for s in self.strides) or any(i < 0 for i in self.max_iters):
            raise ValueError(f"strides need one level or more, each >= 1, and max_iters >= 0, got strides "
                             f"{self.strides} and max_iters {self.max_iters}")
        if not (self.fd_step > 0 and self.learning_rate > 0):  # 0: no shadow derivative, no first-order step
            raise ValueError(f"fd_step and learning_rate must be > 0, got {self.fd_step}, {self.learning_rate}")
        if not (self.tol >= 0 and self.step_tol >= 0):
            raise ValueError(f"tol and step_tol must be >= 0, got {self.tol}, {self.step_tol}")
        if self.irls_passes < 1:
            raise ValueError(f"irls_passes must be >= 1, got {self.irls_passes}")
        if not (self.robust_scale > 0 and self.robust_noise_floor >= 0):
            raise ValueError(f"robust_scale must be > 0 and robust_noise_floor >= 0, got {self.robust_scale}, "
                             f"{self.robust_noise_floor}")


@dataclass(frozen=True)
class Tuning:
    """The estimator's tuned constants, one place for their defaults.

    Each is described in one line here; ``docs/estimation.md`` ("Tuning") gives what
    it does in full and the measurements it was chosen by. Change them from Python
    (``EstimateOptions(tuning=Tuning(coat="never"))``) or from the command line
    (``+estimate.tuning.coat=never``).

    Starts and model selection:
        cnn_grid, cnn_starts: ``cnn+refine`` searches this grid beside the network's
            slots and starts from this many of its best.
        cnn_start: ``cnn+refine``'s first light where the albedo is unknown and no checkpoint
            is named: ``search`` (the grid search, the cost-volume network's lights among its
            starts) or ``settled`` (``cnn``'s answer, the shipped iterative networks settled and
            picked on the frame, refined with no grid; one light more searched leanly beside it:
            1.1-1.5x faster on capture folders, as many successes, but six hard test cases
            fail, glossy lobes among them; not the default).
        cnn_sure: with ``cnn_start=search`` or a named checkpoint, ``cnn+refine`` searches nothing
            where the network's calibrated confidence (an iterative network's,
            :attr:`selfsup.network.IterativePrediction.confidence`) reaches this: its lights are
            refined instead (above 1: search everywhere).
        cnn_settle, cnn_settle_stride: ``cnn`` settles the network's counted slots by this many
            LM steps on every that-many-th pixel (albedo-free on the frame's albedo segments
            where the albedo is unknown; 0: the slots as they are), no search. 15 steps, not 5:
            the network's second slot often lies 0.2-0.6 of the scene from the second lamp, and a
            pair settled further is counted in 55 of 126 two-light captures against 45 (method=cnn,
            eight capture sets: 161 against 155 successes, about 1.1x the command's time;
            docs/decisions.md, 2026-12-08).
        cnn_count: ``cnn``'s count where the albedo is unknown: ``criterion`` (the settled slots'
            albedo-free BIC, :func:`selfsup.estimation.network.counted`) or ``network`` (its presences).
        min_light_share: an added light must carry this share of the rendered direct
            light, or, weaker but at least ``weak_light_min_share``, show its own cast
            shadows (``weak_light_shadow_gain``, 0: off) or pay for its parameters
            ``weak_light_penalty`` times in the criterion (0: off); the black pixels
            (``unlit_evidence``) take no light under ``weak_light_min_share`` either.
        block_width: one independent residual per square block of this x the image
            width (criterion and uncertainty).
        criterion_shadows, criterion_stride, criterion_thickness: every candidate is
            judged under this shadow method, on every that-many-th pixel, with the
            solid behind each pixel this share of the scene size deep (None: unbounded).
        indirect: ``auto`` judges files without ambient with each light's indirect
            light (:mod:`selfsup.scenes.indirect`) | ``never``.
        coat: ``auto`` | ``never`` | ``always``: the specular pixels' diffuse light
            through a rough clear coat (:mod:`render.coat`).
        search_shadows: shadow method of the global search.
        final_robust_scale: Cauchy scale (x median observed) of the chosen model's
            full-resolution refinement.
    Inputs:
        normal_smoothing, normal_noise_threshold: ``auto`` refits normals noisier than
            this many degrees (the 75th percentile; ``always`` | ``never``) as planes of
            the depth over the largest window up to ``plane_window`` x the focal length on
            which the depth is a plane (:func:`selfsup.estimation.normals.planes_that_hold`),
            each pixel free to take a window ``plane_shifts`` of the half-size beside its own.
        mask_saturated: leave out clipped pixels.
        max_pixels: a larger image is estimated on k x k blocks (the least k leaving at
            most this many; None: every pixel).
    Reflectance:
        reflectance: ``auto`` fits a file whose kd is one constant albedo-free
            (:mod:`selfsup.estimation.albedo_free`) | ``given`` | ``albedo_free``;
            ``albedo_free_scale``, ``albedo_free_block_width``: that fit's Cauchy
            scale and block; ``albedo_free_residuals``: ``segments`` (each pixel's log
            shading against its albedo segment's mean; segments cut at the image's
            edges, Felzenszwalb scale ``albedo_segment_scale``, then joined where only
            shading cuts them: the log shading's step across the cut at most
            ``albedo_edge_step`` beyond what the steps beside it predict (None: not joined),
            the chromaticity's at most ``albedo_edge_chroma``) | ``pairs`` (neighbours).
            ``highlights``: ``leave_out`` (the chosen lights' mirror-lobe pixels clearly
            brighter than the diffuse model are left out of their placement, and counted
            in the record) | ``keep``.
            ``albedo_free_lobe_deg``: one more light is taken only if it wins without
            the pixels of the mirror lobes of the lights before it (normal within this many
            degrees of their half vector) that are brighter than their model: where a
            glossy surface shows their highlight, which the diffuse-only fit cannot
            explain and a light beside it can (0: every pixel).
            ``albedo_free_gloss``: ``auto`` gives the fit a specular lobe beside the diffuse
            light (its ratio and shininess one pair a frame, from a grid at the first
            light), where the criterion prefers it: metal and broad paint gloss
            (:mod:`selfsup.estimation.albedo_free.gloss`) | ``instead``: a lobe with the first
            light tried only where the diffuse fit takes more lights, kept where its criterion
            is below theirs (a lobe and a second light beside the first explain the same
            peak), not where the black pixels took the light (a lobe casts no shadow); beside
            one light only a lobe that outshines it, from the highlight's mirror | ``never``.
            ``albedo_free_coat``: ``chosen`` sends the fit's diffuse light through a clear
            coat (:mod:`render.coat`: the glossy paint's and plastic's Fresnel-weighted diffuse
            layer) where the criterion prefers it for the chosen model's lights, after their
            count (one parameter more) | ``auto``: the same at the first light, every later
            fit with it | ``always`` (at the first light) | ``never``.
            ``albedo_free_count``: where one light more is judged: ``segments`` (each
            albedo segment's level free) | ``classes`` (each model on its own segments
            merged into albedo classes, the classes counted as parameters: a light that
            explains how bright segments are beside each other pays for itself;
            :data:`selfsup.estimation.count.CLASS_COUNT_PENALTY`) | ``either`` (one
            light more where it wins either comparison).
            ``unlit_evidence``: one more light is also taken where the capture's black
            pixels need it (:mod:`selfsup.estimation.unlit`: the fewer lights' shadows
            shown lit), judged under the criterion's cast shadows.
            ``albedo_class_rounds``: the chosen model's lights refined this many times on
            its segments merged into classes of one albedo (0: off), a segment joining a
            class of its surface within ``albedo_class_level`` of its level under the model
            (log) and ``albedo_class_chroma`` of its colour (log R/G, B/G)
            (:func:`selfsup.estimation.albedo_free.albedo_classes`).
        reflectance_gains: rounds re-estimating with each smooth surface's albedo
            rescaled by the last fit.
        light_colour: the albedo-free fit's intensities, their ratios the fit's:
            ``neutral`` (the lights and the ambient the image's white) | ``shared`` (one
            colour for all, the image's mean) | ``free`` (each channel of each light and
            of the ambient solved on its own) (:func:`selfsup.estimation.intensities.intensities_of`);
            ``neutral`` also makes ``method=cnn``'s lights white where the albedo is unknown
            (:func:`selfsup.estimation.reflectance.grey_where_unknown`).
        vignetting: ``auto``: the albedo-free fit takes out the lens's falloff towards the
            corners, its strength chosen per frame with the first light
            (:mod:`selfsup.estimation.vignetting`) | ``none``.
    Reporting:
        min_found_share: lights are reported only where the brightest gives at least this
            share of the light on the visible surfaces (with cast shadows) and, albedo-free,
            the lights beat the ambient alone by the criterion; else the record says
            ``light_found: false`` (0: always report).
        evidence_spread: the albedo-free lights' evidence (the ambient alone's criterion less
            theirs) is the larger of it under the fit's own Cauchy scale (the sensor's noise) and
            under one scale fitted to the frame, this times the chosen model's residual spread
            (1.4826 x their median absolute value; 0: the fit's scale alone;
            :func:`selfsup.estimation.intensities.evidence`): 2.385, the Cauchy loss's constant
            for 95% efficiency on Gaussian residuals, so that a model that misses the shading by
            more than the sensor's noise is still judged by how much of it it explains.
    Uncertainty:
        albedo_error: std of the file's kd error (0: exact).
        indirect_variation, indirect_length: files without ambient (every capture, the
            albedo-free fit too) add a smooth field of unaccounted light, this std x the
            fitted ambient, this correlation length (of the scene size); 0: off.
        normal_error: refitted normals add their plane fits' tilt error (both fits).
    refine: the optimiser (:class:`RefineOptions`).
    """

    cnn_grid: tuple[int, int, int] = (7, 6, 7)
    cnn_starts: int = 4
    cnn_start: str = "search"
    cnn_sure: float = 0.8
    cnn_settle: int = 15
    cnn_count: str = "criterion"
    cnn_settle_stride: int = 2
    block_width: float = 0.1
    min_light_share: float = 0.1
    weak_light_shadow_gain: float = 0.01
    weak_light_min_share: float = 0.01
    weak_light_penalty: float = 2.0
    search_shadows: str = "none"
    normal_smoothing: str = "auto"
    normal_noise_threshold: float = 1.5
    plane_window: float = 0.06
    plane_shifts: tuple[float, ...] = (1.0, 0.5, 0.25)
    mask_saturated: bool = True
    final_robust_scale: float = 0.05
    reflectance_gains: int = 0
    reflectance: str = "auto"
    indirect: str = "auto"
    criterion_shadows: str = "epipolar"
    criterion_stride: int = 2
    criterion_thickness: float | None = 0.03
    albedo_free_scale: float = 0.02
    albedo_free_block_width: float = 0.05
    albedo_free_residuals: str = "segments"
    albedo_segment_scale: float = 50.0
    albedo_edge_step: float | None = 0.05
    albedo_edge_chroma: float = 0.03
    albedo_free_lobe_deg: float = 20.0
    highlights: str = "leave_out"
    albedo_free_bounce: str = "never"
    albedo_free_gloss: str = "instead"
    albedo_free_coat: str = "chosen"
    albedo_free_count: str = "segments"
    unlit_evidence: bool = True
    albedo_class_rounds: int = 1
    albedo_class_level: float = 0.1
    albedo_class_chroma: float = 0.06
    albedo_error: float = 0.0
    indirect_variation: float = 0.7
    indirect_length: float = 0.15
    normal_error: bool = True
    coat: str = "auto"
    light_colour: str = "neutral"
    vignetting: str = "auto"
    min_found_share: float = 0.1
    evidence_spread: float = 2.385
    max_pixels: int | None = 19200
    refine: RefineOptions = field(default_factory=RefineOptions)

    def __post_init__(self):
        object.__setattr__(self, "cnn_grid", tuple(self.cnn_grid))
        object.__setattr__(self, "plane_shifts", tuple(self.plane_shifts))
        if isinstance(self.refine, dict):  # from a config
            object.__setattr__(self, "refine", RefineOptions(**self.refine))
        _check_tuning(self)

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The constants' names (``refine`` included)."""
        return tuple(f.name for f in fields(cls))


def _check_choice(name: str, value, choices: tuple) -> None:
    if value not in choices:
        raise ValueError(f"estimate.{name} must be one of {choices}, got {value!r}")


def _check_tuning(t: Tuning) -> None:
    # One clear error per constant out of its range, named as on the command line.
    def need(ok: bool, name: str, what: str) -> None:
        if not ok:
            raise ValueError(f"estimate.tuning.{name} must be {what}, got {getattr(t, name)!r}")

    need(len(t.cnn_grid) == 3 and min(t.cnn_grid) >= 2, "cnn_grid", "3 grid sizes >= 2")
    need(t.cnn_starts >= 1, "cnn_starts", ">= 1")
    need(t.cnn_sure > 0, "cnn_sure", "> 0 (above 1: search everywhere)")
    need(t.cnn_settle >= 0, "cnn_settle", ">= 0 (0: the network's slots as they are)")
    need(t.cnn_settle_stride >= 1, "cnn_settle_stride", ">= 1")
    need(t.weak_light_shadow_gain >= 0, "weak_light_shadow_gain", ">= 0")
    need(t.weak_light_penalty == 0 or t.weak_light_penalty >= 1, "weak_light_penalty", "0 (off) or >= 1")
    need(t.weak_light_min_share >= 0, "weak_light_min_share", ">= 0")
    need(0 <= t.min_light_share <= 1, "min_light_share", "a share in [0, 1]")
    need(0 <= t.min_found_share <= 1, "min_found_share", "a share in [0, 1]")
    need(t.evidence_spread >= 0 and math.isfinite(t.evidence_spread), "evidence_spread",
         "a finite factor >= 0 (0: the fit's own scale)")
    for name in ("block_width", "albedo_free_block_width"):
        need(0 < getattr(t, name) <= 1, name, "in (0, 1] (of the image width)")
    need(t.final_robust_scale > 0, "final_robust_scale", "> 0")
    need(t.reflectance_gains >= 0, "reflectance_gains", ">= 0 rounds")
    need(t.albedo_error >= 0 and math.isfinite(t.albedo_error), "albedo_error",
         "a finite standard deviation >= 0 (albedo units)")
    need(t.indirect_variation >= 0 and math.isfinite(t.indirect_variation), "indirect_variation",
         "a finite standard deviation >= 0 (of the ambient)")
    need(t.indirect_length > 0 and math.isfinite(t.indirect_length), "indirect_length",
         "a finite length > 0 (of the scene size)")
    need(t.albedo_free_scale > 0, "albedo_free_scale", "> 0")
    need(t.albedo_segment_scale > 0, "albedo_segment_scale", "> 0")
    need(t.albedo_edge_step is None or 0 <= t.albedo_edge_step < math.inf, "albedo_edge_step",
         "null (segments not joined) or a log step >= 0")
    need(0 <= t.albedo_edge_chroma < math.inf, "albedo_edge_chroma", "a chromaticity step >= 0")
    need(t.albedo_class_rounds >= 0, "albedo_class_rounds", ">= 0")
    need(t.albedo_class_level >= 0, "albedo_class_level", ">= 0")
    need(t.albedo_class_chroma >= 0, "albedo_class_chroma", ">= 0")
    need(0 <= t.albedo_free_lobe_deg < 90, "albedo_free_lobe_deg", "in [0, 90) degrees")
    need(t.normal_noise_threshold >= 0, "normal_noise_threshold", ">= 0 degrees")
    need(0 < t.plane_window < 1, "plane_window", "in (0, 1) (of the focal length)")
    need(all(0 < f <= 1 for f in t.plane_shifts), "plane_shifts", "fractions in (0, 1] of the plane window")
    need(t.criterion_thickness is None or 0 < t.criterion_thickness < math.inf, "criterion_thickness",
         "null or a share of the scene size > 0")
    need(t.max_pixels is None or (isinstance(t.max_pixels, int) and t.max_pixels >= 1), "max_pixels",
         "null or an integer >= 1")
    need(t.criterion_stride >= 1, "criterion_stride", ">= 1 pixel")
    for name, choices in (("reflectance", REFLECTANCE), ("albedo_free_residuals", ALBEDO_FREE_RESIDUALS),
                          ("normal_smoothing", NORMAL_SMOOTHING), ("coat", COAT), ("light_colour", LIGHT_COLOUR), ("vignetting", VIGNETTING), ("highlights", HIGHLIGHTS), ("albedo_free_bounce", ALBEDO_FREE_BOUNCE), ("albedo_free_gloss", ALBEDO_FREE_GLOSS),
                          ("albedo_free_coat", ALBEDO_FREE_COAT),
                          ("albedo_free_count", ALBEDO_FREE_COUNT), ("cnn_count", CNN_COUNT), ("cnn_start", CNN_START),
                          ("indirect", INDIRECT), ("search_shadows", SHADOW_METHODS),
                          ("criterion_shadows", SHADOW_METHODS)):
        _check_choice(f"tuning.{name}", getattr(t, name), choices)


@dataclass(frozen=True)
class EstimateOptions:
    """What ``mode=estimate`` estimates, as the user chooses it.

    ``method``: ``cnn+refine`` (the network's light slots start the refinement),
    ``cnn`` (the networks alone, their lights settled and counted on the frame, no search) or ``refine``
    (a grid search starts it). ``checkpoint``: the network of the ``cnn`` methods
    (None: the shipped ones, :func:`selfsup.estimation.network.checkpoints_of`). ``max_lights``: model selection tries 1 .. this many
    lights. ``shadows``: the shadow model of the final refinement (``none`` |
    ``epipolar`` | ``paper``; the criterion judges every model with cast shadows
    whatever this says, :attr:`Tuning.criterion_shadows`). ``tuning``: the tuned
    constants (:class:`Tuning`).
    """

    method: str = "cnn+refine"
    checkpoint: str | None = None
    max_lights: int = 2
    shadows: str = "none"
    tuning: Tuning = field(default_factory=Tuning)

    def __post_init__(self):
        if isinstance(self.tuning, dict):  # from a config
            object.__setattr__(self, "tuning", Tuning(**self.tuning))
        _check_choice("method", self.method, METHODS)
        _check_choice("shadows", self.shadows, SHADOW_METHODS)
        if isinstance(self.max_lights, bool) or not isinstance(self.max_lights, int) or self.max_lights < 1:
            raise ValueError(f"estimate.max_lights must be an integer >= 1, got {self.max_lights!r}")

    def tuned(self, **changes) -> "EstimateOptions":
        """These options with some tuned constants changed: ``options.tuned(coat="never")``."""
        return replace(self, tuning=replace(self.tuning, **changes))

    @classmethod
    def from_settings(cls, **settings) -> "EstimateOptions":
        """Options from one flat dict of user settings and tuned constants (scripts and
        sweeps): ``EstimateOptions.from_settings(method="refine", coat="never")``. An
        unknown name is an error that lists the known ones."""
        user = {f.name for f in fields(cls)} - {"tuning"}
        unknown = set(settings) - user - set(Tuning.names())
        if unknown:
            raise ValueError(f"unknown estimate setting(s) {sorted(unknown)}; known: {sorted(user)} and the tuning's "
                             f"{sorted(Tuning.names())}")
        tuning = {k: v for k, v in settings.items() if k not in user}
        return cls(**{k: v for k, v in settings.items() if k in user}, tuning=Tuning(**tuning))

    def changed_settings(self) -> dict:
        """The settings and tuned constants that differ from the defaults, as one flat dict
        (what a results file names)."""
        default, tuning = EstimateOptions(), Tuning()
        changed = {f.name: getattr(self, f.name) for f in fields(self)
                   if f.name != "tuning" and getattr(self, f.name) != getattr(default, f.name)}
        changed.update({name: getattr(self.tuning, name) for name in Tuning.names()
                        if getattr(self.tuning, name) != getattr(tuning, name)})
        return changed
