"""Joint fits of several runs of one apparatus (issue 25, item 2): shared damping constants.

``fit([run1, run2, ...], shared=("b", "D"))`` fits the damping constants named in ``shared``
(and, when named, a shared w0 and a shared cubic stiffness k3) together with each run's own
start (x0, v0 at its window's start), offset and, for the constants not shared, its own values,
as ONE least-squares problem (docs/DESIGN.md, fitting):

    min  sum_j sum_i ((model(t_ij - t0_j; shared, local_j) - x_ij) / sigma_j)^2,

with sigma_j each run's noise level (the rms of its single fit), so runs of different noise
weigh as their information does. The runs are padded to one length with a mask, and the model
is vmapped over them: one compiled program per number of runs, padded length and parameter
layout, whatever the lengths of the runs.

Starts: each run is first fitted alone by :func:`~dampax._fit._api.fit` (its window, guesses,
global starts: the single-fit machinery). The shared constants start from a batch of
n_runs + 1 candidates, the median of the single fits and each single fit's own values (with few
runs one poor single fit spoils the median), optimised together in one vmapped call of the
approximate model; the lowest converged cost goes on to the exact model. From each start, each
run's own coordinates are first fitted with the shared ones held (a run whose single fit was
poor gets a start consistent with the shared constants). The optimizer is optimistix
Levenberg-Marquardt in the internal coordinates of ``_params`` (log coordinates for the damping
constants, natural scales for the rest; the model's own velocity coordinate y), in rounds that
rescale the log coordinates (as the single fit); a round that ends non-finite or with a higher
cost is not taken, and an exact-model fit whose step budget ran out continues from where it
stopped (:data:`CONTINUATIONS`).

Intervals: the AR(1)-prewhitened HAC sandwich of ``_intervals`` (cov = H^-1 S H^-1 with
H = J^T J of the joint Jacobian in the physical parameters and S the sum over runs of each run's
prewhitened score covariance: the runs' noises are independent, each may be correlated in time).

For other samplers (the posterior): :meth:`JointResult.problem` returns the joint problem as a
:class:`JointProblem`, the layout of the joint parameter vector and a pure residual function of
it (jit / grad-able).

Here the public function and its argument checks; the stages (single fits, starts, the joint
optimisation) in ``_joint_stages``, the result built in ``_joint_build``.
"""

from __future__ import annotations

from pathlib import Path

from .._trace import Trace, load_trace
from ._core import MAX_STEPS, MODELS
from ._inputs import held_constants
from ._joint_build import JointContext, _result
from ._joint_problem import SHARED
from ._joint_result import JointResult
from ._joint_search import _optimise
from ._joint_stages import JointSettings, _joint_start, _single_fits
from ._linalg import one_blas_thread
from ._options import LeastSquares, Window
from ._params import DAMPING, check_choice, check_free, oscillator_values
from ._problem import units_of

# ----------------------------------------------------------------------------------------------
# the public function


def _per_run(value, n, name):
    """A per-run list of an argument that is either one value or a list of n."""
    if isinstance(value, (list, tuple)):
        if len(value) != n:
            raise ValueError(f"{name}: give one value or one per run ({n}), got {len(value)}")
        return list(value)
    return [value] * n


def _loaded(item, j):
    """A run's file read into a Trace (errors name ``traces[j]``); anything else as it is."""
    if not isinstance(item, (str, Path)):
        return item
    try:
        return load_trace(item)
    except ValueError as err:
        raise ValueError(f"traces[{j}]: {err}") from err


def _common_unit(runs, units) -> str:
    """The position unit of every run: ``units`` when given, else each run's own (the unit in
    its position column's name); ValueError naming ``traces`` when the runs' units differ
    (a shared D in kg/m, or mu, means one length unit: m and mm gave one D, wrong for one of
    them).

    Arguments:
        runs: the runs (Trace objects or arrays).
        units: Window.units (None: from each run).

    Returns:
        The unit.
    """
    found = [units_of(tr, units) for tr in runs]
    if len(set(found)) > 1:
        listed = ", ".join(f"traces[{j}]: {u!r}" for j, u in enumerate(found))
        raise ValueError(f"traces: the runs' positions are in different units ({listed}); "
                         "shared constants need one unit: read them in one unit (load_trace("
                         "scale=1e-3) turns mm into m) and pass Window(units=...)")
    return found[0]


def _run_input(item, j):
    """(trace_or_t, x) of one run: a Trace, a path, or a pair (t, x)."""
    if isinstance(item, (Trace, str, Path)):
        return item, None
    if isinstance(item, (list, tuple)) and len(item) == 2:
        return item[0], item[1]
    raise ValueError(f"traces[{j}]: give a dampax.Trace, a file path or a pair (t, x), got "
                     f"{type(item).__name__}")


def check_shared(shared, free, *, fit_omega0: bool, k3) -> tuple[tuple, tuple]:
    """(shared, free) of a joint fit: ``shared`` among :data:`SHARED` (a comma list or a
    tuple; default: the free damping constants), the free damping constants including the
    shared ones.

    Raises:
        ValueError: an unknown or repeated name, a shared w0 without ``fit_omega0``, k3 both
            shared and held, or "k3" in ``free`` (a joint fit fits k3 only as shared).
    """
    free = check_free(free, allowed=DAMPING + ("k3",))
    if "k3" in free:
        raise ValueError("free: a joint fit fits k3 as one constant of all runs: name it in "
                         "shared=(..., 'k3'), not in free")
    if shared is None:
        shared = free
    if isinstance(shared, str):
        shared = tuple(s.strip() for s in shared.split(",") if s.strip())
    shared = tuple(shared)
    bad = [s for s in shared if s not in SHARED]
    if bad or len(set(shared)) != len(shared) or not shared:
        raise ValueError(f"shared must name distinct parameters among {SHARED}, got "
                         f"{shared!r}")
    if "w0" in shared and not fit_omega0:
        raise ValueError("shared: 'w0' is shared only when it is fitted (fit_omega0=True, or "
                         "no oscillator)")
    if "k3" in shared and k3 is not None:
        raise ValueError("shared: 'k3' is fitted; do not also pass a fixed k3")
    free = tuple(n for n in DAMPING if n in free or n in shared)
    return tuple(n for n in SHARED if n in shared), free


