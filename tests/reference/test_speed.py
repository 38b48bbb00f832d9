"""The fast paths of issue 12: the merged dense output, the compilation cache, the progress bar.

The dense output's accuracy against scipy is checked in test_reference.py (its sample times
are a uniform grid, so they take the merged path); here the merged path is checked against
the binary-search path and against the exact viscous solution, and the cacheability of the
compiled reference program is checked on its HLO.
"""

from __future__ import annotations

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import ratios_to_constants

import dampax as dp
from dampax._reference import _uniform


@pytest.fixture(scope="module")
def batch():
    rng = np.random.default_rng(12)
    n = 24
    d0 = rng.uniform(0.0, 0.1, n) * (rng.random(n) > 0.25)  # some without friction
    d1 = rng.uniform(0.0, 0.2, n) * (rng.random(n) > 0.5)
    d2 = rng.uniform(0.0, 0.75, n) * (rng.random(n) > 0.25)
    phi0 = rng.uniform(-np.pi, np.pi, n)  # every quadrant
    osc = dp.from_ratios(jnp.asarray(d0), jnp.asarray(d1), jnp.asarray(d2), m=1.0, k=30.0,
                         A0=0.2)
    w0 = np.sqrt(30.0)
    sol = dp.solve(osc, 0.2 * jnp.cos(phi0), -0.2 * w0 * jnp.sin(phi0), method="reference",
                   t_end=6.0, max_swings=40)
    return sol


def test_uniform_detection():
    assert _uniform(np.linspace(0.0, 5.0, 101)) == (0.0, 0.05)
    assert _uniform(np.array([0.0, 1.0, 3.0])) is None  # not uniform
    assert _uniform(np.linspace(5.0, 0.0, 11)) is None  # decreasing
    assert _uniform(np.zeros((3, 4))) is None  # not 1-D
    assert _uniform(np.array([0.0, 1.0])) is None  # too short to be worth it


def test_merged_grid_equals_binary_search(batch):
    """The merged path (uniform grid) and the search path (any t) give the same x and v."""
    t = np.linspace(-0.5, 7.0, 1501)  # before 0, through the halts, beyond t_end
    x_grid, v_grid = batch.state(t)  # detected as a grid
    x_search, v_search = (a[:, 0] for a in batch.state(t[None, :]))  # 2-D: a search per t
    np.testing.assert_array_equal(np.isnan(x_grid), np.isnan(x_search))
    np.testing.assert_allclose(x_grid, x_search, rtol=0, atol=1e-14, equal_nan=True)
    np.testing.assert_allclose(v_grid, v_search, rtol=0, atol=1e-13, equal_nan=True)
    # NaN exactly before 0 and beyond the integrated interval of a still-moving trajectory
    assert np.all(np.isnan(np.asarray(x_grid)[:, t < 0]))
    moving = ~np.asarray(batch.halted)
    assert np.all(np.isnan(np.asarray(x_grid)[moving][:, t > 6.0]))
    assert np.all(np.isfinite(np.asarray(x_grid)[:, (t >= 0) & (t <= 6.0)]))


def test_grid_under_jit_equals_eager(batch):
    t = jnp.linspace(0.0, 6.0, 301)
    eager = batch.state(np.asarray(t))
    traced = jax.jit(lambda s, tt: s.state(tt, grid=(tt[0], tt[1] - tt[0])))(batch, t)
    searched = jax.jit(lambda s, tt: s.state(tt))(batch, t)
    for a, b, c in zip(eager, traced, searched, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-14, equal_nan=True)
        np.testing.assert_allclose(a, c, rtol=0, atol=1e-13, equal_nan=True)
    with pytest.raises(ValueError, match="1-D"):
        batch.state(jnp.zeros((2, 3)), grid=(0.0, 1.0))


