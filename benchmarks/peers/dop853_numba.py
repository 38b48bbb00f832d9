"""A compiled scalar peer: Hairer's DOP853 with stick-slip events, in numba, one thread.

The peer of ``benchmarks/peer_race.py`` (issue 24): what a careful hand-written, compiled
integrator does per trajectory, without JAX. It solves

    m x'' = -k x - k3 x^3 - mu m g sgn(v) - b v - D v|v|

swing by swing, as ``dampax.solve(method="reference")`` and the scipy loop of
``benchmarks/reference.py`` do, and samples x at given sorted times on the way.

The integrator is a port of scipy's ``DOP853`` (``scipy.integrate._ivp.rk``), itself Hairer's
algorithm: the coefficients of ``scipy.integrate._ivp.dop853_coefficients`` (12 stages plus the
first-same-as-last one), the combined 5th/3rd-order error estimator, scipy's step-size control
(safety 0.9, factors in [0.2, 10], exponent -1/8, no increase right after a rejection), the
error norm as the RMS of err / (atol + rtol max(|y|, |y_new|)), scipy's ``select_initial_step``
at the start of every swing (as a restarted ``solve_ivp`` would), and DOP853's 7th-order dense
output (3 extra stages, the ``D`` matrix). The state is two scalars (x, v), the stages two
small arrays allocated once per call.

Events: at the end of each accepted step, s v_new <= 0 means the swing ended inside the step;
the velocity zero is found on the dense output by safeguarded Newton (the derivative from the
equation of motion, bisection when Newton leaves the bracket). There the block sticks for good
when |k x + k3 x^3| <= mu m g, else the next swing starts with v = 0 and s = -sgn(x). At t = 0
with v0 = 0: rest if |k x0 + k3 x0^3| <= mu m g, else s = -sgn(x0).

Samples: x at the sorted times ts is filled during the integration from the dense output of
the step that contains each time; after a halt it is the rest position; beyond t_end, or after
a failure (step size underflow), NaN.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from scipy.integrate._ivp import dop853_coefficients as _coef

# global arrays are frozen into the compiled code as constants
_A = np.ascontiguousarray(_coef.A, dtype=np.float64)  # (16, 16): 12 stages, FSAL, 3 extra
_B = np.ascontiguousarray(_coef.B, dtype=np.float64)  # (12,)
_C = np.ascontiguousarray(_coef.C, dtype=np.float64)  # (16,) (unused: autonomous system)
_E3 = np.ascontiguousarray(_coef.E3, dtype=np.float64)  # (13,)
_E5 = np.ascontiguousarray(_coef.E5, dtype=np.float64)  # (13,)
_D = np.ascontiguousarray(_coef.D, dtype=np.float64)  # (4, 16)
N_STAGES = _coef.N_STAGES  # 12
assert N_STAGES == 12 and _coef.N_STAGES_EXTENDED == 16 and _coef.INTERPOLATOR_POWER == 7

SAFETY, MIN_FACTOR, MAX_FACTOR = 0.9, 0.2, 10.0
ERROR_EXPONENT = -1.0 / 8.0  # -1 / (error_estimator_order + 1), error_estimator_order = 7
EPS = np.finfo(float).eps


@njit(inline="always")
def _acc(x, v, p):
    """v' inside a swing; p = (s, k/m, k3/m, mu g, b/m, D/m)."""
    s, w2, k3m, fric, bm, dm = p
    return -(w2 + k3m * x * x) * x - s * fric - (bm + dm * s * v) * v


@njit(inline="always")
def _stages(kx, kv, x, v, h, p, first, stop):
    """Stages first..stop-1 of the tableau from the ones before them (in place)."""
    for i in range(first, stop):
        dx = 0.0
        dv = 0.0
        for q in range(i):
            dx += _A[i, q] * kx[q]
            dv += _A[i, q] * kv[q]
        xi, vi = x + dx * h, v + dv * h
        kx[i], kv[i] = vi, _acc(xi, vi, p)


