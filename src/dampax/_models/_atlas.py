"""The error atlas: the expected error of every analytic model, interpolated in ratio space.

The motion depends only on the ratios d0/(w0 A0), d1/w0, d2 A0/w0 and the phase phi0 (eq. 21,
docs/DESIGN.md section 1), so one error map over them (``data/error_atlas.nc``, built by
``python scripts/build_atlas.py``) says how far each analytic model is from the exact motion
for every oscillator and initial state in its range: max |x - x_ref| / A0 over the motion up to
the reference's halt (at most 20 undamped periods).
"""

from __future__ import annotations

import functools
import math
import warnings
from importlib import resources

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array

_AXES = ("d0_ratio", "d1_ratio", "d2_ratio", "phi0")
_FLOOR = 1e-16  # errors are interpolated in log space; exact models give 0


@functools.cache
def load_atlas():
    """The atlas as an ``xarray.Dataset`` (max_error over model x d0 x d1 x d2 x phi0)."""
    import xarray as xr

    with resources.as_file(resources.files("dampax") / "data" / "error_atlas.nc") as path:
        return xr.load_dataset(path, engine="scipy")


@functools.cache
def _tables():
    ds = load_atlas()
    axes = tuple(np.asarray(ds[a], dtype=float) for a in _AXES)
    err = np.asarray(ds["max_error"], dtype=float)
    # errors vanish with the damping: interpolate log(err / s), s = the sum of the ratios,
    # which is smooth where log(err) is not (between s = 0 and the next grid point)
    s = (axes[0][:, None, None] + axes[1][None, :, None] + axes[2][None, None, :])[..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        log_rel = np.log(np.maximum(err, _FLOOR) / s)  # NaN stays: no model there
    # at s = 0 (the undamped origin) take the mean of the neighbours along each ratio axis
    near = np.stack([log_rel[:, 1, 0, 0], log_rel[:, 0, 1, 0], log_rel[:, 0, 0, 1]])
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices stay NaN
        origin = np.nanmean(near, axis=0)
    log_rel[:, 0, 0, 0] = np.where(np.isfinite(err[:, 0, 0, 0]), origin, np.nan)
    models = tuple(str(m) for m in np.asarray(ds["model"]))
    return models, axes, log_rel


def atlas_models() -> tuple[str, ...]:
    """The models the atlas holds."""
    return _tables()[0]


def _cell(axis: np.ndarray, value):
    """Index of the left grid value and the weight of the right one; outside: NaN weight."""
    n = axis.size
    i = jnp.clip(jnp.searchsorted(jnp.asarray(axis), value, side="right") - 1, 0, n - 2)
    lo, hi = jnp.asarray(axis)[i], jnp.asarray(axis)[i + 1]
    w = (value - lo) / (hi - lo)
    inside = (value >= axis[0]) & (value <= axis[-1])
    return i, jnp.where(inside, w, jnp.nan)


def interpolate(model: str, d0_ratio, d1_ratio, d2_ratio, phi0, *, bound: bool = False) -> Array:
    """Expected max |x - x_ref| / A0 of ``model`` at the given ratios (atlas interpolation).

    Multilinear interpolation of log(max_error / s), s = d0_ratio + d1_ratio + d2_ratio (the
    errors vanish with the damping), between the atlas' grid points, periodic in phi0 with
    period pi (phi0 + pi is the mirror-image motion). NaN outside the atlas' ratio
    ranges and where a neighbouring grid point has no value (the model does not exist there).
    Works under jit, vmap and grad (arguments broadcast).

    Arguments:
        model: a name of :func:`atlas_models`.
        d0_ratio, d1_ratio, d2_ratio: d0/(w0 A0), d1/w0, d2 A0/w0 (eq. 21).
        phi0: undamped initial phase [rad], any real value.
        bound: instead of interpolating, take the largest error of the 16 surrounding grid
            points (scaled by s): an upper estimate that also covers the jumps of the error
            where a model halts a swing early or late (what ``method="auto"`` uses).

    Returns:
        The estimate, shaped like the broadcast arguments.
    """
    models, axes, log_err = _tables()
    if model not in models:
        raise ValueError(f"model must be one of the atlas' {models}, got {model!r}")
    table = jnp.asarray(log_err[models.index(model)])
    d0, d1, d2, ph = jnp.broadcast_arrays(*(jnp.asarray(a, dtype=float) for a in (
        d0_ratio, d1_ratio, d2_ratio, phi0)))
    cells = [_cell(axes[0], d0), _cell(axes[1], d1), _cell(axes[2], d2)]
    # phi0: periodic grid phi_j = j pi / n on [0, pi)
    n_phi = axes[3].size
    u = jnp.mod(ph, math.pi) / (math.pi / n_phi)
    j = jnp.floor(u).astype(int) % n_phi
    cells.append((j, u - jnp.floor(u)))
    out = jnp.zeros(d0.shape)
    top = jnp.full(d0.shape, -jnp.inf)
    for corner in range(16):
        idx, weight = [], jnp.ones(d0.shape)
        for axis, (i, w) in enumerate(cells):
            up = (corner >> axis) & 1
            if axis == 3:
                idx.append((i + up) % n_phi)
            else:
                idx.append(i + up)
            weight = weight * (w if up else 1.0 - w)
        value = table[idx[0], idx[1], idx[2], idx[3]]
        # a corner of weight 0 (the point lies on a grid plane) does not count, even if the
        # model has no value there (Rizcallah's model beyond d1 = d2 = 0); NaN elsewhere (or
        # a NaN weight: outside the atlas) makes the estimate NaN
        out = out + jnp.where(weight == 0.0, 0.0, weight * value)
        top = jnp.maximum(top, jnp.where(weight == 0.0, -jnp.inf, value))
    if bound:
        out = jnp.where(jnp.isnan(out), jnp.nan, top)
    return (d0 + d1 + d2) * jnp.exp(out)


def ratios(osc, x0, v0):
    """(d0/(w0 A0), d1/w0, d2 A0/w0, phi0) of an oscillator and initial state (eq. 21)."""
    w0 = osc.omega0
    d0, d1, d2 = osc.damping_coefficients
    A0 = jnp.sqrt(x0 * x0 + (v0 / w0) ** 2)
    A0_safe = jnp.where(A0 > 0.0, A0, 1.0)
    phi0 = jnp.arctan2(-v0 / w0, x0)
    return (jnp.where(A0 > 0.0, d0 / (w0 * A0_safe), jnp.nan), d1 / w0, d2 * A0 / w0, phi0)


def estimate(model: str, osc, x0, v0, *, bound: bool = False) -> Array:
    """Expected (or, with ``bound``, upper) max |x - x_ref| / A0 of ``model`` for this
    oscillator and initial state (see :func:`interpolate`)."""
    return interpolate(model, *ratios(osc, x0, v0), bound=bound)
