"""Joint fits of several runs (dampax._fit._joint, issue 25 item 2): shared damping constants.

Truth from an independent integrator (scipy DOP853 with exact stick-slip, tests/helpers.py and
benchmarks/joint_calibration.py). The tests share one layout (2 runs, shared mu and D, the
oscillator given, padded length 4096, 8 global starts, a swing budget of 64) so that the
compiled programs are shared.
"""

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import evaluate, scipy_stick_slip

import dampax as dp
from dampax._trace import load_trace

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
needs_data = pytest.mark.skipif(
    not DATA.is_dir(), reason=f"measured data not found at {DATA} (the shared data folder "
                              "beside the checkout); skipping the real-data fits")

OSC = dp.Oscillator(m=1.0, k=30.0)
MU, D = 0.01, 0.5
RUNS = ((0.2, 0.0, 6.0, 1e-3, 0.003), (0.12, 0.5, 4.0, 2e-3, -0.002))  # x0, v0, T, noise, off
COMMON = dict(oscillator=OSC, free=("mu", "D"), shared=("mu", "D"), start="data", starts=8,
              max_swings=64)


def _runs():
    rng = np.random.default_rng(1)
    out = []
    for x0, v0, T, noise, off in RUNS:
        t = np.arange(0.0, T, 1 / 200)
        seg, _, rest = scipy_stick_slip(1.0, 30.0, MU, 0.0, D, x0, v0, T, rtol=1e-11,
                                        atol=1e-13)
        out.append((t, evaluate(seg, rest, t)[0] + off + noise * rng.standard_normal(t.size)))
    return out


@pytest.fixture(scope="module")
def runs():
    return _runs()


@pytest.fixture(scope="module")
def joint(runs):
    return dp.fit(runs, model="reference", **COMMON)


def test_joint_reference_fit_holds_the_truth(joint, runs):
    assert isinstance(joint, dp.JointResult)
    assert joint.success, joint.reason
    ci = joint.conf_interval(0.99)
    for name, value in (("mu", MU), ("D", D)):
        assert ci[name][0] < value < ci[name][1], (name, ci[name])
    # each run's own residuals at its noise level, offsets and starts recovered
    for res, (x0, _v0, _, noise, off) in zip(joint.runs, RUNS, strict=True):
        assert res.rms == pytest.approx(noise, rel=0.1)
        assert abs(res.params["offset"] - off) < 0.3 * noise
        assert res.params["x0"] == pytest.approx(x0, abs=5 * noise)
    # one joint problem: the intervals are narrower than each run's single fit
    for s in joint.singles:
        assert joint.hac_stderr["D"] < s.hac_stderr["D"]
    assert joint.names[:2] == ["mu", "D"] and "x0[1]" in joint.names
    assert set(joint.conf_interval(0.9, runs=True)) == set(joint.names)


def test_joint_problem_and_report(joint):
    """The joint problem for other samplers: the residual function of the physical vector
    reproduces the fit's residuals; the report and summary read the shared values."""
    pr = joint.problem()
    assert pr.names == joint.names and pr.nonneg == ("mu", "D")
    r = np.asarray(pr.residuals(pr.p0))
    for j, res in enumerate(joint.runs):
        n = res.ndata
        assert pr.mask[j].sum() == n
        np.testing.assert_allclose(-r[j, :n], res.residuals, atol=1e-9)
        assert np.all(r[j, n:] == 0.0)
    text = joint.report()
    assert "[[Shared]]" in text and "single fits" in text and "run 1:" in text
    summary = joint.summary()
    assert summary.splitlines()[0].startswith("joint fit of 2 runs (reference), shared: mu, D")
    assert "rms" in summary
    json.dumps(joint.to_dict())


def test_joint_fit_input_errors(runs):
    with pytest.raises(ValueError, match="shared"):
        dp.fit(*runs[0], oscillator=OSC, shared=("mu", "D"))
    with pytest.raises(ValueError, match="traces"):
        dp.fit([runs[0]], oscillator=OSC)
    with pytest.raises(ValueError, match="shared must name"):
        dp.fit(runs, oscillator=OSC, shared=("mu", "q"))
    with pytest.raises(ValueError, match="shared: 'w0'"):
        dp.fit(runs, oscillator=OSC, shared=("mu", "w0"))
    with pytest.raises(ValueError, match="loss"):
        dp.fit(runs, oscillator=OSC, loss="soft_l1")
    with pytest.raises(ValueError, match=r"traces\[1\]"):
        dp.fit([runs[0], (runs[1][0], np.zeros_like(runs[1][0]))], **COMMON)


def test_cli_joint_fit(runs, tmp_path, capsys, monkeypatch):
    from dampax import _cli
    from dampax._cli.fit import add_arguments, run

    monkeypatch.setitem(_cli.SUBCOMMANDS, "fit", (add_arguments, run))
    paths = []
    for j, (t, x) in enumerate(runs):
        path = tmp_path / f"run{j + 1}.csv"
        path.write_text("t,x\n" + "".join(f"{a:.4f},{b:.7f}\n" for a, b in zip(t, x,
                                                                                strict=True)))
        paths.append(str(path))
    out = tmp_path / "out"
    assert _cli.main(["fit", *paths, "--shared", "mu,D", "--free", "mu,D", "--m", "1",
                      "--k", "30", "--start", "data", "--starts", "8", "--model", "reference",
                      "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "[[Shared]]" in text and "run1.csv" in text
    summary = json.loads((out / "fit.json").read_text())
    assert summary["fit"]["shared"] == ["mu", "D"]
    assert len(summary["fit"]["runs"]) == 2
    assert (out / "fit.png").read_bytes()[:4] == b"\x89PNG"
    assert _cli.main(["fit", paths[0], "--shared", "mu,D"]) == 2
    assert "--shared needs two or more" in capsys.readouterr().err


def test_joint_generated_family_sample():
    """Two sets of benchmarks/joint_calibration.py (2 runs each, the oscillator given, mu and
    D present): the truth inside the 99 % intervals of a successful joint fit."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "joint_calibration.py"
    spec = importlib.util.spec_from_file_location("joint_calibration", path)
    cal = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cal)
    rng = np.random.default_rng(7)
    picked = []
    while len(picked) < 2:
        s = cal.draw(rng, n_runs=2, free=("mu", "D"))
        if s["given"]:
            picked.append(s)
    for s in picked:
        runs = cal.simulate(s)
        res = dp.fit(runs, model="reference", **{**COMMON, "oscillator": dp.Oscillator(
            m=s["m"], k=s["k"]), "start": "data"})
        assert res.success, res.reason
        ci = res.conf_interval(0.99)
        for name, value in cal.truth_of(s).items():
            assert ci[name][0] <= value <= ci[name][1], (name, value, ci[name])


@needs_data
def test_spring_runs_1_and_2_joint_agrees_with_the_single_fits():
    osc = dp.Oscillator(m=0.2016, k=14.91945)
    traces = [load_trace(DATA / "spring_mass_airdrag" / f"run{i}.csv") for i in (1, 2)]
    res = dp.fit(traces, oscillator=osc, free=("b", "D"), shared=("b", "D"), fit_omega0=True,
                 starts=8)
    assert res.success, res.reason
    ci = res.conf_interval(0.95)
    for single, run in zip(res.singles, res.runs, strict=True):
        own = single.conf_interval(0.95)
        for name in ("b", "D"):
            assert own[name][0] < res.params[name] < own[name][1], (name, res.params[name])
            assert ci[name][0] < single.params[name] < ci[name][1]
        assert run.rms < 1.01 * single.rms
        assert 8.40 < run.params["w0"] < 8.50