@njit(inline="always")
def _initial_step(x, v, ax, av, interval, p, rtol, atol):
    """scipy's ``select_initial_step`` (order 7, no max_step) at (x, v) with f = (ax, av)."""
    sx = atol + abs(x) * rtol
    sv = atol + abs(v) * rtol
    d0 = math.sqrt(((x / sx) ** 2 + (v / sv) ** 2) / 2.0)
    d1 = math.sqrt(((ax / sx) ** 2 + (av / sv) ** 2) / 2.0)
    h0 = 1e-6 if (d0 < 1e-5 or d1 < 1e-5) else 0.01 * d0 / d1
    h0 = min(h0, interval)
    x1 = x + h0 * ax
    v1 = v + h0 * av
    d2 = math.sqrt((((v1 - ax) / sx) ** 2 + ((_acc(x1, v1, p) - av) / sv) ** 2) / 2.0) / h0
    if d1 <= 1e-15 and d2 <= 1e-15:
        h1 = max(1e-6, h0 * 1e-3)
    else:
        h1 = (0.01 / max(d1, d2)) ** (1.0 / 8.0)
    return min(100.0 * h0, h1, interval)


@njit(inline="always")
def _dense(F, y_old, th):
    """DOP853's dense output (scipy's Dop853DenseOutput) of one component at theta in [0, 1]."""
    y = 0.0
    for i in range(7):
        y += F[6 - i]
        y *= th if i % 2 == 0 else 1.0 - th
    return y + y_old


@njit
def _solve_many(k, k3, mu, b, D, x0, v0, m, g, t_end, ts, rtol, atol, xs, stats):
    """Fill xs (N, len(ts)); stats (N, 4): accepted steps, rejected steps, swings, status."""
    n_ts = ts.shape[0]
    kx = np.empty(16)
    kv = np.empty(16)
    Fx = np.empty(7)
    Fv = np.empty(7)
    for n in range(k.shape[0]):
        out = xs[n]
        w2, k3m, fric = k[n] / m[n], k3[n] / m[n], mu[n] * g
        bm, dm = b[n] / m[n], D[n] / m[n]
        t, x, v = 0.0, x0[n], v0[n]
        j = 0
        while j < n_ts and ts[j] <= 0.0:  # samples at the start
            out[j] = x if ts[j] == 0.0 else np.nan
            j += 1
        n_acc = n_rej = n_sw = 0
        status = 0
        if v == 0.0:
            if abs(k[n] * x + k3[n] * x ** 3) <= mu[n] * m[n] * g:  # at rest in the band
                for i in range(j, n_ts):
                    out[i] = x
                stats[n, 0], stats[n, 1], stats[n, 2], stats[n, 3] = 0, 0, 0, 0
                continue
            s = -1.0 if x > 0.0 else 1.0
        else:
            s = 1.0 if v > 0.0 else -1.0
        p = (s, w2, k3m, fric, bm, dm)
        fx, fv = v, _acc(x, v, p)
        h_abs = _initial_step(x, v, fx, fv, t_end - t, p, rtol, atol)
        n_sw = 1
        halted = False
        while t < t_end:
            min_step = 10.0 * max(abs(t) * EPS, 5e-324)
            h_abs = max(h_abs, min_step)
            rejected = False
            while True:  # one step, retried until accepted
                if h_abs < min_step:
                    status = 1
                    break
                t_new = t + h_abs
                if t_new > t_end:
                    t_new = t_end
                h = t_new - t
                h_abs = h
                kx[0], kv[0] = fx, fv
                _stages(kx, kv, x, v, h, p, 1, N_STAGES)
                dx = 0.0
                dv = 0.0
                for q in range(N_STAGES):
                    dx += _B[q] * kx[q]
                    dv += _B[q] * kv[q]
                x_new, v_new = x + dx * h, v + dv * h
                kx[12], kv[12] = v_new, _acc(x_new, v_new, p)
                sx = atol + max(abs(x), abs(x_new)) * rtol
                sv = atol + max(abs(v), abs(v_new)) * rtol
                e5x = e5v = e3x = e3v = 0.0
                for q in range(13):
                    e5x += _E5[q] * kx[q]
                    e5v += _E5[q] * kv[q]
                    e3x += _E3[q] * kx[q]
                    e3v += _E3[q] * kv[q]
                e5 = (e5x / sx) ** 2 + (e5v / sv) ** 2
                e3 = (e3x / sx) ** 2 + (e3v / sv) ** 2
                err = 0.0 if (e5 == 0.0 and e3 == 0.0) else h * e5 / math.sqrt(
                    (e5 + 0.01 * e3) * 2.0)
                if err < 1.0:
                    factor = MAX_FACTOR if err == 0.0 else min(
                        MAX_FACTOR, SAFETY * err ** ERROR_EXPONENT)
                    if rejected:
                        factor = min(1.0, factor)
                    h_abs *= factor
                    n_acc += 1
                    break
                h_abs *= max(MIN_FACTOR, SAFETY * err ** ERROR_EXPONENT)
                rejected = True
                n_rej += 1
            if status:
                break
            event = s * v_new <= 0.0
            if event or (j < n_ts and ts[j] <= t_new):
                # dense output: the 3 extra stages and the 7 coefficients (scipy's F)
                _stages(kx, kv, x, v, h, p, 13, 16)
                Fx[0], Fv[0] = x_new - x, v_new - v
                Fx[1], Fv[1] = h * kx[0] - Fx[0], h * kv[0] - Fv[0]
                Fx[2] = 2.0 * Fx[0] - h * (kx[12] + kx[0])
                Fv[2] = 2.0 * Fv[0] - h * (kv[12] + kv[0])
                for r in range(4):
                    dx = 0.0
                    dv = 0.0
                    for q in range(16):
                        dx += _D[r, q] * kx[q]
                        dv += _D[r, q] * kv[q]
                    Fx[3 + r], Fv[3 + r] = h * dx, h * dv
            t_stop = t_new
            if event:  # the velocity zero on the dense output: safeguarded Newton
                lo, hi = 0.0, 1.0
                th = v / (v - v_new) if s * v > 0.0 else 1.0
                for _ in range(40):
                    xt, vt = _dense(Fx, x, th), _dense(Fv, v, th)
                    if s * vt > 0.0:
                        lo = th
                    else:
                        hi = th
                    if vt == 0.0:
                        break
                    at = _acc(xt, vt, p) * h
                    th_new = th - vt / at if at != 0.0 else 0.5 * (lo + hi)
                    if not lo < th_new < hi:
                        th_new = 0.5 * (lo + hi)
                    done = abs(th_new - th) <= 4.0 * EPS
                    th = th_new
                    if done:
                        break
                t_stop = t + th * h
                x_new, v_new = _dense(Fx, x, th), 0.0
            while j < n_ts and ts[j] <= t_stop:  # samples inside this step
                out[j] = _dense(Fx, x, (ts[j] - t) / h)
                j += 1
            t, x, v = t_stop, x_new, v_new
            if event:
                if abs(k[n] * x + k3[n] * x ** 3) <= mu[n] * m[n] * g:
                    halted = True
                    break
                s = -1.0 if x > 0.0 else 1.0
                p = (s, w2, k3m, fric, bm, dm)
                n_sw += 1
                fx, fv = 0.0, _acc(x, 0.0, p)
                if t < t_end:
                    h_abs = _initial_step(x, 0.0, fx, fv, t_end - t, p, rtol, atol)
            else:  # first same as last
                fx, fv = kx[12], kv[12]
        for i in range(j, n_ts):  # after a halt: the rest position; else beyond t_end: NaN
            out[i] = x if halted else np.nan
        stats[n, 0], stats[n, 1], stats[n, 2], stats[n, 3] = n_acc, n_rej, n_sw, status


