"""A posterior of the damping constants by NUTS (blackjax), with AR(1) noise (issue 11, item 5).

Model: the ansatz x(t) = offset + A f(t - t0) cos(w0 (t - t0) + phi) (``_core``, eqs. 11, 20-23)
in its coordinates (mu, b, D, w0, offset, x0, y = A sin(phi)), plus AR(1) noise on the
residuals r = x - model: r_1 ~ N(0, sigma^2 / (1 - phi_n^2)), r_t - phi_n r_(t-1) ~ N(0,
sigma^2) (the exact likelihood of a stationary AR(1)); sigma and phi_n are sampled too.

Parameters sampled (unconstrained): log of every free damping constant, w0 (when fitted), the
offset (when fitted), the cubic stiffness k3 itself (when free: it has either sign), x0, y, log
sigma and atanh phi_n; with k3 the model is the ansatz with the amplitude-dependent phase of
docs/cubic_stiffness.md. Weakly informative priors, documented in :data:`PRIORS`: log c ~ N(log
c_guess, 3) around the turning-point guess of the constant (a factor 20 per sigma), w0 ~
N(w_turn, 0.05 w_turn) around the turning points' frequency, offset ~ N(offset_fit, A), x0 and y
~ N(their least-squares values, 2 A), log sigma ~ N(log rms, 2), atanh phi_n ~ N(0, 2), k3
A^2/(m w0^2) ~ N(0, 0.5). The sampler runs on u with theta = theta_map + L u, L the Cholesky
factor of the Laplace covariance at the posterior mode (found by L-BFGS from the least-squares
fit), so the chains see a nearly isotropic target. One compiled program (blackjax's NUTS kernel,
vmapped over the chains inside a scan) serves the warm-up, in chunks of 25 steps that move the
step size towards an acceptance rate of 0.8 and then set a diagonal mass matrix from the warm-up
draws, and the sampling. The likelihood uses every s-th sample of the window (at most
:data:`MAX_SAMPLES`): with AR(1) noise the information of neighbouring samples overlaps, and the
thinned residuals follow an AR(1) with coefficient phi^s.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._core import _ansatz_curve
from ._params import DAMPING, Constants, TraceCoords, ansatz_v0, unit_of

#: the posterior uses every s-th sample of the fit window, at most this many (the AR(1) noise
#: model holds for the thinned residuals too, with coefficient phi^s)
MAX_SAMPLES = 4096

#: the priors, for the docs and the report
PRIORS = {
    "damping constant c (free)": "log c ~ Normal(log c_guess, 3), c_guess from the turning points",
    "w0": "Normal(w_turn, 0.05 w_turn), w_turn the turning points' frequency",
    "offset": "Normal(offset of the least-squares fit, A)",
    "x0, y = A sin(phi)": "Normal(least-squares value, 2 A)",
    "sigma (AR(1) innovation sd)": "log sigma ~ Normal(log rms of the fit, 2)",
    "phi_n (AR(1) coefficient)": "atanh phi_n ~ Normal(0, 2)",
    "k3 (free)": "k3 A^2/(m w0^2) ~ Normal(0, 0.5) (|k3| A^2/(m w0^2) ~ 1 is far beyond the "
                 "harmonic balance of docs/cubic_stiffness.md)",
}


@dataclass
class Posterior:
    """Posterior draws of a trace fit (:func:`posterior`).

    Attributes:
        draws: xarray Dataset, one variable per parameter (the free damping constants, k3
            when free, w0, offset, x0, v0, sigma, phi_noise), dims (chain, draw): the ArviZ
            layout.
        free: the sampled constants (the damping constants, then k3 when free).
        fit: the least-squares :class:`FitResult` it started from.
        units, per_mass: as the fit's.
        accept_rate, divergences, step_size, seconds: sampler diagnostics.
    """

    draws: object
    free: tuple
    fit: object
    units: str = "m"
    per_mass: bool = False
    accept_rate: float = math.nan
    divergences: int = 0
    step_size: float = math.nan
    seconds: float = math.nan
    stride: int = 1
    priors: dict = field(default_factory=lambda: dict(PRIORS))

    def summary(self, level: float = 0.95) -> dict:
        """{name: {"mean", "lo", "hi", "r_hat", "ess"}}: the posterior mean, the central
        ``level`` interval, split R-hat and the effective sample size (blackjax.diagnostics)."""
        from blackjax.diagnostics import effective_sample_size, potential_scale_reduction

        if not 0.0 < level < 1.0:
            raise ValueError(f"level must be in (0, 1), got {level!r}")
        out = {}
        for name in self.draws.data_vars:
            a = np.asarray(self.draws[name].values, dtype=float)
            q = np.quantile(a, [0.5 - 0.5 * level, 0.5 + 0.5 * level])
            rhat = float(potential_scale_reduction(jnp.asarray(a))) if a.shape[0] > 1 \
                else math.nan
            ess = float(effective_sample_size(jnp.asarray(a)))
            out[name] = {"mean": float(a.mean()), "lo": float(q[0]), "hi": float(q[1]),
                         "r_hat": rhat, "ess": ess}
        return out

    def report(self, level: float = 0.95) -> str:
        """The summary as text, with the sampler's diagnostics and the priors."""
        s = self.summary(level)
        nc, nd = self.draws.sizes["chain"], self.draws.sizes["draw"]
        lines = [f"[[Posterior]] NUTS (blackjax), {nc} chains x {nd} draws, AR(1) noise; "
                 f"accept rate {self.accept_rate:.2f}, {self.divergences} divergences, "
                 f"{self.seconds:.1f} s"
                 + (f"; 1 sample in {self.stride}" if self.stride > 1 else ""),
                 f"    {'':<10} {'mean':>12} {f'{100 * level:g} % interval':>28} "
                 f"{'r_hat':>6} {'ess':>7}"]
        for name, row in s.items():
            unit = unit_of(name, self.units, self.per_mass) if name in DAMPING or name in (
                "w0", "offset", "x0", "v0") else ("" if name == "phi_noise" else self.units)
            lines.append(f"    {name + ':':<10} {row['mean']:>12.6g} [{row['lo']:>12.6g}, "
                         f"{row['hi']:>12.6g}] {row['r_hat']:>6.3f} {row['ess']:>7.0f} {unit}"
                         .rstrip())
        bad = [n for n, row in s.items() if not row["r_hat"] < 1.05]
        if bad:
            lines.append(f"    warning: r_hat >= 1.05 for {', '.join(bad)}: the chains disagree")
        return "\n".join(lines)

    def to_netcdf(self, path) -> Path:
        """Write the draws as netCDF (scipy backend, no _FillValue on the coordinates chain
        and draw, as CF asks); returns the path."""
        from .._io import write_netcdf

        return write_netcdf(self.draws, path)

    def corner(self, path, *, names=None) -> Path:
        """Save a corner plot (pairwise scatter and histograms) of the damping constants (or
        ``names``); ``dampax._plot.plot_corner``."""
        from .._plot import plot_corner

        names = list(names) if names is not None else list(self.free)
        return plot_corner(self.draws, names, path,
                           units={n: unit_of(n, self.units, self.per_mass) for n in names})


