"""The fit problem, made once: the data read, windowed and analysed, the start, the mask of the
varied parameters and the constants, as one immutable value (issue 33).

:func:`prepare` does everything a fit does before it optimises; a :class:`Problem` then
:meth:`~Problem.solve`\\ s itself from a start with a model, and makes the problems that every
"hold and refit" needs without touching the data again: :meth:`~Problem.holding` (a parameter
held: profiles, tests at a bound, neighbouring halts), :meth:`~Problem.with_consts` (k3 or mu_s
held: the k3 and mu_s searches), :meth:`~Problem.starting_at` (another start, other global
starts). lmfit's ``Minimizer`` plays this part there; optimistix's ``least_squares`` takes the
same pieces as arguments.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import threading
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .._trace import Trace, column_unit, load_trace
from ._checks import check_trace, data_rows
from ._core import (
    FIT_MODELS,
    FIT_RESULTS,
    MAX_STEPS,
    ReferenceOptions,
    Tuning,
    is_code,
    run_core,
    swing_budget,
)
from ._guess import Analysis, analyse, guess_trace
from ._inputs import (
    as_times,
    check_gaps,
    check_p0_fitted,
    check_positions,
    check_sampling,
    check_time_axis,
    checked_consts,
    held_offset_warning,
    omega_warning,
)
from ._params import (
    DAMPING,
    MAD,
    PARAMS,
    Constants,
    TraceParams,
    oscillator_values,
    varied_names,
    vary_mask,
)
from ._text import warn_user

#: restarts at a bound that a fit of the exact model creeping toward one takes (the ``settle``
#: of :meth:`Problem.solve`): one per damping constant
SETTLE = len(DAMPING)


class Settings(NamedTuple):
    """What the caller asked of a single-trace fit (checked at the edge, ``_options``)."""

    oscillator: object = None
    free: tuple = ("mu", "D")
    model: str = "auto"
    fit_omega0: bool | None = None
    offset: bool = True
    start: object = "auto"
    end: float | None = None
    loss: str = "linear"
    optimizer: str = "lm"
    p0: dict | None = None
    max_steps: int | None = None
    rtol: float = 1e-8
    atol: float = 1e-10
    max_swings: int | None = None
    units: str | None = None
    starts: int = 32
    seed: int = 0
    k3: float | None = None
    mu_s: float | None = None


class Data(NamedTuple):
    """The trace and its fit window (not padded, and padded to the bucket of its length)."""

    t_all: np.ndarray
    x_all: np.ndarray
    source: str
    t: np.ndarray
    x: np.ndarray
    tp: np.ndarray
    xp: np.ndarray
    wt: np.ndarray
    analysis: Analysis


class Solved(NamedTuple):
    """A solve's output and what produced it: the model, the soft_l1 scale and the
    integrator's options (a held refit of this fit uses the same)."""

    out: object
    model: str
    fs: float
    opts: ReferenceOptions | None


