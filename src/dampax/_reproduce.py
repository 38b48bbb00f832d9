"""Reproduce the papers: Figures 2-21 of Lelas & Pezer, Rizcallah's comparison, quoted numbers.

:func:`reproduce` draws every figure of the Lelas & Pezer paper (Part I) with the same cases and
colour code (matched ansatz solid red, undamped-phase ansatz solid blue, reference black dotted,
the sticking band +-xc dashed) and Rizcallah's Figures 3-5 (the three friction amplitudes and
the energy decay with its parabolic trend). :func:`paper_numbers` computes every value the two
papers quote next to the printed one. The figures are named after the papers' numbers:
``fig02.png`` ... ``fig21.png`` and ``rizcallah_fig3.png`` ... ``rizcallah_fig5.png``.

Every case is the paper's block (m = 1 kg, k = 30 N/m, g = 9.81 m/s^2, A0 = 0.2 m) with the
damping given by the dimensionless ratios d0/(w0 A0) and d2 A0/w0 (inverted with eq. 21).
"""

from __future__ import annotations

import csv
import dataclasses
import math
import re
import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._oscillator import Oscillator, damping_coefficients, from_ratios
from ._plot import MODELS, default_t_end
from ._solve import solve, turning_points

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
# the figures


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
_QUAD = (0.1, 0.25, 0.5, 0.75)


def _pair(d0, d2, start, red=(), **kw) -> tuple[Panel, Panel]:
    """An (a) solution and (b) energy panel of the same case."""
    return (Panel(d0, d2, start, "x", red, **kw), Panel(d0, d2, start, "E", red))


