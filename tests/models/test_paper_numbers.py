"""Every row of docs/DESIGN.md section 4 (the quoted numbers), m = 1 kg, k = 30 N/m, A0 = 0.2 m.

The paper quotes two or three significant figures; each check is to the last printed digit.
"""

import math

import numpy as np
import pytest
from helpers import A0, W0, ratios_to_constants

import dampax as dp


def paper_osc(d0_ratio=0.0, d2_ratio=0.0):
    mu, b, D = ratios_to_constants(d0_ratio, 0.0, d2_ratio)
    return dp.Oscillator(m=1.0, k=30.0, mu=mu, b=b, D=D)


@pytest.mark.parametrize("ratio, D_paper", [(0.1, 1.18), (0.25, 2.95), (0.5, 5.89), (0.75, 8.84)])
def test_quadratic_drag_constants(ratio, D_paper):
    # III.A: d2 A0/w0 -> D in kg/m, via eq. 21 inverted by dampax
    osc = dp.from_ratios(d2_ratio=ratio)
    assert float(osc.D) == pytest.approx(D_paper, abs=0.005)
    d0, d1, d2 = dp.damping_coefficients(dp.Oscillator(m=1.0, k=30.0, D=D_paper))
    assert float(d2) * A0 / W0 == pytest.approx(ratio, abs=0.001)


@pytest.mark.parametrize("ratio, A_paper, phi_paper, A_digits", [(0.05, 0.2002, -0.05, 4),
                                                                 (0.1, 0.201, -0.1, 3)])
def test_coulomb_from_rest(ratio, A_paper, phi_paper, A_digits):
    # IV.A, eq. 40
    sol = dp.solve(paper_osc(ratio), 0.2, 0.0)
    assert round(float(sol.amplitude), A_digits) == pytest.approx(A_paper)
    assert float(sol.phase) == pytest.approx(phi_paper, abs=0.005)
    # eq. 40 in closed form, written out independently
    d0 = ratio * W0 * A0
    A40 = math.sqrt((0.2**2 + math.sqrt(0.2**4 + 4 * (d0 * 0.2 / W0) ** 2)) / 2)
    assert float(sol.amplitude) == pytest.approx(A40, rel=1e-12)
    assert float(sol.phase) == pytest.approx(math.atan(-d0 / (W0 * A40)), rel=1e-12)


def test_coulomb_last_turning_point_outside_band():
    # IV.A, Fig. 8(b): last turning point with |x| > xc at (1.12 s, 0.076 m)
    osc = paper_osc(0.1)
    sol = dp.solve(osc, 0.2, 0.0)
    t, x = (np.asarray(a) for a in dp.turning_points(sol, 8))
    outside = np.abs(x) > float(osc.xc)
    last = np.flatnonzero(outside)[-1]
    assert round(t[last], 2) == 1.12
    assert round(x[last], 3) == 0.076
    tail = dp.solve(osc, 0.2, 0.0, tail="coulomb")
    assert float(tail.t_switch) == pytest.approx(t[last], rel=1e-10)


def test_coulomb_general_start_quartic():
    # IV.C: 30 A^4 - 1.2 A^2 - 0.012 A - 6e-5 = 0 -> A = 0.205, phi = -0.809
    x0 = A0 * math.sqrt(2) / 2
    sol = dp.solve(paper_osc(0.05), x0, W0 * x0)
    A = float(sol.amplitude)
    assert round(A, 3) == 0.205
    assert round(float(sol.phase), 3) == -0.809
    assert 30 * A**4 - 1.2 * A**2 - 0.012 * A - 6e-5 == pytest.approx(0.0, abs=1e-12)
    roots = np.roots([30.0, 0.0, -1.2, -0.012, -6e-5])
    assert np.sort(np.round(roots.real[abs(roots.imag) < 1e-12], 3)).tolist() == [-0.195, 0.205]


def test_combined_general_start():
    # V.C: A = 0.234 m, phi = -0.922;
    # turning points 4 and 5 at (1.84 s, -0.146 x0), (2.37, 0.049 x0)
    x0 = A0 * math.sqrt(2) / 2
    sol = dp.solve(paper_osc(0.03, 0.25), x0, W0 * x0)
    assert round(float(sol.amplitude), 3) == 0.234
    assert round(float(sol.phase), 3) == -0.922
    t, x = (np.asarray(a) for a in dp.turning_points(sol, 6))
    # the paper's "x0" in these pairs is the 0.2 m of the other figures (A0); its values are
    # read off a graph: we get (1.846 s, -0.1453 x0) and (2.370 s, 0.0485 x0)
    assert abs(t[3] - 1.84) < 0.01 and abs(x[3] / A0 - (-0.146)) < 0.001
    assert abs(t[4] - 2.37) < 0.005 and abs(x[4] / A0 - 0.049) < 0.001
    # the fifth is the last one outside the band (V.C: "the fifth turning point")
    xc = float(paper_osc(0.03, 0.25).xc)
    assert abs(x[4]) > xc and (np.isnan(x[5]) or abs(x[5]) <= xc)


def test_combined_from_rest_fig14d():
    # V.A / docs/DESIGN.md note: Fig. 14(d) (x0 = 0.2, v0 = 0) gives (2.26 s, 0.055 x0) as the last
    # turning point outside the band; the third is the paper's (1.74 s, -0.155 x0)
    osc = paper_osc(0.03, 0.25)
    sol = dp.solve(osc, 0.2, 0.0)
    t, x = (np.asarray(a) for a in dp.turning_points(sol, 6))
    assert round(t[3], 2) == 2.26 and round(x[3] / 0.2, 3) == 0.055
    assert abs(t[2] - 1.74) < 0.011 and abs(x[2] / 0.2 - (-0.155)) < 0.0015
    # xc = 0.047 x0 (the paper's "it can be at most 0.047 x0")
    assert round(float(osc.xc) / 0.2, 3) == 0.047
    # eq. 54 tail from the third turning point
    t54 = dp.solve(osc, 0.2, 0.0, tail="coulomb", back=1)
    assert float(t54.t_switch) == pytest.approx(t[2], rel=1e-10)


def test_coulomb_exact_turning_points():
    # Coulomb 0.1 exact, from rest at 0.2 m: -0.13717, 0.07434, -0.01150 at n pi/w0
    sol = dp.solve(paper_osc(0.1), 0.2, 0.0, method="coulomb_exact")
    t, x = (np.asarray(a) for a in dp.turning_points(sol, 4))
    np.testing.assert_allclose(x[:3], [-0.13717, 0.07434, -0.01150], atol=5e-6)
    np.testing.assert_allclose(t[:3], np.arange(1, 4) * math.pi / W0, rtol=1e-12)
    assert np.isnan(t[3]) and np.isnan(x[3])
    assert float(sol.halt_position) == pytest.approx(-0.01150, abs=5e-6)
    assert float(sol.halt_time) == pytest.approx(3 * math.pi / W0, rel=1e-12)
