"""The fit figure (``dampax._plot_fit.plot_fit``, issue 36 item 5): axes with units (t in s,
in the fit's unit, per-mass fits too), and the sticking band that the motion has: the static one
|k y + k3 y^3| <= mu_s m g where mu_s is set (held or fitted), the kinetic one (mu) otherwise,
named in the legend. The band's numbers are checked against hand-computed ones (a root of the
cubic by scipy's brentq), read back from the drawn artists."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import brentq

import dampax as dp
from dampax._fit._result import FitResult
from dampax._plot_fit import fit_figure, plot_fit, plot_joint_fit

M, K, G = 1.0, 30.0, 9.81
W0 = math.sqrt(K / M)


def _result(*, free=("mu", "D"), params=None, fixed=None, units="m", per_mass=False,
            kind="trace"):
    """A FitResult as ``dp.fit`` returns it, built by hand (the figure reads only these)."""
    t = np.linspace(0.0, 3.0, 600)
    x = 0.01 + 0.15 * np.exp(-0.5 * t) * np.cos(W0 * t)
    p = {"mu": 0.04, "b": 0.0, "D": 0.5, "w0": W0, "offset": 0.01, "x0": 0.15, "v0": 0.0,
         **(params or {})}
    n = len(p)
    return FitResult(
        params=p, stderr={k: 0.0 for k in p}, varied=list(free), covariance=np.eye(n),
        correlation=np.eye(n), residuals=np.full(t.size, 1e-3), t=t, x=x, model_x=x,
        success=True, message="", n_iterations=1, chisqr=1.0, redchi=1.0, aic=0.0, bic=0.0,
        ndata=t.size, nvarys=n, free=tuple(free), model="reference", loss="linear",
        optimizer="lm", kind=kind, fixed={"m": M, "g": G, **(fixed or {})},
        derived={"k": M * p["w0"] ** 2, "xc": p["mu"] * G / p["w0"] ** 2},
        units=units, per_mass=per_mass)


def _bands(fig):
    """(label, y bottom, y top) of each filled band of the upper panel."""
    ax = fig.axes[0]
    # the band's y extent from its vertices: axhspan draws a Rectangle from matplotlib 3.9 on,
    # a Polygon before (its vertices already in data units, its patch transform the identity)
    spans = [p.get_patch_transform().transform(p.get_path().vertices)[:, 1] for p in ax.patches]
    return [(p.get_label(), float(y.min()), float(y.max()))
            for p, y in zip(ax.patches, spans, strict=True)]


def test_axes_carry_units(tmp_path):
    fig = fit_figure(_result(units="deg", per_mass=True))
    ax, axr = fig.axes[:2]
    assert ax.get_ylabel() == "position [deg]"
    assert axr.get_ylabel() == "data - fit [deg]" and axr.get_xlabel() == "t [s]"
    assert "deg" in ax.get_title()  # the rms with its unit
    env = fit_figure(_result(kind="envelope", free=("b",), units="mm"))
    assert env.axes[0].get_ylabel() == "amplitude [mm]"
    assert env.axes[1].get_ylabel() == "data - fit [mm]"
    out = plot_fit(_result(units="cm"), tmp_path / "fit.png")
    assert out == tmp_path / "fit.png" and out.read_bytes()[:4] == b"\x89PNG"


def test_the_title_gives_mu_g_where_positions_are_not_metres():
    """For positions in mm the title gives the deceleration mu g [mm/s^2] (the report's mu_g)
    and no "mu =": a coefficient read off a trace in mm is 1000x the one in m. In metres
    the title keeps mu."""
    res = _result(units="mm")
    res = type(res)(**{**res.__dict__, "derived": {**res.derived, "mu_g": 0.04 * G * 1e3}})
    title = fit_figure(res).axes[0].get_title()
    assert "mu g = 392.4 mm/s^2" in title and "mu =" not in title
    assert "mu = 0.04" in fit_figure(_result()).axes[0].get_title()


def test_static_band_where_mu_s_is_held():
    res = _result(fixed={"mu_s": 0.2})
    (label, lo, hi), = _bands(fit_figure(res))
    half = 0.2 * M * G / K  # 0.0654 m, five times the kinetic 0.04 g / w0^2
    assert lo == pytest.approx(0.01 - half, rel=1e-12) and hi == pytest.approx(0.01 + half)
    assert label.startswith("static sticking band") and "μs = 0.2" in label


def test_static_band_where_mu_s_is_fitted_with_k3():
    # a fitted mu_s (in params, free) and a hardening cubic spring: the band's edge solves
    # k y + k3 y^3 = mu_s m g
    res = _result(free=("mu", "D", "mu_s"), params={"mu_s": 0.3, "k3": 400.0, "offset": -0.02})
    (label, lo, hi), = _bands(fit_figure(res))
    half = brentq(lambda y: K * y + 400.0 * y ** 3 - 0.3 * M * G, 0.0, 1.0, xtol=1e-15)
    assert half < 0.3 * M * G / K  # the cubic term narrows it
    assert lo == pytest.approx(-0.02 - half, rel=1e-9) and hi == pytest.approx(-0.02 + half,
                                                                                rel=1e-9)
    assert "static" in label and "k3" in label


def test_kinetic_band_without_mu_s_and_none_without_friction():
    (label, lo, hi), = _bands(fit_figure(_result()))
    half = 0.04 * G / W0 ** 2
    assert (lo, hi) == (pytest.approx(0.01 - half), pytest.approx(0.01 + half))
    assert "kinetic" in label and "static" not in label
    assert _bands(fit_figure(_result(free=("b", "D"), params={"mu": 0.0}))) == []


def test_joint_figure_has_units(tmp_path):
    class Joint:  # the fields plot_joint_fit reads of a JointResult
        runs = [_result(units="deg"), _result(units="deg")]
        units, model, shared, values = "deg", "reference", ("D",), {"D": 0.5}

    out = plot_joint_fit(Joint(), tmp_path / "joint.png")
    assert out.read_bytes()[:4] == b"\x89PNG"


def test_figure_of_a_fit_with_held_mu_s():
    """A real fit with static friction held (the trace of tests/reference/test_static_friction:
    scipy's exact stick-slip, mu_s = 0.2, the block halts at 2.30 s): the band drawn is the
    static one around the fitted offset, mu_s m g / k wide, not the kinetic mu m g / k."""
    from helpers import evaluate, scipy_stick_slip

    t = np.arange(0.0, 3.0, 1.0 / 500.0)
    segments, _, rest = scipy_stick_slip(M, K, 0.04, 0.0, 0.5, 0.2, 0.0, 3.0, rtol=1e-11,
                                         atol=1e-13, mu_s=0.2)
    x = evaluate(segments, rest, t)[0] + 1e-3 * np.random.default_rng(0).standard_normal(t.size)
    res = dp.fit(t, x, oscillator=dp.Oscillator(m=M, k=K), free=("mu", "D"),
                 model="reference", mu_s=0.2)
    (label, lo, hi), = _bands(fit_figure(res))
    off = res.params["offset"]
    half = 0.2 * M * G / K
    assert lo == pytest.approx(off - half, rel=1e-9, abs=1e-12)
    assert hi == pytest.approx(off + half, rel=1e-9)
    assert label.startswith("static sticking band")
    assert abs(res.params["mu"] * M * G / K - half) > 0.04  # the kinetic band differs
