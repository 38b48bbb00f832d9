"""Adversarial inputs (issue 37, items 3 and 4): every bad input gets a named answer in bounded
time, and none a confident wrong one.

Each case is compared against an independent expectation: the error's type and the parameter
(or CLI flag) its message names, a time bound, or a value known without dampax (a start at rest
in the sticking band stays where it is). The cases fail at validation, before anything is
compiled, or re-use programs the other tests compile: the file adds seconds to the suite.
"""

import dataclasses
import math
import os
import re
import time

import numpy as np
import pytest

import dampax as dp
from dampax._cli import main

# ------------------------------------------------------------------------------------------
# option objects: checked when made, every message naming the field


@pytest.mark.parametrize("kwargs, field", [
    (dict(start=math.nan), "Window.start"), (dict(start=math.inf), "Window.start"),
    (dict(start="later"), "Window.start"), (dict(start=True), "Window.start"),
    (dict(start=[1.0, "x"]), r"Window.start\[1\]"), (dict(start=[]), "Window.start"),
    (dict(end=math.inf), "Window.end"), (dict(end=-math.inf), "Window.end"),
    (dict(end=math.nan), "Window.end"), (dict(end="10"), "Window.end"),
    (dict(end=[10.0, math.inf]), r"Window.end\[1\]"), (dict(start=5.0, end=1.0), "Window.end"),
    (dict(start=[0.0, 5.0], end=[3.0, 4.0]), "Window.end"), (dict(units=3), "Window.units"),
    (dict(units=""), "Window.units"), (dict(units=" "), "Window.units"),
])
def test_window_refuses_bad_values_when_made(kwargs, field):
    with pytest.raises(ValueError, match=field):
        dp.Window(**kwargs)


@pytest.mark.parametrize("kwargs, field", [
    (dict(loss="l2"), "LeastSquares.loss"), (dict(optimizer="newton"), "LeastSquares.optimizer"),
    (dict(rtol=-1.0), "LeastSquares.rtol"), (dict(rtol=math.nan), "LeastSquares.rtol"),
    (dict(rtol=math.inf), "LeastSquares.rtol"), (dict(rtol="1e-8"), "LeastSquares.rtol"),
    (dict(atol=0.0), "LeastSquares.atol"), (dict(max_steps=0), "LeastSquares.max_steps"),
    (dict(max_steps=1.5), "LeastSquares.max_steps"), (dict(starts=0), "LeastSquares.starts"),
    (dict(starts=math.inf), "LeastSquares.starts"), (dict(seed=-1), "LeastSquares.seed"),
    (dict(seed=1.0), "LeastSquares.seed"), (dict(seed=True), "LeastSquares.seed"),
    (dict(max_swings=-3), "LeastSquares.max_swings"),
    (dict(p0=[1.0]), "LeastSquares.p0"), (dict(p0={"xx": 1.0}), "LeastSquares.p0"),
    (dict(p0={"w0": 0.0}), r"LeastSquares.p0\['w0'\]"),
    (dict(p0={"w0": -2.0}), r"LeastSquares.p0\['w0'\]"),
    (dict(p0={"mu": -1.0}), r"LeastSquares.p0\['mu'\]"),
    (dict(p0={"mu": math.nan}), r"LeastSquares.p0\['mu'\]"),
    (dict(p0={"D": math.inf}), r"LeastSquares.p0\['D'\]"),
    (dict(p0={"mu": "a"}), r"LeastSquares.p0\['mu'\]"),
    (dict(p0={"x0": True}), r"LeastSquares.p0\['x0'\]"),
])
def test_least_squares_refuses_bad_values_when_made(kwargs, field):
    with pytest.raises(ValueError, match=field):
        dp.LeastSquares(**kwargs)


