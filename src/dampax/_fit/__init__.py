"""Fitting the damping constants mu, b, D to measured free-decay traces (docs/DESIGN.md, fitting).

A fit is a pipeline of values (issue 33): ``_problem.prepare`` reads, windows and analyses the
data once into an immutable ``Problem`` (which solves itself, and makes the held problems of
every "hold and refit"); ``_pipeline.run(problem, plan)`` runs the stages a ``Plan`` names
(global starts, robust restart, exact model, continued budget, neighbouring halts, assessment,
static halt); ``_assess`` judges the result by a table of checks; the searches of k3
(``_stiffness``) and mu_s (``_static``) run plans on held problems.

Layers, bottom up (tests/test_layers.py): ``_params``, ``_dist``, ``_intervals``, ``_profile``,
``_mcmc``, ``_sampler``; ``_curves`` (the fit models); ``_core`` (the solver: pure, vmappable);
``_analysis`` (what a trace says before any fit), ``_guess``, ``_checks``, ``_assess``,
``_options``; ``_problem``, ``_context`` (what a fit was asked to do), ``_report`` (a result's
report and figure), ``_result``, ``_example``; ``_starts`` (vmapped global starts), ``_halts``;
``_pipeline``; ``_static``, ``_stiffness``; ``_api`` (single-trace functions);
``_joint_problem``, ``_joint_result``, ``_joint_build``, ``_joint_stages``, ``_joint``;
``_entry`` (``dp.fit``); ``_posterior_result``, ``_posterior_joint``, ``_posterior``. The
command ``dampax fit`` lives in ``dampax._cli.fit``.
"""

from ._api import compare_envelope_models as compare_envelope_models
from ._api import compare_models as compare_models
from ._api import fit_arrays as fit_arrays
from ._api import fit_envelope as fit_envelope
from ._api import residual_function as residual_function
from ._core import FIT_MODELS as FIT_MODELS
from ._core import METHOD_NAMES as METHOD_NAMES
from ._core import MODELS as MODELS
from ._core import OPTIMIZERS as OPTIMIZERS
from ._core import FitModel as FitModel
from ._entry import fit as fit
from ._example import EXAMPLE as EXAMPLE
from ._example import example_trace as example_trace
from ._guess import initial_guess as initial_guess
from ._joint import fit_joint as fit_joint
from ._joint_problem import SHARED as SHARED
from ._joint_result import JointProblem as JointProblem
from ._joint_result import JointResult as JointResult
from ._options import LeastSquares as LeastSquares
from ._options import Window as Window
from ._params import CANDIDATES as CANDIDATES
from ._params import DAMPING as DAMPING
from ._params import ENVELOPE_PARAMS as ENVELOPE_PARAMS
from ._params import FREE as FREE
from ._params import LOSSES as LOSSES
from ._params import PARAMS as PARAMS
from ._params import EnvelopeParams as EnvelopeParams
from ._params import TraceParams as TraceParams
from ._params import check_free as check_free
from ._posterior import posterior as posterior
from ._posterior_result import Posterior as Posterior
from ._problem import full_starts as full_starts
from ._result import ArrayFit as ArrayFit
from ._result import FitResult as FitResult
from ._result import ModelComparison as ModelComparison

__all__ = [
    "FitResult", "ModelComparison", "ArrayFit", "fit", "fit_arrays", "fit_envelope",
    "compare_models", "compare_envelope_models", "initial_guess", "example_trace",
    "residual_function", "PARAMS", "ENVELOPE_PARAMS", "CANDIDATES", "DAMPING", "FREE", "MODELS",
    "LOSSES", "OPTIMIZERS", "METHOD_NAMES", "FIT_MODELS", "FitModel", "TraceParams",
    "EnvelopeParams", "EXAMPLE", "check_free", "posterior", "Posterior", "fit_joint",
    "JointResult", "JointProblem", "SHARED",
]
