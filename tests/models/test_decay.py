"""The amplitude factor f(t) of eq. 20 and the matched amplitude/phase of eqs. 22-23.

f' = -(a f^2 + b' f + c), f(0) = 1 (a = d2 A, b' = d1, c = d0/A) is integrated numerically
(scipy DOP853, rtol 1e-13, atol 1e-15, terminal event at f = 0 for the halt time) and compared
with the closed form ``dampax._models._decay.decay`` / ``halt_time`` in every regime: each
combination of a, b', c zero or positive and the discriminant b'^2 - 4ac negative, exactly
zero and positive, plus near-boundary values that show the regimes meet continuously. The
halt time is also checked against independent, cancellation-free closed forms (docs/DESIGN.md
2.3). Then the amplitude A and phase phi returned by ``dp.solve(..., phase="matched")`` are
checked against the quartic of eq. 22 (numpy.roots) and the initial conditions in all four
quadrants of (x0, v0).
"""

import math

import jax
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

import dampax as dp  # noqa: E402
from dampax._models._ansatz import matched_amplitude  # noqa: E402
from dampax._models._decay import decay, halt_time  # noqa: E402

F_ATOL = 1e-9  # f(t) against the numerical solution of eq. 20
TAU_RTOL = 1e-9  # halt time, relative
N_GRID = 201
LONG_WINDOW = 60.0  # window when the motion never halts (c = 0)

_decay = jax.jit(decay)
_halt = jax.jit(halt_time)


# --------------------------------------------------------------------------------------------
# references


def tau_closed_form(a, bp, c):
    """Halt time from closed forms written to avoid cancellation (independent of the package).

    With Q = b'^2/4 - a c and k = c + b'/2 (f = (1 - k T)/(1 + (a + b'/2) T), T = tanh(q t)/q):
    Q > 0: tau = atanh(q/k)/q = log1p(2q/(k - q)) / (2q), k - q = c (a + b' + c)/(k + q);
    Q < 0: tau = atan(s/k)/s, s = sqrt(-Q); Q = 0: tau = 1/k. Also a = 0: log1p(b'/c)/b'.
    """
    if c == 0.0:
        return math.inf
    if a == 0.0 and bp > 0.0:
        return math.log1p(bp / c) / bp
    Q = 0.25 * bp * bp - a * c
    k = c + 0.5 * bp
    if Q > 0.0:
        q = math.sqrt(Q)
        k_minus_q = c * (a + bp + c) / (k + q)
        return math.log1p(2.0 * q / k_minus_q) / (2.0 * q)
    if Q < 0.0:
        s = math.sqrt(-Q)
        return math.atan(s / k) / s
    return 1.0 / k


def tau_design(a, bp, c):
    """Halt time from the regime formulas of docs/DESIGN.md 2.3 (well-conditioned cases)."""
    if c == 0.0:
        return math.inf
    if a == 0.0 and bp == 0.0:
        return 1.0 / c
    if a == 0.0:
        return math.log(1.0 + bp / c) / bp
    disc = bp * bp - 4.0 * a * c
    if disc < 0.0:
        s = math.sqrt(-disc) / 2.0
        th0 = math.atan((2.0 * a + bp) / (2.0 * s))
        return (th0 - math.atan(bp / (2.0 * s))) / s
    if disc == 0.0:
        u0 = 1.0 + bp / (2.0 * a)
        return 2.0 / bp - 1.0 / (a * u0)
    sq = math.sqrt(disc)
    rp, rm = (-bp + sq) / (2.0 * a), (-bp - sq) / (2.0 * a)
    C = (1.0 - rp) / (1.0 - rm)
    return -math.log(rp / (rm * C)) / (a * (rp - rm))