def test_option_objects_stay_checked():
    """_replace checks as construction does; good values are normalised."""
    with pytest.raises(ValueError, match="Window.end"):
        dp.Window(start=1.0)._replace(end=0.5)
    with pytest.raises(ValueError, match="LeastSquares.seed"):
        dp.LeastSquares()._replace(seed=-4)
    ok = dp.LeastSquares(p0={"mu": 1, "w0": np.float64(8.0)})
    assert ok.p0 == {"mu": 1.0, "w0": 8.0} and ok.checked() is ok
    with pytest.raises(ValueError, match="Window.end: a list of one value per run"):
        dp.fit(np.arange(20.0), np.sin(np.arange(20.0)), window=dp.Window(end=[5.0, 6.0]))


@pytest.mark.parametrize("field, value", [("mu_s", "abc"), ("m", "x"), ("k", None),
                                          ("D", [1.0, "b"]), ("k3", object())])
def test_oscillator_names_a_field_that_is_not_a_number(field, value):
    with pytest.raises(ValueError, match=rf"^{field} must be (a )?finite"):
        dp.Oscillator(**{field: value})


# ------------------------------------------------------------------------------------------
# time axes of fits, and the readers


def _decay(n=400, dt=0.01):
    t = np.arange(n) * dt
    return t, 0.1 * np.exp(-0.1 * t) * np.cos(8.0 * t)


def _time_axes():
    t, x = _decay()
    gap = t.copy()
    gap[-1] = 1e9
    return {
        "every sample twice": (np.repeat(t, 2), np.repeat(x, 2), "repeat"),
        "clock resets": (np.concatenate([t, t]), np.concatenate([x, x]), "goes back"),
        "times near 1e300": (t * 1e300, x, "beyond"),
        "offset by 1e300": (t + 1e300, x, "beyond"),
        "offset by 1e14, steps of 10 ms": (t + 1e14, x, "spacings"),
        "one stray stamp": (gap, x, "gap"),
        "three runs end to end": (np.tile(t, 3), np.tile(x, 3), "goes back 2 time"),
        # told apart from a reset by how often (the message said "a clock that resets")
        "shuffled": (np.random.default_rng(37).permutation(t), x, "not in order"),
        "steps of 1e-302 s": (t * 1e-300, x, "below 1e-12 s"),
    }


@pytest.mark.parametrize("case", list(_time_axes()))
def test_fit_refuses_garbage_time_axes_at_once(case):
    t, x, words = _time_axes()[case]
    began = time.perf_counter()
    with pytest.raises(ValueError, match=rf"^t: .*{words}"):
        dp.fit(t, x, oscillator=dp.Oscillator(m=1.0, k=64.0), model="ansatz")
    assert time.perf_counter() - began < 5.0


def test_fit_names_the_samples_it_leaves_out():
    """NaN or inf samples are left out of a fit with a warning that counts them (they were
    dropped silently), attributed to the caller's line, not to a frame inside dampax."""
    from dampax._fit._problem import read_arrays

    t, x = _decay()
    x[[5, 17, 300]] = [np.nan, np.inf, np.nan]
    t[40] = np.nan
    with pytest.warns(UserWarning, match=r"^t, x: 4 of 400 samples hold NaN or inf") as got:
        kept, _, _ = read_arrays(t, x)
    assert kept.size == 396
    assert got[0].filename == __file__, got[0].filename


@pytest.mark.parametrize("scale", [1e200, 1e-200, 1e-150, 1e150])
def test_fit_refuses_positions_beyond_float64s_squares(scale):
    """x * 1e200 or x * 1e-150 stopped the fit with "SVD did not converge"."""
    t, x = _decay()
    with pytest.raises(ValueError, match=r"^x: positions up to .* outside"):
        dp.fit(t, x * scale, model="ansatz")


