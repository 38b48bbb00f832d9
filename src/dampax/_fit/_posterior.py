"""A posterior of a trace fit by NUTS (blackjax), with AR(1) noise (issues 11 and 25).

Model: the fit model's curve (``_core.FIT_MODELS``): "ansatz", x(t) = offset + A f(t - t0)
cos(w0 (t - t0) + phi) (eqs. 11, 20-23) in its coordinates (mu, b, D, w0, offset, x0,
y = A sin(phi)), or "reference", eq. 3 integrated by DOP853 with exact stick-slip from
(x0, v0), plus AR(1) noise on the residuals r = x - model: r_1 ~ N(0, sigma^2 / (1 - phi_n^2)),
r_t - phi_n r_(t-1) ~ N(0, sigma^2) (the exact likelihood of a stationary AR(1)); sigma and
phi_n are sampled too.

Structure (so that other residuals, e.g. a joint fit of several traces, plug in): the log
density is built from a residual function ``residual(p, args) -> r`` of a physical parameter
vector ``p`` whose entries a :class:`Layout` names (and says which are sampled as logarithms),
plus the two noise parameters; :func:`sample` runs the mode search, the Laplace
preconditioning and NUTS for any such residual. :func:`posterior` builds the residual of one
trace (:class:`TraceResidual`) from a least-squares fit; ``_posterior_joint`` that of a joint
fit of several runs (``JointResidual``), with one AR(1) noise series per run.

Parameters sampled (unconstrained): log of every free damping constant, w0 (when fitted), the
offset (when fitted), the cubic stiffness k3 itself (when free: it has either sign), x0, y
(ansatz) or v0 (reference), log sigma and atanh phi_n. Weakly informative priors, documented
in :data:`PRIORS`: log c ~ N(log c_guess, 3) around the turning-point guess of the constant (a
factor 20 per sigma), w0 ~ N(w_turn, 0.05 w_turn) around the turning points' frequency,
offset ~ N(offset_fit, A), x0 and y ~ N(their least-squares values, 2 A) (v0: 2 A w0), log
sigma ~ N(log rms, 2), atanh phi_n ~ N(0, 2), k3 A^2/(m w0^2) ~ N(0, 0.5). The sampler runs on
u with theta = theta_map + L u, L the Cholesky factor of the Laplace covariance at the
posterior mode (found by L-BFGS from the least-squares fit), so the chains see a nearly
isotropic target. Warm-up: blackjax's window adaptation (step size by dual averaging towards an
acceptance rate of 0.8, a diagonal mass matrix from growing windows), each chain its own,
vmapped over the chains together with the sampling in one compiled program. The likelihood
uses every s-th sample of the window (at most :data:`MAX_SAMPLES`): with AR(1) noise the
information of neighbouring samples overlaps, and the thinned residuals follow an AR(1) with
coefficient phi^s.

Gradients: the ansatz is differentiated in reverse mode; the reference integrator in forward
mode (its plain ``lax`` loop, ``adjoint="forward"``): the log density's gradient is one
``jacfwd`` over the few parameters, wrapped as a custom JVP so that NUTS's ``value_and_grad``
goes through it (:data:`GRADIENTS`).

The result writes an ArviZ InferenceData file (``Posterior.to_netcdf``: groups posterior,
sample_stats, observed_data; ``_mcmc.write_inference_data``) and reports rank-normalised split
R-hat and bulk and tail ESS as ArviZ computes them (``_mcmc``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._core import FIT_MODELS, MODELS, ReferenceOptions, reference_solution, swing_budget
from ._entry import fit_flat
from ._inputs import check_fitted_on
from ._joint_result import JointResult
from ._linalg import one_blas_thread
from ._options import LeastSquares, Window, options
from ._params import (
    DAMPING,
    FREE,
    Constants,
    TraceCoords,
    ansatz_v0,
    check_choice,
    check_free,
)
from ._posterior_joint import _joint_groups, _joint_setup
from ._posterior_result import Posterior, narrow_text
from ._problem import quiet_windows, read_arrays
from ._sampler import (
    GRADIENTS,
    MAX_DOUBLINGS,
    MAX_SAMPLES,
    PRIORS,
    REFERENCE_ATOL,
    REFERENCE_RTOL,
    Chains,
    Draws,
    Layout,
    Prior,
    physical,
    sample,
)
from ._text import warn_user

# ----------------------------------------------------------------------------------------------
# one trace


class TraceArgs(NamedTuple):
    """The arrays of :class:`TraceResidual`: the (thinned) window, the fit's values of the
    parameters that are not sampled, the constants and the window's span."""

    t: jax.Array
    x: jax.Array
    base: TraceCoords
    consts: Constants
    span: jax.Array


