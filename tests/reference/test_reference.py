"""Tests of the DOP853 reference integrator (dampax._reference) against independent numbers.

Independent references: the exact half-swing map of pure Coulomb friction, the exact damped
harmonic motion (mu = 0, D = 0), scipy's DOP853 with the same stick/reverse logic written
here, and central finite differences for the derivatives.

Compilation dominates the run time, so every jitted function is compiled once (module-scoped
fixtures) and reused: batch A (tight tolerances, internal broadcasting, eager call), batch B
(default tolerances, user-level jit(vmap)), one dense evaluation of both, one reverse-mode and
one forward-mode derivative function.
"""

import jax
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from helpers import evaluate, scipy_stick_slip  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

from dampax._oscillator import Oscillator  # noqa: E402
from dampax._reference import ReferenceSolution, solve_reference  # noqa: E402
from dampax._reference._solve import resolve_engine  # noqa: E402

G = 9.81
TIGHT = dict(rtol=1e-12, atol=1e-14, max_swings=64, max_steps_per_swing=64)
# Default tolerances; a table of 8 rows per swing (a swing takes about 5 to 10 steps at
# rtol = 1e-10)
DEFAULT = dict(max_swings=64, max_steps_per_swing=8)


def mu_for_xc(xc, m, k):
    """Friction coefficient giving the band half-width xc."""
    return xc * k / (m * G)


# ---------------------------------------------------------------- independent references


def coulomb_exact(m, k, mu, x0, v0):
    """Turning points (t_n, x_n), t_n > 0, of pure Coulomb friction; the rest point last."""
    w0 = np.sqrt(k / m)
    xc = mu * G / w0**2
    if v0 == 0.0:
        if abs(x0) <= xc:
            return np.zeros(0), np.zeros(0)
        ts, xs = [0.0], [x0]
    else:
        s = np.sign(v0)
        c = -s * xc  # the first (partial) swing is harmonic about -sgn(v0) xc
        r = np.hypot(x0 - c, v0 / w0)
        phi = np.arctan2(-v0 / w0, x0 - c)  # x - c = r cos(w0 t + phi)
        t1 = (-phi if s > 0 else np.pi - phi) / w0
        ts, xs = [t1], [c + s * r]
    while abs(xs[-1]) > xc:
        xs.append(-xs[-1] + 2.0 * np.sign(xs[-1]) * xc)
        ts.append(ts[-1] + np.pi / w0)
    if v0 == 0.0:
        ts, xs = ts[1:], xs[1:]
    return np.array(ts), np.array(xs)


def viscous_exact(m, k, b, x0, v0, t):
    """Damped harmonic motion (mu = D = 0, underdamped)."""
    gamma = b / (2.0 * m)
    wd = np.sqrt(k / m - gamma**2)
    return np.exp(-gamma * t) * (x0 * np.cos(wd * t) + (v0 + gamma * x0) / wd * np.sin(wd * t))


def scipy_reference(m, k, mu, b, D, x0, v0, t_end):
    """Swing-by-swing DOP853 solution: list of (t_a, t_b, dense, s), turning points, rest."""
    xc = mu * m * G / k
    if v0 == 0.0 and abs(x0) <= xc:
        return [], [], (0.0, x0)
    t, x, v = 0.0, x0, v0
    s = np.sign(v) if v != 0.0 else -np.sign(x)
    segs, tps = [], []
    while True:
        def rhs(_, y, s=s):
            return [y[1], -(k / m) * y[0] - s * mu * G - (b / m) * y[1] - (D / m) * s * y[1] ** 2]

        def ev(_, y, s=s):
            return s * y[1]

        ev.terminal, ev.direction = True, -1
        r = solve_ivp(rhs, (t, t_end), [x, v], method="DOP853", rtol=1e-12, atol=1e-14,
                      events=ev, dense_output=True)
        assert r.success
        if r.status != 1:
            segs.append((t, t_end, r.sol))
            return segs, tps, None
        t_ev, y_ev = r.t_events[0][0], r.y_events[0][0]
        segs.append((t, t_ev, r.sol))
        t, x, v = t_ev, y_ev[0], 0.0
        tps.append((t, x))
        if abs(x) <= xc:
            return segs, tps, (t, x)
        s = -np.sign(x)