class _Cfg(NamedTuple):
    """Static layout of theta: the free constants and which of w0, offset are sampled."""

    free: tuple  # the sampled damping constants (k3 is vary_k3)
    vary_w0: bool
    vary_off: bool
    vary_k3: bool = False


class _Data(NamedTuple):
    """What the log posterior needs besides theta (traced: one compilation per shape)."""

    t: jax.Array
    x: jax.Array
    fixed: jax.Array  # mu, b, D, w0, offset of the fit (the values of what is not sampled)
    consts: Constants
    span: jax.Array
    centre: jax.Array
    width: jax.Array
    theta_map: jax.Array
    L: jax.Array


#: chunk length of the warm-up and the sampling scans (one compiled program for both)
CHUNK = 25


def _unpack(theta, data: _Data, cfg: _Cfg):
    vals = {c: data.fixed[i] for i, c in enumerate(DAMPING)}
    for i, c in enumerate(cfg.free):
        vals[c] = jnp.exp(theta[i])
    j = len(cfg.free)
    w0 = theta[j] if cfg.vary_w0 else data.fixed[3]
    j += int(cfg.vary_w0)
    off = theta[j] if cfg.vary_off else data.fixed[4]
    j += int(cfg.vary_off)
    k3 = theta[j] if cfg.vary_k3 else None  # None: the linear spring's curve, as without k3
    j += int(cfg.vary_k3)
    q = TraceCoords(mu=vals["mu"], b=vals["b"], D=vals["D"], w0=w0, offset=off,
                    x0=theta[j], y=theta[j + 1])
    return q, jnp.exp(theta[j + 2]), jnp.tanh(theta[j + 3]), k3


