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
trace (:class:`TraceResidual`) from a least-squares fit.

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

import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._core import FIT_MODELS, ReferenceOptions, reference_solution
from ._params import DAMPING, Constants, TraceCoords, ansatz_v0, unit_of

#: the posterior uses every s-th sample of the fit window, at most this many (the AR(1) noise
#: model holds for the thinned residuals too, with coefficient phi^s)
MAX_SAMPLES = 4096
#: the most doublings of a NUTS trajectory (2^7 = 128 leapfrog steps)
MAX_DOUBLINGS = 7
#: the acceptance rate the window adaptation aims at
TARGET_ACCEPT = 0.8
#: tolerances of the reference integrator inside the posterior (well below any noise level)
REFERENCE_RTOL, REFERENCE_ATOL = 1e-9, 1e-12
#: how each fit model's log density is differentiated ("reverse": jax.grad; "forward": one
#: jacfwd over the parameters, as a custom JVP). For the reference, forward mode through the
#: plain loop took 1.8 ms per value and gradient (2 chains, 750 samples, 7 parameters) against
#: 8.6 ms in reverse mode through the checkpointed loop (adjoint="recursive"), and compiled in
#: half the time
GRADIENTS = {"ansatz": "reverse", "reference": "forward"}

#: the priors, for the docs and the report
PRIORS = {
    "damping constant c (free)": "log c ~ Normal(log c_guess, 3), c_guess from the turning points",
    "w0": "Normal(w_turn, 0.05 w_turn), w_turn the turning points' frequency",
    "offset": "Normal(offset of the least-squares fit, A)",
    "x0, y = A sin(phi) (ansatz) or v0 (reference)":
        "Normal(least-squares value, 2 A) (v0: 2 A w0)",
    "sigma (AR(1) innovation sd)": "log sigma ~ Normal(log rms of the fit, 2)",
    "phi_n (AR(1) coefficient)": "atanh phi_n ~ Normal(0, 2)",
    "k3 (free)": "k3 A^2/(m w0^2) ~ Normal(0, 0.5) (|k3| A^2/(m w0^2) ~ 1 is far beyond the "
                 "harmonic balance of docs/cubic_stiffness.md)",
}
#: the variables of the sample_stats group (ArviZ's names)
SAMPLE_STATS = ("lp", "diverging", "energy", "step_size", "tree_depth", "acceptance_rate",
                "n_steps")


# ----------------------------------------------------------------------------------------------
# the log density of any residual function


class Layout(NamedTuple):
    """The entries of the physical parameter vector p of a residual function (static).

    Attributes:
        names: the name of each entry, in order.
        log: per entry, whether it is sampled as its logarithm (a positive constant).
        noise: the number of independent noise series, each with its own sigma and phi_n:
            1 (every row of the residual shares them) or the residual's number of rows (one
            per row, e.g. per run of a joint fit).
    """

    names: tuple
    log: tuple
    noise: int = 1

    @property
    def dim(self) -> int:
        """Entries of theta: the layout's, then log sigma and atanh phi_n of each series."""
        return len(self.names) + 2 * self.noise


class _Data(NamedTuple):
    """What the log posterior needs besides theta (traced: one compilation per shape)."""

    args: Any  # the residual's arguments (a pytree)
    centre: jax.Array  # prior centres and widths of theta (the layout's entries, then noise)
    width: jax.Array
    theta_map: jax.Array
    L: jax.Array
    mask: Any = None  # (rows, n) booleans: the samples that count (None: all)


