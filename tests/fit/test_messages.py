"""The numbers in the fit's messages say what the sentence claims (issue 36, item 5)."""

from __future__ import annotations

import math
import re

import pytest

from dampax._fit._text import lower_cost, time_span


@pytest.mark.parametrize("new, old", [(0.032391, 0.0323914), (1.0, 2.0), (5e-9, 5.0000001e-9),
                                      (2333.0, 2333.0000004)])
def test_a_lower_cost_prints_a_lower_number(new, old):
    text = lower_cost(new, old)
    a, b = (float(v) for v in re.match(r"(\S+) < (\S+),", text).groups())
    assert a < b and a == pytest.approx(new, rel=1e-3) and b == pytest.approx(old, rel=1e-3)


@pytest.mark.parametrize("lo, hi", [(2333.1, 2333.4), (0.5, 12.0), (1e-3, 1.0001e-3)])
def test_a_time_span_prints_two_different_ends(lo, hi):
    a, b = (float(v) for v in re.match(r"(\S+)-(\S+) s", time_span(lo, hi)).groups())
    assert a < b and a == pytest.approx(lo, rel=1e-4) and b == pytest.approx(hi, rel=1e-4)


def test_a_held_k3_is_reported_as_fixed():
    """issue 36: dp.fit(..., k3=...) names the held k3 in params, fixed, the report and JSON."""
    import json

    import numpy as np

    import dampax as dp

    ts = np.linspace(0.0, 12.0, 300)  # (the cubic ansatz: its phase integral per sample)
    osc = dp.Oscillator(m=1.0, k=4.0, D=0.5, k3=2.0)
    sol = dp.solve(osc, 0.3, 0.0, method="reference", t_end=12.0, ts=ts)
    x = np.asarray(sol.x(ts)) + 0.002 * np.random.default_rng(0).standard_normal(ts.size)
    res = dp.fit(ts, x, oscillator=dp.Oscillator(m=1.0, k=4.0), free=("D",), k3=2.0,
                 model="ansatz")
    assert res.params["k3"] == 2.0 and res.fixed["k3"] == 2.0
    assert json.loads(json.dumps(res.to_dict(), default=str))["fixed"]["k3"] == 2.0
    assert any(line.split()[:3] == ["k3:", "2", "(fixed)"] for line in res.report().splitlines())


def test_an_oscillators_own_k3_is_held_by_the_fit():
    """An oscillator's k3 is held by the fit as k3=... is (it was left out without a word: a
    linear spring fitted); a different k3= beside it, and an envelope fit of it, are refused
    with the reason."""
    import numpy as np

    import dampax as dp

    ts = np.linspace(0.0, 12.0, 300)  # (the shapes of the test above: its programs)
    osc = dp.Oscillator(m=1.0, k=4.0, D=0.5, k3=2.0)
    sol = dp.solve(osc, 0.3, 0.0, method="reference", t_end=12.0, ts=ts)
    x = np.asarray(sol.x(ts)) + 0.002 * np.random.default_rng(0).standard_normal(ts.size)
    held = dp.Oscillator(m=1.0, k=4.0, k3=2.0)
    res = dp.fit(ts, x, oscillator=held, free=("D",), model="ansatz")
    ref = dp.fit(ts, x, oscillator=dp.Oscillator(m=1.0, k=4.0), free=("D",), k3=2.0,
                 model="ansatz")
    assert res.fixed["k3"] == 2.0 and res.params["D"] == ref.params["D"]
    lo, hi = res.conf_interval(0.99)["D"]
    assert lo <= 0.5 <= hi
    with pytest.raises(ValueError, match="k3: the oscillator holds k3=2.0"):
        dp.fit(ts, x, oscillator=held, free=("D",), k3=1.0, model="ansatz")
    with pytest.raises(ValueError, match="oscillator: an envelope fit"):
        dp.fit_envelope([1.0, 2.0, 3.0, 4.0], [1.0, 0.8, 0.6, 0.45], oscillator=held)


def test_residual_structure_finds_a_swing_and_skips_a_curve_that_is_not_finite():
    """The residual test of the fit's verdict (_checks.residual_structure): white noise passes,
    a swing at w0 in two periods of the window is found there, and residuals that are not
    finite everywhere (a held refit of a k3 or mu_s search whose model diverged) give no test
    (p NaN, its fit fails elsewhere), not numpy's LinAlgError, which was counted a refusal of
    the whole fit (3 draws of benchmarks/fit_calibration.py)."""
    import numpy as np

    from dampax._fit._checks import residual_structure

    rng = np.random.default_rng(1)
    t = np.arange(4000) * 0.01
    w0 = 2.0 * np.pi
    r = rng.standard_normal(t.size)
    assert residual_structure(t, r, w0)["p"] > 0.01
    bump = np.where((t > 20) & (t < 22), 1.5 * np.cos(w0 * t), 0.0)
    found = residual_structure(t, r + bump, w0)
    assert found["p"] < 1e-6 and 19.5 < found["worst"][0] < 22.5
    r[100] = np.nan
    assert np.isnan(residual_structure(t, r, w0)["p"])


