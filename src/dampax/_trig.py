"""sin, cos and tan of float64 arrays as vectorizable polynomials (Cephes), for the per-sample work.

XLA's float64 sin, cos and tan on CPU are scalar libm calls: a cos costs about 13 ns per sample
where a tanh or an exp costs 2-3 ns, and a model's x(t) over a grid spent most of its time in
them (issue 12). Here the argument is reduced by multiples of pi/2 (subtracted in three exact
parts, as Cephes does) and the functions are polynomials on [-pi/4, pi/4], which the compiler
vectorizes:

- :func:`sincos`: (sin u, cos u) within 2 ulp of the true values for |u| < 4.2e8 rad;
  beyond, and for inf/NaN, ``jnp.sin``/``jnp.cos`` themselves (a branch taken only when some
  argument of the call is that large). Derivatives are exact: d sin = cos, d cos = -sin, from
  the same values.
- :func:`_tan_fraction`: tan u as (numerator, denominator), leaving the one division to the
  caller (f(t) of eq. 20 needs tan(|q| t) only through a Moebius expression).
"""

from __future__ import annotations

import equinox.internal as eqxi
import jax
import jax.numpy as jnp

# pi/2 in three parts (25, 24 and 53 significant bits): n times each of the first two is exact
# for |n| < 2^28 (|u| < 4.2e8), with or without fused multiply-adds. Beyond, only a compiler
# that fuses u - n p0 into one exact multiply-add keeps the reduced angle right (XLA on a CPU
# does, to 8e8; an H200 did not: 3.8e8 ulp at u = -6.2e8, as numpy's replay without them)
_PIO2 = (1.570796310901641845703125, 1.589325471229585673428e-8, 6.12323399573676588614e-17)
_SINCOS_MAX = 4.2e8  # |u| beyond (|n| near 2^28): jnp.sin and jnp.cos

# Cephes sin.c: sin z = z + z^3 S(z^2), cos z = 1 - z^2/2 + z^4 C(z^2), |z| <= pi/4
_SIN = (1.58962301576546568060e-10, -2.50507477628578072866e-8, 2.75573136213857245213e-6,
        -1.98412698295895385996e-4, 8.33333333332211858878e-3, -1.66666666666666307295e-1)
_COS = (-1.13585365213876817300e-11, 2.08757008419747316778e-9, -2.75573141792967388112e-7,
        2.48015872888517045348e-5, -1.38888888888730564116e-3, 4.16666666666665929218e-2)

# Cephes tan.c: tan z = z + z^3 P(z^2)/Q(z^2) in numerator/denominator form
_TAN_P = (-1.30936939181383777646e4, 1.15351664838587416140e6, -1.79565251976484877988e7)
_TAN_Q = (1.36812963470692954678e4, -1.32089234440210967447e6, 2.50083801823357915839e7,
          -5.38695755929454629881e7)


def _reduce(u):
    """(n, z) with u = n pi/2 + z, |z| <= pi/4 (n a float holding an integer)."""
    n = jnp.floor(u * (2.0 / jnp.pi) + 0.5)
    z = ((u - n * _PIO2[0]) - n * _PIO2[1]) - n * _PIO2[2]
    return n, z


def _horner(coefficients, x):
    y = coefficients[0]
    for c in coefficients[1:]:
        y = y * x + c
    return y


def _sincos_poly(u):
    n, z = _reduce(u)
    zz = z * z
    s = z + z * (zz * _horner(_SIN, zz))
    c = (1.0 - 0.5 * zz) + (zz * zz) * _horner(_COS, zz)
    q = n - 4.0 * jnp.floor(0.25 * n)  # quadrant 0..3: u = z + q pi/2 (mod 2 pi)
    odd = (q == 1.0) | (q == 3.0)
    sin, cos = jnp.where(odd, c, s), jnp.where(odd, s, c)
    return jnp.where(q >= 2.0, -sin, sin), jnp.where((q == 1.0) | (q == 2.0), -cos, cos)


def _sincos_libm(u):
    return jnp.sin(u), jnp.cos(u)


@jax.custom_jvp
def sincos(u):
    """(sin u, cos u) of a float64 array, vectorizable on CPU (see the module docstring).

    Arguments:
        u: angles in radians (any shape).

    Returns:
        (sin u, cos u), within 2 ulp of the true values; ``jnp.sin``/``jnp.cos`` when some
        |u| of the call (of the whole vmapped batch) reaches 4.2e8 or is not finite.
    """
    u = jnp.asarray(u, dtype=float)
    far = eqxi.unvmap_any(jnp.any(~(jnp.abs(u) < _SINCOS_MAX)))
    return jax.lax.cond(far, _sincos_libm, _sincos_poly, u)


@sincos.defjvp
def _sincos_jvp(primals, tangents):
    (u,), (du,) = primals, tangents
    s, c = sincos(u)
    return (s, c), (c * du, -s * du)


def _tan_fraction(u):
    """(num, den) with num/den = tan(u), for |u| < 4.2e8 (f(t) needs 0 <= u < pi/2); den != 0.

    Within 3 ulp of the true value, derivative within 2e-15.
    """
    n, z = _reduce(u)
    zz = z * z
    p = _horner(_TAN_P, zz)
    q = _horner((1.0,) + _TAN_Q, zz)  # < 0
    r = z * q + z * (zz * p)  # tan(z) = r / q
    even = 2.0 * jnp.floor(0.5 * n) == n  # tan(u) = tan(z), else -1/tan(z)
    return jnp.where(even, r, -q), jnp.where(even, q, r)