@one_blas_thread
def fit_joint(traces, *, shared=None, free=("mu", "D"), oscillator=None, model: str = "auto",
              fit_omega0: bool | None = None, offset: bool = True, start="auto", end=None,
              loss: str = "linear", optimizer: str = "lm", max_steps: int | None = None,
              rtol: float = 1e-8, atol: float = 1e-10, max_swings: int | None = None,
              units: str | None = None, starts: int = 32, seed: int = 0,
              k3: float | None = None) -> JointResult:
    """Fit several runs of one apparatus together: shared damping constants (eq. 3), each run
    with its own start, offset and window, as one vmapped least-squares problem.

    Arguments:
        traces: two or more runs: :class:`Trace` objects, file paths or pairs (t, x).
        shared: the parameters common to all runs, among "mu", "b", "D", "w0" and "k3"
            (a tuple or a comma list; default: the free damping constants). A shared damping
            constant is fitted even when not in ``free``; "w0" needs a fitted w0; "k3" fits
            one cubic stiffness for all runs (a parameter of the joint problem, not profiled).
        free: the damping constants fitted; those not shared are fitted per run.
        oscillator, fit_omega0, offset, units, starts, seed, k3: as in
            :func:`~dampax._fit._api.fit` (the same for every run).
        model: "auto" (the default) and "reference": the exact model (started from the
            ansatz's joint fit, then searched from every candidate start); "ansatz": the
            closed form alone (an approximation; see ``dp.fit``).
        start, end: each run's window, as in ``fit``: one value or one per run.
        loss, optimizer: "linear" and "lm" (the joint fit is least squares).
        max_steps, rtol, atol: the joint optimizer's budget and tolerances.
        max_swings: the reference model's budget (default from the longest window).

    Returns:
        A :class:`JointResult`.

    Raises:
        ValueError: fewer than two runs, bad arguments (named), or a run without a free decay
            in it (its index and the reason named).
    """

    if not isinstance(traces, (list, tuple)) or len(traces) < 2:
        raise ValueError("traces: a joint fit needs a list of two or more runs")
    check_choice("model", model, (*MODELS, "auto"))
    model = "reference" if model == "auto" else model  # a joint fit answers exactly
    if loss != "linear":
        raise ValueError(f"loss: a joint fit is least squares ('linear'), got {loss!r}")
    if optimizer != "lm":
        raise ValueError(f"optimizer: a joint fit uses 'lm', got {optimizer!r}")
    # the settings checked once, here (dp.fit hands a list of runs over unchecked)
    checked = LeastSquares(loss=loss, optimizer=optimizer, rtol=rtol, atol=atol,
                           max_steps=max_steps, starts=starts, seed=seed,
                           max_swings=max_swings).checked()
    units = Window(units=units).checked().units
    if fit_omega0 is None:
        fit_omega0 = oscillator is None
    named = [n.strip() for group in (shared or (), free)
             for n in (group.split(",") if isinstance(group, str) else group)]
    k3, mu_s = held_constants(oscillator, named, k3, None)
    if mu_s is not None:
        raise ValueError("oscillator.mu_s: static friction is not supported by a joint fit of "
                         "several runs; fit each run alone")
    shared, free = check_shared(shared, free, fit_omega0=bool(fit_omega0), k3=k3)
    windows = _windows(start, end, len(traces))
    cfg = JointSettings(model=model, shared=shared, free=free, oscillator=oscillator,
                        osc=oscillator_values(oscillator), fit_omega0=fit_omega0,
                        offset=offset, units=units, starts=checked.starts, seed=seed, k3=k3,
                        max_steps=int(checked.max_steps or MAX_STEPS["lm"]), rtol=float(rtol),
                        atol=float(atol), max_swings=checked.max_swings)
    runs = [_run_input(item, j) for j, item in enumerate(traces)]
    runs = [(_loaded(tr, j), x) for j, (tr, x) in enumerate(runs)]
    unit = _common_unit([tr for tr, _ in runs], units)
    singles, notes = _single_fits(runs, windows, cfg)
    init = _joint_start(singles, cfg)
    out, arrays, opts, stages, search = _optimise(init, cfg)
    return _result(out, arrays, JointContext(
        lay=init.lay, singles=singles, sigma=init.data.sigma, free=free, model=model,
        unit=unit, per_mass=oscillator is None, fit_omega0=bool(fit_omega0), opts=opts,
        stages=stages, notes=notes, osc=cfg.osc, search=search))


def _windows(start, end, n_runs: int) -> tuple[list, list]:
    """(starts, ends) of the runs' windows, one per run, each pair checked as a single fit's.

    Arguments:
        start, end: one value or one per run.
        n_runs: the number of runs.

    Returns:
        The per-run lists.
    """
    starts_at = _per_run(start, n_runs, "start")
    ends_at = _per_run(end, n_runs, "end")
    for s_at, e_at in zip(starts_at, ends_at, strict=True):  # finite, ordered, as a single fit
        Window(start=s_at, end=e_at)
    return starts_at, ends_at
