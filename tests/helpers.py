"""Independent references for the tests: scipy integration of eq. 3 with exact stick-slip."""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_ivp

W0 = math.sqrt(30.0)  # the paper's block: m = 1 kg, k = 30 N/m, A0 = 0.2 m
A0 = 0.2


def ratios_to_constants(d0_ratio=0.0, d1_ratio=0.0, d2_ratio=0.0, *, m=1.0, k=30.0, A0=A0,
                        g=9.81):
    """(mu, b, D) for the dimensionless ratios, inverting eq. 21 by hand (independent of dampax)."""
    w0 = math.sqrt(k / m)
    mu = d0_ratio * w0 * A0 * math.pi * w0 / (2 * g)
    b = 2 * m * d1_ratio * w0
    D = 3 * math.pi * m * d2_ratio * w0 / A0 / (4 * w0)
    return mu, b, D


def scipy_stick_slip(m, k, mu, b, D, x0, v0, t_end, *, g=9.81, rtol=1e-12, atol=1e-14,
                     max_swings=10_000, k3=0.0, mu_s=None):
    """Integrate eq. 3 swing by swing with DOP853 and a v = 0 event.

    With ``k3`` the spring force is k x + k3 x^3, and the block sticks at a velocity zero where
    |k x + k3 x^3| <= mu_s m g (static friction ``mu_s``; None: mu_s = mu).

    Returns (segments, turning, rest): a list of dense-output pieces (t0, t1, sol), the turning
    points [(t, x)] and the rest state (t, x) or None.
    """
    t, x, v = 0.0, float(x0), float(v0)
    segments, turning = [], []

    def holds(x):
        return abs(k * x + k3 * x**3) <= (mu if mu_s is None else mu_s) * m * g

    if v == 0.0:
        if holds(x):
            return segments, turning, (0.0, x)
        s = -math.copysign(1.0, x)
    else:
        s = math.copysign(1.0, v)
    for _ in range(max_swings):
        def rhs(_t, y, s=s):
            return [y[1], (-k * y[0] - k3 * y[0] ** 3 - s * mu * m * g - b * y[1]
                           - D * s * y[1] ** 2) / m]

        def event(_t, y, s=s):
            return s * y[1]

        event.terminal = True
        event.direction = -1
        sol = solve_ivp(rhs, (t, t_end), [x, v], method="DOP853", rtol=rtol, atol=atol,
                        events=event, dense_output=True)
        segments.append((t, sol.t[-1], sol.sol))
        if sol.status != 1:
            return segments, turning, None
        t = float(sol.t_events[0][0])
        x = float(sol.y_events[0][0][0])
        v = 0.0
        turning.append((t, x))
        if holds(x):
            return segments, turning, (t, x)
        s = -math.copysign(1.0, x)
    raise RuntimeError("max_swings exhausted")


def evaluate(segments, rest, ts):
    """x(t) and v(t) of a scipy_stick_slip result on the times ts."""
    ts = np.asarray(ts, dtype=float)
    x = np.full(ts.shape, np.nan)
    v = np.full(ts.shape, np.nan)
    for t0, t1, sol in segments:
        sel = (ts >= t0) & (ts <= t1)
        if np.any(sel):
            y = sol(ts[sel])
            x[sel], v[sel] = y[0], y[1]
    if rest is not None:
        sel = ts >= rest[0]
        x[sel], v[sel] = rest[1], 0.0
    return x, v


def check_cf_file(path, *, flags=()) -> dict:
    """CF checks of a netCDF file, read undecoded with scipy.io (independent of xarray).

    Asserts: the file has coordinate variables (a 1-d variable named as its dimension) and none
    carries ``_FillValue`` (CF 2.5.1); each variable named in ``flags`` has ``flag_values`` and
    ``flag_meanings`` (CF 3.5), as many distinct values as meanings, values of the variable's
    own type, and every stored value among them; no other variable has half of that pair.

    Returns:
        {name: attributes} of every variable, for further checks.
    """
    from scipy.io import netcdf_file

    with netcdf_file(path, "r", mmap=False) as f:
        variables = {name: (var.dimensions, var.typecode(), dict(var._attributes),
                            np.array(var.data)) for name, var in f.variables.items()}
    coords = [name for name, (dims, *_) in variables.items() if dims == (name,)]
    assert coords, f"no coordinate variable in {path}"
    for name in coords:
        assert "_FillValue" not in variables[name][2], f"coordinate {name} has a _FillValue"
    for name, (_, typecode, attrs, data) in variables.items():
        has = {"flag_values" in attrs, "flag_meanings" in attrs}
        if name not in flags:
            assert has == {False}, f"{name}: flag_values without flag_meanings or the reverse"
            continue
        assert has == {True}, f"flag variable {name} lacks flag_values / flag_meanings: {attrs}"
        values = np.atleast_1d(attrs["flag_values"])
        meanings = attrs["flag_meanings"]
        meanings = (meanings.decode() if isinstance(meanings, bytes) else meanings).split()
        assert len(values) == len(set(values.tolist())) == len(meanings) >= 2, (name, attrs)
        assert values.dtype == data.dtype, (name, values.dtype, typecode)
        assert set(np.unique(data).tolist()) <= set(values.tolist()), name
    return {name: attrs for name, (_, _, attrs, _) in variables.items()}


