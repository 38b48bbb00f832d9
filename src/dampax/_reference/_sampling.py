"""Dense output: x(t), v(t) between the stored steps.

Each stored step ("row": its ends t_a, t_b, the states there and the swing's sign) becomes one
polynomial, built once: the degree-9 Hermite interpolant that matches x and its first four
derivatives (eq. 3 with the swing's sign) at both ends. Its error is at most
h^10 max|x^(10)| / (10! 4^5): about 1e-11 A0 for the largest steps rtol = 1e-10 takes
(w0 h = 0.7), 1e-13 for typical ones, as accurate as the steps. A sample then costs one
gathered row of twelve numbers and two Horner evaluations (x and v).

The row of each sample: for sorted times, the steps are merged into the samples in one pass
(each step's start is located among the samples, a scatter-max and a running maximum: O(steps
log samples + samples)); otherwise a binary search per sample. Which one runs is decided at run
time (`jax.lax.cond` on whether the times are sorted), so no option is needed, also under jit.
"""

from __future__ import annotations

import math

import equinox.internal as eqxi
import jax
import jax.numpy as jnp

from ._stepping import derivatives

# columns of a stored row: its start, 1/h, and the ten coefficients of its polynomial
T_A, INV_H = 0, 1
WIDTH = 12

# Hermite interpolation with x and its first four derivatives at both ends: the polynomial is
# sum_k c_k th^k (th in [0, 1]); c_0..c_4 are the left end's Taylor coefficients and c_5..c_9
# = _HERMITE9 @ (r_0..r_4), r_m being what the right end's m-th derivative (times h^m) asks
# beyond the Taylor part.
_HERMITE9 = ((126.0, -56.0, 10.5, -1.0, 1.0 / 24.0),
             (-420.0, 196.0, -38.5, 23.0 / 6.0, -1.0 / 6.0),
             (540.0, -260.0, 53.0, -5.5, 0.25),
             (-315.0, 155.0, -32.5, 3.5, -1.0 / 6.0),
             (70.0, -35.0, 7.5, -5.0 / 6.0, 1.0 / 24.0))


def hermite_row(t_a, t_b, x_a, v_a, x_b, v_b, args):
    """The interpolating polynomial of one step: (t_a, 1/h, c_0..c_9) stacked on a last axis.

    The degree-9 polynomial sum_k c_k th^k, th = (t - t_a)/h in [0, 1], matches x and its
    first four derivatives (eq. 3 with the swing's sign, in ``args``) at both ends. Works
    elementwise on arrays of steps as on scalars.
    """
    return jnp.stack(hermite_columns(t_a, t_b, x_a, v_a, x_b, v_b, args), axis=-1)


def hermite_columns(t_a, t_b, x_a, v_a, x_b, v_b, args):
    """:func:`hermite_row` as a list of its twelve columns (t_a, 1/h, c_0..c_9), not stacked
    (the fused kernel keeps them as separate registers)."""
    h = t_b - t_a
    da = derivatives(args, x_a, v_a)
    db = derivatives(args, x_b, v_b)
    hk = [1.0, h, h * h, h * h * h, h * h * h * h]
    c = [hk[k] * da[k] / math.factorial(k) for k in range(5)]
    r = [hk[m] * db[m] - sum(math.perm(k, m) * c[k] for k in range(m, 5)) for m in range(5)]
    c += [sum(w * r_m for w, r_m in zip(row, r, strict=True)) for row in _HERMITE9]
    inv_h = jnp.where(h > 0.0, 1.0 / jnp.where(h > 0.0, h, 1.0), 0.0)
    # a zero-length step (a turning point found at its step's start): constant, v = v_a
    c[1] = jnp.where(h > 0.0, c[1], v_a)
    return [t_a, inv_h] + c


def _horner(coef, th, zero_length):
    """x and v of one gathered row (t_a, 1/h, c_0..c_9) at th."""
    return horner([coef[..., k] for k in range(WIDTH)], th, zero_length)


def horner(cols, th, zero_length):
    """x and v at th of a row given as its twelve columns (t_a, 1/h, c_0..c_9)."""
    c = cols[2:]
    x = c[9]
    dx = 9.0 * c[9]
    for k in range(8, -1, -1):
        x = c[k] + th * x
        if k > 0:
            dx = k * c[k] + th * dx
    return x, jnp.where(zero_length, c[1], dx * cols[1])


def _rows_sorted(starts, t):
    """Row of each sorted time t: the last row whose start is <= t (merge, see module doc)."""
    n = t.shape[0]
    pos = jnp.searchsorted(t, starts, side="left")  # first sample at or after each row start
    first = jnp.full((n,), 0).at[pos].max(jnp.arange(starts.shape[0]), mode="drop")
    return jax.lax.cummax(first).astype(jnp.int32)


def _rows_search(starts, t):
    """Row of each time t by a binary search among the row starts."""
    return (jnp.searchsorted(starts, t, side="right") - 1).astype(jnp.int32)


def _rows_grid(starts, start, step, n: int):
    """Row of each t_i = start + i step (i < n): each row start goes to the first grid point at
    or after it (a scatter-max), then a running maximum: O(rows + n)."""
    pos = jnp.ceil((starts - start) / step)
    pos = jnp.where(jnp.isfinite(starts) & (pos < n), jnp.maximum(pos, 0.0), n).astype(int)
    first = jnp.full((n,), 0).at[pos].max(jnp.arange(starts.shape[0]), mode="drop")
    return jax.lax.cummax(first)