def scipy_x(ref, t):
    segs, _, rest = ref
    out = np.full(t.shape, np.nan)
    for t_a, t_b, dense in segs:
        sel = (t >= t_a) & (t <= t_b)
        out[sel] = dense(t[sel])[0]
    if rest is not None:
        out[t >= rest[0]] = rest[1]
    return out


# ---------------------------------------------------------------- the cases

# Batch A: exact Coulomb cases, viscous cases, rest starts, gradient cases (tight tolerances).
W = np.sqrt(30.0)
CASES_A = [
    # name, m, k, mu, b, D, x0, v0, t_end
    ("quadrant ++", 1.0, 30.0, mu_for_xc(0.02, 1.0, 30.0), 0.0, 0.0, 0.15, 0.8, 8.0),
    ("quadrant -+", 1.0, 30.0, mu_for_xc(0.02, 1.0, 30.0), 0.0, 0.0, -0.15, 0.8, 8.0),
    ("quadrant --", 1.0, 30.0, mu_for_xc(0.02, 1.0, 30.0), 0.0, 0.0, -0.15, -0.8, 8.0),
    ("quadrant +-", 2.0, 50.0, mu_for_xc(0.02, 2.0, 50.0), 0.0, 0.0, 0.15, -0.8, 8.0),
    ("rest, paper", 1.0, 30.0, 0.1 * np.pi * W**2 * 0.2 / (2 * G), 0.0, 0.0, 0.2, 0.0, 8.0),
    ("rest, negative", 1.0, 30.0, mu_for_xc(0.03, 1.0, 30.0), 0.0, 0.0, -0.2, 0.0, 8.0),
    ("dozens of swings", 1.0, 30.0, mu_for_xc(0.2 / 84.0, 1.0, 30.0), 0.0, 0.0, 0.2, 0.3, 30.0),
    ("inside band", 1.0, 30.0, mu_for_xc(0.03, 1.0, 30.0), 0.0, 0.0, 0.01, 0.0, 8.0),
    ("all zero", 1.0, 30.0, 0.0, 0.0, 0.0, 0.0, 0.0, 8.0),
    ("viscous", 1.0, 30.0, 0.0, 0.5, 0.0, 0.2, 0.5, 6.0),
    ("harmonic", 1.5, 20.0, 0.0, 0.0, 0.0, -0.1, 0.7, 6.0),
    ("grad case", 1.0, 30.0, 0.05, 0.1, 0.5, 0.2, 0.3, 6.0),
    ("grad case mu=0", 1.0, 30.0, 0.0, 0.2, 0.8, -0.1, 0.5, 6.0),
]
COULOMB_A = [0, 1, 2, 3, 4, 5, 6, 7]


def case_arrays(cases):
    cols = list(zip(*cases, strict=True))[1:]
    return [np.array(c, dtype=float) for c in cols]


def random_cases(n, seed):
    """Random (m, k, mu, b, D, x0, v0): each damping sometimes exactly zero, all quadrants."""
    rng = np.random.default_rng(seed)
    m = rng.uniform(0.5, 2.0, n)
    k = rng.uniform(10.0, 60.0, n)
    mu = rng.uniform(0.0, 0.06, n) * (rng.random(n) > 0.25)
    b = rng.uniform(0.0, 1.0, n) * (rng.random(n) > 0.35)
    D = rng.uniform(0.0, 3.0, n) * (rng.random(n) > 0.35)
    x0 = rng.uniform(-0.3, 0.3, n)
    v0 = rng.uniform(-1.5, 1.5, n) * (rng.random(n) > 0.2)
    return m, k, mu, b, D, x0, v0


N_B = 32
T_END_B = 4.0


@pytest.fixture(scope="module")
def batch_a():
    m, k, mu, b, D, x0, v0, t_end = case_arrays(CASES_A)
    osc = Oscillator(m=m, k=k, mu=mu, b=b, D=D)
    return solve_reference(osc, x0, v0, t_end=t_end, **TIGHT)


