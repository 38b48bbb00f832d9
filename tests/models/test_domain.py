"""Every model's domain (issue 15): outside it valid = False under jit and vmap, a start at rest
inside the band stays at rest, options are checked eagerly, and a property test over the whole
input space (hypothesis, under jit) with the reference compared against scipy.

The domain rule is written out here in numpy from the design sheet (m, k, g finite and > 0;
mu, b, D finite and >= 0; the ansatz needs d1 < w0; rizcallah b = D = 0; coulomb_exact D = 0 and
b < 2 sqrt(k m); a start at rest with |x0| <= xc is exact for every model), not read from dampax.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import evaluate, ratios_to_constants, scipy_stick_slip
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import dampax as dp

MODELS = {name: m.solve_options for name, m in dp.MODELS.items()}
MODELS["rizcallah_impulse"] = dict(method="rizcallah", kappa=math.pi / 2)
ANSATZ = ("matched", "undamped", "matched_tail")
S = np.linspace(0.0, 40.0, 801)  # w0 t: about six periods, inside the reference's t_end
_COMPILED = {}


def compiled(model):
    """One jitted solve per model; the inputs (m, k, g, mu, b, D, x0, v0) are one array."""
    if model not in _COMPILED:
        opts = MODELS[model]

        @jax.jit
        def run(p):
            m, k, g, mu, b, D, x0, v0 = p
            sol = dp.solve(dp.Oscillator(m=m, k=k, mu=mu, b=b, D=D, g=g), x0, v0, **opts)
            ts = jnp.asarray(S) / jnp.sqrt(k / m)
            return (sol.result == dp.RESULTS.successful, sol.result._value, sol.x(ts),
                    sol.v(ts), sol.energy(ts), sol.halt_time, sol.halt_position)

        _COMPILED[model] = run
    return _COMPILED[model]


def solve_jit(model, **kw):
    p = dict(m=1.0, k=30.0, g=9.81, mu=0.05, b=0.0, D=0.0, x0=0.2, v0=0.0) | kw
    return compiled(model)(jnp.asarray(list(p.values()), dtype=float))


def in_domain(model, p):
    """The design sheet's domain of ``model`` at the inputs p (numpy, independent of dampax)."""
    m, k, g, mu, b, D, x0, v0 = (float(a) for a in p)
    if not all(math.isfinite(a) for a in p):
        return False
    if min(m, k, g) <= 0.0 or min(mu, b, D) < 0.0:
        return False
    if v0 == 0.0 and abs(x0) <= mu * g * m / k:  # at rest inside the band: exact everywhere
        return True
    underdamped = b / (2.0 * m) < math.sqrt(k / m)
    if model in ANSATZ:
        return underdamped
    if model.startswith("rizcallah"):
        return b == 0.0 and D == 0.0
    if model == "coulomb_exact":
        return D == 0.0 and underdamped
    return True


def reason(value):
    """The message of a result returned as its integer value."""
    return dp.RESULTS[eqx.tree_at(lambda r: r._value, dp.RESULTS.successful, jnp.asarray(value))]


# ------------------------------------------------------------------------------------------
# out of the domain: a reason, NaN values, under jit and vmap

BAD_CONSTANTS = [("m", math.nan), ("m", 0.0), ("m", -1.0), ("k", -30.0), ("k", math.inf),
                 ("g", 0.0), ("g", -9.81), ("mu", -0.05), ("mu", math.nan), ("b", -0.1),
                 ("D", -1.0)]


@pytest.mark.parametrize("model", MODELS)
def test_out_of_domain_constants_under_jit(model):
    for field, value in BAD_CONSTANTS:
        valid, result, x, v, e, halt_t, halt_x = solve_jit(model, **{field: value})
        assert not bool(valid), (model, field, value)
        assert reason(result) == dp.RESULTS[dp.RESULTS.invalid_constants], (model, field)
        assert np.all(np.isnan(x)) and np.all(np.isnan(e)), (model, field, value)
        assert np.isnan(halt_t) and np.isnan(halt_x), (model, field, value, halt_t)
    for field in ("x0", "v0"):
        valid, result, x, *_ = solve_jit(model, **{field: math.nan})
        assert reason(result) == dp.RESULTS[dp.RESULTS.nonfinite_state], (model, field)
        assert np.all(np.isnan(x))
    assert bool(solve_jit(model)[0]), model  # the same compiled solve, inside the domain