#: Figures 2-21 of Lelas & Pezer, Part I (captions shortened).
FIGURES: tuple[Figure, ...] = (
    Figure(2, "quadratic drag, x(t), (x0 = 0.2 m, v0 = 0), d2 A0/w0 = 0.1, 0.25, 0.5, 0.75 "
              "(eqs. 29, 30)",
           tuple(Panel(0.0, r, "rest", "x", t_end=2.5 if r == 0.1 else 5.0) for r in _QUAD)),
    Figure(3, "quadratic drag, energies of Fig. 2 (eqs. 15, 10)",
           tuple(Panel(0.0, r, "rest", "E", t_end=2.5 if r == 0.1 else 5.0) for r in _QUAD)),
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


class _Cases:
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


_REFERENCE = (("method", "reference"),)
_UNDAMPED = (("method", "ansatz"), ("phase", "undamped"))


def _red_options(panel: Panel) -> tuple:
    return (("method", "ansatz"),) + tuple(panel.red)


def _panel_t_end(cases: _Cases, panel: Panel) -> float:
    """The panel's time span: its own, else :func:`default_t_end` of the models drawn."""
    if panel.t_end is not None:
        return panel.t_end
    probe = np.linspace(0.0, REFERENCE_T_END, 9)
    halts = [cases.curve(*panel.case, opts, probe).halt_time
             for opts in (_REFERENCE, _red_options(panel), _UNDAMPED)]
    osc = paper_oscillator(panel.d0_ratio, panel.d2_ratio)
    return min(default_t_end(osc, halts), REFERENCE_T_END)


def _ratio_title(panel: Panel) -> str:
    parts = []
    if panel.d0_ratio:
        parts.append(rf"$d_0/(\omega_0 A_0)$ = {panel.d0_ratio:g}")
    if panel.d2_ratio:
        parts.append(rf"$d_2 A_0/\omega_0$ = {panel.d2_ratio:g}")
    return ",  ".join(parts)


def _style(name: str) -> dict:
    spec = MODELS[name]
    return dict(color=spec.color, linestyle=spec.linestyle, linewidth=spec.linewidth,
                zorder=spec.zorder)


def _red_label(panel: Panel) -> str:
    opts = dict(panel.red)
    if opts.get("tail"):
        return "improved x(t), eq. 54" if opts.get("back") else "improved x(t), eqs. 41/52"
    return "x(t), matched ansatz"


def _draw_panel(ax, cases: _Cases, panel: Panel, letter: str | None, n_points: int):
    t_end = _panel_t_end(cases, panel)
    t = np.linspace(0.0, t_end, n_points)
    red = cases.curve(*panel.case, _red_options(panel), t)
    ref = cases.curve(*panel.case, _REFERENCE, t)
    blue = cases.curve(*panel.case, _UNDAMPED, t) if panel.blue or panel.quantity == "E" else None
    q = "x" if panel.quantity == "x" else "energy"
    what = "x" if q == "x" else "E"
    ax.plot(t, getattr(red, q), **_style("matched"),
            label=_red_label(panel).replace("x(t)", f"{what}(t)"))
    if blue is not None:
        ax.plot(t, getattr(blue, q), **_style("undamped"), label=rf"$\tilde{{{what}}}(t)$, "
                "undamped-phase ansatz")
    ax.plot(t, getattr(ref, q), **_style("reference"), label="reference (numerical)")
    xc = float(paper_oscillator(panel.d0_ratio, panel.d2_ratio).xc)
    if q == "x":
        if xc > 0.0:
            for sign in (1.0, -1.0):
                ax.axhline(sign * xc, color="0.3", linestyle="--", linewidth=0.9, zorder=1,
                           label=r"$\pm\mu m g/k$" if sign > 0 else None)
        ax.axhline(0.0, color="0.85", linewidth=0.6, zorder=0.5)
        for index, color in panel.arrows:
            if index == LAST:
                plain = cases.curve(*panel.case, (("method", "ansatz"),), t)
                index = _last_outside(plain, xc)
            tn, xn = red.turning_t[index - 1], red.turning_x[index - 1]
            if index > 0 and np.isfinite(tn):
                ax.annotate(f"TP{index} ({tn:.3g} s, {xn / A0:.3g} $x_0$)", xy=(tn, xn),
                            xytext=(tn + 0.06 * t_end, xn + math.copysign(0.32 * A0, xn)),
                            color=color, fontsize=7.5, ha="left",
                            arrowprops=dict(arrowstyle="->", color=color, linewidth=1.2))
        ax.set_ylabel("x [m]")
        ax.text(0.99, 0.97, _halt_text(red, ref), transform=ax.transAxes, ha="right",
                va="top", fontsize=7, color="0.2",
                bbox=dict(boxstyle="round,pad=0.2", facecolor="white", alpha=0.8,
                          edgecolor="0.8"))
    else:
        ax.set_ylabel("E [J]")
        ax.set_ylim(bottom=0.0)
    ax.set_xlim(0.0, t_end)
    ax.set_xlabel("t [s]")
    ax.grid(True, alpha=0.3)
    title = _ratio_title(panel)
    ax.set_title(f"({letter}) {title}" if letter else title, fontsize=9.5)


def _halt_text(red: Curve, ref: Curve) -> str:
    def one(name, c):
        if not math.isfinite(c.halt_time):
            return f"{name}: no halt"
        return f"{name}: halt {c.halt_time:.3f} s at x = {c.halt_position:+.4f} m"
    return one("red", red) + "\n" + one("reference", ref)


def draw_figure(figure: Figure, path, cases: _Cases | None = None, *, dpi: int = 110,
                n_points: int = 1500):
    """Draw one figure of the Lelas & Pezer paper and save it.

    Arguments:
        figure: an entry of :data:`FIGURES`.
        path: output file (format from the suffix).
        cases: a shared solution cache (one is made when None).
        dpi: resolution; n_points: samples per panel.

    Returns:
        ``path``.
    """
    from matplotlib.figure import Figure as MplFigure

    cases = cases or _Cases()
    n = len(figure.panels)
    cols = 2 if n > 1 else 1
    rows = math.ceil(n / cols)
    width = 5.6 * cols if cols > 1 else 8.0
    fig = MplFigure(figsize=(width, 3.3 * rows + 1.0), layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
    for i, panel in enumerate(figure.panels):
        _draw_panel(axes[i], cases, panel, "abcd"[i] if n > 1 else None, n_points)
    x0, v0 = STARTS[figure.panels[0].start]
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center",
               ncol=len(labels) if cols > 1 else 2, fontsize=8, frameon=False)
    caption = "\n".join(textwrap.wrap(f"Fig. {figure.number}: {figure.caption}",
                                         110 if cols > 1 else 80))
    fig.suptitle(f"{caption}\nm = 1 kg, k = 30 N/m, "
                 f"x0 = {x0:.4g} m, v0 = {v0:.4g} m/s", fontsize=10)
    fig.savefig(path, dpi=dpi)
    fig.clear()
    return path


# ----------------------------------------------------------------------------------------------
# Rizcallah's comparison


def _rizcallah_case():
    osc = paper_oscillator(RIZCALLAH_RATIO)
    return osc, float(osc.mu), float(osc.xc)


def _rizcallah_solutions(cases: _Cases, t) -> tuple[dict[str, Curve], Curve]:
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


_KAPPA_STYLE = {"least squares": dict(color="black", linestyle="-", linewidth=1.8),
                "impulse": dict(color="tab:green", linestyle="--", linewidth=1.3),
                "rms": dict(color="tab:red", linestyle="-.", linewidth=1.3)}
_KAPPA_TEXT = {"least squares": r"least squares, $\kappa = 4/\pi$",
               "impulse": r"equal impulse, $\kappa = \pi/2$",
               "rms": r"equal rms, $\kappa = \sqrt{2}$"}


def draw_rizcallah(name: str, path, cases: _Cases | None = None, *, dpi: int = 110):
    """Rizcallah's Fig. 3 (forces), 4 (x(t) of the three amplitudes) or 5 (energy decay).

    Arguments:
        name: one of :data:`RIZCALLAH_FIGURES`.
        path: output file.
        cases: a shared solution cache.
        dpi: resolution.

    Returns:
        ``path``.
    """
    from matplotlib.figure import Figure as MplFigure

    cases = cases or _Cases()
    osc, mu, xc = _rizcallah_case()
    fig = MplFigure(figsize=(9.0, 4.2), layout="constrained")
    ax = fig.subplots()
    case_text = (rf"$d_0/(\omega_0 A_0)$ = {RIZCALLAH_RATIO:g} ($\mu$ = {mu:.4f}), "
                 "m = 1 kg, k = 30 N/m, from rest at x0 = 0.2 m")
    if name == "rizcallah_fig3":
        t = np.linspace(0.0, T0, 1001)
        # -mu m g sgn(v) with v = -w0 A0 sin(w0 t) of the first swings from rest at x0 > 0
        friction = mu * M * G * np.sign(np.sin(W0 * t))
        ax.plot(t, friction, color="tab:blue", linewidth=1.8, label="sliding friction")
        for key, kappa in KAPPAS.items():
            ax.plot(t, kappa * mu * M * G * np.sin(W0 * t), **_KAPPA_STYLE[key],
                    label=_KAPPA_TEXT[key])
        ax.set(xlabel="t [s]", ylabel="force [N]", xlim=(0, T0),
               title="Fig. 3 (Rizcallah): friction and the three sinusoidal resistive forces "
                     "over one period")
    elif name == "rizcallah_fig4":
        t = np.linspace(0.0, REFERENCE_T_END, GRID)
        models, exact = _rizcallah_solutions(cases, t)
        ref = cases.curve(RIZCALLAH_RATIO, 0.0, "rest", _REFERENCE, t)
        for key, c in models.items():
            ax.plot(t, c.x, **_KAPPA_STYLE[key], label=_KAPPA_TEXT[key])
        ax.plot(t, ref.x, color="tab:blue", linestyle=(0, (3, 1, 1, 1)), linewidth=1.3,
                label="numerical (reference)")
        ax.plot(exact.turning_t, exact.turning_x, "o", color="tab:purple", markersize=4,
                label=r"exact turning points $(-1)^n (x_0 - 2 n x_c)$")
        for sign in (1.0, -1.0):
            ax.axhline(sign * xc, color="0.3", linestyle="--", linewidth=0.8)
        ax.set(xlabel="t [s]", ylabel="x [m]", xlim=(0, REFERENCE_T_END),
               title="Fig. 4 (Rizcallah): the three amplitudes against the numerical solution")
    elif name == "rizcallah_fig5":
        t = np.linspace(0.0, REFERENCE_T_END, GRID)
        models, exact = _rizcallah_solutions(cases, t)
        ax.plot(t, exact.energy, color="tab:blue", linewidth=1.6,
                label="exact (step-like decay)")
        ax.plot(t, models["least squares"].energy, color="black", linewidth=1.2,
                label=r"best fit, $\kappa = 4/\pi$")
        ax.plot(t, parabolic_trend(t), color="tab:red", linestyle="--", linewidth=1.4,
                label=r"parabolic trend $E_0 (1 - d_0 t/A_0)^2$ (eq. 6)")
        ax.set(xlabel="t [s]", ylabel="E [J]", xlim=(0, REFERENCE_T_END),
               title="Fig. 5 (Rizcallah): energy decay and its parabolic trend")
        ax.set_ylim(bottom=0.0)
    else:
        raise ValueError(f"name must be one of {RIZCALLAH_FIGURES}, got {name!r}")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="upper right", framealpha=0.9)
    fig.suptitle(case_text, fontsize=9)
    fig.savefig(path, dpi=dpi)
    fig.clear()
    return path


