"""The papers' cases: the block, its starts, the figures' panels, and one solution cache.

Every case is the paper's block (m = 1 kg, k = 30 N/m, g = 9.81 m/s^2, A0 = 0.2 m) with the
damping given by the dimensionless ratios d0/(w0 A0) and d2 A0/w0 (inverted with eq. 21).
``_reproduce`` draws the figures and ``_numbers`` recomputes the quoted values from here.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._oscillator import Oscillator, from_ratios
from .._solve import solve, turning_points

A0 = 0.2  # m, the amplitude of every case in both papers' comparisons
M, K, G = 1.0, 30.0, 9.81
W0 = math.sqrt(K / M)
T0 = 2.0 * math.pi / W0
#: The reference is integrated once per case over this window (longer than every panel).
REFERENCE_T_END = 8.0
#: Samples of every evaluation (shorter grids are padded: one compilation per model).
GRID = 2000

#: Initial states of the paper, by name: (x0, v0) for A0 = 0.2 m.
STARTS: dict[str, tuple[float, float]] = {
    "rest": (A0, 0.0),                                      # (x0 = A0, v0 = 0), phi0 = 0
    "push": (0.0, W0 * A0),                                 # (x0 = 0, v0 = w0 A0), phi0 = -pi/2
    "diag-": (A0 * math.sqrt(0.5), -W0 * A0 * math.sqrt(0.5)),  # phi0 = pi/4 (Sec. III.C)
    "diag+": (A0 * math.sqrt(0.5), W0 * A0 * math.sqrt(0.5)),   # phi0 = -pi/4 (Secs. IV.C, V.C)
}


def paper_oscillator(d0_ratio: float = 0.0, d2_ratio: float = 0.0) -> Oscillator:
    """The papers' block (m = 1 kg, k = 30 N/m) with d0/(w0 A0) and d2 A0/w0 (A0 = 0.2 m)."""
    return from_ratios(d0_ratio=d0_ratio, d2_ratio=d2_ratio, m=M, k=K, A0=A0, g=G)


# ----------------------------------------------------------------------------------------------
# the figures' panels


@dataclasses.dataclass(frozen=True)
class Panel:
    """One panel of a figure: a case, the red model's options and what is drawn.

    ``red`` holds the options of :func:`dampax.solve` for the red curve (the paper's new
    solution: eq. 29/36/47 plain, 41/52 with ``tail``, 54 with ``back=1``); the blue curve is
    always the undamped-phase ansatz (eqs. 30/39/49) and the black dotted one the reference.
    """

    d0_ratio: float
    d2_ratio: float
    start: str
    quantity: str  # "x" or "E"
    red: tuple[tuple[str, object], ...] = ()
    blue: bool = True
    t_end: float | None = None  # default: a bit past the latest halt, or 5 s
    # (turning-point index from 1, or LAST: the last one with |x| > xc; colour) of the red curve
    arrows: tuple[tuple[int, str], ...] = ()

    @property
    def case(self) -> tuple[float, float, str]:
        return (self.d0_ratio, self.d2_ratio, self.start)


@dataclasses.dataclass(frozen=True)
class Figure:
    """A figure of the paper: number, caption (short) and panels."""

    number: int
    caption: str
    panels: tuple[Panel, ...]

    @property
    def name(self) -> str:
        return f"fig{self.number:02d}"


LAST = 0  # arrow index: the red curve's last turning point with |x| > xc
_TAIL = (("tail", "coulomb"),)
_TAIL54 = (("tail", "coulomb"), ("back", 1))
QUAD = (0.1, 0.25, 0.5, 0.75)


def _pair(d0, d2, start, red=(), **kw) -> tuple[Panel, Panel]:
    """An (a) solution and (b) energy panel of the same case."""
    return (Panel(d0, d2, start, "x", red, **kw), Panel(d0, d2, start, "E", red))