@dataclass(frozen=True)
class TraceResidual:
    """Residuals x - model(t; p) of one trace for a fit model (static, hashable).

    Attributes:
        model: "ansatz" or "reference".
        names: the names of p: among mu, b, D, k3, w0, offset, then x0 and y (ansatz:
            A sin(phi)) or v0 (reference).
        opts: the reference integrator's budget and tolerances (None for the ansatz).
        adjoint: the reference integrator's adjoint ("forward" or "recursive").
    """

    model: str
    names: tuple
    opts: ReferenceOptions | None = None
    adjoint: str = "forward"

    def __call__(self, p, args: TraceArgs):
        vals = dict(zip(self.names, (p[i] for i in range(len(self.names))), strict=True))
        vals.setdefault("y", vals.get("v0"))
        q = TraceCoords(**{f: vals[f] if f in vals else getattr(args.base, f)
                           for f in TraceCoords._fields})
        consts = args.consts._replace(k3=vals["k3"]) if "k3" in vals else args.consts
        tau = args.t - args.t[0]
        if self.model == "reference":
            return args.x - _reference_curve(tau, q, consts, args.span, self.opts, self.adjoint)
        return args.x - FIT_MODELS[self.model].curve(tau, q, consts, args.span, self.opts)


def _reference_curve(tau, q: TraceCoords, consts: Constants, span, opts: ReferenceOptions,
                     adjoint: str):
    """``_core.reference_solution`` with a choice of adjoint; invalid solutions give NaN."""
    sol = reference_solution(q, consts, span, opts, adjoint)
    return jnp.where(sol.valid, q.offset + sol.x(tau), jnp.nan)



# ----------------------------------------------------------------------------------------------
# the public function


def _trace_setup(res, stride: int, vary_k3: bool):
    """(residual, args, layout, centre, width, theta0) of the trace fit ``res``."""
    model = res.model
    t = jnp.asarray(res.t[::stride])
    xd = jnp.asarray(res.x[::stride])
    span = float(res.t[-1] - res.t[0])
    m, g = float(res.fixed["m"]), float(res.fixed["g"])
    p = res.params
    free = tuple(c for c in res.free if c not in ("k3", "mu_s"))
    A = float(res.derived["A"])
    if model == "reference":
        x0_hat, y_hat, y_name, y_width = p["x0"], p["v0"], "v0", 2 * A * p["w0"]
    else:
        x0_hat = A * math.cos(res.derived["phi"])
        y_hat, y_name, y_width = A * math.sin(res.derived["phi"]), "y", 2 * A
    r = np.asarray(res.residuals)[::stride]
    phi_hat = float(np.clip(np.corrcoef(r[:-1], r[1:])[0, 1], -0.9, 0.995))
    sig_hat = float(np.std(r[1:] - phi_hat * r[:-1])) or 1e-12
    w_turn = p["w0"] / (1.0 + float(res.diagnostics.get("w0/turning - 1", 0.0)))
    names, log, centre, width, theta0 = [], [], [], [], []

    def add(name, is_log, c, w, start):
        names.append(name)
        log.append(is_log)
        centre.append(c)
        width.append(w)
        theta0.append(start)

    for c in free:
        guess = max(float(res.init.get(c, p[c])), 1e-30)
        add(c, True, math.log(guess), 3.0, math.log(max(p[c], guess * 1e-6)))
    if vary_k3:  # k3 A^2/(m w0^2) ~ N(0, 0.5), started at the profiled fit's k3
        add("k3", False, 0.0, 0.5 * m * p["w0"] ** 2 / A ** 2, p["k3"])
    if "w0" in res.varied:
        add("w0", False, w_turn, 0.05 * w_turn, p["w0"])
    if "offset" in res.varied:
        add("offset", False, p["offset"], A, p["offset"])
    add("x0", False, x0_hat, 2 * A, x0_hat)
    add(y_name, False, y_hat, y_width, y_hat)
    centre += [math.log(float(np.sqrt(np.mean(r * r))) or 1e-12), 0.0]
    width += [2.0, 2.0]
    theta0 += [math.log(sig_hat), math.atanh(phi_hat)]
    opts = None
    if model == "reference":
        opts = ReferenceOptions(swing_budget(span, p["w0"], "data"), REFERENCE_RTOL,
                                REFERENCE_ATOL)
    residual = TraceResidual(model=model, names=tuple(names), opts=opts)
    base = TraceCoords(**{f: jnp.asarray(float(p[f] if f in p else 0.0))
                          for f in TraceCoords._fields})
    mu_s = static_friction(res)
    consts = Constants(m=jnp.asarray(m), g=jnp.asarray(g),
                       mu_s=None if mu_s is None else jnp.asarray(mu_s))
    args = TraceArgs(t=t, x=xd, base=base, consts=consts, span=jnp.asarray(span))
    return residual, args, Layout(tuple(names), tuple(log)), centre, width, theta0