def test_phase_drift_is_bounded_by_the_samples():
    """_checks.phase_drift looped over every period up to the last sample: ~1e9 after one
    stray time stamp (400 s); now only over periods that hold samples."""
    from dampax._fit._checks import phase_drift

    t, x = _decay(2000)
    t = np.append(t, 1e9)
    x = np.append(x, 0.0)
    began = time.perf_counter()
    drift = phase_drift(t, x, x, 8.0, 0.0, 1e-3)
    assert time.perf_counter() - began < 2.0 and drift == pytest.approx(0.0, abs=1e-12)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this platform")
def test_load_trace_refuses_a_fifo_without_blocking(tmp_path):
    fifo = tmp_path / "trace.csv"
    os.mkfifo(fifo)
    began = time.perf_counter()
    with pytest.raises(ValueError, match="FIFO"):
        dp.load_trace(fifo)
    assert time.perf_counter() - began < 2.0


@pytest.mark.parametrize("path, words", [("/dev/zero", "a device"), ("/dev/null", "a device"),
                                         (".", "a folder")])
def test_load_trace_refuses_what_is_not_a_regular_file(path, words):
    if not os.path.exists(path):
        pytest.skip(f"no {path} here")
    with pytest.raises(ValueError, match=words):
        dp.load_trace(path)


def test_trace_files_over_the_limit_are_refused(tmp_path):
    from dampax._trace import MAX_TRACE_BYTES, read_regular_file

    path = tmp_path / "big.csv"
    path.write_text("t,x\n" + "0.1,0.2\n" * 100)
    with pytest.raises(ValueError, match=r"\d+ bytes, more than the 64 "):
        read_regular_file(path, max_bytes=64)
    assert read_regular_file(path) == path.read_bytes()
    assert MAX_TRACE_BYTES == 64 * 2**20


# ------------------------------------------------------------------------------------------
# solve: work estimated before it is spent, and no silent underflow

BLOCK = dict(m=1.0, k=30.0, mu=0.0288, D=2.95)  # the README's block: halts at 2.89 s


def test_reference_with_t_end_far_past_the_halt_returns_at_once():
    """t_end = 1e12 s for a block that halts at 2.9 s: the budget comes from the halt (a bound
    from sliding friction), the same program as the default window's."""
    osc = dp.Oscillator(**BLOCK)
    began = time.perf_counter()
    for t_end in (1e12, 1e300):
        sol = dp.solve(osc, 0.2, 0.0, method="reference", t_end=t_end)
        assert bool(sol.valid) and float(sol.halt_time) == pytest.approx(2.8924857, rel=1e-6)
    assert time.perf_counter() - began < 30.0


@pytest.mark.parametrize("osc, t_end", [
    (dict(m=1.0, k=30.0, b=0.1), 1e12), (dict(m=1.0, k=30.0), 1e300),
    (dict(m=1.0, k=30.0, D=1.0), 1e9), (dict(m=1.0, k=30.0, mu=1e-6), 1e12),
])
def test_reference_refuses_windows_beyond_its_budget(osc, t_end):
    began = time.perf_counter()
    with pytest.raises(ValueError, match=r"^t_end = .* half-swings .* limit of 100000"):
        dp.solve(dp.Oscillator(**osc), 0.2, 0.0, method="reference", t_end=t_end)
    assert time.perf_counter() - began < 2.0


@pytest.mark.parametrize("options, name", [
    (dict(rtol=1e-300), "rtol"), (dict(rtol=0.0), "rtol"), (dict(atol=math.nan), "atol"),
    (dict(max_swings=10**12), "max_swings"), (dict(max_swings=2.5), "max_swings"),
    (dict(max_steps_per_swing=10**9), "max_steps_per_swing"), (dict(t_end=-1.0), "t_end"),
])
def test_reference_options_beyond_reason_are_named(options, name):
    with pytest.raises(ValueError, match=rf"^{name} must"):
        dp.solve(dp.Oscillator(**BLOCK), 0.2, 0.0, method="reference", **options)