@pytest.fixture(scope="module")
def batch_b():
    m, k, mu, b, D, x0, v0 = random_cases(N_B, seed=1)

    @jax.jit
    @jax.vmap
    def solve(m, k, mu, b, D, x0, v0):
        return solve_reference(Oscillator(m=m, k=k, mu=mu, b=b, D=D), x0, v0, t_end=T_END_B,
                               **DEFAULT)

    sol = solve(*(jnp.asarray(a) for a in (m, k, mu, b, D, x0, v0)))
    return (m, k, mu, b, D, x0, v0), sol


T_GRID = np.linspace(0.0, 30.0, 6001)
T_BEFORE = -0.5


@pytest.fixture(scope="module")
def dense(batch_a, batch_b):
    """x, v, E of both batches on one time grid (one compiled evaluation per batch)."""
    t = np.concatenate([[T_BEFORE], T_GRID])
    out = []
    for sol in (batch_a, batch_b[1]):
        x, v, e = (np.asarray(f(t)) for f in (sol.x, sol.v, sol.energy))
        assert np.all(np.isnan(x[:, 0])) and np.all(np.isnan(v[:, 0]))  # before the start
        out.append((x[:, 1:], v[:, 1:], e[:, 1:]))
    return T_GRID, out[0], out[1]


# ---------------------------------------------------------------- exact Coulomb friction


def test_coulomb_turning_points_exact(batch_a):
    assert np.all(np.asarray(batch_a.valid))
    tn_all, xn_all = batch_a.turning_points(90)
    for i in COULOMB_A:
        _, m, k, mu, b, D, x0, v0, _ = CASES_A[i]
        t_ex, x_ex = coulomb_exact(m, k, mu, x0, v0)
        a0 = np.hypot(x0, v0 / np.sqrt(k / m))
        n = len(t_ex)
        tn, xn = np.asarray(tn_all[i]), np.asarray(xn_all[i])
        assert np.all(np.isnan(tn[n:])) and np.all(np.isnan(xn[n:]))
        np.testing.assert_allclose(xn[:n], x_ex, rtol=0, atol=1e-10 * a0)
        np.testing.assert_allclose(tn[:n], t_ex, rtol=0, atol=1e-10 * np.sqrt(m / k))
        assert int(batch_a.n_swings[i]) == n
        if n:
            assert bool(batch_a.halted[i])
            assert float(batch_a.halt_time[i]) == pytest.approx(t_ex[-1], abs=1e-10)
            assert float(batch_a.halt_position[i]) == pytest.approx(x_ex[-1], abs=1e-10 * a0)
    assert int(batch_a.n_swings[6]) >= 36  # several dozen swings


def test_design_numbers(batch_a):
    """docs/DESIGN.md section 4: Coulomb d0/(w0 A0) = 0.1 from rest at 0.2 m."""
    i = 4
    w0 = np.sqrt(30.0)
    tn, xn = batch_a.turning_points(4)
    np.testing.assert_allclose(np.asarray(xn[i, :3]), [-0.13717, 0.07434, -0.01150], atol=5e-6)
    np.testing.assert_allclose(np.asarray(tn[i, :3]), np.arange(1, 4) * np.pi / w0, atol=1e-10)
    assert np.isnan(float(tn[i, 3]))
    assert float(batch_a.halt_position[i]) == pytest.approx(-0.01150, abs=5e-6)


def test_coulomb_motion_between_turning_points(batch_a, dense):
    """x(t) between the turning points is the exact harmonic half-swing."""
    t, (x, _, _), _ = dense
    for i in (0, 4, 6):
        _, m, k, mu, b, D, x0, v0, t_end = CASES_A[i]
        w0 = np.sqrt(k / m)
        xc = mu * G / w0**2
        t_ex, x_ex = coulomb_exact(m, k, mu, x0, v0)
        # start of every swing: (t_j, x_j, v_j); the first from the initial state
        starts = [(0.0, x0, v0)] + [(tj, xj, 0.0)
                                    for tj, xj in zip(t_ex[:-1], x_ex[:-1], strict=True)]
        ref = np.full(t.shape, np.nan)
        for j, (tj, xj, vj) in enumerate(starts):
            s = np.sign(vj) if vj != 0.0 else -np.sign(xj)
            c = -s * xc
            sel = (t >= tj) & (t <= t_ex[j])
            ref[sel] = c + (xj - c) * np.cos(w0 * (t[sel] - tj)) + vj / w0 * np.sin(
                w0 * (t[sel] - tj))
        ref[t >= t_ex[-1]] = x_ex[-1]
        a0 = np.hypot(x0, v0 / w0)
        sel = t <= t_end
        np.testing.assert_allclose(x[i][sel], ref[sel], rtol=0, atol=1e-10 * a0)


