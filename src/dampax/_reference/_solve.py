"""`solve_reference`: eq. 3 integrated swing by swing with exact stick-slip (DESIGN.md 2.6)."""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from .._models._solution import RESULTS
from .._oscillator import Oscillator, check_finite, check_real, is_concrete
from ._diffrax import integrate as integrate_diffrax
from ._engine import _KINDS, integrate
from ._solution import ReferenceSolution, from_engine, sample_single, with_samples


def _kernel():
    """The fused kernel's module (`_kernel`), imported where it is first needed: importing
    Pallas and its Triton backend costs 50-100 ms of every ``import dampax``, and off a CUDA
    GPU only ``engine="pallas"`` uses it."""
    from . import _kernel as module

    return module


def kernel_native() -> bool:
    """Whether the fused kernel runs natively here (`_kernel.available`: a CUDA GPU); its
    module is imported only where JAX's backend is a GPU."""
    try:
        gpu = jax.default_backend() == "gpu"
    except Exception:  # noqa: BLE001 - no backend at all: the XLA engine
        return False
    return gpu and _kernel().available()


# Default t_end in undamped periods: 25 periods are about 50 swings.
DEFAULT_PERIODS = 25.0
# max_swings when neither it nor a concrete t_end and oscillator are given (under jit).
DEFAULT_SWINGS = 64
# The budget sizes are rounded up to these steps (x 2^n), so that nearby windows share one
# compiled program.
_QUANTA = (16, 24, 32, 48)


def _round_up(n: int) -> int:
    """n rounded up to 16, 24, 32, 48, 64, 96, ... (at most 1.5x)."""
    scale = 1
    while True:
        for q in _QUANTA:
            if n <= q * scale:
                return q * scale
        scale *= 4


def rows_per_swing(rtol: float) -> int:
    """Table rows per swing budgeted at a tolerance: DOP853 takes about 5 steps per swing at
    rtol = 1e-10 and the count grows as rtol^(-1/8); the budget is twice that, plus the
    turning point's row."""
    steps = 5.0 * (1e-10 / rtol) ** 0.125
    return max(8, math.ceil(2.0 * steps) + 2)


#: the most half-swings a reference solve takes (from t_end, or given as max_swings): about
#: 12 table rows of 96 bytes each, a few microseconds per step; beyond it a window is refused
#: with its estimate instead of allocating and integrating for minutes (issue 37)
MAX_SWINGS = 100_000
#: the smallest rtol: DOP853 cannot deliver a relative error near float64's epsilon (2.2e-16),
#: and the step budget grows as rtol^(-1/8) (rtol = 1e-300 overflowed it)
MIN_RTOL = 1e-14


def _host_energy(osc, x0, v0) -> np.ndarray:
    """``osc.energy(x0, v0)`` in numpy, for concrete values: no small eager programs for a
    first call to compile (issue 36: a cold fit's first steps)."""
    host = jax.tree_util.tree_map(lambda a: np.asarray(a, dtype=float), osc)
    return host.energy(np.asarray(x0, dtype=float), np.asarray(v0, dtype=float))


def halt_swings(osc, x0, v0) -> np.ndarray:
    """An upper bound on the half-swings before the halt (inf where the motion need not halt).

    Sliding friction takes at least mu m g (|x_n| + |x_n+1|) of energy per half-swing, so the
    amplitude falls by at least 2 mu m g / (k + max(k3, 0) A^2) each time (viscous and
    quadratic drag, and mu_s >= mu, only make it halt sooner); A is bounded by the start's
    energy. With mu = 0, or a softening spring the start's energy escapes, the bound is inf.

    Arguments:
        osc: the Oscillator (concrete).
        x0, v0: the start (concrete).

    Returns:
        The bound (an array broadcast over the inputs).
    """
    with np.errstate(all="ignore"):
        k = np.asarray(osc.k, dtype=float)
        k3 = np.asarray(osc.k3, dtype=float)
        friction = (np.asarray(osc.mu, dtype=float) * np.asarray(osc.m, dtype=float)
                    * np.asarray(osc.g, dtype=float))
        energy = _host_energy(osc, x0, v0)
        # the turning amplitude of this energy: k A^2/2 + k3 A^4/4 = E
        disc = k * k / 4.0 + k3 * energy
        soft = np.where(disc > 0, (k / 2.0 - np.sqrt(np.maximum(disc, 0.0)))
                        / np.where(k3 < 0, -k3 / 2.0, 1.0), np.inf)
        a_sq = np.where(k3 < 0, soft, 2.0 * energy / k)
        amp = np.sqrt(np.abs(a_sq))
        bound = amp * (k + np.maximum(k3, 0.0) * amp * amp) / (2.0 * friction) + 2.0
        return np.where((friction > 0) & np.isfinite(bound), bound, np.inf)