@pytest.mark.parametrize("model", [name for name in MODELS if name != "reference"])
def test_no_halt_where_the_model_does_not_exist(model):
    # outside each model's own domain (drag for the Coulomb models, overdamping for the
    # ansatz, static friction above the sliding one for the models that assume mu_s = mu)
    # the halt is NaN too, not the answer of another model
    cases = [dict(mu=0.02, D=0.5), dict(mu=0.02, b=20.0), dict(mu=0.02, b=0.3, mu_s=0.05)]

    @jax.jit
    def run(mu, b, D, mu_s):
        osc = dp.Oscillator(m=1.0, k=30.0, mu=mu, b=b, D=D, mu_s=mu_s)
        sol = dp.solve(osc, 0.2, 0.0, **MODELS[model])
        return sol.valid, sol.x(1.0), sol.halt_time, sol.halt_position

    for case in cases:
        p = dict(mu=0.02, b=0.0, D=0.0) | case
        valid, x, halt_t, halt_x = run(p["mu"], p["b"], p["D"], p.get("mu_s", p["mu"]))
        if not bool(valid):
            assert np.isnan(x) and np.isnan(halt_t) and np.isnan(halt_x), (model, case)
        else:
            assert in_domain(model, [1.0, 30.0, 9.81, p["mu"], p["b"], p["D"], 0.2, 0.0])
            assert np.isfinite(x) and not np.isnan(halt_t), (model, case)


@pytest.mark.parametrize("model", ["matched", "undamped", "matched_tail", "coulomb_exact",
                                   "reference"])
def test_out_of_domain_under_vmap_per_element(model):
    # rows: good, negative m, g = 0, good: only the middle two are flagged
    p = np.tile([1.0, 30.0, 9.81, 0.05, 0.0, 0.0, 0.2, 0.0], (4, 1))
    p[1, 0], p[2, 2] = -1.0, 0.0
    opts = MODELS[model]

    def run(row):
        m, k, g, mu, b, D, x0, v0 = row
        sol = dp.solve(dp.Oscillator(m=m, k=k, mu=mu, b=b, D=D, g=g), x0, v0, **opts)
        return sol.valid, sol.x(0.3)

    valid, x = jax.jit(jax.vmap(run))(jnp.asarray(p))
    np.testing.assert_array_equal(np.asarray(valid), [True, False, False, True])
    assert np.all(np.isfinite(np.asarray(x)[[0, 3]])) and np.all(np.isnan(np.asarray(x)[1:3]))
    assert float(x[0]) == float(x[3])


@pytest.mark.parametrize("model", ANSATZ)
@pytest.mark.parametrize("factor", [1.0, 3.0])  # critical and overdamped: b = factor 2 sqrt(k m)
def test_ansatz_needs_underdamping(model, factor):
    b = factor * 2.0 * math.sqrt(30.0)
    valid, result, x, *_ = solve_jit(model, mu=0.0, b=b)
    assert not bool(valid) and np.all(np.isnan(x))
    assert reason(result) == dp.RESULTS[dp.RESULTS.ansatz_overdamped]
    assert bool(solve_jit(model, mu=0.0, b=0.99 * 2.0 * math.sqrt(30.0))[0])
    with pytest.raises(ValueError, match=r"^b: .*underdamping"):
        dp.solve(dp.Oscillator(m=1.0, k=30.0, b=b), 0.2, 0.0, **MODELS[model])


def test_reference_t_end_traced_out_of_domain():
    osc = dp.Oscillator(m=1.0, k=30.0, mu=0.05)
    f = jax.jit(lambda te: dp.solve(osc, 0.2, 0.0, method="reference", t_end=te))
    for t_end in (-1.0, 0.0, math.nan):
        sol = f(t_end)
        assert bool(sol.result == dp.RESULTS.invalid_t_end)
        assert np.isnan(float(sol.x(0.1)))
    assert bool(f(2.0).valid)