# ----------------------------------------------------------------------------------------------
# the quoted numbers


@dataclasses.dataclass(frozen=True)
class Number:
    """One value a paper quotes, the value dampax computes, and whether they agree.

    ``quoted`` is the text as printed. A numeric quote agrees when the computed value is within
    half a unit of its last printed digit (``tolerance``); a bound (``low``/``high``) when the
    computed value lies inside it. ``note`` explains a known discrepancy in the paper.
    """

    source: str
    quantity: str
    quoted: str
    computed: float
    unit: str = ""
    tolerance: float | None = None
    low: float | None = None
    high: float | None = None
    note: str = ""

    @property
    def value(self) -> float:
        """The quoted number (NaN for a bound)."""
        if self.low is not None or self.high is not None:
            return math.nan
        return _printed_value(self.quoted)

    @property
    def difference(self) -> float:
        return self.computed - self.value

    @property
    def within(self) -> bool:
        if self.low is not None or self.high is not None:
            lo = -math.inf if self.low is None else self.low
            hi = math.inf if self.high is None else self.high
            return lo <= self.computed <= hi
        tol = self.tolerance if self.tolerance is not None else _half_digit(self.quoted)
        return abs(self.difference) <= tol * (1.0 + 1e-9)

    @property
    def status(self) -> str:
        if self.within:
            return "ok"
        return "explained" if self.note else "MISMATCH"


