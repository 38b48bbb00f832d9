"""Global starts (issue 11, item 2): a batch of jittered starts optimised by one compiled,
vmapped program (:data:`BATCH_LANES` starts per call).

The first start is the turning-point guess of ``_guess`` (the amplitude lost per swing
regressed on the Coulomb, viscous and quadratic columns of eq. 21, dA/dt = -(d0 + d1 A +
d2 A^2), by non-negative least squares). The others multiply each free damping constant by
exp(1.5 z) (z standard normal: a spread of a factor 4.5 per sigma, in log-parameters), w0 by
1 + 0.003 z and the initial amplitude by exp(0.1 z). The batch runs on the trace thinned to one
of the lengths :data:`BATCH_SAMPLES` (every s-th sample, at least :data:`PER_PERIOD` per
period; the shortest length that holds them, else the first samples of the longest: the batch
then sees the first part of the decay), padded to that length, so two compiled functions serve
every trace, with at most :data:`BATCH_STEPS` optimizer steps per start; the best start is
then polished on the whole trace by the caller. The report says how many starts reached the
best cost (within :data:`REACHED_RTOL`) and the spread of the costs.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import jax
import numpy as np

from .._cache import call_cached_tree, prepare_cached_tree
from ._core import FIT_RESULTS, CoreOptions, Tuning, core, program_consts
from ._params import PARAMS, TraceParams, host_arrays

#: samples of the thinned trace of the batch (its padded length): the smallest of these that
#: keeps PER_PERIOD samples per period of the whole trace, else the largest (cut to the first
#: part of the decay). 256 holds the papers' regime of issue 36 (3,000 samples, 2-15 periods:
#: 12-125 per period); the batch's time follows its length (32 starts of 64 steps: 0.42 s CPU
#: at 1,024 samples, 0.14-0.19 s at 256; benchmarks/README.md, issue 36 fourth session), and
#: a long record (spring run 1: 165 periods) keeps 1,024 as before
BATCH_SAMPLES = (256, 1024)
#: fewest samples per period kept by the thinning (else the batch covers the trace's start)
PER_PERIOD = 10
#: step budget of each start (the best is polished on the whole trace afterwards)
BATCH_STEPS = 64
#: a start "reached" the best optimum when its cost is within this relative distance
REACHED_RTOL = 1e-4
#: starts per call of the compiled batch: a batch of n starts is ceil(n / BATCH_LANES) calls of
#: one program (the fit's 32 starts and the 8 of a test at the bound shared none before: two
#: programs, 3.3 s each of a cold fit's compiling; issue 36). A vmapped loop runs as long as
#: its slowest lane, so smaller calls cost no more in all
BATCH_LANES = 8


@dataclass(frozen=True)
class Starts:
    """What the batch of starts found.

    Attributes:
        n: number of starts.
        reached: how many reached the best cost (within ``REACHED_RTOL``).
        costs: the final cost 0.5 sum r^2 of every start on the thinned trace (data units;
            NaN where the optimizer failed), in the order of the starts.
        best: index of the best start (0 is the turning-point guess).
        stride: every stride-th sample was used.
        params: the best start's optimum (physical), the start of the polishing fit.
    """

    n: int
    reached: int
    costs: np.ndarray
    best: int
    stride: int
    params: TraceParams

    def summary(self) -> str:
        """One line for the report."""
        c = self.costs[np.isfinite(self.costs)]
        spread = (f"costs best {c.min():.4g}, median {np.median(c):.4g}, worst {c.max():.4g}"
                  if c.size else "no finite cost")
        thin = f", 1 sample in {self.stride}" if self.stride > 1 else ""
        return (f"{self.reached} of {self.n} jittered starts reached the best optimum "
                f"({spread}{thin})")

    def to_dict(self) -> dict:
        return {"n": self.n, "reached": self.reached, "best": self.best, "stride": self.stride,
                "costs": [float(c) if math.isfinite(c) else None for c in self.costs]}


def jittered(p0: TraceParams, free, n: int, *, seed: int = 0, fit_omega0: bool = True,
             w0_spread: float = 0.003):
    """``n`` starts around p0 (the first one is p0), as a (n, 7) array in the layout PARAMS.

    w0 is multiplied by 1 + w0_spread z (exp(w0_spread z) above 0.003: a trace with few
    turning points fixes its frequency to a few per cent only)."""
    rng = np.random.default_rng(seed)
    base = np.asarray(p0, dtype=float)
    P = np.tile(base, (n, 1))
    if n <= 1:
        return P
    z = rng.standard_normal((n - 1, len(PARAMS)))
    for name in free:
        i = PARAMS.index(name)
        P[1:, i] = base[i] * np.exp(1.5 * z[:, i])
    if fit_omega0:
        P[1:, 3] = base[3] * (1.0 + 0.003 * z[:, 3] if w0_spread <= 0.003 else
                              np.exp(w0_spread * z[:, 3]))
    amp = np.exp(0.1 * z[:, 5])
    P[1:, 5] *= amp
    P[1:, 6] *= amp
    return P


@functools.partial(jax.jit, static_argnames=("options",))
def _batch(t, x, weight, p0s, vary, consts, f_scale, options: CoreOptions):
    """The fits of the starts ``p0s``: (chisqr, code, params) of each (what a batch keeps;
    XLA then drops the statistics that a single fit computes)."""
    def one(p):
        out = core(t, x, weight, p, vary, consts, Tuning(f_scale), options=options)
        return out.chisqr, out.code, out.params

    return jax.vmap(one)(p0s)


def thin(t: np.ndarray, x: np.ndarray, omega: float):
    """(t, x, weight, stride): every stride-th sample (at least PER_PERIOD per period), padded
    with weight 0 to the first length of BATCH_SAMPLES that holds them (else cut to the last)."""
    n = t.size
    dt = float(np.median(np.diff(t)))
    per_period = 2.0 * math.pi / omega / dt
    for size in BATCH_SAMPLES:
        stride = max(1, math.ceil(n / size))
        stride = max(1, min(stride, int(per_period // PER_PERIOD))) if n > size else 1
        if math.ceil(n / stride) <= size:
            break
    td, xd = t[::stride], x[::stride]
    if td.size > size:  # too few samples per period to thin further: cut
        td, xd = td[:size], xd[:size]
    m = td.size
    tp, xp, wt = np.full(size, td[-1]), np.full(size, xd[-1]), np.zeros(size)
    tp[:m], xp[:m], wt[:m] = td, xd, 1.0
    return tp, xp, wt, stride


class _Program(NamedTuple):
    """The batch's kept program for a problem: ``call(key, fn, *head, p0s, *tail)``."""

    key: list
    fn: Callable
    head: tuple
    tail: tuple
    stride: int


