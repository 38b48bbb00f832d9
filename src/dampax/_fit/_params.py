"""Parameters of the fits: names, units, checks, and the map to the optimizer's coordinates.

Parameters travel as NamedTuples, pytrees whose leaves keep the order of the fields (a dict would
be flattened in sorted key order): :class:`TraceParams` (mu, b, D, w0, offset, x0, v0) for
traces, :class:`EnvelopeParams` (mu, b, D, A, offset) for tables of maxima. A mask of the same
type, of booleans, says which parameters vary; every fit has all of them and pins the others
(``_core``), so one compiled solver serves every candidate of ``compare_models``, and a set of
arrays vmaps over traces.

The optimizer works in internal coordinates theta, 0 at the start p0 (docs/DESIGN.md, fitting):

- the damping constants mu, b, D >= 0 are log-parameters, p = p_ref exp(theta), bounded below
  at 1e-6 of a small floor (see :func:`log_bounds`);
- the envelope amplitude A > 0: A = A_ref exp(theta);
- the rest: p = p_ref + scale theta, with natural scales (the amplitude for positions, 1/span
  for w0), so that all coordinates are of order one.

A trace model works in its own coordinates (:class:`TraceCoords`): v0 is replaced by the
model's velocity coordinate y, A sin(phi) for the ansatz (eqs. 22-23), v0 itself for the
reference integrator.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._oscillator import Oscillator, constants_from_damping, damping_from_constants

#: the damping constants of eq. 3, in the order of eq. 21 (d0, d1, d2)
DAMPING = ("mu", "b", "D")
#: the power of the amplitude E in the envelope decay rate dE/dt = -(d0 + d1 E + d2 E^2)
POWER = {"mu": 0, "b": 1, "D": 2}
#: the candidate damping models of ``compare_models``
CANDIDATES = (("mu",), ("D",), ("b",), ("mu", "D"), ("b", "D"), ("mu", "b"), ("mu", "b", "D"))
LOSSES = ("linear", "soft_l1")
UNITS = {"mu": "", "mu_s": "", "b": "kg/s", "D": "kg/m", "w0": "rad/s", "offset": "", "x0": "",
         "v0": "/s", "A": "", "k": "N/m", "k3": "N/m^3"}
#: what ``free`` may name: the damping constants, the cubic stiffness (issue 14) and the
#: static friction mu_s (issue 25; both profiled outside the core, ``_api``, ``_static``)
FREE = DAMPING + ("k3", "mu_s")
#: the parameters that ``fit`` profiles (a search around the core's fits) instead of varying
PROFILED = ("k3", "mu_s")
MAD = 1.482602218505602  # 1 / Phi^-1(3/4): MAD -> sigma for Gaussian noise


def unit_of(name: str, units: str = "m", per_mass: bool = False) -> str:
    """The unit of a reported parameter or derived number, with positions in ``units``.

    Per unit mass (no oscillator given: m = 1 kg) b and D are b/m [1/s] and D/m [1/unit];
    with a given mass they are b [kg/s] and D [kg/unit], k = m w0^2 [kg/s^2, N/m] and k3
    [kg/(s^2 unit^2), N/m^3] whatever the position unit (an angle's "kg/deg" is the fit's
    D with positions in degrees: the values were labelled b/m and D/m per unit mass for
    positions that are not lengths, which they were not). mu is a coefficient only for
    positions in metres (mu g is the friction deceleration, ``mu_g`` [unit/s^2]).
    """
    u = units or "m"
    if name == "mu":
        return "" if u == "m" else f"(= mu_g / 9.81 m/s^2; positions in {u}: use mu_g)"
    if name == "b":
        return "1/s (b/m, per unit mass)" if per_mass else "kg/s"
    if name == "D":
        return f"1/{u} (D/m, per unit mass)" if per_mass else f"kg/{u}"
    if name == "k":
        return "1/s^2 (k/m = w0^2, per unit mass)" if per_mass else \
            ("N/m" if u == "m" else "kg/s^2")
    if name == "k3":
        return f"1/(s^2 {u}^2) (k3/m, per unit mass)" if per_mass else \
            ("N/m^3" if u == "m" else f"kg/(s^2 {u}^2)")
    return {"w0": "rad/s", "offset": u, "x0": u, "v0": f"{u}/s", "A": u, "xc": u,
            "mu_g": f"{u}/s^2", "b/m": "1/s", "D/m": f"1/{u}", "d0": f"{u}/s", "d1": "1/s",
            "d2": f"1/({u} s)", "halt_time": "s", "phi": "rad",
            "x_static": u}.get(name, "")


class TraceParams(NamedTuple):
    """Parameters of a trace fit, physical units: eq. 3 started at the fit start t0.

    Attributes:
        mu, b, D: Coulomb coefficient, viscous [kg/s] and quadratic [kg/m] damping.
        w0: angular frequency sqrt(k/m) [rad/s].
        offset: equilibrium position (data units).
        x0, v0: position and velocity at t0.
    """

    mu: Any
    b: Any
    D: Any
    w0: Any
    offset: Any
    x0: Any
    v0: Any


class TraceCoords(NamedTuple):
    """A trace model's own coordinates: :class:`TraceParams` with v0 replaced by ``y``, the
    model's velocity coordinate (ansatz: A sin(phi) of eqs. 22-23; reference: v0)."""

    mu: Any
    b: Any
    D: Any
    w0: Any
    offset: Any
    x0: Any
    y: Any


class EnvelopeParams(NamedTuple):
    """Parameters of an envelope fit E(t) = offset + A f(t - t1) (eq. 20).

    Attributes:
        mu, b, D: the damping constants.
        A: amplitude at the first maximum t1.
        offset: constant added to the envelope.
    """

    mu: Any
    b: Any
    D: Any
    A: Any
    offset: Any


class Damping(NamedTuple):
    """One value per damping constant."""

    mu: Any
    b: Any
    D: Any


class Constants(NamedTuple):
    """Fixed constants of a fit: mass m [kg], gravitational acceleration g [m/s^2], w0
    [rad/s] of envelope fits (trace fits fit w0 as a parameter: NaN here), and the cubic
    stiffness k3 of trace fits (None: the linear spring, the curves exactly as without k3;
    a number: held at that value; ``fit(free=(..., "k3"))`` profiles it, see ``_api``), and
    the static friction mu_s of the reference model (None: mu_s = mu, every program as
    without it; a number: held at that value; ``fit(free=(..., "mu_s"))`` searches it, see
    ``_static``)."""

    m: Any
    g: Any
    w0: Any = math.nan
    k3: Any = None
    mu_s: Any = None

    @property
    def motion(self) -> tuple:
        """(m, g, k3) of the motion's solves (eq. 3; k3 = 0.0 for the linear spring)."""
        return self.m, self.g, 0.0 if self.k3 is None else self.k3


class Setup(NamedTuple):
    """Reference point (theta = 0 at p0) and scales of the internal coordinates of one fit.

    Attributes:
        ref, scale: model coordinates at p0 and their scales (same type as theta).
        floors: small positive values of mu, b, D (1e-4 of the damping scale, eq. 21).
        sx: amplitude scale of the data (the residuals are divided by it).
        t0, span: start and length of the window.
        consts: the fixed constants.
    """

    ref: Any
    scale: Any
    floors: Damping
    sx: Any
    t0: Any
    span: Any
    consts: Constants


#: names of the parameters of trace fits, the layout of ``fit_arrays``
PARAMS = TraceParams._fields
#: names of the parameters of envelope fits
ENVELOPE_PARAMS = EnvelopeParams._fields


# ----------------------------------------------------------------------------------------------
# checks and construction


