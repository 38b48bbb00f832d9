"""Solve every applicable model once and plot x(t) and E(t) in the papers' colour code.

The models of one oscillator and initial state are solved and summarised by compiled code
(:func:`run_models`), so the command-line tool and the plots share one evaluation; the
figure is drawn with matplotlib's object API on the Agg canvas (no display, no pyplot state).
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections.abc import Callable, Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._oscillator import Oscillator, check_finite, damping_coefficients
from ._solve import solve, turning_points


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """One model of :func:`dampax.solve`: options, when it applies, and how it is drawn."""

    label: str
    options: tuple[tuple[str, object], ...]
    applies: Callable[[Oscillator], bool]
    color: str
    linestyle: str | tuple
    linewidth: float = 1.4
    zorder: float = 2.0


def _scalar(x) -> float:
    return float(np.asarray(x))


def _has_friction(osc: Oscillator) -> bool:
    return _scalar(osc.mu) > 0.0


def _coulomb_only(osc: Oscillator) -> bool:
    return _has_friction(osc) and _scalar(osc.b) == 0.0 and _scalar(osc.D) == 0.0


def _exact_applies(osc: Oscillator) -> bool:
    return (_has_friction(osc) and _scalar(osc.D) == 0.0
            and _scalar(osc.gamma) < _scalar(osc.omega0))


#: The models in table and legend order. ``reference`` is the diffrax integrator of eq. 3.
MODELS: dict[str, ModelSpec] = {
    "matched": ModelSpec("matched ansatz (eqs. 22-23)", (("method", "ansatz"),),
                         lambda osc: True, "tab:red", "-", 2.0, 3.0),
    "undamped": ModelSpec("undamped-phase ansatz (eqs. 8-10)",
                          (("method", "ansatz"), ("phase", "undamped")),
                          lambda osc: True, "tab:blue", "-", 1.6, 2.5),
    "tail": ModelSpec("matched + Coulomb tail (eq. 41)",
                      (("method", "ansatz"), ("tail", "coulomb")),
                      _has_friction, "tab:green", "-.", 1.6, 2.8),
    "rizcallah": ModelSpec("Rizcallah, sinusoidal friction", (("method", "rizcallah"),),
                           _coulomb_only, "tab:orange", (0, (5, 2)), 1.4, 2.2),
    "coulomb_exact": ModelSpec("exact half-swings (D = 0)", (("method", "coulomb_exact"),),
                               _exact_applies, "tab:purple", (0, (8, 3, 2, 3)), 1.4, 2.1),
    "reference": ModelSpec("reference (diffrax)", (("method", "reference"),),
                           lambda osc: True, "black", ":", 2.0, 4.0),
}


@dataclasses.dataclass
class ModelResult:
    """Solution and summary of one model; ``error`` says why it is missing (then no solution)."""

    name: str
    solution: object | None
    halt_time: float = math.nan
    halt_position: float = math.nan
    turning_t: np.ndarray | None = None
    turning_x: np.ndarray | None = None
    error: str | None = None

    @property
    def label(self) -> str:
        return MODELS[self.name].label


@dataclasses.dataclass
class ModelRun:
    """Everything :func:`run_models` computed for one oscillator and initial state."""

    osc: Oscillator
    x0: float
    v0: float
    results: dict[str, ModelResult]
    t_end: float
    notes: list[str]

    def ok(self) -> dict[str, ModelResult]:
        """The models that could be solved, in table order."""
        return {k: r for k, r in self.results.items() if r.error is None}


def applicable_models(osc: Oscillator, *, reference: bool = True) -> tuple[str, ...]:
    """Names of the models that apply to this oscillator, in table order.

    Arguments:
        osc: a scalar :class:`~dampax.Oscillator`.
        reference: include the reference integrator.

    Returns:
        A tuple of keys of :data:`MODELS`: both ansatz phases always; the Coulomb tail when
        mu > 0; Rizcallah's model when mu > 0 and b = D = 0; the exact half-swings when mu > 0,
        D = 0 and b < 2 sqrt(k m); the reference when asked for.
    """
    names = tuple(k for k, spec in MODELS.items() if k != "reference" and spec.applies(osc))
    return names + (("reference",) if reference else ())


# One compiled program per model (name and n_turning are static), reused for every oscillator
# and initial state: a second call with other numbers costs no compilation.


@eqx.filter_jit
def _solve_one(osc, x0, v0, name: str, n_turning: int):
    sol = solve(osc, x0, v0, **dict(MODELS[name].options))
    return sol, _summarize(sol, n_turning)


@eqx.filter_jit
def _summarize(sol, n_turning: int):
    return sol.halt_time, sol.halt_position, sol.valid, turning_points(sol, n_turning)


@eqx.filter_jit
def _curves(sol, t):
    return sol.x(t), sol.energy(t)


def _why_invalid(osc, x0, v0, name: str) -> str:
    """dampax's own reason for an invalid model, from an eager solve."""
    try:
        solve(osc, x0, v0, **dict(MODELS[name].options))
    except ValueError as err:
        return str(err)
    return "the model could not be evaluated for these parameters"


