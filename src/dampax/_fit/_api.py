"""The public fitting functions: checks, windows, guesses and staging around the pure core.

:func:`fit` (traces), :func:`fit_envelope` (tables of maxima), :func:`compare_models` and
:func:`compare_envelope_models` (candidate damping models ranked by BIC), :func:`fit_arrays`
(the jit / vmap-able core on arrays), :func:`residual_function` (for other optimizers) and
:func:`example_trace` (docs/DESIGN.md, fitting).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._core import (
    FIT_MODELS,
    FIT_RESULTS,
    MAX_STEPS,
    MODELS,
    OPTIMIZERS,
    FitModel,
    ReferenceOptions,
    model_curve,
    run_core,
    swing_budget,
)
from ._guess import analyse, guess_envelope
from ._inputs import check_fitted_on, held_constants
from ._linalg import one_blas_thread
from ._options import Window, options
from ._params import (
    CANDIDATES,
    FREE,
    LOSSES,
    MAD,
    Constants,
    EnvelopeParams,
    TraceParams,
    as_arrays,
    as_params,
    check_choice,
    check_free,
    flat,
    oscillator_values,
    to_model,
    varied_names,
    vary_mask,
)
from ._pipeline import DEFAULT, FULL, run
from ._problem import (
    Settings,
    bucket,
    pad,
    prepare,
    quiet_windows,
    read_arrays,
    robust_scale,
    units_of,
)
from ._result import ArrayFit, FitContext, FitResult, ModelComparison, build_result, rank
from ._static import fit_mu_s
from ._stiffness import fit_k3


def _reference_options(model: FitModel, max_swings, rtol, atol, t, w0):
    """:class:`ReferenceOptions` for a model that integrates (else None).

    Arguments:
        model: the fit model.
        max_swings: half swings budget; default from the window t and w0 (concrete values).
        rtol, atol: integrator tolerances.
        t, w0: the window and the angular frequency of the start.
    """
    if not model.integrates:
        return None
    if max_swings is None:
        try:
            span = float(np.max(np.asarray(t)) - np.asarray(t)[0])
            max_swings = swing_budget(span, float(w0))
        except (TypeError, jax.errors.ConcretizationTypeError,
                jax.errors.TracerArrayConversionError) as err:
            raise ValueError(f"fit_arrays(model={model.name!r}) under jit/vmap needs "
                             "max_swings (static): the number of half swings in the window "
                             "plus a margin") from err
    return ReferenceOptions(int(max_swings), float(rtol), float(atol))


def _swings_bucket(max_swings, t, w0) -> int:
    """max_swings of a batch of starts: the user's, else the window's half swings (at 1.5
    times the start's w0, for the jittered ones) rounded up to a power of two, so that
    windows of similar length share the compiled batch."""
    if max_swings is not None:
        return int(max_swings)
    return swing_budget(float(np.max(np.asarray(t)) - np.asarray(t)[0]), float(w0), "starts")


# ----------------------------------------------------------------------------------------------
# fits


def _check_max_steps(max_steps):
    if max_steps is None:
        return None
    if isinstance(max_steps, bool) or int(max_steps) != max_steps or max_steps < 1:
        raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}")
    return int(max_steps)


@one_blas_thread
def fit(trace_or_t, x, settings: Settings) -> FitResult:
    """Fit one trace with the caller's checked settings (the implementation of
    :func:`dampax.fit` for a single trace; its docstring describes the fit).

    Arguments:
        trace_or_t: a :class:`Trace`, a file path, or the times t.
        x: the positions when ``trace_or_t`` holds the times (else None).
        settings: the problem and the options (:class:`~dampax._fit._problem.Settings`;
            ``window`` and ``solver`` were checked at the edge, ``_options``).

    Returns:
        A :class:`FitResult`: of :data:`~dampax._fit._pipeline.FULL`'s plan, or of the mu_s
        or k3 search (``_static.fit_mu_s``, ``_stiffness.fit_k3``) where one is free.
    """
    check_choice("model", settings.model, (*MODELS, "auto"))
    plan = FULL
    if settings.model == "auto":  # the exact model, answered by the ansatz where they agree
        plan = DEFAULT
        settings = settings._replace(model="reference")
    free = check_free(settings.free, allowed=FREE)
    k3, mu_s = held_constants(settings.oscillator, free, settings.k3, settings.mu_s)
    settings = settings._replace(k3=k3, mu_s=mu_s)
    if mu_s is not None or "mu_s" in free:
        if settings.model != "reference":
            raise ValueError(f"mu_s: static friction needs model='reference' (the "
                             f"{settings.model} model assumes mu_s = mu)")
        if "k3" in free:
            raise ValueError("mu_s: free=(..., 'mu_s') and (..., 'k3') together are not "
                             "supported: fix k3 (k3=...) or mu_s")
    if "mu_s" in free and mu_s is not None:
        raise ValueError("mu_s: give either free=(..., 'mu_s') or a fixed mu_s, not both")
    if "k3" in free and k3 is not None:
        raise ValueError("k3: give either free=(..., 'k3') or a fixed k3, not both")
    searched = next((name for name in ("mu_s", "k3") if name in free), None)
    problem = prepare(trace_or_t, x, settings._replace(
        free=tuple(f for f in free if f != searched)))
    if searched == "mu_s":
        return fit_mu_s(problem)
    if searched == "k3":
        return fit_k3(problem)
    res = run(problem, plan)
    if problem.consts.k3 is not None:  # a held k3 is reported as the fixed constant it is
        k3 = float(problem.consts.k3)
        res = dataclasses.replace(res, params={**res.params, "k3": k3},
                                  fixed={**res.fixed, "k3": k3})
    return res


def spacing_omega0(t, extremes) -> float:
    """w0 from the times of a table of extremes: 2 pi / their median spacing for maxima of one
    sign (one a period), pi / it where the signs alternate (turning points, two a period)."""
    t, extremes = np.asarray(t, dtype=float), np.asarray(extremes, dtype=float)
    order = np.argsort(t)
    t, extremes = t[order], extremes[order]
    turns = np.mean(np.sign(extremes[1:]) != np.sign(extremes[:-1])) > 0.5
    return (1.0 if turns else 2.0) * math.pi / float(np.median(np.diff(t)))


def fit_envelope(t_peaks, amplitudes=None, *, free=("mu", "D"), omega0=None, oscillator=None,
                 offset: bool = False, loss: str = "linear", optimizer: str = "lm",
                 max_steps: int | None = None, rtol: float = 1e-10,
                 atol: float = 1e-12, units: str | None = None) -> FitResult:
    """Fit the closed-form amplitude E(t) = A f(t - t_1) of the ansatz to successive maxima.

    f solves f' = -(a f^2 + b' f + c), f(0) = 1 with a = d2 A, b' = d1, c = d0 / A (eq. 20),
    so E' = -(d0 + d1 E + d2 E^2): the envelope decay of eq. 3 with Coulomb, viscous and
    quadratic damping.

    Arguments:
        t_peaks, amplitudes: times and values of the maxima (absolute values are used); or
            a :class:`Trace` (or a path) holding them, with ``amplitudes`` left out.
        free: damping constants to fit ("mu", "b", "D").
        omega0: angular frequency [rad/s] used to convert (d0, d2) to (mu, D) (eq. 21);
            default the oscillator's sqrt(k/m), else from the median spacing of t_peaks:
            2 pi / spacing for maxima of one sign (one per period), pi / spacing for
            extremes whose signs alternate (turning points, two per period).
        oscillator: m, k and g (default m = 1 kg, g = 9.81, omega0 from the spacing);
            non-free damping constants stay at its values.
        offset: also fit a constant added to the envelope (a zero offset of the angle).
        loss, optimizer, max_steps, rtol, atol: as in :func:`fit`.
        units: the unit of the amplitudes (as in :func:`fit`).

    Returns:
        A :class:`FitResult` with params mu, b, D, A (amplitude at t_1), offset; per unit
        mass (b/m, D/m) without an oscillator.
    """
    max_steps = _check_max_steps(max_steps)
    check_choice("loss", loss, LOSSES)
    check_choice("optimizer", optimizer, OPTIMIZERS)
    units = Window(units=units).checked().units
    free = check_free(free)
    if held_constants(oscillator, (), None, None) != (None, None):
        raise ValueError("oscillator: an envelope fit is of eq. 3 with a linear spring and "
                         "mu_s = mu; fit the trace (dp.fit) to hold its k3 or mu_s")
    osc = oscillator_values(oscillator)
    n_params = 1 + len(free) + bool(offset)  # A, the free constants, the offset
    t, E, source = read_arrays(t_peaks, amplitudes, least=n_params + 1,
                               what=f"an envelope fit of {n_params} parameters needs",
                               noun="maxima")
    if omega0 is None and oscillator is not None:  # (k was not used: the spacing was)
        omega0 = osc["w0"]
    elif omega0 is None:
        omega0 = spacing_omega0(t, E)
    E = np.abs(E)
    omega0 = float(omega0)
    if not (math.isfinite(omega0) and omega0 > 0):
        raise ValueError(f"omega0 must be > 0, got {omega0}")
    guess = guess_envelope(t, E, free, osc, omega0)
    vary = vary_mask(EnvelopeParams, free, offset=offset)
    consts = Constants(m=osc["m"], g=osc["g"], w0=omega0)
    n = len(t)
    tp, xp, wt = pad(t, E, bucket(n, 256))
    steps = int(max_steps or MAX_STEPS[optimizer])

    def run(p_start, fs):
        return run_core(tp, xp, wt, p_start, vary, consts, fs, model="envelope",
                        optimizer=optimizer, max_steps=steps, rtol=float(rtol),
                        atol=float(atol), opts=None)

    fs = math.inf
    out = run(guess, fs)
    stages = ""
    if loss == "soft_l1":
        fs = robust_scale(E - np.asarray(out.curve)[:n]) or 1.0
        stages = f"soft_l1 started from the linear-loss fit, f_scale = {fs:.4g}"
        out = run(out.params, fs)
    init = {name: getattr(guess, name) for name in varied_names(vary)}
    return build_result(out, FitContext(
        model="envelope", free=free, vary=vary, consts=consts, t=t, x=E, loss=loss,
        optimizer=optimizer, f_scale=fs, init=init, source=source, stages=stages,
        per_mass=oscillator is None, units=units_of(t_peaks, units)))


def fit_arrays(t, x, p0, *, free=("mu", "D"), fit_omega0: bool = False, offset: bool = True,
               m=1.0, g=9.81, model: str = "ansatz", loss: str = "linear", f_scale=None,
               optimizer: str = "lm", weights=None, max_steps: int | None = None,
               rtol: float = 1e-8, atol: float = 1e-10, max_swings: int | None = None,
               ref_rtol: float = 1e-8, ref_atol: float = 1e-10) -> ArrayFit:
    """Pure, jit/vmap-able core of :func:`fit`: one fit of x(t) from the start p0.

    No data checks, no automatic start or guesses: t[0] is the fit start (t0 of x0, v0).

    Arguments:
        t, x: 1-d arrays of equal length (the fit window); may be traced / batched by vmap.
        p0: initial (and, for the parameters that do not vary, fixed) values: a vector in the
            layout ``PARAMS`` = (mu, b, D, w0, offset, x0, v0), a dict by name or a
            ``TraceParams``. A free damping constant at 0 starts from a small positive value.
        free, fit_omega0, offset: which parameters vary (static); x0, v0 always vary.
        m, g: mass (default 1 kg: b and D per unit mass) and gravitational acceleration
            (fixed).
        model: "ansatz" or "reference".
        loss: "linear" or "soft_l1"; ``f_scale`` (data units) defaults to 1.4826 MAD of the
            residuals at p0.
        optimizer: "lm" (optimistix Levenberg-Marquardt), "adam" or "lbfgs" (optax).
        weights: optional per-sample weights 1/sigma (0 drops a sample).
        max_steps, rtol, atol: optimizer budget and tolerances (internal coordinates).
        max_swings, ref_rtol, ref_atol: reference model only (static).

    Returns:
        An :class:`ArrayFit` (params, stderr, success, n_iterations, chisqr, covariance), the
        vectors in the layout ``PARAMS``.
    """
    check_choice("model", model, MODELS)
    check_choice("loss", loss, LOSSES)
    check_choice("optimizer", optimizer, OPTIMIZERS)
    spec = FIT_MODELS[model]
    vary = vary_mask(TraceParams, free, fit_omega0=fit_omega0, offset=offset)
    t = jnp.asarray(t, dtype=float)
    x = jnp.asarray(x, dtype=float)
    p0 = as_arrays(as_params(p0, TraceParams))
    wt = jnp.ones_like(x) if weights is None else jnp.asarray(weights, dtype=float)
    consts = as_arrays(Constants(m=m, g=g))
    opts = _reference_options(spec, max_swings, ref_rtol, ref_atol, t, p0.w0)
    if loss == "linear":
        fs = jnp.inf
    elif f_scale is None:
        st = spec.setup(p0, t, consts, spec)
        q = to_model(jax.tree_util.tree_map(jnp.zeros_like, st.ref), st, as_arrays(vary, bool))
        r0 = model_curve(spec, t, q, st, opts) - x
        fs = MAD * jnp.median(jnp.abs(r0 - jnp.median(r0)))
    else:
        fs = f_scale
    out = run_core(t, x, wt, p0, vary, consts, fs, model=model, optimizer=optimizer,
                   max_steps=int(max_steps or MAX_STEPS[optimizer]), rtol=float(rtol),
                   atol=float(atol), opts=opts)
    return ArrayFit(flat(out.params), flat(out.stderr), out.code == FIT_RESULTS.successful,
                    out.steps, out.chisqr, out.covariance, out.jac, out.resid)


def residual_function(t, x, *, free=("mu", "D"), oscillator=None, fit_omega0: bool | None = None,
                      offset: bool = True, model: str = "ansatz",
                      max_swings: int | None = None):
    """The residuals model(t; p) - x that :func:`fit` minimises, in physical parameters.

    For checks against other optimizers (e.g. ``scipy.optimize.least_squares``): the same
    model, window (t[0] is the start of x0, v0) and fixed constants as :func:`fit` with
    ``start="data"``.

    Arguments:
        t, x: the fit window.
        free, oscillator, fit_omega0, offset, model: as in :func:`fit`.
        max_swings: reference model budget (default from the window).

    Returns:
        (fun, jac, names): ``fun(p)`` and ``jac(p)`` take the varied parameters ``names`` (in
        the order of PARAMS, physical units) as a numpy vector and return numpy arrays
        (jitted; forward-mode Jacobian).
    """
    check_choice("model", model, MODELS)
    spec = FIT_MODELS[model]
    if fit_omega0 is None:
        fit_omega0 = oscillator is None
    if oscillator is None and not fit_omega0:
        raise ValueError("fit_omega0=False needs an oscillator (m and k)")
    vary = vary_mask(TraceParams, free, fit_omega0=fit_omega0, offset=offset)
    osc = oscillator_values(oscillator)
    names = varied_names(vary)
    base = TraceParams(mu=osc["mu"], b=osc["b"], D=osc["D"], w0=osc["w0"], offset=0.0,
                       x0=0.0, v0=0.0)
    t = jnp.asarray(t, dtype=float)
    x = jnp.asarray(x, dtype=float)
    k3, mu_s = held_constants(oscillator, free, None, None)
    if mu_s is not None and not spec.integrates:
        raise ValueError(f"oscillator.mu_s: static friction needs model='reference' (the "
                         f"{model} model assumes mu_s = mu)")
    consts = as_arrays(Constants(m=osc["m"], g=osc["g"], k3=k3, mu_s=mu_s))
    span = jnp.max(t) - t[0]
    if spec.integrates and max_swings is None:
        omega = analyse(np.asarray(t), np.asarray(x)).omega if fit_omega0 else osc["w0"]
        max_swings = swing_budget(float(span), omega)
    opts = _reference_options(spec, max_swings, 1e-10, 1e-12, t, base.w0)

    def residuals(p):
        full = as_arrays(base._replace(**{name: p[i] for i, name in enumerate(names)}))
        q = spec.to_coords(full, consts)
        return spec.curve(t - t[0], q, consts, span, opts) - x

    fun = jax.jit(residuals)
    jac = jax.jit(jax.jacfwd(residuals))
    return (lambda p: np.asarray(fun(jnp.asarray(p, dtype=float))),
            lambda p: np.asarray(jac(jnp.asarray(p, dtype=float))), names)


# ----------------------------------------------------------------------------------------------
# model comparison


def compare_models(trace=None, x=None, *, candidates=CANDIDATES, criterion: str = "bic",
                   envelope=None, fitted=None, **fit_kwargs) -> ModelComparison:
    """Fit every candidate set of damping terms and rank them by BIC (or AIC).

    Arguments:
        trace: a Trace, a path or the times (then ``x``); or None with ``envelope``.
        x: the positions when ``trace`` holds the times.
        candidates: tuples of free damping terms.
        criterion: "bic" (default) or "aic".
        envelope: (t_peaks, amplitudes) to compare envelope models instead
            (:func:`compare_envelope_models`).
        fitted: optional {candidate tuple: FitResult} of fits already made of this trace with
            these ``fit_kwargs`` (e.g. ``dampax fit``'s own fit): used as they are instead of
            fitting those candidates again (traces only).
        **fit_kwargs: the keywords of :func:`dampax.fit` (``window=``, ``solver=``
            included), passed on (or to :func:`fit_envelope`).

    Returns:
        A :class:`ModelComparison` (``.best``, ``.table``, ``.report()``); a candidate that
        these data cannot fit (its fit raises a ValueError) is left out and named in
        ``.skipped`` with the reason (all refused: the first refusal is raised).
    """
    if envelope is not None:
        if trace is not None:
            raise ValueError("pass either a trace or envelope=(t_peaks, amplitudes)")
        return compare_envelope_models(*envelope, candidates=candidates, criterion=criterion,
                                       **fit_kwargs)
    if trace is None:
        raise ValueError("compare_models needs a trace (or envelope=(t_peaks, amplitudes))")
    if "free" in fit_kwargs:
        raise ValueError("compare_models sets free itself; pass candidates=")
    if "window" in fit_kwargs or "solver" in fit_kwargs:  # dp.fit's option objects
        fit_kwargs.update(options(fit_kwargs.pop("window", None),
                                  fit_kwargs.pop("solver", None)))
    known = {tuple(check_free(k)): r for k, r in (fitted or {}).items()}
    if known:  # (they were ranked whatever data came with them)
        with quiet_windows():
            t_all, x_all, _ = read_arrays(trace, x)
        for r in known.values():
            check_fitted_on(r, t_all, x_all, "fitted")
    with quiet_windows():  # (thread-local: a ranking may run beside the fit, dampax fit)
        return _ranked(candidates, criterion, lambda cand: known[cand] if cand in known else
                       fit(trace, x, Settings(**{**fit_kwargs, "free": cand})))


def _ranked(candidates, criterion: str, fit_one) -> ModelComparison:
    """:func:`rank` of ``fit_one(free)`` over the candidates. A candidate whose fit refuses
    these data (a ValueError: more parameters than an envelope has maxima, constants that are
    not separately identifiable) is left out with its reason (``ModelComparison.skipped``);
    where every candidate is refused, the first refusal is raised (the data or the options
    fit no model)."""
    results, skipped, first = {}, {}, None
    for cand in candidates:
        key = tuple(check_free(cand))
        try:
            results[key] = fit_one(key)
        except ValueError as err:
            skipped[key] = str(err)
            first = first or err
    if not results and first is not None:
        raise first
    return rank(results, criterion, skipped)


def compare_envelope_models(t_peaks, amplitudes=None, *, candidates=CANDIDATES,
                            criterion: str = "bic", **kwargs) -> ModelComparison:
    """:func:`compare_models` for a table of maxima (:func:`fit_envelope` per candidate).

    Arguments:
        t_peaks, amplitudes: as in :func:`fit_envelope`.
        candidates, criterion: as in :func:`compare_models`.
        **kwargs: passed to :func:`fit_envelope`.

    Returns:
        A :class:`ModelComparison`.
    """
    if "free" in kwargs:
        raise ValueError("compare_envelope_models sets free itself; pass candidates=")
    return _ranked(candidates, criterion,
                   lambda cand: fit_envelope(t_peaks, amplitudes, free=cand, **kwargs))


# ----------------------------------------------------------------------------------------------
# synthetic example