def riccati_numeric(a, bp, c, t_end, t_eval=None):
    """DOP853 solution of eq. 20 with a terminal event at f = 0. Returns (t, f, tau_event)."""

    def rhs(_, f):
        return -(a * f * f + bp * f + c)

    def hit_zero(_, f):
        return f[0]

    hit_zero.terminal = True
    hit_zero.direction = -1
    # with c = 0, f = 0 is a fixed point that f only approaches: no event (rounding at the
    # 1e-18 level would otherwise "cross" it)
    sol = solve_ivp(rhs, (0.0, t_end), [1.0], method="DOP853", rtol=1e-13, atol=1e-15,
                    t_eval=t_eval, events=hit_zero if c > 0.0 else None)
    assert sol.status in (0, 1), sol.message
    tau = sol.t_events[0][0] if c > 0.0 and len(sol.t_events[0]) else math.inf
    return sol.t, sol.y[0], tau


# --------------------------------------------------------------------------------------------
# regimes: every zero/positive combination of (a, b', c) and every sign of D = b'^2 - 4ac

REGIMES = [
    # (a, b', c) and the expected sign of D (None: not meaningful / D = b'^2)
    pytest.param(0.0, 0.0, 0.0, 0, id="a0_b0_c0(f=1)"),
    pytest.param(0.0, 0.0, 0.4, 0, id="a0_b0_c+(linear)"),
    pytest.param(0.0, 0.7, 0.0, 1, id="a0_b+_c0(exp)"),
    pytest.param(0.0, 0.7, 0.4, 1, id="a0_b+_c+(exp-shift)"),
    pytest.param(1.3, 0.0, 0.0, 0, id="a+_b0_c0(1/(1+at))"),
    pytest.param(1.3, 0.0, 0.4, -1, id="a+_b0_c+(D<0,tan)"),
    pytest.param(1.3, 0.7, 0.0, 1, id="a+_b+_c0(D>0)"),
    pytest.param(1.3, 0.7, 0.4, -1, id="a+_b+_c+(D<0)"),
    pytest.param(1.0, 2.0, 1.0, 0, id="a+_b+_c+(D=0,1-2-1)"),
    pytest.param(0.25, 1.0, 1.0, 0, id="a+_b+_c+(D=0,.25-1-1)"),
    pytest.param(2.0, 2.0, 0.5, 0, id="a+_b+_c+(D=0,2-2-.5)"),
    pytest.param(0.3, 2.0, 0.4, 1, id="a+_b+_c+(D>0)"),
    pytest.param(5.0, 3.0, 2.0, -1, id="a+_b+_c+(D<0,large)"),
    pytest.param(0.05, 3.0, 0.02, 1, id="a+_b+_c+(D>0,b'-dominated)"),
    # the Taylor-series switch |Q t^2| = 1e-4 of the implementation is crossed at t ~ 1
    pytest.param(0.0, 0.02, 0.001, 1, id="series-switch(Q=+1e-4)"),
    pytest.param(1.0, 0.0, 1e-4, -1, id="series-switch(Q=-1e-4)"),
]

NEAR_BOUNDARY = [
    pytest.param(1e-12, 0.7, 0.4, id="a=1e-12"),
    pytest.param(1e-12, 0.0, 0.4, id="a=1e-12,b'=0"),
    pytest.param(1e-12, 0.7, 0.0, id="a=1e-12,c=0"),
    pytest.param(1.3, 1e-12, 0.4, id="b'=1e-12"),
    pytest.param(1e-12, 1e-12, 0.4, id="a=b'=1e-12"),
    pytest.param(1.3, 0.7, 1e-12, id="c=1e-12"),
    pytest.param(0.0, 0.7, 1e-12, id="a=0,c=1e-12"),
    pytest.param(1.0, 2.0, 1.0 - 1e-14, id="Q=+1e-14"),
    pytest.param(1.0, 2.0, 1.0 + 1e-14, id="Q=-1e-14"),
    pytest.param(1.0, 2.0, 1.0 - 1e-10, id="Q=+1e-10"),
    pytest.param(1.0, 2.0, 1.0 + 1e-10, id="Q=-1e-10"),
    pytest.param(0.25, 1.0, 1.0 - 4e-14, id="Q=+1e-14(b)"),
    pytest.param(0.25, 1.0, 1.0 + 4e-14, id="Q=-1e-14(b)"),
]


