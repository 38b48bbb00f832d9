"""The oscillator's parameters and the damping coefficients of eq. 21."""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array


def jit_method(fn):
    """Compile a solution method ``fn(self, t)`` once per solution type; t becomes an array.

    (``equinox.filter_jit`` alone would treat a Python float t as static and recompile for
    every new value.)
    """
    compiled = eqx.filter_jit(fn)

    @functools.wraps(fn)
    def method(self, t):
        return compiled(self, jnp.asarray(t, dtype=float))

    return method


def _field(value):
    """``value`` as a float64 JAX array: a host value (a number, a numpy array) placed on the
    device as it is, a JAX or traced value converted. (``jnp.asarray`` of a Python number
    compiles a conversion the first time in a process: 40-60 ms of every command.)"""
    if isinstance(value, jax.Array):
        return jnp.asarray(value, dtype=float)
    return jax.device_put(np.asarray(value, dtype=float))


def is_concrete(*xs) -> bool:
    """True when every leaf of ``xs`` holds a value (no tracer): eager checks may run."""
    leaves = jax.tree_util.tree_leaves(xs)
    return not any(isinstance(x, jax.core.Tracer) for x in leaves)


def known_linear(osc) -> bool:
    """True when the oscillator's k3 is a value (not traced) and zero everywhere: a linear
    spring known at trace time, so the analytic models may leave their cubic terms out (and
    their derivatives: with k3 a constant 0 every cubic term vanishes identically)."""
    return is_concrete(osc.k3) and not np.any(np.asarray(osc.k3))


def check_finite(name: str, value) -> None:
    """Raise ValueError naming ``name`` when a concrete ``value`` holds NaN or inf."""
    if is_concrete(value):
        try:
            arr = np.asarray(value, dtype=float)
        except (TypeError, ValueError, OverflowError):
            raise ValueError(f"{name} must be a finite real number (or an array of them), "
                             f"got {value!r}") from None
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be finite, got {value!r}")


def check_count(name: str, value, *, minimum: int = 0) -> int:
    """An integer option (``back``, ``n``, ...) as a Python int; ValueError naming ``name``.

    Arguments:
        name: the option's name, for the message.
        value: an integer (Python or numpy; a float such as 2.0 or a bool is refused).
        minimum: the smallest value allowed.

    Returns:
        ``int(value)``.
    """
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def check_real(name: str, value, *, low: float, high: float = math.inf,
               low_open: bool = False, high_open: bool = False, hint: str = "") -> float:
    """A real option (``rtol``, ``atol``, ``kappa``) as a Python float in a range.

    Arguments:
        name: the option's name, for the message.
        value: a real number (a concrete scalar).
        low, high: the bounds; ``low_open``/``high_open`` exclude them.
        hint: what the option means, appended to the message.

    Returns:
        ``float(value)``.

    Raises:
        ValueError: naming ``name``, when the value is not a real scalar, not finite or out of
            the range.
    """
    if isinstance(value, jax.core.Tracer):
        raise ValueError(f"{name} is static: pass a Python number, not a traced value")
    try:
        x = float(value)
    except (TypeError, ValueError):
        x = math.nan
        ok = False
    else:
        ok = math.isfinite(x) and (x > low if low_open else x >= low) and (
            x < high if high_open else x <= high)
    if not ok:
        lo = f"{'>' if low_open else '>='} {low:g}"
        hi = "" if high == math.inf else f" and {'<' if high_open else '<='} {high:g}"
        raise ValueError(f"{name} must be a finite number {lo}{hi}{hint}, got {value!r}")
    return x


def check_choices(name: str, values, choices) -> tuple[str, ...]:
    """Validate a non-empty list of distinct names from ``choices``; ValueError naming ``name``."""
    values = (values,) if isinstance(values, str) else tuple(values)
    if not values:
        raise ValueError(f"{name} is empty: give at least one of {list(choices)}")
    unknown = [v for v in values if v not in choices]
    if unknown:
        raise ValueError(f"{name}: unknown {unknown}; choose from {list(choices)}")
    if len(set(values)) != len(values):
        raise ValueError(f"{name}: each name at most once, got {list(values)}")
    return values


