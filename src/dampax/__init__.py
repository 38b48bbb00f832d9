"""dampax: the damped harmonic oscillator with sliding friction, viscous and quadratic drag, in JAX.

Importing dampax enables float64 in JAX (``jax_enable_x64``): every number this library
compares against a reference needs it.
"""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

from ._maps import error_map as error_map  # noqa: E402
from ._oscillator import Oscillator as Oscillator  # noqa: E402
from ._oscillator import damping_coefficients as damping_coefficients  # noqa: E402
from ._oscillator import from_ratios as from_ratios  # noqa: E402
from ._sensitivity import Sensitivity as Sensitivity  # noqa: E402
from ._sensitivity import plot_sensitivity as plot_sensitivity  # noqa: E402
from ._sensitivity import sensitivity as sensitivity  # noqa: E402
from ._solve import solve as solve  # noqa: E402
from ._solve import turning_points as turning_points  # noqa: E402

__version__ = "0.1.0"
