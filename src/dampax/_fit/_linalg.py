"""Least squares on tall matrices (n samples x p parameters, n >> p) that XLA runs fast.

XLA's CPU QR and SVD of a 4,103 x 7 Jacobian took 16 and 44 ms, 30-60 times a whole
Jacobian of the exact model (1.3 ms): every fit paid it once per solve (the covariance) and the
approximate model once per Levenberg-Marquardt round (its Gauss-Newton step), most of a
warm fit's time (issue 36). The triangular factor R of the QR (:func:`tall_r`), by p Householder
reflections written in jnp, takes 0.28 ms for 6,144 x 8 unrolled, 0.3-0.4 ms in a loop of p
turns (four times fewer instructions in every fit's program, which loads in time proportional
to its size); the SVD of the p x p factor then gives the singular values and right vectors of
the whole matrix.

Not LAPACK's ``geqrf`` (nor the tall-skinny QR's batch of them over blocks of rows, which
this module used before): jaxlib splits a batch of LAPACK factorizations across XLA's
intra-op threads and waits for the pieces on one of those threads, so two programs doing it at
once on a 2-core machine (two fits in two Python threads) each held a thread waiting for work
queued behind the other, and both hung for ever. A single unbatched ``geqrf`` is never split,
but takes 0.64 ms for the same matrix.
"""

from __future__ import annotations

import functools
import sys

import jax
import jax.numpy as jnp
from threadpoolctl import ThreadpoolController


def householder_r(A):
    """The triangular factor R of A = QR for a stack of (..., m, p) matrices, by min(m, p)
    Householder reflections in jnp (Golub & Van Loan, "Matrix Computations", algorithm 5.2.1):
    the same R as LAPACK's ``geqrf`` up to the signs of its rows, with no custom call.

    Arguments:
        A: an (..., m, p) array.

    Returns:
        R (..., min(m, p), p), upper triangular.
    """
    At = jnp.swapaxes(A, -1, -2)  # (..., p, m): the reflections' sums run along memory
    p, m = At.shape[-2:]
    col = jnp.arange(m)

    def reflect(k, At):
        # one reflection per turn of a loop, not unrolled: the same arithmetic in a program
        # p times smaller (a kept program loads in time proportional to its size)
        row = jax.lax.dynamic_index_in_dim(At, k, axis=-2, keepdims=False)
        x = jnp.where(col >= k, row, 0.0)
        ss = jnp.sum(x * x, axis=-1)
        norm = jnp.where(ss > 0.0, jnp.sqrt(jnp.where(ss > 0.0, ss, 1.0)), 0.0)
        akk = jnp.sum(jnp.where(col == k, row, 0.0), axis=-1)
        alpha = jnp.where(akk >= 0.0, -norm, norm)  # no cancellation in v_k
        v = x - jnp.where(col == k, alpha[..., None], 0.0)
        vv = jnp.sum(v * v, axis=-1)
        scale = jnp.where(vv > 0.0, 2.0 / jnp.where(vv > 0.0, vv, 1.0), 0.0)  # zero column
        w = jnp.einsum("...pm,...m->...p", At, v) * scale[..., None]
        return At - w[..., :, None] * v[..., None, :]

    At = jax.lax.fori_loop(0, min(m, p), reflect, At)
    return jnp.triu(jnp.swapaxes(At, -1, -2)[..., :min(m, p), :])


def tall_r(A):
    """The p x p triangular factor R of A = QR (n x p, any n >= 1).

    Arguments:
        A: an (n, p) array.

    Returns:
        R (p, p) (min(n, p) rows padded with zero rows where n < p).
    """
    n, p = A.shape
    R = householder_r(A)
    if R.shape[0] < p:
        R = jnp.concatenate([R, jnp.zeros((p - R.shape[0], p), R.dtype)])
    return R


def tall_svd(A):
    """(s, vt): the singular values and right singular vectors of A (n x p), from the SVD
    of :func:`tall_r`'s R (the left vectors are not formed)."""
    _, s, vt = jnp.linalg.svd(tall_r(A), full_matrices=False)
    return s, vt


def tall_lstsq(A, b):
    """The minimum-norm least-squares solution x of A x = b (n x p, n >> p), as
    ``jnp.linalg.lstsq(A, b)[0]`` (singular values below eps max(n, p) s_max dropped), by the
    QR of the augmented matrix [A | b]: its R holds R_A and the first p entries of Q^T b.

    Arguments:
        A: (n, p); b: (n,).

    Returns:
        x (p,).
    """
    n, p = A.shape
    R = tall_r(jnp.concatenate([A, b[:, None]], axis=1))
    c = R[:p, p]
    u, s, vt = jnp.linalg.svd(R[:p, :p], full_matrices=False)
    cut = jnp.finfo(A.dtype).eps * max(n, p) * s[0]
    inv = jnp.where(s > cut, 1.0 / jnp.where(s > 0, s, 1.0), 0.0)
    return vt.T @ (inv * (u.T @ c))


def one_blas_thread(fn):
    """``fn`` with the BLAS libraries of the process (numpy's and scipy's OpenBLAS) held to one
    thread while it runs, restored after (``threadpoolctl``).

    A fit's host-side linear algebra is on n x 7 matrices: a second BLAS thread gains nothing
    there, and after each call OpenBLAS's idle worker spins on a core for a while. On a
    2-core machine that spinning took the core XLA's programs run and load on: 21-25 % of
    the CPU samples of a repeated ``dampax fit --example`` (3.19 -> 2.78 s with one BLAS
    thread, the console script's setting) and a warm default fit 0.40-0.47 -> 0.27-0.36 s
    (benchmarks/README.md, issue 36, twentieth session). Calls from other threads during
    ``fn`` also see one BLAS thread.
    """
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with _blas("scipy.linalg" in sys.modules).limit(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper


@functools.lru_cache(maxsize=2)
def _blas(scipy_loaded: bool) -> ThreadpoolController:
    """The process's thread pools, found once, and again once scipy's OpenBLAS is loaded
    (``threadpool_limits`` looks through every loaded library at each call: 4 % of a
    ranking's seven fits)."""
    del scipy_loaded  # (the cache's key)
    return ThreadpoolController()
