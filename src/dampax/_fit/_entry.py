"""``dp.fit``, the public entry point of fitting: it checks the options at the edge
(:mod:`._options`) and hands a single trace to :func:`~dampax._fit._api.fit`, a list of traces
to the joint fit :func:`~dampax._fit._joint.fit_joint` (kept apart so that ``_joint``, which
fits each run alone first, imports ``_api`` without a cycle)."""

from __future__ import annotations

from . import _api
from ._joint import fit_joint
from ._options import LeastSquares, Window, options
from ._problem import Settings


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
    return _api.fit(trace_or_t, x, Settings(**kwargs))


def fit(trace_or_t, x=None, *, oscillator=None, free=("mu", "D"), shared=None,
        model: str = "auto", k3: float | None = None, mu_s: float | None = None,
        fit_omega0: bool | None = None, offset: bool = True, window: Window | None = None,
        solver: LeastSquares | None = None):
    """Fit the damping constants of eq. 3 to a measured (or simulated) free-decay trace, or
    the shared constants of several runs (a list of traces).

    The keywords define the problem; which samples are fitted and how the optimiser runs are
    small option objects (:class:`~dampax.Window`, :class:`~dampax.LeastSquares`), checked
    when they are made.

    From x(t) alone only w0, the friction deceleration mu g, b/m and D/m (and x0, v0, the
    offset) are identifiable. Without an ``oscillator`` the fit is per unit mass: w0 is
    fitted, m = 1 kg, so ``params["b"]`` and ``params["D"]`` are b/m [1/s] and D/m
    [1/unit]; the report says so. With an oscillator, m (and, unless ``fit_omega0``, k) are
    its values and b, D are in kg/s and kg/m (positions in metres).

    Parameters: the damping constants named in ``free`` (mu, b, D >= 0), and always x0, v0 at
    the fit start, the equilibrium ``offset`` and, with ``fit_omega0``, w0 (m fixed,
    k = m w0^2). Non-free damping constants stay at the oscillator's values. The fit is
    global: ``starts`` jittered starts around the turning-point guess are optimised in one
    vmapped call on a thinned copy of the trace (``_starts``), the best is polished on the
    whole trace. With ``loss="soft_l1"`` the fit then restarts from the linear-loss optimum
    with the scale from its residuals (1.4826 MAD); a model with ``start_from`` (the reference)
    starts from the optimum of that model (the ansatz) and from a batch of jittered starts of
    its own around the turning-point guess (the ansatz's optimum among them). The stages are
    a plan (``_pipeline``) run on a problem prepared once (``_problem.prepare``).

    k3 in ``free`` (the cubic stiffness of issue 14, docs/cubic_stiffness.md) is profiled
    (``_stiffness.fit_k3``): the fit of the other parameters is repeated at fixed k3 and k3
    chosen by Brent's method on the residual sum of squares S(k3), searched as
    k3 A^2/(m w0^2) in [-0.3, 0.3] (A: the window's first amplitude); its interval comes from
    the curvature of S at the minimum (sigma^2 inflated for the residuals' lag-1
    autocorrelation), and the other parameters' intervals carry k3's uncertainty. mu_s in
    ``free`` is searched (``_static.fit_mu_s``): x(t) depends on mu_s only through the
    turning point where the block halts, so every candidate halt is screened at the sliding
    fit's optimum, the best ones fitted at fixed mu_s, and mu_s reported with the interval of
    values that give the chosen halt (``profiled["mu_s"]``; ``derived["halt_time"]``).

    Failures are named: ``success`` is False, with a one-line ``reason``, when the optimizer
    did not converge, a parameter ran to absurd values, the model stops moving before (or
    after) the data, a standard error is not finite, the intervals do not hold (the cost is not
    quadratic over them), two motions that halt at different turning points fit nearly as
    well and mu's profile between or beyond them stays below chi2(1)'s 1 % point (two
    answers), or, for the exact model "reference", the residuals hold structure that AR(1)
    noise cannot produce and its search of starts does not settle (``_checks``: tests with
    known null distributions, none on zero crossings). Where a damping constant held at 0
    costs nearly as little (a likelihood ratio below chi2(1)'s 1 % point) although its
    interval excludes 0, the fit succeeds with every interval widened to reach that held fit
    (``diagnostics["note_bound"]``); where a motion halting at a neighbouring turning point
    does, mu's profile is followed out past it until a held fit rises above that point, and
    the intervals are widened to reach it (``diagnostics["note_other_halt"]``). ``adequate``
    says separately whether the model describes the data. Input
    without a free decay in it (constant, pure noise, growing or time-reversed, constant time)
    raises ValueError; a trace that halts after one swing is fitted.

    Arguments:
        trace_or_t: a :class:`Trace` (from :func:`load_trace`), a file path, or the times t;
            or a list of two or more traces (a joint fit, :func:`~dampax._fit._joint.fit_joint`:
            each run with its own start, offset and window).
        x: the positions when ``trace_or_t`` holds the times.
        oscillator: the known constants (m, k, g; the damping constants not in ``free`` stay
            at its values, usually 0; its k3 and mu_s, where set, are held as ``k3=`` and
            ``mu_s=`` hold them). Default None: unit mass, w0 fitted (per-mass b, D).
        free: the constants to fit, among "mu", "b", "D", "k3" (profiled) and "mu_s"
            (searched; model "reference").
        shared: joint fits only: the parameters common to all runs, among "mu", "b", "D",
            "w0", "k3" (default: the free damping constants).
        model: "auto" (the default): the exact model's answer (eq. 3 integrated,
            "reference"), given by the ansatz's fit where the exact model provably agrees with
            it (one Gauss-Newton step of the exact model from the ansatz optimum moves no
            parameter by more than 0.1 interval sd, ``_fit._answer``); ``result.model`` and
            the report say which model answered and why. Its 90 % intervals covered the
            truth for 89-95 % of 200 generated traces, per parameter, with no confident wrong
            answer (benchmarks/README.md). "reference":
            always the exact model (DOP853 integration of eq. 3 with exact stick-slip, started
            from the ansatz fit). "ansatz": the closed form of eqs. 11, 20-23 alone, an
            approximation: fast, but its intervals carry its bias (90 % intervals covered
            mu 75 %, D 81 %, w0 73 %, the offset 80 % of the truths, and 3 of 200 fits were
            confidently wrong, where the data resolve its error).
        k3: hold the cubic stiffness at this value (default None: the linear spring).
        mu_s: model "reference": hold the static friction coefficient at this value (>= mu;
            default None: mu_s = mu).
        fit_omega0: also fit w0 (m fixed, k = m w0^2). Default: True without an oscillator,
            False with one.
        offset: fit the equilibrium offset (else the trace is taken as centred on 0).
        window: :class:`~dampax.Window` (start, end, units of the positions); default
            ``Window()``: the first sample of a record that moves from it, else the first clear
            extreme after the largest excursion (skipping a hand release's hold).
        solver: :class:`~dampax.LeastSquares` (loss, optimizer, tolerances, step budget,
            global starts, seed, initial values, the reference model's swing budget); default
            ``LeastSquares()``.

    Returns:
        A :class:`FitResult` (a :class:`~dampax._fit._joint_result.JointResult` for a list
        of traces).

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
