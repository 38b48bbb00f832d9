"""The fit's options as small immutable objects (issue 27), the way diffrax passes a ``SaveAt``
and optimistix a solver: ``dp.fit(trace, free=..., model=..., window=dp.Window(...),
solver=dp.LeastSquares(...))``. The keywords that define the problem (``oscillator``,
``free``, ``shared``, ``model``, ``k3``, ``mu_s``, ``fit_omega0``, ``offset``) stay keywords;
which samples are fitted and how the optimiser runs live here. Each object checks its values
when it is made (a ValueError naming the field), so ``fit`` receives them valid.
"""

from __future__ import annotations

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


class Window(NamedTuple):
    """Which samples of a trace are fitted, and the unit of its positions.

    Arguments:
        start: where the window begins: "auto" (the first clear extreme after the largest
            excursion, which skips a hand release), "data" / None (the first sample) or a time
            [s].
        end: the window's end time [s] (default None: the last sample).
        units: the unit of the positions, for the report ("m", "deg", ...); default None: from
            the position column's name of a Trace ("Angle(deg)"), else "m".
    """

    start: Any = "auto"
    end: float | None = None
    units: str | None = None

    def checked(self) -> Window:
        """This window with its values checked (ValueError naming the field)."""
        start, end, units = self
        if isinstance(start, str):
            if start not in ("auto", "data"):
                raise ValueError(f"Window.start must be 'auto', 'data', None or a time, got "
                                 f"{start!r}")
        elif start is not None:
            if isinstance(start, bool) or not isinstance(start, numbers.Real) or \
                    not math.isfinite(start):
                raise ValueError(f"Window.start must be 'auto', 'data', None or a finite time, "
                                 f"got {start!r}")
            start = float(start)
        if end is not None:
            if isinstance(end, bool) or not isinstance(end, numbers.Real) or \
                    not math.isfinite(end):
                raise ValueError(f"Window.end must be a finite time or None, got {end!r}")
            end = float(end)
            if isinstance(start, float) and end <= start:
                raise ValueError(f"Window.end ({end}) must lie after Window.start ({start})")
        if units is not None and (not isinstance(units, str) or not units.strip()):
            raise ValueError(f"Window.units must be a non-empty string such as 'm' or 'deg', "
                             f"got {units!r}")
        return Window(start, end, None if units is None else units.strip())


class LeastSquares(NamedTuple):
    """How the least-squares problem is solved.

    Arguments:
        loss: "linear" or "soft_l1" (robust to outliers; its scale from the MAD of a linear
            fit's residuals).
        optimizer: "lm" (optimistix Levenberg-Marquardt), "adam" or "lbfgs" (optax).
        rtol, atol: the optimizer's tolerances.
        max_steps: its step budget (honoured: at most max_steps steps per optimisation;
            default None: the optimizer's own, continued once where it runs out).
        starts: global starts (1: the turning-point guess alone); ``seed``: of their jitter.
        p0: initial values (a mapping by parameter name) overriding the automatic guess.
        max_swings: the reference model's budget of half-swings (default: from the window).
    """

    loss: str = "linear"
    optimizer: str = "lm"
    rtol: float = 1e-8
    atol: float = 1e-10
    max_steps: int | None = None
    starts: int = 32
    seed: int = 0
    p0: Mapping | None = None
    max_swings: int | None = None

    def checked(self) -> LeastSquares:
        """These settings with their values checked (ValueError naming the field)."""
        check_choice("LeastSquares.loss", self.loss, LOSSES)
        check_choice("LeastSquares.optimizer", self.optimizer, OPTIMIZERS)
        p0 = self.p0
        if p0 is not None:
            if not isinstance(p0, Mapping):
                raise ValueError(f"LeastSquares.p0 must be a mapping of parameter name to "
                                 f"value, got {type(p0).__name__}")
            unknown = sorted(set(p0) - set(PARAMS))
            if unknown:
                raise ValueError(f"LeastSquares.p0: unknown parameter(s) {unknown}; "
                                 f"allowed: {list(PARAMS)}")
            p0 = dict(p0)
        if isinstance(self.seed, bool) or not isinstance(self.seed, numbers.Integral):
            raise ValueError(f"LeastSquares.seed must be an integer, got {self.seed!r}")
        return LeastSquares(
            self.loss, self.optimizer, _positive_float("LeastSquares.rtol", self.rtol),
            _positive_float("LeastSquares.atol", self.atol),
            _positive_int("LeastSquares.max_steps", self.max_steps, allow_none=True),
            _positive_int("LeastSquares.starts", self.starts), int(self.seed), p0,
            _positive_int("LeastSquares.max_swings", self.max_swings, allow_none=True))


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
    return {**window._asdict(), **solver._asdict()}