@dataclasses.dataclass(frozen=True)
class Problem:
    """A prepared fit problem (immutable; see the module docstring).

    Attributes:
        settings: the caller's options (:class:`Settings`; ``free`` without "k3" / "mu_s").
        data: the trace, the window and its analysis (:class:`Data`).
        osc: the oscillator's values (w0 and k from the data per unit mass).
        per_mass: no oscillator was given (w0 fitted, b and D per unit mass).
        fit_omega0: w0 is fitted.
        units: the unit of the positions.
        guess: the start (the turning-point guess, or ``p0``'s values in its place).
        vary: the mask of the varied parameters.
        consts: m, g, k3, mu_s.
        warnings: notes about the data (emitted once, by :func:`prepare`).
    """

    settings: Settings
    data: Data
    osc: dict
    per_mass: bool
    fit_omega0: bool
    units: str
    guess: TraceParams
    vary: TraceParams
    consts: Constants
    warnings: tuple

    @property
    def steps(self) -> int:
        """The optimizer's step budget per optimisation."""
        return int(self.settings.max_steps or MAX_STEPS[self.settings.optimizer])

    @property
    def n(self) -> int:
        """The number of samples in the window."""
        return len(self.data.t)

    def reference_options(self, model: str, w0) -> ReferenceOptions | None:
        """The integrator's options of ``model`` for a start of angular frequency ``w0``: the
        swing budget rounded up (``swing_budget(..., "starts")``), so that windows of similar
        length share the compiled fit; None for a closed-form model."""
        if not FIT_MODELS[model].integrates:
            return None
        t = self.data.t
        max_swings = self.settings.max_swings
        if max_swings is None:
            max_swings = swing_budget(float(np.max(t) - t[0]), float(w0), "starts")
        return ReferenceOptions(int(max_swings), 1e-8, 1e-10)

    def solve(self, p_start: TraceParams, model: str, fs: float, *,
              like: Solved | None = None, budget: int | None = None,
              give_up: float | None = None, at_bound: bool = False,
              settle: int = 0) -> Solved:
        """Optimise from ``p_start`` with ``model`` (the jitted core, ``_core.run_core``).

        Arguments:
            p_start: the start (held parameters keep its values).
            model: the fit model's name.
            fs: the soft_l1 scale (inf: the linear loss).
            like: a fit whose integrator options a refit keeps (a held refit of it);
                default: options for ``p_start``'s w0.
            budget: the optimizer's steps (default :attr:`steps`); ``budget=1`` returns the
                start itself with the model's curve and Jacobian there.
            give_up: a chi-square above which the fit stops after ``_lm.GIVE_UP_AFTER``
                steps (10x it after ``GIVE_UP_EARLY``), not converged (None: never).
            at_bound: a varied damping constant that ``p_start`` holds at 0 starts at its
                lower bound, not its floor (``_core.Tuning``).
            settle: a model of one round that creeps towards a damping constant's bound
                stops there and starts again from it, at most this many times
                (:meth:`_settled`).

        Returns:
            :class:`Solved`.
        """
        budget = self.steps if budget is None else int(budget)
        out, opts = self._core(p_start, model, Tuning(fs, budget, give_up, at_bound,
                                                      settle > 0), like)
        last = Solved(out, model, fs, opts)
        return self._settled(last, budget, settle) if settle > 0 and \
            FIT_MODELS[model].lm_rounds == 1 and self.settings.optimizer == "lm" else last

    def prepare(self, p_start: TraceParams, model: str) -> None:
        """Start compiling, in the background, the program of :meth:`solve` for ``model``
        from ``p_start`` (its integrator options: the swing budget of its w0)."""
        self._core(p_start, model, Tuning(math.inf, self.steps), None, prepare=True)

    def _core(self, p_start, model: str, tuning: Tuning, like, prepare: bool = False):
        """(``_core.run_core``'s result, or None where ``prepare``; the integrator's
        options)."""
        opts = like.opts if like is not None else self.reference_options(model, p_start.w0)
        s = self.settings
        # one program for every budget of a model of one Levenberg-Marquardt round (the
        # exact one): its loop's static size is the default budget, the steps are traced
        cap = max(tuning.budget, MAX_STEPS[s.optimizer]) if s.optimizer == "lm" and \
            FIT_MODELS[model].lm_rounds == 1 else tuning.budget
        out = run_core(self.data.tp, self.data.xp, self.data.wt, p_start, self.vary,
                       self.consts, tuning, model=model, optimizer=s.optimizer, max_steps=cap,
                       rtol=float(s.rtol), atol=float(s.atol), opts=opts, prepare=prepare,
                       quick=model != s.model and not getattr(_FULL, "on", False))
        return out, opts

    def _settled(self, last: Solved, budget: int, settle: int) -> Solved:
        """A fit of one round (the exact model) that stopped creeping towards a damping
        constant's bound (``_core.Tuning.leave``: before its ``budget`` ran out, not
        converged), again with the constants its Gauss-Newton step sends to 0 started at their
        bound (``at_bound``), as the other models' rounds place them; kept where lower. A start
        far from the exact model's optimum (k3's profile: fit_calibration.py --wide seed 31
        draw 50, D's optimum 0 at most k3) crept 256 steps and two more rounds towards D = 0:
        2.7 s for what takes 0.2 s from the bound."""
        out = last.out
        if not (is_code(out.code, FIT_RESULTS.max_steps_reached) and int(out.steps) < budget
                and out.jac is not None):
            return last
        jac, rows = data_rows(out, self.vary, self.n)
        step = -np.linalg.lstsq(jac, rows, rcond=None)[0]  # (unprojected: newton_step's is)
        p = out.params._asdict()
        zero = {n: 0.0 for n, d in zip(varied_names(self.vary), step, strict=True)
                if n in DAMPING and 0.0 < float(p[n]) <= -d}
        # (where the step from the fit's last point sends none there, it stopped on its way
        # elsewhere: it goes on from there, as it would have without stopping)
        again = self.solve(out.params._replace(**zero), last.model, last.fs, like=last,
                           budget=budget, at_bound=bool(zero), settle=settle - 1 if zero else 0)
        return self._off_the_clamp(again) if float(again.out.chisqr) < float(out.chisqr) \
            else last

    def _off_the_clamp(self, last: Solved) -> Solved:
        """A fit whose damping constant ended at its lower bound, where the clamp leaves its
        Jacobian column 0 (no standard error: a reference fit with mu = 0 at its bound failed
        "the standard error of mu is not finite", fit_calibration.py seed 44 draws 38 and 97),
        with its statistics one unit above the bound (``budget=1``, ``at_bound``: its curve
        and Jacobian there, its derivative the model's; the cost moves by a 1e-9 of mu); its
        code and steps kept."""
        out = last.out
        jac, _ = data_rows(out, self.vary, self.n)
        cols = dict(zip(varied_names(self.vary), jac.T, strict=True)) if jac is not None else {}
        bare = {n: 0.0 for n in DAMPING if n in cols and not np.any(cols[n]) and
                not math.isfinite(float(getattr(out.stderr, n)))}  # (the clamp's zero column)
        if not bare:
            return last
        there = self.solve(out.params._replace(**bare), last.model, last.fs, like=last,
                           budget=1, at_bound=True).out
        return last._replace(out=there._replace(code=out.code, steps=out.steps))

    def holding(self, *names: str) -> Problem:
        """The problem with the parameters ``names`` held at the start's values."""
        return dataclasses.replace(self, vary=self.vary._replace(**{n: False for n in names}))

    def starting_at(self, p0: dict | None = None, *, starts: int | None = None) -> Problem:
        """The problem started at ``p0``'s values (in place of the guess) with ``starts``
        global starts."""
        guess = self.guess._replace(**{k: float(v) for k, v in (p0 or {}).items()})
        settings = self.settings if starts is None else self.settings._replace(starts=starts)
        return dataclasses.replace(self, guess=guess, settings=settings)

    def with_positions(self, x) -> Problem:
        """The problem on other positions over the same window (a model's own curve, for a
        check of its bias): the window's analysis kept, nothing read or analysed again."""
        x = np.asarray(x, dtype=float)
        _, xp, _ = pad(self.data.t, x, len(self.data.tp))
        data = self.data._replace(t_all=self.data.t, x_all=x, x=x, xp=xp)
        return dataclasses.replace(self, data=data)

    def with_consts(self, **values) -> Problem:
        """The problem with the constants ``k3`` and/or ``mu_s`` held at other values (the
        data, the window and the start unchanged).

        Raises:
            ValueError: a value that is not finite, or mu_s below a held mu.
        """
        k3 = values.get("k3", self.consts.k3)
        mu_s = values.get("mu_s", self.consts.mu_s)
        k3, mu_s = checked_consts(k3, mu_s, self.settings.free, self.osc)
        consts = self.consts._replace(k3=k3, mu_s=mu_s)
        settings = self.settings._replace(k3=k3, mu_s=mu_s)
        return dataclasses.replace(self, consts=consts, settings=settings)


