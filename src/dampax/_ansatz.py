"""The ansatz x(t) = A f(t) cos(w0 t + phi) of Lelas & Pezer (Part I), eqs. 8-24, 36-54.

f solves the Riccati equation f' = -(a f^2 + b' f + c), f(0) = 1 (eq. 20), with a = d2 A,
b' = d1, c = d0 / A. Its five closed forms (docs/DESIGN.md, section 2.3) are one Moebius expression

    f(t) = (1 - (c + b'/2) T(t)) / (1 + (a + b'/2) T(t)),   T(t) = tanh(q t) / q,

with q^2 = Q = b'^2/4 - a c. T is an entire function of Q (tan(|q| t)/|q| for Q < 0, t for
Q = 0), so one formula covers every regime and its gradients stay finite across the
boundaries a = 0, b' = 0, c = 0 and Q = 0. The halt time tau (f(tau) = 0) is the inverse,
tau = atanh(q T*)/q with T* = 1/(c + b'/2).

Evaluation (issue 12): what depends only on the oscillator and initial state (q, the regime,
c + b'/2, a + b'/2, tau) is computed once per solution (:func:`_decay_constants`), so that a
sample of x(t) costs one cos, one tanh, one tan (a vectorized rational function,
:func:`_tan_fraction`), the short series near Q t^2 = 0 and one division; v(t) and energy(t)
share f, f', cos and sin (:meth:`AnsatzSolution.state`).
"""

from __future__ import annotations

import functools

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np

from ._oscillator import Oscillator, initial_amplitude_phase, jit_method, known_linear
from ._solution import (
    RESULTS,
    AbstractSolution,
    cubic_checks,
    first_failure,
    input_checks,
    stuck_at_start,
)

Array = jax.Array

_SERIES = 1e-4  # |Q t^2| below which the Taylor series is used


# tan(u) as a rational function (Cephes tan.c) in numerator/denominator form: it vectorizes,
# unlike XLA's float64 tan on CPU (a scalar libm call, about as costly as the cos of x(t)), and
# leaves the one division to f(t); within 3 ulp of the libm value, derivative within 2e-15
_TAN_P = (-1.30936939181383777646e4, 1.15351664838587416140e6, -1.79565251976484877988e7)
_TAN_Q = (1.36812963470692954678e4, -1.32089234440210967447e6, 2.50083801823357915839e7,
          -5.38695755929454629881e7)
_PIO2 = (1.570796310901641845703125, 1.589325471229585673428e-8, 6.12323399573676588614e-17)


def _tan_fraction(u):
    """(num, den) with num/den = tan(u), for |u| < 8e8 (f(t) needs 0 <= u < pi/2); den != 0."""
    n = jnp.floor(u * (2.0 / jnp.pi) + 0.5)  # u = n pi/2 + z, subtracted in three exact parts
    z = ((u - n * _PIO2[0]) - n * _PIO2[1]) - n * _PIO2[2]  # |z| <= pi/4
    zz = z * z
    p = (_TAN_P[0] * zz + _TAN_P[1]) * zz + _TAN_P[2]
    q = (((zz + _TAN_Q[0]) * zz + _TAN_Q[1]) * zz + _TAN_Q[2]) * zz + _TAN_Q[3]  # < 0
    r = z * q + z * (zz * p)  # tan(z) = r / q
    even = 2.0 * jnp.floor(0.5 * n) == n  # tan(u) = tan(z), else -1/tan(z)
    return jnp.where(even, r, -q), jnp.where(even, q, r)


def _tanc_constants(Q):
    """The per-point part of :func:`_tanc`: (q, q_tan, hyper).

    q = sqrt|Q| (1 where Q = 0, a safe value: there every sample takes the series), q_tan = q
    where Q < 0 and 0 elsewhere (the unused tan branch then evaluates tan(0): no pole, no
    gradient), hyper = Q > 0.
    """
    hyper = Q > 0.0
    trig = Q < 0.0
    q = jnp.sqrt(jnp.where(hyper, Q, jnp.where(trig, -Q, 1.0)))
    return q, jnp.where(trig, q, 0.0), hyper


