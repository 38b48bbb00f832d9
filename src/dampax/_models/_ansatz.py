"""The ansatz x(t) = A f(t) cos(w0 t + phi) of Lelas & Pezer (Part I), eqs. 8-24, 36-54.

f(t), the amplitude factor of eq. 20, and its halt time are in ``_decay.py``; the cubic
stiffness terms in ``_cubic.py``. Here: the matched amplitude and phase (eqs. 22-23) and the
solution object. A sample of x(t) costs one cos and one f(t); v(t) and energy(t) share f, f',
cos and sin (:meth:`AnsatzSolution.state`).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp

from .._oscillator import Oscillator, initial_amplitude_phase, jit_method, known_linear
from .._trig import sincos
from ._cubic import _cubic_terms, cubic_match, excess_frequency, if_cubic, phase_excess
from ._decay import _decay_constants, _decay_from, _DecayConstants, decay_rate, halt_time
from ._solution import (
    RESULTS,
    AbstractSolution,
    cubic_checks,
    first_failure,
    input_checks,
    stuck_at_start,
)

Array = jax.Array


# ----------------------------------------------------------------------------------------------
# amplitude and phase (eqs. 22-23)


def _amplitude_residual(y, s, cphi, sphi, e0, e1, e2):
    """F(y) = y^2 - (y cos phi)^2 - (y sin phi)^2 in units of A0 (the quartic of eq. 22 / y^2).

    y = A / A0, s scales the damping (continuation parameter), y cos(phi) = cos(phi0) and
    y sin(phi) = sin(phi0) - s cos(phi0) (e2 y + e1 + e0 / y).
    Returns F, dF/dy, dF/ds and h = y sin(phi).
    """
    g = e2 * y + e1 + e0 / y
    h = sphi - s * cphi * g
    F = y * y - cphi * cphi - h * h
    F_y = 2.0 * y + 2.0 * s * h * cphi * (e2 - e0 / (y * y))
    F_s = 2.0 * h * cphi * g
    return F, F_y, F_s, h


def matched_amplitude(cphi, sphi, e0, e1, e2, *, steps=16, newton=3):
    """Amplitude ratio A/A0 of eq. 22 on the root branch connected to A0 as damping -> 0.

    Solves (d2 x0 A^2 + (v0 + d1 x0) A + d0 x0)^2 = w0^2 A^2 (A^2 - x0^2) in dimensionless form
    by continuation in the damping strength s from 0 (root A = A0) to 1: an Euler predictor and
    Newton correctors per step. The branch ends at a fold where no admissible root exists
    (e.g. d2 |x0| >= w0 for quadratic damping); ``valid`` is then False.

    Arguments:
        cphi, sphi: cos(phi0) = x0/A0 and sin(phi0) = -v0/(w0 A0).
        e0, e1, e2: the ratios d0/(w0 A0), d1/w0, d2 A0/w0.

    Returns:
        (y, h, valid): y = A/A0, h = y sin(phi) and the validity flag. First derivatives of y are
        exact (implicit function theorem through a final Newton step).
    """
    # broadcast first: the scan's carry takes the shape of the whole batch (an Oscillator with
    # array fields and a scalar start, or the other way round)
    args = tuple(jnp.broadcast_arrays(*(jnp.asarray(v, dtype=float)
                                        for v in (cphi, sphi, e0, e1, e2))))
    const = jax.lax.stop_gradient(args)
    ds = 1.0 / steps

    def correct(y, s):
        def body(_, y):
            F, F_y, _, _ = _amplitude_residual(y, s, *const)
            y = y - F / jnp.where(F_y == 0.0, 1.0, F_y)
            return jnp.where(jnp.isfinite(y) & (y > 0.0), y, jnp.nan)

        return jax.lax.fori_loop(0, newton, body, y)

    def step(carry, i):
        y, min_fy = carry
        s = i * ds
        _, F_y, F_s, _ = _amplitude_residual(y, s, *const)
        y = y - ds * F_s / jnp.where(F_y == 0.0, 1.0, F_y)
        y = correct(jnp.where(y > 0.0, y, jnp.nan), s + ds)
        _, F_y, _, _ = _amplitude_residual(y, s + ds, *const)
        return (y, jnp.minimum(min_fy, F_y)), None

    y0 = jnp.ones_like(const[0])
    (y, min_fy), _ = jax.lax.scan(step, (y0, jnp.full_like(y0, jnp.inf)), jnp.arange(steps))
    y = correct(y, 1.0)
    F, F_y, _, _ = _amplitude_residual(y, 1.0, *const)
    valid = jnp.isfinite(y) & (y > 0.0) & (min_fy > 1e-8) & (jnp.abs(F) < 1e-10 * y * y)
    # implicit-function-theorem step: exact first derivatives, value unchanged to rounding
    y_c = jnp.where(valid, y, 1.0)
    F, F_y, _, h = _amplitude_residual(y_c, 1.0, *args)
    y_out = y_c - F / jnp.where(valid, F_y, 1.0)
    _, _, _, h = _amplitude_residual(y_out, 1.0, *args)
    return jnp.where(valid, y_out, jnp.nan), jnp.where(valid, h, jnp.nan), valid


def _undamped_x(kappa, beta, operands, *, cubic: bool):
    """A f(t) cos(w0 t + phi + P(t)), the undamped-phase x of `AnsatzSolution._x_energy`
    (operands: A, w0, phi, decay constants, t, f(t)); cubic=False leaves P out."""
    A, w0, phi, k, t, f = operands
    th = w0 * t + phi
    if cubic:
        th = th + phase_excess(k, w0, kappa, t, f)
    return A * f * sincos(th)[1]


def _state_terms(kappa, beta, operands, *, matched: bool, cubic: bool):
    """(x, v) of `AnsatzSolution._state` before masking (eqs. 11-12, or 8-9 unmatched).

    Arguments:
        kappa, beta: the cubic stiffness's constants; operands: (A, w0, phi, decay constants,
            t); cubic: False leaves the cubic terms out (exact when kappa = beta = 0).
    """
    A, w0, phi, k, t = operands
    f = _decay_from(k, t)
    th = w0 * t + phi
    sth, cth = sincos(th)
    x = A * f * cth
    v = -w0 * A * f * sth
    rate = decay_rate(f, k.a, k.bp, k.c)
    if matched:
        v = v + A * rate * cth
    if cubic:  # all exactly 0 when k3 = 0
        dx, dv, dv_rate = _cubic_terms(kappa, beta, (A, w0, k, t, f, cth, sth, rate))
        x = x + dx
        v = v - dv
        if matched:
            v = v + dv_rate
    return x, v


# ----------------------------------------------------------------------------------------------
# the solution object


class AnsatzSolution(AbstractSolution):
    """x(t) = A f(t) cos(w0 t + phi) of eq. 11, zero after the halt time tau (eq. 37).

    ``matched=True``: A and phi from eqs. 22-23, velocity eq. 12, energy eq. 15.
    ``matched=False``: the earlier approach, A = A0, phi = phi0 (eq. 8), velocity without the
    f' term (eq. 9), energy m w0^2 A0^2 f^2 / 2 (eq. 10).
    Where no admissible amplitude exists, ``result`` is ``RESULTS.no_amplitude`` (``valid``
    False) and the values (``halt_time`` and ``halt_position`` too) are NaN; likewise
    ``RESULTS.ansatz_overdamped`` for d1 >= w0 and ``RESULTS.invalid_constants``. A start at
    rest inside the sticking band (``stuck``) stays there: x(t) = x0, v = 0, halt time 0.

    With a cubic stiffness k3 (matched phase only; docs/cubic_stiffness.md):
        x(t) = A f [cos th + eps f^2 (cos 3th - cos th)],  eps = beta = k3 A^2 / (32 k),
        th(t) = w0 t + phi + P(t),  th' = w(A f) = w0 sqrt(1 + kappa f^2),
        kappa = (3/4) k3 A^2 / k;
    every k3 term is exactly zero when k3 = 0.
    """

    A: Array  # amplitude, finite even where invalid (see ``amplitude``)
    phi: Array
    omega0: Array
    a: Array
    bp: Array
    c: Array
    tau: Array  # the halt time of eq. 37, finite even where invalid (see ``halt_time``)
    osc: Oscillator
    result: RESULTS
    stuck: Array  # started at rest inside the band: x(t) = x0 (the model's A is then 0)
    x0: Array
    kappa: Array  # (3/4) k3 A^2 / k: w(A f)^2 = w0^2 (1 + kappa f^2)
    beta: Array  # k3 A^2 / (32 k): the third harmonic's relative amplitude at f = 1
    matched: bool = eqx.field(static=True)
    # k3 was a value 0 at construction (`known_linear`): the cubic terms are left out at trace
    # time; else they are skipped at run time where kappa = beta = 0 (`if_cubic`)
    linear: bool = eqx.field(static=True, default=False)

    @property
    def amplitude(self) -> Array:
        """A of eq. 11 (A0 for the undamped phase); NaN where the model does not exist."""
        return jnp.where(self.valid, self.A, jnp.nan)

    @property
    def phase(self) -> Array:
        """phi of eq. 11 (phi0 for the undamped phase); NaN where the model does not exist."""
        return jnp.where(self.valid, self.phi, jnp.nan)

    @property
    def model(self) -> str:
        """"matched" or "undamped" (the registry names)."""
        return "matched" if self.matched else "undamped"

    def _atlas_start(self):
        if self.matched:  # A, phi are matched to the initial state: x(0) = x0, v(0) = v0
            x0, v0 = self._state(0.0)
        else:  # A = A0, phi = phi0 (eq. 8)
            x0, v0 = self.A * jnp.cos(self.phi), -self.omega0 * self.A * jnp.sin(self.phi)
        return self.osc, x0, v0

    def _rest(self, x):
        """x0 where the block is stuck from the start (there A = 0: x is 0, NaN for t < 0)."""
        return jnp.where(self.stuck, x + self.x0, x)

    @property
    def halt_time(self) -> Array:
        """tau of eq. 37: when the model comes to rest (inf when it never does, 0 for a start
        at rest inside the band); NaN where the model does not exist."""
        return self._mask(self.tau)

    @property
    def halt_position(self) -> Array:
        """Where the model comes to rest: x(tau) = 0 when it halts (x0 for a start at rest
        inside the band), NaN when it never does."""
        return self._mask(jnp.where(self.stuck, self.x0,
                                    jnp.where(jnp.isfinite(self.tau), 0.0, jnp.nan)))

    def _decay(self) -> _DecayConstants:
        """The per-point constants of f(t), shared by x, v and energy (computed once per call,
        outside the per-sample work)."""
        return _decay_constants(self.a, self.bp, self.c, self.tau)

    def f(self, t) -> Array:
        """Amplitude factor f(t) (eq. 20 in closed form), 0 after the halt."""
        return _decay_from(self._decay(), t)

    def _with_cubic(self, fn, operands):
        """``fn(kappa, beta, operands, cubic=...)``: with its cubic terms unless the spring is
        linear (known at trace time, or kappa = beta = 0 at run time: `if_cubic`)."""
        if self.linear:
            return fn(self.kappa, self.beta, operands, cubic=False)
        return if_cubic(functools.partial(fn, cubic=True), functools.partial(fn, cubic=False),
                        self.kappa, self.beta, operands)

    def _state(self, t):
        t = jnp.asarray(t, dtype=float)
        x, v = self._with_cubic(functools.partial(_state_terms, matched=self.matched),
                                (self.A, self.omega0, self.phi, self._decay(), t))
        return self._mask(self._rest(x)), self._mask(v)

    @jit_method
    def x(self, t) -> Array:
        """Displacement A f(t) cos(w0 t + phi) (eq. 11; with k3 see the class docstring)."""
        return self._state(t)[0]

    def _undamped_energy(self, f):
        """m w0^2 A^2 f^2 / 2 (eq. 10); k x0^2 / 2 for a start at rest inside the band."""
        return self._mask(jnp.where(self.stuck, 0.5 * self.osc.k * self._rest(0.0 * f) ** 2,
                                    0.5 * self.osc.m * (self.omega0 * self.A * f) ** 2))

    def v(self, t) -> Array:
        """Velocity: eq. 12 (matched) or eq. 9 (undamped phase)."""
        # x and v compiled together, as in `state` (XLA's fused multiply-adds depend on the
        # fusion: this keeps v bit for bit what it was before k3 when k3 = 0)
        return self.state(t)[1]

    @jit_method
    def state(self, t) -> tuple[Array, Array]:
        """(x(t), v(t)) together, sharing f(t), f'(t), cos and sin (eqs. 11-12 or 8-9)."""
        return self._state(t)

    def energy(self, t) -> Array:
        """Energy: k x^2/2 + m v^2/2 (eq. 15) or m w0^2 A0^2 f^2/2 (eq. 10)."""
        if self.matched:
            return self._energy_xv(t)[2]
        return self._energy_undamped(t)

    @jit_method
    def _energy_undamped(self, t):
        return self._undamped_energy(self.f(t))

    @jit_method
    def _energy_xv(self, t):
        """(x, v, energy) compiled together (see `v`)."""
        x, v = self._state(t)
        return x, v, self.osc.energy(x, v)

    def _x_energy(self, t, grid=None):
        if self.matched:
            x, v = self._state(t)
            return x, self.osc.energy(x, v)
        t = jnp.asarray(t, dtype=float)
        k = self._decay()
        f = _decay_from(k, t)
        x = self._with_cubic(_undamped_x, (self.A, self.omega0, self.phi, k, t, f))
        return self._mask(self._rest(x)), self._undamped_energy(f)

    # -- turning points: v = 0 <=> w0 t + phi = n pi + atan(f'/(w0 f)), one per half period --

    def _turning_residual(self, t, n, params):
        """G(t) = th(t) - n pi - atan(q f'/(w f)) and G'(t); G = 0 at turning point n.

        th = w0 t + phi (+ P(t)) and w = th' = w(A f) (w0 without cubic stiffness). With the
        third harmonic v = 0 reads tan th = q f'/(w f), q = (1 - 12 e s^2)/(1 + 8 e - 12 e s^2),
        e = beta f^2, s = sin th (q = 1 exactly when k3 = 0); G' leaves out dq/dt.
        """
        w0, ph, a, bp, c, tau, kappa, beta = params
        k = _decay_constants(a, bp, c, tau)
        f = _decay_from(k, t)
        f_safe = jnp.where(f > 0.0, f, 1.0)
        fp = -(a * f_safe**2 + bp * f_safe + c)
        fpp = -(2.0 * a * f_safe + bp) * fp
        dw = excess_frequency(f_safe, w0, kappa)
        w = w0 + dw
        w_dot = w0 * kappa * f_safe * fp / (w / w0)  # dw/dt
        r = fp / (w * f_safe)
        dr = (fpp * f_safe - fp * fp) / (w * f_safe * f_safe) - fp * w_dot / (w * w * f_safe)
        th = w0 * t + ph
        if not self.linear:  # P(t) = 0 exactly for a linear spring
            th = th + phase_excess(k, w0, kappa, t, f)
        e = beta * f_safe * f_safe
        s2 = jnp.sin(th) ** 2
        q = (1.0 - 12.0 * e * s2) / (1.0 + 8.0 * e - 12.0 * e * s2)
        r, dr = r * q, dr * q
        if not self.matched:  # eq. 9: v ~ sin(w0 t + phi0)
            r, dr = 0.0 * r, 0.0 * dr
        return th - n * jnp.pi - jnp.arctan(r), (w0 + excess_frequency(f, w0, kappa)) - dr / (
            1.0 + r * r)

    def _params(self):
        return (self.omega0, self.phi, self.a, self.bp, self.c, self.tau, self.kappa,
                self.beta)

    def _turning_newton(self, n):
        """Turning point n (v = 0 near w0 t + phi = n pi) by Newton's method, no gradient."""
        frozen = jax.lax.stop_gradient(self._params())
        # the iterates stay short of the halt: at t = tau itself f is 0 or a rounding error
        # away from it, whichever the compiled program gives (it differed between jit and
        # vmap), and at f = 0 the residual is meaningless (Newton stuck at tau and missed a
        # turning point just before the halt); one that ends at the cap found none: tau
        tau = frozen[5]
        t_max = tau * (1.0 - 1e-9)

        def newton(_, t):
            val, der = self._turning_residual(t, n, frozen)
            return jnp.clip(t - val / der, 0.0, t_max)

        t = jnp.clip((n * jnp.pi - frozen[1]) / frozen[0], 0.0, t_max)
        t = jax.lax.fori_loop(0, 6, newton, t)
        return jnp.where(t >= t_max, tau, t)

    def _turning_refine(self, n, t):
        """One Newton step at the converged t: exact first derivatives (implicit function)."""
        val, der = self._turning_residual(t, n, self._params())
        return t - val / der

    def _turning_time(self, n):
        """Turning point n with derivatives w.r.t. the parameters."""
        return self._turning_refine(n, self._turning_newton(n))

    def _first_index(self):
        """Index n of the first turning point w0 t + phi = n pi + atan(f'/(w0 f)) with t > 0."""
        w_a = self.omega0 + excess_frequency(1.0, self.omega0, self.kappa)
        s2 = jnp.sin(self.phi) ** 2
        q0 = (1.0 - 12.0 * self.beta * s2) / (1.0 + 8.0 * self.beta - 12.0 * self.beta * s2)
        r0 = decay_rate(1.0, self.a, self.bp, self.c) / w_a * q0 if self.matched else 0.0
        return jax.lax.stop_gradient(
            jnp.floor((self.phi - jnp.arctan(r0)) / jnp.pi + 1e-9) + 1.0)

    @eqx.filter_jit
    def turning_points(self, n: int):
        """First n turning points (t_k, x_k), t_k > 0, before the halt; NaN-padded."""
        ks = self._first_index() + jnp.arange(n, dtype=float)
        ts = jax.vmap(self._turning_time)(ks)
        ok = (ts > 0.0) & (ts < self.tau) & self.valid
        ts_safe = jnp.where(ok, ts, 0.0)
        xs = self.x(ts_safe)
        return jnp.where(ok, ts, jnp.nan), jnp.where(ok, xs, jnp.nan)