_NUMBER = re.compile(r"[-+]?\d*\.?\d+(?:[eE][-+]?\d+)?")


def _printed_value(text: str) -> float:
    match = _NUMBER.search(text.replace("−", "-"))
    if match is None:
        raise ValueError(f"quoted: no number in {text!r}")
    return float(match.group())


def _half_digit(text: str) -> float:
    """Half a unit in the last printed digit: "0.2002" -> 5e-5, "6e-5" -> 5e-6, "30" -> 0.5."""
    match = _NUMBER.search(text.replace("−", "-"))
    mantissa, _, exponent = match.group().lower().partition("e")
    decimals = len(mantissa.partition(".")[2])
    return 0.5 * 10.0 ** (-decimals + (int(exponent) if exponent else 0))


def _first_after_period(cases: _Cases, d0, d2, options) -> float:
    """|x| at the second turning point (one period after the start at rest) over x0."""
    c = cases.curve(d0, d2, "rest", options, np.linspace(0.0, 1.0, 3))
    return abs(c.turning_x[1]) / A0


def _last_outside(c: Curve, xc: float) -> int:
    """Index (from 1) of the last turning point with |x| > xc."""
    outside = np.flatnonzero(np.abs(c.turning_x) > xc)
    return int(outside[-1]) + 1 if outside.size else 0


