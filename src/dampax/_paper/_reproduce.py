"""Reproduce the papers: Figures 2-21 of Lelas & Pezer, Rizcallah's comparison, quoted numbers.

:func:`reproduce` draws every figure of the Lelas & Pezer paper (Part I) with the same cases and
colour code (matched ansatz solid red, undamped-phase ansatz solid blue, reference black dotted,
the sticking band +-xc dashed) and Rizcallah's Figures 3-5 (the three friction amplitudes and
the energy decay with its parabolic trend), and writes the quoted numbers recomputed by
``_numbers.paper_numbers``. The figures are named after the papers' numbers: ``fig02.png`` ...
``fig21.png`` and ``rizcallah_fig3.png`` ... ``rizcallah_fig5.png``. The cases are in
``_paper``.
"""

from __future__ import annotations

import dataclasses
import math
import re
import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from .._io import save_figure
from .._models._registry import MODELS
from .._studies._summary import default_t_end
from ._cases import (
    A0,
    ALL_FIGURES,
    FIGURES,
    GRID,
    KAPPAS,
    LAST,
    REFERENCE,
    REFERENCE_T_END,
    RIZCALLAH_FIGURES,
    RIZCALLAH_RATIO,
    STARTS,
    T0,
    UNDAMPED,
    W0,
    Cases,
    Curve,
    Figure,
    G,
    M,
    Panel,
    last_outside,
    paper_oscillator,
    parabolic_trend,
    rizcallah_case,
    rizcallah_solutions,
)
from ._numbers import Number, paper_numbers, write_numbers


def _red_options(panel: Panel) -> tuple:
    return (("method", "ansatz"),) + tuple(panel.red)


def _panel_t_end(cases: Cases, panel: Panel) -> float:
    """The panel's time span: its own, else :func:`default_t_end` of the models drawn."""
    if panel.t_end is not None:
        return panel.t_end
    probe = np.linspace(0.0, REFERENCE_T_END, 9)
    halts = [cases.curve(*panel.case, opts, probe).halt_time
             for opts in (REFERENCE, _red_options(panel), UNDAMPED)]
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
    """The registry's line style without its label (the panels label their own curves)."""
    return {k: v for k, v in MODELS[name].style.items() if k != "label"}


def _red_label(panel: Panel) -> str:
    opts = dict(panel.red)
    if opts.get("tail"):
        return "improved x(t), eq. 54" if opts.get("back") else "improved x(t), eqs. 41/52"
    return "x(t), matched ansatz"


def _draw_panel(ax, cases: Cases, panel: Panel, letter: str | None, n_points: int):
    t_end = _panel_t_end(cases, panel)
    t = np.linspace(0.0, t_end, n_points)
    red = cases.curve(*panel.case, _red_options(panel), t)
    ref = cases.curve(*panel.case, REFERENCE, t)
    blue = cases.curve(*panel.case, UNDAMPED, t) if panel.blue or panel.quantity == "E" else None
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
                index = last_outside(plain, xc)
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


def draw_figure(figure: Figure, path, cases: Cases | None = None, *, dpi: int = 110,
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

    cases = cases or Cases()
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
    save_figure(fig, path, dpi=dpi)
    fig.clear()
    return path


_KAPPA_STYLE = {"least squares": dict(color="black", linestyle="-", linewidth=1.8),
                "impulse": dict(color="tab:green", linestyle="--", linewidth=1.3),
                "rms": dict(color="tab:red", linestyle="-.", linewidth=1.3)}
_KAPPA_TEXT = {"least squares": r"least squares, $\kappa = 4/\pi$",
               "impulse": r"equal impulse, $\kappa = \pi/2$",
               "rms": r"equal rms, $\kappa = \sqrt{2}$"}


def draw_rizcallah(name: str, path, cases: Cases | None = None, *, dpi: int = 110):
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

    cases = cases or Cases()
    osc, mu, xc = rizcallah_case()
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
        models, exact = rizcallah_solutions(cases, t)
        ref = cases.curve(RIZCALLAH_RATIO, 0.0, "rest", REFERENCE, t)
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
        models, exact = rizcallah_solutions(cases, t)
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
    save_figure(fig, path, dpi=dpi)
    fig.clear()
    return path


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
    cases = Cases()
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