def static_friction(res) -> float | None:
    """The static friction mu_s a trace fit's motion has (None: mu_s = mu): held at its value
    (``fixed["mu_s"]``), or the value of ``fit(free=(..., "mu_s"))``. x(t) depends on mu_s only
    through which turning point is the halt (a step function, ``_static``), so the posterior
    does not sample it: it samples the other parameters at that mu_s, i.e. conditional on
    the fitted halt; the values of mu_s that give the same halt are the fit's interval."""
    if "mu_s" in res.free:
        return float(res.params["mu_s"])
    value = res.fixed.get("mu_s")
    return None if value is None else float(value)


def _trace_groups(out: Draws, layout: Layout, res, names_in: tuple, stride: int) -> tuple:
    """The posterior group and the observed data of a trace's posterior (xarray Datasets):
    the sampled parameters in physical units (v0 for y), the fixed ones as attributes.

    Arguments:
        out: the sampler's draws.
        layout: the sampled parameters' layout.
        res: the start fit.
        names_in: the free constants as given (the damping constants, k3, mu_s).
        stride: the likelihood's thinning.

    Returns:
        (draws, observed).
    """
    import xarray as xr

    model = res.model
    vary_k3 = "k3" in names_in
    free = tuple(c for c in names_in if c not in ("k3", "mu_s"))  # the damping constants
    # the posterior group: the sampled parameters in physical units, v0 for y
    nch, nd, dim = out.theta.shape
    flat = jnp.asarray(out.theta.reshape(-1, dim))
    P, sigma, phi_n = jax.vmap(lambda th: physical(th, layout))(flat)
    P = np.asarray(P)
    vals = {n: P[:, i] for i, n in enumerate(layout.names)}
    if model == "ansatz":
        full = {f: vals.get(f, float(res.params[f])) for f in ("mu", "b", "D", "w0")}
        vals["v0"] = np.asarray(ansatz_v0(vals["x0"], vals.pop("y"), full["mu"], full["b"],
                                          full["D"], full["w0"], float(res.fixed["m"]),
                                          float(res.fixed["g"])))
    vals["sigma"] = np.asarray(sigma)
    vals["phi_noise"] = np.asarray(phi_n)
    order = [*free, *(("k3",) if vary_k3 else ()),
             *(n for n in ("w0", "offset") if n in layout.names), "x0", "v0", "sigma",
             "phi_noise"]
    coords = {"chain": np.arange(nch), "draw": np.arange(nd)}
    sampled = set(order)
    fixed = {f"fixed_{n}": float(res.params[n]) for n in (*DAMPING, "w0", "offset")
             if n not in sampled}
    fixed.update(fixed_m=float(res.fixed["m"]), fixed_g=float(res.fixed["g"]))
    if static_friction(res) is not None:  # held (not sampled): see static_friction
        fixed["fixed_mu_s"] = static_friction(res)
        if "mu_s" in res.free:
            fixed["mu_s_interval"] = [float(v) for v in res.profiled["mu_s"]["interval"]]
    attrs = {"inference_library": "blackjax", "sampler": "NUTS, window adaptation",
             "model": f"{model} + AR(1) noise", "units": res.units,
             "per_mass": int(res.per_mass), "free": ",".join(names_in), "t_start": float(res.t[0]),
             "stride": stride, "priors": "; ".join(f"{k}: {v}" for k, v in PRIORS.items()),
             **fixed}
    draws = xr.Dataset({n: (("chain", "draw"), np.asarray(vals[n], dtype=float).reshape(nch, nd))
                        for n in order}, coords=coords, attrs=attrs)
    observed = xr.Dataset({"x": (("t",), np.asarray(res.x, dtype=float))},
                          coords={"t": np.asarray(res.t, dtype=float)},
                          attrs={"units": res.units, "source": str(res.source),
                                 "stride": stride})
    return draws, observed


