"""Figures of fits: data, fit and residuals with units and the sticking band (a trace, several
runs), and the corner plot of a posterior's draws.

Drawn with matplotlib's object API on the Agg canvas, as the other figures (``_plot`` shares
this module's panel placement, :func:`_place`). This module imports nothing of dampax but
``_io`` and nothing of JAX: ``dampax fit`` draws its figure in a process of its own that
never imports JAX (``dampax_cli._figures``), from :func:`figure_data`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ._io import save_figure


def _place(fig, *, nrows: int = 1, ncols: int = 1, left: float, right: float, bottom: float,
           top: float, wspace: float = 0.0, hspace: float = 0.0) -> None:
    """Place the subplot grid with fixed margins and gaps given in inches.

    The figures are drawn without matplotlib's constrained layout, which measures every text
    of a figure before placing the panels (about half the time of a heat-map figure, issue 26);
    the margins here leave room for tick labels, axis labels, titles and legends of the sizes
    this module uses.

    Arguments:
        fig: the figure (its size is fixed).
        nrows, ncols: the subplot grid.
        left, right, bottom, top: margins [in] between the figure's edges and the grid.
        wspace, hspace: gaps [in] between columns and between rows.
    """
    width, height = fig.get_size_inches()
    panel_w = max((width - left - right - (ncols - 1) * wspace) / ncols, 0.1)
    panel_h = max((height - top - bottom - (nrows - 1) * hspace) / nrows, 0.1)
    fig.subplots_adjust(left=left / width, right=1.0 - right / width, bottom=bottom / height,
                        top=1.0 - top / height, wspace=wspace / panel_w,
                        hspace=hspace / panel_h)


# ----------------------------------------------------------------------------------------------
# issue 11: the posterior of a fit (corner plot)


def plot_corner(draws, names, path, *, units: Mapping | None = None, bins: int = 40,
                dpi: int = 110):
    """Corner plot of posterior draws: histograms on the diagonal, pairwise scatter below.

    Arguments:
        draws: an xarray Dataset with dims (chain, draw) (``Posterior.draws``) or a mapping
            name -> array.
        names: the variables to draw.
        path: where to save the PNG.
        units: optional unit per name, for the axis labels.
        bins, dpi: histogram bins and resolution.

    Returns:
        The path written.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    names = list(names)
    if not names:
        raise ValueError("names: give at least one variable to draw")
    units = dict(units or {})
    values = {n: np.asarray(draws[n]).reshape(-1) for n in names}
    k = len(names)
    fig = Figure(figsize=(2.4 * k + 0.8, 2.4 * k + 0.6))
    FigureCanvasAgg(fig)
    axes = np.atleast_2d(fig.subplots(k, k, squeeze=False))
    _place(fig, nrows=k, ncols=k, left=0.75, right=0.2, bottom=0.6, top=0.4, wspace=0.5,
           hspace=0.35)
    for i, ni in enumerate(names):
        for j, nj in enumerate(names):
            ax = axes[i, j]
            if j > i:
                ax.set_visible(False)
                continue
            if i == j:
                ax.hist(values[ni], bins=bins, color="tab:blue", alpha=0.8)
                ax.set_yticks([])
            else:
                ax.plot(values[nj], values[ni], ".", ms=1.5, alpha=0.3, color="tab:blue")
            if i == k - 1:
                unit = units.get(nj, "")
                ax.set_xlabel(f"{nj} [{unit}]" if unit else nj, fontsize=8)
            if j == 0 and i > 0:
                unit = units.get(ni, "")
                ax.set_ylabel(f"{ni} [{unit}]" if unit else ni, fontsize=8)
            ax.tick_params(labelsize=7)
    fig.suptitle("posterior draws (NUTS)", fontsize=10, y=1.0 - 0.06 / fig.get_figheight(),
                 va="top")
    save_figure(fig, path, dpi=dpi)
    fig.clear()
    return Path(path)


# ----------------------------------------------------------------------------------------------
# fits (dampax.fit): data, fit and residuals, with units and the sticking band