def test_registry_leaves_out_what_does_not_apply():
    # overdamped with friction: only the reference applies; each listed model solves eagerly
    over = dp.Oscillator(m=1.0, k=30.0, mu=0.05, b=3.0 * 2.0 * math.sqrt(30.0))
    assert dp._models._registry.applicable_models(over) == ("reference",)
    under = dp.Oscillator(m=1.0, k=30.0, mu=0.05, b=0.5)
    assert dp._models._registry.applicable_models(under) == ("matched", "undamped", "matched_tail",
                                                   "coulomb_exact", "reference")


def test_rizcallah_does_not_rest_beyond_its_amplitude():
    # xc = 1.57 A0 and a small start velocity: the model would swing out to 2.13 A0 and rest
    # there, with four times its initial energy (found by the property test)
    sol = jax.jit(lambda v0: dp.solve(dp.Oscillator(m=1.0, k=1.0, mu=0.16012195), 0.96891242,
                                      v0, method="rizcallah"))(-0.24740396)
    assert bool(sol.result == dp.RESULTS.rizcallah_gains_energy)
    with pytest.raises(ValueError, match="^mu: Rizcallah"):
        dp.solve(dp.Oscillator(m=1.0, k=1.0, mu=0.16012195), 0.96891242, -0.24740396,
                 method="rizcallah")


def test_tiny_friction_stays_finite():
    # mu = 1e-300: c = d0/A of eq. 20 is so small that (c + b'/2)^2 underflows; the halt time
    # is then the series value 1/c (found by the property test: it was NaN with valid = True)
    for model in ("undamped", "matched", "matched_tail"):
        valid, _, x, _, e, halt_t, _ = solve_jit(model, mu=1e-300, x0=1.0)
        assert bool(valid) and np.all(np.isfinite(x)) and np.all(np.isfinite(e)), model
        assert float(halt_t) > 1e290, model
        np.testing.assert_allclose(x, np.cos(S), atol=1e-12)  # the undamped motion


# ------------------------------------------------------------------------------------------
# a start at rest inside the band: the trivial answer from every model


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("case", [
    dict(mu=1e3, x0=0.2),  # the mu = 1e3
    dict(mu=0.3, x0=-0.05, b=3.0 * 2.0 * math.sqrt(30.0), D=1e6),  # overdamped, strong drag
    dict(mu=0.05, x0=0.05 * 9.81 / 30.0),  # on the band's edge (static friction still holds)
])
def test_start_at_rest_inside_the_band_stays(model, case):
    x0 = case["x0"]
    fields = {k: v for k, v in case.items() if k != "x0"}
    valid, _, x, v, e, halt_t, halt_x = solve_jit(model, x0=x0, **fields)
    assert bool(valid)
    np.testing.assert_array_equal(np.asarray(x), x0)
    np.testing.assert_array_equal(np.asarray(v), 0.0)
    np.testing.assert_allclose(np.asarray(e), 0.5 * 30.0 * x0**2, rtol=1e-15)
    assert float(halt_t) == 0.0 and float(halt_x) == x0
    sol = dp.solve(dp.Oscillator(m=1.0, k=30.0, **fields), x0, 0.0, **MODELS[model])  # eager
    assert float(sol.x(1.0)) == x0 and float(sol.halt_time) == 0.0
    assert np.all(np.isnan(np.asarray(dp.turning_points(sol, 3)[0])))


@pytest.mark.parametrize("model", ["matched", "undamped", "rizcallah"])
def test_start_at_rest_gradients(model):
    # x(t) = x0: dx/dx0 = 1 and dx/dmu = 0, finite (no NaN from the unused branch)
    def x_at(x0, mu):
        osc = dp.Oscillator(m=1.0, k=30.0, mu=mu)
        return dp.solve(osc, x0, 0.0, **MODELS[model]).x(0.7)

    gx, gmu = jax.grad(x_at, argnums=(0, 1))(0.05, 0.3)
    assert float(gx) == 1.0 and float(gmu) == 0.0


# ------------------------------------------------------------------------------------------
# options are checked eagerly, naming the option