def _check_field(name: str, value, *, positive: bool) -> None:
    check_finite(name, value)
    if not is_concrete(value):
        return
    arr = np.asarray(value, dtype=float)
    if positive and np.any(arr <= 0):
        raise ValueError(f"{name} must be > 0, got {value!r}")
    if not positive and np.any(arr < 0):
        raise ValueError(f"{name} must be >= 0 (damping constants cannot be negative), "
                         f"got {value!r}")


class Oscillator(eqx.Module):
    """Block of mass m on a spring k with sliding friction mu, viscous b and quadratic drag D.

    Equation of motion (paper eq. 3, with the cubic stiffness of issue 14):
        m x'' = -k x - k3 x^3 - mu m g sgn(x') - b x' - D x' |x'|.

    Arguments:
        m: mass [kg], > 0.
        k: spring stiffness [N/m], > 0.
        mu: coefficient of sliding (Coulomb) friction, >= 0.
        b: viscous damping constant [kg/s], >= 0.
        D: quadratic drag constant [kg/m], >= 0.
        g: gravitational acceleration [m/s^2], > 0.
        k3: cubic stiffness [N/m^3], finite, either sign (default 0: the linear spring of eq. 3,
            every result exactly as without it). k3 > 0 hardens the spring (the frequency rises
            with the amplitude), k3 < 0 softens it (a pendulum in radians: k3 = -k/6). With
            k3 < 0 the potential k x^2/2 + k3 x^4/4 has its maxima at |x| = sqrt(k/|k3|): a
            start beyond them, or with more energy than the barrier k^2/(4 |k3|), escapes, and
            ``solve`` reports ``RESULTS.unconfined`` (docs/cubic_stiffness.md).
        mu_s: coefficient of static friction, >= mu, or None (the default: mu_s = mu, every
            result and every compiled program exactly as without it; None is no pytree leaf).
            At a turning point the block sticks for good when |k x + k3 x^3| <= mu_s m g and
            slides on with mu otherwise; with mu_s > mu it halts earlier, up to
            mu_s m g / k off centre. Supported by the reference, the exact half-swings and
            the ansatz's Coulomb tail; the other analytic models (which assume mu_s = mu)
            report ``RESULTS.static_friction``. Traced values below mu act as mu.

    Every field may be a JAX array (a batch); the module is a pytree, so it passes through
    ``jax.jit``, ``jax.vmap`` and ``jax.grad``. Concrete values are validated at construction
    (ValueError naming the field); traced values are not.
    """

    m: Array
    k: Array
    mu: Array = 0.0
    b: Array = 0.0
    D: Array = 0.0
    g: Array = 9.81
    k3: Array = 0.0
    mu_s: Array | None = None

    def __init__(self, m=1.0, k=1.0, mu=0.0, b=0.0, D=0.0, g=9.81, k3=0.0, mu_s=None):
        for name, value, positive in (("m", m, True), ("k", k, True), ("mu", mu, False),
                                      ("b", b, False), ("D", D, False), ("g", g, True)):
            _check_field(name, value, positive=positive)
        check_finite("k3", k3)
        if is_concrete(m, k):
            with np.errstate(all="ignore"):
                w0 = np.sqrt(np.asarray(k, dtype=float) / np.asarray(m, dtype=float))
            if not np.all(np.isfinite(w0) & (w0 >= 1e-150) & (w0 <= 1e150)):
                raise ValueError(f"m, k: w0 = sqrt(k/m) = {float(np.min(w0)):.3g} rad/s is outside "
                                 f"[1e-150, 1e150], where its squares leave float64's range; "
                                 f"give m and k in other units, got m={m!r}, k={k!r}")
        self.m = _field(m)
        self.k = _field(k)
        self.mu = _field(mu)
        self.b = _field(b)
        self.D = _field(D)
        self.g = _field(g)
        # a k3 given as a value stays a value inside jit (not a traced constant), so that the
        # analytic models see a linear spring at trace time and leave the cubic terms out
        with jax.ensure_compile_time_eval():
            self.k3 = _field(k3)
        if mu_s is None:
            self.mu_s = None
        else:
            _check_field("mu_s", mu_s, positive=False)
            if is_concrete(mu_s, mu) and np.any(np.asarray(mu_s, dtype=float)
                                                < np.asarray(mu, dtype=float)):
                raise ValueError(f"mu_s must be >= mu (static friction is at least the sliding "
                                 f"friction), got mu_s={mu_s!r} and mu={mu!r}")
            self.mu_s = _field(mu_s)

    @classmethod
    def unchecked(cls, *, m, k, mu, b, D, g=9.81, k3=0.0, mu_s=None) -> Oscillator:
        """An Oscillator of values already checked (the grid of an error map, checked at its
        edge), built without checking them again: the fields as ``__init__`` stores them."""
        self = object.__new__(cls)
        for name, value in (("m", m), ("k", k), ("mu", mu), ("b", b), ("D", D), ("g", g)):
            object.__setattr__(self, name, _field(value))
        with jax.ensure_compile_time_eval():
            object.__setattr__(self, "k3", _field(k3))
        object.__setattr__(self, "mu_s", None if mu_s is None else _field(mu_s))
        return self

    @property
    def omega0(self) -> Array:
        """Undamped angular frequency w0 = sqrt(k/m)."""
        return jnp.sqrt(self.k / self.m)

    @property
    def xc(self) -> Array:
        """Half-width of the sticking band, xc = mu g / w0^2 = mu m g / k."""
        return self.mu * self.g * self.m / self.k

    @property
    def x_static(self) -> Array:
        """Half-width of the static band, mu_s m g / k (exactly :attr:`xc` when mu_s is None).

        A traced mu_s below mu acts as mu (max(mu_s, mu)), so the model stays defined."""
        if self.mu_s is None:
            return self.xc
        return jnp.maximum(self.mu_s, self.mu) * self.g * self.m / self.k

    @property
    def static_differs(self) -> Array:
        """True where static friction exceeds sliding friction (mu_s > mu); False for None."""
        if self.mu_s is None:
            return jnp.asarray(False)
        return self.mu_s > self.mu

    @property
    def gamma(self) -> Array:
        """Viscous decay rate b/(2m) (= d1)."""
        return self.b / (2.0 * self.m)

    def energy(self, x, v) -> Array:
        """Mechanical energy k x^2/2 + k3 x^4/4 + m v^2/2 (eq. 4 with the cubic stiffness).

        Every solution's energy(t) uses it. The k3 term is added last, so with k3 = 0 the
        value is exactly eq. 4's.

        Arguments:
            x, v: displacement [m] and velocity [m/s] (arrays broadcast with the fields).

        Returns:
            E [J].
        """
        return 0.5 * self.k * x**2 + 0.5 * self.m * v**2 + 0.25 * self.k3 * x**4

    def sticks(self, x) -> Array:
        """True where a block at rest at x is held by static friction:
        |k x + k3 x^3| <= mu_s m g (mu_s = mu when None).

        Written |x (1 + (k3/k) x^2)| <= x_static, which is exactly |x| <= xc when k3 = 0 and
        mu_s is None.
        """
        return held(x, self.k3 / self.k, self.x_static)

    @property
    def damping_coefficients(self) -> tuple[Array, Array, Array]:
        """(d0, d1, d2) of the amplitude equation, eq. 21 (see :func:`damping_from_constants`)."""
        return damping_from_constants(self.mu, self.b, self.D, w0=self.omega0, m=self.m,
                                      g=self.g)

    @classmethod
    def from_damping(cls, d0, d1, d2, *, m=1.0, k=1.0, g=9.81) -> Oscillator:
        """The oscillator of mass m, stiffness k whose eq.-21 coefficients are (d0, d1, d2).

        Arguments:
            d0 [m/s], d1 [1/s], d2 [1/(m s)]: the damping coefficients, >= 0.
            m, k, g: mass [kg], stiffness [N/m], gravitational acceleration [m/s^2].

        Returns:
            An Oscillator with mu, b, D from eq. 21 inverted.
        """
        w0 = math.sqrt(k / m) if is_concrete(m, k) and np.ndim(m) == np.ndim(k) == 0 \
            else jnp.sqrt(k / m)
        mu, b, D = constants_from_damping(d0, d1, d2, w0=w0, m=m, g=g)
        return cls(m=m, k=k, mu=mu, b=b, D=D, g=g)

    def __repr__(self) -> str:
        # k3 is shown only when it is not a concrete zero (the linear spring's repr unchanged)
        plain = is_concrete(self.k3) and not np.any(np.asarray(self.k3))
        return _repr_fields(self, ("m", "k", "mu", "b", "D", "g") + (() if plain else ("k3",))
                            + (() if self.mu_s is None else ("mu_s",)))


