"""Finite values and correct gradients of the ansatz solution (docs/DESIGN.md 2.1-2.3).

Hypothesis draws damping ratios (each exactly 0 or positive, inside the regime where the model
exists), a reference amplitude and an initial phase in any quadrant; the Oscillator's mu, b, D
follow from the ratios. For the "matched" and "undamped" ansatz, x, v, energy, halt time,
amplitude and phase must be finite where ``sol.valid``, and ``jax.grad`` of x(t) (fixed t) and of
the halt time w.r.t. (mu, b, D, x0, v0) must be finite and agree with finite differences
(central; one-sided second order where a damping parameter is too close to 0 for a central
step). The Oscillator is built inside the differentiated function. Then: continuity of f across
the regime boundaries c = 0 and Q = b'^2/4 - ac = 0, finite gradients at exactly mu = b = D = 0,
and the rest state x0 = v0 = 0.
"""

import functools
import math

import jax
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from hypothesis import HealthCheck, assume, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import dampax as dp  # noqa: E402
from dampax._models._decay import decay, halt_time  # noqa: E402

M, K, G = 1.0, 30.0, 9.81
W0 = math.sqrt(K / M)
TS = jnp.asarray([0.0, 0.15, 0.6, 1.4, 3.0])
NAMES = ("mu", "b", "D", "x0", "v0")
NONNEG = np.array([True, True, True, False, False])  # damping parameters must stay >= 0
SCALE = np.array([0.1, 1.0, 1.0, 0.1, 0.5])  # typical magnitudes, for the step size
REL_STEP = 1e-6
RTOL, ATOL = 1e-4, 1e-7
KINK_GAP = 1e-4  # skip t this close to the halt time (x has a kink at t = tau)
PHASES = ("matched", "undamped")

SETTINGS = settings(derandomize=True, max_examples=40, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])


# --------------------------------------------------------------------------------------------
# jitted model evaluations (module level: compiled once per phase, no retracing in loops)


def _solution(p, phase):
    mu, b, D, x0, v0 = p[0], p[1], p[2], p[3], p[4]
    osc = dp.Oscillator(m=M, k=K, mu=mu, b=b, D=D)
    return dp.solve(osc, x0, v0, method="ansatz", phase=phase)


def _x_at(p, t, phase):
    return _solution(p, phase).x(t)


def _tau(p, phase):
    return _solution(p, phase).halt_time


def _values(p, phase):
    sol = _solution(p, phase)
    return dict(x=sol.x(TS), v=sol.v(TS), E=sol.energy(TS), tau=sol.halt_time,
                A=sol.amplitude, phi=sol.phase, valid=sol.valid)


def _grads(p, phase):
    gx = jax.vmap(jax.grad(functools.partial(_x_at, phase=phase)), in_axes=(None, 0))(p, TS)
    gtau = jax.grad(functools.partial(_tau, phase=phase))(p)
    return gx, gtau


def _batch(P, phase):
    """x(TS) and tau at each row of P (finite-difference points)."""

    def one(p):
        sol = _solution(p, phase)
        return sol.x(TS), sol.halt_time

    return jax.vmap(one)(P)


VALUES = {ph: jax.jit(functools.partial(_values, phase=ph)) for ph in PHASES}
GRADS = {ph: jax.jit(functools.partial(_grads, phase=ph)) for ph in PHASES}
BATCH = {ph: jax.jit(functools.partial(_batch, phase=ph)) for ph in PHASES}
X_GRID = {ph: jax.jit(lambda p, ph=ph: jax.vmap(functools.partial(_x_at, phase=ph),
                                                in_axes=(None, 0))(p, jnp.linspace(0.0, 10.0, 201)))
          for ph in PHASES}


# --------------------------------------------------------------------------------------------
# finite differences


def _fd_points(p, h):
    """Rows p + h e_i, p - h e_i, p + 2 h e_i for every parameter i (15 rows, fixed shape)."""
    rows = []
    for i in range(5):
        e = np.zeros(5)
        e[i] = h[i]
        rows += [p + e, p - e, p + 2.0 * e]
    return np.stack(rows)


def _fd_from(vals, p, h):
    """Derivatives from the batch values: central, or one-sided second order
    (-3 f(p) + 4 f(p+h) - f(p+2h)) / (2h) where p - h would leave the domain (p_i < h)."""
    base = vals[-1]
    out = []
    with np.errstate(invalid="ignore"):  # tau = inf (mu = 0): inf - inf, never compared
        return _fd_loop(vals, base, p, h, out)