def rows_of(starts, t, grid=None):
    """Row index of every time of the 1-D array t (the last row starting at or before it).

    Arguments:
        starts: (R,) row start times, non-decreasing, inf-padded.
        t: (n,) times (finite).
        grid: optional (start, step) with t[i] = start + i step.
    """
    if grid is not None:
        return _rows_grid(starts, grid[0], grid[1], t.shape[0])
    if t.shape[0] < 2:
        return _rows_search(starts, t)
    ordered = jnp.all(t[1:] >= t[:-1])
    return jax.lax.cond(ordered, _rows_sorted, _rows_search, starts, t)


# Gathering a row of twelve numbers per sample dominated the dense output (XLA's gather on CPU
# moves one element at a time), and so did finding each sample's row. Neighbouring samples
# mostly share rows: in chunks of _CHUNK samples, the row of the chunk's first sample is found
# by a binary search, the _WINDOW rows from it (and the start of the next) are gathered once,
# and each sample counts the row starts of the window it has passed. Where a chunk spans more
# rows (steps much shorter than the sample spacing) or a sample precedes its chunk's first
# (unsorted times), every sample finds and gathers its own row instead (`rows_of`), for the
# whole batch. (1,024 random trajectories, 1,000 samples in 5 s: a chunk of 16 spans at most 5
# rows at rtol = 1e-10 and 6 at 1e-11; a window of 4 made the default fall back.)
_CHUNK = 16
_WINDOW = 6


def _windowed(coef, lo, t_chunks, n):
    """x, v at the (chunked) times: each sample's row is one of its chunk's window."""
    rows = coef[jnp.minimum(lo[:, None] + jnp.arange(_WINDOW)[None, :], coef.shape[0] - 1)]
    local = _passed(coef, lo, t_chunks)
    cols = []
    for j in range(WIDTH):
        val = jnp.broadcast_to(rows[:, :1, j], t_chunks.shape)
        for w in range(1, _WINDOW):
            val = jnp.where(local == w, rows[:, w : w + 1, j], val)
        cols.append(val.reshape(-1)[:n])
    return _evaluate_rows(jnp.stack(cols, axis=-1), t_chunks.reshape(-1)[:n])


def _passed(coef, lo, t_chunks):
    """How many row starts after the chunk's first row each sample has passed (up to
    _WINDOW; padding rows start at inf and are never passed)."""
    nxt = jnp.minimum(lo[:, None] + jnp.arange(1, _WINDOW + 1)[None, :], coef.shape[0] - 1)
    starts = jnp.where(lo[:, None] + jnp.arange(1, _WINDOW + 1)[None, :] < coef.shape[0],
                       coef[nxt, 0], jnp.inf)
    return sum((t_chunks >= starts[:, w : w + 1]).astype(jnp.int32) for w in range(_WINDOW))


def _gathered(coef, n_rows, t, grid):
    """x, v at t, every sample finding and gathering its own row."""
    idx = jnp.clip(rows_of(coef[:, 0], t, grid), 0, jnp.maximum(n_rows - 1, 0))
    return _evaluate_rows(coef[idx], t)


def _evaluate_rows(row, t):
    inv_h = row[:, 1]
    t_a = jnp.where(jnp.isfinite(row[:, 0]), row[:, 0], t)  # no row: nothing moved
    th = jnp.clip((t - t_a) * inv_h, 0.0, 1.0)
    return _horner(row, th, inv_h == 0.0)


def sample(coef, n_rows, t, grid=None):
    """(x, v) at the 1-D times t from the rows' polynomials (inside the integrated part).

    Arguments:
        coef: (R, 12) rows from `hermite_row`, in time order, inf-padded (t_a = inf).
        n_rows: number of real rows (>= 1 where anything was integrated).
        t: (n,) times; values outside [first row start, last row end] are clamped to the
            nearest row (the caller masks them).
        grid: optional (start, step) of a uniform t.
    """
    t_safe = jnp.where(jnp.isfinite(t), t, 0.0)
    n = t.shape[0]
    if n < 2 * _CHUNK:
        return _gathered(coef, n_rows, t_safe, grid)
    t_chunks = jnp.concatenate([t_safe, jnp.broadcast_to(t_safe[-1:], (-n % _CHUNK,))])
    t_chunks = t_chunks.reshape(-1, _CHUNK)
    first = t_chunks[:, 0]
    lo = jnp.clip(jnp.searchsorted(coef[:, 0], first, side="right") - 1, 0,
                  jnp.maximum(n_rows - 1, 0))
    fits = (jnp.all(t_chunks >= first[:, None])
            & jnp.all(_passed(coef, lo, t_chunks) < _WINDOW))
    # unbatched predicate (every trajectory of a vmapped batch): a real branch; each branch
    # evaluates the polynomials itself, so that the rows are not stored in between
    return jax.lax.cond(eqxi.unvmap_all(fits),
                        lambda: _windowed(coef, lo, t_chunks, n),
                        lambda: _gathered(coef, n_rows, t_safe, grid))