def test_rest_starts(batch_a, dense):
    t, (x, v, _), _ = dense
    for i, x0 in ((7, 0.01), (8, 0.0)):
        assert bool(batch_a.halted[i]) and bool(batch_a.valid[i])
        assert float(batch_a.halt_time[i]) == 0.0
        assert float(batch_a.halt_position[i]) == x0
        assert int(batch_a.n_swings[i]) == 0
        assert np.all(x[i] == x0) and np.all(v[i] == 0.0)
        assert np.all(np.isnan(np.asarray(batch_a.turning_points(3)[0][i])))


# ---------------------------------------------------------------- mu = 0


def test_viscous_exact_and_never_halts(batch_a, dense):
    t, (x, _, _), _ = dense
    for i in (9, 10):
        _, m, k, mu, b, D, x0, v0, t_end = CASES_A[i]
        assert bool(batch_a.valid[i]) and not bool(batch_a.halted[i])
        assert float(batch_a.halt_time[i]) == np.inf
        assert np.isnan(float(batch_a.halt_position[i]))
        sel = t <= t_end
        a0 = np.hypot(x0, v0 / np.sqrt(k / m))
        np.testing.assert_allclose(x[i][sel], viscous_exact(m, k, b, x0, v0, t[sel]), rtol=0,
                                   atol=1e-9 * a0)
        assert np.all(np.isnan(x[i][t > t_end]))  # not integrated beyond t_end
        # turning points of the damped cosine: v = 0 at (theta + n pi) / wd
        gamma = b / (2 * m)
        wd = np.sqrt(k / m - gamma**2)
        c_cos, c_sin = x0, (v0 + gamma * x0) / wd
        theta = np.arctan2(c_sin * wd - gamma * c_cos, c_cos * wd + gamma * c_sin) % np.pi
        t_ex = (theta + np.pi * np.arange(40)) / wd
        t_ex = t_ex[(t_ex > 0) & (t_ex < t_end)]
        tn, xn = batch_a.turning_points(len(t_ex) + 1)
        np.testing.assert_allclose(np.asarray(tn[i, :-1]), t_ex, rtol=0, atol=1e-10)
        np.testing.assert_allclose(np.asarray(xn[i, :-1]),
                                   viscous_exact(m, k, b, x0, v0, t_ex), rtol=0, atol=1e-10 * a0)
        assert np.isnan(float(tn[i, -1]))  # the motion at t_end is not a turning point


# ---------------------------------------------------------------- scipy, random cases


@pytest.fixture(scope="module")
def scipy_refs(batch_b):
    (m, k, mu, b, D, x0, v0), _ = batch_b
    return [scipy_reference(m[i], k[i], mu[i], b[i], D[i], x0[i], v0[i], T_END_B)
            for i in range(N_B)]


def test_against_scipy_dense(batch_b, dense, scipy_refs):
    (m, k, mu, b, D, x0, v0), sol = batch_b
    t, _, (x, _, _) = dense
    assert np.all(np.asarray(sol.valid))
    sel = t <= T_END_B
    worst = 0.0
    for i in range(N_B):
        a0 = np.hypot(x0[i], v0[i] / np.sqrt(k[i] / m[i]))
        err = np.max(np.abs(x[i][sel] - scipy_x(scipy_refs[i], t[sel]))) / a0
        worst = max(worst, err)
    assert worst <= 1e-8