def _fd_loop(vals, base, p, h, out):
    for i in range(5):
        fp, fm, f2 = vals[3 * i], vals[3 * i + 1], vals[3 * i + 2]
        if NONNEG[i] and p[i] - h[i] < 0.0:
            out.append((-3.0 * base + 4.0 * fp - f2) / (2.0 * h[i]))
        else:
            out.append((fp - fm) / (2.0 * h[i]))
    return np.stack(out, axis=-1)


def finite_differences(phase, p, h):
    P = np.vstack([_fd_points(p, h), p[None, :]])
    xs, taus = BATCH[phase](jnp.asarray(P))
    return _fd_from(np.asarray(xs), p, h), _fd_from(np.asarray(taus), p, h)


def _assert_close(ad, fd, what, noise=0.0):
    """|ad - fd| <= ATOL + RTOL |fd| + noise (noise: the rounding floor of the difference
    quotient, ~ ulps(value) / h, which matters only for large values such as tau ~ 1/c)."""
    ad, fd = np.asarray(ad), np.asarray(fd)
    assert np.all(np.isfinite(ad)), f"{what}: non-finite gradient {ad}"
    bad = np.abs(ad - fd) > ATOL + RTOL * np.abs(fd) + noise
    assert not np.any(bad), (f"{what}: jax.grad {ad} vs finite differences {fd} "
                             f"(mismatch in {[NAMES[i] for i in np.flatnonzero(bad)]})")


def check_model(phase, p, require_valid=True):
    """Finite values where valid; gradients of x(TS) and tau agree with finite differences."""
    vals = {k: np.asarray(v) for k, v in VALUES[phase](jnp.asarray(p)).items()}
    valid = bool(vals["valid"])
    if require_valid:
        assume(valid)
    if not valid:
        return vals
    mu = p[0]
    for key in ("x", "v", "E", "A", "phi"):
        assert np.all(np.isfinite(vals[key])), (key, vals[key], p)
    tau = float(vals["tau"])
    if mu > 0.0:
        assert math.isfinite(tau) and tau > 0.0, (tau, p)
    else:
        assert tau == math.inf, (tau, p)
    # the initial conditions are reproduced (both phases)
    assert vals["x"][0] == pytest.approx(p[3], abs=1e-12)
    assert vals["v"][0] == pytest.approx(p[4], abs=1e-11)
    assert np.all(vals["E"] >= 0.0)

    gx, gtau = (np.asarray(g) for g in GRADS[phase](jnp.asarray(p)))
    assert np.all(np.isfinite(gx)), (gx, p)
    h = REL_STEP * np.maximum(np.abs(p), SCALE)
    fdx, _ = finite_differences(phase, p, h)
    for j, t in enumerate(np.asarray(TS)):
        if abs(t - tau) < KINK_GAP * (1.0 + tau):
            continue
        _assert_close(gx[j], fdx[j], f"{phase} dx({t})/dp at p={p.tolist()}")
    if math.isfinite(tau):
        assert np.all(np.isfinite(gtau)), (gtau, p)
        # tau(a, b', c) is homogeneous of degree -1 and varies on the scale max(a, b', c)
        # (tau = log(1 + b'/c)/b' when a = 0): steps relative to that scale, not to SCALE
        A = float(vals["A"])
        d0, d1, d2 = 2 * mu * G / (math.pi * W0), p[1] / (2 * M), 4 * p[2] * W0 / (3 * math.pi * M)
        kappa = max(d2 * A, d1, d0 / A)
        h_tau = h.copy()
        h_tau[0] = REL_STEP * mu
        h_tau[1] = REL_STEP * 2.0 * M * kappa
        h_tau[2] = REL_STEP * 3.0 * math.pi * M * kappa / (4.0 * W0 * A)
        _, fdtau = finite_differences(phase, p, h_tau)
        # rounding floor: 1000 ulps of tau divided by the step
        noise = 1e3 * np.finfo(float).eps * tau / h_tau
        _assert_close(gtau, fdtau, f"{phase} dtau/dp at p={p.tolist()} (tau={tau})", noise)
    return vals