def unconfined(osc: Oscillator, x0, v0) -> Array:
    """True where a softening spring (k3 < 0) lets the block escape from (x0, v0).

    The potential U(x) = k x^2/2 + k3 x^4/4 has its maxima at |x| = x_b = sqrt(k/|k3|), of
    height U_b = k^2/(4 |k3|). Damping only removes energy, so the motion stays in |x| < x_b
    exactly when |x0| < x_b and E0 = U(x0) + m v0^2/2 < U_b; elsewhere (including the
    boundary, where the block creeps towards the maximum forever) it is out of the domain.
    False wherever k3 >= 0. Elementwise; works on traced values.
    """
    x0 = jnp.asarray(x0, dtype=float)
    v0 = jnp.asarray(v0, dtype=float)
    soft = -osc.k3  # > 0 for a softening spring
    x2 = x0 * x0
    e0 = 0.5 * osc.k * x2 - 0.25 * soft * x2 * x2 + 0.5 * osc.m * v0 * v0
    return (osc.k3 < 0.0) & ((soft * x2 >= osc.k) | (4.0 * soft * e0 >= osc.k * osc.k))


def as_float(x) -> float:
    """A concrete scalar (Python number, numpy or JAX array) as a Python float."""
    return float(np.asarray(x))


def _value_text(value) -> str:
    """A field's value for repr: the number for a scalar, a short array otherwise."""
    if isinstance(value, jax.core.Tracer):
        return f"<traced {value.dtype}{list(value.shape)}>"
    arr = np.asarray(value)
    if arr.ndim == 0:
        return repr(arr.item())
    return np.array2string(arr, precision=6, threshold=8, separator=", ")