def default_swings(osc, x0, v0, t_end, *, until_halt: bool = True) -> int:
    """max_swings for a concrete window: the swings of the fastest motion in [0, t_end]
    (w_hi t_end / pi, w_hi the frequency bound of `_engine`) with a margin, rounded up; at most
    those before the halt (:func:`halt_swings`), so a t_end long past the halt costs nothing.
    ``until_halt=False`` leaves that bound out: the budget then depends on the window and the
    frequency only, not on the damping (one compiled program for the motions of a search).

    Raises:
        ValueError: naming t_end when the window needs more than :data:`MAX_SWINGS` swings
            (a motion that does not halt, integrated over a very long t_end).
    """
    w0 = np.sqrt(np.asarray(osc.k, dtype=float) / np.asarray(osc.m, dtype=float))
    k3 = np.maximum(np.asarray(osc.k3, dtype=float), 0.0)
    k = np.asarray(osc.k, dtype=float)
    energy = _host_energy(osc, x0, v0)
    with np.errstate(all="ignore"):
        w_hi = w0 * np.sqrt(1.0 + 6.0 * k3 * energy / (k * k))
        swings = np.asarray(t_end, dtype=float) * w_hi / math.pi
        if until_halt:
            swings = np.minimum(swings, halt_swings(osc, x0, v0))
    swings = np.where(np.isfinite(swings), swings, 0.0)
    need = 1.1 * float(np.max(swings)) + 4
    if need > MAX_SWINGS:
        b = float(np.max(np.asarray(osc.b, dtype=float) / np.asarray(osc.m, dtype=float)))
        halts = float(np.max(halt_swings(osc, x0, v0)))
        why = ("the motion does not halt: mu = 0 or a start that escapes" if halts == math.inf
               else f"sliding friction halts it only after up to {halts:.3g} half-swings")
        decay = (f"; its amplitude decays as exp(-b t/(2m)), below 1e-12 of the start after "
                 f"about {2.0 * math.log(1e12) / b:.3g} s" if b > 0 else "")
        raise ValueError(
            f"t_end = {float(np.max(np.asarray(t_end, dtype=float))):.3g} s needs about "
            f"{need:.3g} half-swings of the reference integrator, more than its limit of "
            f"{MAX_SWINGS} ({why}{decay}); choose a shorter t_end")
    return _round_up(int(math.ceil(need)))


def _solve_single(osc, x0, v0, t_end, ts, *, rtol, atol, max_swings, rows, adjoint,
                  engine="dampax"):
    """Unbatched core of `solve_reference` (all inputs scalars)."""
    out = ENGINES[engine](osc, x0, v0, t_end, rtol=rtol, atol=atol, max_swings=max_swings,
                          rows=rows, adjoint=adjoint)
    sol = from_engine(out, osc, x0, v0, t_end)
    if ts is None:
        return sol
    xs, vs = sample_single(sol, ts)
    return with_samples(sol, ts, xs, vs)


def _solve_batched(osc, x0, v0, t_end, ts, **kw):
    """`_solve_single` over the broadcast shape of all inputs (vmapped when not scalar); the
    fused kernel (``engine="pallas"``) over all of them at once."""
    leaves = jax.tree_util.tree_leaves((osc, x0, v0, t_end))
    shape = jnp.broadcast_shapes(*(jnp.shape(a) for a in leaves))
    kernel = kw.get("engine") == "pallas"
    if shape == () and not kernel:
        return _solve_single(osc, x0, v0, t_end, ts, **kw)
    size = math.prod(shape)

    def flat(a):
        return jnp.broadcast_to(a, shape).reshape(size)

    args = jax.tree_util.tree_map(flat, (osc, x0, v0, t_end))
    if kernel:
        sol = _kernel_solve(tuple(sorted(kw.items())))(*args, ts)
    else:
        sol = jax.vmap(lambda o, a, b, c: _solve_single(o, a, b, c, ts, **kw))(*args)
    out = jax.tree_util.tree_map(lambda a: a.reshape(shape + a.shape[1:]), sol)
    if ts is not None:  # the sample times are shared, not batched
        out = with_samples(out, ts, out.xs, out.vs)
    return out


