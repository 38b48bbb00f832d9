"""The reference engine as one fused kernel (issue 35 item 2): `jax.experimental.pallas`.

The XLA engine (`_engine`) is a `jax.lax.while_loop` vmapped over the trajectories: on a GPU
every iteration of that loop is several kernel launches over the whole batch (about 60 us per
iteration at 4,096 trajectories), so the batch waits on launches, not arithmetic. Here the whole
loop runs inside one kernel: each program holds :data:`BLOCK` trajectories in registers (one
GPU thread each, under Triton) and takes DOP853 steps until all of them halted, reached t_end,
failed or spent their budget. The numerics are the XLA engine's own functions, unchanged: the
step (`_stepping.rk_step`, `error_norm`, `step_factor`), the step's polynomial
(`_sampling.hermite_columns`), the turning point on it (`_events.turning_point_of`) and the
sticking test; what differs is only where results go:

- each accepted step's row is written to the row table at the trajectory's own row (one
  masked scatter store per column), the turning points likewise: the same table as the XLA
  engine's, so the solution's dense output (``sol.x(t)`` at any later times) is unchanged;
- the samples of ``solve(..., ts=ts)`` (sorted ts) are written inside the loop, as each
  accepted step passes them: the step's polynomial is evaluated at the next
  :data:`SAMPLES_PER_PASS` sample times from the trajectory's pointer, repeated until the
  pointer has passed the step's end. No table is searched or gathered afterwards.

The buffers arrive pre-filled (rows inf, turning points and samples NaN) and are aliased to
the outputs, so the kernel only writes what a trajectory produced. Where ts is not sorted the
samples come from the row table as in the XLA engine.

Selection: :func:`available` says whether the kernel runs natively (a CUDA GPU, where Triton
lowers it); ``engine="auto"`` (the default of ``solve_reference``) takes it there for the
reverse-mode adjoint after a one-time self-check against the XLA engine in the process
(:func:`self_check`), and the XLA engine everywhere else. ``engine="pallas"`` forces it; off a
GPU it runs in Pallas's interpreter (``interpret=True``: correct, slow; the tests use it).

Gradients: a custom VJP whose backward pass is the XLA engine's reverse mode at the same inputs
(the same steps, the same results to rounding), so ``jax.grad`` works; forward mode
(``adjoint="forward"``/``"direct"``) always runs the XLA engine.
"""

from __future__ import annotations

import functools
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np

try:  # Pallas ships with jax; guarded so that a build without it still imports dampax
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as plt
except ImportError:  # pragma: no cover - engine="pallas" then says so
    pl = plt = None

from .._models._solution import RESULTS, first_failure
from .._oscillator import Oscillator
from ._engine import DT0_W0, DTMAX_W0, domain_input
from ._events import turning_point_of
from ._sampling import WIDTH, hermite_columns, horner
from ._solution import FIELDS, ReferenceSolution, from_engine, mask_samples, sample_single
from ._stepping import error_norm, ode_args, rk_step, step_factor

#: trajectories per program (a power of two, as Triton's blocks must be): 4 warps of 32
BLOCK = 128
#: sample times evaluated per pass of the inner sampling loop (a power of two)
SAMPLES_PER_PASS = 16
# the per-trajectory inputs of the kernel, in order
_INPUTS = ("x0", "v0", "t_end", "w_hi", "w2", "fric", "bm", "dm", "k3m", "k3k", "xstat",
           "rest0", "s0")
# the per-trajectory scalar outputs: floats, then int32
_FLOATS = ("t", "x", "v", "t_halt", "x_halt")
_INTS = ("halted", "finished", "failed", "budget", "n_rows", "n_swings", "n_turns")


def available() -> bool:
    """Whether the kernel runs natively here: JAX's default backend is a CUDA GPU."""
    try:
        device = jax.devices()[0]
        return (pl is not None and jax.default_backend() == "gpu"
                and "cuda" in device.client.platform_version.lower())
    except Exception:  # noqa: BLE001 - no backend at all: the XLA engine
        return False


