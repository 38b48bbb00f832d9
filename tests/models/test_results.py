"""Solutions carry a RESULTS reason under jit and vmap; throw=True raises it; one model registry.

Each failure case is checked against the condition that makes the model undefined (from the
papers: no admissible root of eq. 22 when d2 |x0| >= w0; Rizcallah's model is for Coulomb
damping only; the half-swings need D = 0 and underdamping), not against stored output.
"""

import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dampax as dp
from dampax._cli import main
from dampax._models._solution import message

W0 = math.sqrt(30.0)


def _jit_result(model, **fields):
    """The result of a registry model solved under jit, from (x0, v0) = (0.2, 0)."""
    opts = dp.MODELS[model].solve_options

    @jax.jit
    def run(mu, b, D):
        sol = dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=mu, b=b, D=D), 0.2, 0.0, **opts)
        return sol.result, sol.x(0.5)

    values = dict(mu=0.0, b=0.0, D=0.0) | fields
    return run(*(jnp.asarray(v) for v in values.values()))


@pytest.mark.parametrize("model, fields, reason", [
    # d2 |x0| >= w0: D >= 3 pi m / (4 |x0|) has no admissible amplitude (eq. 22)
    ("matched", dict(D=1.01 * 3 * math.pi / (4 * 0.2)), dp.RESULTS.no_amplitude),
    ("rizcallah", dict(mu=0.05, D=0.5), dp.RESULTS.coulomb_only),
    ("rizcallah", dict(mu=0.05, b=0.1), dp.RESULTS.coulomb_only),
    ("coulomb_exact", dict(mu=0.05, D=0.5), dp.RESULTS.no_drag),
    ("coulomb_exact", dict(mu=0.05, b=2.0 * math.sqrt(30.0) * 1.01), dp.RESULTS.overdamped),
])
def test_reason_under_jit(model, fields, reason):
    result, x = _jit_result(model, **fields)
    assert bool(result == reason), message(result)
    assert np.isnan(float(x))  # values are NaN where the model does not exist
    ok, x_ok = _jit_result(model, mu=0.05)
    assert bool(ok == dp.RESULTS.successful) and np.isfinite(float(x_ok))


def test_reason_under_vmap_per_element():
    D = jnp.array([0.0, 0.5, 0.0])

    def result(D):
        sol = dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=0.05, D=D), 0.2, 0.0,
                       method="coulomb_exact")
        return sol.result

    res = jax.vmap(result)(D)
    np.testing.assert_array_equal(np.asarray(res == dp.RESULTS.successful),
                                  [True, False, True])
    assert message(res) == dp.RESULTS[dp.RESULTS.no_drag]


def test_reference_budget_is_a_reason():
    sol = jax.jit(lambda mu: dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=mu), 0.2, 0.0,
                                      method="reference", max_swings=2))(0.01)
    assert bool(sol.result == dp.RESULTS.max_swings_reached)
    assert not bool(sol.valid)
    with pytest.raises(ValueError, match=r"increase max_swings.*now max_swings = 2"):
        dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=0.01), 0.2, 0.0, method="reference",
                 max_swings=2)


def test_throw_raises_the_message_under_jit():
    D_bad = 1.01 * 3 * math.pi / (4 * 0.2)

    @jax.jit
    def x_at(D):
        return dp.solve(dp.Oscillator(m=1.0, k=30.0, D=D), 0.2, 0.0, throw=True).x(0.3)

    assert np.isfinite(float(x_at(1.0)))
    with pytest.raises(Exception, match="no admissible amplitude"):
        jax.block_until_ready(x_at(D_bad))


def test_eager_error_is_the_result_message():
    with pytest.raises(ValueError) as err:
        dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=0.05, D=0.5), 0.2, 0.0, method="rizcallah")
    assert str(err.value) == dp.RESULTS[dp.RESULTS.coulomb_only]