def _program(problem, model: str, f_scale: float, vary, opts) -> _Program:
    """The batch's program and its fixed arguments: the thinned trace, the mask, the
    constants and the soft_l1 scale."""
    s = problem.settings
    tp, xp, wt, stride = thin(np.asarray(problem.data.t), np.asarray(problem.data.x),
                              problem.data.analysis.omega)
    static = dict(model=model, optimizer=s.optimizer,
                  max_steps=min(problem.steps, BATCH_STEPS), rtol=float(s.rtol),
                  atol=float(s.atol), opts=opts)
    return _Program(sorted(static.items()),
                    functools.partial(_batch, options=CoreOptions(**static)),
                    (np.asarray(tp), np.asarray(xp), np.asarray(wt)),
                    (host_arrays(vary, bool), host_arrays(program_consts(problem.consts, model)),
                     np.asarray(f_scale, dtype=float)), stride)


def _lanes(P: np.ndarray):
    """The batch's parameter arrays of a block of at most BATCH_LANES starts (the spare lanes
    repeat its first start)."""
    block = np.concatenate([P, np.tile(P[:1], (max(BATCH_LANES - len(P), 0), 1))])
    return TraceParams(*(np.ascontiguousarray(block[:, i], dtype=float)
                         for i in range(P.shape[1])))