def ar1_loglik(r, sigma, phi, mask=None):
    """Exact log likelihood of a stationary AR(1) series r (along the last axis; rows of a
    2-D r are independent series).

    Arguments:
        r: residuals, shape (n,) or (rows, n).
        sigma: innovation standard deviation: one, or one per row (rows,).
        phi: lag-1 coefficient, |phi| < 1: one, or one per row.
        mask: None, or booleans of r's shape: the samples that are data (padding left out of
            the likelihood; each unbroken stretch of data is a stationary series of its own).

    Returns:
        sum_rows [-1/2 sum_t e_t^2 / sigma^2 - r_1^2 (1 - phi^2) / (2 sigma^2) - n log sigma
        + 1/2 log(1 - phi^2)] with e_t = r_t - phi r_(t-1), n the samples of the row that count
        (the constant -n/2 log 2 pi left out).
    """
    r = jnp.atleast_2d(r)
    sigma = jnp.reshape(sigma, (-1, 1))
    phi = jnp.reshape(phi, (-1, 1))
    if mask is None:
        mask = jnp.ones(r.shape, dtype=bool)
    mask = jnp.broadcast_to(jnp.atleast_2d(mask), r.shape)
    prev = jnp.concatenate([jnp.zeros_like(mask[:, :1]), mask[:, :-1]], axis=1)
    lagged = jnp.concatenate([jnp.zeros_like(r[:, :1]), r[:, :-1]], axis=1)
    inner = mask & prev                 # innovations e_t = r_t - phi r_(t-1)
    first = mask & ~prev                # the first sample of a stretch: stationary
    e = jnp.where(inner, r - phi * lagged, 0.0)
    r1 = jnp.where(first, r, 0.0)
    quad = (jnp.sum(e * e, axis=-1, keepdims=True)
            + (1 - phi ** 2) * jnp.sum(r1 * r1, axis=-1, keepdims=True)) / sigma ** 2
    n = jnp.sum(mask, axis=-1, keepdims=True)
    starts = jnp.sum(first, axis=-1, keepdims=True)
    per_row = -0.5 * quad - n * jnp.log(sigma) + 0.5 * starts * jnp.log1p(-phi ** 2)
    return jnp.sum(per_row)


def physical(theta, layout: Layout):
    """p of the layout from the unconstrained theta (exp of the log entries), then sigma and
    phi_n from the last entries (scalars for one noise series, else one per series)."""
    n, k = len(layout.names), layout.noise
    p = jnp.stack([jnp.exp(theta[i]) if lg else theta[i] for i, lg in enumerate(layout.log)])
    sigma, phi = jnp.exp(theta[n:n + k]), jnp.tanh(theta[n + k:n + 2 * k])
    if k == 1:
        return p, sigma[0], phi[0]
    return p, sigma, phi


def _logpost(theta, data: _Data, residual: Callable, layout: Layout):
    """log prior (independent normals on theta) + AR(1) log likelihood of residual(p)."""
    p, sigma, phi = physical(theta, layout)
    out = ar1_loglik(residual(p, data.args), sigma, phi, data.mask) \
        - 0.5 * jnp.sum(((theta - data.centre) / data.width) ** 2)
    return jnp.where(jnp.isfinite(out), out, -jnp.inf)


def _density(residual: Callable, layout: Layout, mode: str):
    """The log posterior f(theta, data), differentiated in ``mode`` ("reverse" or
    "forward": the gradient by jacfwd inside a custom JVP, for models whose loops have no
    reverse mode)."""
    f = functools.partial(_logpost, residual=residual, layout=layout)
    if mode == "reverse":
        return f
    if mode != "forward":
        raise ValueError(f"mode must be 'reverse' or 'forward', got {mode!r}")

    @jax.custom_jvp
    def g(theta, data):
        return f(theta, data)

    @g.defjvp
    def g_jvp(primals, tangents):
        theta, data = primals
        grad, value = jax.jacfwd(lambda th: (f(th, data),) * 2, has_aux=True)(theta)
        return value, grad @ tangents[0]

    return g


@functools.partial(jax.jit, static_argnames=("residual", "layout", "mode"))
def _neg_value_and_grad(theta, data, residual, layout, mode):
    f = _density(residual, layout, mode)
    return jax.value_and_grad(lambda th: -f(th, data))(theta)


@functools.partial(jax.jit, static_argnames=("residual", "layout", "mode"))
def _neg_hessian(theta, data, residual, layout, mode):
    f = _density(residual, layout, mode)
    return jax.jacfwd(jax.grad(lambda th: -f(th, data)))(theta)


@functools.partial(jax.jit, static_argnames=("residual", "layout", "mode", "num_warmup",
                                             "num_samples"))