def paper_numbers(cases: _Cases | None = None) -> list[Number]:
    """Every value quoted in the two papers (and DESIGN section 4), computed with dampax.

    Arguments:
        cases: a shared solution cache (one is made when None).

    Returns:
        A list of :class:`Number` rows in the order of the papers' sections.
    """
    cases = cases or _Cases()
    probe = np.linspace(0.0, 1.0, 3)
    LP = "Lelas & Pezer"
    rows: list[Number] = []

    def add(*args, **kw):
        rows.append(Number(*args, **kw))

    def ansatz(d0, d2, start, options=(("method", "ansatz"),)):
        return cases.curve(d0, d2, start, options, probe)

    def solved(d0, d2, start):
        return solve(paper_oscillator(d0, d2), *STARTS[start])

    # Sec. II: the block
    add(f"{LP} II", "w0 = sqrt(k/m)", "5.48", W0, "1/s")
    add(f"{LP} II", "T0 = 2 pi/w0", "1.15", T0, "s")
    # Sec. III: quadratic drag
    for ratio, D in zip(_QUAD, ("1.18", "2.95", "5.89", "8.84"), strict=True):
        add(f"{LP} III.A", f"D for d2 A0/w0 = {ratio:g} (eq. 21)", D,
            float(paper_oscillator(0.0, ratio).D), "kg/m")
    for model, options in (("E(0), eq. 15", (("method", "ansatz"),)), ("E~(0), eq. 10", _UNDAMPED)):
        c = cases.curve(0.0, 0.25, "rest", options, np.zeros(1))
        add(f"{LP} III.A", model, "0.6", float(c.energy[0]), "J")
    add(f"{LP} III.A / Fig. 2(b)",
        "numerical |x| one period after release, d2 A0/w0 = 0.25, over x0",
        "somewhat less than 50 %", _first_after_period(cases, 0.0, 0.25, _REFERENCE),
        low=0.35, high=0.5)
    add(f"{LP} III.A / Fig. 2(c)",
        "numerical |x| one period after release, d2 A0/w0 = 0.5, over x0",
        "slightly less than 25 %", _first_after_period(cases, 0.0, 0.5, _REFERENCE),
        low=0.2, high=0.25)
    add(f"{LP} III.B", "v0 = w0 A0", "1.10", W0 * A0, "m/s")
    sol = solved(0.0, 0.25, "push")
    add(f"{LP} III.B", "A for (x0 = 0, v0 = w0 A0): A = A0 (eq. 26)", "0.2",
        float(sol.amplitude), "m", tolerance=1e-12)
    add(f"{LP} III.B", "phi for (x0 = 0, v0 = w0 A0): phi = -pi/2 (eq. 27)", "-1.5707963268",
        float(sol.phase), "rad", tolerance=1e-10)
    x0, v0 = STARTS["diag-"]
    add(f"{LP} III.C", "x0 = A0 sqrt(2)/2", "0.14", x0, "m")
    add(f"{LP} III.C", "v0 = -w0 x0", "-0.77", v0, "m/s")
    add(f"{LP} III.C", "phi0 = pi/4", "0.7853981634", math.atan2(-v0 / W0, x0), "rad",
        tolerance=1e-10)
    # Sec. IV: Coulomb
    for ratio, mu in ((0.05, "0.048"), (0.1, "0.096"), (0.03, "0.029")):
        add(f"{LP} IV.A", f"mu for d0/(w0 A0) = {ratio:g}", mu,
            float(paper_oscillator(ratio).mu))
    for ratio, A, phi in ((0.05, "0.2002", "-0.05"), (0.1, "0.201", "-0.1")):
        sol = solved(ratio, 0.0, "rest")
        add(f"{LP} IV.A", f"A, d0/(w0 A0) = {ratio:g}, from rest (eq. 40)", A,
            float(sol.amplitude), "m")
        add(f"{LP} IV.A", f"phi, d0/(w0 A0) = {ratio:g}, from rest (eq. 40)", phi,
            float(sol.phase), "rad")
    c = ansatz(0.1, 0.0, "rest")
    n = _last_outside(c, float(paper_oscillator(0.1).xc))
    add(f"{LP} IV.A / Fig. 8(b)", "last turning point with |x| > xc: t0", "1.12",
        float(c.turning_t[n - 1]), "s")
    add(f"{LP} IV.A / Fig. 8(b)", "last turning point with |x| > xc: x(t0)", "0.076",
        float(c.turning_x[n - 1]), "m")
    exact = cases.curve(0.03, 0.0, "rest", (("method", "coulomb_exact"),), probe)
    add(f"{LP} IV.A / Fig. 11", "half-periods of the exact solution, d0/(w0 A0) = 0.03",
        "eleven (11)", exact.halt_time / (T0 / 2), tolerance=1e-9)
    exact = cases.curve(0.1, 0.0, "rest", (("method", "coulomb_exact"),), probe)
    add(f"{LP} IV.D", "half-periods of the exact solution, d0/(w0 A0) = 0.1",
        "three (3)", exact.halt_time / (T0 / 2), tolerance=1e-9)
    add(f"{LP} IV.D / Fig. 9(b)",
        "numerical |x| one period after release, d0/(w0 A0) = 0.1, over x0",
        "less than 50 %", _first_after_period(cases, 0.1, 0.0, _REFERENCE), high=0.5)
    for k, (xn, tn) in enumerate((("-0.13717", 1), ("0.07434", 2), ("-0.01150", 3))):
        add("DESIGN 4 (exact Coulomb 0.1)", f"exact turning point {k + 1}", xn,
            float(exact.turning_x[k]), "m")
        add("DESIGN 4 (exact Coulomb 0.1)", f"time of exact turning point {k + 1} = n pi/w0",
            f"{tn * math.pi / W0:.10f}", float(exact.turning_t[k]), "s", tolerance=1e-10)
    add("DESIGN 4 (exact Coulomb 0.1)", "rest position", "-0.01150", exact.halt_position, "m")
    sol = solved(0.05, 0.0, "push")
    add(f"{LP} IV.B", "A for (x0 = 0, v0 = w0 A0), Coulomb 0.05: A = A0 (eq. 33)", "0.2",
        float(sol.amplitude), "m", tolerance=1e-12)
    add(f"{LP} IV.B", "phi for (x0 = 0, v0 = w0 A0), Coulomb 0.05: -pi/2 (eq. 34)",
        "-1.5707963268", float(sol.phase), "rad", tolerance=1e-10)
    # IV.C: the quartic of eq. 33 with dampax's d0
    x0, v0 = STARTS["diag+"]
    d0 = float(damping_coefficients(paper_oscillator(0.05))[0])
    coeffs = np.array([W0**2, 0.0, -(v0**2 + W0**2 * x0**2), -2 * x0 * v0 * d0,
                       -(d0**2) * x0**2])
    for name, printed, value in (("A^4", "30", coeffs[0]), ("A^2", "-1.200", coeffs[2]),
                                 ("A^1", "-0.012", coeffs[3]), ("A^0", "-6e-5", coeffs[4])):
        add(f"{LP} IV.C", f"eq. 33 coefficient of {name}", printed, float(value))
    roots = np.roots(coeffs)
    real = np.sort(roots[np.abs(roots.imag) < 1e-12].real)[::-1]
    cplx = roots[np.abs(roots.imag) >= 1e-12]
    add(f"{LP} IV.C", "eq. 33 root 1", "0.205", float(real[0]), "m")
    add(f"{LP} IV.C", "eq. 33 root 2", "-0.195", float(real[1]), "m")
    add(f"{LP} IV.C", "eq. 33 complex roots, real part", "-0.005", float(cplx[0].real), "m")
    add(f"{LP} IV.C", "eq. 33 complex roots, |imaginary part|", "0.005",
        float(abs(cplx[0].imag)), "m")
    sol = solved(0.05, 0.0, "diag+")
    add(f"{LP} IV.C", "A (the root near A0)", "0.205", float(sol.amplitude), "m")
    add(f"{LP} IV.C", "phi (eq. 34)", "-0.809", float(sol.phase), "rad")
    # Sec. V: Coulomb + quadratic
    for ratio, text in ((0.01, "0.016"), (0.03, "0.047")):
        add(f"{LP} V.A", f"xc = mu m g/k over x0, d0/(w0 A0) = {ratio:g}", text,
            float(paper_oscillator(ratio).xc) / A0)
    c14c = ansatz(0.03, 0.15, "rest")
    xc = float(paper_oscillator(0.03).xc)
    note14c = ("the paper's text disagrees with its equations: A, phi of eqs. 43, 23 and f(t) of "
               "eq. 45 put the fifth turning point 3.8 % above xc (2.809 s; confirmed by an "
               "independent scipy integration of eq. 20 in the tests), so the fifth, not the "
               "fourth, is the last one outside the band; on the graph the two are hard to tell "
               "apart")
    add(f"{LP} V.A / Fig. 14(c)", "|x| of the fifth turning point over xc",
        "just slightly less (than 1)", abs(float(c14c.turning_x[4])) / xc, low=0.9, high=1.0,
        note=note14c)
    add(f"{LP} V.A / Fig. 14(c)", "index of the last turning point with |x| > xc", "4",
        _last_outside(c14c, xc), tolerance=0, note=note14c)
    c14d = ansatz(0.03, 0.25, "rest")
    note14 = ("the paper's (2.37 s, 0.049 x0) is the V.C case's fifth turning point (DESIGN 4): "
              "the equations give the fourth turning point here")
    add(f"{LP} V.A / Fig. 14(d)", "last turning point with |x| > xc (red arrow): t0", "2.37",
        float(c14d.turning_t[3]), "s", note=note14)
    add(f"{LP} V.A / Fig. 14(d)", "last turning point with |x| > xc (red arrow): x(t0)/x0",
        "0.049", float(c14d.turning_x[3]) / A0, note=note14)
    add(f"{LP} V.A / Fig. 14(d)", "x(t0) larger than xc by", "4 %",
        100.0 * (abs(float(c14d.turning_x[3])) / xc - 1.0), "%", tolerance=0.5,
        note="4 % is 0.049/0.047 of the misplaced pair; the fourth turning point of this case "
             "lies 17.6 % above xc (and V.C's fifth 2.9 %)")
    note3 = ("read off the graph (green arrow) in the paper; the model's third turning point "
             "by Newton's method is 0.009 s earlier (the reference's is at 1.745 s, "
             "-0.150 x0)")
    add(f"{LP} V.A / Fig. 14(d)", "third turning point (green arrow): t3", "1.74",
        float(c14d.turning_t[2]), "s", note=note3)
    add(f"{LP} V.A / Fig. 14(d)", "third turning point (green arrow): x(t3)/x0", "-0.155",
        float(c14d.turning_x[2]) / A0, note=note3)
    add(f"{LP} V.D / Fig. 14(d)", "|x| one period after release (red curve), over x0",
        "about 30 %", abs(float(c14d.turning_x[1])) / A0, low=0.25, high=0.35)
    c19 = ansatz(0.03, 0.25, "push")
    add(f"{LP} V.B / Fig. 19", "index of the last turning point with |x| > xc", "4",
        _last_outside(c19, xc), tolerance=0)
    sol = solved(0.03, 0.25, "diag+")
    add(f"{LP} V.C", "A (the root of eq. 43 nearest A0)", "0.234", float(sol.amplitude), "m")
    add(f"{LP} V.C", "phi", "-0.922", float(sol.phase), "rad")
    c20 = ansatz(0.03, 0.25, "diag+")
    add(f"{LP} V.C / Fig. 20", "index of the last turning point with |x| > xc", "5",
        _last_outside(c20, xc), tolerance=0)
    note20 = ("read off the graph; the model's turning point by Newton's method (A and phi agree "
              "with the printed digits; with the rounded A = 0.234, phi = -0.922 the point moves "
              "by < 1e-4)")
    add(f"{LP} V.C / Fig. 21", "fourth turning point: t4", "1.84", float(c20.turning_t[3]),
        "s", note=note20)
    add(f"{LP} V.C / Fig. 21", "fourth turning point: x(t4)/x0", "-0.146",
        float(c20.turning_x[3]) / A0, note=note20)
    add(f"{LP} V.C / Fig. 20", "fifth turning point: t5", "2.37", float(c20.turning_t[4]), "s")
    add(f"{LP} V.C / Fig. 20", "fifth turning point: x(t5)/x0", "0.049",
        float(c20.turning_x[4]) / A0, note=note20)
    rows.extend(_rizcallah_numbers(cases))
    return rows