@functools.cache
def _kernel_solve(kw: tuple):
    """The fused kernel's solve of a flat batch (`_kernel.solve_flat`) with the XLA engine's
    reverse mode as its VJP (the same steps and results, to rounding; issue 35 item 2)."""
    kw = dict(kw)
    opts = {k: kw[k] for k in ("rtol", "atol", "max_swings", "rows")}
    xla = dict(kw, engine="dampax", adjoint="recursive")

    @jax.custom_vjp
    def solve(osc, x0, v0, t_end, ts):
        return _kernel().packed(interpret=not kernel_native(), **opts)(osc, x0, v0, t_end,
                                                                       ts)

    def forward(*args):
        return solve(*args), args

    def backward(args, cotangent):
        # the XLA engine's solution as the kernel's leaves it: without the shared ts
        def xla_solve(*a):
            sol = _solve_batched(*a, **xla)
            return with_samples(sol, None, sol.xs, sol.vs)

        return jax.vjp(xla_solve, *args)[1](cotangent)

    solve.defvjp(forward, backward)
    return solve


_solve_jit = jax.jit(_solve_batched,
                     static_argnames=("rtol", "atol", "max_swings", "rows", "adjoint", "engine"))


#: the integrators of the reference, by ``engine``: dampax's DOP853 loop (``_engine``) and
#: diffrax's Dopri8 swing by swing (``_diffrax``; diffrax itself is imported when it runs)
ENGINES = {"dampax": integrate, "diffrax": integrate_diffrax}
#: what ``engine`` accepts: the integrators above, the fused kernel of a whole batch
#: (``_kernel``: "pallas") and "auto" (:func:`resolve_engine`)
ENGINE_NAMES = (*ENGINES, "pallas", "auto")


def solve_reference(osc: Oscillator, x0, v0, *, t_end=None, rtol: float = 1e-10,
                    atol: float = 1e-12, max_swings: int | None = None,
                    max_steps_per_swing: int | None = None, ts=None,
                    adjoint: str = "recursive", solver: str = "dop853",
                    engine: str = "auto") -> ReferenceSolution:
    """Integrate eq. 3 swing by swing with exact stick-slip: the reference for the analytic
    models (DESIGN.md section 2.6).

    Inside a swing sgn(v) is constant and DOP853 integrates the smooth motion; the swing ends
    at the velocity zero (located by Newton's method on re-taken steps), where the block
    sticks for good if |k x + k3 x^3| <= mu_s m g (``Oscillator.mu_s``; mu when None), else
    reverses and slides with mu. sgn(v) is never smoothed.

    Arguments:
        osc: the Oscillator. Its fields, x0, v0 and t_end broadcast together; a non-scalar
            shape solves every element (vmapped) and gives a batched solution.
        x0: initial position [m].
        v0: initial velocity [m/s].
        t_end: end of the time interval [s]; default 25 undamped periods (50 pi / w0), about
            50 swings. May be traced.
        rtol, atol: tolerances of the step-size control (static): 0 < rtol < 1, atol >= 0.
        max_swings: the most swings integrated (static); default from t_end and the
            oscillator when both are concrete (the swings of the window, with a margin),
            else 64. Past it the solution is invalid (``RESULTS.max_swings_reached``).
        max_steps_per_swing: rows of the step table budgeted per swing (static; default from
            rtol, about twice the steps a swing takes). The table holds max_swings times
            this; a trajectory uses only the steps its motion takes.
        ts: optional 1-D sample times: x and v there are computed in the same compiled call
            (from each step's polynomial, built once) and `x(ts)`, `v(ts)` return them.
        adjoint: "recursive" (default; reverse mode, jax.grad), "forward" (jax.jacfwd) or
            "direct" (both; slower).
        solver: "dop853" (the only one; kept as an option for clarity).
        engine: "auto" (default: the fused kernel on a CUDA GPU where not differentiated, else
            "dampax"; :func:`resolve_engine`), "dampax" (its own DOP853 loop in XLA,
            ``_engine``), "pallas" (the same loop as one fused kernel, ``_kernel``: the same
            results to rounding; off a GPU it runs interpreted, slowly) or "diffrax" (diffrax's
            Dopri8 with its events, swing by swing, ``_diffrax``: an independent second
            integrator of the same equation, slower; the same solution type).

    Returns:
        A `ReferenceSolution`. Called eagerly it raises ValueError when x0, v0 or t_end is not
        finite, t_end is not positive, or the budget ran out before t_end or the halt (naming
        max_swings); under jit it returns valid = False instead.
    """
    options = check_reference_options(x0, v0, osc=osc, t_end=t_end, rtol=rtol, atol=atol,
                                      max_swings=max_swings,
                                      max_steps_per_swing=max_steps_per_swing, ts=ts,
                                      adjoint=adjoint, solver=solver, engine=engine)
    return solve_reference_checked(osc, x0, v0, **options)