def _check_against_ode(a, bp, c):
    tau_ref = tau_closed_form(a, bp, c)
    if math.isinf(tau_ref):
        t_end = LONG_WINDOW
    else:
        t_end = tau_ref
    grid = np.linspace(0.0, t_end, N_GRID)
    # finer near t = 0 and near the halt, and the series switch at t ~ 1
    extra = np.array([1e-12, 1e-6, 1e-3, 1.0 - 1e-9, 1.0, 1.0 + 1e-9])
    extra = extra[extra < t_end]
    grid = np.unique(np.concatenate([grid, extra, t_end * (1.0 - np.logspace(-12, -2, 6))]))
    # integrate a little past the end so the terminal event (if any) is located
    t_num, f_num, tau_ode = riccati_numeric(a, bp, c, t_end * (1.0 + 1e-6) + 1e-12,
                                            t_eval=grid)
    assert len(t_num) >= len(grid) - 1, (len(t_num), len(grid))
    f_cf = np.asarray(_decay(jnp.asarray(t_num), a, bp, c))
    assert np.all(np.isfinite(f_cf))
    err = np.max(np.abs(f_cf - f_num))
    assert err < F_ATOL, f"max |f - f_ode| = {err:.3e} for a={a}, b'={bp}, c={c}"
    return tau_ref, tau_ode


@pytest.mark.parametrize("a, bp, c, dsign", REGIMES)
def test_decay_matches_riccati_ode(a, bp, c, dsign):
    disc = bp * bp - 4.0 * a * c
    assert np.sign(disc) == dsign  # the regime is the intended one (D = 0 exactly)
    tau_ref, tau_ode = _check_against_ode(a, bp, c)
    tau = float(_halt(a, bp, c))
    if c == 0.0:
        assert math.isinf(tau) and tau > 0 and math.isinf(tau_ode)
    else:
        assert math.isfinite(tau)
        assert tau == pytest.approx(tau_ode, rel=TAU_RTOL)
        assert tau == pytest.approx(tau_ref, rel=TAU_RTOL)
        assert tau == pytest.approx(tau_design(a, bp, c), rel=TAU_RTOL)


@pytest.mark.parametrize("a, bp, c, dsign", REGIMES)
def test_decay_boundaries_and_domain(a, bp, c, dsign):
    tau = float(_halt(a, bp, c))
    f0 = float(_decay(0.0, a, bp, c))
    assert f0 == pytest.approx(1.0, abs=1e-15)
    # NaN for t < 0
    assert np.isnan(float(_decay(-1e-3, a, bp, c)))
    if math.isfinite(tau):
        after = np.asarray(_decay(jnp.asarray([tau * (1 + 1e-12), tau * 1.5, tau + 100.0]),
                                  a, bp, c))
        np.testing.assert_array_equal(after, 0.0)
        assert abs(float(_decay(tau, a, bp, c))) < 1e-12
    # decay is monotone non-increasing and within [0, 1]
    ts = np.linspace(0.0, min(tau, LONG_WINDOW) * 1.2, 400)
    f = np.asarray(_decay(jnp.asarray(ts), a, bp, c))
    assert np.all((f >= 0.0) & (f <= 1.0 + 1e-15))
    assert np.all(np.diff(f) <= 1e-15)
    # passing tau explicitly gives the same values
    f2 = np.asarray(decay(jnp.asarray(ts), a, bp, c, tau=_halt(a, bp, c)))
    np.testing.assert_allclose(f, f2, rtol=0, atol=1e-15)


@pytest.mark.parametrize("a, bp, c", NEAR_BOUNDARY)
def test_decay_near_boundaries_matches_ode(a, bp, c):
    _check_against_ode(a, bp, c)


def _boundary_partner(a, bp, c):
    """The exact-boundary parameters next to a near-boundary point."""
    snap = lambda v: 0.0 if v <= 1e-12 else v  # noqa: E731
    a0, bp0, c0 = snap(a), snap(bp), snap(c)
    if a0 > 0.0 and bp0 > 0.0 and c0 > 0.0 and abs(0.25 * bp * bp - a * c) < 1e-9:
        c0 = 0.25 * bp * bp / a  # Q ~ 0: put Q = 0 exactly
    return a0, bp0, c0