def check_choice(name, value, choices):
    """ValueError unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")


def check_free(free, *, allowed=DAMPING) -> tuple[str, ...]:
    """The constants to fit, as a tuple, from a tuple or a comma list.

    Arguments:
        free: names among ``allowed`` (default the damping constants; trace fits also take
            "k3", see :data:`FREE`).

    Raises:
        ValueError: an unknown or repeated name.
    """
    if isinstance(free, str):
        free = tuple(s.strip() for s in free.split(",") if s.strip())
    free = tuple(free)
    bad = [f for f in free if f not in allowed]
    if bad or len(set(free)) != len(free):
        raise ValueError(f"free must name distinct constants among {allowed}, "
                         f"got {free!r}")
    return free


def vary_mask(params_type, free, *, fit_omega0: bool = False, offset: bool = True):
    """Which parameters vary, as a ``params_type`` of booleans.

    Arguments:
        params_type: TraceParams or EnvelopeParams.
        free: the damping constants to fit.
        fit_omega0: traces: fit w0 (else fixed at sqrt(k/m)).
        offset: fit the offset.

    Returns:
        The mask: the free damping constants, w0 when ``fit_omega0``, the offset when
        ``offset``; x0, v0 (traces) and A (envelopes) always.
    """
    free = check_free(free)
    others = {"w0": fit_omega0, "offset": offset, "x0": True, "v0": True, "A": True}
    return params_type(**{name: name in free if name in DAMPING else bool(others[name])
                          for name in params_type._fields})


def varied_names(vary) -> list[str]:
    """Names of the varied parameters of a mask, in the order of its fields."""
    return [name for name, on in vary._asdict().items() if on]


def as_params(p, params_type):
    """``params_type`` from an instance, a dict by name or a vector in its field order."""
    if isinstance(p, params_type):
        return p
    if isinstance(p, dict):
        return params_type(**p)
    return params_type(*p)


def flat(p) -> jax.Array:
    """The leaves of a parameter pytree as one vector (the optimizer's view), field order."""
    return jnp.stack([jnp.asarray(v) for v in p], axis=-1)


def unflat(v, params_type):
    """Inverse of :func:`flat`: a ``params_type`` of the entries of a vector."""
    return params_type(*(v[..., i] for i in range(len(params_type._fields))))


def as_arrays(p, dtype=float):
    """Every leaf as a JAX array of ``dtype`` (strong type: one compiled function for all)."""
    return jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype=dtype), p)


def host_arrays(p, dtype=float):
    """Every leaf as :func:`host_array` makes it: the arguments of a kept program, with no
    eager conversion compiled (``jnp.asarray`` of a host value compiles one per shape and
    type the first time in a process, 15-60 ms each)."""
    return jax.tree_util.tree_map(lambda v: host_array(v, dtype), p)


def host_array(v, dtype):
    """``v`` as a strongly typed array of ``dtype`` for a kept program (``_core.run_core``):
    a JAX array of that type as it is (not awaited), anything else as a numpy array (a
    jnp.asarray per leaf cost each fit's call of 26 leaves 6-11 ms of Python)."""
    if isinstance(v, jax.Array):
        same = v.dtype == np.dtype(dtype) and not v.weak_type
        return v if same else jnp.asarray(v, dtype=dtype)
    return np.asarray(v, dtype=dtype)


def oscillator_values(oscillator) -> dict:
    """m, k, mu, b, D, g and w0 = sqrt(k/m) of a single Oscillator, as floats.

    Arguments:
        oscillator: an Oscillator, a dict of its constants, or None: unit mass (m = 1 kg) and
            an unknown w0 (NaN: it must be fitted); no damping, g = 9.81.
    """
    if oscillator is None:
        return {"m": 1.0, "k": math.nan, "mu": 0.0, "b": 0.0, "D": 0.0, "g": 9.81,
                "w0": math.nan}
    if isinstance(oscillator, dict):
        oscillator = Oscillator(**oscillator)
    if not isinstance(oscillator, Oscillator):
        raise TypeError(f"oscillator must be a dampax.Oscillator, got "
                        f"{type(oscillator).__name__}")
    vals = {}
    for name in ("m", "k", "mu", "b", "D", "g"):
        arr = np.asarray(getattr(oscillator, name), dtype=float)
        if arr.shape != ():
            raise ValueError(f"oscillator.{name}: fit needs a single oscillator, not a batch")
        vals[name] = float(arr)
    vals["w0"] = math.sqrt(vals["k"] / vals["m"])
    return vals


# ----------------------------------------------------------------------------------------------
# eq. 21 and eqs. 22-23


def damping_d(mu, b, D, w0, m, g):
    """(d0, d1, d2) of eq. 21 at a (fitted) w0: ``_oscillator.damping_from_constants``."""
    return damping_from_constants(mu, b, D, w0=w0, m=m, g=g)


