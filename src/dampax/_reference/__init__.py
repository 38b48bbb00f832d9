"""The exact reference of eq. 3 with true stick-slip (docs/DESIGN.md sections 2.6 and 6).

- `_tableau`: DOP853's coefficients;
- `_stepping`: one step of the swing's smooth motion, its error and the step-size control;
- `_events`: the velocity zero at a swing's end and sticking there;
- `_engine`: the one flat loop of steps, turning points and the halt, storing one row per step;
- `_sampling`: the rows' interpolating polynomials and their evaluation at sample times;
- `_kernel`: the same loop as one fused Pallas kernel (a CUDA GPU; interpreted elsewhere),
  its samples written inside the loop;
- `_diffrax`: diffrax's Dopri8 swing by swing, a second, independent integrator;
- `_solution`, `_solve`: `ReferenceSolution` and `solve_reference`.
"""

from ._solution import ReferenceSolution as ReferenceSolution
from ._solution import uniform as _uniform  # noqa: F401  (used by the fits and the tests)
from ._solve import _solve_jit as _solve_jit  # noqa: F401
from ._solve import solve_reference as solve_reference
