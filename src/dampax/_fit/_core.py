"""The solver of the fits: residuals, robust loss, optimisers, covariance.

Everything here works on arrays and named parameter pytrees (``_params``) and is jit / vmap
friendly; :func:`core` is the one compiled function of every fit (docs/DESIGN.md, fitting).
The fit models it fits (their curves and settings, :data:`FIT_MODELS`) are in ``_curves``.

Optimisers: Levenberg-Marquardt (default; optimistix's algorithm in one small loop, ``_lm``),
optax adam or L-BFGS on the same (robust) sum of squares. ``loss="soft_l1"``:
rho(z) = 2 (sqrt(1 + z) - 1) of z = (r / s)^2 as scipy, by residual reweighting
r -> r sqrt(rho(z) / z). Covariance: s2 (J^T J)^-1 with s2 = chi2 / (n - n_varys), carried
to the physical parameters by the delta method, computed as (J_p^T J_p)^-1 with J_p = J G^-1
(G the Jacobian of the map), which stays exact when a log-parameter tends to 0.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._cache import call_cached_tree, prepare_cached_tree
from .._models._solution import result_where
from .._oscillator import is_concrete
from ._curves import FIT_MODELS as FIT_MODELS
from ._curves import MODELS as MODELS
from ._curves import FitModel as FitModel
from ._curves import ReferenceOptions as ReferenceOptions
from ._curves import model_curve as model_curve
from ._curves import reference_solution as reference_solution
from ._curves import swing_budget as swing_budget
from ._linalg import tall_lstsq, tall_svd
from ._lm import LMSolution, levenberg_marquardt, optax_minimise, rows_and_jacobian
from ._params import (
    Damping,
    Setup,
    clamp,
    flat,
    host_array,
    log_bounds,
    on_damping,
    to_model,
    unflat,
)

OPTIMIZERS = ("lm", "adam", "lbfgs")
MAX_STEPS = {"lm": 256, "lbfgs": 1000, "adam": 4000}
METHOD_NAMES = {"lm": "Levenberg-Marquardt (optimistix's trust-region algorithm)",
                "adam": "adam (optax)", "lbfgs": "L-BFGS (optax)"}


class FIT_RESULTS(eqx.Enumeration):
    """Outcome of the optimizer of a fit (the report's first line)."""

    successful = "converged"
    max_steps_reached = "maximum number of steps reached"
    failed = "the optimizer failed (non-finite values or divergence)"


def is_code(code, item) -> bool:
    """Whether a fit's concrete result code is ``item`` of :class:`FIT_RESULTS`, read on the
    host (``code == item`` compiles an eager comparison the first time in each process)."""
    return int(np.asarray(code._value)) == int(np.asarray(item._value))


# ----------------------------------------------------------------------------------------------
# residuals


class ResidualArgs(NamedTuple):
    """What the residuals need besides theta (a pytree: traced under jit / vmap).

    Attributes:
        t, x: sample times and data (padded).
        weight: 1/sigma per sample; 0 drops a sample (padding).
        setup: reference point and scales of the internal coordinates.
        vary: the mask of varied parameters.
        f_scale: soft_l1 scale in data units (inf: linear loss).
    """

    t: jax.Array
    x: jax.Array
    weight: jax.Array
    setup: Setup
    vary: Any
    f_scale: jax.Array


def _robust(r, fs):
    """soft_l1 reweighting: r sqrt(rho(z)/z), z = (r/fs)^2, rho(z)/z = 2/(1 + sqrt(1 + z))."""
    z = (r / fs) ** 2
    return r * jnp.sqrt(2.0 / (1.0 + jnp.sqrt(1.0 + z)))


def _residual_rows(theta, args: ResidualArgs, model: FitModel, opts, clamped=True,
                   with_curve=False):
    """Normalised residuals (model - data)/sx of the data rows, robust-weighted, masked."""
    st = args.setup
    q = to_model(unflat(theta, model.coords), st, args.vary, clamped)
    curve = model_curve(model, args.t, q, st, opts)
    r = (curve - args.x) / st.sx * args.weight
    r = jnp.where(args.weight > 0.0, _robust(r, args.f_scale / st.sx), 0.0)
    return (r, curve) if with_curve else r


def _residual_fn(theta, args: ResidualArgs, model: FitModel, opts):
    """Data rows plus one pin row per parameter: theta_i for fixed ones (0 at the optimum)."""
    pins = jnp.where(flat(args.vary), 0.0, theta)
    return jnp.concatenate([_residual_rows(theta, args, model, opts), pins])


def _materialised(fn, args):
    """``fn(theta, args)`` whose derivative is an explicit Jacobian matrix (custom_jvp).

    Its JVP computes r and J = jacfwd(fn) together and returns J @ dtheta: a linear map whose
    transpose is J^T, so reverse mode (optax's gradients) works on a model that is only
    forward-differentiable (the reference integrator with ``adjoint="forward"``), and the
    model is traced and compiled once instead of once for the linearisation and again for its
    transpose. (Levenberg-Marquardt, ``_lm``, takes the Jacobian of the plain function.)
    """
    @jax.custom_jvp
    def residuals(theta):
        return fn(theta, args)

    @residuals.defjvp
    def residuals_jvp(primals, tangents):
        (theta,), (dtheta,) = primals, tangents
        r, J = rows_and_jacobian(lambda th: fn(th, args), theta)
        return r, J @ dtheta

    return lambda theta, args: residuals(theta)


def _clamp_flat(theta, args: ResidualArgs, model: FitModel):
    return flat(clamp(unflat(theta, model.coords), args.setup, args.vary))


# ----------------------------------------------------------------------------------------------
# optimisers


def _optax_fit(fn, theta0, args: ResidualArgs, options: CoreOptions):
    """(theta, code, steps) of optax's adam or L-BFGS on the (robust) sum of squares."""
    _, optimizer, max_steps, rtol, atol, _ = options

    def loss_fn(th):
        return 0.5 * jnp.sum(fn(th, args) ** 2)

    theta, steps, ok = optax_minimise(loss_fn, theta0, optimizer, max_steps, rtol, atol)
    return theta, result_where(ok, FIT_RESULTS.successful, FIT_RESULTS.max_steps_reached if
                               optimizer == "lbfgs" else FIT_RESULTS.failed), steps


def _lm_code(sol: LMSolution) -> FIT_RESULTS:
    """The :class:`FIT_RESULTS` member of a Levenberg-Marquardt solution."""
    return result_where(sol.converged, FIT_RESULTS.successful, result_where(
        sol.finite, FIT_RESULTS.max_steps_reached, FIT_RESULTS.failed))


def _lm_once(fn, theta0, args: ResidualArgs, model: FitModel, options: CoreOptions, budget,
             give_up=None, leave=False):
    """One round of :func:`_lm_rounds`: (theta, code, steps, (r, J) at the returned point);
    ``give_up`` a chi-square in data units (the residuals are in units of ``sx``)."""
    b = _log_coordinates(args, model)
    sol = levenberg_marquardt(lambda th: fn(th, args), theta0, rtol=options.rtol,
                              atol=options.atol, max_steps=int(options.max_steps),
                              budget=budget, give_up=None if give_up is None else
                              give_up / args.setup.sx ** 2,
                              leave=lambda y, newton: leave & _creeping(b, y, newton))
    return (_clamp_flat(sol.value, args, model), _lm_code(sol), sol.steps,
            (sol.residual, sol.jac))


class _LogBounds(NamedTuple):
    """The damping constants of a fit in log coordinates (flat, like theta): p = dref
    exp(theta) for ``is_log``, theta >= lo, ``vary`` the mask."""

    dref: Any
    lo: Any
    is_log: Any
    vary: Any


def _log_coordinates(args: ResidualArgs, model: FitModel) -> _LogBounds:
    dref, lo = log_bounds(args.setup, args.vary)
    return _LogBounds(flat(on_damping(model.coords, dref, 1.0)),
                      flat(on_damping(model.coords, lo, -jnp.inf)),
                      flat(on_damping(model.coords, Damping(True, True, True), False)),
                      flat(args.vary))


def _creeping(b: _LogBounds, theta, newton):
    """Whether the Gauss-Newton step -``newton`` (theta) sends a damping constant above lo + 1
    to p <= 0 (its log coordinate falls by 1 or more, linearised): a creep to its bound (the
    next round, or the caller where one round stops there, ``_pipeline``, starts it there)."""
    return jnp.any(b.is_log & b.vary & (theta > b.lo + 1.0) & (newton >= 1.0))


def _start(args: ResidualArgs, model: FitModel, at_bound):
    """theta0: p0 (a damping constant's floor where p0 is below it); ``at_bound``: a varied
    damping constant at 0 one unit above its lower bound (the floor stalls
    Levenberg-Marquardt's log-step: wide draw 2, ``_pipeline.from_the_bound``)."""
    b = _log_coordinates(args, model)
    low = at_bound & b.is_log & b.vary & (flat(args.setup.ref) <= 0.0)
    return jnp.where(low, b.lo + 1.0, 0.0).astype(args.setup.sx.dtype)


def _between_rounds(b: _LogBounds, theta, scale, r, J):
    """(theta, scale, redo) after a round of :func:`_lm_rounds`: (1) a Gauss-Newton step in
    the physical constants p (where the model is smooth through p = 0) places a constant
    that it sends to p <= 0 next to its lower bound; (2) the log coordinates rescaled so that
    their columns match the largest nuisance column (Marquardt's scaling). ``redo``: a
    constant moved or a scale changed 10x (a constant held at its bound by the step gains
    nothing from another scale: a round for it alone changed nothing, 28 steps on the
    example's (b, D) ansatz fit)."""
    p = b.dref * jnp.exp(theta)
    Jx = jnp.where(b.vary, jnp.where(b.is_log, J / p, J), 0.0)
    step = tall_lstsq(Jx, -r)  # (XLA's CPU lstsq of a tall J: 44 ms; _linalg)
    down = b.is_log & b.vary & (p + step <= 0.0)
    snap = down & (theta > b.lo + 1.0)
    theta = jnp.where(snap, b.lo + 1.0, theta)
    cn = jnp.sqrt(jnp.sum(J * J, axis=0))
    ref = jnp.max(jnp.where(b.vary & ~b.is_log, cn, 0.0))
    safe = jnp.where(cn > 0.0, cn, 1.0)
    new = jnp.where(b.is_log & b.vary & (cn > 0.0), jnp.clip(ref / safe, 1.0, 1e15), 1.0)
    ratio = new / scale
    rescaled = ((ratio > 10.0) | (ratio < 0.1)) & ~(down & ~snap)
    return theta, new, jnp.any(snap) | jnp.any(rescaled)


def _lm_rounds(fn, theta0, args: ResidualArgs, model: FitModel, options: CoreOptions,
               budget=None, give_up=None, leave=False):
    """optimistix Levenberg-Marquardt in ``model.lm_rounds`` restarts, for constants that go
    to 0.

    optimistix damps with lambda I (Levenberg), which is not scale-invariant: a log-parameter
    whose constant tends to 0 has a vanishing Jacobian column and creeps towards its bound by
    tiny steps. Between rounds a constant that a Gauss-Newton step sends below 0 is placed
    at its bound and the log coordinates are rescaled (:func:`_between_rounds`). A round
    other than the last ends where that step would move a constant
    (``_lm.levenberg_marquardt``'s ``leave``: 10 accepted points in a row, so that the
    unsettled steps of a far start do not place a constant; the example's (b, D) ansatz fit
    crept 51 steps towards D = 0 before). A round after a converged one
    with nothing changed is skipped. Returns (theta, code, steps, final) with final = (r, J)
    for one round. ``budget``: the steps of one round (traced, at most max_steps; None:
    max_steps); ``give_up``, ``leave``: :class:`Tuning`'s (one round only)."""
    _, _, max_steps, rtol, atol, opts = options
    # the step budget is honoured: never more rounds than steps, never more steps in all
    rounds = max(min(model.lm_rounds, int(max_steps)), 1)
    if rounds == 1:
        return _lm_once(fn, theta0, args, model, options, budget, give_up, leave)
    per_round = max(int(max_steps) // rounds, 1)
    b = _log_coordinates(args, model)

    def rows(th):
        return _residual_rows(th, args, model, opts, clamped=False)

    def solve(theta, scale, last):
        def leave(u, newton):  # (the step is -scale newton in theta)
            return _creeping(b, theta + scale * u, scale * newton) & ~last

        sol = levenberg_marquardt(lambda u: fn(theta + scale * u, args),
                                  jnp.zeros_like(theta), rtol=rtol, atol=atol,
                                  max_steps=per_round, leave=leave)
        return (_clamp_flat(theta + scale * sol.value, args, model), sol.steps,
                _lm_code(sol))

    def one(carry, index):
        theta, scale, steps, code, redo = carry
        again = (steps == 0) | (code != FIT_RESULTS.successful) | redo
        theta, n_steps, code = jax.lax.cond(again, solve, lambda th, sc, la: (th, 0, code),
                                            theta, scale, index == rounds - 1)
        r, J = rows_and_jacobian(rows, theta)
        theta, scale, redo = _between_rounds(b, theta, scale, r, J)
        return (theta, scale, steps + n_steps, code, redo), None

    init = (theta0, jnp.ones_like(theta0), jnp.array(0), FIT_RESULTS.successful,
            jnp.array(True))
    (theta, _, steps, code, _), _ = jax.lax.scan(one, init, jnp.arange(rounds))
    return theta, code, steps, None


# ----------------------------------------------------------------------------------------------
# one fit: optimise, then the statistics


class CoreResult(NamedTuple):
    """Output of :func:`core` (arrays; named parameters of the model's ``params`` type).

    Attributes:
        params: the fitted parameters (fixed ones at their p0 value).
        stderr: their standard errors (NaN for fixed ones).
        covariance: covariance of the parameters in the order of their fields (zero rows and
            columns for fixed ones).
        code: a :class:`FIT_RESULTS` member (converged, step budget exhausted, failed).
        steps: optimizer steps.
        chisqr: sum of squared (robust-weighted) residuals in data units.
        ndata, nvarys: samples with weight > 0, varied parameters.
        curve: the model at the (padded) data times.
        coords: the optimum in the model's coordinates.
        jac, resid: the Jacobian of the data rows in the physical parameters (n_pad x 7,
            zero columns for fixed ones) and the data rows (normalised, robust-weighted):
            for the intervals that allow for correlated residuals (``_intervals``).
    """

    params: Any
    stderr: Any
    covariance: jax.Array
    code: FIT_RESULTS
    steps: jax.Array
    chisqr: jax.Array
    ndata: jax.Array
    nvarys: jax.Array
    curve: jax.Array
    coords: Any
    jac: jax.Array = None
    resid: jax.Array = None


def _covariance(J, params_of, theta, vary, s2):
    """Covariance of the physical parameters: s2 (J_p^T J_p)^-1, J_p = J G^-1 with G the
    Jacobian of ``params_of`` (internal -> physical) at theta; (cov, stderr) over ``vary``."""
    L = theta.shape[0]
    G = jax.jacfwd(params_of)(theta)
    eye = jnp.eye(L, dtype=G.dtype)
    G = jnp.where(vary[:, None], G, eye)
    Jp = jnp.linalg.solve(G.T, J.T).T  # J G^-1
    norm2 = jnp.sum(Jp * Jp, axis=0)
    # a constant at its bound with a zero Jacobian column (reference model) gets no stderr
    active = vary & (norm2 > 0.0)
    pair = active[:, None] & active[None, :]
    d = jnp.sqrt(jnp.where(active, norm2, 1.0))
    # (J^T J)^-1 from the singular values of the column-scaled Jacobian, not by inverting
    # J^T J (cond(J)^2 ~ 1e16 where damping constants sit at 0, their columns equal to 1e-8:
    # the inverse's diagonal took its sign from the data's last bits; issue 34, a GPU's
    # rounding). 1/s^2 stays accurate down to s ~ eps s_max; fixed and inactive columns are
    # unit columns (C = 1 there, dropped by `pair` below).
    Jn = jnp.where(active[None, :], Jp / d[None, :], 0.0)
    A = jnp.concatenate([Jn, jnp.diag(jnp.where(active, 0.0, 1.0)).astype(Jn.dtype)])
    s, vt = tall_svd(A)  # (XLA's CPU SVD of a tall A: 44 ms; _linalg)
    w = vt / jnp.where(s > 0.0, s, jnp.nan)[:, None]  # V^T / s: C = w^T w
    C = (w.T @ w) / (d[:, None] * d[None, :])
    cov = jnp.where(pair, s2 * C, 0.0)
    var = jnp.diag(cov)
    stderr = jnp.where(active, jnp.sqrt(jnp.where(var >= 0.0, var, jnp.nan)), jnp.nan)
    return cov, stderr, jnp.where(vary[None, :], Jp, 0.0)


class CoreOptions(NamedTuple):
    """The static settings of :func:`core` (equal settings share one compiled program).

    Attributes:
        model: the name of an entry of :data:`FIT_MODELS`.
        optimizer: "lm", "adam" or "lbfgs".
        max_steps, rtol, atol: budget and tolerances (internal coordinates).
        opts: :class:`ReferenceOptions` for models that integrate, else None."""

    model: str
    optimizer: str
    max_steps: int
    rtol: float
    atol: float
    opts: ReferenceOptions | None = None


class Tuning(NamedTuple):
    """The traced settings of one fit (:func:`core`): the soft_l1 scale ``f_scale`` in data
    units (inf: the linear loss); for the models of one round (``FitModel.lm_rounds``) the
    step ``budget`` (at most ``CoreOptions.max_steps``; None: that), ``give_up``, a
    chi-square (data units) above which the fit stops after ``_lm.GIVE_UP_AFTER`` steps
    (None or inf: never), and ``leave``: stop where it creeps to a bound (:func:`_creeping`);
    ``at_bound``: a varied damping constant started at 0 starts at its lower bound (a
    continuation from a fit with it held at 0), not at its floor (its reference: its start)."""

    f_scale: Any
    budget: Any = None
    give_up: Any = None
    at_bound: Any = False
    leave: Any = False


@functools.partial(jax.jit, static_argnames=("options",))
def core(t, x, weight, p0, vary, consts, tuning: Tuning, *,
         options: CoreOptions) -> CoreResult:
    """One fit, pure: optimise, then the covariance by the delta method.

    Arguments:
        t, x, weight: samples (padded with weight 0); t[0] is the fit start.
        p0: the start (and the values of the fixed parameters), of the model's ``params`` type.
        vary: the mask, same type, booleans (traced: one compilation for every candidate).
        consts: :class:`~dampax._fit._params.Constants`.
        tuning: the soft_l1 scale and the step budget (:class:`Tuning`, traced).
        options: the model, the optimizer, its budget and tolerances, the integrator's
            options (:class:`CoreOptions`, static).

    Returns:
        A :class:`CoreResult`.
    """
    model, optimizer, max_steps, rtol, atol, opts = options
    f_scale, budget, give_up, at_bound, leave = tuning
    spec = FIT_MODELS[model]
    st = spec.setup(p0, t, consts, spec)
    args = ResidualArgs(t=t, x=x, weight=weight, setup=st, vary=vary, f_scale=f_scale)
    theta0 = _start(args, spec, at_bound)
    raw = functools.partial(_residual_fn, model=spec, opts=opts)
    fn = _materialised(raw, args)  # (reverse mode for optax: J built forward, transposed)
    final = None
    if optimizer == "lm":
        theta, code, steps, final = _lm_rounds(raw, theta0, args, spec, options, *(
            (budget, give_up, leave) if spec.lm_rounds == 1 else ()))
    else:
        theta, code, steps = _optax_fit(fn, theta0, args, options)

    theta = _clamp_flat(theta, args, spec)
    npad = t.shape[0]
    if spec.reuse_jacobian:
        # reuse the optimizer's last residuals and Jacobian (no further copy of the integrator
        # to compile); a constant at its lower bound has a zero column there and gets no
        # standard error
        if final is None:
            r, J = rows_and_jacobian(lambda th: fn(th, args), theta)
        else:
            r, J = final
        r, J = r[:npad], J[:npad]
        z = ((1.0 + 0.5 * (r * st.sx / f_scale) ** 2) ** 2 - 1.0)  # invert soft_l1 weighting
        r_plain = jnp.where(jnp.isfinite(f_scale), jnp.sign(r) * f_scale / st.sx * jnp.sqrt(z),
                            r)
        curve = x + r_plain * st.sx / jnp.where(weight > 0.0, weight, 1.0)
    else:
        # statistics at the (clamped) optimum, without the clamp so that a constant at its
        # lower bound keeps its (tiny) derivative and the delta method stays regular
        def rows(th):
            r, curve = _residual_rows(th, args, spec, opts, clamped=False, with_curve=True)
            return r, (r, curve)

        J, (r, curve) = jax.jacfwd(rows, has_aux=True)(theta)
    n = jnp.sum(weight > 0.0)
    vary_v = flat(vary)
    nvary = jnp.sum(vary_v)
    chi2_n = jnp.sum(r * r)
    s2 = chi2_n / jnp.maximum(n - nvary, 1)

    def params_of(th):
        return flat(spec.to_params(to_model(unflat(th, spec.coords), st, vary, False), consts))

    params = params_of(theta)
    cov, stderr, Jp = _covariance(J, params_of, theta, vary_v, s2)
    finite = jnp.all(jnp.isfinite(params)) & jnp.isfinite(chi2_n)
    code = result_where(finite, code, FIT_RESULTS.failed)
    return CoreResult(params=unflat(params, spec.params), stderr=unflat(stderr, spec.params),
                      covariance=cov, code=code, steps=steps, chisqr=chi2_n * st.sx ** 2,
                      ndata=n, nvarys=nvary, curve=curve,
                      coords=to_model(unflat(theta, spec.coords), st, vary), jac=Jp, resid=r)


def program_consts(consts, model: str):
    """``consts`` as the compiled fits of ``model`` take them: eq. 3 integrated with the linear
    spring (k3 None) is k3 = 0, so its programs are those of a held or profiled k3 (one
    compiled fit for both; the closed form's k3 has terms of its own)."""
    if FIT_MODELS[model].integrates and consts.k3 is None:
        return consts._replace(k3=consts.motion[2])
    return consts


def run_core(t, x, weight, p0, vary, consts, tuning, **static) -> CoreResult | None:
    """:func:`core` with every input as a (strongly typed) JAX array, so that every fit of
    the same shapes shares one compiled function. ``static``: the fields of
    :class:`CoreOptions` by name; ``tuning``: a :class:`Tuning` (the soft_l1 scale, the
    steps, traced, at most ``max_steps``, None: ``max_steps``, honoured by the models of one
    Levenberg-Marquardt round, and the chi-square above which the fit gives up after
    ``_lm.GIVE_UP_AFTER`` steps, None: never) or the soft_l1 scale alone.

    Called with concrete values (an eager fit), the compiled program is kept
    (``_cache.call_cached_tree``): a repeated fit, also in a new process, neither traces nor
    compiles it; under jit/vmap the plain traced route runs. ``prepare=True`` among
    ``static``: only start compiling that program in the background
    (``_cache.prepare_cached_tree``; returns None). ``quick=True``: the program is compiled
    by XLA's quickest route (``_cache.QUICK_PROGRAMS``), for a fit that only starts another
    model's (the same numbers to rounding; it runs about 3x longer, compiles 2 s sooner)."""
    prepare = static.pop("prepare", False)
    quick = static.pop("quick", False)
    f_scale, budget, give_up, at_bound, leave = tuning if isinstance(tuning, Tuning) else \
        Tuning(tuning)
    args = (t, x, weight, p0, vary, program_consts(consts, static["model"]), Tuning(
        f_scale, static["max_steps"] if budget is None else budget,
        jnp.inf if give_up is None else give_up, at_bound, leave))
    options = CoreOptions(**static)
    types = (float, float, float, float, bool, float, Tuning(float, int, float, bool, bool))
    concrete = is_concrete(args)
    to_array = host_array if concrete else jnp.asarray
    args = jax.tree_util.tree_map(
        lambda d, a: jax.tree_util.tree_map(lambda v: to_array(v, dtype=d), a), types, args)
    if concrete:
        call = prepare_cached_tree if prepare else call_cached_tree
        return call("fit-core-quick" if quick else "fit-core", sorted(static.items()),
                    functools.partial(core, options=options), *args)
    return core(*args, options=options)