@pytest.mark.parametrize("method", ["ansatz", "reference", "auto", "coulomb_exact"])
@pytest.mark.parametrize("x0, v0", [(1e-155, 0.0), (0.0, 1e-154), (1e-300, 0.0),
                                    (1e155, 0.0), (0.0, 1e160)])
def test_amplitudes_outside_float64s_range_are_refused(method, x0, v0):
    """A start of amplitude 1e-155 came out as x(0) = 0 with valid = True (A^2 underflows)."""
    osc = dp.Oscillator(m=1.0, k=30.0, b=0.1)
    with pytest.raises(ValueError, match=r"^x0, v0: the start's amplitude .* outside"):
        dp.solve(osc, x0, v0, method=method)


def test_a_tiny_start_at_rest_in_the_sticking_band_is_exact():
    """The exact rest (every model answers it exactly) is not refused, however small."""
    sol = dp.solve(dp.Oscillator(**BLOCK), 1e-155, 0.0)
    assert bool(sol.valid) and float(sol.x(0.5)) == 1e-155


# ------------------------------------------------------------------------------------------
# fits: no confident wrong answer


def test_joint_fit_refuses_runs_in_different_units():
    t, x = _decay()
    a = dp.Trace(t=t, x=x, position_column="x(m)")
    b = dp.Trace(t=t, x=1e3 * x, position_column="x(mm)")
    began = time.perf_counter()
    with pytest.raises(ValueError, match=r"^traces: .*different units .*'m'.*'mm'"):
        dp.fit([a, b], oscillator=dp.Oscillator(m=1.0, k=64.0), model="ansatz")
    assert time.perf_counter() - began < 2.0


@pytest.mark.parametrize("end", [math.inf, [4.0, math.nan], -math.inf])
def test_joint_fit_refuses_windows_a_single_fit_refuses(end):
    from dampax._fit._joint import fit_joint

    t, x = _decay()
    with pytest.raises(ValueError, match="Window.end"):
        fit_joint([(t, x), (t, x)], end=end)


@dataclasses.dataclass(frozen=True)
class _Fit:
    params: dict
    success: bool = True
    reason: str = ""


@pytest.mark.parametrize("mu, mu_s, fails", [(3e-3, 1e-5, True), (1e-5, 1e-5, False),
                                             (2e-3, 3e-3, False), (1.0 + 1e-6, 1.0, True)])
def test_a_fitted_mu_above_the_given_mu_s_fails_with_the_reason(mu, mu_s, fails):
    """fit(model="reference", mu_s=1e-5) reported mu = 0.003 > mu_s as a success."""
    from dampax._fit._halts import above_mu_s

    out = above_mu_s(_Fit({"mu": mu, "D": 0.1}), mu_s)
    assert out.success is not fails
    if fails:
        assert re.search(r"fitted mu = .* exceeds the given mu_s", out.reason)


def test_the_halt_search_skips_a_motion_that_cannot_be_integrated():
    """A fitted motion that the reference cannot follow past the data (here a softening
    spring, k = 1, k3 = -1, whose start x0 = 2 lies beyond the potential's maximum at
    sqrt(k/|k3|) = 1: ``dp.solve`` raises) has no neighbouring halt to search: the thresholds
    are NaN. Before, the solver's ValueError ("check the oscillator's parameters") left
    dp.fit (draw 54 of ``fit_calibration.py --wide --seed 8``, a fit with k3) instead of a
    failed fit with its reason. A start below the barrier has both thresholds."""
    from dampax._fit._halts import other_halts

    t = np.linspace(0.0, 10.0, 100)
    with pytest.raises(ValueError, match="softening spring"):
        dp.solve(dp.Oscillator(m=1, k=1, mu=0.01, k3=-1.0), 2.0, 0.0, method="reference",
                 t_end=20.0)
    p = dict(mu=0.01, b=0.0, D=0.0, w0=1.0, x0=2.0, v0=0.0)
    assert all(math.isnan(v) for v in other_halts(p, t, 1.0, 9.81, -1.0))
    below = other_halts(dict(p, x0=0.5), t, 1.0, 9.81, -1.0)
    assert all(math.isfinite(v) and v > 0 for v in below)