def d_per_unit(w0, m, g) -> dict:
    """{mu, b, D: d of eq. 21 per unit of that constant} at a (fitted) w0 (floats)."""
    return {n: float(d) for n, d in zip(DAMPING, damping_d(1.0, 1.0, 1.0, w0, m, g),
                                        strict=True)}


def d_to_physical(d0, d1, d2, w0, m, g):
    """Inverse of eq. 21, (mu, b, D) from (d0, d1, d2): ``_oscillator.constants_from_damping``."""
    return constants_from_damping(d0, d1, d2, w0=w0, m=m, g=g)


def start_amplitude(params) -> float:
    """The undamped amplitude of a fit's start, hypot(x0, v0/w0) (``params``: a mapping with
    x0, v0, w0): the size of the motion where the fit starts."""
    return math.hypot(float(params["x0"]), float(params["v0"]) / float(params["w0"]))


def phase_rate(w0, d1):
    """The rate at which the fitted ansatz's phase advances: the viscous damped frequency
    wd = sqrt(w0^2 - d1^2), d1 = b/(2m) (the exact half period pi/wd of a viscous swing,
    docs/DESIGN.md 2.4; w0 exactly when b = 0). Eq. 11's cos(w0 t + phi) lets the phase drift
    by d1^2 t/(2 w0), which a fit of w0 absorbs as a bias of w0 (issue 25's calibration:
    w0 of ansatz fits 3-8 sd low with viscous damping)."""
    r = d1 / w0
    return w0 * jnp.sqrt(jnp.clip(1.0 - r * r, 1e-6, 1.0))


def ansatz_y(p: TraceParams, consts: Constants, iters: int = 40):
    """y = A sin(phi) of the ansatz through (x0, v0), eqs. 22-23 with x0 = A cos(phi):
    v0 = -(d2 A + d1 + d0/A) x0 - wd y, A = sqrt(x0^2 + y^2), by fixed-point iteration
    (wd: :func:`phase_rate`).

    Arguments:
        p: the trace parameters (x0, v0, the damping constants and w0).
        consts: the fixed constants (m and g).
        iters: iterations of the fixed point.

    Returns:
        y, of the shape of p's entries.
    """
    x0, v0 = p.x0, p.v0
    d0, d1, d2 = damping_d(p.mu, p.b, p.D, p.w0, consts.m, consts.g)
    w0 = phase_rate(p.w0, d1)

    def body(index, w):
        A = jnp.sqrt(x0 * x0 + w * w)
        A = jnp.where(A > 0.0, A, 1.0)
        return -(v0 + (d2 * A + d1 + d0 / A) * x0) / w0

    return jax.lax.fori_loop(0, iters, body, -v0 / w0)


def ansatz_v0(x0, y, mu, b, D, w0, m, g):
    """v0 of the ansatz at (x0, y = A sin(phi)): eq. 12 at t = 0 with eqs. 22-23, the phase
    advancing at wd (:func:`phase_rate`)."""
    d0, d1, d2 = damping_d(mu, b, D, w0, m, g)
    w0 = phase_rate(w0, d1)
    A = jnp.sqrt(x0 * x0 + y * y)
    return -(d2 * A + d1 + d0 / A) * x0 - w0 * y


def damping_floors(w0, amplitude, consts: Constants) -> Damping:
    """Small positive (mu, b, D): d0, d1, d2 of eq. 21 at 1e-4 of the damping scale w0 (with
    ``amplitude`` for d0 and d2); the log-parameters of :func:`log_bounds` stop far below."""
    return Damping(*d_to_physical(1e-4 * w0 * amplitude, 1e-4 * w0, 1e-4 * w0 / amplitude,
                                  w0, consts.m, consts.g))


# ----------------------------------------------------------------------------------------------
# setups: the reference point and the scales of the internal coordinates