def _logpost(theta, data: _Data, cfg: _Cfg):
    """log prior + exact stationary AR(1) log likelihood of the residuals."""
    q, sigma, phi, k3 = _unpack(theta, data, cfg)
    consts = data.consts._replace(k3=k3) if cfg.vary_k3 else data.consts
    rr = data.x - _ansatz_curve(data.t - data.t[0], q, consts, data.span, None)
    e = rr[1:] - phi * rr[:-1]
    n = rr.shape[0]
    ll = (-0.5 * jnp.sum(e * e) / sigma ** 2 - 0.5 * rr[0] ** 2 * (1 - phi ** 2) / sigma ** 2
          - n * jnp.log(sigma) + 0.5 * jnp.log1p(-phi ** 2))
    lp = -0.5 * jnp.sum(((theta - data.centre) / data.width) ** 2)
    out = ll + lp
    return jnp.where(jnp.isfinite(out), out, -jnp.inf)


@functools.partial(jax.jit, static_argnames=("cfg",))
def _neg_value_and_grad(theta, data, cfg):
    return jax.value_and_grad(lambda th: -_logpost(th, data, cfg))(theta)


@functools.partial(jax.jit, static_argnames=("cfg",))
def _neg_hessian(theta, data, cfg):
    return jax.hessian(lambda th: -_logpost(th, data, cfg))(theta)


def _logdensity(u, data, cfg):
    return _logpost(data.theta_map + data.L @ u, data, cfg)


@functools.partial(jax.jit, static_argnames=("cfg", "nch"))
def _chunk(states, keys, step_size, imm, data, cfg, nch):
    """CHUNK NUTS steps of every chain (vmapped) in one scan: the warm-up and the sampling
    share this program (step size and the diagonal inverse mass matrix are arguments)."""
    import blackjax

    kernel = blackjax.nuts.build_kernel()

    def logdensity(u):
        return _logdensity(u, data, cfg)

    def one(st, k):
        ks = jax.random.split(k, nch)
        st, info = jax.vmap(lambda kk, ss: kernel(kk, ss, logdensity, step_size, imm,
                                                  max_num_doublings=6))(ks, st)
        return st, (st.position, info.acceptance_rate, info.is_divergent)

    return jax.lax.scan(one, states, keys)


def _layout(free, cfg: _Cfg):
    """Names of the entries of theta, in order."""
    names = [f"log_{c}" for c in free]
    if cfg.vary_w0:
        names.append("w0")
    if cfg.vary_off:
        names.append("offset")
    if cfg.vary_k3:
        names.append("k3")
    return names + ["x0", "y", "log_sigma", "atanh_phi"]