def test_the_motion_that_halts_at_its_first_turning_point_keeps_the_fits_first_swing():
    """The flat side of mu's profile (fit_calibration.py --wide, seed 9, draw 6, refitted with
    b and D at their truth: a fit of mu = 0.0116 +- 0.0027 that halts at its second turning
    point, with the truth 0.065 19 sd away, was a confident wrong answer). Over the first
    swing eq. 3's friction only moves the centre, so the start of the first-halt basin
    (``_halts.first_halt_start``: mu doubled past the threshold, x0 and the offset moved by
    the centre's shift) must give the fit's first swing to rounding and then halt at that
    turning point, by scipy's integrator with events; every larger mu does too."""
    from helpers import evaluate, scipy_stick_slip

    from dampax._fit._halts import first_halt, first_halt_start
    from dampax._fit._params import TraceParams

    p = TraceParams(mu=0.0116046, b=3.28444, D=19.5844, w0=3.54693, offset=0.0429704,
                    x0=0.0233933, v0=-0.237092)
    t = np.linspace(0.0, 6.63504, 2000)
    constants = (1.0, 9.81, 0.0)
    assert not first_halt(p, t, constants)  # its own motion halts at the second
    q = first_halt_start(p, t, constants)
    assert q.mu > 2.0 * p.mu - 1e-12 and q.v0 == p.v0 and q.w0 == p.w0

    def measured(r, mu):
        seg, turning, rest = scipy_stick_slip(1.0, r.w0 ** 2, mu, r.b, r.D, r.x0, r.v0,
                                              t[-1])
        return seg, turning, rest, r.offset + evaluate(seg, rest, t)[0]

    seg, turning, _, x_p = measured(p, p.mu)
    assert len(turning) >= 2
    first = t <= turning[0][0]
    for mu in (q.mu, 3.0 * q.mu):
        shift = (mu - q.mu) * 9.81 / q.w0 ** 2  # (v0 < 0: the centre moves up with mu)
        r = q._replace(x0=q.x0 + shift, offset=q.offset - shift)
        seg, turning, rest, x_q = measured(r, mu)
        assert rest is not None and len(seg) == 1 and rest[0] == pytest.approx(turning[0][0])
        np.testing.assert_allclose(x_q[first], x_p[first], rtol=0, atol=1e-9)
        assert first_halt(r._replace(mu=mu), t, constants)


# ------------------------------------------------------------------------------------------
# error maps: the size first


@pytest.mark.parametrize("n", [1000, 100_000])
def test_error_map_refuses_a_grid_beyond_the_memory(n):
    from dampax._studies._maps import physical_memory

    axis = np.linspace(0.0, 0.1, n)
    if 6000.0 * n ** 3 < 0.5 * physical_memory():
        pytest.skip("this machine has the memory for it")
    began = time.perf_counter()
    with pytest.raises(ValueError, match=r"d0_ratio, d1_ratio, d2_ratio, phi0: a grid of .* "
                                         r"GiB of memory .* days"):
        dp.error_map(d0_ratio=axis, d2_ratio=axis, phi0=axis, progress=False)
    assert time.perf_counter() - began < 5.0


@pytest.mark.parametrize("text", ["0:0.1:" + "1" * 70, "0:0.1:0", "0:0.1:-4", "10**400",
                                  "1" * 400, "-" * 5000 + "1", "pi(1)", "__import__('os')"])
def test_error_map_axes_of_the_command_line_are_named(text):
    from dampax._studies._maps import parse_axis

    with pytest.raises(ValueError, match="^--d0: cannot read"):
        parse_axis(text, "--d0")


# ------------------------------------------------------------------------------------------
# the command line: one named line and a nonzero status, never a traceback