def trace_setup(p0: TraceParams, t, consts: Constants, model) -> Setup:
    """:class:`Setup` of a trace fit from p0 (ref: the model coordinates of p0).

    Arguments:
        p0: the start (physical).
        t: the data times (t[0] is the fit start).
        consts: m, g.
        model: the fit model (its ``to_coords`` and ``y_scale``).
    """
    t0 = t[0]
    span = jnp.maximum(jnp.max(t) - t0, 1e-12)
    sx = jnp.sqrt(p0.x0 * p0.x0 + (p0.v0 / p0.w0) ** 2)
    sx = jnp.where(sx > 0.0, sx, 1.0)
    one = jnp.ones_like(sx)
    scale = TraceCoords(mu=one, b=one, D=one, w0=1.0 / span, offset=sx, x0=sx,
                        y=model.y_scale(p0.w0, sx))
    return Setup(ref=model.to_coords(p0, consts), scale=scale,
                 floors=damping_floors(p0.w0, sx, consts), sx=sx, t0=t0, span=span,
                 consts=consts)


def envelope_setup(p0: EnvelopeParams, t, consts: Constants, model=None) -> Setup:
    """:class:`Setup` of an envelope fit from p0 (A > 0 is the amplitude scale)."""
    t0 = t[0]
    span = jnp.maximum(jnp.max(t) - t0, 1e-12)
    A = jnp.maximum(jnp.abs(p0.A), 1e-300)
    one = jnp.ones_like(A)
    scale = EnvelopeParams(mu=one, b=one, D=one, A=one, offset=A)
    return Setup(ref=p0._replace(A=A), scale=scale,
                 floors=damping_floors(consts.w0, A, consts), sx=A, t0=t0, span=span,
                 consts=consts)


# ----------------------------------------------------------------------------------------------
# internal coordinates <-> model coordinates


def coords_mask(vary, coords_type):
    """The mask ``vary`` (by parameter) by model coordinate: y varies with v0."""
    values = vary._asdict()
    if "y" in coords_type._fields:
        values["y"] = values.pop("v0")
    return coords_type(**values)


def on_damping(coords_type, values: Damping, fill):
    """A ``coords_type`` holding ``values`` at mu, b, D and ``fill`` elsewhere."""
    damping = values._asdict()
    return coords_type(**{name: damping.get(name, fill) for name in coords_type._fields})


def log_bounds(setup: Setup, vary) -> tuple[Damping, Damping]:
    """(reference, lowest log-offset) of the damping log-parameters.

    A constant that the data do not support stops at 1e-6 of its small floor (~1e-10 of the
    damping scale) instead of drifting to -inf, so the optimizer converges (gracefully at ~0).
    """
    dref, lo = {}, {}
    for name in DAMPING:
        floor = getattr(setup.floors, name)
        dref[name] = jnp.where(getattr(vary, name), jnp.maximum(getattr(setup.ref, name), floor),
                               1.0)
        lo[name] = jnp.log(1e-6 * floor / dref[name])
    return Damping(**dref), Damping(**lo)


def clamp(theta, setup: Setup, vary):
    """theta with the damping log-parameters raised to their lower bounds."""
    _, lo = log_bounds(setup, vary)
    return theta._replace(**{name: jnp.maximum(getattr(theta, name), getattr(lo, name))
                             for name in DAMPING})


def to_model(theta, setup: Setup, vary, clamped: bool = True):
    """Model coordinates from the internal ones; fixed parameters stay at their p0 value.

    Arguments:
        theta: internal coordinates (the type of ``setup.ref``).
        setup: reference point and scales.
        vary: the mask (by parameter).
        clamped: apply the lower bounds of the log-parameters (the statistics do not, so that
            a constant at its bound keeps its tiny derivative).
    """
    dref, lo = log_bounds(setup, vary)
    free = coords_mask(vary, type(theta))
    out = {}
    for name, th in theta._asdict().items():
        ref, on = getattr(setup.ref, name), getattr(free, name)
        if name in DAMPING:
            th = jnp.maximum(th, getattr(lo, name)) if clamped else th
            out[name] = jnp.where(on, getattr(dref, name) * jnp.exp(th), ref)
        elif name == "A":  # always varies
            out[name] = ref * jnp.exp(th)
        else:
            out[name] = jnp.where(on, ref + getattr(setup.scale, name) * th, ref)
    return type(theta)(**out)