def default_t_end(osc: Oscillator, halt_times: Sequence[float]) -> float:
    """Time span of a plot: half an undamped period past the latest finite halt time.

    Arguments:
        osc: the oscillator (its undamped period T0 = 2 pi / w0 sets the margin).
        halt_times: halt times [s] of the models; inf / nan entries are ignored.

    Returns:
        t_end [s]: latest finite halt + T0/2, at most 100 T0; 6 T0 when nothing halts.
    """
    period = 2.0 * math.pi / _scalar(osc.omega0)
    finite = [t for t in halt_times if math.isfinite(t)]
    if not finite:
        return 6.0 * period
    return min(max(finite) + 0.5 * period, 100.0 * period)


def run_models(osc: Oscillator, x0: float, v0: float, *, models: Sequence[str] | None = None,
               n_turning: int = 6, t_end: float | None = None) -> ModelRun:
    """Solve and summarise several models of one oscillator with compiled code.

    The analytic models are solved under ``jax.jit``, one compiled program per model that is
    reused for other numbers (much faster than eager evaluation); a model that comes out
    invalid is solved again eagerly to report dampax's reason. The reference integrator
    (``dampax._reference``) is imported lazily and skipped, with a note, when it is missing or
    not implemented yet.

    Arguments:
        osc: a scalar :class:`~dampax.Oscillator`.
        x0, v0: initial displacement [m] and velocity [m/s].
        models: keys of :data:`MODELS`; default :func:`applicable_models`.
        n_turning: how many turning points to compute per model.
        t_end: time span [s] (reference integration, plots); default :func:`default_t_end`.

    Returns:
        A :class:`ModelRun`; ``results[name].error`` holds the reason a model is missing.
    """
    if np.ndim(osc.m) or any(np.ndim(v) for v in (osc.k, osc.mu, osc.b, osc.D, osc.g)):
        raise ValueError("osc: plots and summaries need a scalar Oscillator, not a batch")
    check_finite("x0", x0)
    check_finite("v0", v0)
    x0, v0 = float(x0), float(v0)
    if n_turning < 0:
        raise ValueError(f"n_turning must be >= 0, got {n_turning}")
    if t_end is not None and not (math.isfinite(t_end) and t_end > 0.0):
        raise ValueError(f"t_end must be a finite time > 0, got {t_end}")
    names = applicable_models(osc) if models is None else tuple(models)
    unknown = [k for k in names if k not in MODELS]
    if unknown:
        raise ValueError(f"models: unknown {unknown}; choose from {list(MODELS)}")
    analytic = tuple(k for k in names if k != "reference")
    notes: list[str] = []
    results: dict[str, ModelResult] = {}
    for k in analytic:
        sol, (tau, x_h, valid, (tt, tx)) = _solve_one(osc, jnp.asarray(x0), jnp.asarray(v0),
                                                      k, n_turning)
        if bool(valid):
            results[k] = ModelResult(k, sol, _scalar(tau), _scalar(x_h),
                                     np.asarray(tt), np.asarray(tx))
        else:
            results[k] = ModelResult(k, None, error=_why_invalid(osc, x0, v0, k))
    if t_end is None:
        t_end = default_t_end(osc, [r.halt_time for r in results.values() if r.error is None])
    if "reference" in names:
        results["reference"] = _run_reference(osc, x0, v0, t_end, n_turning, notes)
    results = {k: results[k] for k in MODELS if k in results}
    return ModelRun(osc, x0, v0, results, float(t_end), notes)


def _run_reference(osc, x0, v0, t_end, n_turning, notes) -> ModelResult:
    try:
        import dampax._reference  # noqa: F401  (written separately; may not exist yet)

        sol = solve(osc, x0, v0, method="reference", t_end=t_end)
    except (ImportError, NotImplementedError) as err:
        why = f"{type(err).__name__}: {err}"
        notes.append(f"reference integrator not available, skipped ({why})")
        return ModelResult("reference", None, error="not available")
    except (ValueError, RuntimeError) as err:  # e.g. its step budget ran out before t_end
        notes.append(f"reference integrator failed, skipped: {err}")
        return ModelResult("reference", None, error=str(err))
    tau, x_h, _, (tt, tx) = _summarize(sol, n_turning)
    return ModelResult("reference", sol, _scalar(tau), _scalar(x_h), np.asarray(tt),
                       np.asarray(tx))