def _rizcallah_numbers(cases: _Cases) -> list[Number]:
    R = "Rizcallah"
    osc, mu, xc = _rizcallah_case()
    t = np.linspace(0.0, 1.0, 3)
    models, exact = _rizcallah_solutions(cases, t)
    n = int(np.sum(np.isfinite(exact.turning_t)))
    ns = np.arange(1, n + 1)
    x_exact = (-1.0) ** ns * (A0 - 2 * ns * xc)  # eq. 2
    best = models["least squares"]
    rows = [
        Number(f"{R} 4", "amplitude factor kappa, equal rms", "1.414", KAPPAS["rms"]),
        Number(f"{R} 4", "amplitude factor kappa, equal impulse", "1.571", KAPPAS["impulse"]),
        Number(f"{R} 4", "amplitude factor kappa, least squares", "1.273",
               KAPPAS["least squares"]),
        Number(f"{R} 4", "kappa 4/pi: max |x_n - (-1)^n (x0 - 2 n xc)| over the turning points "
               "(perfect agreement, eq. 2)", "0", float(np.max(np.abs(best.turning_x[:n]
                                                                     - x_exact))),
               "m", tolerance=1e-12),
        Number(f"{R} 4", "kappa 4/pi: max |t_n - n pi/w0| (turning points at the right times)",
               "0", float(np.max(np.abs(best.turning_t[:n] - ns * math.pi / W0))), "s",
               tolerance=1e-12),
    ]
    half = n // 2
    for key in ("impulse", "rms"):
        ratio = abs(models[key].turning_x[half - 1]) / abs(x_exact[half - 1])
        rows.append(Number(f"{R} 4", f"kappa {key}: |x_n| over the exact one at n = {half} "
                           "(too fast a decay)", "< 1", float(ratio), high=1.0))
    # eq. 6: the energy at the turning points lies on the parabolic trend
    E_tp = 0.5 * K * x_exact**2
    trend = parabolic_trend(ns * math.pi / W0)
    rows.append(Number(f"{R} 5", "max |E(t_n) - E0 (1 - d0 t_n/A0)^2| / E0, exact solution at "
                       "its turning points (the trend through the steps)", "0",
                       float(np.max(np.abs(E_tp - trend)) / (0.5 * K * A0**2)),
                       tolerance=1e-12))
    # Sec. 6: the model's acceleration at a turning point is halfway between the exact limits
    sol = solve(osc, A0, 0.0, method="rizcallah")
    t1 = math.pi / W0
    acc = float(jax.grad(lambda s: sol.v(s))(jnp.asarray(t1)))
    x1 = float(exact.turning_x[0])
    left, right = (-K * x1 - mu * M * G) / M, (-K * x1 + mu * M * G) / M  # v < 0, then v > 0
    rows.append(Number(f"{R} 6", "acceleration at the first turning point minus the mean of "
                       "the exact left and right limits, over mu g (halfway)", "0",
                       abs(acc - 0.5 * (left + right)) / (mu * G), tolerance=1e-9))
    return rows