def _tanc_fraction(Q, q, q_tan, hyper, t):
    """Per-sample part of :func:`_tanc` as (num, den), num/den = T, from :func:`_tanc_constants`.

    The Taylor series where |Q t^2| < _SERIES keeps the value and the gradients finite and
    exact across Q = 0 (den = 1); elsewhere tanh(q t)/q (Q > 0) or tan(q t)/q (Q < 0). No
    division here: the caller's f(t) takes the only one, and none is taken in an unused branch.
    """
    z = Q * t * t
    small = jnp.abs(z) < _SERIES
    series = t * (1.0 - z / 3.0 + 2.0 * z * z / 15.0 - 17.0 * z**3 / 315.0)
    tan_num, tan_den = _tan_fraction(q_tan * t)
    num = jnp.where(small, series, jnp.where(hyper, jnp.tanh(q * t), tan_num))
    den = jnp.where(small, 1.0, jnp.where(hyper, 1.0, tan_den) * q)
    return num, den


def _tanc(Q, t):
    """tanh(sqrt(Q) t) / sqrt(Q), analytic in Q (tan for Q < 0, t at Q = 0)."""
    num, den = _tanc_fraction(Q, *_tanc_constants(Q), t)
    return num / den


def _atanc(Q, x):
    """Inverse of :func:`_tanc` in t: atanh(sqrt(Q) x) / sqrt(Q); inf where Q x^2 >= 1."""
    w = Q * x * x
    small = jnp.abs(w) < _SERIES
    pos = (w >= _SERIES) & (w < 1.0)
    neg = w <= -_SERIES
    series = x * (1.0 + w / 3.0 + w * w / 5.0 + w**3 / 7.0)
    r_pos = jnp.sqrt(jnp.where(pos, w, 0.25))
    r_neg = jnp.sqrt(jnp.where(neg, -w, 0.25))
    q_pos = jnp.sqrt(jnp.where(pos, Q, 1.0))
    q_neg = jnp.sqrt(jnp.where(neg, -Q, 1.0))
    return jnp.where(small, series,
                     jnp.where(pos, jnp.arctanh(r_pos) / q_pos,
                               jnp.where(neg, jnp.arctan(r_neg) / q_neg, jnp.inf)))


def halt_time(a, bp, c):
    """Halt time tau with f(tau) = 0 for f' = -(a f^2 + b' f + c), f(0) = 1 (eq. 20).

    Arguments:
        a, bp, c: the Riccati coefficients a = d2 A, b' = d1, c = d0 / A (all >= 0).

    Returns:
        tau; inf when c = 0 (no Coulomb term, f never reaches zero).
    """
    a, bp, c = jnp.broadcast_arrays(*(jnp.asarray(v, dtype=float) for v in (a, bp, c)))
    halts = c > 0.0
    c_safe = jnp.where(halts, c, 1.0)
    k = c_safe + 0.5 * bp
    Q = 0.25 * bp * bp - a * c_safe
    # Q > 0: atanh(q/k)/q = log1p(2q/(k - q))/(2q) with k - q = c (a + b' + c)/(k + q), free of
    # the cancellation in 1 - q/k when c << b'
    hyper = (Q >= _SERIES * k * k) & (Q > 0.0)  # Q > 0: k * k may underflow for tiny c
    q = jnp.sqrt(jnp.where(hyper, Q, 1.0))
    k_minus_q = c_safe * (a + bp + c_safe) / (k + q)
    tau = jnp.where(hyper, jnp.log1p(2.0 * q / k_minus_q) / (2.0 * q), _atanc(Q, 1.0 / k))
    return jnp.where(halts, tau, jnp.inf)


class _DecayConstants(eqx.Module):
    """What f(t) of eq. 20 needs per oscillator and initial state, computed once.

    Q = b'^2/4 - a c, the square root of its modulus and the regime (see :func:`_tanc_constants`),
    K1 = c + b'/2, K2 = a + b'/2 and the halt time tau; a, b', c for f' (eq. 20). The per-sample
    work of :func:`_decay_from` is then a tanh, a rational tan, a short series and one
    division.
    """

    a: Array
    bp: Array
    c: Array
    Q: Array
    q: Array
    q_tan: Array
    hyper: Array
    K1: Array
    K2: Array
    tau: Array


def _decay_constants(a, bp, c, tau=None) -> _DecayConstants:
    """The per-point constants of f(t) (see :class:`_DecayConstants`); tau from :func:`halt_time`
    unless given."""
    a, bp, c = (jnp.asarray(v, dtype=float) for v in (a, bp, c))
    if tau is None:
        tau = halt_time(a, bp, c)
    Q = 0.25 * bp * bp - a * c
    q, q_tan, hyper = _tanc_constants(Q)
    return _DecayConstants(a=a, bp=bp, c=c, Q=Q, q=q, q_tan=q_tan, hyper=hyper,
                           K1=c + 0.5 * bp, K2=a + 0.5 * bp, tau=jnp.asarray(tau, dtype=float))


