"""f(t) of the ansatz (Lelas & Pezer, Part I, eq. 20) in closed form, and its halt time.

f solves the Riccati equation f' = -(a f^2 + b' f + c), f(0) = 1 (eq. 20), with a = d2 A,
b' = d1, c = d0 / A. Its five closed forms (docs/DESIGN.md, section 2.3) are one Moebius expression

    f(t) = (1 - (c + b'/2) T(t)) / (1 + (a + b'/2) T(t)),   T(t) = tanh(q t) / q,

with q^2 = Q = b'^2/4 - a c. T is an entire function of Q (tan(|q| t)/|q| for Q < 0, t for
Q = 0), so one formula covers every regime and its gradients stay finite across the
boundaries a = 0, b' = 0, c = 0 and Q = 0. The halt time tau (f(tau) = 0) is the inverse,
tau = atanh(q T*)/q with T* = 1/(c + b'/2).

Evaluation (issue 12): what depends only on the oscillator and initial state (q, the regime,
c + b'/2, a + b'/2, tau) is computed once per solution (:func:`_decay_constants`), so that a
sample costs one tanh, one tan (a vectorized rational function, :func:`_tan_fraction`), the
short series near Q t^2 = 0 and one division.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._trig import _tan_fraction

Array = jax.Array

_SERIES = 1e-4  # |Q t^2| below which the Taylor series is used


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