def test_against_scipy_events(batch_b, scipy_refs):
    (m, k, mu, b, D, x0, v0), sol = batch_b
    tn_all, xn_all = sol.turning_points(64)
    n_halted = 0
    for i in range(N_B):
        _, tps, rest = scipy_refs[i]
        a0 = np.hypot(x0[i], v0[i] / np.sqrt(k[i] / m[i]))
        n = len(tps)
        tn, xn = np.asarray(tn_all[i]), np.asarray(xn_all[i])
        if n:
            np.testing.assert_allclose(tn[:n], [p[0] for p in tps], rtol=0, atol=1e-8)
            np.testing.assert_allclose(xn[:n], [p[1] for p in tps], rtol=0, atol=1e-8 * a0)
        assert np.all(np.isnan(tn[n:]))
        if rest is None:
            assert not bool(sol.halted[i]) and float(sol.halt_time[i]) == np.inf
        else:
            n_halted += 1
            assert bool(sol.halted[i])
            assert float(sol.halt_time[i]) == pytest.approx(rest[0], abs=1e-8)
            assert float(sol.halt_position[i]) == pytest.approx(rest[1], abs=1e-8 * a0)
    assert 3 <= n_halted < N_B  # both kinds are covered
    # the step table holds exactly the stored steps (t_a, 1/h, c_0..c_9), in time order and
    # without gaps: each row starts within the step before (at its end, or at the turning
    # point inside it); the padding after them is inf
    rows, n_rows = np.asarray(sol.rows), np.asarray(sol.n_rows)
    for i in range(N_B):
        real = rows[i, : n_rows[i]]
        t_a, h = real[:, 0], 1.0 / real[:, 1]
        assert np.all(t_a[1:] > t_a[:-1])
        assert np.all(t_a[1:] <= t_a[:-1] + h[:-1] * (1.0 + 1e-12))
        assert np.all(np.isinf(rows[i, n_rows[i]:, 0]))


def test_energy_never_increases(batch_b, dense):
    (m, k, mu, b, D, x0, v0), sol = batch_b
    t, _, (x, v, e) = dense
    sel = t <= T_END_B
    e = e[:, sel]
    np.testing.assert_allclose(e, 0.5 * k[:, None] * x[:, sel] ** 2
                               + 0.5 * m[:, None] * v[:, sel] ** 2, rtol=1e-14)
    e0 = 0.5 * k * x0**2 + 0.5 * m * v0**2
    np.testing.assert_allclose(e[:, 0], e0, rtol=1e-12)
    assert np.all(np.diff(e, axis=1) <= 1e-9 * e0[:, None])
    halted = np.asarray(sol.halted)
    xc = mu * G * m / k
    assert np.all(np.abs(np.asarray(sol.halt_position)[halted]) <= xc[halted])


# ---------------------------------------------------------------- derivatives

I_EVAL = (180, 341)  # x(t) is differentiated at these points of T_GRID (0.9 s, 1.705 s)
T_EVAL = tuple(float(T_GRID[i]) for i in I_EVAL)
GRAD_CASES = [11, 12]
TRACES = {"forward": 0}


def _outputs(p, t_end, **kw):
    """x at T_EVAL, halt_time, halt_position for p = (mu, b, D, x0, v0); and the valid flag."""
    mu, b, D, x0, v0 = p
    sol = solve_reference(Oscillator(m=1.0, k=30.0, mu=mu, b=b, D=D), x0, v0, t_end=t_end,
                          **TIGHT, **kw)
    out = jnp.concatenate([sol.x(jnp.array(T_EVAL)),
                           jnp.stack([sol.halt_time, sol.halt_position])])
    return out, sol.valid


@pytest.fixture(scope="module")
def reverse_fn():
    """Reverse mode with the default solver and adjoint: (outputs, w^T J, valid)."""

    @jax.jit
    def fn(p, t_end, w):
        out, vjp, valid = jax.vjp(lambda q: _outputs(q, t_end), p, has_aux=True)
        return out, vjp(w)[0], valid

    return fn


@pytest.fixture(scope="module")
def forward_fn():
    """Forward mode (jax.jacfwd, adjoint="forward"): (outputs, J, valid)."""

    @jax.jit
    def fn(p, t_end):
        TRACES["forward"] += 1

        def with_aux(q):
            out, valid = _outputs(q, t_end, adjoint="forward")
            return out, (out, valid)

        jac, (out, valid) = jax.jacfwd(with_aux, has_aux=True)(p)
        return out, jac, valid

    return fn


def _params(i):
    _, m, k, mu, b, D, x0, v0, t_end = CASES_A[i]
    return jnp.array([mu, b, D, x0, v0]), t_end