@pytest.mark.parametrize("phi0", [0.3, 2.0, -2.5, -0.7])
def test_dense_output_exact_viscous(phi0):
    """x and v between the solver's steps against the exact damped harmonic motion."""
    m, k = 1.0, 30.0
    _, b, _ = ratios_to_constants(d1_ratio=0.05)
    w0 = np.sqrt(k / m)
    x0, v0 = 0.2 * np.cos(phi0), -0.2 * w0 * np.sin(phi0)
    sol = dp.solve(dp.Oscillator(m=m, k=k, b=b), x0, v0, method="reference", t_end=5.0)
    t = np.linspace(0.0, 5.0, 2001)
    gamma = b / (2 * m)
    wd = np.sqrt(w0**2 - gamma**2)
    x_ex = np.exp(-gamma * t) * (x0 * np.cos(wd * t) + (v0 + gamma * x0) / wd * np.sin(wd * t))
    v_ex = np.exp(-gamma * t) * (v0 * np.cos(wd * t)
                                 - (gamma * v0 + w0**2 * x0) / wd * np.sin(wd * t))
    x, v = sol.state(t)
    assert np.max(np.abs(np.asarray(x) - x_ex)) < 1e-9 * 0.2
    assert np.max(np.abs(np.asarray(v) - v_ex)) < 1e-8 * 0.2 * w0


def test_reference_program_has_no_host_callback():
    """JAX writes no program with host callbacks to its persistent cache: the reference solve
    (and with it every error-map step) must compile to one without."""
    from dampax._reference import _solve_jit

    osc = dp.Oscillator(m=1.0, k=30.0, mu=0.03, D=2.95)
    lowered = _solve_jit.lower(osc, jnp.asarray(0.2), jnp.asarray(0.0), jnp.asarray(5.0), None,
                               rtol=1e-10, atol=1e-12, max_swings=8, rows=128,
                               adjoint="recursive")
    text = lowered.as_text()
    assert "callback" not in text.lower()


def _cache_dir_in_subprocess(env_extra: dict) -> str:
    env = {k: v for k, v in os.environ.items()
           if k not in ("DAMPAX_CACHE", "DAMPAX_CACHE_DIR", "JAX_COMPILATION_CACHE_DIR")}
    env.update(env_extra)
    code = "import dampax, jax; print(jax.config.jax_compilation_cache_dir)"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True)
    return out.stdout.strip().splitlines()[-1]


def test_compilation_cache_settings(tmp_path):
    assert _cache_dir_in_subprocess({"DAMPAX_CACHE_DIR": str(tmp_path / "c")}) == str(
        tmp_path / "c" / "jax")
    assert (tmp_path / "c" / "jax").is_dir()
    assert _cache_dir_in_subprocess({"XDG_CACHE_HOME": str(tmp_path / "x")}) == str(
        tmp_path / "x" / "dampax" / "jax") or sys.platform in ("darwin", "win32")
    assert _cache_dir_in_subprocess({"DAMPAX_CACHE": "0"}) == "None"
    # the user's own setting wins
    assert _cache_dir_in_subprocess({"JAX_COMPILATION_CACHE_DIR": str(tmp_path / "j")}) == str(
        tmp_path / "j")


def test_progress_says_compiling_first(capsys):
    dp.error_map(d0_ratio=[0.0, 0.05], d2_ratio=0.3, phi0=0.0, periods=2.0,
                 samples_per_period=16, models=("matched",), reference="coulomb_exact",
                 d1_ratio=0.0, progress=True)
    err = capsys.readouterr().err
    assert "error map: compiling" in err
    assert err.index("compiling") < err.rindex("100%")


_MAP_SCRIPT = """
import sys, numpy as np, dampax as dp
ds = dp.error_map(d0_ratio=[0.0, 0.04], d2_ratio=[0.0, 0.3], phi0=[0.0, 2.0], periods=3.0,
                  samples_per_period=16, chunk_size=4, models=("matched",), progress=False)
np.save(sys.argv[1], ds["max_error"].values)
"""


