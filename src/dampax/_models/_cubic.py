"""Cubic stiffness k3 in the ansatz (issue 14, docs/cubic_stiffness.md).

The amplitude-dependent phase (harmonic balance), the Lindstedt third harmonic, the matched
amplitude and phase corrected for k3, and `if_cubic`, which spares a linear spring all of it.
"""

from __future__ import annotations

import functools

import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np

from ._decay import _decay_from, _DecayConstants, decay_rate


def _leggauss(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(nodes, weights) of the n-point Gauss--Legendre rule on [-1, 1], by the steps of
    ``np.polynomial.legendre.leggauss(n)`` (whose import, numpy.polynomial, costs 80 ms of
    ``import dampax``): the eigenvalues of the Jacobi matrix of the Legendre recurrence, one
    Newton step on P_n, weights 1 / (P_(n-1) P_n') normalised to sum 2, symmetrised."""
    k = np.arange(1, n)
    x = np.linalg.eigvalsh(np.diag(k / np.sqrt(4.0 * k * k - 1.0), 1), UPLO="U")
    pn, pm = _legendre(n, x)
    df = n * (x * pn - pm) / (x * x - 1.0)  # P_n'
    x = x - pn / df
    fm = _legendre(n, x)[1]
    w = 1.0 / ((fm / np.abs(fm).max()) * (df / np.abs(df).max()))
    w = 0.5 * (w + w[::-1])
    return 0.5 * (x - x[::-1]), w * (2.0 / w.sum())


def _legendre(n: int, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P_n(x), P_(n-1)(x)) by the three-term recurrence (n >= 1)."""
    p0, p1 = np.ones_like(x), x
    for j in range(1, n):
        p0, p1 = p1, ((2 * j + 1) * x * p1 - j * p0) / (j + 1)
    return p1, p0


# ----------------------------------------------------------------------------------------------
# cubic stiffness (issue 14, docs/cubic_stiffness.md): the amplitude-dependent phase
# theta(t) = phi + int_0^t w(A f(s)) ds with w(a) = w0 sqrt(1 + (3/4) (k3/k) a^2) (harmonic
# balance), the first (Lindstedt) harmonic correction A f eps (cos 3 theta - cos theta) with
# eps = (k3/(32 k)) (A f)^2, and the matched amplitude and phase extended to both

#: Gauss--Legendre rules of the phase integral: over t while f changes by less than
#: _F_SWITCH, over f (ds = -df / (a f^2 + b' f + c)) beyond
_GL_T = _leggauss(6)
_GL_F = _leggauss(20)
_F_SWITCH = 0.1
#: :func:`phase_excess_sampled`: an interval over which f falls by more than _F_STEP is
#: integrated over f with this rule (6 nodes: 2.3e-8 of P at worst against scipy's quad, 4
#: nodes 3e-6, 8 nodes 2.2e-8)
_GL_STEP = _leggauss(6)
_F_STEP = 0.002


def excess_frequency(f, w0, kappa):
    """w(A f) - w0 = w0 (sqrt(1 + kappa f^2) - 1), kappa = (3/4) k3 A^2 / k (harmonic balance).

    Written w0 kappa f^2 / (sqrt(1 + kappa f^2) + 1): no cancellation for small kappa, and
    exactly 0 when kappa = 0.
    """
    kf2 = kappa * f * f
    return w0 * kf2 / (jnp.sqrt(jnp.maximum(1.0 + kf2, 1e-300)) + 1.0)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def if_cubic(fn, linear, kappa, beta, operands):
    """``fn(kappa, beta, operands)``, a computation with cubic-stiffness terms, evaluated as
    ``linear(kappa, beta, operands)`` when those terms all vanish.

    When every kappa and beta of the call (across a vmapped batch too: ``unvmap_any``) is 0,
    the linear form runs instead of ``fn`` (a branch, not both: the Gauss--Legendre phase
    integral costs some 26 f(t) evaluations per sample, and a linear spring must not pay for
    it). Derivatives (jvp, grad) always come from ``fn``, so d/dk3 at k3 = 0 stays exact.

    Arguments:
        fn: a function of (kappa, beta, operands) returning a pytree of arrays.
        linear: what ``fn`` is when kappa = beta = 0 (same signature, same output
            structure), without its cubic terms.
        kappa, beta: (3/4) k3 A^2 / k and k3 A^2 / (32 k) (arrays of any shape).
        operands: a pytree of arrays passed on to ``fn``.

    Returns:
        ``fn(kappa, beta, operands)``.
    """
    live = eqxi.unvmap_any(jnp.any(kappa != 0.0) | jnp.any(beta != 0.0))
    return jax.lax.cond(live, fn, linear, kappa, beta, operands)


@if_cubic.defjvp
def _if_cubic_jvp(fn, linear, primals, tangents):
    return jax.jvp(fn, primals, tangents)


def _nodes(rule, ndim):
    """Gauss--Legendre nodes on [0, 1] and weights (summing to 1), shaped (n,) + (1,) * ndim."""
    x, w = rule
    shape = (x.size,) + (1,) * ndim
    return jnp.asarray(0.5 * (1.0 + x)).reshape(shape), jnp.asarray(0.5 * w).reshape(shape)


def phase_excess(k: _DecayConstants, w0, kappa, t, f):
    """P(t) = int_0^min(t, tau) (w(A f(s)) - w0) ds, the phase the cubic stiffness adds.

    A fixed-order Gauss--Legendre quadrature (no closed form for every damping case, see
    docs/cubic_stiffness.md): over s in [0, t] (6 nodes, f from :func:`_decay_from`) while
    1 - f(t) <= 0.1, where the integrand hardly changes; else over f in [f(t), 1] with
    ds = -df / (a f^2 + b' f + c) (eq. 20; 20 nodes, no further f(t) needed: rational
    functions only), smooth on that interval because a f^2 + b' f + c > 0 there; the roots of
    a f^2 + b' f + c near f = 0 (weak Coulomb and viscous terms beside drag) set the number of
    nodes. Exactly 0 when kappa = 0; finite, with finite
    gradients, under jit/vmap/grad (both rules evaluated, the unused one on safe values).

    Arguments:
        k: the decay constants; w0: [rad/s]; kappa: (3/4) k3 A^2 / k.
        t: times (any shape broadcasting with the constants); f: f(t) at those times.

    Returns:
        P(t) [rad] (0 for t < 0).
    """
    t = jnp.asarray(t, dtype=float)
    t_e = jnp.clip(t, 0.0, k.tau)
    gone = 1.0 - f
    over_f = gone > _F_SWITCH  # False where f is NaN (t < 0): the t rule on t_e = 0
    nd = jnp.ndim(gone)
    # over t
    u, wt = _nodes(_GL_T, max(nd, jnp.ndim(t_e)))
    t_q = jnp.where(over_f, 0.0, t_e)
    p_t = t_q * jnp.sum(wt * excess_frequency(_decay_from(k, u * t_q), w0, kappa), axis=0)
    # over f
    p_f = _integral_over_f(k, w0, kappa, 1.0 - jnp.where(over_f, gone, 0.0), gone, over_f, _GL_F)
    return jnp.where(over_f, p_f, p_t)


def _integral_over_f(k: _DecayConstants, w0, kappa, lo, span, use, rule):
    """The phase added while f falls from lo + span to lo: int (w(A f) - w0) df / (a f^2 + b' f
    + c) over [lo, lo + span] (ds = -df / (a f^2 + b' f + c), eq. 20) by the Gauss--Legendre
    ``rule``; rational functions of f only. 0 where ``use`` is False (safe values there)."""
    v, w = _nodes(rule, jnp.ndim(span))
    span = jnp.where(use, span, 0.0)
    f_q = lo + span * v
    R = k.a * f_q * f_q + k.bp * f_q + k.c
    R = jnp.where(use & (R > 0.0), R, 1.0)
    return span * jnp.sum(w * excess_frequency(f_q, w0, kappa) / R, axis=0)


def phase_excess_sampled(k: _DecayConstants, w0, kappa, t, f):
    """:func:`phase_excess` at every sample of a 1-d ``t`` at once, accumulated from sample to
    sample (the fits' model, whose samples are the data): no f(t) beyond the samples' own,
    where :func:`phase_excess` takes 6 more and 20 nodes of the f rule per sample (a k3 fit
    of 1,200 samples: 12.3 -> 6.2 s warm).

    In time order, P(t_i) = P(t_(i-1)) + the integral over [t_(i-1), t_i] (both clipped to the
    halt): by the cubic Hermite rule h/2 (g0 + g1) + h^2/12 (g0' - g1') of the integrand g =
    w(A f) - w0, with g' = dg/df f' and f' = -(a f^2 + b' f + c) of eq. 20 in closed form
    (error h^5 g^(4) / 720: g follows the envelope, not the oscillation); where f falls by
    more than ``_F_STEP`` over the interval, over f instead (ds = -df / (a f^2 + b' f + c),
    ``_GL_STEP``'s nodes on [f_i, f_(i-1)]). Against scipy's quad, over random decays of every
    regime sampled 50-300 times over 2-40 periods: 2.3e-8 of P at worst (:func:`phase_excess`
    4.3e-7); tests/models/test_cubic.py checks it to 1e-7. The first sample in time order
    takes :func:`phase_excess` itself.

    Arguments:
        k, w0, kappa: as in :func:`phase_excess` (one oscillator: scalars).
        t: the sample times, 1-d, any order.
        f: f(t) at those times (:func:`_decay_from`).

    Returns:
        P(t) [rad], the shape of ``t``.
    """
    t = jnp.asarray(t, dtype=float)
    order = jnp.argsort(t)
    ts, fs = t[order], f[order]
    t_e = jnp.clip(ts, 0.0, k.tau)
    f_e = jnp.where(ts < 0.0, 1.0, fs)  # (f is NaN before the start, where P = 0)
    g = excess_frequency(f_e, w0, kappa)
    root = jnp.sqrt(jnp.maximum(1.0 + kappa * f_e * f_e, 1e-300))  # (XLA shares it with g's)
    dg = w0 * kappa * f_e * decay_rate(f_e, k.a, k.bp, k.c) / root  # g' = dg/df f'
    h = jnp.diff(t_e)
    pieces = 0.5 * h * (g[1:] + g[:-1]) + h * h / 12.0 * (dg[:-1] - dg[1:])
    # where f falls by more than _F_STEP within an interval, the integral over f instead
    # (ds = -df / (a f^2 + b' f + c), Gauss--Legendre on [f_i, f_(i-1)]: rational functions)
    span = jnp.maximum(f_e[:-1] - f_e[1:], 0.0)
    over_f = span > _F_STEP
    by_f = _integral_over_f(k, w0, kappa, f_e[1:], span, over_f, _GL_STEP)
    pieces = jnp.where(over_f, by_f, pieces)
    first = phase_excess(k, w0, kappa, ts[:1], fs[:1])
    p = jnp.concatenate([first, first + jnp.cumsum(pieces)])
    return jnp.zeros_like(p).at[order].set(p)


def _cubic_residual(dy, dphi, y, phi, e0, e1, e2, e3):
    """Matching conditions of the cubic ansatz at t = 0, minus those of the linear one at (y, phi).

    With y' = y + dy, phi' = phi + dphi, g = e2 y + e1 + e0/y (f'(0) = -w0 g),
    kappa = (3/4) e3 y'^2, eps = e3 y'^2 / 32, r = sqrt(1 + kappa):
        x0/A0  = y' (cos phi' + eps (cos 3phi' - cos phi'))
        -v0/(w0 A0) = y' (g' (cos phi' + 3 eps (cos 3phi' - cos phi'))
                          + r (sin phi' + eps (3 sin 3phi' - sin phi')))
    (x = A f (cos th + eps f^2 (cos 3th - cos th)) and its velocity at t = 0). The linear
    conditions y cos phi = x0/A0, y (g cos phi + sin phi) = -v0/(w0 A0) hold at (y, phi), so
    their differences are written out (exactly 0 at dy = dphi = 0) and the cubic terms added
    (exactly 0 at e3 = 0).
    """
    y1 = y + dy
    half = 0.5 * dphi
    sh = jnp.sin(half)
    dc = -2.0 * jnp.sin(phi + half) * sh  # cos phi' - cos phi
    ds = 2.0 * jnp.cos(phi + half) * sh  # sin phi' - sin phi
    c1, s1 = jnp.cos(phi + dphi), jnp.sin(phi + dphi)
    g = e2 * y + e1 + e0 / y
    g1 = e2 * y1 + e1 + e0 / y1
    r1 = dy * c1 + y * dc
    r2 = (e2 * dy * (2.0 * y + dy) + e1 * dy) * c1 + y * g * dc + dy * s1 + y * ds
    kappa = 0.75 * e3 * y1 * y1
    eps = e3 * y1 * y1 / 32.0
    root = jnp.sqrt(jnp.maximum(1.0 + kappa, 1e-300))
    c3 = -4.0 * c1 * s1 * s1  # cos 3phi' - cos phi'
    s3 = 4.0 * s1 * (2.0 - 3.0 * s1 * s1)  # 3 sin 3phi' - sin phi'
    r1 = r1 + y1 * eps * c3
    r2 = r2 + y1 * (3.0 * g1 * eps * c3 + kappa / (root + 1.0) * s1 + root * eps * s3)
    return r1, r2


def cubic_match(y, phi, e0, e1, e2, e3, *, newton=4):
    """The matched amplitude ratio and phase of the cubic ansatz, as corrections (dy, dphi).

    Newton's method on :func:`_cubic_residual` from the linear solution (y = A/A0, phi of
    eqs. 22-23); ``newton`` steps with the derivative held fixed, then one more that carries
    it (implicit function theorem: exact first derivatives, including d/dk3 at k3 = 0).
    Exactly (0, 0) when e3 = k3 A0^2 / k = 0.

    Arguments:
        y, phi: the linear matched solution (finite, y > 0); e0, e1, e2: the damping ratios
            d0/(w0 A0), d1/w0, d2 A0/w0; e3: k3 A0^2 / k.

    Returns:
        (dy, dphi, ok): ok is False where Newton's method did not converge.
    """
    args = jnp.broadcast_arrays(*(jnp.asarray(a, dtype=float) for a in (y, phi, e0, e1, e2, e3)))
    frozen = jax.lax.stop_gradient(args)
    zero = jnp.zeros_like(args[0])
    one = jnp.ones_like(zero)

    def step(d, params):
        def res(dy, dphi):
            return _cubic_residual(dy, dphi, *params)

        (r1, r2), (j11, j21) = jax.jvp(res, d, (one, zero))
        _, (j12, j22) = jax.jvp(res, jax.lax.stop_gradient(d), (zero, one))
        j11, j21, j12, j22 = (jax.lax.stop_gradient(j) for j in (j11, j21, j12, j22))
        det = j11 * j22 - j12 * j21
        det = jnp.where(det != 0.0, det, 1.0)
        return (d[0] - (j22 * r1 - j12 * r2) / det, d[1] - (j11 * r2 - j21 * r1) / det), (r1, r2)

    d = (zero, zero)
    for _ in range(newton):
        d = jax.lax.stop_gradient(step(d, frozen)[0])
    d, _ = step(d, args)
    r1, r2 = _cubic_residual(*jax.lax.stop_gradient(d), *frozen)
    ok = (jnp.isfinite(d[0]) & jnp.isfinite(d[1]) & (jnp.abs(r1) < 1e-10)
          & (jnp.abs(r2) < 1e-10) & (y + d[0] > 0.0))
    return d[0], d[1], ok


def _cubic_terms(kappa, beta, operands):
    """What the cubic stiffness adds to x and v at the samples of `AnsatzSolution._state`.

    The phase P(t) enters by rotating (cos th, sin th) by P, as differences dc = cos(th + P)
    - cos th, ds = sin(th + P) - sin th added to the linear model (whose expression stays as
    it was); then the third harmonic and th' - w0 (class docstring).

    Returns:
        (dx, dv, dv_rate): x + dx, then v - dv (+ dv_rate for the matched velocity, the f'
        term); all exactly 0 when kappa = beta = 0.
    """
    A, w0, k, t, f, cth, sth, rate = operands
    p = phase_excess(k, w0, kappa, t, f)
    sp, vers = jnp.sin(p), 2.0 * jnp.sin(0.5 * p) ** 2  # sin P, 1 - cos P
    dc = -(cth * vers + sth * sp)
    ds = cth * sp - sth * vers
    cth, sth = cth + dc, sth + ds
    eps = beta * f * f
    c3 = -4.0 * cth * sth * sth  # cos 3th - cos th
    s3 = 4.0 * sth * (2.0 - 3.0 * sth * sth)  # 3 sin 3th - sin th
    dw = excess_frequency(f, w0, kappa)
    dx = A * f * (dc + eps * c3)
    dv = A * f * (w0 * ds + dw * sth + (w0 + dw) * eps * s3)
    return dx, dv, A * rate * (dc + 3.0 * eps * c3)