def predicted_start(out, name: str, value: float) -> TraceParams:
    """The start of a refit with ``name`` held at ``value``: the fit's optimum moved along its
    linearised profile (p_j + C_jh / C_hh (value - p_h), C the fit's covariance), where the
    other parameters' optimum lies to first order; a damping constant stays within a factor 4
    of its value (its optimizer coordinate is logarithmic, and the profile bends).

    Arguments:
        out: the fit's core output (its ``params`` and ``covariance`` in the layout PARAMS).
        name, value: the held parameter and its value.

    Returns:
        The start (TraceParams), ``name`` at ``value``.
    """
    p = np.asarray(out.params, dtype=float)
    C = np.asarray(out.covariance, dtype=float)
    i = PARAMS.index(name)
    moved = {name: float(value)}
    if C.shape == (len(PARAMS), len(PARAMS)) and np.isfinite(C[i, i]) and C[i, i] > 0 and \
            np.all(np.isfinite(C[:, i])) and math.isfinite(value - p[i]):
        step = C[:, i] / C[i, i] * (float(value) - p[i])
        for j, other in enumerate(PARAMS):
            if j == i or not C[j, j] > 0:
                continue
            v = p[j] + step[j]
            if other in ("mu", "b", "D"):
                v = min(max(v, 0.25 * p[j]), 4.0 * p[j])
            moved[other] = float(v)
    return TraceParams(*(float(v) for v in p))._replace(**moved)