def test_traced_error_map_step_is_reused_across_processes(tmp_path):
    """A second process deserializes the traced step (jax.export) instead of tracing it; the
    numbers are those of a process without any cache, and a damaged file is traced again.
    (One model: the mechanism, not the map, is tested; each process compiles its step.)"""
    env = {k: v for k, v in os.environ.items() if k not in ("DAMPAX_CACHE", "JAX_COMPILATION_"
                                                            "CACHE_DIR")}
    script = tmp_path / "map.py"
    script.write_text(_MAP_SCRIPT)

    def run(out, **extra):
        subprocess.run([sys.executable, str(script), str(tmp_path / out)], check=True,
                       env={**env, "DAMPAX_CACHE_DIR": str(tmp_path / "cache"), **extra})
        return np.load(tmp_path / out)

    first = run("a.npy")
    files = list((tmp_path / "cache" / "exported").glob("error_map-*.jaxexport"))
    executables = list((tmp_path / "cache" / "exported").glob("error_map-*.jaxexe"))
    assert len(files) == 1 and len(executables) == 1  # the program, and its executable
    stamps = [f.stat().st_mtime_ns for f in files + executables]
    second = run("b.npy")
    assert [f.stat().st_mtime_ns for f in files + executables] == stamps  # read, not written
    files[0].write_bytes(b"not a program")
    executables[0].write_bytes(b"not an executable")
    damaged = run("c.npy")
    plain = run("d.npy", DAMPAX_CACHE="0")
    assert np.isfinite(plain).sum() > 0
    for other in (first, second, damaged):
        np.testing.assert_array_equal(other, plain)
    assert files[0].read_bytes() != b"not a program"  # rewritten


def test_eager_sensitivity_is_kept_compiled_and_equals_the_traced_path():
    """An eager dp.sensitivity runs a kept program (in this process, and exported for the next
    one: a repeated `dampax sensitivity` neither traces nor compiles); its numbers are those of
    the traced path to rounding (under jax.jit the inputs are tracers and the plain path runs)."""
    from dampax import _cache

    osc = dp.Oscillator(m=1.0, k=30.0, mu=0.03, D=2.0)
    ts = jnp.linspace(0.0, 2.0, 9)
    kw = dict(wrt=("mu", "D"), trend=False)  # the mechanism, not the sweep: a short compile
    eager = dp.sensitivity(osc, 0.2, 0.0, ts, **kw)
    kept = len(_cache._EXECUTABLES)
    again = dp.sensitivity(dp.Oscillator(m=1.0, k=30.0, mu=0.04, D=2.0), 0.2, 0.0, ts, **kw)
    assert len(_cache._EXECUTABLES) == kept  # new values, same program
    assert list(_cache.dampax_cache_dir().glob("exported/sensitivity-*.jax*"))
    traced = jax.jit(lambda mu: dp.sensitivity(dp.Oscillator(m=1.0, k=30.0, mu=mu, D=2.0),
                                               0.2, 0.0, ts, **kw))(0.03)
    for name in ("x", "dx", "energy", "dhalt_time", "dhalt_position"):
        np.testing.assert_allclose(np.asarray(getattr(eager, name)),
                                   np.asarray(getattr(traced, name)), rtol=1e-12, atol=1e-15,
                                   err_msg=name)  # two programs: rounding may differ
    assert eager.wrt == traced.wrt and bool(eager.valid) and bool(again.valid)
    assert float(again.halt_time) < float(eager.halt_time)  # more friction: halts sooner


def _leaves_equal(a, b) -> bool:
    """Same tree structure, and every leaf equal to the bit (NaN where NaN), same dtype and
    weak type."""
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    return ta == tb and all(
        np.asarray(x).dtype == np.asarray(y).dtype
        and getattr(x, "weak_type", False) == getattr(y, "weak_type", False)
        and np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True)
        for x, y in zip(la, lb, strict=True))