@pytest.mark.parametrize("a, bp, c", NEAR_BOUNDARY)
def test_decay_continuous_across_boundaries(a, bp, c):
    a0, bp0, c0 = _boundary_partner(a, bp, c)
    assert (a0, bp0, c0) != (a, bp, c)
    tau = float(_halt(a, bp, c))
    tau0 = float(_halt(a0, bp0, c0))
    t_end = min(tau, tau0, LONG_WINDOW)
    ts = jnp.linspace(0.0, t_end, 1001)
    f = np.asarray(_decay(ts, a, bp, c))
    f0 = np.asarray(_decay(ts, a0, bp0, c0))
    assert np.all(np.isfinite(f)) and np.all(np.isfinite(f0))
    assert np.max(np.abs(f - f0)) < 1e-9
    if c0 > 0.0:  # both halt: the halt times are continuous too
        assert tau == pytest.approx(tau0, rel=1e-9)


@pytest.mark.parametrize("a, bp, c", NEAR_BOUNDARY)
def test_halt_time_near_boundaries(a, bp, c):
    tau = float(_halt(a, bp, c))
    ref = tau_closed_form(a, bp, c)
    if math.isinf(ref):
        assert math.isinf(tau)
    else:
        assert tau == pytest.approx(ref, rel=TAU_RTOL)


@pytest.mark.parametrize("c", [1e-4, 1e-6, 1e-8, 1e-10, 1e-12])
@pytest.mark.parametrize("a, bp", [(0.0, 1.0), (1.0, 1.0), (2.0, 0.5)])
def test_halt_time_small_coulomb_term(a, bp, c):
    """c -> 0 with b' > 0: tau ~ log(b'/c)/b' is well-conditioned (relative condition number
    ~ 1/log(b'/c)), so double precision must give it to far better than 1e-9 relative."""
    tau = float(_halt(a, bp, c))
    assert tau == pytest.approx(tau_closed_form(a, bp, c), rel=TAU_RTOL)


def test_decay_broadcasts_over_parameters():
    a = jnp.asarray([0.0, 1.3, 1.0, 0.3])
    bp = jnp.asarray([0.7, 0.0, 2.0, 2.0])
    c = jnp.asarray([0.4, 0.4, 1.0, 0.4])
    t = jnp.asarray(0.3)
    f = np.asarray(decay(t, a, bp, c))
    for i in range(4):
        assert f[i] == pytest.approx(float(decay(0.3, float(a[i]), float(bp[i]), float(c[i]))),
                                     abs=1e-15)


# --------------------------------------------------------------------------------------------
# matched amplitude and phase (eqs. 22-23)

M, K = 1.0, 30.0
W0 = math.sqrt(K / M)
A0 = 0.2

DAMPING = [
    pytest.param(0.05, 0.1, 0.25, id="d0=.05,d1=.1,d2=.25"),
    pytest.param(0.1, 0.2, 0.5, id="d0=.1,d1=.2,d2=.5"),
    pytest.param(0.2, 0.3, 0.6, id="d0=.2,d1=.3,d2=.6"),
    pytest.param(0.03, 0.01, 0.1, id="d0=.03,d1=.01,d2=.1"),
]
PHASES = [
    pytest.param(0.7, id="Q1(x>0,v<0)"),
    pytest.param(2.3, id="Q2(x<0,v<0)"),
    pytest.param(-2.5, id="Q3(x<0,v>0)"),
    pytest.param(-0.4, id="Q4(x>0,v>0)"),
    pytest.param(0.0, id="x>0,v=0"),
    pytest.param(math.pi / 2, id="x=0,v<0"),
    pytest.param(math.pi, id="x<0,v=0"),
    pytest.param(-math.pi / 2, id="x=0,v>0"),
]


