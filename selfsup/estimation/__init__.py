"""Lights from images: the estimator, as named stages (``docs/estimation.md``).

Read it top down, each module one job, every import pointing down this list:

- :mod:`~selfsup.estimation.files`: scene files in, JSON Lines out (``mode=estimate``), the worker pool;
- :mod:`~selfsup.estimation.stages`: the driver, a list of stage calls (first light, coat, grow, drop, polish);
- :mod:`~selfsup.estimation.records`: the JSON-ready records;
- :mod:`~selfsup.estimation.network`, :mod:`~selfsup.estimation.reflectance`: the network's starts; unknown albedo
  (:mod:`~selfsup.estimation.intensities`: its lights' intensities; :mod:`~selfsup.estimation.gains`: per-surface
  albedo gains);
- :mod:`~selfsup.estimation.count`: whether the albedo-free fit takes one light more;
- :mod:`~selfsup.estimation.criterion`: model selection (how many lights, which terms);
- :mod:`~selfsup.estimation.uncertainty`: covariances of the chosen lights;
- :mod:`~selfsup.estimation.solvers`: LM, first-order (the paper's GD, Adam), grid search;
- :mod:`~selfsup.estimation.prepare`: per-frame inputs (normals refit, clipped pixels, working range);
- :mod:`~selfsup.estimation.problem`: the fit problem and its closed-form linear part;
- :mod:`~selfsup.estimation.albedo_free`, :mod:`~selfsup.estimation.normals`: the albedo-free fit, normals of
  noisy depth (indirect light: :mod:`selfsup.scenes.indirect`, shared with the generator);
- :mod:`~selfsup.estimation.options`: the user's settings and the tuned constants.

Example:
    >>> from selfsup.estimation import EstimateOptions, estimate_files
    >>> summary = estimate_files("scenes/", "lights.jsonl", EstimateOptions())  # doctest: +SKIP
"""

from selfsup.estimation.files import estimate_files, scene_files
from selfsup.estimation.options import EstimateOptions, RefineOptions, Tuning
from selfsup.estimation.prepare import prepare
from selfsup.estimation.problem import Fit, FitProblem
from selfsup.estimation.records import records
from selfsup.estimation.solvers import refine, search
from selfsup.estimation.stages import estimate_batch, estimate_scene

__all__ = ["EstimateOptions", "Tuning", "RefineOptions", "estimate_files", "scene_files", "estimate_scene",
           "estimate_batch", "prepare", "records", "FitProblem", "Fit", "refine", "search"]