def params_from(r0, r1, r2, A0, phi0):
    """(mu, b, D, x0, v0) with d0/(w0 A0) = r0, d1/w0 = r1, d2 A0/w0 = r2 at amplitude A0."""
    osc = dp.from_ratios(r0, r1, r2, m=M, k=K, A0=A0, g=G)
    return np.array([float(osc.mu), float(osc.b), float(osc.D),
                     A0 * math.cos(phi0), -W0 * A0 * math.sin(phi0)])


def _ratio(max_value):
    return st.one_of(st.just(0.0), st.floats(min_value=1e-6, max_value=max_value,
                                             allow_nan=False, allow_infinity=False))


# phi0 = (quadrant - 2 + frac) pi/2: hypothesis would otherwise favour phi0 near 0+
RATIOS = dict(r0=_ratio(0.2), r1=_ratio(0.3), r2=_ratio(0.6),
              A0=st.floats(min_value=0.05, max_value=0.4),
              quadrant=st.sampled_from([0, 3, 1, 2]),
              frac=st.floats(min_value=0.0, max_value=1.0))


# --------------------------------------------------------------------------------------------
# property tests


@pytest.mark.parametrize("phase", PHASES)
@SETTINGS
@given(**RATIOS)
def test_values_finite_and_gradients_match_fd(phase, r0, r1, r2, A0, quadrant, frac):
    phi0 = (quadrant - 2 + frac) * math.pi / 2
    p = params_from(r0, r1, r2, A0, phi0)
    check_model(phase, p)


# the corners: exact zeros of every damping parameter, all four quadrants of (x0, v0)
ZERO_PATTERNS = [(0.0, 0.0, 0.0), (0.1, 0.0, 0.0), (0.0, 0.2, 0.0), (0.0, 0.0, 0.5),
                 (0.1, 0.2, 0.0), (0.1, 0.0, 0.5), (0.0, 0.2, 0.5), (0.1, 0.2, 0.5)]


@pytest.mark.parametrize("phase", PHASES)
@pytest.mark.parametrize("phi0", [0.7, 2.3, -2.5, -0.4])
@pytest.mark.parametrize("ratios", ZERO_PATTERNS, ids=lambda r: "r=" + ",".join(map(str, r)))
def test_gradients_at_exact_zero_damping(phase, phi0, ratios):
    p = params_from(*ratios, 0.2, phi0)
    assert np.array_equal(p[:3] == 0.0, np.asarray(ratios) == 0.0)
    vals = check_model(phase, p, require_valid=False)
    assert bool(vals["valid"])


@pytest.mark.parametrize("phase", PHASES)
@pytest.mark.parametrize("x0, v0", [(0.0, 1.0), (0.0, -1.0), (0.2, 0.0), (-0.2, 0.0)])
@pytest.mark.parametrize("ratios", [(0.0, 0.0, 0.0), (0.1, 0.2, 0.5), (0.1, 0.0, 0.0)],
                         ids=lambda r: "r=" + ",".join(map(str, r)))
def test_gradients_on_the_axes(phase, x0, v0, ratios):
    """x0 = 0 or v0 = 0 exactly (phi0 = 0, +-pi/2, pi: the atan2 branch points)."""
    p = params_from(*ratios, 0.2, 0.0)
    p[3], p[4] = x0, v0
    vals = check_model(phase, p, require_valid=False)
    assert bool(vals["valid"])


@pytest.mark.parametrize("phase", PHASES)
@pytest.mark.parametrize("ratios", ZERO_PATTERNS, ids=lambda r: "r=" + ",".join(map(str, r)))
def test_rest_state(phase, ratios):
    p = params_from(*ratios, 0.2, 0.0)
    p[3] = p[4] = 0.0
    vals = {k: np.asarray(v) for k, v in VALUES[phase](jnp.asarray(p)).items()}
    assert bool(vals["valid"])
    np.testing.assert_array_equal(vals["x"], 0.0)
    np.testing.assert_array_equal(vals["v"], 0.0)
    np.testing.assert_array_equal(vals["E"], 0.0)
    assert float(vals["A"]) == 0.0
    assert np.isfinite(vals["phi"]) and not np.isnan(vals["tau"])
    gx, gtau = (np.asarray(g) for g in GRADS[phase](jnp.asarray(p)))
    assert np.all(np.isfinite(gx)), gx
    assert np.all(np.isfinite(gtau)), gtau


