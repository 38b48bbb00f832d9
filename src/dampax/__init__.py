"""dampax: the damped harmonic oscillator with sliding friction, viscous and quadratic drag, in JAX.

Importing dampax enables float64 in JAX (``jax_enable_x64``): every number this library
compares against a reference needs it. It also turns JAX's persistent compilation cache on in
the user's cache directory (``DAMPAX_CACHE=0`` turns that off; see ``dampax._cache``).

The fitting stack (``dampax._fit``: optimistix, optax, lineax), the global sensitivity, the
error maps, the plots and the paper's reproduction are imported when one of their names is
first used (a module ``__getattr__``, PEP 562): ``import dampax`` and ``dampax solve`` do not
pay for them. ``from dampax import fit`` and ``dir(dampax)`` work as for any other name.
"""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

from ._cache import CacheWarning as CacheWarning  # noqa: E402
from ._cache import enable_compilation_cache as _enable_compilation_cache  # noqa: E402

_enable_compilation_cache()

from ._cache import exported_dir as _exported_dir  # noqa: E402
from ._cachethreads import start_prefetch as _start_prefetch  # noqa: E402

_start_prefetch(_exported_dir)  # the console script's command: its programs load meanwhile

from ._models._registry import MODELS as MODELS  # noqa: E402
from ._models._registry import Model as Model  # noqa: E402
from ._models._solution import RESULTS as RESULTS  # noqa: E402
from ._models._solution import AbstractSolution as AbstractSolution  # noqa: E402
from ._oscillator import Oscillator as Oscillator  # noqa: E402
from ._oscillator import damping_coefficients as damping_coefficients  # noqa: E402
from ._oscillator import from_ratios as from_ratios  # noqa: E402
from ._solve import solve as solve  # noqa: E402
from ._solve import turning_points as turning_points  # noqa: E402
from ._studies._sensitivity import Sensitivity as Sensitivity  # noqa: E402
from ._studies._sensitivity import sensitivity as sensitivity  # noqa: E402
from ._trace import Trace as Trace  # noqa: E402
from ._trace import load_trace as load_trace  # noqa: E402
from ._version import __version__ as __version__  # noqa: E402

#: public name -> the module that defines it, imported on first use (:func:`__getattr__`)
_LAZY = {
    "ArrayFit": "._fit",
    "FitResult": "._fit",
    "JointProblem": "._fit",
    "JointResult": "._fit",
    "LeastSquares": "._fit",
    "ModelComparison": "._fit",
    "Posterior": "._fit",
    "Window": "._fit",
    "compare_envelope_models": "._fit",
    "compare_models": "._fit",
    "example_trace": "._fit",
    "fit": "._fit",
    "fit_arrays": "._fit",
    "fit_envelope": "._fit",
    "fit_joint": "._fit",
    "initial_guess": "._fit",
    "posterior": "._fit",
    "residual_function": "._fit",
    "global_sensitivity": "._studies._global",
    "error_map": "._studies._maps",
    "plot_global_sensitivity": "._plot",
    "plot_sensitivity": "._plot",
    "plot_trend": "._plot",
    "paper_numbers": "._paper._reproduce",
    "reproduce": "._paper._reproduce",
}


def __getattr__(name: str):
    """A public name of :data:`_LAZY`: import its module, bind the name here and return it."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    """The module's names with the lazy ones (autocompletion lists them before first use)."""
    return sorted(set(globals()) | set(_LAZY))


#: every public name, the lazy ones included (``from dampax import *`` imports them all)
__all__ = sorted(name for name in (*globals(), *_LAZY) if not name.startswith("_"))
