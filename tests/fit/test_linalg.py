"""The tall least squares of the fit's core (``_fit._linalg``) against numpy's LAPACK."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from dampax._fit._linalg import householder_r, tall_lstsq, tall_r, tall_svd


def _matrix(n, scales, seed=0, zero=()):
    A = np.random.default_rng(seed).standard_normal((n, len(scales))) * np.asarray(scales)
    for j in zero:  # a fixed parameter's column
        A[:, j] = 0.0
    return A


@pytest.mark.parametrize("n", [5, 100, 4103])
def test_singular_values_and_r_match_lapack(n):
    A = _matrix(n, [1.0, 1e-4, 1e3, 1.0, 1.0, 1e-6, 1.0])
    s, vt = jax.jit(tall_svd)(A)
    s_np, vt_np = np.linalg.svd(A, full_matrices=False)[1:]
    k = min(n, 7)
    assert np.allclose(np.asarray(s)[:k], s_np[:k], rtol=1e-10)
    if n >= 7:  # R^T R = A^T A, and the right vectors agree up to sign
        R = np.asarray(tall_r(A))
        assert np.allclose(R.T @ R, A.T @ A, rtol=1e-10, atol=1e-10 * np.abs(A.T @ A).max())
        assert np.allclose(np.abs(np.asarray(vt)), np.abs(vt_np), atol=1e-8)


@pytest.mark.parametrize("zero", [(), (1, 4)])
def test_lstsq_matches_numpy_with_zero_columns(zero):
    A = _matrix(4103, [1.0, 1e-3, 1e2, 1.0, 1.0, 1e-5, 1.0], seed=1, zero=zero)
    b = np.random.default_rng(2).standard_normal(4103)
    x = np.asarray(jax.jit(tall_lstsq)(A, b))
    x_np = np.linalg.lstsq(A, b, rcond=None)[0]
    assert np.allclose(x, x_np, rtol=1e-9, atol=1e-12 * np.abs(x_np).max())
    assert np.all(np.abs(x[list(zero)]) <= 1e-9 * np.abs(x).max())  # (numpy: 0)


def test_lstsq_under_vmap_and_grad():
    A = _matrix(300, [1.0, 2.0, 0.5])
    bs = np.random.default_rng(3).standard_normal((4, 300))
    xs = jax.vmap(lambda b: tall_lstsq(A, b))(bs)
    assert np.allclose(xs, np.linalg.lstsq(A, bs.T, rcond=None)[0].T, rtol=1e-10)
    g = jax.grad(lambda b: tall_lstsq(A, b)[0])(bs[0])  # linear in b: the pseudo-inverse's row
    assert np.allclose(g, np.linalg.pinv(A)[0], rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("shape", [(3, 64, 7), (2, 5, 7), (300, 4)])
def test_householder_r_matches_lapack_up_to_row_signs(shape):
    """The jnp Householder R of a stack (a stack of blocks, fewer rows than columns, a zero
    column) against numpy's LAPACK R: equal up to the sign of each row."""
    A = np.random.default_rng(4).standard_normal(shape) * np.geomspace(1e-5, 1e3, shape[-1])
    A[..., 1] = 0.0
    R = np.asarray(jax.jit(householder_r)(A))
    R_np = np.linalg.qr(A, mode="r")
    assert R.shape == R_np.shape and np.all(np.tril(R, -1) == 0.0)
    sign = np.where(np.sign(np.diagonal(R, axis1=-2, axis2=-1)) == np.sign(
        np.diagonal(R_np, axis1=-2, axis2=-1)), 1.0, -1.0)
    np.testing.assert_allclose(R * sign[..., :, None], R_np, rtol=1e-10,
                               atol=1e-12 * np.abs(R_np).max())


def test_the_tall_factorizations_make_no_lapack_qr():
    """The fit's QRs are jnp (no ``lapack_dgeqrf``): jaxlib splits a batch of LAPACK QRs
    across XLA's intra-op threads and waits on one of them, which hung two fits run at once
    on 2 cores (the next test)."""
    A = np.zeros((8, 4096, 8))
    for fn in (jax.vmap(tall_r), jax.vmap(tall_svd),
               jax.vmap(lambda a: tall_lstsq(a[:, :7], a[:, 7]))):
        text = jax.jit(fn).lower(A).as_text()
        assert "lapack_dgeqrf" not in text and "lapack_dorgqr" not in text


_THREADS = """
import os, threading
import jax, numpy as np
import dampax  # noqa: F401 (float64)
from dampax._fit._linalg import tall_r
f = jax.jit(jax.vmap(tall_r))
A = np.random.default_rng(0).standard_normal((8, 4096, 8))
f(A).block_until_ready()
def work():
    for _ in range(20):
        f(A).block_until_ready()
threads = [threading.Thread(target=work) for _ in range(max(2, min(os.cpu_count() or 2, 16)))]
for t in threads:
    t.start()
for t in threads:
    t.join()
print("done")
"""