def solve_ansatz(osc: Oscillator, x0, v0, *, phase: str = "matched",
                 linear: bool | None = None) -> AnsatzSolution:
    """Ansatz solution x(t) = A f(t) cos(w0 t + phi) (Lelas & Pezer eqs. 11-24 or 8-10).

    Arguments:
        osc: the Oscillator.
        x0, v0: initial displacement and velocity.
        phase: "matched" (A, phi from eqs. 22-23) or "undamped" (A0, phi0; eqs. 8-10).
        linear: True states that k3 is a constant 0 (the cubic terms are left out at trace
            time); None: `known_linear` (k3 a value 0, not traced).

    Returns:
        An :class:`AnsatzSolution`: ``result`` is ``RESULTS.invalid_constants`` or
        ``nonfinite_state`` outside every model's domain, ``ansatz_overdamped`` where
        d1 = b/(2m) >= w0, ``no_amplitude`` where eq. 22 has no admissible root; a start at rest
        inside the sticking band stays there (x = x0, halt time 0).
    """
    if phase not in ("matched", "undamped"):
        raise ValueError(f"phase must be 'matched' or 'undamped', got {phase!r}")
    x_start, v_start = jnp.asarray(x0, dtype=float), jnp.asarray(v0, dtype=float)
    linear = known_linear(osc) if linear is None else bool(linear)
    stuck = stuck_at_start(osc, x_start, v_start)
    # stuck: the model is solved from the origin (its trivial, gradient-safe branch, A = 0)
    # and x0 added back (AnsatzSolution._rest)
    x0 = jnp.where(stuck, 0.0, x_start)
    v0 = jnp.where(stuck, 0.0, v_start)
    w0 = osc.omega0
    d0, d1, d2 = osc.damping_coefficients
    A0, phi0 = initial_amplitude_phase(osc, x0, v0)
    at_rest = A0 == 0.0
    A0_safe = jnp.where(at_rest, 1.0, A0)
    if phase == "matched":
        cphi = jnp.where(at_rest, 1.0, jnp.asarray(x0, dtype=float) / A0_safe)
        sphi = jnp.where(at_rest, 0.0, -jnp.asarray(v0, dtype=float) / (w0 * A0_safe))
        e0, e1, e2 = d0 / (w0 * A0_safe), d1 / w0, d2 * A0_safe / w0
        y, h, valid = matched_amplitude(cphi, sphi, e0, e1, e2)
        usable = valid & ~at_rest
        phi_lin = jnp.arctan2(jnp.where(usable, h, 0.0), jnp.where(usable, cphi, 1.0))
        # cubic stiffness: Newton corrections from the linear match (exactly 0 when k3 = 0)
        e3 = jnp.where(usable, osc.k3 * A0_safe * A0_safe / osc.k, 0.0)
        if linear:  # every correction is exactly 0
            dy = dphi = jnp.zeros_like(y)
            ok3 = jnp.ones_like(valid)
        else:
            dy, dphi, ok3 = cubic_match(jnp.where(usable, y, 1.0), phi_lin, e0, e1, e2, e3)
        dy = jnp.where(usable, dy, 0.0)
        dphi = jnp.where(usable, dphi, 0.0)
        valid = valid & ok3
        usable = valid & ~at_rest
        valid = valid | at_rest
        A = jnp.where(at_rest, 0.0, A0_safe * jnp.where(usable, y + dy, 1.0))
        phi = jnp.where(usable, phi_lin + dphi, 0.0)
        A_div = jnp.where(at_rest, 1.0, A)
    else:
        A, phi, A_div = A0, phi0, A0_safe
        valid = jnp.ones_like(A0, dtype=bool)
    a = d2 * A_div
    c = d0 / A_div
    bp = d1 + 0.0 * a
    tau = jnp.where(at_rest, 0.0, halt_time(a, bp, c))
    kappa = 0.75 * osc.k3 * A * A / osc.k
    beta = osc.k3 * A * A / (32.0 * osc.k)
    # w(A f)^2 = w0^2 (1 + kappa f^2) must stay > 0 for 0 <= f <= 1 (a softening spring)
    valid = valid & (1.0 + kappa > 0.0)
    # the undamped phase (eqs. 8-10) has no cubic stiffness; the matched phase has
    ((cubic, no_cubic),) = cubic_checks(osc)
    if phase == "matched":
        cubic = cubic & False
    result = first_failure(*input_checks(osc, x_start, v_start),
                           (cubic & ~stuck, no_cubic),
                           (~stuck & ~(d1 < w0), RESULTS.ansatz_overdamped),
                           (~stuck & ~valid, RESULTS.no_amplitude))
    return AnsatzSolution(A=A, phi=phi, omega0=w0 + 0.0 * A, a=a, bp=bp, c=c,
                          tau=tau, osc=osc, result=result, stuck=stuck,
                          x0=x_start, kappa=kappa, beta=beta, matched=phase == "matched",
                          linear=linear)


