"""What a fit was asked to do (:class:`FitContext`) and what its result derives from the
fitted parameters (eq. 21's d0, d1, d2, xc, k, the ansatz amplitude and phase, the halt time
and the envelope A f(t)): the inputs of ``_result.build_result`` besides the core's arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import jax
import numpy as np

from .._cache import call_cached, prepare_cached
from .._models._decay import decay, halt_time
from ._core import FIT_MODELS
from ._params import Constants, damping_d
from ._problem import bucket, pad


@dataclass(frozen=True)
class FitContext:
    """What a fit was asked to do, besides the core's arrays: what its FitResult reports.

    Attributes:
        model: name of the fit model (an entry of ``FIT_MODELS``).
        free: the fitted damping constants.
        vary: the mask of varied parameters (named booleans).
        consts: m, g (and w0 of envelope fits), floats.
        t, x: the fitted window (not padded).
        loss, optimizer: as asked.
        f_scale: the soft_l1 scale (inf for the linear loss).
        init: initial values of the varied parameters.
        source: where the data came from.
        full_t, full_x: the whole trace (drawn before the fit start), or None.
        warnings: notes about the data.
        stages: how the fit was staged (appended to the message).
        search, exact: as ``_assess.Inputs``'s.
    """

    model: str
    free: tuple
    vary: tuple
    consts: Constants
    t: np.ndarray
    x: np.ndarray
    loss: str
    optimizer: str
    f_scale: float = math.inf
    init: dict = field(default_factory=dict)
    source: str = ""
    full_t: np.ndarray | None = None
    full_x: np.ndarray | None = None
    warnings: tuple = ()
    stages: str = ""
    per_mass: bool = False
    units: str = "m"
    analysis: object = None
    starts: object = None
    profile: object = None
    search: object = None  # the exact model's own batch of starts, where it ran
    exact: bool = False


def _decay_and_halt(t, a, bp, c):
    return decay(t, a, bp, c), halt_time(a, bp, c)


def _envelope_curve(t, a, bp, c):
    """(f(t) of eq. 20 for the figure's envelope, the halt time of eq. 20) by one kept
    compiled program (``_cache.call_cached``): eagerly, decay is some 40 small programs and
    the halt time 15, each compiled or read from the cache in every new process (issue 26;
    0.5 s of a cold fit, issue 36); compiled as one, f may differ from the eager value in the
    last bit. The arguments: concrete numbers; t padded to its bucket (``_problem.bucket``),
    so that windows of other lengths share the program (issue 36: a trace of a new length
    compiled it again, 0.2-0.3 s)."""

    f, halt = call_cached("fit-envelope", ("halt",), _decay_and_halt,
                          *_envelope_args(t, a, bp, c))
    return np.asarray(f)[:np.size(t)], float(halt)


def _envelope_args(t, a, bp, c) -> list:
    """The arguments of the envelope's kept program: t padded to its bucket, float64 arrays."""
    t = np.asarray(t, dtype=float)
    tp, _, _ = pad(t, t, bucket(t.size, 256))
    return [jax.device_put(np.asarray(v, dtype=float)) for v in (tp, a, bp, c)]


def prepare_envelope(t) -> None:
    """Start compiling :func:`_envelope_curve`'s program for the window ``t`` in the
    background (``_cache.prepare_cached``)."""
    prepare_cached("fit-envelope", ("halt",), _decay_and_halt,
                   *_envelope_args(t, 0.0, 0.0, 0.0))


def trace_derived(params: dict, coords, ctx: FitContext):
    """The quantities derived from a trace fit's parameters: eq. 21's d0, d1, d2, xc = mu
    g/w0^2, k = m w0^2, the ansatz amplitude and phase (eqs. 22-23) and its halt time.

    Arguments:
        params: the fitted parameters by name (floats).
        coords: the core's coordinates of the fit (the model's amplitude and phase).
        ctx: the fit's context (its model, constants, window and varied parameters).

    Returns:
        (derived, the envelope A f(t) on the window or None, the fixed constants).
    """
    m, g = ctx.consts.m, ctx.consts.g
    w0 = params["w0"]
    d0, d1, d2 = damping_d(params["mu"], params["b"], params["D"], w0, m, g)
    derived = {"d0": d0, "d1": d1, "d2": d2, "xc": params["mu"] * g / w0 ** 2,
               "k": m * w0 ** 2, "mu_g": params["mu"] * g, "b/m": params["b"] / m,
               "D/m": params["D"] / m}
    A, phi = FIT_MODELS[ctx.model].amplitude_phase(params, coords, m, g)
    envelope = None
    t_start = float(ctx.t[0])
    if math.isfinite(A) and A > 0:
        f, halt = _envelope_curve(ctx.t - t_start, d2 * A, d1, d0 / A)
        envelope, derived["halt_time"] = A * f, t_start + halt
    derived["A"], derived["phi"] = A, phi
    fixed = {"m": m, "g": g}
    if not ctx.vary.w0:
        fixed["k"] = m * params["w0"] ** 2
    return derived, envelope, fixed


def envelope_derived(params: dict, coords, ctx: FitContext):
    """The quantities derived from an envelope fit's parameters: eq. 21 at the fixed w0.

    Arguments:
        params: the fitted parameters by name (floats).
        coords: the core's coordinates of the fit (unused: an envelope has no phase).
        ctx: the fit's context (its constants).

    Returns:
        (derived, None, the fixed constants).
    """
    m, g, w0 = ctx.consts.m, ctx.consts.g, ctx.consts.w0
    d0, d1, d2 = damping_d(params["mu"], params["b"], params["D"], w0, m, g)
    return ({"d0": d0, "d1": d1, "d2": d2, "w0": w0, "mu_g": params["mu"] * g,
             "b/m": params["b"] / m, "D/m": params["D"] / m}, None, {"m": m, "g": g, "w0": w0})