def _decay_from(k: _DecayConstants, t) -> Array:
    """f(t) of :func:`decay` from precomputed constants (the per-sample part)."""
    t = jnp.asarray(t, dtype=float)
    t_eff = jnp.clip(t, 0.0, k.tau)
    num, den = _tanc_fraction(k.Q, k.q, k.q_tan, k.hyper, t_eff)  # T = num / den
    f = (den - k.K1 * num) / (den + k.K2 * num)
    f = jnp.where(t > k.tau, 0.0, jnp.maximum(f, 0.0))
    return jnp.where(t < 0.0, jnp.nan, f)


def decay(t, a, bp, c, tau=None):
    """Amplitude factor f(t) of eq. 20 in closed form for any a, b', c >= 0 (eqs. 28, 45).

    Arguments:
        t: time(s) >= 0.
        a, bp, c: the Riccati coefficients a = d2 A, b' = d1, c = d0 / A.
        tau: the halt time, if already known (see :func:`halt_time`).

    Returns:
        f(t) for 0 <= t <= tau and 0 after the halt (the theta(t) of eq. 37); NaN for t < 0.
    """
    return _decay_from(_decay_constants(a, bp, c, tau), t)


def decay_rate(f, a, bp, c):
    """f' = -(a f^2 + b' f + c) (eq. 20), zero where the motion has halted (f = 0)."""
    return jnp.where(f > 0.0, -(a * f * f + bp * f + c), 0.0)


# ----------------------------------------------------------------------------------------------
# amplitude and phase (eqs. 22-23)


def _amplitude_residual(y, s, cphi, sphi, e0, e1, e2):
    """F(y) = y^2 - (y cos phi)^2 - (y sin phi)^2 in units of A0 (the quartic of eq. 22 / y^2).

    y = A / A0, s scales the damping (continuation parameter), y cos(phi) = cos(phi0) and
    y sin(phi) = sin(phi0) - s cos(phi0) (e2 y + e1 + e0 / y).
    Returns F, dF/dy, dF/ds and h = y sin(phi).
    """
    g = e2 * y + e1 + e0 / y
    h = sphi - s * cphi * g
    F = y * y - cphi * cphi - h * h
    F_y = 2.0 * y + 2.0 * s * h * cphi * (e2 - e0 / (y * y))
    F_s = 2.0 * h * cphi * g
    return F, F_y, F_s, h


def matched_amplitude(cphi, sphi, e0, e1, e2, *, steps=16, newton=3):
    """Amplitude ratio A/A0 of eq. 22 on the root branch connected to A0 as damping -> 0.

    Solves (d2 x0 A^2 + (v0 + d1 x0) A + d0 x0)^2 = w0^2 A^2 (A^2 - x0^2) in dimensionless form
    by continuation in the damping strength s from 0 (root A = A0) to 1: an Euler predictor and
    Newton correctors per step. The branch ends at a fold where no admissible root exists
    (e.g. d2 |x0| >= w0 for quadratic damping); ``valid`` is then False.

    Arguments:
        cphi, sphi: cos(phi0) = x0/A0 and sin(phi0) = -v0/(w0 A0).
        e0, e1, e2: the ratios d0/(w0 A0), d1/w0, d2 A0/w0.

    Returns:
        (y, h, valid): y = A/A0, h = y sin(phi) and the validity flag. First derivatives of y are
        exact (implicit function theorem through a final Newton step).
    """
    # broadcast first: the scan's carry takes the shape of the whole batch (an Oscillator with
    # array fields and a scalar start, or the other way round)
    args = tuple(jnp.broadcast_arrays(*(jnp.asarray(v, dtype=float)
                                        for v in (cphi, sphi, e0, e1, e2))))
    const = jax.lax.stop_gradient(args)
    ds = 1.0 / steps

    def correct(y, s):
        def body(_, y):
            F, F_y, _, _ = _amplitude_residual(y, s, *const)
            y = y - F / jnp.where(F_y == 0.0, 1.0, F_y)
            return jnp.where(jnp.isfinite(y) & (y > 0.0), y, jnp.nan)

        return jax.lax.fori_loop(0, newton, body, y)

    def step(carry, i):
        y, min_fy = carry
        s = i * ds
        _, F_y, F_s, _ = _amplitude_residual(y, s, *const)
        y = y - ds * F_s / jnp.where(F_y == 0.0, 1.0, F_y)
        y = correct(jnp.where(y > 0.0, y, jnp.nan), s + ds)
        _, F_y, _, _ = _amplitude_residual(y, s + ds, *const)
        return (y, jnp.minimum(min_fy, F_y)), None

    y0 = jnp.ones_like(const[0])
    (y, min_fy), _ = jax.lax.scan(step, (y0, jnp.full_like(y0, jnp.inf)), jnp.arange(steps))
    y = correct(y, 1.0)
    F, F_y, _, _ = _amplitude_residual(y, 1.0, *const)
    valid = jnp.isfinite(y) & (y > 0.0) & (min_fy > 1e-8) & (jnp.abs(F) < 1e-10 * y * y)
    # implicit-function-theorem step: exact first derivatives, value unchanged to rounding
    y_c = jnp.where(valid, y, 1.0)
    F, F_y, _, h = _amplitude_residual(y_c, 1.0, *args)
    y_out = y_c - F / jnp.where(valid, F_y, 1.0)
    _, _, _, h = _amplitude_residual(y_out, 1.0, *args)
    return jnp.where(valid, y_out, jnp.nan), jnp.where(valid, h, jnp.nan), valid


