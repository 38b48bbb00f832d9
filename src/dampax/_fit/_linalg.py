"""Least squares on tall matrices (n samples x p parameters, n >> p) that XLA runs fast.

XLA's CPU QR and SVD of a 4,103 x 7 Jacobian took 16 and 44 ms, 30-60 times a whole
Jacobian of the exact model (1.3 ms): every fit paid it once per solve (the covariance) and the
approximate model once per Levenberg-Marquardt round (its Gauss-Newton step), most of a
warm fit's time (issue 36). The tall-skinny QR (TSQR) factors blocks of rows independently
(one vmapped QR of :data:`BLOCK` x p blocks) and then the stack of their R factors: the same
R as one Householder QR up to signs, as stable (Demmel et al., "Communication-optimal parallel
and sequential QR and LU factorizations", SIAM J. Sci. Comput. 34, 2012), in 0.2 ms. The SVD
of the p x p factor then gives the singular values and right vectors of the whole matrix.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
from jax import vmap
from threadpoolctl import threadpool_limits

#: rows per block of the tall-skinny QR (at least p; any size gives the same R up to signs)
BLOCK = 64


def tall_r(A):
    """The p x p triangular factor R of A = QR (n x p, any n >= 1), by blocks (TSQR).

    Arguments:
        A: an (n, p) array.

    Returns:
        R (p, p) (min(n, p) rows padded with zero rows where n < p).
    """
    n, p = A.shape
    block = max(BLOCK, p)
    m = (n // block) * block
    if m < 2 * block:  # few rows: one QR
        stack = A
    else:
        R = vmap(lambda B: jnp.linalg.qr(B, mode="r"))(A[:m].reshape(m // block, block, p))
        stack = jnp.concatenate([R.reshape(-1, p), A[m:]])
    R = jnp.linalg.qr(stack, mode="r")
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
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper
