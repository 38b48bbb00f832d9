"""The reference as one fused kernel (``engine="pallas"``, issue 35 item 2) against dampax's XLA
engine, run here in Pallas's interpreter (a CPU has no Triton): the same arithmetic, so the
same solution to rounding (1e-12), whatever the GPU will make of its speed.

One batch of every kind of motion (tests/helpers.py ``ENGINE_CASES``), solved by both engines
with samples written inside the kernel's loop; the row table behind later ``sol.x(t)``; times
out of order (the samples then come from the table); the gradient (the kernel's custom VJP is
the XLA engine's reverse mode) against finite differences; the kernel under ``jax.vmap``; and
the choice ``engine="auto"`` makes.
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import ENGINE_CASES, evaluate, scipy_stick_slip, solve_cases

import dampax as dp
from dampax._oscillator import Oscillator
from dampax._reference import _kernel, _solve, solve_reference

T_END = 6.0
TS = np.linspace(-0.05, T_END + 0.05, 240)  # before 0 and after t_end: NaN, as the XLA engine
OPTIONS = dict(rtol=1e-11, atol=1e-13, max_swings=32, max_steps_per_swing=48)


@pytest.fixture(scope="module")
def both():
    """The cases by the XLA engine and by the kernel, the kernel with queues: 2 lanes per
    program, each integrating 3 trajectories one after the other (2 programs, 4 padding
    trajectories), as a GPU batch beyond its resident lanes runs."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(_kernel, "BLOCK", 2)
        mp.setattr(_kernel, "RESIDENT", 3)
        assert _kernel.queues(len(ENGINE_CASES)) == (2, 3)
        fused = solve_cases("pallas", T_END, TS, **OPTIONS)
    return solve_cases("dampax", T_END, TS, **OPTIONS), fused


def _same(a, b, atol, name):
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    assert np.array_equal(np.isnan(a), np.isnan(b)), name
    assert np.array_equal(np.isinf(a), np.isinf(b)), name
    ok = np.isfinite(a)
    np.testing.assert_allclose(b[ok], a[ok], rtol=0, atol=atol, err_msg=name)


def test_the_kernel_is_the_xla_engine_on_every_case(both):
    """Halts, turning points, swing counts, results and the samples written inside the loop
    agree to 1e-12 (amplitudes about 1, velocities about 5); the invalid oscillator is
    invalid for both."""
    xla, fused = both
    assert list(np.asarray(fused.result._value)) == list(np.asarray(xla.result._value))
    assert list(np.asarray(fused.valid)) == [True] * 7 + [False]
    for name in ("halted", "n_swings", "n_rows"):
        np.testing.assert_array_equal(getattr(fused, name), getattr(xla, name), err_msg=name)
    for name in ("halt_time", "halt_position", "swing_times", "turning_x", "t_cover"):
        _same(getattr(xla, name), getattr(fused, name), 1e-12, name)
    _same(xla.xs, fused.xs, 1e-12, "xs")
    _same(xla.vs, fused.vs, 1e-11, "vs")


def test_the_kernel_against_scipy(both):
    """The kernel's samples within 1e-8 A0 of scipy's DOP853 with events (an independent
    integrator: the cubic spring and static friction included)."""
    fused = both[1]
    inside = (TS >= 0) & (TS <= T_END)
    for i, (m, k, mu, b, D, k3, mu_s, x0, v0) in enumerate(ENGINE_CASES[:-1]):
        segs, _, rest = scipy_stick_slip(m, k, mu, b, D, x0, v0, T_END, k3=k3,
                                         mu_s=mu_s if mu_s is not None else mu)
        x_sp, _ = evaluate(segs, rest, TS[inside])
        np.testing.assert_allclose(np.asarray(fused.xs)[i, inside], x_sp, rtol=0, atol=1e-8,
                                   err_msg=str(ENGINE_CASES[i]))