def _finite_differences(values, p, eps=1e-5):
    """Central differences of values(p) (an array) in every component of p; one-sided (second
    order) for a damping constant (mu, b, D: the first three) at 0, where p - eps is outside the
    domain (negative constants are flagged invalid, NaN)."""
    cols = []
    for j, e in enumerate(np.eye(len(p))):
        if j < 3 and float(p[j]) - eps < 0.0:
            cols.append((-3.0 * np.asarray(values(p)) + 4.0 * np.asarray(values(p + eps * e))
                         - np.asarray(values(p + 2 * eps * e))) / (2 * eps))
        else:
            cols.append((np.asarray(values(p + eps * e)) - np.asarray(values(p - eps * e)))
                        / (2 * eps))
    return np.stack(cols, axis=1)


def _compare(jac, fd, finite_rows):
    """Rows of finite outputs match the differences; rows of inf/NaN outputs are zero."""
    jac = np.asarray(jac)
    for r in range(jac.shape[0]):
        if not finite_rows[r]:
            assert np.all(jac[r] == 0.0)
            continue
        scale = max(1.0, np.max(np.abs(fd[r])))
        np.testing.assert_allclose(jac[r], fd[r], rtol=0, atol=2e-6 * scale)


@pytest.mark.slow  # compiles the reverse pass of the default solver: about a minute
@pytest.mark.parametrize("i", GRAD_CASES)
def test_grad_matches_finite_differences(reverse_fn, batch_a, dense, i):
    p, t_end = _params(i)
    n_out = len(I_EVAL) + 2
    rows = []
    for r in range(n_out):
        out, g, valid = reverse_fn(p, t_end, jnp.eye(n_out)[r])
        assert bool(valid)
        rows.append(np.asarray(g))
    out = np.asarray(out)
    # the unbatched solve equals the vmapped one of batch A (same settings)
    ref = np.concatenate([dense[1][0][i][list(I_EVAL)],
                          [float(batch_a.halt_time[i]), float(batch_a.halt_position[i])]])
    np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-14)
    with np.errstate(invalid="ignore"):
        fd = _finite_differences(lambda q: reverse_fn(q, t_end, jnp.zeros(n_out))[0], p)
    _compare(np.stack(rows), fd, np.isfinite(out))


@pytest.mark.parametrize("i", GRAD_CASES)
def test_jacfwd_matches_finite_differences(forward_fn, i):
    p, t_end = _params(i)
    out, jac, valid = forward_fn(p, t_end)
    assert bool(valid)
    with np.errstate(invalid="ignore"):
        fd = _finite_differences(lambda q: forward_fn(q, t_end)[0], p)
    _compare(jac, fd, np.isfinite(np.asarray(out)))


def test_no_nan_at_zero_damping_and_rest(forward_fn, reverse_fn):
    for p in ([0.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.2, 0.3]):
        p = jnp.array(p)
        out, jac, valid = forward_fn(p, 3.0)
        w = np.where(np.isfinite(np.asarray(out)), 1.0, 0.0)  # not weakly typed: no retrace
        out_r, g, valid_r = reverse_fn(p, 3.0, w)
        assert bool(valid) and bool(valid_r)
        assert np.all(np.isfinite(np.asarray(jac))) and np.all(np.isfinite(np.asarray(g)))
        if float(p[3]) == 0.0:  # at rest: x(t) = 0, halt_time = 0, halt_position = 0
            np.testing.assert_array_equal(np.asarray(out), [0.0, 0.0, 0.0, 0.0])
            np.testing.assert_array_equal(np.asarray(out_r), [0.0, 0.0, 0.0, 0.0])
        else:  # undamped: never halts
            assert float(out[2]) == np.inf and np.isnan(float(out[3]))
            assert np.all(np.isfinite(np.asarray(out[:2])))


def test_no_recompile_and_budget_under_jit(forward_fn):
    p, _ = _params(12)
    forward_fn(p, 6.0)
    before = TRACES["forward"]
    # new parameter values, and a t_end (mu = 0: about 100 swings) beyond max_swings = 64:
    # no error under jit, valid = False
    _, _, valid = forward_fn(p * 1.01, 60.0)
    assert TRACES["forward"] == before
    assert not bool(valid)


# ---------------------------------------------------------------- errors