def test_an_xla_that_refuses_the_options_compiles_with_its_defaults(monkeypatch):
    """jaxlib 0.11 removed the loop-fusion option ("No such compile option"): dampax then
    compiles that program and every later one with XLA's defaults, and the result is right;
    other compile errors still propagate."""
    from dampax import _cache

    seen, real = [], jax.stages.Lowered.compile

    def refusing(self, compiler_options=None, **kw):
        seen.append(compiler_options)
        if compiler_options:
            raise jax.errors.JaxRuntimeError(
                "INVALID_ARGUMENT: No such compile option: 'xla_cpu_use_fusion_emitters'")
        return real(self, compiler_options, **kw)

    monkeypatch.setattr(jax.stages.Lowered, "compile", refusing)
    monkeypatch.setattr(_cache, "_EXECUTABLES", {})
    monkeypatch.setattr(_cache, "_REFUSED", type(_cache._REFUSED)())
    monkeypatch.setattr(_cache, "compiler_options", lambda name=None: (  # as on a CPU
        None if _cache._REFUSED.is_set() else {"xla_cpu_use_fusion_emitters": False}))
    x = jnp.linspace(0.0, 1.0, 5)
    for k in range(2):
        out = _cache.call_cached("test-refused", k, lambda a, k=k: jnp.cos(a) * k, x)
        np.testing.assert_allclose(out, np.cos(np.asarray(x)) * k, rtol=1e-15)
    assert seen == [{"xla_cpu_use_fusion_emitters": False}, None, None]
    assert _cache._REFUSED.is_set()

    def broken(self, compiler_options=None, **kw):
        raise jax.errors.JaxRuntimeError("INTERNAL: something else")

    monkeypatch.setattr(jax.stages.Lowered, "compile", broken)
    monkeypatch.setattr(_cache, "_REFUSED", type(_cache._REFUSED)())
    with pytest.raises(jax.errors.JaxRuntimeError, match="something else"):
        _cache.call_cached("test-refused", "broken", jnp.sin, x)


def test_kept_programs_compile_with_dampax_options_in_turns(monkeypatch):
    """Every program dampax compiles itself gets ``_cache.compiler_options`` (on a CPU, XLA's
    loop-fusion emitter), is traced in its turn and passes the turn on while it compiles:
    programs prepared in the background are all built, the turn is free afterwards and after
    a program whose trace fails, and the results equal numpy's."""
    from dampax import _cache

    seen = []
    real = jax.stages.Lowered.compile

    def spy(self, compiler_options=None, **kw):
        seen.append(compiler_options)
        return real(self, compiler_options, **kw)

    monkeypatch.setattr(jax.stages.Lowered, "compile", spy)
    monkeypatch.setattr(_cache, "_EXECUTABLES", {})
    x = jnp.linspace(0.0, 1.0, 5)
    for k in range(3):  # three programs started at once, then called
        _cache.prepare_cached("test-turns", k, lambda a, k=k: jnp.sin(a) + k, x)
    outs = [_cache.call_cached("test-turns", k, lambda a, k=k: jnp.sin(a) + k, x)
            for k in range(3)]
    for k, out in enumerate(outs):
        np.testing.assert_allclose(out, np.sin(np.asarray(x)) + k, rtol=1e-15)
    # jaxlib 0.11 has no such option: dampax then compiles with XLA's defaults
    on_cpu = jax.default_backend() == "cpu" and not _cache._REFUSED.is_set()
    want = {"xla_cpu_use_fusion_emitters": False} if on_cpu else None
    assert seen == [want] * 3
    monkeypatch.setenv("DAMPAX_FAST_COMPILE", "0")  # XLA's defaults, another program
    assert _cache.compiler_options() is None
    np.testing.assert_allclose(_cache.call_cached("test-turns", "defaults", jnp.tan, x),
                               np.tan(np.asarray(x)), rtol=1e-15)
    assert seen[-1] is None and len(seen) == 4
    monkeypatch.delenv("DAMPAX_FAST_COMPILE")
    assert not _cache._TRACING.locked()

    import gc

    collecting = []

    def probe(a):  # traced in its turn: Python's cyclic collector paused, back on after
        collecting.append(gc.isenabled())
        return 2.0 * a

    _cache.call_cached("test-turns", "gc", probe, x)
    assert collecting == [False] and gc.isenabled()

    def broken(a):
        raise RuntimeError("no trace")

    with pytest.raises(RuntimeError, match="no trace"):
        _cache.call_cached("test-turns", "broken", broken, x)
    assert not _cache._TRACING.locked() and gc.isenabled()

    # a thread that holds the turn (a trace calling a kept program) and waits for a program
    # being built in the background lets the builder trace: no deadlock
    import threading

    got = []

    def holder():
        with _cache._turn():
            _cache.prepare_cached("test-turns", "inner", jnp.cos, x)
            got.append(_cache.call_cached("test-turns", "inner", jnp.cos, x))

    worker = threading.Thread(target=holder, daemon=True)
    worker.start()
    worker.join(timeout=120)
    assert not worker.is_alive() and not _cache._TRACING.locked() and gc.isenabled()
    np.testing.assert_allclose(got[0], np.cos(np.asarray(x)), rtol=1e-15)