#: Figures 2-21 of Lelas & Pezer, Part I (captions shortened).
FIGURES: tuple[Figure, ...] = (
    Figure(2, "quadratic drag, x(t), (x0 = 0.2 m, v0 = 0), d2 A0/w0 = 0.1, 0.25, 0.5, 0.75 "
              "(eqs. 29, 30)",
           tuple(Panel(0.0, r, "rest", "x", t_end=2.5 if r == 0.1 else 5.0) for r in QUAD)),
    Figure(3, "quadratic drag, energies of Fig. 2 (eqs. 15, 10)",
           tuple(Panel(0.0, r, "rest", "E", t_end=2.5 if r == 0.1 else 5.0) for r in QUAD)),
    Figure(4, "quadratic drag, x(t), (x0 = 0, v0 = w0 A0 = 1.10 m/s): x and x~ coincide (eq. 32)",
           tuple(Panel(0.0, r, "push", "x", blue=False, t_end=5.0) for r in (0.25, 0.5))),
    Figure(5, "quadratic drag, energies of Fig. 4 (E and E~ differ)",
           tuple(Panel(0.0, r, "push", "E", t_end=5.0) for r in (0.25, 0.5))),
    Figure(6, "quadratic drag, x(t), (x0 = 0.14 m, v0 = -0.77 m/s), phi0 = pi/4",
           tuple(Panel(0.0, r, "diag-", "x", t_end=5.0) for r in (0.25, 0.5))),
    Figure(7, "quadratic drag, energies of Fig. 6",
           tuple(Panel(0.0, r, "diag-", "E", t_end=5.0) for r in (0.25, 0.5))),
    Figure(8, "Coulomb, x(t) of eqs. 36, 39, (x0 = 0.2 m, v0 = 0), d0/(w0 A0) = 0.05, 0.1 "
              "(arrow: last turning point outside the band)",
           (Panel(0.05, 0.0, "rest", "x"), Panel(0.1, 0.0, "rest", "x", arrows=((LAST, "red"),)))),
    Figure(9, "Coulomb, improved solution eq. 41, (x0 = 0.2 m, v0 = 0), d0/(w0 A0) = 0.05, 0.1",
           (Panel(0.05, 0.0, "rest", "x", _TAIL), Panel(0.1, 0.0, "rest", "x", _TAIL))),
    Figure(10, "Coulomb, energies of Fig. 9 (eqs. 41, 42)",
           (Panel(0.05, 0.0, "rest", "E", _TAIL), Panel(0.1, 0.0, "rest", "E", _TAIL))),
    Figure(11, "Coulomb, eq. 41, (x0 = 0.2 m, v0 = 0), d0/(w0 A0) = 0.03 (mu = 0.029)",
           _pair(0.03, 0.0, "rest", _TAIL)),
    Figure(12, "Coulomb, eq. 41, (x0 = 0, v0 = w0 A0), d0/(w0 A0) = 0.05",
           _pair(0.05, 0.0, "push", _TAIL)),
    Figure(13, "Coulomb, eq. 41, (x0 = A0 sqrt(2)/2, v0 = w0 x0), d0/(w0 A0) = 0.05",
           _pair(0.05, 0.0, "diag+", _TAIL)),
    Figure(14, "Coulomb + quadratic, eqs. 47, 49, (x0 = 0.2 m, v0 = 0), d0/(w0 A0) = 0.01, 0.03, "
               "d2 A0/w0 = 0.15, 0.25 (red arrow: last turning point outside the band; "
               "green: the third)",
           tuple(Panel(d0, d2, "rest", "x",
                       arrows=((LAST, "red"), (3, "green")) if (d0, d2) == (0.03, 0.25) else ())
                 for d0 in (0.01, 0.03) for d2 in (0.15, 0.25))),
    Figure(15, "Coulomb + quadratic, energies of Fig. 14",
           tuple(Panel(d0, d2, "rest", "E") for d0 in (0.01, 0.03) for d2 in (0.15, 0.25))),
    Figure(16, "Coulomb + quadratic, improved solution eq. 52, (x0 = 0.2 m, v0 = 0), "
               "d0/(w0 A0) = 0.03, d2 A0/w0 = 0.15, 0.25",
           tuple(Panel(0.03, d2, "rest", "x", _TAIL) for d2 in (0.15, 0.25))),
    Figure(17, "Coulomb + quadratic, energies of Fig. 16 (eqs. 52, 53)",
           tuple(Panel(0.03, d2, "rest", "E", _TAIL) for d2 in (0.15, 0.25))),
    Figure(18, "Coulomb + quadratic, eq. 54 (tail from the third turning point), "
               "(x0 = 0.2 m, v0 = 0), d0/(w0 A0) = 0.03, d2 A0/w0 = 0.25",
           (Panel(0.03, 0.25, "rest", "x", _TAIL54, arrows=((3, "green"),)),)),
    Figure(19, "Coulomb + quadratic, eq. 52, (x0 = 0, v0 = w0 A0), d0/(w0 A0) = 0.03, "
               "d2 A0/w0 = 0.25",
           _pair(0.03, 0.25, "push", _TAIL)),
    Figure(20, "Coulomb + quadratic, eq. 52, (x0 = A0 sqrt(2)/2, v0 = w0 x0), d0/(w0 A0) = 0.03, "
               "d2 A0/w0 = 0.25 (arrow: fifth turning point)",
           _pair(0.03, 0.25, "diag+", _TAIL, arrows=((LAST, "red"),))),
    Figure(21, "Coulomb + quadratic, eq. 54 form from the fourth turning point, "
               "(x0 = A0 sqrt(2)/2, v0 = w0 x0), d0/(w0 A0) = 0.03, d2 A0/w0 = 0.25",
           (Panel(0.03, 0.25, "diag+", "x", _TAIL54, arrows=((4, "green"),)),)),
)