def test_residual_structure_finds_a_level_the_model_lacks():
    """White noise about a level of 10 noise sd (a fit that holds the offset at 0 where the
    data have one) is structure: the level is not read as AR(1) noise of phi -> 1 (the lag-1
    autocorrelation about 0 is 0.99 there, and prewhitening by it removed the level); white
    noise about 0 still passes, and AR(1) noise of phi = 0.9 about 0 too."""
    import numpy as np

    from dampax._fit._checks import residual_structure

    rng = np.random.default_rng(3)
    t = np.arange(4000) * 0.01
    w0 = 2.0 * np.pi
    e = rng.standard_normal(t.size)
    assert residual_structure(t, e, w0)["p"] > 0.01
    assert residual_structure(t, e + 10.0, w0)["p"] < 1e-12
    ar = np.zeros(t.size)
    for i in range(1, t.size):
        ar[i] = 0.9 * ar[i - 1] + e[i]
    assert residual_structure(t, ar, w0)["p"] > 1e-3


def test_residual_structure_equals_a_least_squares_fit_per_block():
    """The blocks' regressions, all at once by their normal equations, give what a
    least-squares fit per block gives (numpy's lstsq on the prewhitened 1, cos and sin of
    the time from the block's start, as the test is defined): the sum and the largest of
    the explained shares, and their p-values, for AR(1) residuals with a local swing."""
    import math

    import numpy as np

    from dampax._fit._checks import residual_structure
    from dampax._fit._dist import chi2_sf
    from dampax._fit._intervals import ar1_coefficient

    rng = np.random.default_rng(2)
    for n, w0, dt, phi in [(3000, 2.0, 0.01, 0.8), (700, 30.0, 0.001, -0.5), (20, 1.0, 0.1, 0.3)]:
        t = np.arange(n) * dt
        r = np.zeros(n)
        e = rng.standard_normal(n)
        for i in range(n):
            r[i] = (phi * r[i - 1] if i else 0.0) + e[i]
        r += 0.2 * np.cos(w0 * t) * (t > t[n // 2])
        got = residual_structure(t, r, w0)
        size = int(max(round(math.pi / w0 / dt), 16))
        J = max(n // size, 1)
        edges = np.linspace(0, n, J + 1).astype(int)
        a = ar1_coefficient(r - r.mean(), clip=(-0.99, 0.99))  # about the residuals' mean
        q, rss, dof = np.zeros(J), 0.0, 0
        for j, (lo, hi) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
            tt = t[lo:hi] - t[lo]
            X = np.stack([np.ones(hi - lo), np.cos(w0 * tt), np.sin(w0 * tt)], axis=1)
            rw, Xw = r[lo + 1:hi] - a * r[lo:hi - 1], X[1:] - a * X[:-1]
            coef = np.linalg.lstsq(Xw, rw, rcond=None)[0]
            q[j] = np.sum((Xw @ coef) ** 2)
            rss, dof = rss + np.sum((rw - Xw @ coef) ** 2), dof + rw.size - 3
        q = q / (rss / dof)
        k = int(np.argmax(q))
        assert got["blocks"] == J
        assert got["p_global"] == pytest.approx(chi2_sf(float(q.sum()), 3 * J), rel=1e-9)
        assert got["p_local"] == pytest.approx(min(1.0, J * chi2_sf(float(q[k]), 3)), rel=1e-9)
        assert got["q_share"] == pytest.approx(q[k] / q.sum(), rel=1e-9)
        assert got["worst"] == (t[edges[k]], t[edges[k + 1] - 1])


def test_a_ranking_in_another_thread_does_not_silence_the_fits_warnings():
    """``compare_models`` quiets its candidates' window warnings (the fit's own, repeated) in
    its thread only. It ignored warnings process-wide (``warnings.catch_warnings``), so with
    the ranking beside the fit (``dampax fit``) the fit's own warning could be lost: here the
    ranking's thread holds its quiet block while this thread prepares a fit whose m and k
    disagree with the trace's turning points by 10 %, and the warning must still arrive."""
    import threading
    import warnings

    import numpy as np

    import dampax as dp
    from dampax._fit._problem import Settings, prepare, quiet_windows

    t = np.linspace(0.0, 20.0, 2000)
    x = 0.05 * np.exp(-0.05 * t) * np.cos(6.6 * t)  # w0 = 6.6 rad/s, told 6.0 below
    settings = Settings(oscillator=dp.Oscillator(m=1.0, k=36.0), free=("b",))
    inside, leave = threading.Event(), threading.Event()

    def ranking():
        with quiet_windows():
            inside.set()
            leave.wait(30.0)

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        other = threading.Thread(target=ranking)
        other.start()
        assert inside.wait(30.0)
        try:
            prepare(t, x, settings)
            with quiet_windows():  # and in this thread's own quiet block, none
                prepare(t, x, settings)
        finally:
            leave.set()
            other.join()
    texts = [str(w.message) for w in caught]
    assert len(texts) == 1 and "turning points" in texts[0], texts


class _Stop(Exception):
    pass


def test_full_starts_runs_the_ansatz_start_as_the_ansatz_own_fit(monkeypatch):
    """The default fit starts the exact model from the ansatz compiled by XLA's quickest route
    (``quick``); inside ``full_starts`` (``dampax fit``, whose ranking builds the ansatz's own
    program beside the fit) the start runs that program, in that thread only."""
    import threading

    import numpy as np

    import dampax as dp
    from dampax._fit import _problem
    from dampax._fit._problem import full_starts

    seen = []

    def stop(*args, **kwargs):
        seen.append(kwargs["quick"])
        raise _Stop

    monkeypatch.setattr(_problem, "run_core", stop)
    t = np.linspace(0.0, 10.0, 1000)
    x = 0.05 * np.exp(-0.1 * t) * np.cos(6.0 * t)
    osc = dp.Oscillator(m=1.0, k=36.0)

    def one():
        with pytest.raises(_Stop):
            dp.fit(t, x, oscillator=osc, free=("mu", "D"))

    one()
    with full_starts():
        one()
        other = threading.Thread(target=one)
        other.start()
        other.join()
    one()
    assert seen == [True, False, True, True]


def test_draws_that_never_moved_are_named_not_divided_by():
    """A posterior whose draws of a constant never moved (sd 0, a ratio of 0 to the fit's
    interval) is said so: ``dampax fit --example --posterior --draws 20 --warmup 20
    --chains 1`` stopped with ZeroDivisionError in this line."""
    from dampax._fit._posterior_result import narrow_text

    text = narrow_text({"mu": 0.0, "D": 0.25, "b": 3e-14})
    assert "D 4x" in text and "draws of mu, b never moved" in text and "mu 0" not in text
    assert "never moved" not in narrow_text({"D": 0.25})
    assert narrow_text({"mu": 0.0}).startswith("the draws of mu never moved")


@pytest.mark.parametrize("level", [0.0, 10.0])
def test_an_unidentifiable_split_names_a_level_the_fit_holds(level):
    """mu and D measured together, neither alone (each 1 sd from 0, correlation -0.99): not
    separately identifiable. Where the residuals sit about a level (the offset held at 0 on
    data with an offset of 0.06, 60 noise sd: the refusal named only the split), the reason
    names the level and offset=True; about 0 it does not."""
    from types import SimpleNamespace

    import numpy as np

    from dampax._fit._assess import Inputs, split
    from dampax._fit._measures import Measures

    t = np.linspace(0.0, 20.0, 2000)
    r = np.random.default_rng(4).standard_normal(t.size) + level
    names = ("mu", "D", "w0")
    cov = np.array([[1.0, -0.99, 0.0], [-0.99, 1.0, 0.0], [0.0, 0.0, 1.0]])
    a = Inputs(t=t, x=r, curve=np.zeros_like(t), params={"mu": 1.0, "D": 1.0, "w0": 8.0},
               stderr=dict.fromkeys(names, 1.0), varied=names, derived={},
               an=SimpleNamespace(n_turns=54), converged=True, message="")
    m = Measures(r=r, rms=float(np.sqrt(np.mean(r**2))), period=0.8, cov=cov,
                 sd=dict.fromkeys(names, 1.0), st={})
    text = split(a, m, None).diag["unidentifiable"]
    assert text.startswith("mu and D are not separately identifiable")
    assert ("offset=True fits it" in text) == (level > 0), text


@pytest.mark.parametrize("level, held, noted", [(0.06, 0.0, True), (0.0, 0.0, False),
                                                (0.06, 0.06, False), (0.002, 0.0, False)])
def test_a_held_offset_away_from_the_data_is_noted(level, held, noted):
    """The offset held (offset=False) 0.06 from the centre of swings of 0.1 (scipy's
    integrator, mu and D, 1 % noise): the fit stuck at the level after one swing and was
    refused as "not separately identifiable", naming neither; the note names the level. Held
    at the data's level, or 2 % of the amplitude away, nothing is noted."""
    import numpy as np
    from helpers import evaluate, scipy_stick_slip

    from dampax._fit._analysis import analyse
    from dampax._fit._inputs import held_offset_warning

    t = np.linspace(0.0, 20.0, 2000)
    seg, _, rest = scipy_stick_slip(0.2, 15.0, 0.002, 0.0, 0.02, 0.1, 0.0, t[-1] + 1e-9)
    x = evaluate(seg, rest, t)[0] + level + 0.001 * np.random.default_rng(1).standard_normal(
        t.size)
    an = analyse(t, x, omega0=np.sqrt(15.0 / 0.2))
    notes = held_offset_warning(an, held, False)
    assert bool(notes) == noted, notes
    assert not held_offset_warning(an, held, True)
    if noted:
        assert re.match(r"the data swing about 0\.0(59|6)", notes[0]), notes
        assert "offset=True" in notes[0]


@pytest.mark.parametrize("case, wanders", [("random walk", True), ("AR(1) 0.95", False),
                                           ("AR(1) 0.95 at 6/period", False)])
def test_residuals_that_wander_as_large_as_the_motion_are_inadequate(case, wanders):
    """A random walk fitted with a known oscillator (2,000 steps of 1 mm) was success and
    adequate: AR(1) noise of phi -> 1 took it. Its residuals, correlated over more than a
    period and larger than half the fitted motion, now make the fit inadequate, named. AR(1)
    noise of the generated families (phi up to 0.95, 10 % of the amplitude, 20 or 6 samples
    per period: correlated over 1 or 3.3 periods) is not flagged."""
    from types import SimpleNamespace

    import numpy as np

    from dampax._fit._assess import Inputs, wander
    from dampax._fit._measures import Measures

    rng = np.random.default_rng(5)
    n, w0 = 2000, 8.66
    e = rng.standard_normal(n)
    if case == "random walk":
        r, per = np.cumsum(0.001 * e), 84.0  # 0.01 s steps, period 0.7255 s
    else:
        r = np.zeros(n)
        for i in range(1, n):
            r[i] = 0.95 * r[i - 1] + math.sqrt(1 - 0.95**2) * e[i]
        r, per = 0.002 * r, (20.0 if case == "AR(1) 0.95" else 6.0)
    t = np.arange(n) * (2 * np.pi / w0) / per
    params = dict(mu=0.01, b=0.0, D=0.01, w0=w0, x0=0.0, v0=0.02 * w0, offset=0.0)  # A 0.02
    a = Inputs(t=t, x=r, curve=np.zeros(n), params=params, stderr={}, varied=("mu", "D"),
               derived={"A": 0.02}, an=SimpleNamespace(noise=0.001), converged=True,
               message="", model="reference")
    rms = float(np.sqrt(np.mean(r**2)))
    m = Measures(r=r, rms=rms, period=2 * np.pi / w0, cov=None, sd={}, st={})
    found = wander(a, m, None).bad
    assert bool(found) == wanders, (found, rms)
    if wanders:
        assert found[0].startswith("the residuals wander: correlated over"), found


@pytest.mark.parametrize("units, b, D, k, k3", [
    ("m", "kg/s", "kg/m", "N/m", "N/m^3"),
    ("mm", "kg/s", "kg/mm", "kg/s^2", "kg/(s^2 mm^2)"),
    ("deg", "kg/s", "kg/deg", "kg/s^2", "kg/(s^2 deg^2)"),
])
def test_units_with_a_mass_are_those_of_the_values(units, b, D, k, k3):
    """With a given mass the fit's b, D, k = m w0^2 and k3 are the constants of m x'' = -k x
    - k3 x^3 - b x' - D x'|x'| with x in ``units``: kg/s, kg/unit, kg/s^2 and kg/(s^2 unit^2)
    (b and D were labelled b/m and D/m "per unit mass" for degrees, k "N/mm" for mm)."""
    from dampax._fit._params import unit_of

    assert [unit_of(n, units) for n in ("b", "D", "k", "k3")] == [b, D, k, k3]
    assert unit_of("D", units, per_mass=True) == f"1/{units} (D/m, per unit mass)"