# ----------------------------------------------------------------------------------------------
# cubic stiffness (issue 14, docs/cubic_stiffness.md): the amplitude-dependent phase
# theta(t) = phi + int_0^t w(A f(s)) ds with w(a) = w0 sqrt(1 + (3/4) (k3/k) a^2) (harmonic
# balance), the first (Lindstedt) harmonic correction A f eps (cos 3 theta - cos theta) with
# eps = (k3/(32 k)) (A f)^2, and the matched amplitude and phase extended to both

#: Gauss--Legendre rules of the phase integral: over t while f changes by less than
#: _F_SWITCH, over f (ds = -df / (a f^2 + b' f + c)) beyond
_GL_T = np.polynomial.legendre.leggauss(6)
_GL_F = np.polynomial.legendre.leggauss(20)
_F_SWITCH = 0.1


def excess_frequency(f, w0, kappa):
    """w(A f) - w0 = w0 (sqrt(1 + kappa f^2) - 1), kappa = (3/4) k3 A^2 / k (harmonic balance).

    Written w0 kappa f^2 / (sqrt(1 + kappa f^2) + 1): no cancellation for small kappa, and
    exactly 0 when kappa = 0.
    """
    kf2 = kappa * f * f
    return w0 * kf2 / (jnp.sqrt(jnp.maximum(1.0 + kf2, 1e-300)) + 1.0)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 4))
def if_cubic(fn, kappa, beta, operands, linear=None):
    """``fn(kappa, beta, operands)``, a computation with cubic-stiffness terms, evaluated as
    ``linear(kappa, beta, operands)`` (zeros by default) when those terms all vanish.

    When every kappa and beta of the call (across a vmapped batch too: ``unvmap_any``) is 0,
    the linear form runs instead of ``fn`` (a branch, not both: the Gauss--Legendre phase
    integral costs some 26 f(t) evaluations per sample, and a linear spring must not pay for
    it). Derivatives (jvp, grad) always come from ``fn``, so d/dk3 at k3 = 0 stays exact.

    Arguments:
        fn: a function of (kappa, beta, operands) returning a pytree of arrays.
        kappa, beta: (3/4) k3 A^2 / k and k3 A^2 / (32 k) (arrays of any shape).
        operands: a pytree of arrays passed on to ``fn``.
        linear: what ``fn`` is when kappa = beta = 0 (same signature, same output
            structure), without its cubic terms; None: zeros.

    Returns:
        ``fn(kappa, beta, operands)``.
    """
    live = eqxi.unvmap_any(jnp.any(kappa != 0.0) | jnp.any(beta != 0.0))
    if linear is None:
        def linear(*args):
            return jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype),
                                          jax.eval_shape(fn, *args))

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
    v, wf = _nodes(_GL_F, nd)
    span = jnp.where(over_f, gone, 0.0)
    f_q = (1.0 - span) + span * v
    R = k.a * f_q * f_q + k.bp * f_q + k.c
    R = jnp.where(over_f & (R > 0.0), R, 1.0)
    p_f = span * jnp.sum(wf * excess_frequency(f_q, w0, kappa) / R, axis=0)
    return jnp.where(over_f, p_f, p_t)


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