#: Rizcallah's friction amplitudes: kappa mu m g is the amplitude of the sinusoidal force.
KAPPAS: dict[str, float] = {"least squares": 4.0 / math.pi, "impulse": math.pi / 2.0,
                            "rms": math.sqrt(2.0)}
#: Rizcallah's comparison case: the papers' block from rest at A0, d0/(w0 A0) = 0.025.
RIZCALLAH_RATIO = 0.025
RIZCALLAH_FIGURES = ("rizcallah_fig3", "rizcallah_fig4", "rizcallah_fig5")
ALL_FIGURES = tuple(f.name for f in FIGURES) + RIZCALLAH_FIGURES


@eqx.filter_jit
def _evaluate(osc, x0, v0, t, options: tuple, n_turning: int):
    """x, E on t, turning points and halt of one model; ``options`` static, t_end traced."""
    options = dict(options)
    if options.get("method") == "reference":
        options["t_end"] = jnp.asarray(REFERENCE_T_END)
    sol = solve(osc, x0, v0, **options)
    return (sol.x(t), sol.energy(t), turning_points(sol, n_turning), sol.halt_time,
            sol.halt_position)


@dataclasses.dataclass
class Curve:
    """x(t), E(t), turning points and halt of one model on one time grid (numpy)."""

    x: np.ndarray
    energy: np.ndarray
    turning_t: np.ndarray
    turning_x: np.ndarray
    halt_time: float
    halt_position: float


def last_outside(c: Curve, xc: float) -> int:
    """Index (from 1) of the last turning point with |x| > xc."""
    outside = np.flatnonzero(np.abs(c.turning_x) > xc)
    return int(outside[-1]) + 1 if outside.size else 0


class Cases:
    """Solve each (case, model) once; every figure and number reads from here."""

    def __init__(self, n_turning: int = 12):
        self.n_turning = n_turning
        self._cache: dict = {}

    def curve(self, d0_ratio, d2_ratio, start, options, t) -> Curve:
        t = np.asarray(t, dtype=float)
        key = (d0_ratio, d2_ratio, start, options, t.size, float(t[0]), float(t[-1]))
        if key not in self._cache:
            osc = paper_oscillator(d0_ratio, d2_ratio)
            x0, v0 = STARTS[start]
            if t.size > GRID:
                raise ValueError(f"t: at most {GRID} samples, got {t.size}")
            # one grid length for every call: one compilation per model, not per grid
            padded = np.concatenate([t, np.full(GRID - t.size, t[-1])])
            out = _evaluate(osc, jnp.asarray(x0), jnp.asarray(v0), jnp.asarray(padded),
                            tuple(options), self.n_turning)
            x, e, (tt, tx), tau, xh = jax.tree_util.tree_map(np.asarray, out)
            self._cache[key] = Curve(x[: t.size], e[: t.size], tt, tx, float(tau), float(xh))
        return self._cache[key]


#: solve options of the reference and of the undamped-phase ansatz (the black and blue curves)
REFERENCE = (("method", "reference"),)
UNDAMPED = (("method", "ansatz"), ("phase", "undamped"))


# ----------------------------------------------------------------------------------------------
# Rizcallah's comparison


def rizcallah_case():
    osc = paper_oscillator(RIZCALLAH_RATIO)
    return osc, float(osc.mu), float(osc.xc)


def rizcallah_solutions(cases: Cases, t) -> tuple[dict[str, Curve], Curve]:
    models = {name: cases.curve(RIZCALLAH_RATIO, 0.0, "rest",
                                (("method", "rizcallah"), ("kappa", kappa)), t)
              for name, kappa in KAPPAS.items()}
    exact = cases.curve(RIZCALLAH_RATIO, 0.0, "rest", (("method", "coulomb_exact"),), t)
    return models, exact


def parabolic_trend(t, *, kappa: float = 4.0 / math.pi, d0_ratio: float = RIZCALLAH_RATIO):
    """Rizcallah's eq. 6: the energy's trend E0 (1 - d t/A0)^2, d = kappa mu g/(2 w0).

    Arguments:
        t: times [s].
        kappa: amplitude factor of the sinusoidal force (4/pi: d = d0 of eq. 21).
        d0_ratio: d0/(w0 A0) of the case (the papers' block, from rest at A0).

    Returns:
        E [J] on ``t``, zero after the halt of the trend (t > A0/d).
    """
    osc = paper_oscillator(d0_ratio)
    d = kappa * float(osc.mu) * G / (2.0 * W0)
    E0 = 0.5 * K * A0**2
    return E0 * np.clip(1.0 - d * np.asarray(t) / A0, 0.0, None) ** 2


