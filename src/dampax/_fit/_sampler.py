"""The sampler of the posterior (``_posterior``): the log density of any residual function
(AR(1) noise, the priors of :data:`PRIORS`), the mode search and Laplace preconditioning, and
NUTS with blackjax's window adaptation vmapped over chains (:func:`sample`). The model, the
priors and the sampler are described in ``_posterior``."""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

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


def _neg_hessian(grad: Callable, theta: np.ndarray) -> np.ndarray:
    """The Hessian of the negative log posterior at ``theta`` by central differences of its
    compiled gradient (``grad(theta) -> array``): the Laplace preconditioner of the chains
    needs no second program (differentiating the gradient again compiles a program as large
    as the chains' own).

    Steps of 1e-5 max(1, |theta_i|) first; a column whose step exceeds 1e-3 of the scale that
    its own diagonal gives (s_i = H_ii^-1/2: a coordinate known far better than 1e-5) is
    differenced again with a step of 1e-3 s_i. In float64 the rounding (1e-16 of the
    gradient's terms over the step) and the truncation (the step squared over the scale
    squared) then both stay near 1e-6 of the curvature or below. Symmetrised."""
    theta = np.asarray(theta, dtype=float)

    def column(i, h):
        e = np.zeros_like(theta)
        e[i] = h
        return (grad(theta + e) - grad(theta - e)) / (2.0 * h)

    steps = 1e-5 * np.maximum(1.0, np.abs(theta))
    H = np.stack([column(i, h) for i, h in enumerate(steps)], axis=1)
    diag = np.diag(H)
    scale = np.where(np.isfinite(diag) & (diag > 0.0), 1.0 / np.sqrt(np.abs(diag)), np.inf)
    for i in np.flatnonzero(steps > 1e-3 * scale):
        H[:, i] = column(i, 1e-3 * scale[i])
    return 0.5 * (H + H.T)


class _Adaptation(NamedTuple):
    """The warm-up's state: dual averaging's, the mass matrix's windows', their values."""

    ss_state: Any
    imm_state: Any
    step_size: Any
    inverse_mass_matrix: Any


def _stan_adaptation(target: float):
    """Stan's window adaptation with a diagonal mass matrix, (init, update, final) as
    blackjax's ``window_adaptation.base(True, target)`` (deprecated in blackjax 1.7, to be
    removed), from the same parts (the step size by dual averaging, the mass matrix by
    Welford's windows, both blackjax's): the same arithmetic, the same draws."""
    from blackjax.adaptation.mass_matrix import mass_matrix_adaptation
    from blackjax.adaptation.step_size import dual_averaging_adaptation

    mm_init, mm_update, mm_final = mass_matrix_adaptation(True)
    da_init, da_update, da_final = dual_averaging_adaptation(target)

    def init(u, step_size: float) -> _Adaptation:
        imm = mm_init(u.size)
        return _Adaptation(da_init(step_size), imm, step_size, imm.inverse_mass_matrix)

    def update(a: _Adaptation, stage: tuple, u, acceptance_rate) -> _Adaptation:
        slow, window_end = stage  # (a slow window: the mass matrix's estimate too)
        ss = da_update(a.ss_state, acceptance_rate)
        imm = jax.lax.cond(slow == 1, lambda: mm_update(a.imm_state, u), lambda: a.imm_state)
        a = _Adaptation(ss, imm, jnp.exp(ss.log_step_size), a.inverse_mass_matrix)

        def window_ended(a):  # a new mass matrix, the step size's averaging restarted
            imm = mm_final(a.imm_state)
            ss = da_init(da_final(a.ss_state))
            return _Adaptation(ss, imm, jnp.exp(ss.log_step_size), imm.inverse_mass_matrix)
        return jax.lax.cond(window_end, window_ended, lambda a: a, a)

    def final(a: _Adaptation):
        return jnp.exp(a.ss_state.log_step_size_avg), a.imm_state.inverse_mass_matrix

    return init, update, final