def _undamped_x(kappa, beta, operands, *, cubic: bool):
    """A f(t) cos(w0 t + phi + P(t)), the undamped-phase x of `AnsatzSolution._x_energy`
    (operands: A, w0, phi, decay constants, t, f(t)); cubic=False leaves P out."""
    A, w0, phi, k, t, f = operands
    th = w0 * t + phi
    if cubic:
        th = th + phase_excess(k, w0, kappa, t, f)
    return A * f * jnp.cos(th)


def _state_terms(kappa, beta, operands, *, matched: bool, cubic: bool):
    """(x, v) of `AnsatzSolution._state` before masking (eqs. 11-12, or 8-9 unmatched).

    Arguments:
        kappa, beta: the cubic stiffness's constants; operands: (A, w0, phi, decay constants,
            t); cubic: False leaves the cubic terms out (exact when kappa = beta = 0).
    """
    A, w0, phi, k, t = operands
    f = _decay_from(k, t)
    th = w0 * t + phi
    cth, sth = jnp.cos(th), jnp.sin(th)
    x = A * f * cth
    v = -w0 * A * f * sth
    rate = decay_rate(f, k.a, k.bp, k.c)
    if matched:
        v = v + A * rate * cth
    if cubic:  # all exactly 0 when k3 = 0
        dx, dv, dv_rate = _cubic_terms(kappa, beta, (A, w0, k, t, f, cth, sth, rate))
        x = x + dx
        v = v - dv
        if matched:
            v = v + dv_rate
    return x, v


# ----------------------------------------------------------------------------------------------
# the solution object