def test_the_kernels_row_table_serves_later_times(both):
    """sol.x at times not given to the solve (any order) reads the kernel's row table: the
    XLA engine's values; the table holds the same steps (sizes and coefficients within 1e-6,
    1e-7 absolute: the controller's factor err^(-1/8) of an error estimate near rounding
    differs in its last bits between the two programs' fusions, which moves no sample beyond
    1e-12)."""
    xla, fused = both
    t = jnp.asarray(np.random.default_rng(3).uniform(0.0, T_END, 57))
    _same(xla.x(t), fused.x(t), 1e-12, "x(t)")
    rows_a, rows_b = np.asarray(xla.rows), np.asarray(fused.rows)
    assert np.array_equal(np.isfinite(rows_a), np.isfinite(rows_b))
    ok = np.isfinite(rows_a)
    np.testing.assert_allclose(rows_b[ok], rows_a[ok], rtol=1e-6, atol=1e-7)


def _one(m, k, mu, b, D, x0, v0, ts):
    osc = Oscillator(m=m, k=k, mu=mu, b=b, D=D)
    return solve_reference(osc, x0, v0, t_end=T_END, ts=ts, engine="pallas", **OPTIONS).xs


# one trajectory's solve vmapped over three (Pallas batches the kernel): shared by the tests
_THREE = jax.jit(jax.vmap(_one, in_axes=(0,) * 7 + (None,)))
WEIGHTS = np.cos(np.arange(TS.size))


def test_the_kernel_under_vmap_and_with_unsorted_times(both):
    """A single-trajectory solve vmapped over three oscillators (the kernel batched by Pallas)
    and the same times reversed (samples from the row table): the batched solve's values."""
    xla = both[0]
    cols = [jnp.asarray([c[j] for c in ENGINE_CASES[:3]], dtype=float)
            for j in (0, 1, 2, 3, 4, 7, 8)]
    _same(np.asarray(xla.xs)[:3], _THREE(*cols, jnp.asarray(TS)), 1e-12, "vmapped")
    _same(np.asarray(xla.xs)[:3, ::-1], _THREE(*cols, jnp.asarray(TS[::-1])), 1e-12,
          "reversed")
    # new values (other oscillators, other times of the same shape): the same program
    _THREE(*[c * 1.01 for c in cols], jnp.asarray(TS * 0.9))
    assert _THREE._cache_size() == 1


def test_gradient_through_the_kernel():
    """jax.grad through the kernel (its VJP: the XLA engine's reverse mode) of a weighted sum
    of x(ts) in (mu, D), against central finite differences of the kernel's own values."""
    base = np.asarray([1.0, 25.0, 0.02, 0.05, 0.15, 0.7, 0.4])

    def loss(q):
        xs = _one(*base[:2], q[0], base[3], q[1], *base[5:], jnp.asarray(TS))
        return jnp.nansum(xs * WEIGHTS)

    g = np.asarray(jax.jit(jax.grad(loss))(jnp.asarray(base[[2, 4]])))
    eps = 1e-6
    shifts = [(2, eps), (2, -eps), (4, eps), (4, -eps), (2, 0.0), (2, 0.0)]
    points = np.tile(base, (6, 1))
    for row, (j, d) in enumerate(shifts):
        points[row, j] += d
    xs = np.concatenate([_THREE(*jnp.asarray(points[i:i + 3].T), jnp.asarray(TS))
                         for i in (0, 3)])
    val = np.nansum(xs * WEIGHTS, axis=1)
    fd = [(val[0] - val[1]) / (2 * eps), (val[2] - val[3]) / (2 * eps)]
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-7)


OFF_GPU = pytest.mark.skipif(_kernel.available(), reason="on a CUDA GPU the kernel runs "
                             "natively: see test_on_a_cuda_gpu_the_kernel_runs_natively...")


@OFF_GPU
def test_auto_takes_the_xla_engine_off_a_gpu():
    """engine="auto" (the default) is the XLA engine on a CPU and for forward mode; an engine
    that is not known is named."""
    assert not _kernel.available()
    assert _solve.resolve_engine("auto") == "dampax"
    assert _solve.resolve_engine("auto", "forward") == "dampax"
    assert _solve.resolve_engine("pallas") == "pallas"
    with pytest.raises(ValueError, match="engine must be one of .*'pallas', 'auto'"):
        dp.solve(Oscillator(m=1, k=1, mu=0.1), 1.0, 0.0, method="reference", engine="triton")


