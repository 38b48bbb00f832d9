"""Global sensitivity: Sobol' first-order and total indices and DGSM over ranges of parameters.

:func:`global_sensitivity` answers "which damping constant matters over this whole range of
values", where a derivative (:func:`dampax.sensitivity`) answers "what happens for a small
change here". It draws the Saltelli design (two scrambled-Sobol' matrices A, B and the k
matrices AB_i), evaluates one model of :func:`dampax.solve` on every row as vmapped batches,
and estimates

- S1_i = mean(f(B) (f(AB_i) - f(A))) / V                  (Saltelli et al. 2010, eq. (b) of Table 2)
- ST_i = mean((f(A) - f(AB_i))^2) / (2 V)                 (Jansen 1999; Saltelli et al. 2010)
- DGSM_i = nu_i (hi_i - lo_i)^2 / (pi^2 V), nu_i = mean((df/dtheta_i)^2 over A)
                                                          (Sobol' & Kucherenko 2009, 2010)

with V the variance of f over the rows of A and B, outputs centred first. DGSM_i is the
derivative-based upper bound of ST_i for uniform inputs (ST_i <= DGSM_i), from autodiff
gradients. Confidence half-widths come from a bootstrap over the rows (as SALib's
``sobol.analyze``, whose sample layout and estimators these are: the same outputs give the
same S1 and ST).

References:
    A. Saltelli, P. Annoni, I. Azzini, F. Campolongo, M. Ratto, S. Tarantola, Variance based
    sensitivity analysis of model output. Design and estimator for the total sensitivity
    index, Comput. Phys. Commun. 181, 259-270 (2010).
    M. J. W. Jansen, Analysis of variance designs for model output, Comput. Phys. Commun.
    117, 35-43 (1999).
    I. M. Sobol' and S. Kucherenko, Derivative based global sensitivity measures and their
    link with global sensitivity indices, Math. Comput. Simul. 79, 3009-3017 (2009); A new
    derivative based importance criterion for groups of variables and its link with the
    global sensitivity indices, Comput. Phys. Commun. 181, 1212-1217 (2010).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._models._registry import METHODS
from .._oscillator import Oscillator, check_finite, is_concrete
from .._solve import solve
from ._sensitivity import PARAMETERS, UNITS, with_values

Array = jax.Array

#: The named quantities of :func:`global_sensitivity`.
QUANTITIES = ("halt_time", "halt_position", "energy", "x", "max_error")
_NEEDS_T = ("energy", "x")
_POSITIVE = ("m", "k", "g")  # fields that must stay > 0; mu, b, D must stay >= 0
_MIN_N = 16


def check_bounds(bounds) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    """Validate ``bounds`` = {name: (lo, hi)}; returns (names, lows, highs)."""
    if not isinstance(bounds, Mapping) or not bounds:
        raise ValueError(f"bounds must be a non-empty dict {{name: (lo, hi)}} with names from "
                         f"{PARAMETERS}, got {bounds!r}")
    names, lows, highs = [], [], []
    for name, pair in bounds.items():
        if name not in PARAMETERS:
            raise ValueError(f"bounds: unknown parameter {name!r}; choose from {PARAMETERS}")
        try:
            lo, hi = (float(v) for v in pair)
        except (TypeError, ValueError):
            raise ValueError(f"bounds[{name!r}] must be a pair (lo, hi) of numbers, "
                             f"got {pair!r}") from None
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError(f"bounds[{name!r}] must be finite, got ({lo}, {hi})")
        if lo >= hi:
            raise ValueError(f"bounds[{name!r}]: need lo < hi, got ({lo}, {hi})")
        if name in _POSITIVE and lo <= 0.0:
            raise ValueError(f"bounds[{name!r}]: {name} must be > 0, got lo = {lo}")
        if name in ("mu", "b", "D") and lo < 0.0:
            raise ValueError(f"bounds[{name!r}]: damping constants cannot be negative, "
                             f"got lo = {lo}")
        names.append(name)
        lows.append(lo)
        highs.append(hi)
    return tuple(names), np.asarray(lows), np.asarray(highs)


def _check_int(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def saltelli_design(lows, highs, n: int, seed: int) -> np.ndarray:
    """Saltelli's design in SALib's row order (without second order).

    Arguments:
        lows, highs: bounds of the k parameters.
        n: base samples (a power of 2 keeps the Sobol' sequence balanced).
        seed: seed of the scrambling.

    Returns:
        X of shape (n (k + 2), k): for each base row i the rows A_i, AB_i1, ..., AB_ik, B_i,
        where A, B are the two halves of a scrambled Sobol' sample of dimension 2k and AB_ij is
        A_i with its column j taken from B_i.
    """
    from scipy.stats import qmc

    lows, highs = np.asarray(lows, dtype=float), np.asarray(highs, dtype=float)
    k = lows.size
    sampler = qmc.Sobol(d=2 * k, scramble=True, seed=seed)
    with warnings.catch_warnings():  # n not a power of 2: still a valid (less balanced) design
        warnings.simplefilter("ignore", UserWarning)
        base = sampler.random(n)
    A = lows + (highs - lows) * base[:, :k]
    B = lows + (highs - lows) * base[:, k:]
    blocks = [A]
    for j in range(k):
        AB = A.copy()
        AB[:, j] = B[:, j]
        blocks.append(AB)
    blocks.append(B)
    return np.stack(blocks, axis=1).reshape(n * (k + 2), k)


def _indices(fA, fB, fAB):
    """S1 (Saltelli 2010) and ST (Jansen 1999) from outputs; fAB has shape (k, ...) + fA.shape."""
    V = jnp.var(jnp.concatenate([fA, fB], axis=-1), axis=-1)
    safe = jnp.where(V > 0.0, V, 1.0)
    S1 = jnp.mean(fB * (fAB - fA), axis=-1) / safe
    ST = 0.5 * jnp.mean((fA - fAB) ** 2, axis=-1) / safe
    return jnp.where(V > 0.0, S1, 0.0), jnp.where(V > 0.0, ST, 0.0)


@jax.jit
def _estimate(Y, index, z):
    """Indices and bootstrap half-widths from Y of shape (n, k + 2) (SALib's layout)."""
    Y = Y - jnp.mean(Y)
    fA, fB, fAB = Y[:, 0], Y[:, -1], Y[:, 1:-1].T
    S1, ST = _indices(fA, fB, fAB)
    # index: (R, n) row draws; each resample gives (k,) indices
    S1r, STr = jax.vmap(lambda r: _indices(fA[r], fB[r], fAB[:, r]))(index)
    ok = jnp.ptp(jnp.concatenate([fA[index], fB[index]], axis=None)) > 0.0
    conf = lambda s: jnp.where(ok, z * jnp.std(s, axis=0, ddof=1), 0.0)  # noqa: E731
    return S1, ST, conf(S1r), conf(STr)


def sobol_indices(function: Callable[[Array], Array], lows, highs, names, *, n: int = 4096,
                  seed: int = 0, num_resamples: int = 100, conf_level: float = 0.95,
                  dgsm: bool = True, batch_size: int = 4096,
                  gradient: Callable[[Array], Array] | None = None, attrs=None):
    """Sobol' S1, ST, their bootstrap half-widths and DGSM of a scalar function of k inputs.

    The engine of :func:`global_sensitivity` (estimators in this module's docstring).

    Arguments:
        function: a jittable map from one input vector of shape (k,) to a scalar.
        lows, highs: the uniform ranges of the inputs.
        names: the k input names (the ``parameter`` coordinate).
        n: base samples; n (k + 2) evaluations of ``function`` (plus n gradients for DGSM).
        seed: seed of the design's scrambling and of the bootstrap.
        num_resamples: bootstrap resamples (>= 2).
        conf_level: confidence level of the half-widths, in (0, 1).
        dgsm: compute DGSM (one forward-mode gradient per row of A).
        batch_size: rows per vmapped call (the last batch is padded).
        gradient: map from an input vector to df/dx of shape (k,) (default: ``jax.jacfwd``).
        attrs: extra attributes of the result.

    Returns:
        xarray.Dataset with dimension ``parameter`` and variables S1, ST, S1_conf, ST_conf,
        DGSM, nu (mean squared derivative), lower, upper; and dimension ``sample`` with X
        (the design, SALib's row order) and Y (the outputs): ``SALib.analyze.sobol.analyze(
        problem, ds.Y.values, calc_second_order=False)`` gives the same S1 and ST.

    Raises:
        ValueError: bad n, num_resamples, conf_level, batch_size; a non-finite output.
    """
    import xarray as xr
    from scipy.stats import norm

    n = _check_int("n", n, _MIN_N)
    seed = _check_int("seed", seed, 0)
    num_resamples = _check_int("num_resamples", num_resamples, 2)
    batch_size = _check_int("batch_size", batch_size, 1)
    if not (isinstance(conf_level, float | int) and 0.0 < conf_level < 1.0):
        raise ValueError(f"conf_level must be in (0, 1), got {conf_level!r}")
    lows, highs = np.asarray(lows, dtype=float), np.asarray(highs, dtype=float)
    k = lows.size
    X = saltelli_design(lows, highs, n, seed)
    Y = _batched(_apply_batch, function, X, batch_size)
    bad = ~np.isfinite(Y)
    if np.any(bad):
        i = int(np.argmax(bad))
        at = ", ".join(f"{nm} = {X[i, j]:.6g}" for j, nm in enumerate(names))
        raise ValueError(f"quantity: not finite at {int(bad.sum())} of {Y.size} samples "
                         f"(e.g. {Y[i]} at {at}); narrow the bounds (a model that never halts, "
                         f"mu = 0 or the reference before its t_end, has an infinite halt "
                         f"time; NaN where the model does not exist)")
    rng = np.random.default_rng(seed)
    index = rng.integers(n, size=(num_resamples, n))
    z = float(norm.ppf(0.5 + conf_level / 2.0))
    S1, ST, S1c, STc = (np.asarray(a) for a in _estimate(jnp.asarray(Y.reshape(n, k + 2)),
                                                          jnp.asarray(index), z))
    var = float(np.var(np.concatenate([Y.reshape(n, k + 2)[:, 0], Y.reshape(n, k + 2)[:, -1]])))
    if dgsm:
        G = _batched(_grad_batch if gradient is None else _apply_batch,
                     function if gradient is None else gradient,
                     X.reshape(n, k + 2, k)[:, 0], batch_size)
        nu = np.mean(G**2, axis=0)
        dg = nu * (highs - lows) ** 2 / (math.pi**2 * var) if var > 0.0 else np.zeros(k)
    else:
        nu = dg = np.full(k, np.nan)
    names = list(names)
    ds = xr.Dataset(
        {"S1": ("parameter", S1, dict(long_name="first-order Sobol' index (Saltelli 2010)")),
         "ST": ("parameter", ST, dict(long_name="total Sobol' index (Jansen 1999)")),
         "S1_conf": ("parameter", S1c, dict(long_name=f"bootstrap {conf_level:g} half-width "
                                                      "of S1")),
         "ST_conf": ("parameter", STc, dict(long_name=f"bootstrap {conf_level:g} half-width "
                                                      "of ST")),
         "DGSM": ("parameter", dg, dict(long_name="DGSM upper bound of ST, nu (hi - lo)^2 / "
                                                  "(pi^2 V) (Sobol' & Kucherenko)")),
         "nu": ("parameter", nu, dict(long_name="mean squared derivative E[(df/dtheta)^2]")),
         "lower": ("parameter", lows), "upper": ("parameter", highs),
         "X": (("sample", "parameter"), X), "Y": ("sample", Y)},
        coords={"parameter": names},
        attrs=dict(n=n, seed=seed, evaluations=int(Y.size), variance=var,
                   mean=float(np.mean(Y)), num_resamples=num_resamples,
                   conf_level=float(conf_level),
                   estimators="S1: Saltelli et al. 2010; ST: Jansen 1999; DGSM: Sobol' & "
                              "Kucherenko 2009; outputs centred; scrambled Sobol' design in "
                              "SALib's order (A, AB_1..AB_k, B)",
                   **(attrs or {})))
    return ds


@eqx.filter_jit
def _apply_batch(function, X):
    return jax.vmap(function)(X)


@eqx.filter_jit
def _grad_batch(function, X):
    return jax.vmap(jax.jacfwd(function))(X)


def _batched(compiled, function, X: np.ndarray, batch_size: int) -> np.ndarray:
    """compiled(function, rows of X) in batches of a fixed size (the last one padded), so one
    program serves every batch."""
    size = min(batch_size, X.shape[0])
    out = []
    for start in range(0, X.shape[0], size):
        chunk = X[start:start + size]
        m = chunk.shape[0]
        if m < size:
            chunk = np.concatenate([chunk, np.repeat(chunk[-1:], size - m, axis=0)])
        out.append(np.asarray(compiled(function, jnp.asarray(chunk)))[:m])
    return np.concatenate(out)


class _Model(eqx.Module):
    """The quantity of one model as a function of the parameter vector (a pytree: jit keys on
    its static fields, so a new oscillator or start re-uses the compiled program)."""

    osc: Oscillator
    x0: Array
    v0: Array
    t: Array
    names: tuple[str, ...] = eqx.field(static=True)
    method: str = eqx.field(static=True)
    options: tuple = eqx.field(static=True)
    quantity: object = eqx.field(static=True)
    samples: int = eqx.field(static=True)

    def __call__(self, p):
        osc, x0, v0 = with_values(self.osc, self.x0, self.v0, self.names, p)
        options = dict(self.options)
        q = self.quantity
        if q == "max_error":
            ts = jnp.linspace(0.0, self.t, self.samples)
            ref_options = {key: v for key, v in options.items() if key in _REFERENCE_KEYS}
            model_options = {key: v for key, v in options.items()
                             if key not in _REFERENCE_KEYS}
            sol = solve(osc, x0, v0, method=self.method, **model_options)
            ref = solve(osc, x0, v0, method="reference",
                        **dict(dict(t_end=self.t, adjoint="forward"), **ref_options))
            A0 = jnp.sqrt(x0**2 + (v0 / osc.omega0) ** 2)
            return jnp.max(jnp.abs(sol.x(ts) - ref.x(ts))) / A0
        sol = solve(osc, x0, v0, method=self.method, **options)
        if callable(q):
            return jnp.asarray(q(sol), dtype=float)
        if q == "halt_time":
            return sol.halt_time
        if q == "halt_position":
            return sol.halt_position
        if q == "energy":
            return sol.energy(self.t)
        return sol.x(self.t)


# options of the reference integrator (for max_error they go to the reference, the rest to the
# model)
_REFERENCE_KEYS = ("t_end", "rtol", "atol", "max_swings", "max_steps_per_swing", "solver",
                   "adjoint")


def global_sensitivity(*, bounds: Mapping[str, tuple[float, float]], oscillator: Oscillator,
                       x0, v0, quantity: str | Callable = "halt_time", method: str = "ansatz",
                       n: int = 4096, seed: int = 0, t=None, samples: int | None = None,
                       num_resamples: int = 100, conf_level: float = 0.95, dgsm: bool = True,
                       batch_size: int = 4096, **solve_options):
    """Sobol' indices S1, ST (with bootstrap half-widths) and DGSM of a model's quantity.

    Every parameter named in ``bounds`` is uniform on its (lo, hi), the others are those of
    ``oscillator``, ``x0``, ``v0``. The model ``dampax.solve(..., method=method,
    **solve_options)`` is evaluated on Saltelli's design, n (k + 2) rows for k parameters, as
    vmapped batches, and

        S1_i = mean(f(B) (f(AB_i) - f(A))) / V         (Saltelli et al. 2010)
        ST_i = mean((f(A) - f(AB_i))^2) / (2 V)        (Jansen 1999)
        DGSM_i = E[(df/dtheta_i)^2] (hi_i - lo_i)^2 / (pi^2 V)   (Sobol' & Kucherenko 2009)

    with V the variance of f over A and B (full references in the module docstring). S1_i is
    the share of the variance explained by theta_i alone, ST_i the share it takes part in
    (interactions included; sum S1 <= 1 <= sum ST up to sampling error); DGSM_i >= ST_i is the
    derivative-based bound, from forward-mode autodiff gradients at the rows of A. A quantity
    with jumps (the reference's halt time) has derivatives that miss the jumps: its DGSM is then
    no bound (compare with ST).

    Arguments:
        bounds: {name: (lo, hi)} for any of "m", "k", "mu", "b", "D", "g", "x0", "v0";
            lo < hi, finite; m, k, g > 0 and mu, b, D >= 0 on the whole range.
        oscillator: the :class:`~dampax.Oscillator` for the parameters not in ``bounds``
            (scalar).
        x0, v0: initial displacement [m] and velocity [m/s] (scalars; used unless in bounds).
        quantity: "halt_time" [s], "halt_position" [m], "energy" (E(t) [J] at time ``t``), "x"
            (x(t) [m] at time ``t``), "max_error" (max |x - x_ref| / A0 of ``method`` against
            the reference on ``samples`` times in [0, t], A0 = sqrt(x0^2 + (v0/w0)^2)), or a
            callable ``solution -> scalar`` (jittable, e.g. ``lambda s: s.x(1.0) ** 2``).
        method: the model, as in :func:`dampax.solve` ("ansatz", "reference", ...).
        n: base samples, >= 16 (a power of 2 keeps the scrambled Sobol' design balanced).
        seed: seed of the design and of the bootstrap (results are reproducible).
        t: time [s] of "x" and "energy" (required there); end of the comparison window of
            "max_error" (default 10 undamped periods of ``oscillator``).
        samples: times of the "max_error" window (default 200).
        num_resamples: bootstrap resamples for the half-widths (default 100).
        conf_level: confidence level of S1_conf, ST_conf (default 0.95).
        dgsm: compute DGSM (default True; n forward-mode gradients).
        batch_size: rows per vmapped call (default 4096; lower it to bound memory).
        **solve_options: passed to :func:`dampax.solve` (phase, tail, ... ; for the reference,
            and for "max_error" its reference: t_end, rtol, atol, max_swings, ...).

    Returns:
        xarray.Dataset with dimension ``parameter`` (the names of ``bounds``, in order) and
        variables S1, ST, S1_conf, ST_conf (bootstrap half-widths), DGSM, nu (the mean squared
        derivative), lower, upper; the design X (sample, parameter) and outputs Y (sample) in
        SALib's order (A, AB_1, ..., AB_k, B per base row); attrs with n, seed, quantity,
        method, variance, evaluations.

    Raises:
        ValueError: unknown bound name, lo >= hi, non-finite or out-of-domain bounds; n < 16;
            unknown quantity or method; "x"/"energy" without t; a non-scalar oscillator; a
            quantity that is not finite on some sample (e.g. a halt time where mu = 0, or an
            ansatz without admissible amplitude), with the parameters of one such sample.
    """
    names, lows, highs = check_bounds(bounds)
    if not isinstance(oscillator, Oscillator):
        raise TypeError(f"oscillator must be a dampax.Oscillator, got "
                        f"{type(oscillator).__name__}")
    for name, value in (("oscillator", oscillator), ("x0", x0), ("v0", v0)):
        if any(jnp.ndim(leaf) for leaf in jax.tree_util.tree_leaves(value)):
            raise ValueError(f"{name}: global_sensitivity needs scalars (the ranges go in "
                             f"bounds)")
    check_finite("x0", x0)
    check_finite("v0", v0)
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if not (callable(quantity) or quantity in QUANTITIES):
        raise ValueError(f"quantity must be one of {QUANTITIES} or a callable "
                         f"solution -> scalar, got {quantity!r}")
    if quantity in _NEEDS_T and t is None:
        raise ValueError(f"t: quantity={quantity!r} needs the time t [s]")
    uses = "a callable" if callable(quantity) else repr(quantity)
    if t is not None and quantity not in (*_NEEDS_T, "max_error"):  # (ignored, yet in attrs)
        raise ValueError(f"t: quantity={uses} does not use a time (x, energy and max_error "
                         "do)")
    if samples is not None and quantity != "max_error":
        raise ValueError(f"samples: quantity={uses} does not sample a window (max_error does)")
    if quantity == "max_error":
        if method == "reference":
            raise ValueError("method: max_error compares a model against the reference; "
                             "choose an analytic method")
        if t is None:
            t = 10.0 * 2.0 * math.pi / float(np.asarray(oscillator.omega0))
    samples = _check_int("samples", 200 if samples is None else samples, 2)
    if t is not None:
        check_finite("t", t)
        if is_concrete(t) and (np.ndim(t) != 0 or float(t) < 0.0):
            raise ValueError(f"t must be a scalar time >= 0, got {t!r}")
    options = dict(solve_options)
    if method == "reference":
        options.setdefault("adjoint", "forward")
    model = _Model(osc=oscillator, x0=jnp.asarray(x0, dtype=float),
                   v0=jnp.asarray(v0, dtype=float),
                   t=jnp.asarray(0.0 if t is None else t, dtype=float), names=names,
                   method=method, options=tuple(sorted(options.items())), quantity=quantity,
                   samples=samples)
    # trace once without compiling: bad solve options and a callable quantity that does not
    # give a scalar fail here, with dampax.solve's message
    try:
        out = jax.eval_shape(model, jax.ShapeDtypeStruct((len(names),), jnp.float64))
    except TypeError as err:
        raise ValueError(f"quantity/solve options: {err}") from None
    if out.shape != ():
        raise ValueError(f"quantity must give a scalar, got shape {out.shape}")
    label = quantity if isinstance(quantity, str) else getattr(quantity, "__name__", "callable")
    ds = sobol_indices(model, lows, highs, names, n=n, seed=seed, num_resamples=num_resamples,
                       conf_level=conf_level, dgsm=dgsm, batch_size=batch_size,
                       attrs=dict(quantity=label, method=method,
                                  options=repr(options), t=float("nan") if t is None else
                                  float(t)))
    ds["parameter"].attrs["units"] = [UNITS[nm] for nm in names]
    return ds