def prepare(osc, x0, v0, t_end):
    """The kernel's per-trajectory inputs (1-D arrays, all of one length) and the input checks.

    Returns:
        (inputs, checks, ok_in): ``inputs`` a dict over :data:`_INPUTS` (the domain's stand-in
        where the input is out of it, as the XLA engine's `domain_input`), ``checks`` and
        ``ok_in`` as `domain_input` gives them.
    """
    checks, ok_in, osc, x0, v0, t_end, w_hi = domain_input(osc, x0, v0, t_end)
    _, w2, fric, bm, dm, k3m = ode_args(osc, 0.0)
    rest0 = (v0 == 0.0) & osc.sticks(x0)
    inputs = dict(x0=x0, v0=v0, t_end=t_end, w_hi=w_hi, w2=w2, fric=fric, bm=bm, dm=dm,
                  k3m=k3m, k3k=osc.k3 / osc.k, xstat=osc.x_static,
                  rest0=jnp.where(rest0, 1.0, 0.0),
                  s0=jnp.where(v0 != 0.0, jnp.sign(v0), -jnp.sign(x0)))
    shape = jnp.shape(x0)
    return {k: jnp.broadcast_to(jnp.asarray(a, dtype=float), shape) for k, a in inputs.items()}, \
        checks, ok_in


def _initial(p):
    """The loop's state of a block of trajectories at t = 0 (as `_engine.integrate`'s)."""
    zero = jnp.zeros_like(p["x0"])
    rest0 = p["rest0"] > 0.5
    return dict(k=jnp.int32(0), t=zero, x=p["x0"], v=p["v0"], s=p["s0"],
                h=DT0_W0 / p["w_hi"], halted=rest0, t_halt=zero, x_halt=p["x0"],
                finished=jnp.zeros_like(rest0), failed=jnp.zeros_like(rest0),
                budget=jnp.zeros_like(rest0), n_rows=jnp.zeros(rest0.shape, jnp.int32),
                n_swings=jnp.where(rest0, 0, 1).astype(jnp.int32),
                n_turns=jnp.zeros(rest0.shape, jnp.int32),
                ptr=jnp.zeros(rest0.shape, jnp.int32))


def _any(flags):
    """Whether any lane's flag is set (a max over int32: Triton lowers no ``reduce_or``)."""
    return jnp.max(jnp.where(flags, 1, 0).astype(jnp.int32)) > 0


def _running(c):
    return ~(c["halted"] | c["finished"] | c["failed"] | c["budget"])


def _step(c, p, rtol, atol):
    """One DOP853 step of every trajectory of the block and what it decides (the XLA engine's
    arithmetic, `_engine.integrate`'s body, without its branches)."""
    t, x, v, s = c["t"], c["x"], c["v"], c["s"]
    args = (s, p["w2"], p["fric"], p["bm"], p["dm"], p["k3m"])
    remaining = p["t_end"] - t
    h = jnp.minimum(c["h"], remaining)
    x1, v1, err5, err3 = rk_step(x, v, h, args)
    err = error_norm(x, v, x1, v1, err5, err3, h, rtol, atol)
    finite = jnp.isfinite(x1) & jnp.isfinite(v1) & jnp.isfinite(err)
    accepted = finite & (err <= 1.0)
    crossed = accepted & (s * v1 <= 0.0)
    plain = accepted & ~crossed
    last = plain & (h >= remaining)
    h_next = jnp.minimum(h * step_factor(jnp.where(finite, err, jnp.inf)),
                         DTMAX_W0 / p["w_hi"])
    h_next = jnp.where(last, c["h"], h_next)
    tiny = ~accepted & (h_next <= 1e-13 * jnp.maximum(t, 1.0 / p["w_hi"]))
    cols = hermite_columns(t, t + h, x, v, x1, v1, args)
    t_sw, x_sw = turning_point_of(cols[2:], t, h, v, v1, crossed)
    stick = crossed & (jnp.abs(x_sw * (1.0 + p["k3k"] * (x_sw * x_sw))) <= p["xstat"])
    return dict(h=h, x1=x1, v1=v1, accepted=accepted, crossed=crossed, plain=plain, last=last,
                h_next=h_next, failed=(~finite & (h <= 0.0)) | tiny, cols=cols, t_sw=t_sw,
                x_sw=x_sw, stick=stick, reverse=crossed & ~stick)