def test_kept_executables_load_without_the_turn(monkeypatch):
    """A kept executable is loaded without the tracing turn (loading traces nothing): with
    the turn held by a thread that traces, another thread loads its program (a repeated
    command's programs load side by side) and gets the same result."""
    import threading
    import time

    from dampax import _cache

    x = jnp.linspace(0.0, 1.0, 5)
    shift = float(time.time_ns() % 1000003)  # a program no cache of this session holds

    def fn(a):
        return jnp.sin(a) + shift

    first = _cache.call_cached("test-load", shift, fn, x)  # compiled here, kept as a file
    monkeypatch.setattr(_cache, "_EXECUTABLES", {})  # a new process: only the file is left
    got = []
    with _cache._turn():
        worker = threading.Thread(
            target=lambda: got.append(_cache.call_cached("test-load", shift, fn, x)),
            daemon=True)
        worker.start()
        worker.join(timeout=60)
        assert not worker.is_alive()  # it did not wait for the turn
    np.testing.assert_array_equal(got[0], first)
    assert not _cache._TRACING.locked()


def test_background_programs_finish_before_a_fast_exit(monkeypatch):
    """``_cache.finish_background`` (called by the console script before ``os._exit``) waits
    for a program prepared in the background: afterwards it is built and kept as a file, as a
    normal exit (which joins the compile threads) leaves it."""
    import time

    from dampax import _cache

    monkeypatch.setattr(_cache, "_EXECUTABLES", {})
    x = jnp.linspace(0.0, 1.0, 7)
    shift = float(time.time_ns() % 1000033)
    _cache.prepare_cached("test-finish", shift, lambda a: jnp.cos(a) - shift, x)
    _cache.finish_background()
    (entry,) = _cache._EXECUTABLES.values()
    assert not hasattr(entry, "result") or entry.done()
    assert list(_cache.exported_dir().glob("test-finish-*.jaxexe"))


def test_kept_program_returns_equinox_modules_whole():
    """call_cached_tree: an output holding equinox modules (a solution, its RESULTS member)
    comes back with the traced path's treedef and bits; the file holds the program (an
    executable, kept straight from the trace) and its treedef, and a process that reads it
    (here: the memo cleared) rebuilds the same result."""
    import equinox as eqx

    from dampax import _cache

    def fn(osc, x0, v0):
        return dp.solve(osc, x0, v0, phase="undamped"), jnp.asarray(3)

    osc = dp.Oscillator(m=1.0, k=30.0, mu=0.02, D=1.5)
    args = (osc, jnp.asarray(0.2), jnp.asarray(0.0))
    kept = _cache.call_cached_tree("test-tree", "undamped", fn, *args)
    traced = eqx.filter_jit(fn)(*args)
    assert _leaves_equal(kept, traced)
    assert kept[1].weak_type  # jnp.asarray(3) is weakly typed; serialization drops it
    files = list(_cache.dampax_cache_dir().glob("exported/test-tree-*.jax*"))
    assert len(files) == 1
    entries = len(_cache._EXECUTABLES)
    other = _cache.call_cached_tree("test-tree", "undamped", fn,
                                    dp.Oscillator(m=1.0, k=30.0, mu=0.03, D=1.5), *args[1:])
    assert len(_cache._EXECUTABLES) == entries  # new values, the same program
    assert float(other[0].halt_time) < float(kept[0].halt_time)
    for memo in [m for m in _cache._EXECUTABLES if m[0] == "test-tree"]:
        del _cache._EXECUTABLES[memo]  # as a new process: the file is read, not traced
    stamp = files[0].stat().st_mtime_ns
    again = _cache.call_cached_tree("test-tree", "undamped", fn, *args)
    assert files[0].stat().st_mtime_ns == stamp and _leaves_equal(again, traced)
    assert again[0].valid and again[0].message == ""