def prepare_starts(problem, guess: TraceParams, model: str) -> None:
    """Start compiling :func:`run_starts`' program for ``problem`` (the linear loss, nothing
    held) in the background (``_cache.prepare_cached_tree``)."""
    prog = _program(problem, model, math.inf, problem.vary, None)
    P = np.asarray(guess, dtype=float)[None, :]
    prepare_cached_tree("fit-starts", prog.key, prog.fn, *prog.head, _lanes(P), *prog.tail)


def run_starts(problem, guess: TraceParams, model: str, f_scale: float, *, seed: int,
               held: str | None = None, extra=(), opts=None) -> Starts:
    """Optimise ``problem``'s global starts (``settings.starts`` of them) jittered around
    ``guess`` in one vmapped call on the thinned trace; returns :class:`Starts` (the best
    optimum is the caller's next start).

    Arguments:
        problem: the prepared problem (``_problem.Problem``: its window, mask, constants and
            optimizer settings).
        guess: the centre of the jitter (held parameters keep its values).
        model, f_scale: the fit model and the soft_l1 scale (inf: the linear loss).
        seed: the jitter's seed.
        held: a parameter held at ``guess``'s value (a profile's batch), or None.
        extra: further starts (TraceParams) put in place of the last jittered ones (the
            ansatz's optimum for the reference model).
        opts: the integrating model's options (static; None for the ansatz).
    """
    s, an = problem.settings, problem.data.analysis
    free = tuple(f for f in s.free if f != held)
    vary = problem.vary if held is None else problem.vary._replace(**{held: False})
    n = int(s.starts)
    P = jittered(guess, free, n, seed=seed, fit_omega0=problem.fit_omega0,
                 w0_spread=an.omega_spread)
    for j, p in enumerate(extra):
        P[n - 1 - j] = np.asarray(p, dtype=float)
    prog = _program(problem, model, f_scale, vary, opts)
    stride = prog.stride
    chisqr, codes, rows = [], [], []
    for lo in range(0, n, BATCH_LANES):
        # the compiled batch is kept: a repeated fit, also in a new process, does not trace it
        out = call_cached_tree("fit-starts", prog.key, prog.fn, *prog.head,
                               _lanes(P[lo:lo + BATCH_LANES]), *prog.tail)
        chisqr.append(np.asarray(out[0], dtype=float))
        codes.append(np.asarray(out[1]._value))
        rows.append(np.stack([np.asarray(v, dtype=float) for v in out[2]], axis=1))
    costs = 0.5 * np.concatenate(chisqr)[:n]
    ok = np.concatenate(codes)[:n] == FIT_RESULTS.successful._value
    params = np.concatenate(rows)[:n]
    finite = np.isfinite(costs) & np.all(np.isfinite(params), axis=1)
    costs = np.where(finite, costs, np.nan)
    # a converged start is preferred (its optimum is a stationary point, the others ran out
    # of their step budget on the way), unless one that did not converge costs less than
    # half as much (rms 1.4 times lower): the converged ones stopped at a stationary point
    # far above it (a strongly damped trace: the block halting early, a flat plateau)
    pick = np.where(finite & ok, costs, np.inf)
    lowest = np.where(finite, costs, np.inf)
    if not np.any(np.isfinite(pick)) or np.min(lowest) < 0.5 * np.min(pick):
        pick = lowest
    if not np.any(np.isfinite(pick)):  # nothing finite: keep the guess
        return Starts(n=n, reached=0, costs=costs, best=0, stride=stride, params=guess)
    best = int(np.argmin(pick))
    cbest = costs[best]
    reached = int(np.sum(finite & (costs <= cbest * (1.0 + REACHED_RTOL) + 1e-300)))
    return Starts(n=n, reached=reached, costs=costs, best=best, stride=stride,
                  params=TraceParams(*(float(v) for v in params[best])))