def count_reads(monkeypatch, x) -> tuple:
    """Record every reading of the positions ``x`` by a fit (``_problem.read_arrays``, where
    ``prepare`` starts) and every call of ``analyse`` from any module of the fit package:
    issue 33's "the data are prepared and analysed once per dp.fit", however many fits a
    search makes at fixed k3 or mu_s.

    Returns:
        (reads, analyses): lists that grow by one per reading of ``x`` and per analysis.
    """
    import sys

    from dampax._fit import _analysis, _problem

    real, seen, analysed = _problem.read_arrays, [], []

    def counted(trace_or_t, xs):
        if xs is not None and np.shape(xs) == np.shape(x) and np.array_equal(xs, x):
            seen.append(1)
        return real(trace_or_t, xs)

    def counted_analyse(*args, **kwargs):
        analysed.append(1)
        return _analysis.analyse(*args, **kwargs)

    monkeypatch.setattr(_problem, "read_arrays", counted)
    for name, module in list(sys.modules.items()):
        if name.startswith("dampax._fit.") and getattr(module, "analyse", None) is \
                _analysis.analyse and module is not _analysis:
            monkeypatch.setattr(module, "analyse", counted_analyse)
    return seen, analysed


#: a batch that every reference engine must solve alike (tests/reference/test_diffrax_engine.py,
#: test_kernel.py): every damping term, a cubic spring, static friction, starts in all four
#: quadrants, a start at rest in the band, an invalid oscillator
#      m    k     mu     b     D     k3     mu_s   x0     v0
ENGINE_CASES = [(1.0, 25.0, 0.02, 0.0, 0.0, 0.0, None, 1.0, 0.0),   # Coulomb alone
                (0.5, 10.0, 0.0, 0.1, 0.0, 0.0, None, -0.3, 1.0),  # viscous alone: never halts
                (1.0, 25.0, 0.0, 0.0, 0.4, 0.0, None, -0.5, -2.0),  # drag alone
                (2.0, 30.0, 0.05, 0.2, 0.3, 0.0, None, 0.4, -1.5),  # all three
                (1.0, 25.0, 0.03, 0.05, 0.1, 40.0, None, 0.6, 1.0),  # hardening spring
                (1.0, 25.0, 0.03, 0.0, 0.1, 0.0, 0.06, -0.8, 0.0),  # static friction above mu
                (1.0, 25.0, 0.05, 0.0, 0.0, 0.0, None, 0.01, 0.0),  # at rest inside the band
                (1.0, 25.0, -0.1, 0.0, 0.0, 0.0, None, 1.0, 0.0)]  # mu < 0: invalid


def solve_cases(engine, t_end, ts, **options):
    """:data:`ENGINE_CASES` solved in one batch by ``engine`` (jitted: traced inputs, so the
    invalid oscillator reaches the engine; eagerly it is refused)."""
    import jax

    from dampax._oscillator import Oscillator
    from dampax._reference import solve_reference

    cases = ENGINE_CASES
    cols = [np.asarray([c[j] for c in cases], dtype=float) for j in (0, 1, 2, 3, 4, 5, 7, 8)]
    mu_s = np.asarray([c[6] if c[6] is not None else max(c[2], 0.0) for c in cases])

    @jax.jit
    def solve(m, k, mu, b, D, k3, mu_s, x0, v0):
        osc = Oscillator(m=m, k=k, mu=mu, b=b, D=D, k3=k3, mu_s=mu_s)
        return solve_reference(osc, x0, v0, t_end=t_end, ts=ts, engine=engine, **options)

    return solve(*cols[:6], mu_s, *cols[6:])
