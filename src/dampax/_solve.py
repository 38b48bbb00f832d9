"""One entry point, :func:`solve`, dispatching to the models, with eager input checks."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._cache import call_cached_tree, prepare_cached_tree
from ._models._ansatz import AnsatzSolution, solve_ansatz
from ._models._coulomb import solve_coulomb_exact, solve_rizcallah, with_coulomb_tail
from ._models._registry import METHODS
from ._models._solution import result_where, solution_estimate, static_checks, stuck_at_start
from ._oscillator import (
    Oscillator,
    check_count,
    check_finite,
    check_real,
    is_concrete,
    known_linear,
)
from ._reference._solve import (
    DEFAULT_PERIODS,
    check_reference_options,
    default_swings,
    solve_reference_checked,
)

#: Rizcallah's default amplitude factor (least squares)
KAPPA = 4.0 / math.pi
#: kappa above this makes the envelope lose more than pi xc per half period: the model halts
#: within a couple of swings whatever the start, a band it was never meant for (Rizcallah's
#: kappas are 4/pi, pi/2 and sqrt(2))
KAPPA_MAX = 2.0


def solve(osc: Oscillator, x0, v0, *, method: str = "ansatz", phase: str = "matched",
          tail: str | None = None, back: int = 0, kappa: float | None = None,
          tolerance: float | None = None, throw: bool = False, **options):
    """Solve eq. 3, m x'' = -k x - mu m g sgn(x') - b x' - D x'|x'|, with one of the models.

    The models and their options are listed in ``dampax._models._registry.MODELS`` (the
    registry every command reads): "matched" is ``method="ansatz"``, "undamped" adds
    ``phase="undamped"``, "matched_tail" adds ``tail="coulomb"``.

    Arguments:
        osc: the :class:`Oscillator`.
        x0, v0: initial displacement [m] and velocity [m/s].
        method: "ansatz" (Lelas & Pezer, eq. 11), "rizcallah" (sinusoidal friction),
            "coulomb_exact" (exact half-swings; D = 0) or "reference" (DOP853 integration of
            eq. 3 with exact stick-slip); or "auto": the matched ansatz where the error atlas
            puts max |x - x_ref| / A0 below ``tolerance`` with a margin (twice the largest
            error at the atlas points around this one, see ``dampax._models._atlas``), else the
            reference. The solution's ``model`` says which ("matched" or "reference");
            eager, scalar input only (the choice depends on the values).
        phase: ansatz only: "matched" (A, phi from eqs. 22-23) or "undamped" (eqs. 8-10).
        tail: ansatz only: None, or "coulomb" for the improved solutions (eqs. 41, 52, 54): the
            exact Coulomb (+ viscous) motion from the last turning point with |x| > xc.
        back: with tail="coulomb": start the tail this many turning points earlier (eq. 54: 1);
            an integer >= 0.
        kappa: rizcallah only: 4/pi (least squares, the default), pi/2 (impulse) or sqrt(2)
            (rms); a number in (0, 2].
        tolerance: auto only (a ValueError with another method): the largest acceptable
            expected error of the ansatz, in A0 (``solution.error_estimate``), > 0; default
            1e-2.
        throw: under ``jit``/``vmap``, raise the failure's message at run time
            (``equinox.error_if``, as ``diffrax.diffeqsolve(throw=True)``) instead of
            returning ``valid = False`` and NaN. Eager calls always raise ValueError.
        **options: reference only: t_end, rtol, atol, max_swings, ...

    Returns:
        A solution (a subclass of ``AbstractSolution``) with ``x(t)``, ``v(t)``,
        ``energy(t)``, ``halt_time``, ``halt_position``, ``result`` (a ``RESULTS`` member: why
        it failed and what to do), ``valid`` (``result`` is successful), and ``amplitude``,
        ``phase`` for the ansatz.

    Every model states its domain (``dampax.MODELS[...].domain``): m, k, g finite and > 0;
    mu, b, D finite and >= 0; x0, v0 finite; plus the model's own conditions (the ansatz:
    d1 = b/(2m) < w0 and an admissible amplitude; rizcallah: b = D = 0; coulomb_exact: D = 0,
    b < 2 sqrt(k m)). A start at rest inside the sticking band (v0 = 0, k |x0| <= mu m g) is
    answered by every model with the exact rest: x(t) = x0, v = 0, halt_time 0.

    Called eagerly, invalid input (non-finite x0/v0, a model that does not exist for these
    parameters, e.g. no admissible amplitude of eq. 22) raises ValueError with the result's
    message, which names the parameter; under jit/vmap the solution carries ``result`` (and
    ``valid = False``) with NaN values instead, or raises with ``throw=True``. The options
    (kappa, back, rtol, atol, ...) are static and always checked at once (ValueError naming
    the option).
    """
    if not isinstance(osc, Oscillator):
        raise TypeError(f"osc must be a dampax.Oscillator, got {type(osc).__name__}")
    if method == "auto":
        if tail is not None or phase != "matched" or back != 0 or kappa is not None:
            raise ValueError("method='auto' chooses between the matched ansatz and the "
                             "reference: phase, tail, back and kappa do not apply")
        return _solve_auto(osc, x0, v0, tolerance=1e-2 if tolerance is None else tolerance,
                           throw=throw, options=options)
    if tolerance is not None:  # (it was ignored unsaid)
        raise ValueError(f"tolerance: applies to method='auto' only (its choice of model), "
                         f"not to method={method!r}")
    kappa, back, options = check_options(osc, x0, v0, method=method, phase=phase, tail=tail,
                                         back=back, kappa=kappa, options=options)
    return solve_checked(osc, x0, v0, method=method, phase=phase, tail=tail, back=back,
                         kappa=kappa, throw=throw, **options)


def check_options(osc, x0, v0, *, method, phase="matched", tail=None, back=0, kappa=None,
                  options=None):
    """The checks of :func:`solve`, once at the edge (ValueError naming the option; x0, v0
    finite where concrete).

    Returns:
        (kappa, back, options) normalised for :func:`solve_checked` (the reference's options
        by ``_reference.check_reference_options``).
    """
    options = dict(options or {})
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS + ('auto',)}, got {method!r}")
    if tail not in (None, "coulomb"):
        raise ValueError(f"tail must be None or 'coulomb', got {tail!r}")
    if method != "ansatz" and (tail is not None or phase != "matched" or back != 0):
        raise ValueError(f"phase, tail and back apply to method='ansatz' only, not {method!r}")
    if method != "reference" and options:
        raise ValueError(f"options {sorted(options)} apply to method='reference' only")
    if kappa is not None and method != "rizcallah":
        raise ValueError(f"kappa applies to method='rizcallah' only, not {method!r}")
    kappa = KAPPA if kappa is None else check_real(
        "kappa", kappa, low=0.0, low_open=True, high=KAPPA_MAX,
        hint=" (Rizcallah's amplitude factor: 4/pi, pi/2 or sqrt(2); beyond 2 the"
        " model can halt outside the band with growing energy)")
    back = check_count("back", back)
    if back and tail is None:
        raise ValueError(f"back applies to tail='coulomb' only, got back={back} and tail=None")
    piecewise = method in ("rizcallah", "coulomb_exact") or tail is not None
    if piecewise and any(np.ndim(a) for a in jax.tree_util.tree_leaves((osc, x0, v0))):
        name = f"method={method!r}" + (f", tail={tail!r}" if tail else "")
        raise ValueError(
            f"{name}: array-valued oscillator fields or initial states are not broadcast by "
            "this piecewise model; map over them with jax.vmap(lambda ...: dp.solve(...)) "
            "(the plain ansatz and the reference accept arrays directly)")
    if method == "reference":
        options = check_reference_options(x0, v0, osc=osc, **options)
    else:
        check_finite("x0", x0)
        check_finite("v0", v0)
    check_amplitude(osc, x0, v0)
    return kappa, back, options


#: the smallest and largest start amplitude hypot(x0, v0/w0) [m] the models take: beyond them
#: the squares the models form (A^2, the energy) underflow or overflow float64 (near 1e-154,
#: 1e154) and a start of amplitude 1e-155 came out as x(0) = 0 with valid = True (issue 37)
AMPLITUDE_RANGE = (1e-150, 1e150)


def check_amplitude(osc, x0, v0) -> None:
    """ValueError naming x0, v0 when a concrete start's amplitude A0 = hypot(x0, v0/w0) is
    neither 0 nor inside :data:`AMPLITUDE_RANGE` (a start at rest inside the sticking band,
    exact for every model, is always taken).

    Arguments:
        osc: the Oscillator.
        x0, v0: the start (scalars or arrays; traced values are not checked).
    """
    if not is_concrete(osc, x0, v0):
        return
    with np.errstate(all="ignore"):
        x = np.asarray(x0, dtype=float)
        v = np.asarray(v0, dtype=float)
        m, k = np.asarray(osc.m, dtype=float), np.asarray(osc.k, dtype=float)
        w0 = np.sqrt(k / m)
        a0 = np.hypot(x, v / w0)
        band = (v == 0) & (k * np.abs(x) <= np.asarray(osc.mu, dtype=float) * m
                           * np.asarray(osc.g, dtype=float))
        low, high = AMPLITUDE_RANGE
        bad = (a0 != 0) & ~band & ((a0 < low) | (a0 > high))
    if np.any(bad):
        value = float(np.asarray(np.broadcast_to(a0, bad.shape))[bad].flat[0])
        raise ValueError(
            f"x0, v0: the start's amplitude hypot(x0, v0/w0) = {value:.3g} m is outside "
            f"[{low:g}, {high:g}] m, where the squares the models form (A^2, the energy) "
            f"leave float64's range; solve the scaled problem instead (x = s u: x0/s, v0/s "
            f"with mu/s, D s, k3 s^2) and multiply the positions by s")


def solve_checked(osc, x0, v0, *, method, phase="matched", tail=None, back=0, kappa=KAPPA,
                  throw=False, **options):
    """:func:`solve` for arguments already checked (:func:`check_options`): what the studies
    and the fits call inside their own programs, after checking once at their edge."""
    eager = is_concrete(osc, x0, v0)
    if method == "reference":
        sol = _reference_kept(osc, x0, v0, options) if eager else None
        if sol is None:
            sol = solve_reference_checked(osc, x0, v0, **options)
    else:
        x0, v0 = _as_float64(x0), _as_float64(v0)
        sol = _solve_analytic(osc, x0, v0, method=method, phase=phase, tail=tail,
                              back=back, kappa=kappa, linear=known_linear(osc))
    if eager and is_concrete(sol.result._value) and sol.message:
        raise ValueError(sol.message)
    if throw:
        sol = sol.result.error_if(sol, ~sol.valid)
    return sol


def _as_float64(value):
    """``jnp.asarray(value, dtype=float)``; a Python or numpy number is put on the device as a
    float64 array instead, which compiles no conversion program (a command's eager
    operations each cost a lowering and a cache read, issue 26). The same value and type."""
    if isinstance(value, (int, float, np.number, np.ndarray)) and not isinstance(value, bool):
        return jax.device_put(np.asarray(value, dtype=float))
    return jnp.asarray(value, dtype=float)


def prepare_reference(osc, x0, v0, **options) -> None:
    """Start building, in a background thread, the kept program of the eager call
    ``solve(osc, x0, v0, method="reference", **options)`` (``_cache.prepare_cached_tree``), so
    that a caller who knows the call ahead (a fit's search of the neighbouring halts) finds it
    compiled. Only the options and the budget they imply matter, not the values."""
    _, _, options = check_options(osc, x0, v0, method="reference", options=options)
    _reference_kept(osc, x0, v0, options, prepare=True)


def _reference_kept(osc, x0, v0, options, prepare: bool = False):
    """An eager ``solve_reference`` through a kept compiled program (``_cache.call_cached_tree``:
    a repeated call, also in a new process, neither traces nor compiles the integrator).

    Returns:
        The solution, or None where the plain route must run: options that are not plain
        values, or a failed solution (the plain route raises its ValueError, budget named).
        ``prepare``: the program is only started (``_cache.prepare_cached_tree``): None.
    """
    static = {k: v for k, v in options.items() if k != "t_end" and v is not None}
    t_end = options.get("t_end")
    if not (all(isinstance(v, str | int | float | bool) for v in static.values())
            and is_concrete(t_end)):
        return None
    extra = () if t_end is None else (_as_float64(t_end),)
    if static.get("max_swings") is None:  # the budget from the values, as the plain route's
        span = (DEFAULT_PERIODS * 2.0 * math.pi / np.asarray(osc.omega0) if t_end is None
                else t_end)
        static["max_swings"] = default_swings(osc, x0, v0, span)

    def program(osc, x0, v0, *t_end):
        return solve_reference_checked(osc, x0, v0, t_end=t_end[0] if t_end else None,
                                       **static)

    call = prepare_cached_tree if prepare else call_cached_tree
    sol = call("reference", (sorted(static.items()), t_end is None), program, osc,
               _as_float64(x0), _as_float64(v0), *extra)
    return None if prepare or sol.message else sol


_AUTO_MARGIN = 2.0


def _solve_auto(osc, x0, v0, *, tolerance, throw, options):
    """method="auto": the matched ansatz if its atlas estimate is below tolerance, else the
    reference (see :func:`solve`)."""
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float)) or not (
            math.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance must be a number > 0, got {tolerance!r}")
    if not is_concrete(osc, x0, v0):
        raise ValueError("method='auto' picks the model from the values, so it needs concrete "
                         "input: call dp.solve outside jit/vmap, or name the method")
    if any(np.ndim(a) for a in jax.tree_util.tree_leaves((osc, x0, v0))):
        raise ValueError("method='auto' needs a scalar oscillator and initial state (the "
                         "choice differs from point to point): loop over them, or name the "
                         "method")
    reference = check_reference_options(x0, v0, **options)  # x0, v0 too; before either runs
    check_amplitude(osc, x0, v0)
    try:
        sol = solve_checked(osc, x0, v0, method="ansatz", throw=throw)
    except ValueError:  # the ansatz does not exist here: the reference does
        sol = None
    # the atlas' upper estimate (the largest error at the surrounding atlas points) times a
    # margin of 2, not the interpolation: the ansatz is only chosen where it is good with room
    # to spare (in tests 2 x the upper estimate was never below the true error)
    if sol is not None and _AUTO_MARGIN * float(solution_estimate(sol, bound=True)) < tolerance:
        return sol
    return solve_checked(osc, x0, v0, method="reference", throw=throw, **reference)


@eqx.filter_jit
def _solve_analytic(osc, x0, v0, *, method, phase, tail, back, kappa, linear):
    """The analytic models, compiled once per (method, options) and re-used for new values;
    ``linear``: k3 is a constant 0 outside (`known_linear`, lost inside this jit)."""
    if method == "ansatz":
        sol = solve_ansatz(osc, x0, v0, phase=phase, linear=linear)
        if tail == "coulomb":
            return with_coulomb_tail(sol, osc, x0, v0, back=back)
        return _assumes_mu_s(sol, osc, x0, v0)
    if method == "rizcallah":
        return _assumes_mu_s(solve_rizcallah(osc, x0, v0, kappa=kappa), osc, x0, v0)
    return solve_coulomb_exact(osc, x0, v0)


def _assumes_mu_s(sol, osc, x0, v0):
    """``sol`` of a model that assumes mu_s = mu, with ``RESULTS.static_friction`` where the
    oscillator's mu_s exceeds mu (unchanged when mu_s is None; a start at rest inside the
    static band is exact for every model)."""
    checks = static_checks(osc, stuck_at_start(osc, x0, v0))
    if not checks:
        return sol
    ((differs, reason),) = checks
    return eqx.tree_at(lambda s: s.result, sol,
                       result_where(sol.valid & differs, reason, sol.result))


def turning_points(sol, n: int):
    """First n turning points (t_k, x_k) with t_k > 0 and v = 0.

    A start at rest is not counted; after the halt the arrays are NaN-padded (the rest point of
    models that stop at a turning point is the last one listed).

    Arguments:
        sol: a solution returned by :func:`solve`.
        n: how many (static), an integer from 0 to :data:`MAX_TURNING_POINTS`.

    Returns:
        (t, x), two arrays of shape (n,).
    """
    n = check_count("n", n)
    if n > MAX_TURNING_POINTS:
        raise ValueError(f"n must be at most {MAX_TURNING_POINTS} (two arrays of n values are "
                         f"allocated), got {n}")
    return turning_points_checked(sol, n)


#: the most turning points :func:`turning_points` lists (its arrays are that long: 1e9 asked
#: for 16 GB)
MAX_TURNING_POINTS = 1_000_000


def turning_points_checked(sol, n: int):
    """:func:`turning_points` for a count already checked (the studies' programs)."""
    if isinstance(sol, AnsatzSolution):
        # an ansatz solved for array fields: its leaves broadcast to a batch shape; map the
        # per-trajectory search over it
        leaves = [a for a in jax.tree_util.tree_leaves(sol) if isinstance(a, jax.Array)]
        shape = jnp.broadcast_shapes(*(a.shape for a in leaves))
        if shape:
            size = math.prod(shape)
            flat = jax.tree_util.tree_map(
                lambda a: jnp.broadcast_to(a, shape).reshape(size)
                if isinstance(a, jax.Array) else a, sol)
            t, x = jax.vmap(lambda s: s.turning_points(int(n)))(flat)
            return t.reshape(shape + (int(n),)), x.reshape(shape + (int(n),))
    return sol.turning_points(int(n))