def test_run_models_is_kept_compiled_and_equals_the_traced_path():
    """`dampax solve`'s models run kept programs: the same solutions and summaries to the bit
    as the traced route, a second oscillator compiles nothing, the programs are on disk."""
    import equinox as eqx

    from dampax import _cache
    from dampax._studies import _summary

    osc = dp.Oscillator(m=1.0, k=30.0, mu=0.0288, D=2.95)
    run = _summary.run_models(osc, 0.2, 0.0, models=["matched", "matched_tail"])
    for name in ("matched", "matched_tail"):
        traced = eqx.filter_jit(_summary._solve_and_summarize)(
            osc, jnp.asarray(0.2), jnp.asarray(0.0), name=name, n_turning=6)
        r = run.results[name]
        assert _leaves_equal(r.solution, traced[0]), name
        assert (r.halt_time, r.halt_position) == (float(traced[1][0]), float(traced[1][1]))
        np.testing.assert_array_equal(r.turning_t, np.asarray(traced[1][2][0]))
    entries = len(_cache._EXECUTABLES)
    _summary.run_models(dp.Oscillator(m=1.0, k=30.0, mu=0.03, D=2.0), 0.2, 0.0,
                        models=["matched", "matched_tail"])
    assert len(_cache._EXECUTABLES) == entries
    assert len(list(_cache.dampax_cache_dir().glob("exported/solve-model-*.jax*"))) >= 2


def test_eager_fit_core_is_kept_compiled_and_equals_the_traced_path():
    """An eager fit runs the kept core program (the traced route runs under jit): the same
    CoreResult to the bit as the traced route compiled with dampax's XLA options
    (``_cache.compiler_options``; a user's jit compiles with XLA's defaults, whose rounding
    may differ in the last bits), a second fit of the same shapes compiles nothing."""
    from dampax import _cache
    from dampax._fit import _core
    from dampax._fit._params import Constants, TraceParams

    t = np.linspace(0.0, 4.0, 400)
    osc = dp.Oscillator(m=1.0, k=30.0, mu=0.01, D=0.5)
    x = np.asarray(dp.solve(osc, 0.1, 0.0).x(jnp.asarray(t)))
    p0 = TraceParams(mu=0.012, b=0.0, D=0.4, w0=np.sqrt(30.0), offset=0.0, x0=0.1, v0=0.0)
    vary = TraceParams(True, False, True, False, True, True, True)
    consts = Constants(m=1.0, g=9.81)
    static = dict(model="ansatz", optimizer="lm", max_steps=64, rtol=1e-8, atol=1e-10,
                  opts=None)
    args = (t, x, np.ones_like(t), p0, vary, consts, np.inf)
    kept = _core.run_core(*args, **static)
    traced = jax.jit(lambda *a: _core.run_core(*a, **static)).lower(*args).compile(
        _cache.compiler_options())(*args)
    assert _leaves_equal(kept, traced)
    assert kept.code == _core.FIT_RESULTS.successful
    entries = len(_cache._EXECUTABLES)
    _core.run_core(t, 1.01 * x, *args[2:], **static)
    assert len(_cache._EXECUTABLES) == entries
    assert list(_cache.dampax_cache_dir().glob("exported/fit-core-*.jax*"))
    # the fit that only starts the exact model: its program compiled without XLA's backend
    # optimisations (about half the compile time), the same fit to rounding
    quick = _core.run_core(*args, quick=True, **static)
    assert list(_cache.dampax_cache_dir().glob("exported/fit-core-quick-*.jax*"))
    if _cache.compiler_options() is not None:  # dampax's own options (a CPU)
        assert _cache.compiler_options("fit-core-quick")["xla_backend_optimization_level"] == 0
    assert _core.is_code(quick.code, _core.FIT_RESULTS.successful)
    assert int(quick.steps) == int(kept.steps)
    for name in ("mu", "D", "w0", "x0"):
        np.testing.assert_allclose(getattr(quick.params, name), getattr(kept.params, name),
                                   rtol=1e-10)