def damping_ratios(osc: Oscillator, x0: float, v0: float) -> tuple[float, float, float]:
    """The dimensionless ratios d0/(w0 A0), d1/w0, d2 A0/w0 (DESIGN section 1).

    Arguments:
        osc: a scalar oscillator.
        x0, v0: initial state; A0 = sqrt(x0^2 + (v0/w0)^2).

    Returns:
        (d0/(w0 A0), d1/w0, d2 A0/w0); the first is inf (nan without friction) when A0 = 0.
    """
    w0 = _scalar(osc.omega0)
    d0, d1, d2 = (_scalar(d) for d in damping_coefficients(osc))
    A0 = math.hypot(x0, v0 / w0)
    r0 = d0 / (w0 * A0) if A0 > 0 else (math.inf if d0 > 0 else math.nan)
    return r0, d1 / w0, d2 * A0 / w0


def _grid(osc: Oscillator, t_end: float, n_points: int | None) -> np.ndarray:
    if n_points is None:
        periods = t_end * _scalar(osc.omega0) / (2.0 * math.pi)
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
    curves = {k: tuple(map(np.asarray, _curves(r.solution, jnp.asarray(t))))
              for k, r in run.ok().items()}

    fig = Figure(figsize=(12.0, 4.8), layout="constrained")
    ax_x, ax_e = fig.subplots(1, 2)
    for k in MODELS:
        if k not in curves:
            continue
        spec = MODELS[k]
        style = dict(color=spec.color, linestyle=spec.linestyle, linewidth=spec.linewidth,
                     zorder=spec.zorder, label=spec.label)
        ax_x.plot(t, curves[k][0], **style)
        ax_e.plot(t, curves[k][1], **style)
    xc = _scalar(osc.xc)
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
        rf"m = {_scalar(osc.m):g} kg, k = {_scalar(osc.k):g} N/m, $\mu$ = {_scalar(osc.mu):g}, "
        rf"b = {_scalar(osc.b):g} kg/s, D = {_scalar(osc.D):g} kg/m, "
        rf"$x_0$ = {x0:g} m, $v_0$ = {v0:g} m/s", fontsize=11)
    fig.savefig(path, dpi=dpi)
    fig.clear()
    return path


def plot_solutions(osc: Oscillator, x0: float, v0: float, path, *, t_end: float | None = None,
                   models: Sequence[str] | None = None, n_points: int | None = None):
    """Solve the applicable models and save a two-panel plot of x(t) and E(t).

    Models that cannot be solved (or the reference integrator, while it is missing) are left
    out with a note on stderr.

    Arguments:
        osc: a scalar :class:`~dampax.Oscillator`.
        x0, v0: initial displacement [m] and velocity [m/s].
        path: output file, e.g. ``"fig.png"``.
        t_end: time span [s]; default :func:`default_t_end` (a bit past the latest halt).
        models: keys of :data:`MODELS` to draw; default :func:`applicable_models`.
        n_points: samples of the time grid (default ~120 per undamped period).

    Returns:
        ``path``, unchanged.
    """
    run = run_models(osc, x0, v0, models=models, n_turning=0, t_end=t_end)
    for note in run.notes:
        print(f"dampax: note: {note}", file=sys.stderr)
    for r in run.results.values():
        if r.error is not None and r.name != "reference":
            print(f"dampax: note: {r.label} left out: {r.error}", file=sys.stderr)
    return plot_results(run, path, n_points=n_points)


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

#: Panel titles of the error-map models.
ERROR_MAP_LABELS = {
    "matched": "matched ansatz (eqs. 22-23)",
    "undamped": "undamped-phase ansatz (eqs. 8-10)",
    "matched_tail": "matched + Coulomb tail (eqs. 41, 52)",
    "rizcallah": "Rizcallah (Coulomb only: d2 = d1 = 0)",
    "coulomb_exact": "exact half-swings (D = 0)",
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
    fig = Figure(figsize=(3.6 * n_cols + 1.4, 3.3 * n_rows + 1.5), layout="constrained")
    axes = np.atleast_2d(fig.subplots(n_rows, n_cols, squeeze=False, sharex=True,
                                      sharey=True))
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
            title = ERROR_MAP_LABELS.get(model, model)
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
    bar = fig.colorbar(mesh, ax=axes, shrink=0.9, pad=0.01,
                       extend="min" if spec["log"] else "neither")
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
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=8.5,
               frameon=False)
    ref = ds.attrs.get("reference", "?")
    ref_text = (f"diffrax reference (rtol {ds.attrs.get('reference_rtol', 0):g})"
                if ref == "reference" else "exact half-swings")
    fig.suptitle(f"{spec['title']},  {_phi0_text(phi0)}\n"
                 f"against the {ref_text}, up to its halt or at most "
                 f"{float(ds.attrs.get('periods', math.nan)):g} undamped periods", fontsize=11)
    fig.savefig(path, dpi=dpi)
    fig.clear()
    return path