def test_tall_factorizations_in_threads_at_once_finish():
    """A batched TSQR run by as many Python threads at once as there are cores finishes (in a
    child process, with a time limit). With LAPACK's batched QR each thread's program held one
    of XLA's intra-op threads waiting for chunks queued behind the others': on a 2-core machine
    two fits in two threads (``dp.fit``, ``compare_models``) hung for ever, every time."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", _THREADS], capture_output=True, text=True,
                          timeout=180)
    assert proc.returncode == 0 and proc.stdout.strip() == "done", proc.stderr[-2000:]


def test_gram_inverse_of_a_nearly_collinear_jacobian():
    """(J^T J)^-1 of the intervals (the HAC sandwich, the joint fit) against the exact
    V diag(1/s^2) V^T of a J built from its SVD with cond(J) = 1e9: forming J^T J (cond 1e18)
    lost the small direction (its pseudo-inverse dropped it: variances 1e-8 of the truth);
    a zero column (a fixed constant) gets none, a NaN Jacobian gives NaN (issue 34)."""
    from dampax._fit._intervals import gram_inverse

    rng = np.random.default_rng(5)
    n, p = 3000, 4
    Q = np.linalg.qr(rng.standard_normal((n, p)))[0]
    V = np.linalg.qr(rng.standard_normal((p, p)))[0]
    s = np.array([1.0, 0.3, 1e-4, 1e-9])
    J = Q @ np.diag(s) @ V.T * np.array([1.0, 1e3, 1e-3, 1.0])  # column scales too
    D = np.diag([1.0, 1e3, 1e-3, 1.0])
    Vs = np.linalg.solve(D, V)  # J = Q S V^T D, so (J^T J)^-1 = (D^-1 V) S^-2 (D^-1 V)^T
    exact = Vs @ np.diag(1.0 / s**2) @ Vs.T
    G = gram_inverse(J)
    assert np.allclose(np.diag(G), np.diag(exact), rtol=1e-5)
    assert np.abs(G - exact).max() < 1e-5 * np.abs(exact).max()
    Jz = np.concatenate([J, np.zeros((n, 1))], axis=1)
    Gz = gram_inverse(Jz)
    assert np.all(Gz[-1] == 0.0) and np.allclose(np.diag(Gz[:p, :p]), np.diag(exact), rtol=1e-5)
    J[3, 1] = np.nan
    assert np.all(np.isnan(gram_inverse(J)))


def test_the_sandwich_of_a_nearly_collinear_jacobian_is_its_exact_value():
    """The HAC covariance of a J built from its SVD with cond(J) = 1e9 (two damping constants
    at 0 gave 1.3e-8 on an undamped trace) against the exact T diag(1/s^2) S_T diag(1/s^2)
    T^T, S_T formed from the orthogonal Q diag(s) (the prewhitened sandwich, L = 0; the
    kernel's floor is still taken in the parameters): variances within 1e-6, the same with J
    moved by 4e-16 (a GPU's rounding). As H^-1 S H^-1 in the parameters the product cancels
    terms 1e18 times its result: variances wrong by orders of magnitude, or <= 0 (the undamped
    fit failed with "no width" on an H200, twenty-fourth session)."""
    from dampax._fit._intervals import hac_covariance, score_matrix

    rng = np.random.default_rng(6)
    n, p = 3000, 4
    Q = np.linalg.qr(rng.standard_normal((n, p)))[0]
    V = np.linalg.qr(rng.standard_normal((p, p)))[0]
    s = np.array([1.0, 0.3, 1e-4, 1e-9])
    D = np.array([1.0, 1e3, 1e-3, 1.0])
    J = Q @ np.diag(s) @ V.T * D
    r = 0.01 * rng.standard_normal(n)
    T = V / D[:, None]  # J T = Q diag(s)
    St, _ = score_matrix(Q * s, r, period_samples=50.0, lags=0)
    exact = T @ (St / np.outer(s**2, s**2)) @ T.T
    for moved in (J, J * (1.0 + 4e-16 * rng.standard_normal(J.shape))):
        cov, _ = hac_covariance(moved, r, period_samples=50.0, lags=0)
        np.testing.assert_allclose(np.diag(cov), np.diag(exact), rtol=1e-6)


def test_the_kernel_never_narrows_the_prewhitened_sandwich():
    """White noise on a least-squares fit of a sinusoid and an offset (1,000 samples, 4
    periods), with the Bartlett kernel forced to a quarter of the window (what a Ljung-Box
    rejection by chance of a white trace gives, 1 % of them): each parameter's 90 % interval
    covers the exact truth 86-95 % of 400 draws (binomial sd 1.5 %; 91-92.5 % here) and is
    never narrower than the kernel-free sandwich. The kernel alone over such a window (its
    scores sum to zero; without the AR(1) filter, whose coefficient is about 0 here), as the
    intervals had it before, covered 78-82 %."""
    from dampax._fit._intervals import bartlett_matrix, gram_inverse, hac_covariance

    rng = np.random.default_rng(11)
    n, L = 1000, 250
    t = np.arange(n) / 250.0
    J = np.stack([np.ones(n), np.cos(2 * np.pi * t), np.sin(2 * np.pi * t)], axis=1)
    truth = np.array([0.3, 1.0, -0.5])
    Hinv = gram_inverse(J)
    hits, hits_old = np.zeros(3), np.zeros(3)
    for _ in range(400):
        y = J @ truth + rng.standard_normal(n)
        est = np.linalg.lstsq(J, y, rcond=None)[0]
        r = y - J @ est
        cov, lags = hac_covariance(J, r, period_samples=250.0, lags=L)
        cov0, _ = hac_covariance(J, r, period_samples=250.0, lags=0)
        assert lags == L and np.all(np.diag(cov) >= np.diag(cov0) * (1 - 1e-12))
        hits += np.abs(est - truth) < 1.6449 * np.sqrt(np.diag(cov))
        S = bartlett_matrix(J * r[:, None], L)[0]  # the kernel alone, without the floor
        hits_old += np.abs(est - truth) < 1.6449 * np.sqrt(np.diag(Hinv @ S @ Hinv))
    assert np.all((0.86 < hits / 400) & (hits / 400 < 0.95)), hits
    assert np.all(hits_old / 400 < 0.85), hits_old


@pytest.mark.parametrize("lags", [0, 1, 7, 299])
def test_the_bartlett_sum_in_frequencies_is_the_sum_over_lags(lags):
    """:func:`bartlett_matrix` (one product in the frequency domain) against the sum over
    lags written out, w_0 g^T g + sum_(l=1..L) w_l (G_l + G_l^T), G_l = g[:-l]^T g[l:]."""
    from dampax._fit._intervals import bartlett_matrix

    g = np.random.default_rng(5).standard_normal((300, 4)) * [1.0, 1e-3, 5.0, 1e2]
    S, g0 = bartlett_matrix(g, lags)
    want = g.T @ g
    for lag in range(1, lags + 1):
        G = g[:-lag].T @ g[lag:]
        want = want + (1.0 - lag / (lags + 1.0)) * (G + G.T)
    np.testing.assert_allclose(g0, g.T @ g, rtol=1e-14)
    scale = np.sqrt(np.outer(np.diag(g.T @ g), np.diag(g.T @ g)))
    assert np.max(np.abs(S - want) / scale) < 1e-13
    np.testing.assert_array_equal(S, S.T)


def test_a_zero_width_interval_fails_the_fit():
    """A varied parameter whose interval variance comes out 0 (here a Jacobian column the
    residuals do not feel: its variance is unbounded, not 0) fails the assessment by name,
    although its delta-method standard error is finite; the same fit with that column alive
    passes this check (fit_calibration.py seed 2, draw 10: a quarter-swing window reported
    zero-width intervals with success)."""
    from dampax._fit._assess import Inputs, standard_errors

    rng = np.random.default_rng(2)
    t = np.linspace(0.0, 4.0, 800)
    w0 = 2.0 * np.pi
    J = np.stack([np.cos(w0 * t), np.sin(w0 * t), np.ones_like(t)], axis=1)
    rows = 0.01 * rng.standard_normal(t.size)
    names = ("x0", "v0", "offset")
    kw = dict(t=t, x=rows, curve=np.zeros_like(t), params={"w0": w0, "x0": 1.0, "v0": 0.0,
                                                            "offset": 0.0},
              stderr={n: 1e-3 for n in names}, varied=names, derived={}, an=None,
              converged=True, message="", rows=rows)
    assert standard_errors(Inputs(jac=J, **kw), None).fails == ()
    dead = J.copy()
    dead[:, 1] = 0.0
    (reason,) = standard_errors(Inputs(jac=dead, **kw), None).fails
    assert reason.startswith("the interval of v0 has no width"), reason


class _Stop(Exception):
    pass


def test_a_fit_holds_blas_to_one_thread_and_restores_it(monkeypatch):
    """dp.fit's host-side linear algebra runs with one BLAS thread (OpenBLAS's idle worker
    would spin on the core XLA needs: ``_linalg.one_blas_thread``); the caller's setting is
    back afterwards, also when the fit raises."""
    from threadpoolctl import threadpool_info, threadpool_limits

    import dampax as dp
    from dampax._fit import _api

    def threads():
        return {d["filepath"]: d["num_threads"] for d in threadpool_info()
                if d["user_api"] == "blas"}

    seen = []

    def run(problem, plan):
        seen.append(threads())
        raise _Stop

    monkeypatch.setattr(_api, "run", run)
    t = np.linspace(0.0, 10.0, 600)
    x = 0.05 * np.exp(-0.1 * t) * np.cos(6.0 * t)
    with threadpool_limits(limits=2, user_api="blas"):
        before = threads()
        with pytest.raises(_Stop):
            dp.fit(t, x, oscillator=dp.Oscillator(m=1.0, k=36.0), model="ansatz")
        assert threads() == before
    assert seen and set(seen[0]) == set(before) and set(seen[0].values()) == {1}
