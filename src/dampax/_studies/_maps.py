"""Error maps: the analytic models against a reference over a grid of damping ratios.

The motion depends only on d0/(w0 A0), d1/w0, d2 A0/w0 and phi0 (docs/DESIGN.md section 1), so a map
is computed at w0 = 1, A0 = 1 (m = k = 1, x0 = cos phi0, v0 = -sin phi0) and holds for every
m, k and A0.

How it runs: the grid is flattened and cut into steps of ``chunk_size`` points per local
device. One compiled function, ``jit(shard_map(vmap(per_point)))``, evaluates a step: the
reference and every model are solved per point and compared on a fixed time grid, in blocks of
samples (a ``lax.scan``) that reduce the metrics on the fly, so only a few numbers per point
leave the device and memory stays bounded by ``chunk_size`` whatever the grid and the number
of periods; a block after every window of the step has closed is skipped. Every step has
the same shape (the last is padded), so nothing recompiles. The step is sharded over all
local devices (a 1-device mesh on one device: the same code path); on several hosts (after
``jax.distributed.initialize``) each process takes its share of the steps and the results are
gathered at the end (``dampax._studies._distributed``: the gather's timeout, local worker
processes for ``processes=N``).
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import math
from collections.abc import Sequence

import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np

from .._cache import compile_cached
from .._models._registry import ANALYTIC, MODELS, check_models
from .._oscillator import Oscillator, ratio_constants
from .._reference._solve import check_reference_options
from .._solve import solve_checked
from .._version import __version__
from ._budget import ACCELERATOR_CHUNK as ACCELERATOR_CHUNK
from ._budget import CPU_CHUNK as CPU_CHUNK
from ._budget import MAP_BYTES_PER_POINT as MAP_BYTES_PER_POINT
from ._budget import MAP_MEMORY_SHARE as MAP_MEMORY_SHARE
from ._budget import MAP_SECONDS_PER_POINT as MAP_SECONDS_PER_POINT
from ._budget import MAX_SAMPLES as MAX_SAMPLES
from ._budget import STEP_MEMORY_SHARE as STEP_MEMORY_SHARE
from ._budget import check_map_size as check_map_size
from ._budget import choose_chunk as choose_chunk
from ._budget import device_memory as device_memory
from ._budget import duration_text as duration_text
from ._budget import map_cost as map_cost
from ._budget import physical_memory as physical_memory
from ._budget import step_bytes_per_point as step_bytes_per_point
from ._distributed import (
    DEFAULT_TIMEOUT,
    check_processes,
    check_timeout,
    compile_cached_here,
    gather,
    run_local,
)
from ._mapquery import MAX_AXIS_POINTS as MAX_AXIS_POINTS
from ._mapquery import largest_ratio_below as largest_ratio_below
from ._mapquery import parse_axis as parse_axis
from ._mapquery import worst_in_box as worst_in_box

Array = jax.Array

DEFAULT_MODELS = ("matched", "undamped", "matched_tail", "rizcallah")
#: Accepted references: the DOP853 integrator of eq. 3, or the exact half-swings (D = 0 only).
REFERENCES = ("reference", "coulomb_exact")
#: Per-point metrics, in the order of the compiled function's output.
METRICS = ("max_error", "rms_error", "energy_error", "halt_time_error", "halt_position_error")
#: Without a halt the comparison window ends where the reference energy drops below this * E0.
ENERGY_FLOOR = 1e-4
_AXES = ("d0_ratio", "d1_ratio", "d2_ratio", "phi0")
_BLOCK = 1024  # at most this many samples per scan step (memory per point: a few such arrays)
#: Longer windows integrate the reference in segments of about this many periods.
SEGMENT_PERIODS = 32.0

# CF conventions: dimensionless variables have units "1"; the normalisation is in long_name
_VARIABLE_ATTRS = {
    "max_error": dict(long_name="max |x - x_ref| / A0 over the window", units="1"),
    "rms_error": dict(long_name="rms of (x - x_ref) / A0 over the window", units="1"),
    "energy_error": dict(long_name="max |E - E_ref| / E0 over the window (E0 = k A0^2 / 2)",
                         units="1"),
    "halt_time_error": dict(
        long_name="halt time, model minus reference, in undamped periods T0 = 2 pi / w0 (NaN "
                  "where the reference does not halt within the window)", units="1"),
    "halt_position_error": dict(
        long_name="halt position, model minus reference, in units of xc = mu g / w0^2 (NaN "
                  "without friction or where the reference does not halt within the window)",
        units="1"),
    # flags (bool in memory, bytes 0/1 in a netCDF file): CF flag_values / flag_meanings
    "valid": dict(long_name="the model exists at this point (its validity flag)",
                  flag_values=np.array([0, 1], dtype=np.int8),
                  flag_meanings="model_not_defined model_defined"),
    "reference_valid": dict(long_name="the reference solved without running out of its budget",
                            flag_values=np.array([0, 1], dtype=np.int8),
                            flag_meanings="reference_failed reference_solved"),
    "window": dict(long_name="length of the comparison window in undamped periods (to the "
                             "reference's halt, or until its energy drops below "
                             f"{ENERGY_FLOOR:g} E0, at most `periods`)", units="1"),
    "reference_halt_time": dict(long_name="halt time of the reference in undamped periods T0 "
                                          "(NaN if it does not halt within the window)",
                                units="1"),
}
_COORD_ATTRS = {
    "model": dict(long_name="analytic model"),
    "d0_ratio": dict(long_name="d0/(w0 A0), Coulomb (d0 = 2 mu g/(pi w0))", units="1"),
    "d1_ratio": dict(long_name="d1/w0, viscous (d1 = b/(2m))", units="1"),
    "d2_ratio": dict(long_name="d2 A0/w0, quadratic (d2 = 4 D w0/(3 pi m))", units="1"),
    "phi0": dict(long_name="undamped initial phase, x0 = A0 cos(phi0), v0 = -w0 A0 sin(phi0)",
                 units="rad"),
    "k3_ratio": dict(long_name="k3 A0^2/k, cubic stiffness (m x'' = -k x - k3 x^3 - ...)",
                     units="1"),
}

@dataclasses.dataclass(frozen=True)
class _Config:
    """Everything static about the compiled per-step function."""

    models: tuple[str, ...]
    reference: str
    n_samples: int  # samples at t = i T0 / samples_per_period, i < n_samples
    samples_per_period: int
    block: int
    rtol: float
    atol: float
    max_swings: int  # of the reference, per segment
    seg_blocks: int  # blocks per segment of the reference (all of them: one segment)
    cubic: bool = False  # rows carry a fifth column, k3_ratio (issue 14)
    engine: str = "dampax"  # the reference's integrator (issue 35: "diffrax" beside it)

    @property
    def width(self) -> int:
        return 5 if self.cubic else 4

    @property
    def n_blocks(self) -> int:
        return -(-self.n_samples // self.block)

    @property
    def n_segments(self) -> int:
        return -(-self.n_blocks // self.seg_blocks)


# ----------------------------------------------------------------------------------------------
# one point


def _solve_reference(cfg: _Config, osc, x0, v0, t_end):
    if cfg.reference == "reference":
        sol = solve_checked(osc, x0, v0, method="reference", t_end=t_end, rtol=cfg.rtol,
                            atol=cfg.atol, max_swings=cfg.max_swings, engine=cfg.engine)
    else:  # exact half-swings: valid only where D = 0 and b < 2 sqrt(k m) (its result says)
        sol = solve_checked(osc, x0, v0, **MODELS[cfg.reference].solve_options)
    halted = jnp.isfinite(sol.halt_time) & (sol.halt_time <= t_end)
    return sol, sol.valid, halted


def _harmonic(cfg: _Config, osc):
    """Whether the point's reference is the harmonic motion (mu = b = D = k3 = 0; traced), or
    False where the reference is not the integrator of eq. 3 (``coulomb_exact`` is analytic
    already)."""
    if cfg.reference != "reference":
        return False
    return (osc.mu == 0.0) & (osc.b == 0.0) & (osc.D == 0.0) & (osc.k3 == 0.0)


def _max_sum_max(a, b):
    return jnp.maximum(a[0], b[0]), a[1] + b[1], jnp.maximum(a[2], b[2])


def _reduce_errors(win, err, e_err):
    """(max, sum of squares) of ``err`` and max of ``e_err`` over the samples in ``win``.

    One variadic reduce per model: XLA then evaluates the model's x and energy once per sample,
    inside it. As three reductions (or one over the models stacked), each got its own fused
    copy of the model's arithmetic: its cos, sin and f(t) computed three times.
    """
    err = jnp.where(win, err, 0.0)
    e_err = jnp.where(win, e_err, 0.0)
    zero = jnp.zeros((), err.dtype)
    return jax.lax.reduce((err, err * err, e_err), (zero, zero, zero), _max_sum_max,
                          (err.ndim - 1,))


def _accumulate(stats, win, t, errs):
    """Running (count, last time, max error, sum of squares, max energy error) over ``win``;
    ``errs`` holds (error, energy error) of each model at the samples t."""
    count, t_win, err_max, err_sq, e_max = stats
    blk_max, blk_sq, blk_e = (jnp.stack(r) for r in
                              zip(*(_reduce_errors(win, *pair) for pair in errs), strict=True))
    return (count + jnp.sum(win), jnp.maximum(t_win, jnp.max(jnp.where(win, t, 0.0))),
            jnp.maximum(err_max, blk_max), err_sq + blk_sq, jnp.maximum(e_max, blk_e))


def _per_point(cfg: _Config, row):
    """Metrics of every model at one grid point row = (d0r, d1r, d2r, phi0), w0 = A0 = 1.

    The reference is integrated segment by segment (``cfg.seg_blocks`` blocks of
    samples each, restarted from the state at the segment's end), so its memory does not grow
    with the window. The comparison window (to the reference's halt, or until its energy falls
    below the floor) is only known at the end; with several segments both candidates are
    accumulated and the right one is picked at the end.
    """
    d0r, d1r, d2r, phi0 = row[0], row[1], row[2], row[3]
    m, k, A0 = 1.0, 1.0, 1.0
    # the grid was checked at the edge (error_map): built, and solved below, unchecked;
    # k3 A0^2 / k = row[4] at k = A0 = 1
    mu, b, D = ratio_constants(d0r, d1r, d2r, m=m, k=k, A0=A0)
    osc = Oscillator.unchecked(m=m, k=k, mu=mu, b=b, D=D, k3=row[4] if cfg.cubic else 0.0)
    w0 = osc.omega0
    period = 2.0 * math.pi / w0
    dt = period / cfg.samples_per_period
    x0 = A0 * jnp.cos(phi0)
    v0 = -w0 * A0 * jnp.sin(phi0)
    E0 = 0.5 * k * A0 * A0
    xc = osc.xc

    sols = [solve_checked(osc, x0, v0, **MODELS[name].solve_options) for name in cfg.models]
    valid = [sol.valid for sol in sols]
    n_mod = len(cfg.models)
    single = cfg.n_segments == 1
    seg_len = cfg.seg_blocks * cfg.block  # samples per segment
    # only friction stops the block for good (drag alone never does): without it the window
    # "to the halt" is never the one used, and only the energy floor keeps a window open
    can_halt = osc.mu > 0.0
    # without damping and with a linear spring eq. 3 is the harmonic oscillator: its motion is
    # sampled in closed form, not integrated (it never stops: integrated, it held its batch for
    # the whole span, issue 35)
    harmonic = _harmonic(cfg, osc)

    def segment(carry, s):
        xs, vs, halted, t_halt, x_halt, ref_ok, fallen, stats = carry
        i0 = s * seg_len
        # one segment: the whole window, up to the last sample (computed as the samples are)
        t_end = (cfg.n_samples - 1) * dt if single else seg_len * dt
        # a point that needs no more of the integrated reference (harmonic, or its energy
        # below the floor where no halt can come) solves nothing: a stand-in that is refused
        # at once (t_end 0), so that it does not hold the batch's loop; the window's samples
        # do not read it
        skip = harmonic | (fallen & ~can_halt)
        ref, ok, seg_halted = _solve_reference(cfg, osc, jnp.where(skip, 0.0, xs),
                                               jnp.where(skip, 0.0, vs),
                                               jnp.where(skip, 0.0, t_end))
        ok, seg_halted = ok | skip, seg_halted & ~skip
        new = ~halted & seg_halted
        t_halt = jnp.where(new, i0 * dt + ref.halt_time, t_halt)
        x_halt = jnp.where(new, ref.halt_position, x_halt)
        ref_ok = ref_ok & (ok | halted)
        halted = halted | seg_halted

        def live_block(carry, j):
            fallen, stats = carry
            idx = j * cfg.block + jnp.arange(cfg.block)
            t = idx * dt
            inside = idx < cfg.n_samples
            t_local = t if single else (idx - i0) * dt
            # A branch of its own: x_ref and e_ref are then computed once and stored. Used
            # directly, XLA fused the reference's Hermite interpolation into every consumer
            # (each model's reduction, the energy floor's cumsum): six times per sample.
            # (Its predicate is the block's own, true here: the branch is the boundary.)
            x_ref, e_ref = jax.lax.cond(
                block_live(fallen, t[0], inside[0]),
                lambda tl: ref._x_energy(tl, (tl[0], dt)),
                lambda tl: (jnp.full_like(tl, jnp.nan), jnp.full_like(tl, jnp.nan)), t_local)
            if harmonic is not False:  # only in a step that holds a harmonic point
                x_ref, e_ref = jax.lax.cond(
                    eqxi.unvmap_any(harmonic),
                    lambda xe: (jnp.where(harmonic, x0 * jnp.cos(w0 * t)
                                          + v0 / w0 * jnp.sin(w0 * t), xe[0]),
                                jnp.where(harmonic, osc.energy(x0, v0), xe[1])),
                    lambda xe: xe, (x_ref, e_ref))
            below = inside & (e_ref < ENERGY_FLOOR * E0)
            fallen_t = fallen | (jnp.cumsum(below) > 0)
            errs = []
            for sol in sols:
                x, e = sol._x_energy(t)
                errs.append((jnp.abs(x - x_ref) / A0, jnp.abs(e - e_ref) / E0))
            if single:  # the halt is known: one window
                wins = (inside & jnp.where(halted, t <= t_halt, ~fallen_t),)
            else:  # to the halt (if any comes), or until the energy falls
                wins = (inside & (t <= t_halt), inside & ~fallen_t)
            stats = tuple(_accumulate(st, w, t, errs)
                          for st, w in zip(stats, wins, strict=True))
            return (fallen_t[-1], stats), None

        def block_live(fallen, t0, inside0):
            """True when some point of the (vmapped) batch may have a sample of the block
            (from t0 on) in a window: not past its halt, or, without one, its energy not yet
            below the floor. Unbatched (``unvmap_any``), so a real branch."""
            if single:
                live = inside0 & jnp.where(halted, t0 <= t_halt, ~fallen)
            else:  # to its halt once halted; before, either candidate may still be open
                live = inside0 & jnp.where(halted, t0 <= t_halt, can_halt | ~fallen)
            return eqxi.unvmap_any(live)

        def block(carry, j):
            # Blocks after every window of the batch has closed change nothing: skipped. (A
            # point's `fallen` may then stay False past its halt; it is not used there.)
            idx0 = j * cfg.block
            live = block_live(carry[0], idx0 * dt, idx0 < cfg.n_samples)
            return jax.lax.cond(live, live_block, lambda c, _: (c, None), carry, j)

        (fallen, stats), _ = jax.lax.scan(block, (fallen, stats),
                                          s * cfg.seg_blocks + jnp.arange(cfg.seg_blocks))
        if not single:
            xs, vs = ref.state(seg_len * dt)
        return (xs, vs, halted, t_halt, x_halt, ref_ok, fallen, stats), None

    zeros = jnp.zeros(n_mod)
    empty = (jnp.array(0), jnp.array(0.0), zeros, zeros, zeros)
    init = (x0, v0, jnp.array(False), jnp.array(jnp.inf), jnp.array(jnp.nan), jnp.array(True),
            jnp.array(False), (empty,) if single else (empty, empty))
    def segment_or_skip(carry, s):
        """A segment, or nothing once every window of the (vmapped) batch has closed: no
        point may still halt in it or have its energy above the floor (``unvmap_any``: a
        real branch). So the reference costs what the motion in the windows takes, not
        what ``periods`` asks."""
        halted, t_halt, fallen = carry[2], carry[3], carry[6]
        live = jnp.where(halted, s * seg_len * dt <= t_halt, can_halt | ~fallen)
        return jax.lax.cond(eqxi.unvmap_any(live), segment, lambda c, _: (c, None), carry, s)

    (_, _, halted, t_halt, x_halt, ref_valid, _, stats), _ = jax.lax.scan(
        segment if single else segment_or_skip, init, jnp.arange(cfg.n_segments))
    if single:
        stats = stats[0]
    else:
        stats = jax.tree_util.tree_map(lambda a, b: jnp.where(halted, a, b), *stats)
    count, t_win, err_max, err_sq, e_max = stats
    rms = jnp.sqrt(err_sq / jnp.maximum(count, 1))

    rows = []
    for j, sol in enumerate(sols):
        dt_halt = jnp.where(halted, (sol.halt_time - t_halt) / period, jnp.nan)
        xc_safe = jnp.where(xc > 0.0, xc, 1.0)
        dx_halt = jnp.where(halted & (xc > 0.0),
                            (sol.halt_position - x_halt) / xc_safe, jnp.nan)
        ok = valid[j] & ref_valid
        rows.append(jnp.where(ok, jnp.stack([err_max[j], rms[j], e_max[j], dt_halt, dx_halt]),
                              jnp.nan))
    metrics = jnp.stack(rows)  # (n_models, 5)
    info = jnp.stack([ref_valid.astype(float), t_win / period,
                      jnp.where(halted & ref_valid, t_halt / period, jnp.nan)])
    return metrics, jnp.stack(valid), info


# ----------------------------------------------------------------------------------------------
# the compiled step


@functools.lru_cache(maxsize=16)
def _compiled(cfg: _Config, device_ids: tuple[int, ...]):
    """jit(shard_map(vmap(per_point))) over a mesh of the given local devices, and the mesh."""
    from jax.sharding import PartitionSpec as P

    by_id = {d.id: d for d in jax.local_devices()}
    devices = [by_id[i] for i in device_ids]
    mesh = jax.make_mesh((len(devices),), ("points",), devices=devices,
                         axis_types=(jax.sharding.AxisType.Explicit,))

    def step(rows):
        return jax.vmap(lambda r: _per_point(cfg, r))(rows)

    sharded = jax.shard_map(step, mesh=mesh, in_specs=P("points"), out_specs=P("points"),
                            check_vma=False)
    return jax.jit(sharded), mesh


@functools.lru_cache(maxsize=16)
def _executable(cfg: _Config, device_ids: tuple[int, ...], step: int):
    """The compiled step for ``step`` rows (lowered and compiled ahead of time)."""
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    fn, mesh = _compiled(cfg, device_ids)
    rows = jax.ShapeDtypeStruct((step, cfg.width), jnp.float64,
                                sharding=NamedSharding(mesh, P("points")))
    if jax.process_index() != 0:  # jax's persistent cache keeps only process 0's programs
        return compile_cached_here("error_map", (cfg, device_ids), fn, rows)
    return compile_cached("error_map", (cfg, device_ids), fn, rows)


# ----------------------------------------------------------------------------------------------
# input checks


def _axis(name: str, value, *, ratio: bool) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} must be a number or a 1-D sequence of numbers, got "
                         f"{value!r}") from err
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be a number or a 1-D sequence, got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name} is empty: give at least one value")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if ratio and np.any(arr < 0.0):
        raise ValueError(f"{name} must be >= 0 (damping ratios cannot be negative), "
                         f"got {value!r}")
    return arr


def _window_estimate(grid, periods: float) -> np.ndarray:
    """Rough comparison window of every grid point (w0 = A0 = 1), to group long ones.

    The time f(t) of eq. 20 (f' = -(d2 f^2 + d1 f + d0) at A = A0) takes to reach 0 (with
    friction: the halt) or 0.01 (without: the energy floor), by quadrature over f; at most
    ``periods``. Only an ordering key: it changes which points share a step, not any result.
    """
    d0, d1, d2 = (np.asarray(grid[:, i], dtype=float)[:, None] for i in range(3))
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(d0 > 0.0, np.linspace(0.0, 1.0, 129)[None, :],
                     np.geomspace(0.01, 1.0, 129)[None, :])
        rate = d2 * f * f + d1 * f + d0
        t = np.trapezoid(np.where(rate > 0.0, 1.0 / rate, np.inf), f, axis=1)
    return np.minimum(np.nan_to_num(t, nan=np.inf), 2.0 * math.pi * periods)


#: points per step (and device) of the longest windows (see `_tail_count`)
TAIL_CHUNK = 8

def _tail_count(estimate, step: int, tail_step: int) -> int:
    """How many of the points (sorted by estimated window, longest first) form the tail: those
    whose window is more than 4x the longest outside the first step. A multiple of
    ``tail_step``, at most one step; 0 when there is no such tail (or one step holds all)."""
    if estimate.size <= step or tail_step >= step:
        return 0
    far = int(np.sum(estimate > 4.0 * estimate[step]))
    if far == 0:
        return 0
    return min(-(-far // tail_step) * tail_step, step)


def _positive_int(name: str, value, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _config(models, reference, periods, samples_per_period, rtol, atol,
            cubic: bool = False, engine: str = "dampax") -> _Config:
    """The static settings of the compiled step (arguments already checked)."""
    n_samples = int(math.floor(periods * samples_per_period + 1e-9)) + 1
    if n_samples > MAX_SAMPLES:
        raise ValueError(
            f"periods x samples_per_period: {periods:g} x {samples_per_period} = "
            f"{n_samples - 1:.3g} samples per grid point, more than the {MAX_SAMPLES:.0e} a map "
            "allows (its cost grows with the window); shorten periods or sample less often")
    block = -(-n_samples // -(-n_samples // _BLOCK))  # equal blocks of at most _BLOCK
    n_blocks = -(-n_samples // block)
    seg_blocks, seg_periods = n_blocks, periods
    if reference == "reference" and periods > SEGMENT_PERIODS:
        # the reference in segments of about SEGMENT_PERIODS: memory independent of periods
        seg_blocks = max(1, int(SEGMENT_PERIODS * samples_per_period) // block)
        seg_periods = seg_blocks * block / samples_per_period
    cfg = _Config(models=models, reference=reference, n_samples=n_samples,
                  samples_per_period=samples_per_period, block=block,
                  rtol=float(rtol), atol=float(atol),
                  max_swings=2 * math.ceil(seg_periods) + 6, seg_blocks=seg_blocks,
                  cubic=cubic, engine=engine)
    return cfg


# ----------------------------------------------------------------------------------------------
# the public function


def error_map(*, d0_ratio, d2_ratio, phi0, d1_ratio=0.0,
              models: Sequence[str] = DEFAULT_MODELS, periods: float = 20.0,
              samples_per_period: int = 64, chunk_size: int | None = None,
              reference: str = "reference", rtol: float = 1e-10, atol: float = 1e-12,
              progress: bool = True, k3_ratio=None, processes: int | None = None,
              timeout: float = DEFAULT_TIMEOUT, engine: str = "auto"):
    """Errors of the analytic models against a reference over a grid of damping ratios.

    Every combination of the axes is one initial-value problem at w0 = 1, A0 = 1 (m = k = 1,
    x0 = cos phi0, v0 = -sin phi0; mu, b, D from the ratios by eq. 21), so the map holds for
    every m, k and A0. Model and reference are compared on the samples t = i T0 /
    samples_per_period of a window that runs to the reference's halt or, when it does not halt,
    until its energy drops below 1e-4 E0; at most ``periods`` undamped periods T0. Where there
    is no damping at all (d0 = d1 = d2 = 0, a linear spring) the reference is the harmonic
    motion cos(t + phi0) itself, in closed form: it is not integrated over the whole span.

    Arguments:
        d0_ratio: d0/(w0 A0), Coulomb friction; a number or a 1-D sequence, >= 0.
        d2_ratio: d2 A0/w0, quadratic drag; a number or a 1-D sequence, >= 0.
        phi0: undamped initial phase(s) [rad] (phi0 + pi gives the mirror-image motion).
        d1_ratio: d1/w0, viscous damping; a number or a 1-D sequence, >= 0.
        models: analytic models of the registry (``dampax._models._registry.MODELS``): "matched"
            (ansatz, matched phase, eqs. 22-23), "undamped" (ansatz,
            undamped phase, eqs. 8-10), "matched_tail" (matched + exact Coulomb tail, eqs. 41,
            52), "rizcallah" (only d1 = d2 = 0; NaN elsewhere), "coulomb_exact" (exact
            half-swings; only d2 = 0).
        periods: length of the time grid in undamped periods (the window's cap), > 0. Beyond
            ``SEGMENT_PERIODS`` (32) the reference is integrated in segments of about 32
            periods, each restarted from the state where the last ended, so memory does not
            grow with ``periods``; at most ``MAX_SAMPLES`` samples per point.
        samples_per_period: samples per undamped period, >= 2.
        chunk_size: grid points per device evaluated at once, >= 1; None (default): chosen
            from the platform and the memory (``choose_chunk``: 128 on a CPU, up to 32768
            on a GPU). Given or not, clipped to the grid and to a quarter of a device's
            memory; the value used is in ``attrs['chunk_size']``.
        reference: "reference" (the DOP853 integrator of eq. 3 with exact stick-slip) or
            "coulomb_exact" (the exact half-swings, analytic and fast: valid only where
            d2 = 0 and d1 < 1, NaN elsewhere).
        rtol, atol: tolerances of the DOP853 reference (at A0 = 1, w0 = 1).
        engine: the integrator of ``reference="reference"``: "auto" (default: the fused
            kernel on a CUDA GPU, else "dampax"), "dampax" (its own DOP853 loop), "pallas"
            (the same loop as one fused kernel) or "diffrax" (diffrax's Dopri8 with its
            events, swing by swing: an independent second integrator, slower;
            ``solve_reference``).
        progress: show a tqdm progress bar over the steps (on stderr; nothing else is printed).
        k3_ratio: optional cubic stiffness axis k3 A0^2/k (issue 14; a number or a 1-D
            sequence, either sign, finite). Default None: no such axis, the map (its dims, its
            compiled program and its numbers) exactly as without k3. Given (0 included), it
            becomes the last dim; models without k3 (all but "matched") are NaN with
            ``valid`` False where k3 != 0, and a softening start beyond the barrier is invalid
            for every model. E0 stays k A0^2/2.
        processes: None (default): computed in this process, or, after
            ``jax.distributed.initialize()`` (a cluster: Slurm, Open MPI, or explicit
            arguments), this process's share of the steps, the shares gathered so that every
            process returns the whole map. N >= 2: N local worker processes compute it (a
            ``jax.distributed`` run on 127.0.0.1 at a free port, each computing an equal share
            of the steps; the map is bit for bit the one-process map); 1: this process.
        timeout: multi-process runs only: seconds for the processes to connect (processes >=
            2), and for each to wait at the gather for the others to finish their shares; a
            process that dies ends the run sooner. Past it the run fails (DistributedError).

    Returns:
        An ``xarray.Dataset`` with dims (model, d0_ratio, d1_ratio, d2_ratio, phi0), plus
        k3_ratio last when given (a scalar axis becomes a length-1 dim) and variables
        max_error (in A0), rms_error (in A0),
        energy_error (in E0), halt_time_error (model minus reference, in periods),
        halt_position_error (model minus reference, in xc), valid (the model exists there), and
        per point reference_valid, window and reference_halt_time (in periods). Metrics are
        NaN where the model or the reference is not valid. Settings are in ``attrs``; write it
        with ``ds.to_netcdf(path)``.

    Raises:
        ValueError: naming the argument, for an empty, non-finite or negative axis, an unknown
            model or reference, chunk_size < 1, periods <= 0, samples_per_period < 2 or
            more than ``MAX_SAMPLES`` samples per point; a grid whose memory estimate
            (``map_cost``) exceeds half the machine's memory (its points, memory and time
            named); processes < 1, or >= 2 in a process
            that already joined a ``jax.distributed`` run; timeout <= 0.
        dampax._studies._distributed.DistributedError: a multi-process run failed: a process died,
            failed or timed out (nothing is returned).
    """
    from tqdm import tqdm  # plain text bar: tqdm.auto warns in notebooks without ipywidgets

    axes = {"d0_ratio": _axis("d0_ratio", d0_ratio, ratio=True),
            "d1_ratio": _axis("d1_ratio", d1_ratio, ratio=True),
            "d2_ratio": _axis("d2_ratio", d2_ratio, ratio=True),
            "phi0": _axis("phi0", phi0, ratio=False)}
    cubic = k3_ratio is not None
    if cubic:  # an extra, last axis; without it the map is exactly what it was
        axes["k3_ratio"] = _axis("k3_ratio", k3_ratio, ratio=False)
    models = check_models(models, allowed=ANALYTIC)
    if reference not in REFERENCES:
        raise ValueError(f"reference must be one of {REFERENCES}, got {reference!r}")
    defaults = inspect.signature(error_map).parameters  # (the defaults, written once)
    given = [n for n, v in (("rtol", rtol), ("atol", atol), ("engine", engine))
             if v != defaults[n].default]
    if reference != "reference" and given:  # (they were ignored unsaid)
        raise ValueError(f"{', '.join(given)}: set the integrator of reference='reference', "
                         f"not the closed form reference={reference!r}")
    # a ValueError naming engine; "auto" resolved here, outside the compiled step
    engine = check_reference_options(0.0, 0.0, engine=engine)["engine"]
    if chunk_size is not None:
        chunk_size = _positive_int("chunk_size", chunk_size)
    samples_per_period = _positive_int("samples_per_period", samples_per_period, 2)
    try:
        periods = float(periods)
    except (TypeError, ValueError) as err:
        raise ValueError(f"periods must be a number > 0, got {periods!r}") from err
    if not (math.isfinite(periods) and periods > 0.0):
        raise ValueError(f"periods must be a finite number > 0, got {periods!r}")
    for name, tol in (("rtol", rtol), ("atol", atol)):
        if isinstance(tol, bool) or not (isinstance(tol, (int, float)) and math.isfinite(tol)
                                         and tol > 0):
            raise ValueError(f"{name} must be a number > 0, got {tol!r}")

    check_map_size({k: a.size for k, a in axes.items()}, len(models), periods,
                   samples_per_period)
    processes = check_processes(processes)
    timeout = check_timeout(timeout)
    cfg = _config(models, reference, periods, samples_per_period, rtol, atol, cubic, engine)
    n_samples = cfg.n_samples
    if processes is not None and processes > 1:
        if jax.distributed.is_initialized():
            raise ValueError(f"processes={processes}: this process is already one of a "
                             "jax.distributed run (its share is computed with processes=None)")

        checked = dict(axes, models=models, periods=periods,
                       samples_per_period=samples_per_period, chunk_size=chunk_size,
                       reference=reference, rtol=rtol, atol=atol, k3_ratio=axes.get("k3_ratio"),
                       engine=engine)
        return run_local(checked, processes, timeout=timeout, progress=progress)

    shape = tuple(a.size for a in axes.values())
    grid = np.stack([g.ravel() for g in np.meshgrid(*axes.values(), indexing="ij")], axis=-1)
    n_points = grid.shape[0]
    # points with long windows computed together (longest first): a vmapped step costs its
    # slowest point, so one point that never stops should not keep a whole step of points
    # that stopped long ago integrating (the metrics do not depend on the company a point keeps)
    estimate = _window_estimate(grid, periods)
    order = np.argsort(-estimate, kind="stable")
    grid = grid[order]

    devices = jax.local_devices()
    _, mesh = _compiled(cfg, tuple(d.id for d in devices))
    n_proc, proc = jax.process_count(), jax.process_index()
    # from the platform and its memory when not given; clipped to the grid and the memory
    chunk_size = choose_chunk(chunk_size, cfg, n_points, devices, n_proc)
    step = chunk_size * len(devices)
    # the few points whose windows are far longer than all others' (a motion that never
    # stops runs the whole window) go first, in steps of TAIL_CHUNK points: a vmapped loop
    # costs about the same per iteration for few points as for a step of them
    tail = _tail_count(estimate[order], step, TAIL_CHUNK * len(devices)) if n_proc == 1 else 0
    tail_grid, grid = grid[:tail], grid[tail:]
    n_main = n_points - tail
    n_steps = -(-n_main // step)
    per_proc = -(-n_steps // n_proc)
    my_steps = range(proc * per_proc, min((proc + 1) * per_proc, n_steps))

    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    rows_sharding = NamedSharding(mesh, P("points"))
    n_mod = len(models)
    out_metrics = np.full((per_proc * step, n_mod, len(METRICS)), np.nan)
    out_valid = np.zeros((per_proc * step, n_mod), dtype=bool)
    out_info = np.full((per_proc * step, 3), np.nan)

    bar = tqdm(total=len(my_steps), desc="error map: compiling", unit="chunk",
               disable=(not progress) or proc != 0)
    # compiled ahead of the first step (from the persistent cache when it has it), so the bar
    # says "compiling" meanwhile and its rate and ETA come from measured steps only
    executable = _executable(cfg, tuple(d.id for d in devices), step)
    tail_out = None
    if tail:
        tail_step = TAIL_CHUNK * len(devices)
        tail_exe = _executable(cfg, tuple(d.id for d in devices), tail_step)
        bar.set_description("error map: the longest windows")
        parts = [tail_exe(jax.device_put(tail_grid[i:i + tail_step], rows_sharding))
                 for i in range(0, tail, tail_step)]
        tail_out = [np.concatenate([np.asarray(p[j]) for p in parts]) for j in range(3)]
    bar.set_description("error map")
    bar.reset(total=len(my_steps))

    def launch(s):
        rows = grid[s * step:(s + 1) * step]
        if rows.shape[0] < step:  # pad the last step: same shapes, no recompilation
            rows = np.concatenate([rows, np.repeat(rows[:1], step - rows.shape[0], axis=0)])
        return executable(jax.device_put(rows, rows_sharding))

    try:
        pending = None
        for i, s in enumerate(my_steps):
            current = (i, launch(s))  # dispatched asynchronously: overlaps the host copy below
            if pending is not None:
                _store(pending, step, out_metrics, out_valid, out_info)
                bar.update(1)
            pending = current
        if pending is not None:
            _store(pending, step, out_metrics, out_valid, out_info)
            bar.update(1)
    finally:
        bar.close()

    if n_proc > 1:  # every process gets every share (waiting at most `timeout` for them)
        out_metrics, out_valid, out_info = (
            np.asarray(a).reshape((-1,) + a.shape[2:])
            for a in gather((out_metrics, out_valid, out_info), timeout=timeout))
    if tail_out is not None:
        out_metrics, out_valid, out_info = (np.concatenate([t, a[:n_main]]) for t, a in
                                            zip(tail_out, (out_metrics, out_valid, out_info),
                                                strict=True))
    inverse = np.argsort(order)
    out_metrics = out_metrics[:n_points][inverse].reshape(shape + (n_mod, len(METRICS)))
    out_valid = out_valid[:n_points][inverse].reshape(shape + (n_mod,))
    out_info = out_info[:n_points][inverse].reshape(shape + (3,))

    point_dims = tuple(axes)
    dims = ("model",) + point_dims
    data = {}
    for j, name in enumerate(METRICS):
        data[name] = (dims, np.moveaxis(out_metrics[..., j], -1, 0), _VARIABLE_ATTRS[name])
    data["valid"] = (dims, np.moveaxis(out_valid, -1, 0), _VARIABLE_ATTRS["valid"])
    data["reference_valid"] = (point_dims, out_info[..., 0] > 0.5,
                               _VARIABLE_ATTRS["reference_valid"])
    data["window"] = (point_dims, out_info[..., 1], _VARIABLE_ATTRS["window"])
    data["reference_halt_time"] = (point_dims, out_info[..., 2],
                                   _VARIABLE_ATTRS["reference_halt_time"])
    coords = {"model": ("model", list(models), _COORD_ATTRS["model"])}
    for name, values in axes.items():
        coords[name] = (name, values, _COORD_ATTRS[name])
    attrs = {
        "Conventions": "CF-1.10",
        "title": "dampax error map: analytic models against a reference",
        "source": f"dampax {__version__} (jax {jax.__version__})",
        "history": f"{_now()} dampax.error_map(d0_ratio=<{axes['d0_ratio'].size} values>, "
                   f"d1_ratio=<{axes['d1_ratio'].size}>, d2_ratio=<{axes['d2_ratio'].size}>, "
                   f"phi0=<{axes['phi0'].size}>, "
                   + (f"k3_ratio=<{axes['k3_ratio'].size}>, " if cubic else "")
                   + f"models={list(models)}, periods={periods:g}, "
                   f"samples_per_period={samples_per_period}, reference={reference!r})",
        "dampax_version": __version__,
        "models": ", ".join(models),
        "reference": reference,
        "reference_description": (
            ("DOP853 integration of eq. 3, swing by swing with exact stick-slip"
             + (" (one fused kernel)" if engine == "pallas" else "")
             if engine != "diffrax" else "diffrax Dopri8 integration of eq. 3, swing by swing "
             "with its events and exact stick-slip")
            + "; without damping the harmonic motion in closed form"
            if reference == "reference" else "exact Coulomb (+ viscous) half-swings (D = 0)"),
        "reference_engine": engine if reference == "reference" else "",
        "reference_rtol": float(rtol) if reference == "reference" else 0.0,
        "reference_atol": float(atol) if reference == "reference" else 0.0,
        "reference_max_swings": cfg.max_swings,
        "reference_segments": cfg.n_segments,
        "periods": periods,
        "samples_per_period": samples_per_period,
        "n_samples": n_samples,
        "energy_floor": ENERGY_FLOOR,
        "chunk_size": chunk_size,
        "devices": f"{len(devices)} x {devices[0].platform}, {n_proc} process(es)",
        "scaling": "dimensionless: w0 = 1, A0 = 1 (m = k = 1, x0 = cos phi0, v0 = -sin phi0); "
                   "the errors hold for every m, k, A0",
        "window": "the reference motion up to its halt, or until its energy falls below "
                  f"{ENERGY_FLOOR:g} E0 when it does not halt; at most `periods` periods",
    }
    import xarray as xr  # (here, not first: ``dampax errormap`` imports it beside the map)

    ds = xr.Dataset(data, coords=coords, attrs=attrs)
    for name in ds.coords:  # CF: coordinate variables carry no _FillValue (ds.to_netcdf(path))
        ds[name].encoding["_FillValue"] = None
    return ds


def _now() -> str:
    """The current UTC time, ISO 8601 to the second (for the netCDF ``history``)."""
    import datetime

    return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def _store(pending, step, out_metrics, out_valid, out_info):
    i, (metrics, valid, info) = pending
    sl = slice(i * step, (i + 1) * step)
    out_metrics[sl] = np.asarray(metrics)
    out_valid[sl] = np.asarray(valid)
    out_info[sl] = np.asarray(info)


# ----------------------------------------------------------------------------------------------
# helpers for the command line and the plots
