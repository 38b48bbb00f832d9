"""Which model answers a default fit (issue 36): the exact model of eq. 3, unless the
approximate one (the ansatz, eqs. 11, 20-23) provably answers the same.

At the ansatz's optimum p_a the exact model's curve differs from the ansatz's by
delta = x_ref(p_a) - x_ans(p_a). Its least-squares optimum lies, to first order, one
Gauss-Newton step away: dp = -(J^T J)^-1 J^T delta (J: the fit's Jacobian; the ansatz's
residuals are orthogonal to J at its optimum), and what no parameter change absorbs,
delta - J dp, adds to the cost. The ansatz answers when both are negligible against what the
fit reports:

- every |dp_i| is at most :data:`BIAS_SD` of its interval's sd (the sd that
  ``conf_interval`` reports: HAC, allowing for correlated noise), and
- the remainder's sum of squares is at most :data:`REMAINDER_VARIANCES` noise variances (no
  test of the residuals could see it).

Otherwise the exact model answers (the pipeline's next stage, started from p_a). The numbers
behind the two constants:

===================  =======  ====================================================================
constant             value    why
===================  =======  ====================================================================
BIAS_SD              0.1      a 90 % interval shifted by b sd covers P(|Z + b| < 1.645):
                              89.8 % at b = 0.1 (89.3 % at 0.2), inside the 85-95 % goal with
                              room for the step's own first-order error
REMAINDER_VARIANCES  1.0      one noise variance in all: the likelihood-ratio chi2 of the
                              difference is 1, below chi2(1)'s 68 % point (no test at 5 % sees it)
===================  =======  ====================================================================
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ._checks import interval_sd
from ._params import PARAMS

#: largest shift of a parameter, in interval sd, that the ansatz may leave (module docstring)
BIAS_SD = 0.1
#: largest part of the exact model's difference that no parameter absorbs, in noise variances
REMAINDER_VARIANCES = 1.0


class Bias(NamedTuple):
    """The exact model's first-order correction of an ansatz optimum.

    Attributes:
        shift_sd: {parameter: dp_i / sd_i} for the varied parameters.
        remainder: the sum of squares of delta - J dp, in noise variances.
        negligible: both within their bounds (the ansatz answers).
    """

    shift_sd: dict
    remainder: float
    negligible: bool

    def text(self) -> str:
        """One line for the report: which model answers and why."""
        if not self.shift_sd:
            return "the exact model answers (the ansatz's bias could not be estimated)"
        name = max(self.shift_sd, key=lambda k: abs(self.shift_sd[k]))
        worst = abs(self.shift_sd[name])
        if self.negligible:
            return (f"the ansatz answers: the exact model (eq. 3) would move no parameter by "
                    f"more than {worst:.2g} interval sd ({name}; bound {BIAS_SD:g}) and leave "
                    f"{self.remainder:.2g} noise variances unexplained (bound "
                    f"{REMAINDER_VARIANCES:g}), one Gauss-Newton step from the ansatz optimum")
        return (f"the exact model (eq. 3) answers: the ansatz's optimum is biased by "
                f"{worst:.2g} interval sd in {name} (bound {BIAS_SD:g}), "
                f"{self.remainder:.2g} noise variances of the difference unexplained (bound "
                f"{REMAINDER_VARIANCES:g})")


def approximation_bias(problem, out) -> Bias:
    """The exact model's one-step correction of the ansatz optimum ``out`` (the module
    docstring).

    Arguments:
        problem: the fit's ``_problem.Problem`` (its window, padding and constants).
        out: the ansatz fit's core output (params, jac, resid of the padded rows).

    Returns:
        A :class:`Bias`; not negligible where anything is not finite.
    """
    n = problem.n
    names = [k for k, v in zip(PARAMS, problem.vary, strict=True) if bool(v)]
    params = {k: float(getattr(out.params, k)) for k in PARAMS}
    # the exact model's curve at the ansatz optimum: its fit with a budget of one step
    # returns the start (the step is proposed, not taken), by the exact fit's own program
    at = problem.solve(out.params, problem.settings.model, math.inf, budget=1).out
    exact = np.asarray(at.curve)[:n]
    approx = np.asarray(out.curve)[:n]
    cols = [PARAMS.index(k) for k in names]
    J = np.asarray(out.jac)[:n][:, cols]
    rows = np.asarray(out.resid)[:n]
    r = problem.data.x - approx
    scale = float(np.sqrt(np.sum(r * r) / max(np.sum(rows * rows), 1e-300)))
    delta = (exact - approx) / scale if scale > 0 else np.full(n, np.nan)
    if not (np.all(np.isfinite(delta)) and np.all(np.isfinite(J)) and J.size):
        return Bias({}, math.inf, False)
    dp, *_ = np.linalg.lstsq(J, -delta, rcond=None)
    rest = delta + J @ dp
    s2 = float(rows @ rows) / max(n - len(names), 1)
    remainder = float(rest @ rest) / s2 if s2 > 0 else math.inf
    sd = interval_sd(J, rows, params, problem.data.t)
    if sd is None or not np.all(sd > 0):
        return Bias({}, remainder, False)
    shift = {k: float(dp[i] / sd[i]) for i, k in enumerate(names)}
    ok = max(abs(v) for v in shift.values()) <= BIAS_SD and remainder <= REMAINDER_VARIANCES
    return Bias(shift, remainder, bool(ok))