def _next_state(c, d, run, p, rows, max_swings):
    """The state after the step ``d`` (lanes not running keep theirs)."""
    t, x, v, s = c["t"], c["x"], c["v"], c["s"]
    plain, crossed, last = d["plain"], d["crossed"], d["last"]
    full = d["accepted"] & (c["n_rows"] >= rows)
    new = dict(
        t=jnp.where(plain, jnp.where(last, p["t_end"], t + d["h"]),
                    jnp.where(crossed, d["t_sw"], t)),
        x=jnp.where(plain, d["x1"], jnp.where(crossed, d["x_sw"], x)),
        v=jnp.where(plain, d["v1"], jnp.where(crossed, 0.0, v)),
        s=jnp.where(d["reverse"], -jnp.sign(d["x_sw"]), s), h=d["h_next"],
        halted=c["halted"] | d["stick"],
        t_halt=jnp.where(d["stick"], d["t_sw"], c["t_halt"]),
        x_halt=jnp.where(d["stick"], d["x_sw"], c["x_halt"]),
        finished=c["finished"] | last, failed=c["failed"] | d["failed"],
        budget=c["budget"] | full | (d["reverse"] & (c["n_swings"] >= max_swings)),
        n_rows=c["n_rows"] + jnp.where(d["accepted"] & ~full, 1, 0),
        n_swings=c["n_swings"] + jnp.where(d["reverse"], 1, 0),
        n_turns=c["n_turns"] + jnp.where(crossed, 1, 0))
    out = {k: jnp.where(run, new[k], c[k]).astype(c[k].dtype) for k in new}
    return dict(out, k=c["k"] + 1, ptr=c["ptr"])


def _write_step(refs, c, d, run, rows, max_swings):
    """Store the step's row at the trajectory's next row and its turning point (masked scatter
    stores: only what the trajectory produced)."""
    lanes = jnp.arange(c["t"].shape[0], dtype=jnp.int32)
    store = run & d["accepted"] & (c["n_rows"] < rows)
    at_row = jnp.minimum(c["n_rows"], rows - 1)
    for j, col in enumerate(d["cols"]):
        col = jnp.broadcast_to(col, lanes.shape)
        _store(refs["rows"].at[lanes, at_row, jnp.full_like(lanes, j)], col, store)
    turn = run & d["crossed"] & (c["n_turns"] < max_swings)
    at_turn = jnp.minimum(c["n_turns"], max_swings - 1)
    for j, val in enumerate((d["t_sw"], d["x_sw"])):
        _store(refs["turns"].at[lanes, at_turn, jnp.full_like(lanes, j)], val, turn)
    return store


def _store(ref, value, mask):
    plt.store(ref, value, mask=mask)


def _load(ref):
    return plt.load(ref)


def _write_samples(refs, c, d, p, store):
    """x, v at the sample times inside the stored step, from its polynomial: passes of
    :data:`SAMPLES_PER_PASS` times from each trajectory's pointer until every pointer has
    passed its step's end (t_end included on the last step). Returns the pointers."""
    lanes = jnp.arange(c["t"].shape[0], dtype=jnp.int32)[:, None]
    window = jnp.arange(SAMPLES_PER_PASS, dtype=jnp.int32)[None, :]
    upper = jnp.where(d["crossed"], d["t_sw"], c["t"] + d["h"])[:, None]
    last, t_end = d["last"][:, None], p["t_end"][:, None]
    cols = [jnp.broadcast_to(col, c["t"].shape)[:, None] for col in d["cols"]]

    def inside(tv):
        return store[:, None] & ((tv < upper) | (last & (tv <= t_end)))

    def pending(ptr):
        return _any(inside(_load(refs["ts"].at[ptr[:, None]])))

    def one_pass(ptr):
        idx = ptr[:, None] + window
        tv = _load(refs["ts"].at[idx])
        ok = inside(tv)
        th = jnp.clip((tv - cols[0]) * cols[1], 0.0, 1.0)
        x, v = horner(cols, th, cols[1] == 0.0)
        lane_idx = jnp.broadcast_to(lanes, idx.shape)
        _store(refs["xs"].at[lane_idx, idx], x, ok)
        _store(refs["vs"].at[lane_idx, idx], v, ok)
        return ptr + jnp.sum(ok, axis=1, dtype=jnp.int32)

    return jax.lax.while_loop(pending, one_pass, c["ptr"])


