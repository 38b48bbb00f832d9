"""dampax: the damped harmonic oscillator with sliding friction, viscous and quadratic drag, in JAX.

Importing dampax enables float64 in JAX (``jax_enable_x64``): every number this library
compares against a reference needs it. It also turns JAX's persistent compilation cache on in
the user's cache directory (``DAMPAX_CACHE=0`` turns that off; see ``dampax._cache``).
"""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

from ._cache import enable_compilation_cache as _enable_compilation_cache  # noqa: E402

_enable_compilation_cache()

from ._fit import ArrayFit as ArrayFit  # noqa: E402
from ._fit import FitResult as FitResult  # noqa: E402
from ._fit import JointProblem as JointProblem  # noqa: E402
from ._fit import JointResult as JointResult  # noqa: E402
from ._fit import ModelComparison as ModelComparison  # noqa: E402
from ._fit import Posterior as Posterior  # noqa: E402
from ._fit import compare_envelope_models as compare_envelope_models  # noqa: E402
from ._fit import compare_models as compare_models  # noqa: E402
from ._fit import example_trace as example_trace  # noqa: E402
from ._fit import fit as fit  # noqa: E402
from ._fit import fit_arrays as fit_arrays  # noqa: E402
from ._fit import fit_envelope as fit_envelope  # noqa: E402
from ._fit import fit_joint as fit_joint  # noqa: E402
from ._fit import initial_guess as initial_guess  # noqa: E402
from ._fit import posterior as posterior  # noqa: E402
from ._fit import residual_function as residual_function  # noqa: E402
from ._global import global_sensitivity as global_sensitivity  # noqa: E402
from ._maps import error_map as error_map  # noqa: E402
from ._models import MODELS as MODELS  # noqa: E402
from ._models import Model as Model  # noqa: E402
from ._oscillator import Oscillator as Oscillator  # noqa: E402
from ._oscillator import damping_coefficients as damping_coefficients  # noqa: E402
from ._oscillator import from_ratios as from_ratios  # noqa: E402
from ._plot import plot_global_sensitivity as plot_global_sensitivity  # noqa: E402
from ._plot import plot_sensitivity as plot_sensitivity  # noqa: E402
from ._plot import plot_trend as plot_trend  # noqa: E402
from ._reproduce import paper_numbers as paper_numbers  # noqa: E402
from ._reproduce import reproduce as reproduce  # noqa: E402
from ._sensitivity import Sensitivity as Sensitivity  # noqa: E402
from ._sensitivity import sensitivity as sensitivity  # noqa: E402
from ._solution import RESULTS as RESULTS  # noqa: E402
from ._solution import AbstractSolution as AbstractSolution  # noqa: E402
from ._solve import solve as solve  # noqa: E402
from ._solve import turning_points as turning_points  # noqa: E402
from ._trace import Trace as Trace  # noqa: E402
from ._trace import load_trace as load_trace  # noqa: E402
from ._version import __version__ as __version__  # noqa: E402