CLI_CASES = [
    (["solve", "--b", "20"], "--b 20: the oscillator is not underdamped"),
    (["solve", "--x0", "1e-160"], "--x0 1e-160, --v0 0: the start's amplitude"),
    (["solve", "--v0", "inf"], "--v0 must be a finite number"),
    (["solve", "--t-end", "inf"], "--t-end must be a finite time"),
    (["solve", "--t-end", "-3"], "--t-end must be a finite time"),
    (["errormap", "--d0", "0:0.1:" + "9" * 70], "--d0: cannot read"),
    (["errormap", "--d0", "0:0.1:1000", "--d2", "0:0.5:1000", "--phi0", "0:3:1000"],
     "--d0, --d1, --d2, --phi0: a grid of 1e\\+09 points"),
    (["errormap", "--d0", "0:0.1:100", "--d2", "0:0.5:100", "--phi0", "0:3:100"],
     "--d0, --d1, --d2, --phi0: a grid of 1000000 points .* pass --yes"),
    (["fit", "--example", "--seed", "-1"], "--seed must be an integer >= 0"),
    (["fit", "--example", "--end", "nan"], "--end must be"),
    (["fit", "--example", "--starts", "0"], "--starts must be a positive integer"),
]


@pytest.mark.parametrize("argv, message", CLI_CASES, ids=[" ".join(a)[:40] for a, _ in CLI_CASES])
def test_cli_answers_bad_input_with_one_named_line(argv, message, capsys, tmp_path):
    if argv[0] in ("errormap", "fit"):
        argv = [*argv, "--out", str(tmp_path / "out")]
    began = time.perf_counter()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert re.match(rf"dampax: error: {message}", err), err
    assert time.perf_counter() - began < 10.0