@pytest.mark.parametrize("name, kwargs", [
    ("kappa", dict(method="rizcallah", kappa=math.nan)),
    ("kappa", dict(method="rizcallah", kappa=0.0)),
    ("kappa", dict(method="rizcallah", kappa=-1.0)),
    ("kappa", dict(method="rizcallah", kappa=math.inf)),
    ("kappa", dict(method="rizcallah", kappa=1e9)),
    ("kappa", dict(method="ansatz", kappa=4.0 / math.pi)),  # the ansatz has no kappa
    ("back", dict(tail="coulomb", back=-1)),
    ("back", dict(tail="coulomb", back=1.5)),
    ("back", dict(back=1)),  # back without the tail
    ("rtol", dict(method="reference", rtol=-1e-8)),
    ("rtol", dict(method="reference", rtol=0.0)),
    ("rtol", dict(method="reference", rtol=1.0)),
    ("rtol", dict(method="reference", rtol=math.nan)),
    ("atol", dict(method="reference", atol=-1e-12)),
    ("atol", dict(method="reference", atol=math.inf)),
])
def test_options_checked_eagerly(name, kwargs):
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=0.05), 0.2, 0.0, **kwargs)


@pytest.mark.parametrize("n", [-1, 2.5, True])
def test_turning_point_count_checked(n):
    for method in ("ansatz", "coulomb_exact"):  # (the reference's check is the same helper)
        sol = dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=0.05), 0.2, 0.0, method=method)
        with pytest.raises(ValueError, match=r"^n must be an integer"):
            dp.turning_points(sol, n)


# ------------------------------------------------------------------------------------------
# the property over the whole input space

BAD = [math.nan, math.inf, -math.inf, -1.0, 0.0]
#: the analytic approximations' energy (eq. 15 and its kin) wiggles at second order in the damping
#: ratios, near the halt, where the energy left is itself of order rho^2 E0: measured up to
#: 0.13 rho^2 E0 between samples over 1,500 random draws of this test's input space
#: (rizcallah_impulse 0.128, matched 0.097, rizcallah 0.085, matched_tail 0.011; seed 1), so the
#: bound is 0.2 rho^2 (0.1 failed on a drawn Coulomb decay, rho = 0.10, at 0.1035 rho^2); a
#: damping term of the wrong sign would raise it by about 2 rho E0 per radian (0.1 rho E0 between
#: these samples, 0.05 rad apart). The exact models' energy wiggles only by rounding
APPROX = ("matched", "matched_tail", "rizcallah", "rizcallah_impulse")
APPROX_RISE = 0.2
EXACT_TOL = {"undamped": 1e-12, "coulomb_exact": 1e-12, "reference": 1e-8}


@st.composite
def inputs(draw, *, bad=True, moderate=False):
    """(m, k, g, mu, b, D, x0, v0): physical scales, damping ratios up to far beyond the
    papers' ranges, starts at rest (v0 = 0 exactly) or moving, and one input replaced by a
    non-finite, negative or zero value in a quarter of the draws."""
    m = 10.0 ** draw(st.floats(-1.0, 1.0))
    k = 10.0 ** draw(st.floats(0.0, 3.0))
    g = draw(st.sampled_from([9.81, 1.62]))
    A0 = 10.0 ** draw(st.floats(-2.0, 0.3))
    hi = 0.2 if moderate else 3.0
    r0 = draw(st.one_of(st.just(0.0), st.floats(0.0, 0.3), st.floats(0.0, hi)))
    r1 = draw(st.one_of(st.just(0.0), st.floats(0.0, 0.5 if moderate else 1.5)))
    r2 = draw(st.one_of(st.just(0.0), st.floats(0.0, 1.0 if moderate else 1.5)))
    if draw(st.booleans()):  # Coulomb only: the domain of rizcallah and coulomb_exact
        r1 = r2 = 0.0
    phi0 = draw(st.one_of(st.sampled_from([0.0, math.pi]), st.floats(-math.pi, math.pi)))
    w0 = math.sqrt(k / m)
    mu, b, D = ratios_to_constants(r0, r1, r2, m=m, k=k, A0=A0, g=g)
    x0 = A0 * math.cos(phi0)
    v0 = 0.0 if phi0 in (0.0, math.pi) else -w0 * A0 * math.sin(phi0)
    # XLA on CPU flushes subnormal numbers to zero: so does the domain rule's input
    mu, b, D = (c if c >= np.finfo(float).tiny else 0.0 for c in (mu, b, D))
    p = [m, k, g, mu, b, D, x0, v0]
    if bad and draw(st.integers(0, 3)) == 0:
        p[draw(st.integers(0, 7))] = draw(st.sampled_from(BAD))
    return np.array(p, dtype=float)