def _whole(value, low: int, high: int) -> bool:
    """Whether ``value`` is a whole number (int, numpy integer or integral float) in
    [low, high]."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        return False
    return math.isfinite(value) and float(value).is_integer() and low <= value <= high


def check_reference_options(x0, v0, *, t_end=None, rtol: float = 1e-10, atol: float = 1e-12,
                            max_swings: int | None = None,
                            max_steps_per_swing: int | None = None, ts=None,
                            adjoint: str = "recursive", solver: str = "dop853",
                            engine: str = "auto", osc=None) -> dict:
    """The checks of :func:`solve_reference` (at the edge: ``dp.solve``, ``solve_reference``):
    ValueError naming the option; x0, v0, t_end and ts finite where concrete.

    Returns:
        The options of :func:`solve_reference_checked`, normalised (floats, arrays).
    """
    if solver not in ("dop853", "dopri8"):
        raise ValueError(f"solver must be 'dop853' (Hairer's 8th-order pair), got {solver!r}")
    if engine not in ENGINE_NAMES:
        raise ValueError(f"engine must be one of {ENGINE_NAMES}, got {engine!r}")
    if engine == "pallas" and _kernel().pl is None:
        raise ValueError("engine='pallas' needs jax.experimental.pallas, which this jax lacks")
    if engine == "diffrax":
        try:
            import diffrax  # noqa: F401
        except ImportError as err:
            raise ValueError("engine='diffrax' needs diffrax: pip install diffrax") from err
    if adjoint not in _KINDS:
        raise ValueError(f"adjoint must be one of {tuple(_KINDS)}, got {adjoint!r}")
    if jax.dtypes.canonicalize_dtype(float) != jnp.float64:  # (no conversion compiled)
        raise ValueError("solve_reference needs float64: call "
                         "jax.config.update('jax_enable_x64', True) first")
    rtol = check_real("rtol", rtol, low=MIN_RTOL, high=1.0, high_open=True,
                      hint=" (the relative tolerance of the step-size control; DOP853 cannot"
                      " deliver less in float64)")
    atol = check_real("atol", atol, low=0.0,
                      hint=" (the absolute tolerance of the step-size control)")
    if max_swings is not None and not _whole(max_swings, 1, MAX_SWINGS):
        raise ValueError(f"max_swings must be an int between 1 and {MAX_SWINGS}, got "
                         f"{max_swings!r}")
    if max_steps_per_swing is not None and not _whole(max_steps_per_swing, 2, 1000):
        raise ValueError(f"max_steps_per_swing must be an int between 2 and 1000, got "
                         f"{max_steps_per_swing!r}")
    check_finite("x0", x0)
    check_finite("v0", v0)
    if t_end is not None:  # None: the default span, from the oscillator
        check_finite("t_end", t_end)
        if is_concrete(t_end) and np.any(np.asarray(t_end, dtype=float) <= 0):
            raise ValueError(f"t_end must be > 0, got {t_end!r}")
    if ts is not None:
        check_finite("ts", ts)
        ts = jnp.asarray(ts, dtype=float)
        if ts.ndim != 1:
            raise ValueError(f"ts must be a 1-D array of sample times, got shape {ts.shape}")
    return dict(t_end=t_end, rtol=rtol, atol=atol, max_swings=max_swings,
                max_steps_per_swing=max_steps_per_swing, ts=ts, adjoint=adjoint,
                engine=resolve_engine(engine, adjoint, (osc, x0, v0, t_end, ts),
                                      trajectories((osc, x0, v0, t_end))))


#: "auto" takes the fused kernel for at most this many trajectories in one solve (vmapped
#: solves counted together): on an H200 (jax 0.11.2, 1,000 samples, 5 s), with programs of 32
#: lanes and 2 samples a pass, the kernel took 1.92 ms for 4,096 trajectories where the XLA
#: engine took 7.1-8.1 ms, and 11.2 ms against 25.2 ms at 131,072 (benchmarks/README.md,
#: issue 35); with 128 lanes and 16 samples a pass it had lost to XLA above 65,536
KERNEL_MAX_TRAJECTORIES = 1 << 20


def resolve_engine(engine: str, adjoint: str = "recursive", inputs=(),
                   trajectories: int = 1) -> str:
    """The engine that runs for ``engine`` (a name of :data:`ENGINE_NAMES`): "auto" is the
    fused kernel ("pallas") on a CUDA GPU for a solve that is not differentiated (no input is
    an autodiff tracer: derivatives of every order and mode stay with the XLA engine, as
    before) with the reverse-mode adjoint, of at most :data:`KERNEL_MAX_TRAJECTORIES`
    ``trajectories``, once the kernel has passed its self-check in this process
    (`_kernel.self_check`); "dampax" (the XLA engine) otherwise. Other names are returned as
    they are."""
    if engine != "auto":
        return engine
    if adjoint == "recursive" and trajectories <= KERNEL_MAX_TRAJECTORIES and \
            not differentiated(inputs) and kernel_native() and _kernel().self_check(_solve_jit):
        return "pallas"
    return "dampax"


def trajectories(tree) -> int:
    """How many trajectories a solve of these inputs integrates: the largest size among the
    leaves, each with the batch axes of the vmaps around the call (a vmapped solve joins one
    launch of the kernel)."""
    most = 1
    for leaf in jax.tree_util.tree_leaves(tree):
        for _ in range(32):  # the vmaps stacked on the value, innermost first
            if not (isinstance(leaf, jax.core.Tracer) and hasattr(leaf, "batch_dim")):
                break
            leaf = leaf.val  # the value with this vmap's axis
        most = max(most, math.prod(np.shape(leaf)))
    return most


def differentiated(tree) -> bool:
    """Whether a leaf of ``tree`` is, or wraps (under vmap or jit), an autodiff tracer."""
    for leaf in jax.tree_util.tree_leaves(tree):
        for _ in range(32):  # the transformations stacked on the value, outermost first
            if not isinstance(leaf, jax.core.Tracer):
                break
            kind = type(leaf).__name__
            if "JVP" in kind or "Linearize" in kind:
                return True
            leaf = getattr(leaf, "primal", getattr(leaf, "val", None))
    return False


def solve_reference_checked(osc: Oscillator, x0, v0, *, t_end=None, rtol: float = 1e-10,
                            atol: float = 1e-12, max_swings: int | None = None,
                            max_steps_per_swing: int | None = None, ts=None,
                            adjoint: str = "recursive",
                            engine: str = "dampax") -> ReferenceSolution:
    """:func:`solve_reference` for options already checked (:func:`check_reference_options`):
    the integration, and eagerly the failure's ValueError (budget named)."""
    x0 = jnp.asarray(x0, dtype=float)
    v0 = jnp.asarray(v0, dtype=float)
    last = None if ts is None or not np.size(ts) else jnp.max(ts)
    if t_end is None:
        t_end = DEFAULT_PERIODS * 2.0 * math.pi / osc.omega0
        if last is not None:  # the default span reaches the last sample asked for
            t_end = jnp.maximum(t_end, last)
    elif last is not None and is_concrete(t_end, last) and \
            float(last) > float(np.min(np.asarray(t_end, dtype=float))):
        raise ValueError(f"ts: samples up to {float(last):.6g} s lie beyond t_end = "
                         f"{float(np.min(np.asarray(t_end, dtype=float))):.6g} s, where x is "
                         "not solved (NaN): give a t_end that covers them, or leave it out")
    t_end = jnp.asarray(t_end, dtype=float)
    if max_swings is None:
        max_swings = (default_swings(osc, x0, v0, t_end) if is_concrete(osc, x0, v0, t_end)
                      else DEFAULT_SWINGS)
    per_swing = rows_per_swing(rtol) if max_steps_per_swing is None else max_steps_per_swing
    sol = _solve_jit(osc, x0, v0, t_end, ts, rtol=rtol, atol=atol, max_swings=int(max_swings),
                     rows=int(max_swings) * int(per_swing), adjoint=adjoint, engine=engine)
    if is_concrete(sol.result._value) and sol.message:
        budget = bool(np.any(np.asarray(sol.result == RESULTS.max_swings_reached)))
        raise ValueError(sol.message + (f" (now max_swings = {max_swings}, max_steps_per_swing"
                                        f" = {per_swing})" if budget else ""))
    return sol