def _repr_fields(obj, names) -> str:
    """``Type(name=value, ...)`` with the values shown (equinox would print ``f64[]``)."""
    body = ", ".join(f"{n}={_value_text(getattr(obj, n))}" for n in names)
    return f"{type(obj).__name__}({body})"


def damping_from_constants(mu, b, D, *, w0, m, g):
    """Eq. 21: d0 = 2 mu g / (pi w0), d1 = b / (2 m), d2 = 4 D w0 / (3 pi m).

    The one place eq. 21 is written; :attr:`Oscillator.damping_coefficients` and the fits
    (with a fitted w0) call it.

    Arguments:
        mu, b, D: friction coefficient, viscous [kg/s] and quadratic [kg/m] constants.
        w0: undamped angular frequency [rad/s]; m: mass [kg]; g: [m/s^2].

    Returns:
        (d0, d1, d2).
    """
    d0 = 2.0 * mu * g / (math.pi * w0)
    d1 = b / (2.0 * m)
    d2 = 4.0 * D * w0 / (3.0 * math.pi * m)
    return d0, d1, d2


def constants_from_damping(d0, d1, d2, *, w0, m, g):
    """Eq. 21 inverted: mu = pi w0 d0 / (2 g), b = 2 m d1, D = 3 pi m d2 / (4 w0).

    Arguments:
        d0, d1, d2: the damping coefficients of eq. 21.
        w0: undamped angular frequency [rad/s]; m: mass [kg]; g: [m/s^2].

    Returns:
        (mu, b, D).
    """
    mu = d0 * math.pi * w0 / (2.0 * g)
    b = 2.0 * m * d1
    D = 3.0 * math.pi * m * d2 / (4.0 * w0)
    return mu, b, D