# --------------------------------------------------------------------------------------------
# continuity across the regime boundaries (decay directly, and through solve)

_decay = jax.jit(decay)
_decay_grad = jax.jit(jax.vmap(jax.grad(decay, argnums=(1, 2, 3)), in_axes=(0, None, None, None)))
T_GRID = jnp.linspace(0.0, 8.0, 401)


@pytest.mark.parametrize("a, bp", [(0.0, 0.0), (0.0, 0.7), (1.3, 0.0), (1.3, 0.7)])
def test_continuity_c_zero(a, bp):
    f0 = np.asarray(_decay(T_GRID, a, bp, 0.0))
    f1 = np.asarray(_decay(T_GRID, a, bp, 1e-12))
    assert np.all(np.isfinite(f0)) and np.all(np.isfinite(f1))
    assert np.max(np.abs(f0 - f1)) < 1e-9
    g0 = np.stack(_decay_grad(T_GRID, a, bp, 0.0))
    g1 = np.stack(_decay_grad(T_GRID, a, bp, 1e-12))
    assert np.all(np.isfinite(g0)) and np.all(np.isfinite(g1))
    assert np.max(np.abs(g0 - g1)) < 1e-6


@pytest.mark.parametrize("dq", [1e-12, -1e-12, 1e-14, -1e-14])
@pytest.mark.parametrize("a, bp", [(1.0, 2.0), (0.25, 1.0), (2.0, 0.3)])
def test_continuity_Q_zero(a, bp, dq):
    c0 = 0.25 * bp * bp / a  # Q = 0 exactly
    c1 = c0 - dq / a  # Q = dq
    assert 0.25 * bp * bp - a * c0 == 0.0
    tau0, tau1 = float(halt_time(a, bp, c0)), float(halt_time(a, bp, c1))
    assert tau0 == pytest.approx(tau1, rel=1e-9)
    ts = jnp.linspace(0.0, min(tau0, tau1), 401)
    f0 = np.asarray(_decay(ts, a, bp, c0))
    f1 = np.asarray(_decay(ts, a, bp, c1))
    assert np.max(np.abs(f0 - f1)) < 1e-9
    g0 = np.stack(_decay_grad(ts[:-1], a, bp, c0))
    g1 = np.stack(_decay_grad(ts[:-1], a, bp, c1))
    assert np.all(np.isfinite(g0)) and np.all(np.isfinite(g1))
    assert np.max(np.abs(g0 - g1)) < 1e-6


@pytest.mark.parametrize("a, bp, c", [(0.0, 0.0, 0.0), (0.0, 0.0, 0.3), (0.0, 0.7, 0.0),
                                      (1.3, 0.0, 0.0), (0.0, 0.7, 0.3), (1.3, 0.0, 0.3),
                                      (1.3, 0.7, 0.0), (1.0, 2.0, 1.0)])
def test_decay_gradient_at_boundaries_matches_fd(a, bp, c):
    """d f / d(a, b', c) at the boundaries (zeros, Q = 0) against one-sided / central FD."""
    ts = jnp.asarray([0.0, 0.2, 0.5, 1.0, 1.5])
    tau = float(halt_time(a, bp, c))
    ts = ts[np.abs(np.asarray(ts) - tau) > 1e-3]
    g = np.stack(_decay_grad(ts, a, bp, c), axis=-1)
    assert np.all(np.isfinite(g))
    p = np.array([a, bp, c])
    for i in range(3):
        h = 1e-6
        e = np.zeros(3)
        e[i] = h
        f = lambda q: np.asarray(_decay(ts, *q))  # noqa: E731
        if p[i] == 0.0:
            fd = (-3.0 * f(p) + 4.0 * f(p + e) - f(p + 2 * e)) / (2 * h)
        else:
            fd = (f(p + e) - f(p - e)) / (2 * h)
        np.testing.assert_allclose(g[:, i], fd, rtol=1e-5, atol=1e-8)
    if a == 0.0 and bp == 0.0 and c == 0.0:  # f = 1: df/da = df/db' = df/dc = -t
        for i in range(3):
            np.testing.assert_allclose(g[:, i], -np.asarray(ts), rtol=0, atol=1e-14)