class Request(NamedTuple):
    """A posterior call's model, sampler settings and progress (:func:`posterior`).

    Attributes:
        model: the fit model sampled.
        num_samples, num_chains, num_warmup, seed: as in :func:`posterior`.
        bar: the tqdm bar over the stages.
        began: ``time.perf_counter()`` at the call's start.
    """

    model: str
    num_samples: int
    num_chains: int
    num_warmup: int
    seed: int
    bar: Any
    began: float


def _joint_posterior(traces, req: Request, *, start_fit, shared, free, fit_kw) -> Posterior:
    """The posterior of a joint fit of several runs (:func:`posterior` with a list).

    Arguments:
        traces: the runs.
        req: the model, the sampler's settings and the progress.
        start_fit, shared, free: as in :func:`posterior` (free: the damping constants).
        fit_kw: the start fit's other settings (checked).

    Returns:
        A :class:`Posterior`.
    """
    model, bar, began = req.model, req.bar, req.began
    num_samples, num_chains, num_warmup, seed = (req.num_samples, req.num_chains,
                                                 req.num_warmup, req.seed)
    res = start_fit if start_fit is not None else fit_flat(
        list(traces), shared=shared, free=free, model=model, **fit_kw)
    bar.update()
    if not isinstance(res, JointResult) or res.model != model:
        raise ValueError(f"start_fit must be a {model!r} joint fit (a JointResult of dp.fit "
                         f"with the list of runs), got {type(res).__name__}"
                         + (f" of the {res.model!r} model" if hasattr(res, "model") else ""))
    if shared is not None and set(_names(shared)) != set(res.shared):
        raise ValueError(f"start_fit: its shared parameters {res.shared!r} are not "
                         f"shared={_names(shared)!r}")
    stride = max(1, math.ceil(max(r.ndata for r in res.runs) / MAX_SAMPLES))
    residual, args, layout, centre, width, theta0, mask = _joint_setup(res, stride)
    out = sample(residual, args, layout, Prior(centre, width), theta0, mode=GRADIENTS[model],
                 chains=Chains(num_samples, num_chains, num_warmup, seed), mask=mask)
    bar.update(2)
    bar.close()
    draws, observed = _joint_groups(out, layout, res, stride)
    return _finish(out, draws, observed, res, model, began, stride, free=tuple(res.free))


def _names(value) -> tuple:
    if isinstance(value, str):
        return tuple(s.strip() for s in value.split(",") if s.strip())
    return tuple(value)


#: a posterior sd below this fraction of the start fit's HAC sd is called too narrow. Where
#: the noise is AR(1) both estimate the same sd, up to the Monte Carlo error of the draws'
#: sd (ESS >= 100: under 10 %), the HAC estimate's own (10-20 % at the bandwidths of
#: _intervals) and the prior: 1.45 (mu) and 1.54 (D) on the white-noise trace of
#: tests/fit/test_posterior.py, so a right model lies far above it; residuals that AR(1)
#: cannot describe (structure at the oscillation frequency) made w0's 20x narrower (spring
#: run 1, issue 36). On a generated family whose noise the model describes (issue 36's
#: papers'-regime decays, white or AR(1) noise: benchmarks/posterior_narrow.py, 19 default
#: fits and posteriors) the ratio lay at 0.81-1.97 (mu) and 0.87-1.96 (D), median 1.00, and
#: no warning was given.
NARROW = 0.5