def _kernel(*refs, names, rtol, atol, max_swings, rows, max_steps):
    """One block of trajectories: the whole integration loop (see the module docstring)."""
    refs = dict(zip(names, refs, strict=True))
    p = {k: refs[k][...] for k in _INPUTS}

    def cond(c):
        return _any(_running(c)) & (c["k"] < max_steps)

    def body(c):
        run = _running(c)
        d = _step(c, p, rtol, atol)
        store = _write_step(refs, c, d, run, rows, max_swings)
        new = _next_state(c, d, run, p, rows, max_swings)
        if "ts" in refs:
            new["ptr"] = _write_samples(refs, c, d, p, store)
        return new

    final = jax.lax.while_loop(cond, body, _initial(p))
    for k in _FLOATS:
        refs["out_" + k][...] = final[k]
    for k in _INTS:
        refs["out_" + k][...] = final[k].astype(jnp.int32)


def _padded_times(ts):
    """ts padded with inf to a power of two with room for one pass beyond its end."""
    n = ts.shape[0]
    n_pad = 1 << max(4, math.ceil(math.log2(n + SAMPLES_PER_PASS)))
    return jnp.concatenate([ts, jnp.full((n_pad - n,), jnp.inf, ts.dtype)])


def run_blocks(inputs, ts, *, rtol, atol, max_swings: int, rows: int, interpret: bool):
    """The kernel over 1-D per-trajectory ``inputs`` (from :func:`prepare`).

    Arguments:
        inputs: dict over :data:`_INPUTS` of arrays of one length B.
        ts: sorted sample times (n,), or None.
        rtol, atol, max_swings, rows: as `_engine.integrate`.
        interpret: run Pallas's interpreter (off a GPU).

    Returns:
        The dict of `_engine.integrate` (batched over B) without ``result`` and ``ok_in``,
        with ``xs``, ``vs`` (B, n) when ts is given (NaN where no step passed the sample).
    """
    size = inputs["x0"].shape[0]
    lanes = -(-size // BLOCK) * BLOCK
    stand_in = dict(x0=0.0, v0=0.0, t_end=1.0, rest0=1.0, s0=1.0, k3k=0.0, k3m=0.0)
    args = [jnp.concatenate([inputs[k], jnp.full((lanes - size,), stand_in.get(k, 1.0))])
            for k in _INPUTS]
    lane = pl.BlockSpec((BLOCK,), lambda i: (i,))
    names, specs = list(_INPUTS), [lane] * len(_INPUTS)
    buffers = {"rows": jnp.full((lanes, rows, WIDTH), jnp.inf),
               "turns": jnp.full((lanes, max_swings, 2), jnp.nan)}
    if ts is not None:
        tpad = _padded_times(ts)
        names.append("ts")
        specs.append(pl.BlockSpec(tpad.shape, lambda i: (0,)))
        args.append(tpad)
        buffers.update(xs=jnp.full((lanes, tpad.shape[0]), jnp.nan),
                       vs=jnp.full((lanes, tpad.shape[0]), jnp.nan))

    def block_of(a):
        return pl.BlockSpec((BLOCK,) + a.shape[1:], lambda i: (i,) + (0,) * (a.ndim - 1))

    first = len(args)
    names += [f"in_{k}" for k in buffers]
    specs += [block_of(a) for a in buffers.values()]
    args += list(buffers.values())
    outs = [jax.ShapeDtypeStruct((lanes,), jnp.float64) for _ in _FLOATS] + \
        [jax.ShapeDtypeStruct((lanes,), jnp.int32) for _ in _INTS] + \
        [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in buffers.values()]
    out_names = [f"out_{k}" for k in _FLOATS + _INTS] + list(buffers)
    kernel = functools.partial(_kernel, names=tuple(names + out_names), rtol=rtol, atol=atol,
                               max_swings=max_swings, rows=rows, max_steps=2 * rows + 64)
    res = pl.pallas_call(
        kernel, out_shape=outs, grid=(lanes // BLOCK,), in_specs=specs,
        out_specs=[lane] * (len(_FLOATS) + len(_INTS)) + [block_of(a) for a in buffers.values()],
        input_output_aliases={first + j: len(_FLOATS) + len(_INTS) + j
                              for j in range(len(buffers))},
        # Triton, one thread per trajectory (BLOCK / 32 warps); not Mosaic GPU, whose
        # blocks live in shared memory (a row table of 128 trajectories does not fit)
        compiler_params=plt.CompilerParams(num_warps=BLOCK // 32, num_stages=1),
        interpret=interpret)(*args)
    out = {k: a[:size] for k, a in zip(out_names, res, strict=True)}
    final = {k: out["out_" + k] for k in _FLOATS}
    final.update({k: out["out_" + k] != 0 for k in _INTS[:4]})
    final.update({k: out["out_" + k] for k in _INTS[4:]})
    final.update(rows=out["rows"], turns=out["turns"])
    if ts is not None:
        final.update(xs=out["xs"][:, : ts.shape[0]], vs=out["vs"][:, : ts.shape[0]])
    return final


def solve_flat(osc, x0, v0, t_end, ts, *, rtol, atol, max_swings: int, rows: int,
               interpret: bool) -> ReferenceSolution:
    """`_solve._solve_single` of a flat batch (every input of shape (B,)) by the kernel: the
    same `ReferenceSolution`, its samples from inside the loop where ts is sorted (from the
    row table otherwise)."""
    inputs, checks, ok_in = prepare(osc, x0, v0, t_end)
    out = run_blocks(inputs, ts, rtol=rtol, atol=atol, max_swings=max_swings, rows=rows,
                     interpret=interpret)
    out_of_steps = _running(out)  # the loop's iteration cap
    out["result"] = first_failure(*checks, (out["failed"], RESULTS.solver_failed),
                                  (out["budget"] | out_of_steps, RESULTS.max_swings_reached))
    out["ok_in"] = ok_in
    sol = from_engine(out, osc, x0, v0, t_end)
    if ts is None:
        return sol

    def in_loop():
        return jax.vmap(lambda one, x, v: mask_samples(one, ts, x, v))(sol, out["xs"], out["vs"])

    def from_rows():
        return jax.vmap(lambda one: sample_single(one, ts))(sol)

    ordered = jnp.all(ts[1:] >= ts[:-1]) if ts.shape[0] > 1 else jnp.array(True)
    xs, vs = jax.lax.cond(ordered, in_loop, from_rows)
    # ts itself (shared by the batch) is attached by the caller, as after the XLA engine's vmap
    return ReferenceSolution(**{f: getattr(sol, f) for f in FIELDS}, xs=xs, vs=vs)


_CHECK: dict[str, bool] = {}


def self_check(solve_jit) -> bool:
    """Whether the native kernel reproduces the XLA engine here (once per process, cached):
    a small batch (every damping term, a cubic spring, a halt, a start at rest) solved by both
    through ``solve_jit`` (`_solve._solve_jit`), samples within 1e-9 of the amplitude and the
    same halts. Where the kernel does not lower or does not agree, a warning says why and
    ``engine="auto"`` keeps the XLA engine."""
    if "ok" not in _CHECK:
        osc = Oscillator(m=1.0, k=jnp.array([25.0, 10.0, 30.0, 25.0]),
                         mu=jnp.array([0.02, 0.0, 0.05, 0.05]), b=jnp.array([0.0, 0.1, 0.2, 0.0]),
                         D=jnp.array([0.0, 0.3, 0.3, 0.0]), k3=jnp.array([0.0, 0.0, 40.0, 0.0]))
        x0, v0 = jnp.array([1.0, -0.3, 0.4, 0.01]), jnp.array([0.0, 1.0, -1.5, 0.0])
        ts = jnp.linspace(0.0, 4.0, 101)
        kw = dict(rtol=1e-10, atol=1e-12, max_swings=32, rows=32 * 24, adjoint="recursive")
        try:
            ours = solve_jit(osc, x0, v0, jnp.full(4, 4.0), ts, engine="pallas", **kw)
            theirs = solve_jit(osc, x0, v0, jnp.full(4, 4.0), ts, engine="dampax", **kw)
            worst = float(np.max(np.abs(np.asarray(ours.xs) - np.asarray(theirs.xs))))
            same = bool(np.array_equal(np.asarray(ours.halted), np.asarray(theirs.halted)))
            why = "" if worst <= 1e-9 and same else (
                f"its samples differ from the XLA engine's by {worst:.3g} (halts agree: {same})")
        except Exception as err:  # noqa: BLE001 - any failure to lower or run: keep XLA
            why = f"it does not run here ({type(err).__name__}: {err})"
        _CHECK["ok"] = not why
        if why:
            warnings.warn(f"dampax: the fused GPU kernel of the reference is not used: {why}; "
                          "the XLA engine runs instead", RuntimeWarning, stacklevel=3)
    return _CHECK["ok"]
