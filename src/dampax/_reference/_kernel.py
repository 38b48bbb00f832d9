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

Lanes that do not wait (issue 35 item 1, on the GPU): a program's lanes run until the last of
them is done, so the batch is sorted by an estimate of each trajectory's steps
(:func:`work_estimate`, from the amplitude equation: it correlates 0.989 with the steps) and a
program takes neighbours in that order, the longest first; and where the batch exceeds the
lanes a GPU holds at once (:data:`RESIDENT`), each lane keeps a queue of trajectories and
starts its next one as soon as its current one ends (its outcome written, its state reset
from the next one's inputs), instead of waiting for a whole program to finish. On the steps
of 16,384 random trajectories (benchmarks/README.md), the lane-iterations per useful one fall
from 1.94 (programs of 128 lanes in the given order) to 1.14 sorted, 1.08 sorted with queues
of 4. Nothing is permuted: the lanes read their trajectory's index from the order and write
its results at that index.

Selection: :func:`available` says whether the kernel runs natively (a CUDA GPU, where Triton
lowers it); ``engine="auto"`` (the default of ``solve_reference``) takes it there for a solve that
is not differentiated (derivatives of every mode stay with the XLA engine), after a one-time
self-check against the XLA engine in the process
(:func:`self_check`), and the XLA engine everywhere else. ``engine="pallas"`` forces it; off a
GPU it runs in Pallas's interpreter (``interpret=True``: correct, slow; the tests use it).

Under ``jax.vmap`` (an error map's points, each a scalar solve) the mapped trajectories join
the kernel's batch (:func:`packed`, a custom vmap rule): one launch with every lane at work,
where Pallas's own batching would give each point a program of :data:`BLOCK` lanes with one
at work.

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
except Exception:  # noqa: BLE001  # pragma: no cover - engine="pallas" then says so
    pl = plt = None

from .._models._solution import RESULTS, first_failure
from .._oscillator import Oscillator, held
from ._engine import DT0_W0, DTMAX_W0, decide, domain_input, next_state
from ._events import turning_point_of
from ._sampling import WIDTH, hermite_columns, horner
from ._solution import ReferenceSolution, from_engine, mask_samples, sample_single, with_samples
from ._stepping import error_norm, ode_args, rk_step

#: lanes per program (a power of two, as Triton's blocks must be): one warp. On an H200
#: (benchmarks/gpu_kernel.py) programs of 32 lanes took 11.2 ms for 131,072 trajectories where
#: 128 took 12.7-13.4 ms (both with the sampling below), 1.92 against 2.05-2.16 ms at 4,096
BLOCK = 32
#: lanes a GPU holds at once with this kernel's registers (an estimate for an H100: about 256
#: threads per SM of 132 at ~250 float64 registers each; ncu on an H200 counted 168 registers a
#: thread, 384 threads per SM); a batch beyond it is queued
RESIDENT = 32768
#: the longest queue of trajectories per lane
MAX_DEPTH = 16
#: sample times evaluated per pass of the inner sampling loop (a power of two): on an H200 a
#: pass of 16 took 2.8-3.2x the kernel's time of a pass of 2 or 4 at 131,072 trajectories x
#: 1,000 samples (36 ms against 11.2-12.7 ms; the (lanes x 16) tensors of a pass spill to
#: local memory: 168 registers a thread, 3 kB of stack), 8 took 1.9x, 1 took 1.1x
SAMPLES_PER_PASS = 2
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
    return dict(k=jnp.zeros(rest0.shape, jnp.int32), t=zero, x=p["x0"], v=p["v0"], s=p["s0"],
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
    `_engine.decide`, with the step's polynomial and turning point computed directly: a
    kernel has no use for the XLA engine's branches)."""
    t, x, v = c["t"], c["x"], c["v"]
    args = (c["s"], p["w2"], p["fric"], p["bm"], p["dm"], p["k3m"])
    remaining = p["t_end"] - t
    h = jnp.minimum(c["h"], remaining)
    x1, v1, err5, err3 = rk_step(x, v, h, args)
    err = error_norm(x, v, x1, v1, err5, err3, h, rtol, atol)
    d = decide(c, h, remaining, x1, v1, err, DTMAX_W0 / p["w_hi"], p["w_hi"])
    d["cols"] = hermite_columns(t, t + h, x, v, x1, v1, args)
    d["t_sw"], d["x_sw"] = turning_point_of(d["cols"][2:], t, h, v, v1, d["crossed"])
    d["stick"] = d["crossed"] & held(d["x_sw"], p["k3k"], p["xstat"])
    d["reverse"] = d["crossed"] & ~d["stick"]
    return d


def _next_state(c, d, run, p, rows, max_swings):
    """The state after the step ``d`` (`_engine.next_state`; lanes not running keep theirs,
    and their count of steps ``k``)."""
    new = next_state(c, d, p["t_end"], rows, max_swings)
    out = {k: jnp.where(run, new[k], c[k]).astype(c[k].dtype) for k in new}
    return dict(out, k=c["k"] + jnp.where(run, 1, 0).astype(jnp.int32), ptr=c["ptr"])


def _write_step(refs, cur, c, d, run, rows, max_swings, keep_rows=True):
    """Store the step's row at the trajectory's next row and its turning point (masked scatter
    stores at each lane's current trajectory ``cur``: only what it produced; no row where
    ``keep_rows`` is False, when only the samples are read)."""
    store = run & d["accepted"] & (c["n_rows"] < rows)
    # 64-bit indices: the row table of a large batch has more than 2^31 elements
    cur = cur.astype(jnp.int64)
    at_row = jnp.minimum(c["n_rows"], rows - 1).astype(jnp.int64)
    for j, col in enumerate(d["cols"] if keep_rows else ()):
        col = jnp.broadcast_to(col, cur.shape)
        _store(refs["rows"].at[cur, at_row, jnp.full_like(cur, j)], col, store)
    turn = run & d["crossed"] & (c["n_turns"] < max_swings)
    at_turn = jnp.minimum(c["n_turns"], max_swings - 1).astype(jnp.int64)
    for j, val in enumerate((d["t_sw"], d["x_sw"])):
        _store(refs["turns"].at[cur, at_turn, jnp.full_like(cur, j)], val, turn)
    return store


def _store(ref, value, mask):
    plt.store(ref, value, mask=mask)


def _load(ref):
    return plt.load(ref)


def _write_samples(refs, cur, c, d, p, store, per_pass):
    """x, v at the sample times inside the stored step, from its polynomial: passes of
    ``per_pass`` (:data:`SAMPLES_PER_PASS`) times from each trajectory's pointer until every
    pointer has passed its step's end (t_end included on the last step). Returns the
    pointers."""
    window = jnp.arange(per_pass, dtype=jnp.int32)[None, :]
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
        at = (jnp.broadcast_to(cur[:, None], idx.shape).astype(jnp.int64),
              idx.astype(jnp.int64))  # 64-bit: a large batch's samples pass 2^31
        _store(refs["xs"].at[at], x, ok)
        _store(refs["vs"].at[at], v, ok)
        return ptr + jnp.sum(ok, axis=1, dtype=jnp.int32)

    return jax.lax.while_loop(pending, one_pass, c["ptr"])


def _kernel(*refs, names, rtol, atol, max_swings, rows, max_steps, block, depth, keep_rows,
            per_pass):
    """One program: ``block`` lanes, each integrating its queue of ``depth`` trajectories one
    after the other (program i, lane j, queue position q: the trajectory ``order[i block depth
    + q block + j]``); a lane whose trajectory ends writes its outcome and starts its next one
    in the same iteration (see the module docstring)."""
    refs = dict(zip(names, refs, strict=True))
    lane = jnp.arange(block, dtype=jnp.int32)
    first = pl.program_id(0) * (block * depth)

    def at(q):  # the trajectory of each lane at queue position q: the order's entry
        return _load(refs["order"].at[first + jnp.minimum(q, depth - 1) * block + lane])

    def start(cur):
        p = {k: _load(refs[k].at[cur]) for k in _INPUTS}
        return p, _initial(p)

    def live(c):
        return _running(c) & (c["k"] < max_steps)

    def cond(state):
        return _any(state["q"] < depth)

    def body(state):
        q, p, c, cur = state["q"], state["p"], state["c"], state["cur"]
        run = live(c) & (q < depth)
        d = _step(c, p, rtol, atol)
        store = _write_step(refs, cur, c, d, run, rows, max_swings, keep_rows)
        new = _next_state(c, d, run, p, rows, max_swings)
        if "ts" in refs:
            new["ptr"] = _write_samples(refs, cur, c, d, p, store, per_pass)
        ended = (q < depth) & ~live(new)
        for k in _FLOATS + _INTS:
            _store(refs["out_" + k].at[cur], new[k].astype(refs["out_" + k].dtype), ended)
        q = q + jnp.where(ended, 1, 0).astype(jnp.int32)
        nxt = jnp.where(ended, at(q), cur)
        p_next, c_next = start(nxt)
        return dict(q=q, cur=nxt, p={k: jnp.where(ended, p_next[k], p[k]) for k in p},
                    c={k: jnp.where(ended, c_next[k], new[k]) for k in new})

    q0 = jnp.zeros(block, jnp.int32)
    p0, c0 = start(at(q0))
    jax.lax.while_loop(cond, body, dict(q=q0, cur=at(q0), p=p0, c=c0))


def _padded_times(ts, per_pass: int):
    """ts padded with inf to a power of two with room for one pass of ``per_pass`` beyond its
    end."""
    n = ts.shape[0]
    n_pad = 1 << max(4, math.ceil(math.log2(n + per_pass)))
    return jnp.concatenate([ts, jnp.full((n_pad - n,), jnp.inf, ts.dtype)])


def work_estimate(p):
    """The steps each trajectory will take, up to a factor: its half-swings before the halt or
    t_end, min(t_end, T) w_hi / pi, T the halt time of the amplitude equation dA/dt =
    -(d0 + d1 A + d2 A^2) (eq. 21 with the constants of eq. 3: d0 = 2 mu g / (pi w0),
    d1 = b / 2m, d2 = 4 D w0 / (3 pi m)) from A0 down to the sticking amplitude mu g / w0^2,
    by the trapezoid rule on 17 log-spaced amplitudes. It correlates 0.989 with the steps
    taken on benchmarks/peer_race.py's problem; the kernel sorts the batch by it, so that
    the lanes of a program take about as long (benchmarks/README.md)."""
    w = jnp.sqrt(p["w2"])
    a0 = jnp.sqrt(p["x0"] ** 2 + (p["v0"] / w) ** 2)
    d0, d1, d2 = 2.0 * p["fric"] / (math.pi * w), 0.5 * p["bm"], 4.0 * p["dm"] * w / (3 * math.pi)
    low = jnp.maximum(p["fric"] / p["w2"], 1e-6 * a0)
    moving = (a0 > low) & (low > 0.0)
    a0, low = jnp.where(moving, a0, 1.0), jnp.where(moving, low, 0.5)
    amp = low * (a0 / low) ** jnp.linspace(0.0, 1.0, 17)[:, None]
    rate = amp / jnp.maximum(d0 + d1 * amp + d2 * amp * amp, 1e-300)
    t_halt = jnp.sum(0.5 * (rate[1:] + rate[:-1]), axis=0) * jnp.log(a0 / low) / 16.0
    span = jnp.where(moving, jnp.minimum(p["t_end"], t_halt), 0.0)
    return jax.lax.stop_gradient(jnp.nan_to_num(span * p["w_hi"] / math.pi))


def queues(size: int) -> tuple[int, int]:
    """(lanes per program, trajectories per lane) for a batch of ``size``: :data:`BLOCK` lanes,
    and queues long enough that the batch fits :data:`RESIDENT` lanes (at most
    :data:`MAX_DEPTH`)."""
    return BLOCK, max(1, min(MAX_DEPTH, -(-size // RESIDENT)))


def _buffers(n_pad, ts, rows, max_swings, keep_rows=True):
    """The pre-filled buffers the kernel writes into (aliased to its outputs; the row table one
    row long where ``keep_rows`` is False)."""
    out = {"rows": jnp.full((n_pad, rows if keep_rows else 1, WIDTH), jnp.inf),
           "turns": jnp.full((n_pad, max_swings, 2), jnp.nan)}
    if ts is not None:
        out.update(xs=jnp.full((n_pad, ts.shape[0]), jnp.nan),
                   vs=jnp.full((n_pad, ts.shape[0]), jnp.nan))
    return out


def run_blocks(inputs, ts, *, rtol, atol, max_swings: int, rows: int, interpret: bool,
               block: int | None = None, depth: int | None = None, keep_rows: bool = True,
               samples_per_pass: int = SAMPLES_PER_PASS):
    """The kernel over 1-D per-trajectory ``inputs`` (from :func:`prepare`).

    Arguments:
        inputs: dict over :data:`_INPUTS` of arrays of one length B.
        ts: sorted sample times (n,), or None.
        rtol, atol, max_swings, rows: as `_engine.integrate`.
        interpret: run Pallas's interpreter (off a GPU).
        block, depth: lanes per program and trajectories per lane (default :func:`queues`).
        keep_rows: write the row table (the dense output); False writes the samples alone
            (``rows`` then comes back one row long, inf).
        samples_per_pass: sample times evaluated per pass of the sampling loop
            (:data:`SAMPLES_PER_PASS`; the same samples for any value, benchmarks/gpu_kernel.py
            sweeps it).

    Returns:
        The dict of `_engine.integrate` (batched over B) without ``result`` and ``ok_in``,
        with ``xs``, ``vs`` (B, n) when ts is given (NaN where no step passed the sample).
    """
    size = inputs["x0"].shape[0]
    default = queues(size)
    block, depth = block or default[0], depth or default[1]
    per = block * depth
    n_pad = -(-size // per) * per
    stand_in = dict(x0=0.0, v0=0.0, t_end=1.0, rest0=1.0, s0=1.0, k3k=0.0, k3m=0.0)
    args = {k: jnp.concatenate([inputs[k], jnp.full((n_pad - size,), stand_in.get(k, 1.0))])
            for k in _INPUTS}
    # the longest trajectories first, neighbours in work side by side (`work_estimate`)
    args["order"] = jnp.argsort(-work_estimate(args)).astype(jnp.int32)
    if ts is not None:
        args["ts"] = _padded_times(ts, samples_per_pass)
    buffers = _buffers(n_pad, None if ts is None else args["ts"], rows, max_swings, keep_rows)
    args.update({f"in_{k}": a for k, a in buffers.items()})

    def spec(a):  # every program sees whole arrays: its trajectories are the order's
        return pl.BlockSpec(a.shape, lambda i: (0,) * a.ndim)

    outs = [jax.ShapeDtypeStruct((n_pad,), jnp.float64 if k in _FLOATS else jnp.int32)
            for k in _FLOATS + _INTS] + \
        [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in buffers.values()]
    out_names = [f"out_{k}" for k in _FLOATS + _INTS] + list(buffers)
    kernel = functools.partial(_kernel, names=tuple(args) + tuple(out_names), rtol=rtol,
                               atol=atol, max_swings=max_swings, rows=rows,
                               max_steps=2 * rows + 64, block=block, depth=depth,
                               keep_rows=keep_rows, per_pass=samples_per_pass)
    first = len(args) - len(buffers)
    res = pl.pallas_call(
        kernel, out_shape=outs, grid=(n_pad // per,),
        in_specs=[spec(a) for a in args.values()],
        out_specs=[spec(o) for o in outs],
        input_output_aliases={first + j: len(_FLOATS) + len(_INTS) + j
                              for j in range(len(buffers))},
        # Triton, one thread per lane (block / 32 warps); not Mosaic GPU, whose blocks live
        # in shared memory (the row table of a program's trajectories does not fit)
        compiler_params=plt.CompilerParams(num_warps=max(1, block // 32), num_stages=1),
        interpret=interpret)(*args.values())
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
    return with_samples(sol, None, xs, vs)


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


def packed(**opts):
    """:func:`solve_flat` with ``opts``, such that under ``jax.vmap`` the mapped trajectories
    join the kernel's batch (one launch, every lane a trajectory) instead of Pallas's own
    batching, which would give each mapped element a program of its own (a vmapped scalar
    solve, as in an error map's points: 1 lane of :data:`BLOCK` at work). Where the sample
    times are themselves mapped, Pallas's batching runs (the kernel shares one ts per launch)."""

    @jax.custom_batching.custom_vmap
    def run(osc, x0, v0, t_end, ts):
        return solve_flat(osc, x0, v0, t_end, ts, **opts)

    @run.def_vmap
    def _joined(axis_size, in_batched, osc, x0, v0, t_end, ts):
        *batched, ts_batched = in_batched
        if ts is not None and ts_batched:
            axes = jax.tree_util.tree_map(lambda b: 0 if b else None, tuple(in_batched))
            out = jax.vmap(lambda *a: solve_flat(*a, **opts), in_axes=axes)(
                osc, x0, v0, t_end, ts)
            return out, jax.tree_util.tree_map(lambda _: True, out)
        size = x0.shape[-1]

        def join(a, b):
            a = a if b else jnp.broadcast_to(a, (axis_size,) + jnp.shape(a))
            return jnp.broadcast_to(a, (axis_size, size)).reshape(axis_size * size)

        args = jax.tree_util.tree_map(join, (osc, x0, v0, t_end), tuple(batched))
        out = jax.tree_util.tree_map(lambda a: a.reshape((axis_size, size) + a.shape[1:]),
                                     run(*args, ts))
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return run
