"""Figures: x(t) and E(t) of several models, error-map heat maps, sensitivities.

This module only draws: what it draws was computed elsewhere (``_summary.run_models``,
``error_map``, ``sensitivity``). Lines follow the model registry's styles (the papers' colour
code); figures use matplotlib's object API on the Agg canvas (no display, no pyplot state).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from ._io import save_figure
from ._models._registry import MODELS
from ._oscillator import Oscillator, as_float
from ._plot_fit import _place
from ._studies._sensitivity import _SYMBOLS, UNITS, Sensitivity
from ._studies._summary import ModelRun, damping_ratios


def _legend_rows(n_labels: int, ncols: int = 4) -> int:
    """Rows of a figure legend of ``n_labels`` entries in ``ncols`` columns."""
    return max(1, math.ceil(n_labels / ncols))


def _title_in(title: str | None, fontsize: float = 11.0) -> float:
    """Height [in] of a figure title of that many lines (0 without one), with its padding."""
    if not title:
        return 0.0
    return 0.1 + (title.count("\n") + 1) * 1.25 * fontsize / 72.0


def _finish(fig, handles, labels, path, *, title, dpi):
    """Legend below the panels, optional title, the file written whole; returns ``path``."""
    fig.legend(handles, labels, loc="lower center", bbox_to_anchor=(0.5, 0.0),
               ncols=min(len(labels), 4), fontsize=9, frameon=False)
    if title:
        fig.suptitle(title, fontsize=11, y=1.0 - 0.06 / fig.get_figheight(), va="top")
    save_figure(fig, path, dpi=dpi)
    fig.clear()
    return path


def _grid(osc: Oscillator, t_end: float, n_points: int | None) -> np.ndarray:
    if n_points is None:
        periods = t_end * as_float(osc.omega0) / (2.0 * math.pi)
        n_points = int(min(max(2000, 500 * math.ceil(120 * periods / 500)), 200_000))
    return np.linspace(0.0, t_end, n_points)


def plot_results(run: ModelRun, path, *, n_points: int | None = None, dpi: int = 120):
    """Draw x(t) and E(t) of already-solved models side by side and save the figure.

    Colours follow the papers: matched ansatz solid red, undamped-phase ansatz solid blue,
    reference black dotted; the other models get their own colours and dash patterns. With
    friction (mu > 0) the sticking band +-xc is drawn as dashed horizontal lines.

    Arguments:
        run: the output of :func:`run_models`.
        path: output file (the format follows the suffix, e.g. ``.png``).
        n_points: samples of the time grid; default ~120 per undamped period, >= 2000.
        dpi: resolution of raster output.

    Returns:
        ``path``, unchanged.
    """
    from matplotlib.figure import Figure  # Agg canvas; no pyplot, no display needed

    osc, x0, v0 = run.osc, run.x0, run.v0
    t = _grid(osc, run.t_end, n_points)
    curves = run.curves(t)

    fig = Figure(figsize=(12.0, 4.8))
    ax_x, ax_e = fig.subplots(1, 2)
    _place(fig, ncols=2, left=0.85, right=0.2, bottom=0.55, top=1.0, wspace=0.85)
    for k in MODELS:
        if k not in curves:
            continue
        style = MODELS[k].style
        ax_x.plot(t, curves[k][0], **style)
        ax_e.plot(t, curves[k][1], **style)
    xc = as_float(osc.xc)
    if xc > 0.0:
        for sign in (1.0, -1.0):
            ax_x.axhline(sign * xc, color="0.35", linestyle="--", linewidth=0.9, zorder=1.0,
                         label=r"$\pm x_c$" if sign > 0 else None)
    ax_x.axhline(0.0, color="0.8", linewidth=0.6, zorder=0.5)
    ax_x.set(xlabel="t [s]", ylabel="x [m]", title="displacement x(t)", xlim=(0, run.t_end))
    ax_e.set(xlabel="t [s]", ylabel="E [J]", title="energy E(t) = k x²/2 + m v²/2",
             xlim=(0, run.t_end))
    ax_e.set_ylim(bottom=0.0)
    for ax in (ax_x, ax_e):
        ax.grid(True, alpha=0.3)
    # the energy decays from the upper left: its upper right corner is free for the legend
    handles, labels = ax_x.get_legend_handles_labels()
    ax_e.legend(handles, labels, loc="upper right", fontsize=8, framealpha=0.9)
    r0, r1, r2 = damping_ratios(osc, x0, v0)
    fig.suptitle(
        rf"$d_0/(\omega_0 A_0)$ = {r0:.4g},   $d_1/\omega_0$ = {r1:.4g},   "
        rf"$d_2 A_0/\omega_0$ = {r2:.4g}" "\n"
        rf"m = {as_float(osc.m):g} kg, k = {as_float(osc.k):g} N/m, $\mu$ = {as_float(osc.mu):g}, "
        rf"b = {as_float(osc.b):g} kg/s, D = {as_float(osc.D):g} kg/m, "
        rf"$x_0$ = {x0:g} m, $v_0$ = {v0:g} m/s", fontsize=11, y=1.0 - 0.06 / 4.8, va="top")
    save_figure(fig, path, dpi=dpi)
    fig.clear()
    return path


# ----------------------------------------------------------------------------------------------
# error maps (dampax.error_map): heat maps of d0 ratio against d2 ratio


#: How each metric of an error map is drawn: title, colour-bar label, log scale, contours.
ERROR_MAP_METRICS: dict[str, dict] = {
    "max_error": dict(title=r"max $|x - x_\mathrm{ref}|\,/\,A_0$", label="max error [A0]",
                      log=True, contours=(0.01, 0.05)),
    "rms_error": dict(title=r"rms of $(x - x_\mathrm{ref})\,/\,A_0$", label="rms error [A0]",
                      log=True, contours=(0.01, 0.05)),
    "energy_error": dict(title=r"max $|E - E_\mathrm{ref}|\,/\,E_0$", label="energy error [E0]",
                         log=True, contours=(0.01, 0.05)),
    "halt_time_error": dict(title=r"|halt time $-$ reference's| in undamped periods",
                            label="|halt time error| [periods]", log=False, contours=()),
    "halt_position_error": dict(title=r"|halt position $-$ reference's| in units of $x_c$",
                                label=r"|halt position error| [$x_c$]", log=False,
                                contours=()),
}

# contour line colours (each with a black outline), by level
_CONTOUR_STYLES = (("white", "1 %"), ("red", "5 %"))


def _edges(values: np.ndarray) -> np.ndarray:
    """Cell edges around sorted grid values (half-way between neighbours), never below 0.

    The ratios are >= 0: the cell of a 0 value starts at 0 (half width) instead of showing
    negative ratios on the axis.
    """
    v = np.asarray(values, dtype=float)
    if v.size == 1:
        half = 0.05 * (abs(v[0]) if v[0] != 0 else 1.0)
        edges = np.array([v[0] - half, v[0] + half])
    else:
        mid = 0.5 * (v[1:] + v[:-1])
        edges = np.concatenate([[v[0] - (mid[0] - v[0])], mid, [v[-1] + (v[-1] - mid[-1])]])
    if v[0] >= 0.0:
        edges[0] = max(edges[0], 0.0)
    return edges


def _in_pi(value: float) -> str:
    """An angle as a multiple of pi when it is one (to 1e-9), e.g. "7π/8"; else decimals."""
    from fractions import Fraction

    frac = Fraction(value / math.pi).limit_denominator(64)
    if abs(float(frac) * math.pi - value) > 1e-9:
        return f"{value:.3g}"
    if frac == 0:
        return "0"
    num = {1: "", -1: "-"}.get(frac.numerator, str(frac.numerator))
    return f"{num}π" + (f"/{frac.denominator}" if frac.denominator != 1 else "")


def _phi0_text(phi0: np.ndarray) -> str:
    if phi0.size == 1:
        return rf"$\varphi_0$ = {_in_pi(phi0[0])}"
    return (rf"worst case over {phi0.size} initial phases $\varphi_0$ from "
            rf"{_in_pi(phi0.min())} to {_in_pi(phi0.max())}")


def plot_error_map(ds, metric: str, path, *, dpi: int = 110):
    """Heat maps of one metric of an error map: d0 ratio (y) against d2 ratio (x), per model.

    Each panel is one model (rows: the d1 ratios of the map); the colour is the worst case
    (largest magnitude) over phi0. Error metrics use a shared logarithmic colour scale with
    contour lines at 1 % and 5 %; halt errors a linear one. Grey cells: the model does not
    exist there (e.g. Rizcallah's model with d2 > 0) or, for halt errors, the reference does
    not halt within the window. The paper's stated ranges are outlined for orientation.

    Arguments:
        ds: the ``xarray.Dataset`` of :func:`dampax.error_map`.
        metric: one of :data:`ERROR_MAP_METRICS`.
        path: output file, e.g. ``"max_error.png"``.
        dpi: resolution.

    Returns:
        ``path``, unchanged.
    """
    from matplotlib import colormaps, colors, patheffects
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Rectangle

    if metric not in ERROR_MAP_METRICS:
        raise ValueError(f"metric must be one of {list(ERROR_MAP_METRICS)}, got {metric!r}")
    spec = ERROR_MAP_METRICS[metric]
    models = [str(m) for m in np.asarray(ds["model"])]
    d0 = np.asarray(ds["d0_ratio"], dtype=float)
    d1 = np.asarray(ds["d1_ratio"], dtype=float)
    d2 = np.asarray(ds["d2_ratio"], dtype=float)
    phi0 = np.asarray(ds["phi0"], dtype=float)
    # worst case over phi0; NaN as soon as one phi0 is NaN would hide too much: skip NaN
    values = np.abs(np.asarray(ds[metric].transpose("model", "d1_ratio", "d0_ratio",
                                                    "d2_ratio", "phi0"), dtype=float))
    with np.errstate(invalid="ignore"):
        all_nan = np.all(np.isnan(values), axis=-1)
        worst = np.where(all_nan, np.nan, np.nanmax(np.where(np.isnan(values), -np.inf,
                                                             values), axis=-1))
    finite = worst[np.isfinite(worst)]
    if spec["log"]:
        top = float(finite.max()) if finite.size and finite.max() > 0 else 1.0
        vmax = 10.0 ** math.ceil(math.log10(max(top, 1e-3)))
        vmin = max(vmax * 1e-3, 1e-6)
        norm = colors.LogNorm(vmin=vmin, vmax=vmax, clip=True)
        shown = np.where(np.isfinite(worst), np.clip(worst, vmin, vmax), np.nan)
    else:
        vmax = float(finite.max()) if finite.size and finite.max() > 0 else 1.0
        norm = colors.Normalize(vmin=0.0, vmax=vmax)
        shown = worst

    n_rows, n_cols = d1.size, len(models)
    fig = Figure(figsize=(3.6 * n_cols + 1.4, 3.3 * n_rows + 1.5))
    axes = np.atleast_2d(fig.subplots(n_rows, n_cols, squeeze=False, sharex=True,
                                      sharey=True))
    title_in = 0.42 if n_rows > 1 else 0.25  # the panels' titles: one or two lines
    _place(fig, nrows=n_rows, ncols=n_cols, left=0.75, right=1.25, bottom=0.95,
           top=0.6 + title_in, wspace=0.15, hspace=title_in + 0.15)
    cmap = colormaps["viridis"].with_extremes(bad=(0.0, 0.0, 0.0, 0.0))
    xe, ye = _edges(d2), _edges(d0)
    mesh = None
    for r in range(n_rows):
        for c, model in enumerate(models):
            ax = axes[r, c]
            ax.set_facecolor("0.82")
            z = shown[c, r]
            mesh = ax.pcolormesh(xe, ye, np.ma.masked_invalid(z), cmap=cmap, norm=norm,
                                 shading="flat")
            if spec["contours"] and d0.size > 1 and d2.size > 1:
                zc = worst[c, r]
                lo, hi = np.nanmin(zc, initial=np.inf), np.nanmax(zc, initial=-np.inf)
                levels = [lv for lv in spec["contours"] if lo < lv < hi]
                if levels:
                    styles = [_CONTOUR_STYLES[spec["contours"].index(lv)] for lv in levels]
                    cs = ax.contour(d2, d0, np.ma.masked_invalid(zc), levels=levels,
                                    colors=[st[0] for st in styles], linewidths=1.8)
                    cs.set(path_effects=[patheffects.withStroke(linewidth=3.2,
                                                                foreground="black")])
                    fmt = {lv: (f"{100 * lv:g} %" if spec["log"] else f"{lv:g}")
                           for lv in levels}
                    labels = ax.clabel(cs, fmt=fmt, fontsize=8, inline=True)
                    for text in labels:
                        text.set_color("white")
                        text.set_fontweight("bold")
                        text.set_path_effects([patheffects.withStroke(linewidth=2.2,
                                                                      foreground="black")])
            # the paper's combined range (Sec. V): d0 <= 0.03, d2 <= 0.25
            ax.add_patch(Rectangle((0.0, 0.0), 0.25, 0.03, fill=False, edgecolor="black",
                                   linestyle="--", linewidth=1.0, zorder=3))
            title = MODELS[model].label if model in MODELS else model
            if n_rows > 1:
                title += f"\n$d_1/\\omega_0$ = {d1[r]:.3g}"
            ax.set_title(title, fontsize=9.5)
            ax.set_xlim(xe[0], xe[-1])
            ax.set_ylim(ye[0], ye[-1])
            if r == n_rows - 1:
                ax.set_xlabel(r"$d_2 A_0/\omega_0$ (quadratic)")
            if c == 0:
                ax.set_ylabel(r"$d_0/(\omega_0 A_0)$ (Coulomb)")
    # log scale: values below the bottom (e.g. an exact model) are drawn in its colour; the
    # triangle at the foot of the bar says so
    width, height = fig.get_size_inches()
    grid = fig.subplotpars
    cax = fig.add_axes((grid.right + 0.15 / width, grid.bottom, 0.14 / width,
                        grid.top - grid.bottom))
    bar = fig.colorbar(mesh, cax=cax, extend="min" if spec["log"] else "neither")
    bar.set_label(spec["label"] + (" (log scale)"
                                   if spec["log"] else ""))
    handles = [Patch(facecolor="0.82", edgecolor="0.5",
                     label="not defined here" if spec["log"]
                     else "not defined / the reference does not halt"),
               Line2D([], [], color="black", linestyle="--",
                      label=r"paper's combined range, $d_0 \leq 0.03$, $d_2 \leq 0.25$")]
    for level, (color, _) in zip(spec["contours"], _CONTOUR_STYLES, strict=False):
        text = f"{100 * level:g} %" if spec["log"] else f"{level:g}"
        handles.append(Line2D([], [], color=color, linewidth=1.8, label=f"{text} contour",
                              path_effects=[patheffects.withStroke(linewidth=3.2,
                                                                   foreground="black")]))
    fig.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, 0.0),
               ncol=len(handles), fontsize=8.5, frameon=False)
    ref = ds.attrs.get("reference", "?")
    ref_text = (f"DOP853 reference (rtol {ds.attrs.get('reference_rtol', 0):g})"
                if ref == "reference" else "exact half-swings")
    fig.suptitle(f"{spec['title']},  {_phi0_text(phi0)}\n"
                 f"against the {ref_text}, up to its halt or at most "
                 f"{float(ds.attrs.get('periods', math.nan)):g} undamped periods", fontsize=11,
                 y=1.0 - 0.08 / height, va="top")
    save_figure(fig, path, dpi=dpi)
    fig.clear()
    return path


# ----------------------------------------------------------------------------------------------
# sensitivities (dampax.sensitivity): d x(t)/d theta per parameter


_EXTRA_COLORS = ("tab:cyan", "tab:olive", "tab:pink", "tab:brown", "tab:gray")


def _style(key: str, n_other: int) -> dict:
    """Line style of a model: the registry's (the papers' colours) for its names."""
    if key in MODELS:
        return MODELS[key].style
    return dict(color=_EXTRA_COLORS[n_other % len(_EXTRA_COLORS)],
                linestyle=("-", "--", "-.")[n_other % 3], linewidth=1.5, zorder=2.0, label=key)


def axis_label(name: str) -> str:
    """y-axis label of d x/d name with its unit, e.g. 'dx/dD [m per kg/m]'."""
    unit = UNITS[name]
    sym = _SYMBOLS[name]
    per = f"m per {unit}" if unit else "m"
    return rf"$\partial x / \partial {sym}$  [{per}]"


def plot_sensitivity(results: Mapping[str, Sensitivity], path, *, title: str | None = None,
                     dpi: int = 120):
    """Plot d x(t)/d theta of several models, one panel per parameter, and save the figure.

    Arguments:
        results: model name -> unbatched :class:`Sensitivity` over a 1-d grid ``ts``. The keys
            of the model registry (``dampax._models._registry.MODELS``) are drawn in the papers'
            colours (matched ansatz solid
            red, reference black dotted, ...); any other key gets its own colour and is its
            own legend label. The panels are the union of the results' ``wrt``, in order.
        path: output file; the format follows the suffix (e.g. ``.png``).
        title: figure title (default: none).
        dpi: resolution of raster output.

    Returns:
        ``path``, unchanged.

    Each panel marks the halt time of each model that halts by a thin vertical line in the
    model's colour (x has a kink there: the derivative jumps to 0, or to the rest position's).
    """
    from matplotlib.figure import Figure  # Agg canvas; no pyplot, no display needed

    if not results:
        raise ValueError("results: nothing to plot")
    for key, r in results.items():
        if not isinstance(r, Sensitivity) or np.ndim(r.ts) != 1 or np.ndim(r.dhalt_time) != 1:
            raise ValueError(f"results[{key!r}]: need an unbatched Sensitivity over a 1-d ts")
    names: list[str] = []
    for r in results.values():
        names += [n for n in r.wrt if n not in names]
    n = len(names)
    ncols = 1 if n <= 3 else 2
    nrows = math.ceil(n / ncols)
    fig = Figure(figsize=(7.0 * ncols + 2.0 * (ncols == 1), 2.5 * nrows + 1.2))
    axes = np.atleast_1d(fig.subplots(nrows, ncols, sharex=True, squeeze=False)).ravel()
    n_labels = len(results) + 1  # the models and "halt time"
    _place(fig, nrows=nrows, ncols=ncols, left=1.0, right=0.25,
           bottom=0.6 + 0.22 * _legend_rows(n_labels), top=0.35 + _title_in(title),
           wspace=1.0, hspace=0.4 + (0.45 if n % ncols else 0.0))
    styles, n_other = {}, 0
    for key in results:
        styles[key] = _style(key, n_other)
        n_other += styles[key]["label"] == key
    t_max = max(float(np.max(np.asarray(r.ts))) for r in results.values())
    for ax, name in zip(axes[:n], names, strict=True):
        for key, r in results.items():
            if name not in r.wrt:
                continue
            st = styles[key]
            ax.plot(np.asarray(r.ts), np.asarray(r.of(name)["x"]), **st)
            tau = float(np.asarray(r.halt_time))
            if math.isfinite(tau) and tau <= t_max:
                ax.axvline(tau, color=st["color"], linestyle="--", linewidth=0.8, alpha=0.6,
                           zorder=1.0)
        ax.axhline(0.0, color="0.8", linewidth=0.6, zorder=0.5)
        ax.set_ylabel(axis_label(name))
        ax.set_title(rf"sensitivity to ${_SYMBOLS[name]}$", fontsize=10)
        ax.grid(True, alpha=0.3)
        ax.set_xlim(0.0, t_max)
    for ax in axes[n:]:
        ax.set_visible(False)
    for ax in axes[max(n - ncols, 0):n]:
        ax.set_xlabel("t [s]")
        ax.xaxis.set_tick_params(labelbottom=True)
    handles, labels = axes[0].get_legend_handles_labels()
    if any(math.isfinite(float(np.asarray(r.halt_time))) for r in results.values()):
        from matplotlib.lines import Line2D

        handles.append(Line2D([], [], color="0.4", linestyle="--", linewidth=0.8))
        labels.append("halt time")
    return _finish(fig, handles, labels, path, title=title, dpi=dpi)


def plot_trend(results: Mapping[str, Sensitivity], path, *, title: str | None = None,
               dpi: int = 120):
    """Plot the halt time and position over each parameter's trend window, and save the figure.

    One row per parameter of ``wrt``, two panels (halt time, halt position): the sweep of
    :func:`dampax.sensitivity` (dots joined by thin lines, so a jump between two values shows
    as a step), the local derivative as a dashed tangent at the nominal value and the trend (the
    least-squares slope) as a solid line through the sweep's mean.

    Arguments:
        results: model name -> unbatched :class:`Sensitivity` computed with ``trend=True``;
            registry keys are drawn in the papers' colours.
        path: output file; the format follows the suffix.
        title: figure title (default: none).
        dpi: resolution of raster output.

    Returns:
        ``path``, unchanged.
    """
    from matplotlib.figure import Figure

    if not results:
        raise ValueError("results: nothing to plot")
    for key, r in results.items():
        if not isinstance(r, Sensitivity) or np.ndim(r.dhalt_time) != 1:
            raise ValueError(f"results[{key!r}]: need an unbatched Sensitivity")
    names: list[str] = []
    for r in results.values():
        names += [n for n in r.wrt if n not in names]
    fig = Figure(figsize=(10.0, 2.6 * len(names) + 1.2))
    axes = fig.subplots(len(names), 2, squeeze=False)
    _place(fig, nrows=len(names), ncols=2, left=0.9, right=0.2,
           bottom=0.6 + 0.22 * _legend_rows(len(results) + 2), top=0.15 + _title_in(title),
           wspace=0.9, hspace=0.6)
    styles, n_other = {}, 0
    for key in results:
        styles[key] = _style(key, n_other)
        n_other += styles[key]["label"] == key
    quantities = (("halt_time", "halt time [s]", "s"), ("halt_position", "halt position [m]", "m"))
    for row, name in enumerate(names):
        unit = UNITS[name]
        for col, (q, ylabel, _) in enumerate(quantities):
            ax = axes[row, col]
            for key, r in results.items():
                if name not in r.wrt:
                    continue
                i = r.index(name)
                st = dict(styles[key])
                label = st.pop("label")
                u = np.asarray(r.window_values)[i]
                y = np.asarray(getattr(r, f"window_{q}"))[i]
                centre = float(u[len(u) // 2])
                ax.plot(u, y, marker="o", markersize=2.5, linewidth=0.6, color=st["color"],
                        label=label, zorder=st["zorder"])
                local = float(np.asarray(getattr(r, f"d{q}"))[i])
                trend = float(np.asarray(getattr(r, f"d{q}_trend"))[i])
                y0 = float(np.asarray(getattr(r, q)))
                if math.isfinite(local) and math.isfinite(y0):
                    ax.plot(u, y0 + local * (u - centre), color=st["color"], linestyle="--",
                            linewidth=1.0, zorder=st["zorder"])
                if math.isfinite(trend) and np.all(np.isfinite(y)):
                    ax.plot(u, np.mean(y) + trend * (u - np.mean(u)), color=st["color"],
                            linestyle="-", linewidth=1.8, alpha=0.5, zorder=st["zorder"])
            ax.set_xlabel(rf"${_SYMBOLS[name]}$" + (f" [{unit}]" if unit else ""))
            ax.set_ylabel(ylabel)
            ax.grid(True, alpha=0.3)
    from matplotlib.lines import Line2D

    handles, labels = axes[0, 0].get_legend_handles_labels()
    handles += [Line2D([], [], color="0.3", linestyle="--", linewidth=1.0),
                Line2D([], [], color="0.3", linestyle="-", linewidth=1.8, alpha=0.5)]
    labels += ["local derivative (tangent)", "trend (least-squares slope)"]
    return _finish(fig, handles, labels, path, title=title, dpi=dpi)


def plot_global_sensitivity(results, path, *, title: str | None = None, dpi: int = 120):
    """Bar chart of Sobol' S1 and ST with their confidence half-widths, and save the figure.

    Arguments:
        results: an xarray Dataset of :func:`dampax.global_sensitivity`, or a mapping
            label -> Dataset (e.g. one per model; registry keys get the papers' colours): the
            datasets' parameters are grouped on the x axis, S1 solid, ST hatched, error bars the
            bootstrap half-widths.
        path: output file; the format follows the suffix.
        title: figure title (default: the quantity).
        dpi: resolution of raster output.

    Returns:
        ``path``, unchanged.
    """
    from matplotlib.figure import Figure

    if not isinstance(results, Mapping):
        results = {str(results.attrs.get("method", "model")): results}
    if not results:
        raise ValueError("results: nothing to plot")
    names: list[str] = []
    for ds in results.values():
        names += [str(n) for n in ds["parameter"].values if str(n) not in names]
    n_sets = len(results)
    width = 0.8 / (2 * n_sets)
    fig = Figure(figsize=(max(5.5, 1.6 + 1.4 * len(names) * n_sets), 4.2))
    ax = fig.subplots()
    _place(fig, left=0.8, right=0.2, bottom=0.45,
           top=0.2 + _title_in(title if title is not None else "two\nlines", 10.0))
    x = np.arange(len(names))
    n_other = 0
    for s, (key, ds) in enumerate(results.items()):
        st = _style(key, n_other)
        n_other += st["label"] == key
        idx = [names.index(str(nm)) for nm in ds["parameter"].values]
        for j, (var, hatch) in enumerate((("S1", None), ("ST", "//"))):
            pos = x[idx] - 0.4 + width * (2 * s + j + 0.5)
            ax.bar(pos, np.asarray(ds[var]), width, yerr=np.asarray(ds[f"{var}_conf"]),
                   color=st["color"], alpha=0.85 if j == 0 else 0.45, hatch=hatch,
                   edgecolor=st["color"], capsize=3,
                   label=f"{var}, {st['label']} (n = {ds.attrs.get('n', '?')})")
    ax.set_xticks(x, [rf"${_SYMBOLS[nm]}$" for nm in names])
    ax.axhline(0.0, color="0.5", linewidth=0.8)
    ax.set_ylabel("Sobol' index")
    ax.set_ylim(min(0.0, ax.get_ylim()[0]), max(1.0, ax.get_ylim()[1]))
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    first = next(iter(results.values()))
    ax.set_title(title if title is not None else
                 f"global sensitivity of {first.attrs.get('quantity', 'the quantity')}\n"
                 f"(S1 first order, ST total; "
                 f"{first.attrs.get('conf_level', 0.95):g} bootstrap bars)", fontsize=10)
    save_figure(fig, path, dpi=dpi)
    fig.clear()
    return path


def warm_figures() -> None:
    """Import matplotlib's Agg canvas and load its font list (0.3-0.4 s), for a command that
    draws later: run beside computing that leaves a core free (``dampax errormap``)."""
    from matplotlib import font_manager
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: F401
    from matplotlib.figure import Figure  # noqa: F401

    font_manager.findfont("DejaVu Sans")