def test_cli_fit_names_the_flag_of_a_window_without_samples(tmp_path, capsys):
    t, x = _decay()
    path = tmp_path / "trace.csv"
    path.write_text("t,x\n" + "".join(f"{a:.17g},{b:.17g}\n" for a, b in zip(t, x, strict=True)))
    assert main(["fit", str(path), "--end", "-5", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert re.match(r"dampax: error: --start, --end: the fit window .* fewer than 10", err), err


def test_cli_turns_any_other_exception_into_one_line(monkeypatch, capsys):
    """No traceback reaches a user: an exception no check caught ends with one line naming its
    type and status 1 (DAMPAX_TRACEBACK=1 shows it)."""
    from dampax import _cli

    def broken(args):
        raise OverflowError("int too large to convert to float")

    add, _ = _cli.SUBCOMMANDS["solve"]
    monkeypatch.setitem(_cli.SUBCOMMANDS, "solve", (add, broken))
    monkeypatch.delenv("DAMPAX_TRACEBACK", raising=False)
    assert main(["solve"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    assert err.startswith("dampax: error: unexpected OverflowError: int too large")
    monkeypatch.setenv("DAMPAX_TRACEBACK", "1")
    with pytest.raises(OverflowError):
        main(["solve"])


@dataclasses.dataclass(frozen=True)
class _K3Fit:
    params: dict
    t: np.ndarray
    chisqr: float = 0.0
    free: tuple = ("mu", "D")
    varied: tuple = ("mu", "D")
    stderr: dict = dataclasses.field(default_factory=lambda: {"mu": 1e-5, "D": 1e-4})


def test_k3_model_bias_is_the_refit_of_the_exact_motion(monkeypatch):
    """_stiffness.model_bias (the k3 fit of an approximate model: D came out 43 standard errors
    off with success): the exact motion of the fit's constants replaces the data of the same
    prepared problem (no new analysis), started at the fit's values with one start, and is
    refitted at k3 = e -+ h; a stand-in fit whose cost is a parabola in e with its minimum at
    e0 and whose D moves by 0.002 + 0.5 (e - e_best) gives the shifts known in closed form."""
    from dampax._fit import _stiffness
    from dampax._fit._params import Constants
    from dampax._fit._problem import Settings

    t = np.linspace(0.0, 2.0, 64)
    params = dict(mu=0.002, b=0.0, D=0.05, w0=8.66, offset=0.0, x0=0.1, v0=0.0)
    best = _K3Fit(params, t)
    e_best, e0, scale, h = 0.07, 0.0712, 2000.0, 2e-3
    prepared, seen = [], []

    class Held:
        def __init__(self, k3=None):
            self.k3 = k3

        def with_consts(self, k3):
            return Held(k3)

    class Problem:
        settings = Settings(model="ansatz")
        consts = Constants(m=1.0, g=9.81)

        def with_positions(self, x_):
            prepared.append(("positions", x_.shape))
            return self

        def starting_at(self, p0, *, starts=None):
            prepared.append(("start", starts, p0 == params))
            return Held()

    def run(problem, plan):
        e = problem.k3 / scale
        seen.append(e)
        return _K3Fit({**params, "D": params["D"] + 0.002 + 0.5 * (e - e_best)}, t,
                      chisqr=3.0 * (e - e0) ** 2 + 1.0)

    monkeypatch.setattr(_stiffness, "run", run)
    out = _stiffness.model_bias(Problem(), best, (e_best, scale, h, 5e-4))
    assert prepared == [("positions", t.shape), ("start", 1, True)]
    assert seen == pytest.approx([e_best - h, e_best, e_best + h])
    assert out["k3"]["shift"] == pytest.approx((e0 - e_best) * scale, rel=1e-9)
    assert out["k3"]["z"] == pytest.approx(abs(e0 - e_best) / 5e-4, rel=1e-9)
    assert out["D"]["shift"] == pytest.approx(0.002 + 0.5 * (e0 - e_best), rel=1e-9)
    assert out["D"]["z"] == pytest.approx(out["D"]["shift"] / 1e-4, rel=1e-9)
    assert out["mu"]["shift"] == pytest.approx(0.0, abs=1e-15)


@pytest.mark.parametrize("n, words", [(10**9, "at most 1000000"), (-1, ">= 0"), (2.0, "integer")])
def test_turning_points_refuses_counts_it_cannot_allocate(n, words):
    sol = dp.solve(dp.Oscillator(**BLOCK), 0.2, 0.0)
    with pytest.raises(ValueError, match=rf"^n must .*{words}"):
        dp.turning_points(sol, n)


@pytest.mark.parametrize("m, k", [(1e300, 1e-300), (1e-300, 1e300), (1e200, 1e-200)])
def test_oscillator_refuses_a_frequency_float64_cannot_square(m, k):
    with pytest.raises(ValueError, match=r"^m, k: w0 = sqrt\(k/m\)"):
        dp.Oscillator(m=m, k=k)


def test_sensitivity_refuses_turning_points_it_cannot_follow():
    with pytest.raises(ValueError, match=r"^turning_points must be at most 1000"):
        dp.sensitivity(dp.Oscillator(**BLOCK), 0.2, 0.0, np.linspace(0.0, 1.0, 5),
                       wrt=("mu",), turning_points=10**9)


@pytest.mark.parametrize("argv, message", [
    (["sensitivity", "--x0", "0", "--v0", "1e-170"], "--x0 0, --v0 1e-170: the start's amplitude"),
    (["sensitivity", "--turning-points", "1000000000"], "--turning-points must be between 0 and"),
    (["solve", "--m", "1e300", "--k", "1e-300"], r"m, k: w0 = sqrt\(k/m\)"),
])
def test_cli_sensitivity_and_units_answer_at_once(argv, message, capsys):
    began = time.perf_counter()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert re.match(rf"dampax: error: {message}", err) and "\n" not in err, err
    assert time.perf_counter() - began < 10.0