def test_budget_exhausted_eagerly(batch_a):
    m, k, mu, b, D, x0, v0, t_end = case_arrays(CASES_A)
    t_end[10] = 60.0  # the harmonic case: about 100 swings, more than max_swings = 64
    with pytest.raises(ValueError, match="max_swings"):
        solve_reference(Oscillator(m=m, k=k, mu=mu, b=b, D=D), x0, v0, t_end=t_end, **TIGHT)


@pytest.mark.parametrize("bad", [dict(x0=np.nan), dict(v0=np.inf)])
def test_nonfinite_initial_state(bad):
    kw = dict(x0=0.1, v0=0.0)
    kw.update(bad)
    with pytest.raises(ValueError, match="x0" if "x0" in bad else "v0"):
        solve_reference(Oscillator(m=1.0, k=30.0, mu=0.01), kw["x0"], kw["v0"])


def test_bad_t_end():
    with pytest.raises(ValueError, match="t_end"):
        solve_reference(Oscillator(m=1.0, k=30.0), 0.1, 0.0, t_end=-1.0)


def test_solution_type(batch_a):
    assert isinstance(batch_a, ReferenceSolution)
    assert batch_a.swing_times.shape == (len(CASES_A), 64)
    assert batch_a.turning_points(70)[0].shape == (len(CASES_A), 70)


# ---------------------------------------------------------------- samples, cost, accuracy

N_C = 12
T_END_C = 3.0
TS_C = np.linspace(0.0, T_END_C, 301)


def _cases_c():
    """Random cases with every damping term and a cubic stiffness (hardening and softening)."""
    rng = np.random.default_rng(7)
    m, k, mu, b, D, x0, v0 = random_cases(N_C, seed=7)
    k3 = rng.uniform(-0.3, 1.0, N_C) * k / 0.3**2 * (rng.random(N_C) > 0.25)
    return m, k, mu, b, D, x0, v0, k3


@pytest.fixture(scope="module")
def batch_c():
    m, k, mu, b, D, x0, v0, k3 = _cases_c()
    osc = Oscillator(m=m, k=k, mu=mu, b=b, D=D, k3=k3)
    return (m, k, mu, b, D, x0, v0, k3), solve_reference(osc, x0, v0, t_end=T_END_C,
                                                          ts=TS_C, **TIGHT)


def test_samples_with_every_damping_and_k3_against_scipy(batch_c):
    """solve(ts=) fills x, v at the samples: 1e-10 A0 from scipy's DOP853 with events."""
    (m, k, mu, b, D, x0, v0, k3), sol = batch_c
    assert np.all(np.asarray(sol.valid))
    xs, vs = (np.asarray(a) for a in sol.state(TS_C))  # the samples of the solve
    assert xs is not None and xs.shape == (N_C, TS_C.size)
    for i in range(N_C):
        segs, _, rest = scipy_stick_slip(m[i], k[i], mu[i], b[i], D[i], x0[i], v0[i], T_END_C,
                                         k3=k3[i])
        x_sp, v_sp = evaluate(segs, rest, TS_C)
        a0 = np.hypot(x0[i], v0[i] / np.sqrt(k[i] / m[i]))
        np.testing.assert_allclose(xs[i], x_sp, rtol=0, atol=1e-10 * a0)
        np.testing.assert_allclose(vs[i], v_sp, rtol=0, atol=1e-9 * a0 * np.sqrt(k[i] / m[i]))


def test_filled_samples_equal_the_dense_output_on_any_times(batch_c):
    """The samples of solve(ts=) are the dense output's values there; unsorted times (the
    binary-search path) give the same numbers as sorted ones (the merge)."""
    _, sol = batch_c
    filled = np.asarray(sol.x(TS_C))
    shuffled = np.random.default_rng(0).permutation(TS_C.size)
    again = np.asarray(sol.x(TS_C[shuffled]))[:, np.argsort(shuffled)]
    if resolve_engine("auto") == "dampax":
        np.testing.assert_array_equal(filled, again)
    else:  # on a CUDA GPU the fused kernel filled them: its own rounding of the same sums
        np.testing.assert_allclose(filled, again, rtol=1e-14, atol=1e-15)
    sub = TS_C[::7] + 1e-3  # sorted, not a uniform grid
    np.testing.assert_array_equal(np.asarray(sol.x(sub)), np.asarray(sol.x(sub[::-1]))[:, ::-1])