def test_repr_shows_values():
    osc = dp.Oscillator(m=1.5, k=2.0)
    assert repr(osc) == "Oscillator(m=1.5, k=2.0, mu=0.0, b=0.0, D=0.0, g=9.81)"
    sol = dp.solve(dp.Oscillator(m=1.0, k=30.0, mu=0.05), 0.2, 0.0)
    text = repr(sol)
    assert f"amplitude={float(sol.amplitude)!r}" in text and "result='successful'" in text


def test_eq21_round_trip():
    """Eq. 21 forward and inverse (both on Oscillator) against the printed formulas."""
    osc = dp.Oscillator(m=2.0, k=50.0, mu=0.03, b=0.4, D=1.5, g=9.8)
    w0 = 5.0
    d0, d1, d2 = osc.damping_coefficients
    assert float(d0) == pytest.approx(2 * 0.03 * 9.8 / (math.pi * w0), rel=1e-15)
    assert float(d1) == pytest.approx(0.4 / 4.0, rel=1e-15)
    assert float(d2) == pytest.approx(4 * 1.5 * w0 / (3 * math.pi * 2.0), rel=1e-15)
    back = dp.Oscillator.from_damping(d0, d1, d2, m=2.0, k=50.0, g=9.8)
    for name in ("mu", "b", "D"):
        assert float(getattr(back, name)) == pytest.approx(float(getattr(osc, name)), rel=1e-14)
    assert float(osc.energy(0.1, 0.2)) == pytest.approx(0.5 * 50 * 0.01 + 0.5 * 2 * 0.04)


def test_registry_models_solve_with_their_options():
    osc = dp.Oscillator(m=1.0, k=30.0, mu=0.05)
    for name, model in dp.MODELS.items():
        assert model.applies(osc), name
        sol = dp.solve(osc, 0.2, 0.0, **model.solve_options)
        assert bool(sol.valid), name
        # every model halts at the exact Coulomb rest point within a band of width xc
        assert abs(float(sol.halt_position)) <= float(osc.xc) + 1e-12 or name in (
            "matched", "undamped"), name


def test_one_spelling_in_every_command(tmp_path, capsys):
    """The model's one name (errormap, sensitivity) and label (solve) of the registry in every
    command. The commands run with the settings of other tests (``errormap --quick`` as
    tests/studies/test_maps.py, ``solve`` with the analytic models only): their compiled programs
    are shared."""
    label = dp.MODELS["matched_tail"].label
    assert main(["errormap", "--quick", "--out", str(tmp_path / "maps"), "--no-progress",
                 "--plots", "none"]) == 0
    assert re.search(r"^  matched_tail\s+[0-9]", capsys.readouterr().out, re.M)
    assert main(["solve", "--mu", "0.03", "--no-reference", "--turning", "0"]) == 0
    assert label in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["sensitivity", "--help"])
    assert "matched_tail" in capsys.readouterr().out
    assert main(["sensitivity", "--models", "tail"]) == 2  # the old spelling is gone
    assert "matched_tail" in capsys.readouterr().err


def test_traced_t_end_under_jit_and_vmap():
    """The reference's t_end may be traced (issue 15, item 4): same x(t) as an eager solve."""
    osc = dp.Oscillator(m=1.0, k=30.0, mu=0.0288, D=2.95)
    eager = float(dp.solve(osc, 0.2, 0.0, method="reference", t_end=5.0).x(1.0))

    def x_at_one(t_end):
        return dp.solve(osc, 0.2, 0.0, method="reference", t_end=t_end).x(1.0)

    assert float(jax.jit(x_at_one)(5.0)) == pytest.approx(eager, abs=1e-12)
    # t_end = 0.5 stops before t = 1 while the block still moves: NaN there, by design
    both = np.asarray(jax.vmap(x_at_one)(jnp.array([0.5, 5.0])))
    assert np.isnan(both[0]) and both[1] == pytest.approx(eager, abs=1e-12)