def _chains(keys, u0, data, residual, layout, mode, num_warmup, num_samples):
    """Window adaptation then NUTS sampling of every chain, vmapped over the chains (keys,
    u0: one row per chain); returns the draws of u and the sample stats."""
    import blackjax
    from blackjax.adaptation.base import get_filter_adapt_info_fn

    f = _density(residual, layout, mode)

    def logdensity(u):
        return f(data.theta_map + data.L @ u, data)

    def one_chain(key, u):
        k_warm, k_draw = jax.random.split(key)
        warmup = blackjax.window_adaptation(
            blackjax.nuts, logdensity, target_acceptance_rate=TARGET_ACCEPT,
            adaptation_info_fn=get_filter_adapt_info_fn(), max_num_doublings=MAX_DOUBLINGS)
        (state, params), _ = warmup.run(k_warm, u, num_warmup)
        step = blackjax.nuts(logdensity, step_size=params["step_size"],
                             inverse_mass_matrix=params["inverse_mass_matrix"],
                             max_num_doublings=MAX_DOUBLINGS).step

        def draw(st, k):
            st, info = step(k, st)
            return st, (st.position, {
                "lp": st.logdensity, "diverging": info.is_divergent, "energy": info.energy,
                "tree_depth": info.num_trajectory_expansions,
                "acceptance_rate": info.acceptance_rate,
                "n_steps": info.num_integration_steps})

        _, (pos, stats) = jax.lax.scan(draw, state, jax.random.split(k_draw, num_samples))
        stats["step_size"] = jnp.broadcast_to(params["step_size"], (num_samples,))
        return pos, stats

    return jax.vmap(one_chain)(keys, u0)


class Draws(NamedTuple):
    """What :func:`sample` returns: theta (chain, draw, dim), the sample stats (each (chain,
    draw)), the mode and the Laplace factor, and the seconds of the mode search and of the
    compiled chains."""

    theta: np.ndarray
    stats: dict
    theta_map: np.ndarray
    L: np.ndarray
    seconds_mode: float
    seconds_chains: float


def sample(residual: Callable, args, layout: Layout, centre, width, theta0, *,
           mode: str = "reverse", num_samples: int = 1000, num_chains: int = 4,
           num_warmup: int = 500, seed: int = 0, mask=None) -> Draws:
    """NUTS draws of theta = (the layout's entries, log sigma and atanh phi_n of each noise
    series) for any residual.

    The posterior: independent normal priors N(centre, width) on theta, AR(1) noise on
    ``residual(p, args)`` (:func:`ar1_loglik`, the samples of ``mask``), p = :func:`physical`
    (theta). Mode by L-BFGS from theta0, Laplace preconditioning, window adaptation and
    sampling vmapped over chains.

    Arguments:
        residual: ``residual(p, args) -> r`` (data minus model, shape (n,) or (rows, n)),
            hashable (a frozen dataclass: it is a static argument of the compiled programs).
        args: its arrays (a pytree; traced).
        layout: the names of p and which are sampled as logarithms.
        centre, width, theta0: prior centres, widths and the start, ``layout.dim`` entries.
        mode: "reverse" or "forward" differentiation of the log density.
        num_samples, num_chains, num_warmup: draws per chain, chains, warm-up steps.
        seed: random seed.
        mask: None, or booleans of the residual's shape: the samples in the likelihood (the
            padding of runs of different lengths left out).

    Returns:
        :class:`Draws`.
    """
    from scipy.optimize import minimize

    dim = layout.dim
    for name, v in (("centre", centre), ("width", width), ("theta0", theta0)):
        if np.shape(v) != (dim,):
            raise ValueError(f"{name} must have {dim} entries (the layout's and 2 per noise "
                             f"series), got shape {np.shape(v)}")
    began = time.perf_counter()
    data = _Data(args=args, centre=jnp.asarray(centre, dtype=float),
                 width=jnp.asarray(width, dtype=float), theta_map=jnp.zeros(dim),
                 L=jnp.eye(dim), mask=None if mask is None else jnp.asarray(mask, dtype=bool))
    static = dict(residual=residual, layout=layout, mode=mode)

    def fun(th):
        v, gr = _neg_value_and_grad(jnp.asarray(th), data, **static)
        v = float(v)
        return (v, np.asarray(gr, dtype=float)) if math.isfinite(v) else (1e300, np.zeros_like(th))

    opt = minimize(fun, np.asarray(theta0, dtype=float), jac=True, method="L-BFGS-B",
                   options={"maxiter": 500})
    theta_map = np.asarray(opt.x, dtype=float)
    H = np.asarray(_neg_hessian(jnp.asarray(theta_map), data, **static), dtype=float)
    H = 0.5 * (H + H.T)
    if not np.all(np.isfinite(H)):
        H = np.diag(1.0 / np.asarray(width, dtype=float) ** 2)
    ev, V = np.linalg.eigh(H)
    ev = np.clip(ev, max(ev.max(), 1e-300) * 1e-12, None)
    L = np.linalg.cholesky((V / ev) @ V.T + 1e-300 * np.eye(dim))
    data = data._replace(theta_map=jnp.asarray(theta_map), L=jnp.asarray(L))
    mid = time.perf_counter()
    k_init, k_chains = jax.random.split(jax.random.PRNGKey(int(seed)))
    nch = int(num_chains)
    u0 = 0.5 * jax.random.normal(k_init, (nch, dim))
    U, stats = _chains(jax.random.split(k_chains, nch), u0, data, num_warmup=int(num_warmup),
                       num_samples=int(num_samples), **static)
    U = np.asarray(U)  # (chain, draw, dim)
    stats = {k: np.asarray(v) for k, v in stats.items()}
    done = time.perf_counter()
    theta = theta_map[None, None, :] + U @ L.T
    return Draws(theta=theta, stats=stats, theta_map=theta_map, L=L,
                 seconds_mode=mid - began, seconds_chains=done - mid)


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
# the result