def test_samples_under_jit_and_vmap():
    """Under jit, x(ts) of the solve's own ts returns its samples; vmapped scalar solves equal
    the batched one."""
    m, k, mu, b, D, x0, v0, k3 = (jnp.asarray(a[:4]) for a in _cases_c())

    def one(m, k, mu, b, D, x0, v0, k3):
        sol = solve_reference(Oscillator(m=m, k=k, mu=mu, b=b, D=D, k3=k3), x0, v0,
                              t_end=T_END_C, ts=TS_C, max_swings=24)
        return sol.x(TS_C), sol.x(TS_C[::-1])

    a, back = jax.jit(jax.vmap(one))(m, k, mu, b, D, x0, v0, k3)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(back)[:, ::-1])


def test_cost_follows_the_motion():
    """A trajectory that halts stores the steps of its motion and nothing after the halt: the
    same rows for t_end = 3 s and 300 s (same budget); one that never halts stores steps in
    proportion to its window."""
    osc = Oscillator(m=1.0, k=30.0, mu=0.05, D=2.0)  # halts at 2.3 s
    short = solve_reference(osc, 0.2, 0.0, t_end=3.0, max_swings=400)
    long = solve_reference(osc, 0.2, 0.0, t_end=300.0, max_swings=400)
    assert bool(short.halted) and bool(long.halted)
    assert int(short.n_rows) == int(long.n_rows) < 60
    np.testing.assert_array_equal(np.asarray(short.rows), np.asarray(long.rows))
    free = Oscillator(m=1.0, k=30.0, b=0.05)
    n1 = int(solve_reference(free, 0.2, 0.0, t_end=10.0, max_swings=400).n_rows)
    n2 = int(solve_reference(free, 0.2, 0.0, t_end=20.0, max_swings=400).n_rows)
    assert 1.8 < n2 / n1 < 2.2


def test_grad_through_many_samples_matches_finite_differences():
    """Reverse mode through the dense output's chunked path (>= 32 sorted samples) and through
    the samples of solve(ts=), against central differences."""
    ts = jnp.linspace(0.0, 3.0, 200)

    def f(q, with_ts):
        mu, D = q
        sol = solve_reference(Oscillator(m=1.0, k=30.0, mu=mu, D=D), 0.2, 0.1, t_end=3.0,
                              max_swings=24, ts=ts if with_ts else None)
        return jnp.sum(sol.x(ts) * jnp.cos(ts))

    # one program per path and derivative (eager, every op would compile alone)
    grad, f = jax.jit(jax.grad(f), static_argnums=1), jax.jit(f, static_argnums=1)
    q = jnp.array([0.01, 1.0])
    for with_ts in (False, True):
        g = np.asarray(grad(q, with_ts))
        fd = _finite_differences(lambda p, w=with_ts: np.asarray(f(p, w))[None], q, eps=1e-6)[0]
        np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_samples_past_the_default_span_are_solved_and_past_t_end_refused():
    """solve(ts=...) without t_end reaches the last sample (the default span, 25 periods, left
    x NaN after it with a successful result): a linear viscous decay against its closed form;
    an explicit t_end before the last sample is a ValueError naming ts."""
    import math

    import dampax as dp

    m, k, b, x0 = 1.0, 30.0, 0.01, 0.2
    ts = np.array([0.0, 10.0, 100.0])
    sol = dp.solve(dp.Oscillator(m=m, k=k, b=b), x0, 0.0, method="reference", ts=ts)
    gamma = b / (2.0 * m)
    wd = math.sqrt(k / m - gamma**2)
    exact = x0 * np.exp(-gamma * ts) * (np.cos(wd * ts) + gamma / wd * np.sin(wd * ts))
    np.testing.assert_allclose(np.asarray(sol.x(ts)), exact, rtol=0, atol=1e-8)
    with pytest.raises(ValueError, match="ts: samples up to 100 s lie beyond t_end = 50 s"):
        dp.solve(dp.Oscillator(m=m, k=k, b=b), x0, 0.0, method="reference", ts=ts, t_end=50.0)