# ----------------------------------------------------------------------------------------------
# reading the data


def read_arrays(trace_or_t, x, *, least: int = 10, what: str = "a fit needs",
                noun: str = "samples"):
    """(t, x, source) from a Trace, a path or two arrays; sorted by t, non-finite dropped
    (with a warning, outside :func:`quiet_windows`); at least ``least`` finite samples (the
    error: "{what} at least {least} finite {noun}")."""
    source = ""
    if isinstance(trace_or_t, Trace):
        if x is not None:
            raise ValueError("pass either a Trace or the arrays t and x, not both")
        t, x, source = trace_or_t.t, trace_or_t.x, trace_or_t.source
    elif isinstance(trace_or_t, (str, Path)):
        trace = load_trace(trace_or_t)
        t, x, source = trace.t, trace.x, trace.source
    else:
        if x is None or isinstance(x, Trace):
            raise ValueError("fit(t, x): x is missing (a dampax.Trace is passed alone)")
        t = trace_or_t
    t = as_times(t).reshape(-1)
    x = np.asarray(x, dtype=float).reshape(-1)
    if t.shape != x.shape:
        raise ValueError(f"t and x must have the same length, got {t.size} and {x.size}")
    ok = np.isfinite(t) & np.isfinite(x)
    if not ok.all() and not getattr(_QUIET, "on", False):
        warn_user(f"t, x: {int(ok.size - ok.sum())} of {ok.size} {noun} hold NaN or inf "
                  "(a gap in the logger?) and were left out")
    t, x = t[ok], x[ok]
    check_time_axis(t)
    check_positions(x)
    order = np.argsort(t, kind="stable")
    t, x = t[order], x[order]
    if t.size < least:
        raise ValueError(f"{what} at least {least} finite {noun}, got {t.size}")
    return t, x, source


def robust_scale(r) -> float:
    """1.4826 MAD of residuals: the soft_l1 scale f_scale."""
    return float(MAD * np.median(np.abs(r - np.median(r))))