@dataclass
class Posterior:
    """Posterior draws of a trace fit or of a joint fit of several runs (:func:`posterior`).

    Attributes:
        draws: xarray Dataset, one variable per sampled parameter (the free damping constants,
            k3 when free, w0 and offset when fitted, x0, v0, sigma, phi_noise), dims (chain,
            draw): the ``posterior`` group of ArviZ; the fixed parameters are its attributes
            ``fixed_<name>``. Of a joint fit: the shared parameters (chain, draw), each run's
            own (x0, v0, offset, sigma, phi_noise, ...) (chain, draw, run).
        sample_stats: xarray Dataset of the sampler's statistics per draw (:data:`SAMPLE_STATS`:
            lp, diverging, energy, step_size, tree_depth, acceptance_rate, n_steps).
        observed_data: xarray Dataset of the fit window: x over the coordinate t (of a joint
            fit: x and t over (run, sample), NaN after each run's last sample).
        free: the sampled constants (the damping constants, then k3 when free).
        fit: the least-squares :class:`FitResult` (``JointResult``) it started from.
        model: the fit model sampled ("ansatz" or "reference").
        units, per_mass: as the fit's.
        accept_rate, divergences, step_size: sampler diagnostics (means over chains and
            draws; the step size averaged over the chains).
        seconds: wall time of :func:`posterior` (the start fit included when it ran).
        seconds_chains: wall time of the warm-up and sampling program (compilation included
            on its first call for a shape).
        stride: the likelihood uses 1 sample in ``stride`` of the window.
    """

    draws: object
    free: tuple
    fit: object
    sample_stats: object = None
    observed_data: object = None
    model: str = "ansatz"
    units: str = "m"
    per_mass: bool = False
    accept_rate: float = math.nan
    divergences: int = 0
    step_size: float = math.nan
    seconds: float = math.nan
    seconds_chains: float = math.nan
    stride: int = 1
    priors: dict = field(default_factory=lambda: dict(PRIORS))

    def summary(self, level: float = 0.95) -> dict:
        """Posterior summary per sampled parameter.

        Arguments:
            level: the two-sided level of the central interval.

        Returns:
            {name: {"mean", "sd", "lo", "hi", "r_hat", "ess_bulk", "ess_tail", "ess"}}: the
            mean, standard deviation, the central ``level`` interval, the rank-normalised
            split R-hat and the bulk and tail effective sample sizes, as ``arviz.rhat`` and
            ``arviz.ess`` compute them (``_mcmc``; Vehtari et al. 2021); "ess" is the bulk
            ESS. R-hat is NaN for one chain.
        """
        from ._mcmc import ess_bulk, ess_tail, rhat

        if not 0.0 < level < 1.0:
            raise ValueError(f"level must be in (0, 1), got {level!r}")
        out = {}
        for var in self.draws.data_vars:
            v = self.draws[var]
            if "run" in v.dims:  # a joint posterior's per-run parameter: name[j]
                v = v.transpose("chain", "draw", "run")
                items = [(f"{var}[{j}]", v.values[..., j]) for j in range(v.sizes["run"])]
            else:
                items = [(var, v.values)]
            for name, a in items:
                a = np.asarray(a, dtype=float)
                q = np.quantile(a, [0.5 - 0.5 * level, 0.5 + 0.5 * level])
                bulk = ess_bulk(a)
                out[name] = {"mean": float(a.mean()), "sd": float(a.std(ddof=1)),
                             "lo": float(q[0]), "hi": float(q[1]), "r_hat": rhat(a),
                             "ess_bulk": bulk, "ess_tail": ess_tail(a), "ess": bulk}
        return out

    def report(self, level: float = 0.95) -> str:
        """The summary as text, with the sampler's diagnostics."""
        s = self.summary(level)
        nc, nd = self.draws.sizes["chain"], self.draws.sizes["draw"]
        joint = "run" in self.draws.dims
        what = (f"joint {self.model} fit of {self.draws.sizes['run']} runs"
                if joint else f"{self.model} model")
        lines = [f"[[Posterior]] NUTS (blackjax, window adaptation), {what}, "
                 f"{nc} chains x {nd} draws, AR(1) noise{' per run' if joint else ''}; "
                 f"accept rate "
                 f"{self.accept_rate:.2f}, {self.divergences} divergences, "
                 f"{self.seconds:.1f} s"
                 + (f"; 1 sample in {self.stride}" if self.stride > 1 else ""),
                 f"    {'':<10} {'mean':>12} {f'{100 * level:g} % interval':>28} "
                 f"{'r_hat':>6} {'ess_bulk':>8} {'ess_tail':>8}"]
        for name, row in s.items():
            base = _base(name)
            unit = unit_of(base, self.units, self.per_mass) if base in DAMPING or base in (
                "w0", "offset", "x0", "v0", "k3") else ("" if base == "phi_noise"
                                                        else self.units)
            lines.append(f"    {name + ':':<10} {row['mean']:>12.6g} [{row['lo']:>12.6g}, "
                         f"{row['hi']:>12.6g}] {row['r_hat']:>6.3f} {row['ess_bulk']:>8.0f} "
                         f"{row['ess_tail']:>8.0f} {unit}".rstrip())
        attrs = self.draws.attrs
        if "fixed_mu_s" in attrs:  # static friction: held, not sampled (static_friction)
            held = f"    mu_s held at {attrs['fixed_mu_s']:.6g}"
            if "mu_s_interval" in attrs:
                lo, hi = attrs["mu_s_interval"]
                held += (f" (the fit's; every value in [{lo:.6g}, {hi:.6g}) gives the same "
                         "halt): the draws are conditional on that halt")
            lines.append(held)
        bad = [n for n, row in s.items() if not row["r_hat"] < 1.01] if nc > 1 else []
        if bad:
            lines.append(f"    warning: r_hat >= 1.01 for {', '.join(bad)}: the chains "
                         "disagree (more warm-up or draws)")
        return "\n".join(lines)

    def to_netcdf(self, path) -> Path:
        """Write an ArviZ InferenceData file: groups posterior (:attr:`draws`), sample_stats
        and observed_data (netCDF-4, ``arviz.from_netcdf`` opens it; ArviZ is not needed to
        write it). Returns the path."""
        from ._mcmc import write_inference_data

        return write_inference_data({"posterior": self.draws,
                                     "sample_stats": self.sample_stats,
                                     "observed_data": self.observed_data}, path)

    def corner(self, path, *, names=None) -> Path:
        """Save a corner plot (pairwise scatter and histograms) of the damping constants (or
        ``names``); ``dampax._plot.plot_corner``."""
        from .._plot import plot_corner

        if names is None:  # of a joint posterior: the shared constants
            names = [n for n in self.free if n in self.draws.data_vars
                     and self.draws[n].dims == ("chain", "draw")]
        names = list(names)
        return plot_corner(self.draws, names, path,
                           units={n: unit_of(n, self.units, self.per_mass) for n in names})


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
        opts = ReferenceOptions(int(1.2 * span * p["w0"] / math.pi) + 8, REFERENCE_RTOL,
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


def _base(name: str) -> str:
    """The parameter of a layout name: "x0" of "x0[1]"."""
    return name.split("[")[0]


def _joint_setup(res, stride: int):
    """(residual, args, layout, centre, width, theta0, mask) of the joint fit ``res`` (a
    :class:`~dampax._fit._joint.JointResult`): the joint problem's residuals of every run,
    thinned by ``stride``, its padding masked out, one AR(1) noise series per run; the priors
    of :data:`PRIORS` per parameter (a shared one centred on the runs' median)."""
    from ._joint import JointResidual

    pr = res.problem()
    lay = pr.residual.layout
    opts = pr.residual.opts
    if opts is not None:
        opts = ReferenceOptions(opts.max_swings, REFERENCE_RTOL, REFERENCE_ATOL)
    a = pr.args
    # the padding beyond the longest run dropped (to a power of two: similar sets share the
    # compiled sampler), then every stride-th sample
    n_max = int(np.max(np.sum(pr.mask, axis=1)))
    keep = min(a.tau.shape[1], max(256, 1 << int(math.ceil(math.log2(max(n_max, 1))))))
    args = a._replace(tau=a.tau[:, :keep:stride], x=a.x[:, :keep:stride],
                      weight=a.weight[:, :keep:stride])
    mask = np.asarray(args.weight) > 0.0
    residual = JointResidual(lay, opts)
    singles, runs = res.singles, res.runs
    amp = [max(float(s.derived["A"]), 1e-300) for s in singles]
    w_turn = [s.params["w0"] / (1.0 + float(s.diagnostics.get("w0/turning - 1", 0.0)))
              for s in singles]
    m = float(runs[0].fixed["m"])
    names, log, centre, width, theta0 = [], [], [], [], []
    for name, v in zip(pr.names, np.asarray(pr.p0, dtype=float), strict=True):
        base = _base(name)
        j = int(name[len(base) + 1:-1]) if "[" in name else None
        if base in DAMPING:
            guesses = [max(float(s.init.get(base, s.params[base])), 1e-30)
                       for s in (singles if j is None else [singles[j]])]
            guess = float(np.median(guesses))
            c, w, start, is_log = math.log(guess), 3.0, math.log(max(v, guess * 1e-6)), True
        elif base == "w0":
            wt = float(np.median(w_turn)) if j is None else w_turn[j]
            c, w, start, is_log = wt, 0.05 * wt, v, False
        elif base == "k3":  # k3 A^2/(m w0^2) ~ N(0, 0.5) at the runs' median
            scale = m * float(np.median([r.params["w0"] for r in runs])) ** 2
            c, w, start, is_log = 0.0, 0.5 * scale / float(np.median(amp)) ** 2, v, False
        elif base == "offset":
            c, w, start, is_log = v, amp[j], v, False
        elif base == "x0":
            c, w, start, is_log = v, 2 * amp[j], v, False
        else:  # v0
            c, w, start, is_log = v, 2 * amp[j] * runs[j].params["w0"], v, False
        names.append(name)
        log.append(is_log)
        centre.append(c)
        width.append(w)
        theta0.append(start)
    r = np.asarray(residual(jnp.asarray(pr.p0, dtype=float), args))
    log_rms, log_sig, atanh_phi = [], [], []
    for j in range(len(runs)):
        rj = r[j][mask[j]]
        phi_hat = float(np.clip(np.corrcoef(rj[:-1], rj[1:])[0, 1], -0.9, 0.995))
        log_rms.append(math.log(float(np.sqrt(np.mean(rj * rj))) or 1e-12))
        log_sig.append(math.log(float(np.std(rj[1:] - phi_hat * rj[:-1])) or 1e-12))
        atanh_phi.append(math.atanh(phi_hat))
    n = len(runs)
    centre += log_rms + [0.0] * n
    width += [2.0] * (2 * n)
    theta0 += log_sig + atanh_phi
    layout = Layout(tuple(names), tuple(log), noise=n)
    return residual, args, layout, centre, width, theta0, mask


def _joint_posterior(traces, *, start_fit, shared, free, model, num_samples, num_chains,
                     num_warmup, seed, bar, began, fit_kw) -> Posterior:
    """The posterior of a joint fit of several runs (:func:`posterior` with a list)."""
    import xarray as xr

    from ._entry import fit
    from ._joint import JointResult

    res = start_fit if start_fit is not None else fit(
        list(traces), shared=shared, free=free, model=model, seed=seed, **fit_kw)
    bar.update()
    if not isinstance(res, JointResult) or res.model != model:
        raise ValueError(f"start_fit must be a {model!r} joint fit (a JointResult of dp.fit "
                         f"with the list of runs), got {type(res).__name__}"
                         + (f" of the {res.model!r} model" if hasattr(res, "model") else ""))
    if shared is not None and set(_names(shared)) != set(res.shared):
        raise ValueError(f"start_fit: its shared parameters {res.shared!r} are not "
                         f"shared={_names(shared)!r}")
    n_runs = len(res.runs)
    stride = max(1, math.ceil(max(r.ndata for r in res.runs) / MAX_SAMPLES))
    residual, args, layout, centre, width, theta0, mask = _joint_setup(res, stride)
    out = sample(residual, args, layout, centre, width, theta0, mode=GRADIENTS[model],
                 num_samples=num_samples, num_chains=num_chains, num_warmup=num_warmup,
                 seed=seed, mask=mask)
    bar.update(2)
    bar.close()
    nch, nd, dim = out.theta.shape
    flat = jnp.asarray(out.theta.reshape(-1, dim))
    P, sigma, phi_n = (np.asarray(v) for v in jax.vmap(lambda th: physical(th, layout))(flat))
    coords = {"chain": np.arange(nch), "draw": np.arange(nd), "run": np.arange(n_runs)}
    data = {}
    shared_names = [nm for nm in layout.names if "[" not in nm]
    for nm in shared_names:
        data[nm] = (("chain", "draw"), P[:, layout.names.index(nm)].reshape(nch, nd))
    per_run = [_base(nm) for nm in layout.names if nm.endswith("[0]")]
    for base in per_run:
        cols = [layout.names.index(f"{base}[{j}]") for j in range(n_runs)]
        data[base] = (("chain", "draw", "run"), P[:, cols].reshape(nch, nd, n_runs))
    data["sigma"] = (("chain", "draw", "run"), sigma.reshape(nch, nd, n_runs))
    data["phi_noise"] = (("chain", "draw", "run"), phi_n.reshape(nch, nd, n_runs))
    r0 = res.runs[0]
    sampled = set(shared_names) | set(per_run)
    fixed = {f"fixed_{nm}": float(r0.params[nm]) for nm in (*DAMPING, "w0")
             if nm not in sampled}
    fixed.update(fixed_m=float(r0.fixed["m"]), fixed_g=float(r0.fixed["g"]))
    attrs = {"inference_library": "blackjax", "sampler": "NUTS, window adaptation",
             "model": f"joint {model} fit of {n_runs} runs + AR(1) noise per run",
             "units": res.units, "per_mass": int(res.per_mass), "free": ",".join(res.free),
             "shared": ",".join(res.shared), "stride": stride,
             "t_start": [float(r.t[0]) for r in res.runs],
             "priors": "; ".join(f"{k}: {v}" for k, v in PRIORS.items()), **fixed}
    draws = xr.Dataset(data, coords=coords, attrs=attrs)
    n_max = max(r.ndata for r in res.runs)
    tt = np.full((n_runs, n_max), np.nan)
    xx = np.full((n_runs, n_max), np.nan)
    for j, r in enumerate(res.runs):
        tt[j, :r.ndata] = r.t
        xx[j, :r.ndata] = r.x
    observed = xr.Dataset({"x": (("run", "sample"), xx), "t": (("run", "sample"), tt)},
                          coords={"run": np.arange(n_runs), "sample": np.arange(n_max)},
                          attrs={"units": res.units, "stride": stride,
                                 "sources": [str(r.source) for r in res.runs],
                                 "padding": "NaN after each run's last sample"})
    return _finish(out, draws, observed, res, model, began, stride, free=tuple(res.free))


def _names(value) -> tuple:
    if isinstance(value, str):
        return tuple(s.strip() for s in value.split(",") if s.strip())
    return tuple(value)


def _finish(out: Draws, draws, observed, res, model, began, stride, *, free) -> Posterior:
    """The :class:`Posterior` of the draws (the sample_stats group built here)."""
    import xarray as xr

    st = out.stats
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
                     stride=stride)