@OFF_GPU
def test_auto_keeps_the_xla_engine_where_the_kernel_fails_its_check(monkeypatch):
    """Where the kernel is taken to run natively but does not (here: Triton's lowering on a
    CPU), the one-time self-check warns with the reason and "auto" stays with XLA."""
    monkeypatch.setattr(_solve, "kernel_native", lambda: True)
    monkeypatch.setattr(_kernel, "_CHECK", {})
    with pytest.warns(RuntimeWarning, match="fused GPU kernel .* not used: it does not run"):
        assert _solve.resolve_engine("auto") == "dampax"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # decided once per process: no second warning
        assert _solve.resolve_engine("auto") == "dampax"


def test_the_kernel_lowers_to_triton_for_a_cuda_gpu(monkeypatch):
    """The natural call with the kernel, lowered for CUDA on this CPU (no GPU needed to lower):
    every primitive of the kernel has a Triton lowering (no ``reduce_or``, no slices, blocks
    of powers of two) and it becomes one Triton custom call with BLOCK / 32 warps. Whether
    the GPU's compiler and the figures hold is for benchmarks/gpu.py on a GPU."""
    monkeypatch.setattr(_solve, "kernel_native", lambda: True)  # not interpreted

    def natural(k, mu, x0, ts):
        osc = Oscillator(m=1.0, k=k, mu=mu, D=0.1)
        return solve_reference(osc, x0, 0.0, t_end=5.0, ts=ts, engine="pallas").x(ts)

    shapes = [jax.ShapeDtypeStruct((300,), jnp.float64)] * 3 + \
        [jax.ShapeDtypeStruct((1000,), jnp.float64)]
    try:
        text = jax.jit(natural).trace(*shapes).lower(lowering_platforms=("cuda",)).as_text()
    except RuntimeError as err:  # jax 0.11 reads the GPU's properties to lower for Triton
        if "No supported GPU devices found" not in str(err):
            raise
        pytest.skip("this jax lowers for Triton only where a CUDA GPU is present")
    assert text.count("__gpu$xla.gpu.triton") == 1
    programs = -(-300 // _kernel.BLOCK)
    assert f"num_warps = {_kernel.BLOCK // 32}" in text and f"grid_x = {programs}" in text
    # a scalar solve vmapped over the same 300 (an error map's points): the mapped
    # trajectories join one launch, programs of BLOCK lanes, not 300 programs of 1
    mapped = jax.vmap(natural, in_axes=(0, 0, 0, None))
    text = jax.jit(mapped).trace(*shapes).lower(lowering_platforms=("cuda",)).as_text()
    assert text.count("__gpu$xla.gpu.triton") == 1
    assert f"grid_x = {programs} : i32, grid_y = 1" in text


def test_the_work_estimate_orders_the_trajectories_by_their_steps():
    """The kernel sorts its batch by `work_estimate` so that a program's lanes take about as
    long: on 64 random stick-slip trajectories its ranks follow the steps the XLA engine
    takes (Spearman's rho > 0.9; 0.989 Pearson on 16,384 of benchmarks/peer_race.py's)."""
    rng = np.random.default_rng(5)
    k, mu, b, D = (rng.uniform(10, 50, 64), rng.uniform(0, 0.05, 64), rng.uniform(0, 0.5, 64),
                   rng.uniform(0, 3, 64))
    x0, v0 = rng.uniform(-0.3, 0.3, 64), rng.uniform(-1, 1, 64)
    osc = Oscillator(m=np.ones(64), k=k, mu=mu, b=b, D=D)
    steps = np.asarray(solve_reference(osc, x0, v0, t_end=5.0, max_swings=64).n_rows)
    inputs, _, _ = _kernel.prepare(osc, jnp.asarray(x0), jnp.asarray(v0), jnp.full(64, 5.0))
    est = np.asarray(_kernel.work_estimate(inputs))
    ranks = [np.argsort(np.argsort(a)) for a in (est, steps)]
    assert np.corrcoef(*ranks)[0, 1] > 0.9


@pytest.mark.skipif(not _kernel.available(), reason="no CUDA GPU: the kernel runs natively "
                    "only there")
def test_on_a_cuda_gpu_the_kernel_runs_natively_and_auto_takes_it(both):
    """Where a CUDA GPU is the backend: the kernel compiles (Triton), passes its self-check,
    "auto" takes it, and the cases solved natively match the XLA engine to 1e-12."""
    assert _solve.resolve_engine("auto") == "pallas"
    native = solve_cases("pallas", T_END, TS, **OPTIONS)
    _same(both[0].xs, native.xs, 1e-12, "xs on the GPU")
    _same(both[0].halt_time, native.halt_time, 1e-12, "halt_time on the GPU")


def test_the_kernel_fails_as_the_xla_engine_does():
    """Out of the domain and out of budget (jitted, so nothing is refused at the edge): a
    start beyond a softening spring's barrier, t_end <= 0, a non-finite start, and motions
    that need more swings than max_swings = 3 (one Coulomb, one viscous). The same result
    codes, and the same samples (NaN where invalid, the covered part where out of budget)."""
    k3 = jnp.asarray([-100.0, 0.0, 0.0, 0.0, 0.0])
    t_end = jnp.asarray([2.0, -1.0, 2.0, 6.0, 6.0])
    x0 = jnp.asarray([0.5, 0.3, jnp.nan, 1.0, 0.5])
    mu, b = jnp.asarray([0.02, 0.02, 0.02, 0.01, 0.0]), jnp.asarray([0.0, 0, 0, 0, 0.1])

    def solve(engine, mu, b, k3, x0, t_end):
        osc = Oscillator(m=1.0, k=25.0, mu=mu, b=b, k3=k3)
        return solve_reference(osc, x0, 0.0, t_end=t_end, ts=TS[:64], engine=engine,
                               rtol=1e-10, atol=1e-12, max_swings=3)

    xla, fused = (jax.jit(solve, static_argnums=0)(e, mu, b, k3, x0, t_end)
                  for e in ("dampax", "pallas"))
    codes = np.asarray(fused.result._value)
    assert list(codes) == list(np.asarray(xla.result._value))
    expected = (dp.RESULTS.unconfined, dp.RESULTS.invalid_t_end, dp.RESULTS.nonfinite_state,
                dp.RESULTS.max_swings_reached, dp.RESULTS.max_swings_reached)
    assert list(codes) == [int(r._value) for r in expected]
    _same(xla.t_cover, fused.t_cover, 1e-12, "t_cover")
    _same(xla.xs, fused.xs, 1e-12, "xs")


def test_error_map_with_the_kernel_as_its_reference():
    """The map's reference by the kernel (what "auto" runs on a CUDA GPU: each chunk's points
    one batch of the kernel, inside the map's compiled step) gives the XLA engine's map to
    1e-12 and says which engine it used. (The same small map as test_diffrax_engine.py.)"""
    kw = dict(d0_ratio=[0.0, 0.03], d2_ratio=[0.0, 0.2], phi0=[0.4, 2.5], periods=4,
              samples_per_period=16, progress=False)
    ours, fused = dp.error_map(**kw), dp.error_map(**kw, engine="pallas")
    assert fused.attrs["reference_engine"] == "pallas"
    assert "fused kernel" in fused.attrs["reference_description"]
    for name in ("max_error", "rms_error", "reference_halt_time"):
        _same(ours[name].values, fused[name].values, 1e-12, name)


def test_auto_leaves_every_derivative_to_the_xla_engine(monkeypatch):
    """Where the kernel would run ("auto" on a CUDA GPU, taken so here), a solve that is
    differentiated, in any mode and under any other transformation, runs the XLA engine (as
    before the kernel: forward-over-reverse included), a plain one (jit, vmap) the kernel."""
    monkeypatch.setattr(_solve, "kernel_native", lambda: True)
    monkeypatch.setattr(_kernel, "self_check", lambda solve_jit: True)
    chosen = []

    def f(mu):
        osc = Oscillator(m=1.0, k=25.0, mu=mu)
        chosen.append(_solve.check_reference_options(0.3, 0.0, osc=osc)["engine"])
        return mu * mu

    mus = jnp.asarray([0.01, 0.02])
    cases = {"eager": lambda: f(0.02), "jit": lambda: jax.jit(f)(0.02),
             "vmap": lambda: jax.vmap(f)(mus), "grad": lambda: jax.grad(f)(0.02),
             "jit(grad)": lambda: jax.jit(jax.grad(f))(0.02),
             "vmap(grad)": lambda: jax.vmap(jax.grad(f))(mus),
             "grad(sum(vmap))": lambda: jax.grad(lambda m: jax.vmap(f)(m).sum())(mus),
             "jacfwd": lambda: jax.jacfwd(f)(0.02), "hessian": lambda: jax.hessian(f)(0.02)}
    for name, call in cases.items():
        chosen.clear()
        call()
        want = "pallas" if name in ("eager", "jit", "vmap") else "dampax"
        assert set(chosen) == {want}, name


def test_auto_leaves_large_batches_to_the_xla_engine(monkeypatch):
    """Where the kernel would run, "auto" takes it for up to KERNEL_MAX_TRAJECTORIES
    trajectories in one solve (an H200 ran 65,536 in the same time by either engine, and
    131,072 in 0.74 of the kernel's by XLA's), counting the batch of an array oscillator and
    of the vmaps around a scalar solve alike; beyond, the XLA engine."""
    monkeypatch.setattr(_solve, "kernel_native", lambda: True)
    monkeypatch.setattr(_kernel, "self_check", lambda solve_jit: True)
    most = _solve.KERNEL_MAX_TRAJECTORIES

    def engine(mu, x0=0.3):
        return _solve.check_reference_options(x0, 0.0, osc=Oscillator(m=1.0, k=25.0, mu=mu))[
            "engine"]

    assert engine(jnp.full(most, 0.01)) == "pallas"
    assert engine(jnp.full(most + 1, 0.01)) == "dampax"
    assert engine(0.01, jnp.full((2, most // 2 + 1), 0.3)) == "dampax"  # x0's batch counts
    chosen = []

    def f(mu):
        chosen.append(engine(mu))
        return mu

    jax.vmap(jax.vmap(f))(jnp.full((2, most // 2), 0.01))
    jax.vmap(jax.vmap(f))(jnp.full((2, most // 2 + 1), 0.01))
    jax.jit(jax.vmap(f))(jnp.full(most + 1, 0.01))
    assert chosen == ["pallas", "dampax", "dampax"]


def test_samples_per_pass_changes_no_sample(both):
    """The sampling loop's passes (``run_blocks(samples_per_pass=...)``, swept by
    benchmarks/gpu_kernel.py) change how many times each pass evaluates, not the samples: 5 a
    pass (a step holds 0-3 of these samples) gives the XLA engine's values."""
    xla = both[0]
    m, k, mu, b, D, _, _, x0, v0 = (np.asarray([c[j] for c in ENGINE_CASES[:3]], dtype=float)
                                    for j in range(9))
    inputs, _, _ = _kernel.prepare(Oscillator(m=m, k=k, mu=mu, b=b, D=D), x0, v0,
                                   jnp.full(3, T_END))
    inside = (TS >= 0) & (TS <= T_END)
    out = _kernel.run_blocks(inputs, jnp.asarray(TS[inside]), rtol=OPTIONS["rtol"],
                             atol=OPTIONS["atol"], max_swings=OPTIONS["max_swings"],
                             rows=OPTIONS["max_swings"] * OPTIONS["max_steps_per_swing"],
                             interpret=True, block=2, samples_per_pass=5)
    _same(np.asarray(xla.xs)[:3, inside], out["xs"], 1e-12, "xs")
    _same(np.asarray(xla.vs)[:3, inside], out["vs"], 1e-11, "vs")