class AnsatzSolution(AbstractSolution):
    """x(t) = A f(t) cos(w0 t + phi) of eq. 11, zero after the halt time tau (eq. 37).

    ``matched=True``: A and phi from eqs. 22-23, velocity eq. 12, energy eq. 15.
    ``matched=False``: the earlier approach, A = A0, phi = phi0 (eq. 8), velocity without the
    f' term (eq. 9), energy m w0^2 A0^2 f^2 / 2 (eq. 10).
    Where no admissible amplitude exists, ``result`` is ``RESULTS.no_amplitude`` (``valid``
    False) and the values are NaN; likewise ``RESULTS.ansatz_overdamped`` for d1 >= w0 and
    ``RESULTS.invalid_constants``. A start at rest inside the sticking band (``stuck``) stays
    there: x(t) = x0, v = 0, halt time 0.

    With a cubic stiffness k3 (matched phase only; docs/cubic_stiffness.md):
        x(t) = A f [cos th + eps f^2 (cos 3th - cos th)],  eps = beta = k3 A^2 / (32 k),
        th(t) = w0 t + phi + P(t),  th' = w(A f) = w0 sqrt(1 + kappa f^2),
        kappa = (3/4) k3 A^2 / k;
    every k3 term is exactly zero when k3 = 0.
    """

    A: Array  # amplitude, finite even where invalid (see ``amplitude``)
    phi: Array
    omega0: Array
    a: Array
    bp: Array
    c: Array
    halt_time: Array
    osc: Oscillator
    result: RESULTS
    stuck: Array  # started at rest inside the band: x(t) = x0 (the model's A is then 0)
    x0: Array
    kappa: Array  # (3/4) k3 A^2 / k: w(A f)^2 = w0^2 (1 + kappa f^2)
    beta: Array  # k3 A^2 / (32 k): the third harmonic's relative amplitude at f = 1
    matched: bool = eqx.field(static=True)
    # k3 was a value 0 at construction (`known_linear`): the cubic terms are left out at trace
    # time; else they are skipped at run time where kappa = beta = 0 (`if_cubic`)
    linear: bool = eqx.field(static=True, default=False)

    @property
    def amplitude(self) -> Array:
        """A of eq. 11 (A0 for the undamped phase); NaN where the model does not exist."""
        return jnp.where(self.valid, self.A, jnp.nan)

    @property
    def phase(self) -> Array:
        """phi of eq. 11 (phi0 for the undamped phase); NaN where the model does not exist."""
        return jnp.where(self.valid, self.phi, jnp.nan)

    def _mask(self, value):
        return jnp.where(self.valid, value, jnp.nan)

    def _rest(self, x):
        """x0 where the block is stuck from the start (there A = 0: x is 0, NaN for t < 0)."""
        return jnp.where(self.stuck, x + self.x0, x)

    @property
    def halt_position(self) -> Array:
        """Where the model comes to rest: x(tau) = 0 when it halts (x0 for a start at rest
        inside the band), NaN when it never does."""
        return self._mask(jnp.where(self.stuck, self.x0,
                                    jnp.where(jnp.isfinite(self.halt_time), 0.0, jnp.nan)))

    def _decay(self) -> _DecayConstants:
        """The per-point constants of f(t), shared by x, v and energy (computed once per call,
        outside the per-sample work)."""
        return _decay_constants(self.a, self.bp, self.c, self.halt_time)

    def f(self, t) -> Array:
        """Amplitude factor f(t) (eq. 20 in closed form), 0 after the halt."""
        return _decay_from(self._decay(), t)

    def _with_cubic(self, fn, operands):
        """``fn(kappa, beta, operands, cubic=...)``: with its cubic terms unless the spring is
        linear (known at trace time, or kappa = beta = 0 at run time: `if_cubic`)."""
        if self.linear:
            return fn(self.kappa, self.beta, operands, cubic=False)
        return if_cubic(functools.partial(fn, cubic=True), self.kappa, self.beta, operands,
                        functools.partial(fn, cubic=False))

    def _state(self, t):
        t = jnp.asarray(t, dtype=float)
        x, v = self._with_cubic(functools.partial(_state_terms, matched=self.matched),
                                (self.A, self.omega0, self.phi, self._decay(), t))
        return self._mask(self._rest(x)), self._mask(v)

    @jit_method
    def x(self, t) -> Array:
        """Displacement A f(t) cos(w0 t + phi) (eq. 11; with k3 see the class docstring)."""
        return self._state(t)[0]

    def _undamped_energy(self, f):
        """m w0^2 A^2 f^2 / 2 (eq. 10); k x0^2 / 2 for a start at rest inside the band."""
        return self._mask(jnp.where(self.stuck, 0.5 * self.osc.k * self._rest(0.0 * f) ** 2,
                                    0.5 * self.osc.m * (self.omega0 * self.A * f) ** 2))

    def v(self, t) -> Array:
        """Velocity: eq. 12 (matched) or eq. 9 (undamped phase)."""
        # x and v compiled together, as in `state` (XLA's fused multiply-adds depend on the
        # fusion: this keeps v bit for bit what it was before k3 when k3 = 0)
        return self.state(t)[1]

    @jit_method
    def state(self, t) -> tuple[Array, Array]:
        """(x(t), v(t)) together, sharing f(t), f'(t), cos and sin (eqs. 11-12 or 8-9)."""
        return self._state(t)

    def energy(self, t) -> Array:
        """Energy: k x^2/2 + m v^2/2 (eq. 15) or m w0^2 A0^2 f^2/2 (eq. 10)."""
        if self.matched:
            return self._energy_xv(t)[2]
        return self._energy_undamped(t)

    @jit_method
    def _energy_undamped(self, t):
        return self._undamped_energy(self.f(t))

    @jit_method
    def _energy_xv(self, t):
        """(x, v, energy) compiled together (see `v`)."""
        x, v = self._state(t)
        return x, v, self.osc.energy(x, v)

    def _x_energy(self, t, grid=None):
        if self.matched:
            x, v = self._state(t)
            return x, self.osc.energy(x, v)
        t = jnp.asarray(t, dtype=float)
        k = self._decay()
        f = _decay_from(k, t)
        x = self._with_cubic(_undamped_x, (self.A, self.omega0, self.phi, k, t, f))
        return self._mask(self._rest(x)), self._undamped_energy(f)

    # -- turning points: v = 0 <=> w0 t + phi = n pi + atan(f'/(w0 f)), one per half period --

    def _turning_residual(self, t, n, params):
        """G(t) = th(t) - n pi - atan(q f'/(w f)) and G'(t); G = 0 at turning point n.

        th = w0 t + phi (+ P(t)) and w = th' = w(A f) (w0 without cubic stiffness). With the
        third harmonic v = 0 reads tan th = q f'/(w f), q = (1 - 12 e s^2)/(1 + 8 e - 12 e s^2),
        e = beta f^2, s = sin th (q = 1 exactly when k3 = 0); G' leaves out dq/dt.
        """
        w0, ph, a, bp, c, tau, kappa, beta = params
        k = _decay_constants(a, bp, c, tau)
        f = _decay_from(k, t)
        f_safe = jnp.where(f > 0.0, f, 1.0)
        fp = -(a * f_safe**2 + bp * f_safe + c)
        fpp = -(2.0 * a * f_safe + bp) * fp
        dw = excess_frequency(f_safe, w0, kappa)
        w = w0 + dw
        w_dot = w0 * kappa * f_safe * fp / (w / w0)  # dw/dt
        r = fp / (w * f_safe)
        dr = (fpp * f_safe - fp * fp) / (w * f_safe * f_safe) - fp * w_dot / (w * w * f_safe)
        th = w0 * t + ph
        if not self.linear:  # P(t) = 0 exactly for a linear spring
            th = th + phase_excess(k, w0, kappa, t, f)
        e = beta * f_safe * f_safe
        s2 = jnp.sin(th) ** 2
        q = (1.0 - 12.0 * e * s2) / (1.0 + 8.0 * e - 12.0 * e * s2)
        r, dr = r * q, dr * q
        if not self.matched:  # eq. 9: v ~ sin(w0 t + phi0)
            r, dr = 0.0 * r, 0.0 * dr
        return th - n * jnp.pi - jnp.arctan(r), (w0 + excess_frequency(f, w0, kappa)) - dr / (
            1.0 + r * r)

    def _params(self):
        return (self.omega0, self.phi, self.a, self.bp, self.c, self.halt_time, self.kappa,
                self.beta)

    def _turning_newton(self, n):
        """Turning point n (v = 0 near w0 t + phi = n pi) by Newton's method, no gradient."""
        frozen = jax.lax.stop_gradient(self._params())
        # the iterates stay short of the halt: at t = tau itself f is 0 or a rounding error
        # away from it, whichever the compiled program gives (it differed between jit and
        # vmap), and at f = 0 the residual is meaningless (Newton stuck at tau and missed a
        # turning point just before the halt); one that ends at the cap found none: tau
        tau = frozen[5]
        t_max = tau * (1.0 - 1e-9)

        def newton(_, t):
            val, der = self._turning_residual(t, n, frozen)
            return jnp.clip(t - val / der, 0.0, t_max)

        t = jnp.clip((n * jnp.pi - frozen[1]) / frozen[0], 0.0, t_max)
        t = jax.lax.fori_loop(0, 6, newton, t)
        return jnp.where(t >= t_max, tau, t)

    def _turning_refine(self, n, t):
        """One Newton step at the converged t: exact first derivatives (implicit function)."""
        val, der = self._turning_residual(t, n, self._params())
        return t - val / der

    def _turning_time(self, n):
        """Turning point n with derivatives w.r.t. the parameters."""
        return self._turning_refine(n, self._turning_newton(n))

    def _first_index(self):
        """Index n of the first turning point w0 t + phi = n pi + atan(f'/(w0 f)) with t > 0."""
        w_a = self.omega0 + excess_frequency(1.0, self.omega0, self.kappa)
        s2 = jnp.sin(self.phi) ** 2
        q0 = (1.0 - 12.0 * self.beta * s2) / (1.0 + 8.0 * self.beta - 12.0 * self.beta * s2)
        r0 = decay_rate(1.0, self.a, self.bp, self.c) / w_a * q0 if self.matched else 0.0
        return jax.lax.stop_gradient(
            jnp.floor((self.phi - jnp.arctan(r0)) / jnp.pi + 1e-9) + 1.0)

    @eqx.filter_jit
    def turning_points(self, n: int):
        """First n turning points (t_k, x_k), t_k > 0, before the halt; NaN-padded."""
        ks = self._first_index() + jnp.arange(n, dtype=float)
        ts = jax.vmap(self._turning_time)(ks)
        ok = (ts > 0.0) & (ts < self.halt_time) & self.valid
        ts_safe = jnp.where(ok, ts, 0.0)
        xs = self.x(ts_safe)
        return jnp.where(ok, ts, jnp.nan), jnp.where(ok, xs, jnp.nan)