def test_ar1_filter_equals_lfilter():
    """The HAC's backward AR(1) filter (in blocks) gives scipy.signal.lfilter's array to
    rounding, for lengths around the block size and columns of very different scales."""
    from scipy.signal import lfilter

    from dampax._fit._intervals import AR1_BLOCK, _backward_ar1

    rng = np.random.default_rng(3)
    for n in (1, AR1_BLOCK - 1, AR1_BLOCK, 5 * AR1_BLOCK + 7, 3001):
        for order in ("C", "F"):
            J = np.asarray(rng.standard_normal((n, 4)) * [1e-6, 1.0, 1e3, 0.1], order=order)
            for phi in (-0.9, 0.0, 0.37, 0.999):
                want = lfilter([1.0], [1.0, -phi], J[::-1], axis=0)[::-1]
                got = _backward_ar1(J, phi)
                scale = np.max(np.abs(want), axis=0)
                assert got.shape == want.shape
                assert np.max(np.abs(got - want) / scale) < 1e-13, (n, order, phi)


def test_a_kept_program_is_loaded_by_whoever_needs_it_first(monkeypatch):
    """A prepared program with a kept executable is loaded (not compiled) by the loader
    thread, or by its first caller if the loader has not begun it (``_cache._Claimable``):
    loaded once, the same numbers as the compiled program's; a load begun elsewhere is
    awaited, not repeated."""
    import threading
    import time

    from dampax import _cache

    x = jnp.linspace(0.0, 1.0, 6)
    shift = float(time.time_ns() % 1000037)

    def fn(a):
        return jnp.tan(a) - shift

    first = _cache.call_cached("test-claim", shift, fn, x)  # compiled, kept as a file
    monkeypatch.setattr(_cache, "_EXECUTABLES", {})  # a new process
    _cache.prepare_cached("test-claim", shift, fn, x)
    (job,) = _cache._EXECUTABLES.values()
    assert isinstance(job, _cache._Claimable)  # a load, not a compile
    np.testing.assert_array_equal(_cache.call_cached("test-claim", shift, fn, x), first)

    calls, gate = [], threading.Event()

    def slow():
        calls.append(threading.current_thread().name)
        gate.wait(10)
        return "loaded"

    job = _cache._Claimable(slow)
    other = threading.Thread(target=job.run, name="other")
    other.start()
    while not calls:
        time.sleep(0.001)
    job.run()  # claimed by the other thread: returns at once
    gate.set()
    assert job.result() == "loaded" and calls == ["other"]
    other.join()
    mine = _cache._Claimable(lambda: threading.current_thread().name)
    assert mine.result() == threading.current_thread().name  # unclaimed: run by the caller
    mine.run()
    assert mine.result() == threading.current_thread().name