def narrow_parameters(draws, res) -> dict:
    """{name: posterior sd / the fit's HAC sd} of the sampled physical constants (the damping
    constants, w0, k3; not per run; x0, v0 and the offset are sampled in other coordinates) whose
    posterior is narrower than :data:`NARROW` times the fit's interval allows: the AR(1) noise
    model is too simple for the residuals, whose correlation the fit's intervals allow for
    (issue 36)."""
    fit_sd = res.hac_stderr
    out = {}
    for name in draws.data_vars:
        v = draws[name]
        sd = fit_sd.get(name, math.nan)
        if name not in (*DAMPING, "w0", "k3") or "run" in v.dims or not (
                math.isfinite(sd) and sd > 0):
            continue
        ratio = float(np.std(np.asarray(v.values, dtype=float), ddof=1)) / sd
        if ratio < NARROW:
            out[name] = ratio
    return out


def _finish(out: Draws, draws, observed, res, model, began, stride, *, free) -> Posterior:
    """The :class:`Posterior` of the draws (the sample_stats group built here; a warning when
    a parameter's posterior is too narrow for the residuals, :func:`narrow_parameters`)."""
    import xarray as xr

    st = out.stats
    narrow = narrow_parameters(draws, res)
    if narrow:
        warn_user(narrow_text(narrow))
    coords = {"chain": draws.coords["chain"].values, "draw": draws.coords["draw"].values}
    stats = xr.Dataset(
        {"lp": (("chain", "draw"), st["lp"].astype(float)),
         "diverging": (("chain", "draw"), st["diverging"].astype(bool)),
         "energy": (("chain", "draw"), st["energy"].astype(float)),
         "step_size": (("chain", "draw"), st["step_size"].astype(float)),
         "tree_depth": (("chain", "draw"), st["tree_depth"].astype(np.int64)),
         "acceptance_rate": (("chain", "draw"), st["acceptance_rate"].astype(float)),
         "n_steps": (("chain", "draw"), st["n_steps"].astype(np.int64))},
        coords=coords, attrs={"inference_library": "blackjax",
                              "max_tree_depth": MAX_DOUBLINGS,
                              "sampling_time": out.seconds_chains})
    return Posterior(draws=draws, free=free, fit=res, sample_stats=stats,
                     observed_data=observed, model=model, units=res.units,
                     per_mass=res.per_mass, accept_rate=float(np.mean(st["acceptance_rate"])),
                     divergences=int(np.sum(st["diverging"])),
                     step_size=float(np.mean(st["step_size"][:, 0])),
                     seconds=time.perf_counter() - began, seconds_chains=out.seconds_chains,
                     stride=stride, narrow=narrow)