def solve_ansatz(osc: Oscillator, x0, v0, *, phase: str = "matched",
                 linear: bool | None = None) -> AnsatzSolution:
    """Ansatz solution x(t) = A f(t) cos(w0 t + phi) (Lelas & Pezer eqs. 11-24 or 8-10).

    Arguments:
        osc: the Oscillator.
        x0, v0: initial displacement and velocity.
        phase: "matched" (A, phi from eqs. 22-23) or "undamped" (A0, phi0; eqs. 8-10).
        linear: True states that k3 is a constant 0 (the cubic terms are left out at trace
            time); None: `known_linear` (k3 a value 0, not traced).

    Returns:
        An :class:`AnsatzSolution`: ``result`` is ``RESULTS.invalid_constants`` or
        ``nonfinite_state`` outside every model's domain, ``ansatz_overdamped`` where
        d1 = b/(2m) >= w0, ``no_amplitude`` where eq. 22 has no admissible root; a start at rest
        inside the sticking band stays there (x = x0, halt time 0).
    """
    if phase not in ("matched", "undamped"):
        raise ValueError(f"phase must be 'matched' or 'undamped', got {phase!r}")
    x_start, v_start = jnp.asarray(x0, dtype=float), jnp.asarray(v0, dtype=float)
    linear = known_linear(osc) if linear is None else bool(linear)
    stuck = stuck_at_start(osc, x_start, v_start)
    # stuck: the model is solved from the origin (its trivial, gradient-safe branch, A = 0)
    # and x0 added back (AnsatzSolution._rest)
    x0 = jnp.where(stuck, 0.0, x_start)
    v0 = jnp.where(stuck, 0.0, v_start)
    w0 = osc.omega0
    d0, d1, d2 = osc.damping_coefficients
    A0, phi0 = initial_amplitude_phase(osc, x0, v0)
    at_rest = A0 == 0.0
    A0_safe = jnp.where(at_rest, 1.0, A0)
    if phase == "matched":
        cphi = jnp.where(at_rest, 1.0, jnp.asarray(x0, dtype=float) / A0_safe)
        sphi = jnp.where(at_rest, 0.0, -jnp.asarray(v0, dtype=float) / (w0 * A0_safe))
        e0, e1, e2 = d0 / (w0 * A0_safe), d1 / w0, d2 * A0_safe / w0
        y, h, valid = matched_amplitude(cphi, sphi, e0, e1, e2)
        usable = valid & ~at_rest
        phi_lin = jnp.arctan2(jnp.where(usable, h, 0.0), jnp.where(usable, cphi, 1.0))
        # cubic stiffness: Newton corrections from the linear match (exactly 0 when k3 = 0)
        e3 = jnp.where(usable, osc.k3 * A0_safe * A0_safe / osc.k, 0.0)
        if linear:  # every correction is exactly 0
            dy = dphi = jnp.zeros_like(y)
            ok3 = jnp.ones_like(valid)
        else:
            dy, dphi, ok3 = cubic_match(jnp.where(usable, y, 1.0), phi_lin, e0, e1, e2, e3)
        dy = jnp.where(usable, dy, 0.0)
        dphi = jnp.where(usable, dphi, 0.0)
        valid = valid & ok3
        usable = valid & ~at_rest
        valid = valid | at_rest
        A = jnp.where(at_rest, 0.0, A0_safe * jnp.where(usable, y + dy, 1.0))
        phi = jnp.where(usable, phi_lin + dphi, 0.0)
        A_div = jnp.where(at_rest, 1.0, A)
    else:
        A, phi, A_div = A0, phi0, A0_safe
        valid = jnp.ones_like(A0, dtype=bool)
    a = d2 * A_div
    c = d0 / A_div
    bp = d1 + 0.0 * a
    tau = jnp.where(at_rest, 0.0, halt_time(a, bp, c))
    kappa = 0.75 * osc.k3 * A * A / osc.k
    beta = osc.k3 * A * A / (32.0 * osc.k)
    # w(A f)^2 = w0^2 (1 + kappa f^2) must stay > 0 for 0 <= f <= 1 (a softening spring)
    valid = valid & (1.0 + kappa > 0.0)
    # the undamped phase (eqs. 8-10) has no cubic stiffness; the matched phase has
    ((cubic, no_cubic),) = cubic_checks(osc)
    if phase == "matched":
        cubic = cubic & False
    result = first_failure(*input_checks(osc, x_start, v_start),
                           (cubic & ~stuck, no_cubic),
                           (~stuck & ~(d1 < w0), RESULTS.ansatz_overdamped),
                           (~stuck & ~valid, RESULTS.no_amplitude))
    return AnsatzSolution(A=A, phi=phi, omega0=w0 + 0.0 * A, a=a, bp=bp, c=c,
                          halt_time=tau, osc=osc, result=result, stuck=stuck,
                          x0=x_start, kappa=kappa, beta=beta, matched=phase == "matched",
                          linear=linear)