NUMBER_FIELDS = ("source", "quantity", "quoted", "computed", "difference", "unit", "status",
                 "note")


def write_numbers(rows: Sequence[Number], out: Path) -> tuple[Path, Path]:
    """Write ``numbers.csv`` and ``numbers.md`` into ``out``.

    Arguments:
        rows: the output of :func:`paper_numbers`.
        out: the folder.

    Returns:
        The two paths.
    """
    out = Path(out)
    csv_path, md_path = out / "numbers.csv", out / "numbers.md"
    with open(csv_path, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(NUMBER_FIELDS)
        for r in rows:
            writer.writerow([r.source, r.quantity, r.quoted, repr(r.computed),
                             "" if math.isnan(r.value) else repr(r.difference), r.unit,
                             r.status, r.note])
    counts = {s: sum(r.status == s for r in rows) for s in ("ok", "explained", "MISMATCH")}
    lines = [
        "# Numbers quoted in the papers, recomputed with dampax",
        "",
        "Lelas & Pezer (Part I) and Rizcallah (2019); the papers' block m = 1 kg, k = 30 N/m, "
        "g = 9.81 m/s^2, A0 = 0.2 m. *ok*: the computed value is within half a unit of the "
        "last printed digit (or inside the quoted bound); *explained*: a known discrepancy "
        "of the paper's text, see the note.",
        "",
        f"{len(rows)} rows: {counts['ok']} ok, {counts['explained']} explained, "
        f"{counts['MISMATCH']} mismatched.",
        "",
        "| # | source | quantity | paper | dampax | difference | unit | status |",
        "|---|---|---|---|---|---|---|---|",
    ]
    notes: dict[str, list[int]] = {}  # note -> rows (one note often covers t and x)
    for i, r in enumerate(rows, 1):
        diff = "" if math.isnan(r.value) else f"{r.difference:+.2g}"
        status = r.status
        if r.note:
            notes.setdefault(r.note, []).append(i)
            status += f" (note {list(notes).index(r.note) + 1})" if r.status != "ok" else ""
        lines.append(f"| {i} | {r.source} | {r.quantity} | {r.quoted} | {_fmt(r.computed)} | "
                     f"{diff} | {r.unit} | {status} |")
    if notes:
        lines += ["", "Notes:", ""]
        for j, (note, at) in enumerate(notes.items(), 1):
            where = ("rows " if len(at) > 1 else "row ") + ", ".join(map(str, at))
            lines.append(f"{j}. ({where}) {note}")
    md_path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return csv_path, md_path


def _fmt(value: float) -> str:
    if value == 0 or not math.isfinite(value):
        return f"{value:g}"
    return f"{value:.6g}" if abs(value) >= 1e-4 else f"{value:.3g}"


# ----------------------------------------------------------------------------------------------
# the whole job


@dataclasses.dataclass
class Reproduction:
    """What :func:`reproduce` wrote."""

    figures: dict[str, Path]
    numbers: list[Number]
    numbers_csv: Path | None
    numbers_md: Path | None


def select_figures(spec: str | Sequence[str] | None) -> tuple[str, ...]:
    """Figure names from a selection such as ``"2,3,8-10,rizcallah"``.

    Arguments:
        spec: None (all), a comma-separated string or a list of items: figure numbers 2-21,
            ranges ``a-b``, names (``fig08``, ``rizcallah_fig4``), ``rizcallah`` (its three
            figures), ``none`` (numbers only).

    Returns:
        Names in :data:`ALL_FIGURES` order.
    """
    if spec is None:
        return ALL_FIGURES
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    chosen: set[str] = set()
    for raw in items:
        item = str(raw).strip().lower()
        if not item or item == "none":
            continue
        if item == "all":
            chosen.update(ALL_FIGURES)
        elif item == "rizcallah":
            chosen.update(RIZCALLAH_FIGURES)
        elif item in ALL_FIGURES:
            chosen.add(item)
        elif re.fullmatch(r"\d+(-\d+)?", item):
            lo, _, hi = item.partition("-")
            numbers = range(int(lo), int(hi or lo) + 1)
            bad = [n for n in numbers if not 2 <= n <= 21]
            if bad or not numbers:
                raise ValueError(f"figures: {item!r} is not among the paper's Figures 2-21")
            chosen.update(f"fig{n:02d}" for n in numbers)
        else:
            raise ValueError(f"figures: unknown item {raw!r}; use numbers 2-21, ranges such as "
                             f"8-10, 'rizcallah', 'all', 'none' or names {ALL_FIGURES[:2]}...")
    return tuple(name for name in ALL_FIGURES if name in chosen)


def reproduce(out, *, figures: str | Sequence[str] | None = None, numbers: bool = True,
              fmt: str = "png", dpi: int = 110, progress: bool = True,
              callback: Callable[[str], None] | None = None) -> Reproduction:
    """Regenerate the papers' figures and quoted numbers into a folder.

    Arguments:
        out: output folder (created).
        figures: which figures (see :func:`select_figures`); default all 20 + 3.
        numbers: also write ``numbers.csv`` and ``numbers.md``.
        fmt: image format (``png``, ``pdf``, ``svg``).
        dpi: resolution of raster images.
        progress: show a tqdm progress bar (stderr).
        callback: called with each written file's name.

    Returns:
        A :class:`Reproduction`: figure paths by name, the numbers and their files.
    """
    from matplotlib.backend_bases import FigureCanvasBase

    if fmt not in FigureCanvasBase.get_supported_filetypes():
        raise ValueError(f"fmt: unsupported image format {fmt!r}")
    names = select_figures(figures)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cases = _Cases()
    by_name = {f.name: f for f in FIGURES}
    written: dict[str, Path] = {}
    steps = list(names) + (["numbers"] if numbers else [])
    from tqdm import tqdm  # plain text bar: tqdm.auto warns in notebooks without ipywidgets

    bar = tqdm(steps, desc="reproduce", unit="item", disable=not progress, leave=True)
    rows: list[Number] = []
    csv_path = md_path = None
    for step in bar:
        bar.set_postfix_str(step)
        if step == "numbers":
            rows = paper_numbers(cases)
            csv_path, md_path = write_numbers(rows, out)
            if callback:
                callback(csv_path.name)
                callback(md_path.name)
            continue
        path = out / f"{step}.{fmt}"
        if step in by_name:
            draw_figure(by_name[step], path, cases, dpi=dpi)
        else:
            draw_rizcallah(step, path, cases, dpi=dpi)
        written[step] = path
        if callback:
            callback(path.name)
    bar.close()
    return Reproduction(written, rows, csv_path, md_path)