@pytest.mark.parametrize("phase", PHASES)
@pytest.mark.parametrize("r1, r2", [(0.0, 0.0), (0.2, 0.0), (0.0, 0.5), (0.2, 0.5)])
def test_solution_continuous_at_mu_zero(phase, r1, r2):
    """x(t) at mu = 0 (c = 0) and at mu giving c ~ 1e-12 differ by < 1e-9."""
    p0 = params_from(0.0, r1, r2, 0.2, 0.7)
    p1 = p0.copy()
    p1[0] = 1e-12 * 0.2 * math.pi * W0 / (2.0 * G)  # d0/A0 = c = 1e-12
    v0, v1 = VALUES[phase](jnp.asarray(p0)), VALUES[phase](jnp.asarray(p1))
    assert bool(v0["valid"]) and bool(v1["valid"])
    assert float(v0["tau"]) == math.inf and math.isfinite(float(v1["tau"]))
    x0 = np.asarray(X_GRID[phase](jnp.asarray(p0)))
    x1 = np.asarray(X_GRID[phase](jnp.asarray(p1)))
    assert np.all(np.isfinite(x0)) and np.all(np.isfinite(x1))
    assert np.max(np.abs(x0 - x1)) < 1e-9


def _tau_reference(a, bp, c):
    """Cancellation-free halt time for Q = b'^2/4 - ac > 0 (see tests/models/test_decay.py)."""
    q = math.sqrt(0.25 * bp * bp - a * c)
    k = c + 0.5 * bp
    return math.log1p(2.0 * q * (k + q) / (c * (a + bp + c))) / (2.0 * q)


_halt_grad = jax.jit(jax.grad(halt_time, argnums=(0, 1, 2)))


@pytest.mark.parametrize("c", [1e-4, 1e-6, 1e-8, 1e-10, 1e-12])
@pytest.mark.parametrize("a, bp", [(0.0, 1.0), (1.0, 1.0), (2.0, 0.5)])
def test_halt_time_gradient_small_coulomb_term(a, bp, c):
    """d tau / d(a, b', c) as c -> 0 with b' > 0 (tau ~ log(b'/c)/b'): well-conditioned, so the
    gradient must be accurate to far better than 1e-7 relative."""
    g = np.array([float(v) for v in _halt_grad(a, bp, c)])
    assert np.all(np.isfinite(g))
    if a == 0.0:  # tau = log1p(b'/c)/b'
        tau = math.log1p(bp / c) / bp
        ref = np.array([np.nan, (1.0 / (c + bp) - tau) / bp, -1.0 / (c * (bp + c))])
        np.testing.assert_allclose(g[1:], ref[1:], rtol=1e-8)
    else:  # central differences of the reference, relative steps
        ref = []
        for i, v in enumerate((a, bp, c)):
            h = 1e-5 * v
            hi = [a, bp, c]
            lo = [a, bp, c]
            hi[i] += h
            lo[i] -= h
            ref.append((_tau_reference(*hi) - _tau_reference(*lo)) / (2.0 * h))
        np.testing.assert_allclose(g, ref, rtol=1e-7)


@pytest.mark.parametrize("x0", [0.2, -0.2])
@pytest.mark.parametrize("mu, b", [(0.0, 0.0), (0.0288, 0.3)])
def test_coulomb_exact_derivative_in_v0_at_rest(x0, mu, b):
    """The exact half-swings started at rest: d x(t)/d v0 is the derivative of a velocity
    away from the centre (one side of the friction's kink; both sides and the exact
    sin(w0 t)/w0 without damping), in reverse and forward mode. It was cut to 0 (the start's
    branch masked the tangent; helper audit of the fortieth session)."""
    osc = dp.Oscillator(m=1.0, k=30.0, mu=mu, b=b)

    def x_at(v0):
        return dp.solve(osc, x0, v0, method="coulomb_exact").x(1.1)

    h = 1e-7 * math.copysign(1.0, x0)  # away from the centre
    one_sided = float((x_at(h) - x_at(0.0)) / h)
    if mu == b == 0.0:
        one_sided = math.sin(math.sqrt(30.0) * 1.1) / math.sqrt(30.0)
    assert float(jax.grad(x_at)(0.0)) == pytest.approx(one_sided, rel=1e-5)
    assert float(jax.jacfwd(x_at)(0.0)) == pytest.approx(one_sided, rel=1e-5)