def _quartic_coefficients(x0, v0, d0, d1, d2, w0):
    """(d2 x0 A^2 + (v0 + d1 x0) A + d0 x0)^2 - w0^2 A^2 (A^2 - x0^2), highest power first."""
    p, q, r = d2 * x0, v0 + d1 * x0, d0 * x0
    return np.array([p * p - w0 * w0, 2 * p * q, q * q + 2 * p * r + w0 * w0 * x0 * x0,
                     2 * q * r, r * r])


@pytest.mark.parametrize("phi0", PHASES)
@pytest.mark.parametrize("r0, r1, r2", DAMPING)
def test_matched_amplitude_solves_quartic(r0, r1, r2, phi0):
    osc = dp.from_ratios(r0, r1, r2, m=M, k=K, A0=A0)
    d0, d1, d2 = (float(v) for v in dp.damping_coefficients(osc))
    assert d0 > 0 and d1 > 0 and d2 > 0
    x0 = A0 * math.cos(phi0)
    v0 = -W0 * A0 * math.sin(phi0)
    sol = dp.solve(osc, x0, v0, method="ansatz", phase="matched")
    assert bool(sol.valid)
    A = float(sol.amplitude)
    phi = float(sol.phase)
    assert math.isfinite(A) and math.isfinite(phi)
    assert A >= abs(x0) - 1e-15

    # A is a root of the quartic (relative residual), and the real root closest to A0
    coeffs = _quartic_coefficients(x0, v0, d0, d1, d2, W0)
    scale = np.polyval(np.abs(coeffs), A)
    assert abs(np.polyval(coeffs, A)) <= 1e-12 * scale
    roots = np.roots(coeffs)
    real = roots[np.abs(roots.imag) <= 1e-7 * np.abs(roots)].real
    assert real.size > 0
    closest = real[np.argmin(np.abs(real - A0))]
    assert A == pytest.approx(closest, rel=1e-9)

    # phase: cos(phi) = x0/A, sin(phi) = -(v0 + (d2 A + d1 + d0/A) x0)/(w0 A)
    assert math.cos(phi) == pytest.approx(x0 / A, abs=1e-12)
    assert math.sin(phi) == pytest.approx(-(v0 + (d2 * A + d1 + d0 / A) * x0) / (W0 * A),
                                          abs=1e-12)
    assert -math.pi <= phi <= math.pi

    # initial conditions
    assert float(sol.x(0.0)) == pytest.approx(x0, abs=1e-13)
    assert float(sol.v(0.0)) == pytest.approx(v0, abs=1e-12)
    E0 = 0.5 * K * x0 * x0 + 0.5 * M * v0 * v0
    assert float(sol.energy(0.0)) == pytest.approx(E0, rel=1e-12)
    # and f of the solution is the closed form with a = d2 A, b' = d1, c = d0/A
    ts = jnp.linspace(0.0, 3.0, 7)
    f_expect = np.asarray(decay(ts, d2 * A, d1, d0 / A))
    np.testing.assert_allclose(np.asarray(sol.f(ts)), f_expect, rtol=0, atol=1e-14)
    assert float(sol.halt_time) == pytest.approx(tau_closed_form(d2 * A, d1, d0 / A), rel=1e-9)


@pytest.mark.parametrize("phi0", PHASES)
def test_matched_amplitude_dimensionless(phi0):
    """matched_amplitude(cos phi0, sin phi0, e0, e1, e2) is the quartic root in units of A0."""
    e0, e1, e2 = 0.1, 0.2, 0.5
    y, h, valid = matched_amplitude(math.cos(phi0), math.sin(phi0), e0, e1, e2)
    assert bool(valid)
    y, h = float(y), float(h)
    # y^2 = cos^2 phi0 + (sin phi0 - cos phi0 (e2 y + e1 + e0/y))^2
    g = e2 * y + e1 + e0 / y
    assert h == pytest.approx(math.sin(phi0) - math.cos(phi0) * g, abs=1e-13)
    assert y * y == pytest.approx(math.cos(phi0) ** 2 + h * h, rel=1e-12)