def solve_many(k, mu, b, D, x0, v0, m=1.0, g=9.81, t_end=5.0, ts=None, rtol=1e-10,
               atol=1e-12, k3=0.0, return_stats=False):
    """x at the sorted times ts for N trajectories, one after another on one thread.

    Arguments broadcast to one shape (N,); ts defaults to 1000 samples in [0, t_end].

    Returns:
        xs, shape (N, len(ts)); with ``return_stats`` also stats (N, 4): accepted steps,
        rejected steps, swings, status (0 ok, 1 step size underflow).
    """
    if ts is None:
        ts = np.linspace(0.0, t_end, 1000)
    ts = np.ascontiguousarray(ts, dtype=np.float64)
    if ts.ndim != 1 or np.any(np.diff(ts) < 0):
        raise ValueError("ts must be a sorted 1-D array")
    arrays = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, dtype=np.float64))
                                   for a in (k, k3, mu, b, D, x0, v0, m)))
    arrays = [np.ascontiguousarray(a.ravel()) for a in arrays]
    xs = np.empty((arrays[0].shape[0], ts.shape[0]))
    stats = np.zeros((arrays[0].shape[0], 4), dtype=np.int64)
    _solve_many(*arrays[:5], arrays[5], arrays[6], arrays[7], float(g), float(t_end), ts,
                float(rtol), float(atol), xs, stats)
    return (xs, stats) if return_stats else xs