def posterior(trace_or_t, x=None, *, oscillator=None, free=("mu", "D"), model: str = "ansatz",
              fit_omega0: bool | None = None, offset: bool = True, start="auto", end=None,
              num_samples: int = 1000, num_chains: int = 4, num_warmup: int = 500,
              seed: int = 0, units: str | None = None, start_fit=None,
              progress: bool = False) -> Posterior:
    """Sample the posterior of the free damping constants (and the nuisance parameters) with
    NUTS from blackjax, on log-parameters, with AR(1) noise (see the module doc for the model
    and the priors).

    Arguments:
        trace_or_t, x, oscillator, free, fit_omega0, offset, start, end, units: as in
            :func:`~dampax.fit` (no oscillator: per unit mass, w0 sampled). ``free`` may
            include "k3" (the cubic stiffness, sampled on its own scale; the start fit then
            profiles it, as ``dp.fit(free=(..., "k3"))`` does).
        model: "ansatz" (the only model sampled).
        num_samples, num_chains, num_warmup: draws per chain, chains, warm-up steps.
        seed: random seed.
        start_fit: a :class:`FitResult` of the same data and options to start from (default:
            ``fit(...)`` is run).
        progress: show a tqdm bar over the sampling (stderr).

    Returns:
        A :class:`Posterior`.
    """
    import blackjax
    import xarray as xr
    from scipy.optimize import minimize
    from tqdm import tqdm

    from ._api import fit
    from ._params import FREE, check_free

    if model != "ansatz":
        raise ValueError(f"model must be 'ansatz' for the posterior, got {model!r}")
    for name, value, low in (("num_samples", num_samples, 10), ("num_chains", num_chains, 1),
                             ("num_warmup", num_warmup, 10)):
        if isinstance(value, bool) or int(value) != value or value < low:
            raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    names_in = check_free(free, allowed=FREE)
    vary_k3 = "k3" in names_in
    free = tuple(c for c in names_in if c != "k3")  # the damping constants
    if not free:
        raise ValueError("free: name at least one damping constant")
    began = time.perf_counter()
    res = start_fit if start_fit is not None else fit(
        trace_or_t, x, oscillator=oscillator, free=free + ("k3",) * vary_k3,
        fit_omega0=fit_omega0, offset=offset,
        start=start, end=end, units=units, seed=seed)
    if tuple(res.free) != free + ("k3",) * vary_k3 or res.model != "ansatz":
        raise ValueError("start_fit must be an ansatz fit with the same free constants")
    stride = max(1, math.ceil(len(res.t) / MAX_SAMPLES))
    t = jnp.asarray(res.t[::stride])
    xd = jnp.asarray(res.x[::stride])
    t0 = float(res.t[0])
    span = float(res.t[-1] - t0)
    m, g = res.fixed["m"], res.fixed["g"]
    vary_w0 = "w0" in res.varied
    vary_off = "offset" in res.varied

    cfg = _Cfg(free=tuple(free), vary_w0=vary_w0, vary_off=vary_off, vary_k3=vary_k3)
    names = _layout(free, cfg)
    p = res.params
    A = res.derived["A"]
    y_hat = A * math.sin(res.derived["phi"])
    x0_hat = A * math.cos(res.derived["phi"])
    r = np.asarray(res.residuals)[::stride]
    phi_hat = float(np.clip(np.corrcoef(r[:-1], r[1:])[0, 1], -0.9, 0.995))
    sig_hat = float(np.std(r[1:] - phi_hat * r[:-1])) or 1e-12
    w_cross = p["w0"] / (1.0 + float(res.diagnostics.get("w0/turning - 1", 0.0)))
    # prior centres and widths, and the start (theta at the least-squares fit)
    centre, width, theta0 = [], [], []
    for c in free:
        guess = max(float(res.init.get(c, p[c])), 1e-30)
        centre.append(math.log(guess))
        width.append(3.0)
        theta0.append(math.log(max(p[c], guess * 1e-6)))
    if vary_w0:
        centre.append(w_cross)
        width.append(0.05 * w_cross)
        theta0.append(p["w0"])
    if vary_off:
        centre.append(p["offset"])
        width.append(A)
        theta0.append(p["offset"])
    if vary_k3:  # k3 A^2/(m w0^2) ~ N(0, 0.5), started at the profiled fit's k3
        centre.append(0.0)
        width.append(0.5 * float(m) * p["w0"] ** 2 / A ** 2)
        theta0.append(p["k3"])
    centre += [x0_hat, y_hat, math.log(float(np.sqrt(np.mean(r * r))) or 1e-12), 0.0]
    width += [2 * A, 2 * A, 2.0, 2.0]
    theta0 += [x0_hat, y_hat, math.log(sig_hat), math.atanh(phi_hat)]
    dim = len(names)
    data = _Data(t=t, x=xd, fixed=jnp.asarray([p[c] for c in (*DAMPING, "w0", "offset")]),
                 consts=Constants(m=jnp.asarray(float(m)), g=jnp.asarray(float(g))),
                 span=jnp.asarray(span), centre=jnp.asarray(centre),
                 width=jnp.asarray(width), theta_map=jnp.zeros(dim), L=jnp.eye(dim))

    def f(th):
        v, gr = _neg_value_and_grad(jnp.asarray(th), data, cfg)
        v = float(v)
        return (v, np.asarray(gr, dtype=float)) if math.isfinite(v) else (1e300, np.zeros_like(th))

    opt = minimize(f, np.asarray(theta0, dtype=float), jac=True, method="L-BFGS-B",
                   options={"maxiter": 500})
    theta_map = jnp.asarray(opt.x)
    H = np.asarray(_neg_hessian(theta_map, data, cfg), dtype=float)
    H = 0.5 * (H + H.T)
    ev, V = np.linalg.eigh(H)
    ev = np.clip(ev, max(ev.max(), 1e-300) * 1e-12, None)
    cov = (V / ev) @ V.T
    L = np.linalg.cholesky(cov + 1e-300 * np.eye(dim))
    data = data._replace(theta_map=theta_map, L=jnp.asarray(L))

    key = jax.random.PRNGKey(int(seed))
    k_warm, k_init, k_sample = jax.random.split(key, 3)
    nch = int(num_chains)

    def logdensity(u):
        return _logdensity(u, data, cfg)

    starts = 0.5 * jax.random.normal(k_init, (nch, dim))
    states = jax.vmap(lambda u: blackjax.nuts.init(u, logdensity))(starts)
    # warm-up in chunks: the step size moves towards an acceptance rate of 0.8, and after the
    # first half the diagonal mass matrix is the variance of the draws of u (nearly 1 when the
    # Laplace preconditioning is good)
    step, imm = 0.8, jnp.ones(dim)
    n_w = max(math.ceil(int(num_warmup) / CHUNK), 2)
    n_s = math.ceil(int(num_samples) / CHUNK)
    bar = tqdm(total=n_w + n_s, desc="posterior", unit="chunk", disable=not progress)
    warm_keys = jax.random.split(k_warm, n_w * CHUNK).reshape(n_w, CHUNK, -1)
    warm_pos = []
    for i in range(n_w):
        states, (pp, aa, _) = _chunk(states, warm_keys[i], step, imm, data, cfg, nch)
        acc_w = float(np.mean(np.asarray(aa)))
        step = float(np.clip(step * math.exp(2.0 * (acc_w - 0.8)), 1e-4, 2.0))
        if i >= n_w // 2:
            warm_pos.append(np.asarray(pp).reshape(-1, dim))
        if i == (3 * n_w) // 4 and warm_pos:
            var = np.var(np.concatenate(warm_pos), axis=0)
            imm = jnp.asarray(np.clip(var, 1e-4, 1e4))
        bar.update()
    keys = jax.random.split(k_sample, n_s * CHUNK).reshape(n_s, CHUNK, -1)
    pos, acc, div = [], [], []
    for i in range(n_s):
        states, (pp, aa, dd) = _chunk(states, keys[i], step, imm, data, cfg, nch)
        pos.append(np.asarray(pp))
        acc.append(np.asarray(aa))
        div.append(np.asarray(dd))
        bar.update()
    bar.close()
    ns = int(num_samples)
    U = np.concatenate(pos, axis=0)[:ns]  # (draw, chain, dim)
    theta = np.asarray(theta_map)[None, None, :] + U @ np.asarray(L).T
    theta = np.transpose(theta, (1, 0, 2))  # (chain, draw, dim)
    draws = {}
    flat = theta.reshape(-1, dim)
    q, sigma, phi_n, k3s = jax.vmap(lambda th: _unpack(th, data, cfg))(jnp.asarray(flat))
    shape = theta.shape[:2]
    for c in free:
        draws[c] = np.asarray(getattr(q, c)).reshape(shape)
    if vary_k3:
        draws["k3"] = np.asarray(k3s).reshape(shape)
    draws["w0"] = np.broadcast_to(np.asarray(q.w0), (flat.shape[0],)).reshape(shape)
    draws["offset"] = np.broadcast_to(np.asarray(q.offset), (flat.shape[0],)).reshape(shape)
    draws["x0"] = np.asarray(q.x0).reshape(shape)
    v0 = ansatz_v0(q.x0, q.y, q.mu, q.b, q.D, q.w0, m, g)
    draws["v0"] = np.asarray(v0).reshape(shape)
    draws["sigma"] = np.asarray(sigma).reshape(shape)
    draws["phi_noise"] = np.asarray(phi_n).reshape(shape)
    ds = xr.Dataset({k: (("chain", "draw"), np.array(v, dtype=float)) for k, v in draws.items()},
                    coords={"chain": np.arange(shape[0]), "draw": np.arange(shape[1])},
                    attrs={"model": "ansatz + AR(1) noise", "sampler": "blackjax NUTS",
                           "units": res.units, "per_mass": int(res.per_mass),
                           "free": ",".join(names_in), "t_start": t0,
                           "priors": "; ".join(f"{k}: {v}" for k, v in PRIORS.items())})
    return Posterior(draws=ds, free=names_in, fit=res, units=res.units,
                     per_mass=res.per_mass, accept_rate=float(np.mean(np.concatenate(acc))),
                     divergences=int(np.sum(np.concatenate(div))),
                     step_size=step,
                     seconds=time.perf_counter() - began, stride=stride)