def rho(p):
    """Sum of the damping ratios d0/(w0 A0) + d1/w0 + d2 A0/w0 of eq. 21."""
    m, k, g, mu, b, D, x0, v0 = p
    w0 = math.sqrt(k / m)
    A0 = math.hypot(x0, v0 / w0)
    return (2 * mu * g / (math.pi * w0)) / (w0 * A0) + b / (2 * m * w0) + (
        4 * D * w0 / (3 * math.pi * m)) * A0 / w0


def check_property(model, p):
    valid, result, x, v, e, halt_t, halt_x = (np.asarray(a) for a in compiled(model)(p))
    if not valid:  # every value NaN, the halt's too
        assert not np.any(np.isfinite(x)), (model, p, reason(result))
        assert np.isnan(halt_t) and np.isnan(halt_x), (model, p, reason(result), halt_t)
        return
    assert in_domain(model, p), (model, p)  # valid only inside the stated domain
    assert np.all(np.isfinite(x)) and np.all(np.isfinite(v)) and np.all(np.isfinite(e)), p
    m, k, g, mu, b, D, x0, v0 = p
    E0 = 0.5 * k * x0**2 + 0.5 * m * v0**2
    if v0 == 0.0 and abs(x0) <= mu * g * m / k:  # at rest inside the band: stays there
        assert np.all(x == x0) and np.all(v == 0.0) and halt_t == 0.0 and halt_x == x0, p
        return
    tol = max(APPROX_RISE * rho(p) ** 2, 1e-12) if model in APPROX else EXACT_TOL[model]
    assert np.max(np.diff(e)) <= tol * E0, (model, p, np.max(np.diff(e)) / E0)
    assert e[0] == pytest.approx(E0, rel=1e-9), (model, p)


@pytest.mark.parametrize("model", MODELS)
@settings(max_examples=60, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(p=inputs())
def test_property_valid_means_finite_and_dissipative(model, p):
    """Every input: valid is False (and the values NaN), or the input is inside the model's
    stated domain, every value is finite and the energy never increases (beyond the
    approximations' second-order wiggle)."""
    check_property(model, p)


@pytest.mark.parametrize("model", ["undamped", "coulomb_exact"])
def test_domain_is_complete(model):
    # the converse, for the models with no condition beyond the stated domain (the matched
    # amplitude, rizcallah's halt search and the reference's budget can still fail): every
    # input inside it is valid, every input outside it is not
    rng = np.random.default_rng(3)
    for _ in range(40):
        m, k, A0 = 10 ** rng.uniform(-1, 1), 10 ** rng.uniform(0, 3), 10 ** rng.uniform(-2, 0)
        r = rng.uniform(0, 1.5, 3) * (rng.uniform(size=3) < 0.7)
        if model == "coulomb_exact":
            r[2] = 0.0
        mu, b, D = ratios_to_constants(*r, m=m, k=k, A0=A0)
        phi0 = rng.uniform(-math.pi, math.pi)
        w0 = math.sqrt(k / m)
        p = np.array([m, k, 9.81, mu, b, D, A0 * math.cos(phi0), -w0 * A0 * math.sin(phi0)])
        assert bool(compiled(model)(p)[0]) == in_domain(model, p), p


@settings(max_examples=5, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(p=inputs(bad=False, moderate=True))
def test_property_reference_agrees_with_scipy(p):
    """valid = True for the reference means agreement with scipy (DOP853, exact stick-slip,
    rtol 1e-10) within its tolerance."""
    valid, _, x, *_ = (np.asarray(a) for a in compiled("reference")(p))
    assert valid, p
    m, k, g, mu, b, D, x0, v0 = p
    w0 = math.sqrt(k / m)
    A0 = math.hypot(x0, v0 / w0)
    ts = S / w0
    segs, _, rest = scipy_stick_slip(m, k, mu, b, D, x0, v0, ts[-1], g=g, rtol=1e-10,
                                     atol=1e-12 * A0)
    x_sp, _ = evaluate(segs, rest, ts)
    np.testing.assert_allclose(x, x_sp, atol=1e-7 * A0, rtol=0)