def test_two_threads_that_need_a_program_at_once_build_it_once(monkeypatch):
    """Two threads that call the same program at once (``dampax fit``'s model ranking beside
    its fit) share one build: a kept program is loaded once, a new one traced once; both get
    its numbers. The ranking loaded the approximate model's program a second time beside the
    loader thread before (1.3 s of CPU on 2 cores)."""
    import threading
    import time

    from dampax import _cache

    x = jnp.linspace(0.0, 1.0, 7)
    shift = float(time.time_ns() % 1000039)
    traced = []

    def fn(a):
        traced.append(1)
        time.sleep(0.2)  # (tracing) long enough for the other thread to ask meanwhile
        return jnp.cosh(a) + shift

    def both():
        got, start = [], threading.Barrier(2)

        def call():
            start.wait(10)
            got.append(np.asarray(_cache.call_cached("test-once", shift, fn, x)))

        threads = [threading.Thread(target=call, daemon=True) for _ in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        assert len(got) == 2
        np.testing.assert_array_equal(got[0], got[1])
        return got[0]

    first = both()  # no program yet: traced and compiled once
    assert len(traced) == 1
    np.testing.assert_allclose(first, np.cosh(np.asarray(x)) + shift, rtol=1e-15)
    monkeypatch.setattr(_cache, "_EXECUTABLES", {})  # a new process: the kept file is left
    loads, load = [], _cache._load_executable

    def slow_load(*args, **kwargs):
        loads.append(1)
        time.sleep(0.2)
        return load(*args, **kwargs)

    monkeypatch.setattr(_cache, "_load_executable", slow_load)
    np.testing.assert_array_equal(both(), first)
    assert len(loads) == 1 and len(traced) == 1


def test_jax_cache_does_not_write_the_programs_dampax_keeps(monkeypatch):
    """A program kept as its own executable file is not written to JAX's persistent cache
    too (``_cache._fresh_compilation(kept=True)``: a second serialized copy, and one a later
    process would read instead of keeping its own); elsewhere JAX's rule is unchanged."""
    import time

    from jax._src import compilation_cache
    from jax._src import config as jax_config

    from dampax import _cache

    written = []
    real = compilation_cache.put_executable_and_time
    monkeypatch.setattr(compilation_cache, "put_executable_and_time",
                        lambda *a, **k: (written.append(a[0]), real(*a, **k))[1])
    x = jnp.linspace(0.0, 1.0, 4)
    shift = float(time.time_ns() % 1000039)
    with jax_config.persistent_cache_min_compile_time_secs(0.0):  # write whatever compiles
        out = _cache.call_cached("test-nowrite", shift, lambda a: jnp.sinh(a) * shift, x)
        assert list(_cache.exported_dir().glob("test-nowrite-*.jaxexe"))
        assert written == []
        jax.jit(lambda a: jnp.cosh(a) * shift)(x).block_until_ready()  # not kept by dampax
    np.testing.assert_allclose(out, np.sinh(np.asarray(x)) * shift, rtol=1e-15)
    assert len(written) == 1


def test_an_oscillator_of_numbers_compiles_nothing():
    """Oscillator(m=..., k=...) of Python numbers places its fields as they are: no eager
    conversion is compiled (``jnp.asarray`` of a number compiled one the first time in each
    process: 40-60 ms of every command); inside jit the fields are traced as before."""
    import logging

    seen = []

    class Compiles(logging.Handler):
        def emit(self, record):
            if record.getMessage().startswith("Compiling"):
                seen.append(record.getMessage())

    jax.clear_caches()
    handler, logger = Compiles(), logging.getLogger("jax")
    logger.addHandler(handler)
    try:
        with jax.log_compiles(True):
            osc = dp.Oscillator(m=1.5, k=30.0, mu=0.02, b=0.1, D=1.2, k3=0.0, mu_s=0.03)
    finally:
        logger.removeHandler(handler)
    assert seen == []
    for name in ("m", "k", "mu", "b", "D", "g", "k3", "mu_s"):
        value = getattr(osc, name)
        assert isinstance(value, jax.Array) and value.dtype == jnp.float64
        assert not value.weak_type
    assert float(osc.m) == 1.5 and float(osc.mu_s) == 0.03
    w = jax.jit(lambda m: dp.Oscillator(m=m, k=30.0).omega0)(2.0)
    assert float(w) == pytest.approx(np.sqrt(15.0), rel=1e-15)