def damping_coefficients(osc: Oscillator) -> tuple[Array, Array, Array]:
    """Damping coefficients (d0, d1, d2) of the amplitude equation.

    Implements eq. 21: d0 = 2 mu g / (pi w0), d1 = b / (2 m), d2 = 4 D w0 / (3 pi m).

    Arguments:
        osc: the Oscillator (fields may be batched arrays).

    Returns:
        (d0, d1, d2), each broadcast like the oscillator's fields.
    """
    return osc.damping_coefficients


def initial_amplitude_phase(osc: Oscillator, x0, v0) -> tuple[Array, Array]:
    """Undamped amplitude and phase (eq. 6): x0 = A0 cos(phi0), v0 = -w0 A0 sin(phi0).

    The phase comes from atan2, so every quadrant of (x0, v0) is handled; at rest
    (x0 = v0 = 0) the phase is 0 and its gradient finite.
    """
    w0 = osc.omega0
    x0 = jnp.asarray(x0, dtype=float)
    v0 = jnp.asarray(v0, dtype=float)
    s = -v0 / w0
    r2 = x0**2 + s**2
    at_rest = r2 == 0.0
    r2_safe = jnp.where(at_rest, 1.0, r2)
    A0 = jnp.where(at_rest, 0.0, jnp.sqrt(r2_safe))
    phi0 = jnp.where(at_rest, 0.0,
                     jnp.arctan2(jnp.where(at_rest, 0.0, s), jnp.where(at_rest, 1.0, x0)))
    return A0, phi0


def from_ratios(d0_ratio=0.0, d1_ratio=0.0, d2_ratio=0.0, *, m=1.0, k=30.0, A0=0.2,
                g=9.81) -> Oscillator:
    """Oscillator whose dimensionless damping ratios are the given ones.

    d0_ratio = d0/(w0 A0), d1_ratio = d1/w0, d2_ratio = d2 A0/w0 (docs/DESIGN.md section 1);
    eq. 21 inverted for mu, b and D at the given m, k and reference amplitude A0.

    Arguments:
        d0_ratio, d1_ratio, d2_ratio: the ratios (numbers or arrays, >= 0).
        m, k: mass [kg] and stiffness [N/m]; A0: the reference amplitude [m]; g [m/s^2].

    Returns:
        An :class:`Oscillator` (array fields for array ratios).
    """
    mu, b, D = ratio_constants(d0_ratio, d1_ratio, d2_ratio, m=m, k=k, A0=A0, g=g)
    return Oscillator(m=m, k=k, mu=mu, b=b, D=D, g=g)


def ratio_constants(d0_ratio, d1_ratio, d2_ratio, *, m=1.0, k=30.0, A0=0.2, g=9.81):
    """(mu, b, D) of :func:`from_ratios` (eq. 21 inverted at w0 = sqrt(k/m), A0), unchecked."""
    w0 = math.sqrt(k / m)
    d0 = jnp.asarray(d0_ratio, dtype=float) * w0 * A0
    d1 = jnp.asarray(d1_ratio, dtype=float) * w0
    d2 = jnp.asarray(d2_ratio, dtype=float) * w0 / A0
    return constants_from_damping(d0, d1, d2, w0=w0, m=m, g=g)


def held(x, k3_over_k, x_static) -> Array:
    """:meth:`Oscillator.sticks` from its two constants, k3/k and the static band's half-width
    (the fused reference kernel holds only these): |x (1 + (k3/k) x^2)| <= x_static."""
    return jnp.abs(x * (1.0 + k3_over_k * (x * x))) <= x_static