@functools.partial(jax.jit, static_argnames=("residual", "layout", "mode", "num_warmup",
                                             "num_samples"))
def _chains(keys, start, data, residual, layout, mode, num_warmup, num_samples):
    """Window adaptation then NUTS sampling of every chain, vmapped over the chains (keys and
    ``start``: one row per chain; ``start`` = (u0, the log density there, its gradient in
    u), computed by the caller's compiled gradient, so that this program holds the gradient
    only inside its kernel); returns the draws of u and the sample stats.

    Stan's window adaptation (:func:`_stan_adaptation` and blackjax's ``build_schedule``:
    the step size by dual averaging, a diagonal mass matrix over doubling windows) and the
    draws run in ONE scan over warm-up and draws, through one NUTS kernel: the step size and
    mass matrix are the adaptation's during the warm-up and its final values after. Running
    blackjax's ``window_adaptation(...).run`` and then a scan of ``nuts(...).step`` (the same
    keys, the same draws to the last bit) put two copies of the kernel, the log density's
    gradient inside, into the program: the reference posterior of tests/fit/test_posterior.py
    compiled in 10.8 s, 8.2 s in one scan (the ansatz's 6.6 -> 5.9 s)."""
    import blackjax.mcmc.nuts as nuts
    from blackjax.adaptation.window_adaptation import build_schedule

    f = _density(residual, layout, mode)

    def logdensity(u):
        return f(data.theta_map + data.L @ u, data)

    kernel = nuts.build_kernel()
    adapt_init, adapt_update, adapt_final = _stan_adaptation(TARGET_ACCEPT)
    schedule = jnp.reshape(jnp.asarray(build_schedule(num_warmup), dtype=int), (num_warmup, 2))
    after = jnp.zeros(num_samples, dtype=int)
    stages = (jnp.concatenate([schedule[:, 0], after]),
              jnp.concatenate([schedule[:, 1], after]).astype(bool),
              jnp.arange(num_warmup + num_samples) < num_warmup)

    def one_chain(key, u, lp, grad):
        k_warm, k_draw = jax.random.split(key)
        keys = jnp.concatenate([jax.random.split(k_warm, num_warmup),
                                jax.random.split(k_draw, num_samples)])

        def step(carry, xs):
            state, adapt = carry
            k, stage, window_end, warming = xs
            final_step, final_imm = adapt_final(adapt)
            step_size = jnp.where(warming, adapt.step_size, final_step)
            state, info = kernel(k, state, logdensity, step_size,
                                 jnp.where(warming, adapt.inverse_mass_matrix, final_imm),
                                 max_num_doublings=MAX_DOUBLINGS)
            updated = adapt_update(adapt, (stage, window_end), state.position,
                                   info.acceptance_rate)
            adapt = jax.tree_util.tree_map(lambda a, b: jnp.where(warming, a, b), updated,
                                           adapt)
            return (state, adapt), (state.position, {
                "lp": state.logdensity, "diverging": info.is_divergent, "energy": info.energy,
                "tree_depth": info.num_trajectory_expansions,
                "acceptance_rate": info.acceptance_rate,
                "n_steps": info.num_integration_steps, "step_size": step_size})

        _, (pos, stats) = jax.lax.scan(
            step, (nuts.init(u, logdensity)._replace(logdensity=lp, logdensity_grad=grad),
                   adapt_init(u, 1.0)), (keys, *stages))
        return pos[num_warmup:], {k: v[num_warmup:] for k, v in stats.items()}

    return jax.vmap(one_chain)(keys, *start)


class Prior(NamedTuple):
    """The independent normal priors N(centre, width) on theta (``Layout.dim`` entries each).

    Attributes:
        centre: the prior centres.
        width: the prior widths.
    """

    centre: Any
    width: Any


class Chains(NamedTuple):
    """How :func:`sample` runs NUTS.

    Attributes:
        num_samples: draws per chain.
        num_chains: chains.
        num_warmup: warm-up (window adaptation) steps per chain.
        seed: random seed.
    """

    num_samples: int = 1000
    num_chains: int = 4
    num_warmup: int = 500
    seed: int = 0


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


