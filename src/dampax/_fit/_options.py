"""The fit's options as small immutable objects (issue 27), the way diffrax passes a ``SaveAt``
and optimistix a solver: ``dp.fit(trace, free=..., model=..., window=dp.Window(...),
solver=dp.LeastSquares(...))``. The keywords that define the problem (``oscillator``,
``free``, ``shared``, ``model``, ``k3``, ``mu_s``, ``fit_omega0``, ``offset``) stay keywords;
which samples are fitted and how the optimiser runs live here. Each object checks its values
when it is made (a ValueError naming the field), so ``fit`` receives them valid.
"""

from __future__ import annotations

import inspect
import math
import numbers
from collections.abc import Mapping
from typing import Any, NamedTuple

from ._core import OPTIMIZERS
from ._params import LOSSES, PARAMS, check_choice


def _positive_int(name: str, value, *, allow_none: bool = False):
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or \
            not math.isfinite(value) or int(value) != value or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def _positive_float(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or \
            not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return float(value)


def _time(name: str, value, *, words=()) -> Any:
    """A window time: a finite real number as a float, one of ``words`` or None."""
    if value is None or (isinstance(value, str) and value in words):
        return value
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or \
            not math.isfinite(value):
        allowed = ", ".join([repr(w) for w in words] + ["None", "a finite time [s]"])
        raise ValueError(f"{name} must be {allowed}, got {value!r}")
    return float(value)


def _window_values(start, end, units) -> tuple:
    """The checked, normalised fields of a :class:`Window` (ValueError naming the field).

    ``start`` and ``end`` may also be lists of one value per run (a joint fit), each checked.
    """
    def times(name, value, words):
        if isinstance(value, (list, tuple)):
            if not value:
                raise ValueError(f"{name}: an empty list (give one value, or one per run)")
            return [_time(f"{name}[{i}]", v, words=words) for i, v in enumerate(value)]
        return _time(name, value, words=words)

    start = times("Window.start", start, ("auto", "data"))
    end = times("Window.end", end, ())
    n = max(len(v) if isinstance(v, list) else 1 for v in (start, end))
    starts = start if isinstance(start, list) else [start] * n
    ends = end if isinstance(end, list) else [end] * n
    for s, e in zip(starts, ends, strict=False):  # unequal lists: _per_run names them
        if isinstance(s, float) and isinstance(e, float) and e <= s:
            raise ValueError(f"Window.end ({e}) must lie after Window.start ({s})")
    if units is not None and (not isinstance(units, str) or not units.strip()):
        raise ValueError(f"Window.units must be a non-empty string such as 'm' or 'deg', "
                         f"got {units!r}")
    return start, end, None if units is None else units.strip()


def check_p0(p0, name: str = "LeastSquares.p0") -> dict | None:
    """Initial values of a fit, by parameter name, checked: a mapping of names among
    ``PARAMS`` to finite real numbers; mu, b, D >= 0 (damping constants) and w0 > 0.

    Arguments:
        p0: None or the mapping.
        name: the option named in errors.

    Returns:
        None or a dict of floats.

    Raises:
        ValueError: naming ``name``, the parameter and the reason.
    """
    if p0 is None:
        return None
    if not isinstance(p0, Mapping):
        raise ValueError(f"{name} must be a mapping of parameter name to value, got "
                         f"{type(p0).__name__}")
    unknown = sorted(str(k) for k in set(p0) - set(PARAMS))
    if unknown:
        raise ValueError(f"{name}: unknown parameter(s) {unknown}; allowed: {list(PARAMS)}")
    out = {}
    for key, value in p0.items():
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or \
                not math.isfinite(value):
            raise ValueError(f"{name}[{key!r}] must be a finite real number, got {value!r}")
        value = float(value)
        if key in ("mu", "b", "D") and value < 0:
            raise ValueError(f"{name}[{key!r}] must be >= 0 (a damping constant), got {value!r}")
        if key == "w0" and value <= 0:
            raise ValueError(f"{name}['w0'] must be > 0 (the angular frequency), got {value!r}")
        out[key] = value
    return out


class _WindowFields(NamedTuple):
    start: Any = "auto"
    end: Any = None
    units: str | None = None


class Window(_WindowFields):
    """Which samples of a trace are fitted, and the unit of its positions; checked when made
    (a ValueError naming the field: ``Window.start``, ``Window.end``, ``Window.units``).

    Arguments:
        start: where the window begins: "auto" (the first sample where the record moves
            freely from it; else the first clear extreme after the largest excursion, which
            skips the hold of a hand release), "data" / None (the first sample) or a
            finite time [s]; for a joint fit also a list of these, one per run.
        end: the window's end, a finite time [s] after ``start`` (default None: the last
            sample); for a joint fit also a list, one per run.
        units: the unit of the positions, for the report ("m", "deg", ...); default None: from
            the position column's name of a Trace ("Angle(deg)"), else "m".
    """

    __slots__ = ()

    def __new__(cls, start="auto", end=None, units=None):
        return super().__new__(cls, *_window_values(start, end, units))

    def _replace(self, **changes) -> Window:
        """A copy with some fields changed, checked as when made."""
        return type(self)(**{**self._asdict(), **changes})

    def checked(self) -> Window:
        """This window (its values were checked when it was made)."""
        return self


class _LeastSquaresFields(NamedTuple):
    loss: str = "linear"
    optimizer: str = "lm"
    rtol: float = 1e-8
    atol: float = 1e-10
    max_steps: int | None = None
    starts: int = 32
    seed: int = 0
    p0: Mapping | None = None
    max_swings: int | None = None


#: a call with a wrong argument is reported as the constructor's (``LeastSquares.__new__() got
#: an unexpected keyword argument ...``): the fields' constructor binds the arguments
_LeastSquaresFields.__new__.__qualname__ = "LeastSquares.__new__"


def _solver_values(given: _LeastSquaresFields) -> tuple:
    """The checked, normalised fields of a :class:`LeastSquares` (ValueError naming the field).

    Arguments:
        given: the fields as given to the constructor.

    Returns:
        The fields, in order.
    """
    check_choice("LeastSquares.loss", given.loss, LOSSES)
    check_choice("LeastSquares.optimizer", given.optimizer, OPTIMIZERS)
    seed = given.seed
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise ValueError(f"LeastSquares.seed must be an integer >= 0, got {seed!r}")
    return (given.loss, given.optimizer, _positive_float("LeastSquares.rtol", given.rtol),
            _positive_float("LeastSquares.atol", given.atol),
            _positive_int("LeastSquares.max_steps", given.max_steps, allow_none=True),
            _positive_int("LeastSquares.starts", given.starts), int(seed), check_p0(given.p0),
            _positive_int("LeastSquares.max_swings", given.max_swings, allow_none=True))


class LeastSquares(_LeastSquaresFields):
    """How the least-squares problem is solved; checked when made (a ValueError naming the
    field, ``LeastSquares.rtol`` ..., and the reason).

    Arguments:
        loss: "linear" or "soft_l1" (robust to outliers; its scale from the MAD of a linear
            fit's residuals).
        optimizer: "lm" (optimistix Levenberg-Marquardt), "adam" or "lbfgs" (optax).
        rtol, atol: the optimizer's tolerances, finite and > 0.
        max_steps: its step budget (honoured: at most max_steps steps per optimisation;
            default None: the optimizer's own, continued once where it runs out).
        starts: global starts (1: the turning-point guess alone); ``seed``: of their jitter,
            an integer >= 0.
        p0: initial values (a mapping by parameter name, finite; mu, b, D >= 0, w0 > 0)
            overriding the automatic guess, of fitted parameters only (a damping constant
            not in ``free`` or w0 without ``fit_omega0`` is a ValueError: the oscillator
            holds it), except the offset: with ``offset=False`` it is held at p0's value.
        max_swings: the reference model's budget of half-swings (default: from the window).
    """

    __slots__ = ()

    #: the signature ``help`` and ``inspect`` show: the fields, with their defaults
    __signature__ = inspect.Signature([
        inspect.Parameter(name, inspect.Parameter.POSITIONAL_OR_KEYWORD, default=default)
        for name, default in _LeastSquaresFields._field_defaults.items()])

    def __new__(cls, *args, **kwargs):
        """The settings, checked: the arguments bound as the fields' (their names, order and
        defaults: :attr:`__signature__`), each then checked (:func:`_solver_values`)."""
        return super().__new__(cls, *_solver_values(_LeastSquaresFields(*args, **kwargs)))

    def _replace(self, **changes) -> LeastSquares:
        """A copy with some fields changed, checked as when made."""
        return type(self)(**{**self._asdict(), **changes})

    def checked(self) -> LeastSquares:
        """These settings (their values were checked when they were made)."""
        return self


def options(window, solver, *, check: bool = True) -> dict:
    """The keyword arguments of the fit's implementation from a :class:`Window` and a
    :class:`LeastSquares`, each checked here, at the edge (``check=False``: by the callee,
    ``fit_joint``, which checks them itself)."""
    window = Window() if window is None else window
    solver = LeastSquares() if solver is None else solver
    if not isinstance(window, Window):
        raise ValueError(f"window must be a dp.Window(start=..., end=..., units=...), got "
                         f"{type(window).__name__}")
    if not isinstance(solver, LeastSquares):
        raise ValueError(f"solver must be a dp.LeastSquares(loss=..., rtol=..., "
                         f"max_steps=..., starts=...), got {type(solver).__name__}")
    if check:
        window, solver = window.checked(), solver.checked()
        for name in ("start", "end"):
            if isinstance(getattr(window, name), list):
                raise ValueError(f"Window.{name}: a list of one value per run is for a joint "
                                 f"fit of several runs, not a single trace")
    return {**window._asdict(), **solver._asdict()}