@one_blas_thread
def posterior(trace_or_t, x=None, *, oscillator=None, free=("mu", "D"), model: str = "auto",
              fit_omega0: bool | None = None, offset: bool = True, start="auto", end=None,
              num_samples: int = 1000, num_chains: int = 4, num_warmup: int = 500,
              seed: int = 0, units: str | None = None, start_fit=None,
              progress: bool = False, shared=None, starts: int = 32,
              max_swings: int | None = None, mu_s: float | None = None) -> Posterior:
    """Sample the posterior of the free damping constants (and the nuisance parameters) with
    NUTS from blackjax, on log-parameters, with AR(1) noise (see the module doc for the model,
    the priors and the sampler).

    Arguments:
        trace_or_t, x, oscillator, free, fit_omega0, offset, start, end, units: as in
            :func:`~dampax.fit` (no oscillator: per unit mass, w0 sampled). ``free`` may
            include "k3" (the cubic stiffness, sampled on its own scale; the start fit then
            profiles it, as ``dp.fit(free=(..., "k3"))`` does). A list of two or more runs
            (as ``dp.fit`` takes it) samples the posterior of their joint fit: the
            parameters of ``shared`` common to all runs, each run's own x0, v0, offset (and
            w0 and constants not shared) and its own AR(1) noise (sigma, phi_noise); the
            padding of the shorter runs is not in the likelihood. In the posterior group the
            shared parameters have dims (chain, draw), the per-run ones (chain, draw, run);
            :meth:`Posterior.summary` names them ``x0[1]`` as ``JointResult.names`` does.
        shared, starts, max_swings: joint fits only, as in ``dp.fit`` (the start fit).
        mu_s: model "reference", one trace: the static friction coefficient held at this value
            (as ``dp.fit(mu_s=...)``). With ``free=(..., "mu_s")`` the start fit searches it
            (x(t) depends on mu_s only through which turning point is the halt, a step
            function no sampler can move); the posterior then samples the other parameters
            at the fitted mu_s, conditional on that halt, and records mu_s and the interval
            of values that give the same halt as the attributes ``fixed_mu_s`` and
            ``mu_s_interval``.
        model: "auto" (as ``dp.fit``'s: the model that answers the start fit is
            sampled, the exact one unless the ansatz provably agrees with it; a joint
            posterior samples the exact model), "ansatz" (closed form, eqs. 11, 20-23) or
            "reference" (eq. 3 integrated with exact stick-slip; slower, forward-mode
            gradients).
        num_samples, num_chains, num_warmup: draws per chain, chains, warm-up steps (blackjax
            window adaptation, per chain).
        seed: random seed.
        start_fit: a :class:`FitResult` (for a list of runs a ``JointResult``) of the same
            data, options and model to start from (default: ``fit(...)`` is run).
        progress: show a tqdm bar over the stages (start fit, mode, chains) on stderr.
        starts, max_swings: the start fit's global starts and the reference model's swing
            budget (as ``dp.LeastSquares``; checked here).

    Returns:
        A :class:`Posterior`.
    """
    from tqdm import tqdm

    check_choice("model", model, (*MODELS, "auto"))
    for name, value, low in (("num_samples", num_samples, 10), ("num_chains", num_chains, 1),
                             ("num_warmup", num_warmup, 10)):
        if isinstance(value, bool) or int(value) != value or value < low:
            raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    names_in = check_free(free, allowed=FREE)
    vary_k3 = "k3" in names_in
    free = tuple(c for c in names_in if c not in ("k3", "mu_s"))  # the damping constants
    if not free:
        raise ValueError("free: name at least one damping constant")
    # the start fit's window and settings, checked here (dp.fit's option objects)
    fit_kw = dict(oscillator=oscillator, fit_omega0=fit_omega0, offset=offset,
                  **options(Window(start=start, end=end, units=units),
                            LeastSquares(starts=starts, seed=seed, max_swings=max_swings)))
    began = time.perf_counter()
    bar = tqdm(total=3, desc="posterior", unit="stage", disable=not progress)
    if isinstance(trace_or_t, (list, tuple)) and x is None:
        if vary_k3:
            raise ValueError("free: a joint posterior samples k3 only as shared=(..., 'k3')")
        if mu_s is not None or "mu_s" in names_in:  # (it was dropped, mu_s = mu sampled)
            raise ValueError("mu_s: static friction is not supported by a joint posterior of "
                             "several runs; sample each run alone")
        req = Request("reference" if model == "auto" else model, num_samples, num_chains,
                      num_warmup, seed, bar, began)
        return _joint_posterior(trace_or_t, req, start_fit=start_fit, shared=shared, free=free,
                                fit_kw=fit_kw)
    if shared is not None:
        raise ValueError("shared: names constants common to several runs; it needs a list of "
                         "two or more traces, not a single trace")
    if start_fit is not None:  # (it was sampled whatever data came with it)
        with quiet_windows():
            check_fitted_on(start_fit, *read_arrays(trace_or_t, x)[:2], "start_fit")
    res = start_fit if start_fit is not None else fit_flat(
        trace_or_t, x, free=names_in, model=model, mu_s=mu_s,
        **fit_kw)
    bar.update()
    model = res.model if model == "auto" else model  # the model that answered
    if tuple(res.free) != names_in or res.model != model:
        raise ValueError(f"start_fit must be a {model!r} fit with free={names_in!r}, got a "
                         f"{res.model!r} fit with free={tuple(res.free)!r}")
    if mu_s is not None and res.fixed.get("mu_s") != float(mu_s):
        raise ValueError(f"start_fit must be a fit with mu_s={mu_s!r}, got one with "
                         f"mu_s={res.fixed.get('mu_s')!r}")
    stride = max(1, math.ceil(len(res.t) / MAX_SAMPLES))
    residual, args, layout, centre, width, theta0 = _trace_setup(res, stride, vary_k3)
    out = sample(residual, args, layout, Prior(centre, width), theta0, mode=GRADIENTS[model],
                 chains=Chains(num_samples, num_chains, num_warmup, seed))
    bar.update(2)
    bar.close()
    draws, observed = _trace_groups(out, layout, res, names_in, stride)
    return _finish(out, draws, observed, res, model, began, stride, free=names_in)
