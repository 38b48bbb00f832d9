"""``dp.fit``, the public entry point of fitting: it checks the options at the edge
(:mod:`._options`) and hands a single trace to :func:`~dampax._fit._api.fit`, a list of traces
to the joint fit :func:`~dampax._fit._joint.fit_joint` (kept apart so that ``_joint``, which
fits each run alone first, imports ``_api`` without a cycle)."""

from __future__ import annotations

from . import _api
from ._joint import fit_joint
from ._options import LeastSquares, Window, options


def fit_flat(trace_or_t, x=None, **kwargs):
    """:func:`fit` with the options as flat, already checked keywords (the implementations'
    signature: ``start``, ``end``, ``units``, ``loss``, ``optimizer``, ``rtol``, ``atol``,
    ``max_steps``, ``starts``, ``seed``, ``p0``, ``max_swings``)."""
    if isinstance(trace_or_t, (list, tuple)) and x is None:
        if kwargs.get("p0") is not None:
            raise ValueError("LeastSquares.p0: not supported by a joint fit of several runs")
        if kwargs.get("mu_s") is not None or "mu_s" in tuple(kwargs.get("free", ())):
            raise ValueError("mu_s: static friction is not supported by a joint fit of "
                             "several runs; fit each run alone")
        kwargs = {k: v for k, v in kwargs.items() if k not in ("p0", "mu_s")}
        return fit_joint(list(trace_or_t), **kwargs)
    return _api.fit(trace_or_t, x, **kwargs)


def fit(trace_or_t, x=None, *, oscillator=None, free=("mu", "D"), shared=None,
        model: str = "ansatz", k3: float | None = None, mu_s: float | None = None,
        fit_omega0: bool | None = None, offset: bool = True, window: Window | None = None,
        solver: LeastSquares | None = None):
    """Fit the damping constants of eq. 3 to a measured (or simulated) free-decay trace, or
    the shared constants of several runs (a list of traces).

    The keywords define the problem; which samples are fitted and how the optimiser runs are
    small option objects (:class:`~dampax.Window`, :class:`~dampax.LeastSquares`), checked
    when they are made.

    Arguments:
        trace_or_t: a :class:`Trace` (from :func:`load_trace`), a file path, or the times t;
            or a list of two or more traces (a joint fit, :func:`~dampax._fit._joint.fit_joint`:
            each run with its own start, offset and window).
        x: the positions when ``trace_or_t`` holds the times.
        oscillator: the known constants (m, k, g; the damping constants not in ``free`` stay
            at its values, usually 0). Default None: unit mass, w0 fitted (per-mass b, D).
        free: the constants to fit, among "mu", "b", "D", "k3" (profiled) and "mu_s"
            (searched; model "reference").
        shared: joint fits only: the parameters common to all runs, among "mu", "b", "D",
            "w0", "k3" (default: the free damping constants).
        model: "ansatz" (closed form of eqs. 11, 20-23, fast) or "reference" (DOP853
            integration of eq. 3, started from the ansatz fit).
        k3: hold the cubic stiffness at this value (default None: the linear spring).
        mu_s: model "reference": hold the static friction coefficient at this value (>= mu;
            default None: mu_s = mu).
        fit_omega0: also fit w0 (m fixed, k = m w0^2). Default: True without an oscillator,
            False with one.
        offset: fit the equilibrium offset (else the trace is taken as centred on 0).
        window: :class:`~dampax.Window` (start, end, units of the positions); default
            ``Window()``: from the first clear extreme after the largest excursion.
        solver: :class:`~dampax.LeastSquares` (loss, optimizer, tolerances, step budget,
            global starts, seed, initial values, the reference model's swing budget); default
            ``LeastSquares()``.

    Returns:
        A :class:`FitResult` (a :class:`~dampax._fit._joint_result.JointResult` for a list
        of traces);
        the statistics, checks and failures are described in :func:`~dampax._fit._api.fit`.

    Raises:
        ValueError: bad arguments (the parameter named), a trace without a free decay in it,
            or a window that fixes the combined decay of some damping terms but not their
            split ("mu and D are not separately identifiable ...: fix all but one of them").
    """
    joint = isinstance(trace_or_t, (list, tuple)) and x is None
    kwargs = dict(oscillator=oscillator, free=free, model=model, k3=k3, mu_s=mu_s,
                  fit_omega0=fit_omega0, offset=offset,
                  **options(window, solver, check=not joint))  # fit_joint checks its own
    if joint:
        kwargs["shared"] = shared
    elif shared is not None:
        raise ValueError("shared: names constants common to several runs; it needs a list of "
                         "two or more traces, not a single trace")
    return fit_flat(trace_or_t, x, **kwargs)