def sample(residual: Callable, args, layout: Layout, prior: Prior, theta0, *,
           mode: str = "reverse", chains: Chains | None = None, mask=None) -> Draws:
    """NUTS draws of theta = (the layout's entries, log sigma and atanh phi_n of each noise
    series) for any residual.

    The posterior: independent normal priors N(``prior.centre``, ``prior.width``) on theta,
    AR(1) noise on ``residual(p, args)`` (:func:`ar1_loglik`, the samples of ``mask``),
    p = :func:`physical` (theta). Mode by L-BFGS from theta0, Laplace preconditioning, window
    adaptation and sampling vmapped over chains.

    Arguments:
        residual: ``residual(p, args) -> r`` (data minus model, shape (n,) or (rows, n)),
            hashable (a frozen dataclass: it is a static argument of the compiled programs).
        args: its arrays (a pytree; traced).
        layout: the names of p and which are sampled as logarithms.
        prior: the prior centres and widths (:class:`Prior`), ``layout.dim`` entries each.
        theta0: the start of the mode search, ``layout.dim`` entries.
        mode: "reverse" or "forward" differentiation of the log density.
        chains: draws per chain, chains, warm-up steps and the seed (:class:`Chains`;
            default ``Chains()``).
        mask: None, or booleans of the residual's shape: the samples in the likelihood (the
            padding of runs of different lengths left out).

    Returns:
        :class:`Draws`.
    """
    from scipy.optimize import minimize

    centre, width = prior
    chains = Chains() if chains is None else chains
    num_samples, num_chains, num_warmup, seed = chains
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

    def value_and_grad(th):  # the one compiled gradient: the mode search's and the Hessian's
        v, gr = _neg_value_and_grad(jnp.asarray(th), data, **static)
        return float(v), np.asarray(gr, dtype=float)

    def fun(th):
        v, gr = value_and_grad(th)
        return (v, gr) if math.isfinite(v) else (1e300, np.zeros_like(th))

    opt = minimize(fun, np.asarray(theta0, dtype=float), jac=True, method="L-BFGS-B",
                   options={"maxiter": 500})
    theta_map = np.asarray(opt.x, dtype=float)
    H = _neg_hessian(lambda th: value_and_grad(th)[1], theta_map)
    if not np.all(np.isfinite(H)):
        H = np.diag(1.0 / np.asarray(width, dtype=float) ** 2)
    ev, V = np.linalg.eigh(H)
    ev = np.clip(ev, max(ev.max(), 1e-300) * 1e-12, None)
    L = np.linalg.cholesky((V / ev) @ V.T + 1e-300 * np.eye(dim))
    data = data._replace(theta_map=jnp.asarray(theta_map), L=jnp.asarray(L))
    mid = time.perf_counter()
    k_init, k_chains = jax.random.split(jax.random.PRNGKey(int(seed)))
    nch = int(num_chains)
    u0 = np.asarray(0.5 * jax.random.normal(k_init, (nch, dim)))
    at = [value_and_grad(theta_map + L @ u) for u in u0]  # -log density, its gradient in theta
    start = (u0, np.array([-v for v, _ in at]), np.array([-(L.T @ g) for _, g in at]))
    U, stats = _chains(jax.random.split(k_chains, nch), start, data,
                       num_warmup=int(num_warmup), num_samples=int(num_samples), **static)
    U = np.asarray(U)  # (chain, draw, dim)
    stats = {k: np.asarray(v) for k, v in stats.items()}
    done = time.perf_counter()
    theta = theta_map[None, None, :] + U @ L.T
    return Draws(theta=theta, stats=stats, theta_map=theta_map, L=L,
                 seconds_mode=mid - began, seconds_chains=done - mid)


def _base(name: str) -> str:
    """The parameter of a layout name: "x0" of "x0[1]"."""
    return name.split("[")[0]