def sticking_band(result) -> tuple[float, str] | None:
    """The half-width of the band around the offset where a fitted trace's block sticks.

    The block sticks at a turning point x where |k y + k3 y^3| <= mu_s m g, y = x - offset
    (eq. 3 with static friction; ``Oscillator.mu_s``): with static friction mu_s set (held,
    ``result.fixed["mu_s"]``, or fitted, ``"mu_s"`` in ``result.free``) the band is the static
    one; without it mu_s = mu and the band is the kinetic one, drawn only when mu was fitted.
    k = m w0^2 and k3 are the fit's (per unit mass in a per-mass fit, where m = 1).

    Arguments:
        result: a trace fit's result (:class:`dampax.FitResult`).

    Returns:
        (half-width in the fit's position units, "static" or "kinetic"), or None when there is
        no band (an envelope fit, no friction, or a softening k3 that never holds the block).
    """
    if getattr(result, "kind", "trace") != "trace":
        return None
    params, fixed, free = result.params, result.fixed, tuple(result.free)
    if "mu_s" in free:
        mu_s = params.get("mu_s")
    else:
        mu_s = fixed.get("mu_s", params.get("mu_s"))
    mu = float(params.get("mu", 0.0))
    if mu_s is not None and math.isfinite(float(mu_s)) and float(mu_s) > 0.0:
        coefficient, which = max(float(mu_s), mu), "static"
    elif "mu" in free and mu > 0.0:
        coefficient, which = mu, "kinetic"
    else:
        return None
    m = float(fixed.get("m", 1.0))
    g = float(fixed.get("g", 9.81))
    k = float(result.derived.get("k", m * float(params.get("w0", math.nan)) ** 2))
    k3 = params.get("k3", fixed.get("k3", 0.0))
    k3 = 0.0 if k3 is None or not math.isfinite(float(k3)) else float(k3)
    force = coefficient * m * g
    if not (math.isfinite(k) and k > 0.0 and math.isfinite(force)):
        return None
    if k3 == 0.0:
        return force / k, which
    # k y + k3 y^3 = force: the smallest positive real root (none for a softening k3 too weak
    # to hold the block anywhere past its turning point)
    roots = np.roots([k3, 0.0, k, -force])
    real = [float(r.real) for r in roots if abs(r.imag) <= 1e-9 * max(abs(r), 1.0)
            and r.real > 0.0]
    return (min(real), which) if real else None


def _band_label(result, which: str) -> str:
    """Legend text of the sticking band: which friction sets it, and the rule."""
    k3 = result.params.get("k3", result.fixed.get("k3", 0.0)) or 0.0
    force = "|k y + k3 y³|" if k3 else "k |y|"
    if which == "static":
        mu_s = (result.params["mu_s"] if "mu_s" in result.free
                else result.fixed.get("mu_s", result.params.get("mu_s")))
        return (f"static sticking band: {force} ≤ μs m g, y = x - offset "
                f"(μs = {float(mu_s):.4g})")
    return f"sticking band (kinetic μ, μs = μ): {force} ≤ μ m g, y = x - offset"


def _position_unit(result) -> str:
    return getattr(result, "units", None) or "m"


def import_figure_modules() -> None:
    """Import what :func:`fit_figure` draws with (matplotlib's Figure and Agg canvas), e.g.
    in a thread while the fit it will draw still runs."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: F401
    from matplotlib.figure import Figure  # noqa: F401


#: resolution of a fit's figure
FIT_DPI = 110


def plot_fit(result, path, *, title: str | None = None, dpi: int = FIT_DPI):
    """Save the figure of a fit: data, fit, envelope and sticking band above, residuals below.

    The axes carry their units: time in s, positions (and residuals) in the fit's position
    unit ``result.units`` (per-mass fits too: only b, D, k3 are per unit mass there). The
    sticking band is the static one |k y + k3 y^3| <= mu_s m g (y = x - offset) where static
    friction mu_s is set (held or fitted), else the kinetic one (mu, drawn when mu was fitted);
    the legend says which (:func:`sticking_band`).

    Arguments:
        result: a :class:`dampax.FitResult` (of a trace or of maxima).
        path: output file; the format follows the suffix (e.g. ``.png``).
        title: the title (default: the source, the fitted terms and the rms).
        dpi: resolution of raster output.

    Returns:
        ``path`` as a :class:`pathlib.Path`.
    """
    fig = fit_figure(result, title=title)
    save_figure(fig, path, dpi=dpi)
    fig.clear()
    return Path(path)


#: what :func:`fit_figure` reads of a trace's or maxima's fit (:class:`dampax.FitResult`)
FIGURE_FIELDS = ("kind", "units", "model", "source", "free", "params", "fixed", "derived", "t",
                 "x", "model_x", "residuals", "envelope", "full_t", "full_x", "rms")


def figure_data(result) -> SimpleNamespace:
    """What :func:`fit_figure` draws of ``result``, as plain values (numbers, strings, numpy
    arrays): drawn the same, and picklable without dampax's classes (``dampax_cli._figures``)."""
    return SimpleNamespace(**{name: getattr(result, name) for name in FIGURE_FIELDS})