def posterior(trace_or_t, x=None, *, oscillator=None, free=("mu", "D"), model: str = "ansatz",
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
        model: "ansatz" (closed form, eqs. 11, 20-23) or "reference" (eq. 3 integrated with
            exact stick-slip; slower, forward-mode gradients).
        num_samples, num_chains, num_warmup: draws per chain, chains, warm-up steps (blackjax
            window adaptation, per chain).
        seed: random seed.
        start_fit: a :class:`FitResult` (for a list of runs a ``JointResult``) of the same
            data, options and model to start from (default: ``fit(...)`` is run).
        progress: show a tqdm bar over the stages (start fit, mode, chains) on stderr.

    Returns:
        A :class:`Posterior`.
    """
    import xarray as xr
    from tqdm import tqdm

    from ._core import MODELS
    from ._entry import fit
    from ._params import FREE, check_choice, check_free

    check_choice("model", model, MODELS)
    for name, value, low in (("num_samples", num_samples, 10), ("num_chains", num_chains, 1),
                             ("num_warmup", num_warmup, 10)):
        if isinstance(value, bool) or int(value) != value or value < low:
            raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    names_in = check_free(free, allowed=FREE)
    vary_k3 = "k3" in names_in
    free = tuple(c for c in names_in if c not in ("k3", "mu_s"))  # the damping constants
    if not free:
        raise ValueError("free: name at least one damping constant")
    began = time.perf_counter()
    bar = tqdm(total=3, desc="posterior", unit="stage", disable=not progress)
    if isinstance(trace_or_t, (list, tuple)) and x is None:
        if vary_k3:
            raise ValueError("free: a joint posterior samples k3 only as shared=(..., 'k3')")
        return _joint_posterior(
            trace_or_t, start_fit=start_fit, shared=shared, free=free, model=model,
            num_samples=num_samples, num_chains=num_chains, num_warmup=num_warmup, seed=seed,
            bar=bar, began=began,
            fit_kw=dict(oscillator=oscillator, fit_omega0=fit_omega0, offset=offset,
                        start=start, end=end, units=units, starts=starts,
                        max_swings=max_swings))
    if shared is not None:
        raise ValueError("shared: names constants common to several runs; it needs a list of "
                         "two or more traces, not a single trace")
    res = start_fit if start_fit is not None else fit(
        trace_or_t, x, oscillator=oscillator, free=names_in, model=model,
        fit_omega0=fit_omega0, offset=offset, start=start, end=end, units=units, seed=seed,
        mu_s=mu_s)
    bar.update()
    if tuple(res.free) != names_in or res.model != model:
        raise ValueError(f"start_fit must be a {model!r} fit with free={names_in!r}, got a "
                         f"{res.model!r} fit with free={tuple(res.free)!r}")
    if mu_s is not None and res.fixed.get("mu_s") != float(mu_s):
        raise ValueError(f"start_fit must be a fit with mu_s={mu_s!r}, got one with "
                         f"mu_s={res.fixed.get('mu_s')!r}")
    stride = max(1, math.ceil(len(res.t) / MAX_SAMPLES))
    residual, args, layout, centre, width, theta0 = _trace_setup(res, stride, vary_k3)
    out = sample(residual, args, layout, centre, width, theta0, mode=GRADIENTS[model],
                 num_samples=num_samples, num_chains=num_chains, num_warmup=num_warmup,
                 seed=seed)
    bar.update(2)
    bar.close()
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
    return _finish(out, draws, observed, res, model, began, stride, free=names_in)