def bucket(n: int, minimum: int = 4096) -> int:
    """Padded length: the next 2^j or 3 2^(j-1) >= n, at least ``minimum``, so that traces of
    different lengths share compiled fits (compiling one takes 10-30 s). A padded sample
    costs what a sample costs (the model is evaluated there at weight 0), so the steps are
    at most 1.5x (powers of 4 before issue 36: the 5,000 samples of ``dampax fit --example``
    ran as 16,384)."""
    n = max(int(n), 1)
    power = 1 << (n - 1).bit_length()  # the next power of two >= n
    return max(minimum, 3 * power // 4 if 4 * n <= 3 * power else power)


def pad(t, x, n_pad):
    """(t, x, weight) padded to ``n_pad`` samples with the last one at weight 0."""
    n = len(t)
    wt = np.zeros(n_pad)
    wt[:n] = 1.0
    tp = np.full(n_pad, t[-1])
    tp[:n] = t
    xp = np.full(n_pad, x[-1])
    xp[:n] = x
    return tp, xp, wt


def units_of(trace_or_t, units):
    """The position unit: ``units``, else the unit in the position column's name of a Trace
    ("Angle(deg)" -> "deg"; "(57.2958 deg)" where ``load_trace(scale=pi/180)`` scaled it: one
    position unit of the fit is 1/scale of the column's), else "m"."""
    if units is not None:  # checked by Window (or fit_envelope)
        return units
    if isinstance(trace_or_t, Trace):  # "x (mm)", "x [mm]", "x / mm", quoted: the loader's
        unit = column_unit(trace_or_t.position_column)
        if unit:
            scale = trace_or_t.scale
            return unit if scale == 1.0 else f"({1.0 / scale:.6g} {unit})"
    return "m"


def _window(t_all, x_all, s: Settings, osc: dict, fit_omega0: bool):
    """(t, x, analysis of the window, notes): the window of the settings, checked."""
    an = analyse(t_all, x_all, omega0=None if fit_omega0 else osc["w0"],
                 window=(s.start, s.end))
    warn = omega_warning(an.whole, osc, fit_omega0)
    t, xw = t_all[slice(*an.window)], x_all[slice(*an.window)]
    check_gaps(t)
    check_trace(t, xw, an)
    return t, xw, an, warn


#: set while another model's start is compiled as that model's own fit is (:func:`full_starts`)
_FULL = threading.local()


@contextlib.contextmanager
def full_starts():
    """In this thread, for the block: another model's start (the ansatz's, where the exact
    model answers) runs the program of that model's own fits, not the one compiled by XLA's
    quickest route (``_core.run_core``'s ``quick``; the same numbers to rounding). For a caller
    that fits that model itself too (``dampax fit``'s ranking, beside the fit): a new process
    then loads one program of the ansatz, not two (``dampax fit --example`` repeated
    2.64-2.74 -> 2.44-2.49 s), and a cold one compiles one."""
    with _set_here(_FULL):
        yield


#: set in a thread whose fits repeat another fit's window warnings (:func:`quiet_windows`)
_QUIET = threading.local()


@contextlib.contextmanager
def quiet_windows():
    """In this thread, for the block: :func:`prepare` does not warn about the window (a model
    ranking's candidates, whose trace and window are the fit's, which warned already), and
    numpy's floating-point warnings are off. Thread-local, unlike ``warnings.catch_warnings``,
    which changes every thread's filters: a ranking beside a fit (``dampax fit``) silenced the
    fit's own warnings."""
    with _set_here(_QUIET), np.errstate(all="ignore"):
        yield


@contextlib.contextmanager
def _set_here(flag: threading.local):
    """``flag.on`` true in this thread for the block, as it was after."""
    before = getattr(flag, "on", False)
    flag.on = True
    try:
        yield
    finally:
        flag.on = before


def prepare(trace_or_t, x, settings: Settings) -> Problem:
    """Read, window and analyse the data once; the :class:`Problem` of a single-trace fit.

    Arguments:
        trace_or_t, x: the data, as for ``dp.fit``.
        settings: the checked options (``free`` without "k3" and "mu_s").

    Returns:
        The problem; its notes about the data are emitted as warnings here, once.

    Raises:
        ValueError: the data hold no free decay, the window is too short, ``p0`` names
            unknown parameters, or a constant is not valid (the reason named).
    """
    s = settings
    k3, mu_s = checked_consts(s.k3, s.mu_s, s.free, {}, against_mu=False)
    per_mass = s.oscillator is None
    fit_omega0 = per_mass if s.fit_omega0 is None else s.fit_omega0
    if per_mass and not fit_omega0:
        raise ValueError("fit_omega0=False needs an oscillator (m and k): without one, w0 is "
                         "fitted per unit mass")
    osc = oscillator_values(s.oscillator)
    units = units_of(trace_or_t, s.units)
    t_all, x_all, source = read_arrays(trace_or_t, x)
    check_sampling(t_all, x_all)
    t, xw, an_w, warn = _window(t_all, x_all, s, osc, fit_omega0)
    if per_mass:
        osc = {**osc, "w0": an_w.omega, "k": an_w.omega ** 2}
    guess = guess_trace(t, xw, s.free, osc, fit_omega0, s.offset, an=an_w)
    if s.p0:
        check_p0_fitted(s.p0, s.free, fit_omega0)
        guess = guess._replace(**{k: float(v) for k, v in s.p0.items()})
    warn += held_offset_warning(an_w, guess.offset, s.offset)
    if not getattr(_QUIET, "on", False):
        for w in warn:
            warn_user(w)
    vary = vary_mask(TraceParams, s.free, fit_omega0=fit_omega0, offset=s.offset)
    k3, mu_s = checked_consts(k3, mu_s, s.free, osc)
    tp, xp, wt = pad(t, xw, bucket(len(t)))
    data = Data(t_all, x_all, source, t, xw, tp, xp, wt, an_w)
    return Problem(settings=s._replace(k3=k3, mu_s=mu_s), data=data, osc=osc,
                   per_mass=per_mass, fit_omega0=fit_omega0, units=units, guess=guess,
                   vary=vary, consts=Constants(m=osc["m"], g=osc["g"], k3=k3, mu_s=mu_s),
                   warnings=tuple(warn))