def fit_figure(result, *, title: str | None = None):
    """The figure of :func:`plot_fit`, not saved (a matplotlib Figure on the Agg canvas).

    Arguments:
        result: a :class:`dampax.FitResult` (or its :func:`figure_data`).
        title: the title (default: the source, the fitted terms and the rms).

    Returns:
        The Figure: its first axes the data, fit, envelope and band, its second the residuals.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    unit = _position_unit(result)
    envelope_fit = result.kind == "envelope"
    fig = Figure(figsize=(10, 6.5))
    FigureCanvasAgg(fig)
    ax, axr = fig.subplots(2, 1, sharex=True, height_ratios=(3, 1))
    _place(fig, nrows=2, left=0.95, right=0.2, bottom=0.6, top=0.35, hspace=0.2)
    off = float(result.params.get("offset", 0.0))
    full_t, full_x = result.full_t, result.full_x
    if full_t is not None and len(full_t) > len(result.t):
        before = np.asarray(full_t) < result.t[0]
        if np.any(before):
            ax.plot(np.asarray(full_t)[before], np.asarray(full_x)[before], color="0.7",
                    lw=0.6, label="data before the fit start")
    marker = dict(ls="none", marker=".", ms=4) if envelope_fit or len(result.t) < 400 \
        else dict(lw=0.6)
    ax.plot(result.t, result.x, color="tab:blue", label="data", **marker)
    ax.plot(result.t, result.model_x, color="tab:red", lw=0.9, label=f"fit ({result.model})")
    if result.envelope is not None and not envelope_fit:
        ax.plot(result.t, off + result.envelope, color="k", lw=0.8, ls="--",
                label="envelope A f(t)")
        ax.plot(result.t, off - result.envelope, color="k", lw=0.8, ls="--")
    band = sticking_band(result)
    if band is not None:
        half, which = band
        ax.axhspan(off - half, off + half, color="tab:orange" if which == "kinetic"
                   else "tab:purple", alpha=0.22, lw=0, label=_band_label(result, which))
    ax.set_ylabel(f"{'amplitude' if envelope_fit else 'position'} [{unit}]")
    # mu is a coefficient only for positions in metres: else the deceleration mu g (the
    # report's mu_g; the title read "mu = 1.999" for a trace in mm, 1000x the coefficient)
    terms = ", ".join(f"mu g = {result.derived['mu_g']:.4g} {unit}/s^2"
                      if k == "mu" and unit != "m" and "mu_g" in result.derived
                      else f"{k} = {result.params[k]:.4g}" for k in result.free)
    what = result.source or ("maxima" if envelope_fit else "trace")
    ax.set_title(title or f"{what}: {terms}  (rms {result.rms:.3g} {unit})", fontsize=9)
    ax.legend(fontsize=8, loc="upper right")
    axr.plot(result.t, result.residuals, color="tab:blue", lw=0.5,
             **({"marker": ".", "ls": "none"} if envelope_fit else {}))
    axr.axhline(0.0, color="k", lw=0.6)
    axr.set_ylabel(f"data - fit [{unit}]")
    axr.set_xlabel("t [s]")
    return fig


def plot_joint_fit(result, path, *, title: str | None = None, dpi: int = 110):
    """Save the figure of a joint fit: each run's data and fit above its residuals, in units.

    Arguments:
        result: a joint fit's result (``dampax.fit`` of several traces; its ``runs`` are
            :class:`dampax.FitResult`).
        path: output file; the format follows the suffix.
        title: the title (default: the shared constants).
        dpi: resolution of raster output.

    Returns:
        ``path`` as a :class:`pathlib.Path`.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    unit = _position_unit(result)
    n = len(result.runs)
    fig = Figure(figsize=(10, 2.6 * n + 1.0))
    FigureCanvasAgg(fig)
    axes = fig.subplots(2 * n, 1, height_ratios=[3, 1] * n)
    _place(fig, nrows=2 * n, left=0.95, right=0.2, bottom=0.55, top=0.45, hspace=0.35)
    for j, r in enumerate(result.runs):
        ax, axr = axes[2 * j], axes[2 * j + 1]
        ax.plot(r.t, r.x, color="tab:blue", lw=0.6, label="data")
        ax.plot(r.t, r.model_x, color="tab:red", lw=0.9, label=f"joint fit ({result.model})")
        ax.set_ylabel(f"run {j} [{unit}]")
        ax.set_title(f"{r.source or f'run {j}'}: rms {r.rms:.3g} {unit}", fontsize=8)
        ax.legend(fontsize=7, loc="upper right")
        axr.plot(r.t, r.residuals, color="tab:blue", lw=0.5)
        axr.axhline(0.0, color="k", lw=0.6)
        axr.set_ylabel(f"resid. [{unit}]", fontsize=8)
        axr.set_xlabel("t [s]", fontsize=8)
    terms = ", ".join(f"{k} = {result.values[k]:.4g}" for k in result.shared)
    fig.suptitle(title or f"joint fit, shared {terms}", fontsize=9,
                 y=1.0 - 0.06 / fig.get_figheight(), va="top")
    save_figure(fig, path, dpi=dpi)
    fig.clear()
    return Path(path)
