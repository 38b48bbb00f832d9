"""Exact Coulomb (+ viscous) half-swings, the Coulomb tail of the ansatz, and Rizcallah's model.

Half-swing map (docs/DESIGN.md 2.4, 2.6): from rest at x_j with |x_j| > xc the block swings
about the shifted centre sgn(x_j) xc. With viscous damping gamma = b/(2m) the swing is a damped
cosine of half period pi/wd, wd = sqrt(w0^2 - gamma^2), and with rho = exp(-gamma pi/wd) the turning
points obey |x_(j+1)| = rho (|x_j| - xc) - xc, i.e. e_j - e* = rho^j (e_0 - e*) with
e* = -xc (1 + rho)/(1 - rho). Position and velocity at any t, the number of swings and the rest
point are therefore closed-form: no loop over swings, jit/vmap/grad-safe.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp

from .._oscillator import Oscillator, initial_amplitude_phase, jit_method
from .._trig import sincos
from ._ansatz import AnsatzSolution
from ._decay import _atanc
from ._solution import (
    RESULTS,
    AbstractSolution,
    cubic_checks,
    first_failure,
    input_checks,
    is_successful,
    result_where,
    stuck_at_start,
)

Array = jax.Array


def _sign(x):
    return jnp.where(x >= 0.0, 1.0, -1.0)


def compact(ts, xs, ok, n: int):
    """Keep the entries where ``ok`` holds, in order, in arrays of static length n (NaN-padded)."""
    pos = jnp.where(ok, jnp.cumsum(ok) - 1, n)
    out_t = jnp.full((n,), jnp.nan).at[pos].set(jnp.where(ok, ts, jnp.nan), mode="drop")
    out_x = jnp.full((n,), jnp.nan).at[pos].set(jnp.where(ok, xs, jnp.nan), mode="drop")
    return out_t, out_x


class _PiecewiseSolution(AbstractSolution):
    """x(t), v(t) and energy(t) of a model that defines ``_state(t) -> (x, v)`` and ``osc``."""

    @jit_method
    def x(self, t) -> Array:
        """Displacement at time(s) t."""
        return self._state(t)[0]

    @jit_method
    def v(self, t) -> Array:
        """Velocity at time(s) t."""
        return self._state(t)[1]

    @jit_method
    def energy(self, t) -> Array:
        """Energy k x^2/2 + m v^2/2 (eq. 4)."""
        return self.osc.energy(*self._state(t))

    def _x_energy(self, t, grid=None):
        x, v = self._state(t)
        return x, self.osc.energy(x, v)


class SwingSolution(_PiecewiseSolution):
    """Exact motion under Coulomb friction (+ viscous damping) from the state (t_s, x_s, v_s).

    Before t_s the solution is undefined (NaN). If v_s != 0 a first partial swing runs to the
    velocity zero (t1, x1); from there whole half-swings follow until |x| <= xc (rest).
    """

    t_start: Array
    x_start: Array
    v_start: Array
    t1: Array
    x1: Array
    n_swings: Array  # number of whole half-swings from (t1, x1) to rest; inf if never
    xc: Array
    gamma: Array
    omega0: Array
    omegad: Array
    osc: Oscillator
    result: RESULTS

    @property
    def model(self) -> str:
        """"coulomb_exact" (the registry name)."""
        return "coulomb_exact"

    def _atlas_start(self):
        return self.osc, self.x_start, self.v_start

    @property
    def half_period(self):
        return jnp.pi / self.omegad

    def _log_rho(self):
        return -self.gamma * self.half_period

    def _e(self, j):
        """Signed distance e_j of turning point j from the origin (|x_j| while e_j > 0)."""
        L = self._log_rho()
        lin = L == 0.0
        L_safe = jnp.where(lin, -1.0, L)
        G = jnp.where(lin, j + 0.5 * j * (j - 1.0) * L, jnp.expm1(j * L_safe) / jnp.expm1(L_safe))
        e0 = jnp.abs(self.x1)
        return jnp.exp(j * L) * e0 - self.xc * (1.0 + jnp.exp(L)) * G

    def _x_turn(self, j):
        parity = 1.0 - 2.0 * jnp.mod(j, 2.0)
        return _sign(self.x1) * parity * self._e(j)

    @property
    def halt_time(self):
        """When the block comes to rest (inf without friction; NaN where not valid)."""
        t = jnp.where(jnp.isfinite(self.n_swings),
                      self.t1 + jnp.where(jnp.isfinite(self.n_swings), self.n_swings, 0.0)
                      * self.half_period, jnp.inf)
        return self._mask(t)

    @property
    def halt_position(self):
        """Where the block comes to rest (NaN where it never does or not valid)."""
        J = jnp.where(jnp.isfinite(self.n_swings), self.n_swings, 0.0)
        return jnp.where(jnp.isfinite(self.n_swings) & self.valid, self._x_turn(J), jnp.nan)

    def _state(self, t):
        t = jnp.asarray(t, dtype=float)
        g, wd, w0, xc = self.gamma, self.omegad, self.omega0, self.xc
        # first partial swing (only when the start has a velocity)
        sv = _sign(self.v_start)
        cen0 = -sv * xc
        U = self.x_start - cen0
        V = self.v_start
        B = (V + g * U) / wd
        K = (g * V + w0 * w0 * U) / wd
        tau0 = jnp.clip(t - self.t_start, 0.0, None)
        # whole half-swings from (t1, x1)
        h = self.half_period
        J = self.n_swings
        j = jnp.floor(jnp.clip(t - self.t1, 0.0, None) / h)
        resting = j >= J
        j = jnp.where(resting, jnp.where(jnp.isfinite(J), J, 0.0), j)
        xj = self._x_turn(j)
        cen = _sign(xj) * xc
        tau = jnp.clip(t - self.t1 - j * h, 0.0, h)
        # one exp, cos and sin per time, at the elapsed time of the branch that is taken
        first = t < self.t1
        tau_t = jnp.where(first, tau0, tau)
        ex = jnp.exp(-g * tau_t)
        sw, cw = sincos(wd * tau_t)
        x_a = cen0 + ex * (U * cw + B * sw)
        v_a = ex * (V * cw - K * sw)
        x_b = jnp.where(resting, xj, cen + (xj - cen) * ex * (cw + (g / wd) * sw))
        v_b = jnp.where(resting, 0.0, -(xj - cen) * ex * (w0 * w0 / wd) * sw)
        x = jnp.where(first, x_a, x_b)
        v = jnp.where(first, v_a, v_b)
        before = (t < self.t_start) | ~self.valid
        return jnp.where(before, jnp.nan, x), jnp.where(before, jnp.nan, v)

    @eqx.filter_jit
    def turning_points(self, n: int):
        """First n velocity zeros after the start (the rest point is the last); NaN-padded."""
        moving = self.v_start != 0.0
        i = jnp.arange(n, dtype=float)
        j = i + jnp.where(moving, 0.0, 1.0)
        ok = (j <= self.n_swings) & self.valid
        j_safe = jnp.where(ok, j, 0.0)
        ts = self.t1 + j_safe * self.half_period
        xs = self._x_turn(j_safe)
        return jnp.where(ok, ts, jnp.nan), jnp.where(ok, xs, jnp.nan)


def swings_from(osc: Oscillator, t_s, x_s, v_s) -> SwingSolution:
    """Exact Coulomb (+ viscous) motion from the state (t_s, x_s, v_s); docs/DESIGN.md 2.4, 2.6.

    Arguments:
        osc: the oscillator; its D is not used (the caller checks D = 0 where it matters).
            Needs underdamping, b < 2 sqrt(k m) (else ``RESULTS.overdamped``), unless the
            block is at rest inside the band |x_s| <= xc (it stays there);
            ``RESULTS.invalid_constants`` outside every model's domain.
        t_s, x_s, v_s: start time and state.

    Returns:
        A :class:`SwingSolution`.
    """
    t_s, x_s, v_s, xc, gamma, w0 = (jnp.asarray(v, dtype=float)
                                    for v in (t_s, x_s, v_s, osc.xc, osc.gamma, osc.omega0))
    underdamped = gamma < w0
    stuck = stuck_at_start(osc, x_s, v_s)
    # the half-swings are those of the linear spring: k3 != 0 is out of their domain (a block
    # at rest inside the band stays there whatever the spring)
    ((cubic, no_cubic),) = cubic_checks(osc)
    result = first_failure(*input_checks(osc, x_s, v_s), (cubic & ~stuck, no_cubic),
                           (~(underdamped | stuck), RESULTS.overdamped))
    valid = is_successful(result)
    wd = jnp.sqrt(jnp.where(valid & underdamped, w0 * w0 - gamma * gamma, 1.0))
    moving = v_s != 0.0
    # first partial swing: u = x - cen0 is a damped cosine; its velocity vanishes at
    # wd tau1 = atan2(|V|, sgn(V) K) in (0, pi). A start at rest is the limit of a velocity
    # away from the centre (sgn(V) = sgn(x_s)): tau1 = 0 and x1 = x_s, as the formulas give
    # at V = 0, so they are not masked and a derivative in v_s at rest is that one-sided one
    # (it was cut to 0: dx/dv0 = 0 at v0 = 0, sin(w0 t)/w0 without damping; helper audit)
    sv = jnp.where(moving, _sign(v_s), _sign(x_s))
    cen0 = -sv * xc
    U = x_s - cen0
    V = v_s
    K = (gamma * V + w0 * w0 * U) / wd
    K = jnp.where(moving | (K != 0.0), K, 1.0)  # (at rest at the centre: no 0/0 in atan2)
    th1 = jnp.arctan2(sv * V, sv * K)
    tau1 = th1 / wd
    B = (V + gamma * U) / wd
    x_end = cen0 + jnp.exp(-gamma * tau1) * (U * jnp.cos(th1) + B * jnp.sin(th1))
    # at rest x_end is x_s to rounding: x_s exactly (x_s - x_end exact, Sterbenz), its tangent
    x1 = jnp.where(moving, x_end, x_end + jax.lax.stop_gradient(x_s - x_end))
    t1 = t_s + tau1
    # number of whole half-swings until |x| <= xc
    e0 = jnp.abs(x1)
    L = -gamma * jnp.pi / wd
    if osc.mu_s is None:
        halts = xc > 0.0
        xc_safe = jnp.where(halts, xc, 1.0)
        over = (e0 - xc) / (2.0 * xc_safe)
        L_safe = jnp.where(L == 0.0, -1.0, L)
        j_star = jnp.where(L == 0.0, over, jnp.log1p(-jnp.expm1(L_safe) * over) / (-L_safe))
        n_swings = jax.lax.stop_gradient(
            jnp.where(e0 <= xc, 0.0, jnp.where(halts, jnp.ceil(j_star - 1e-9), jnp.inf)))
    else:
        n_swings = _static_swings(e0, xc, jnp.asarray(osc.x_static, dtype=float), L)
    return SwingSolution(t_start=t_s, x_start=x_s, v_start=v_s, t1=t1, x1=x1,
                         n_swings=n_swings, xc=xc, gamma=gamma, omega0=w0, omegad=wd,
                         osc=osc, result=result)


def _static_swings(e0, xc, xs, L):
    """Whole half-swings from the turning point |x| = e0 until the first one inside the static
    band |x| <= xs (>= xc, the sliding band; mu_s of ``Oscillator``).

    The turning points obey e_j - e* = rho^j (e0 - e*), e* = -xc (1 + rho)/(1 - rho),
    rho = exp(L), so e_j <= xs from j* = log((e0 - e*)/(xs - e*)) / (-L)
    = log1p((1 - rho) (e0 - xs)/(xs (1 - rho) + xc (1 + rho))) / (-L), (e0 - xs)/(2 xc) when
    L = 0. Never (inf) when the denominator vanishes (no friction, or no viscous damping and
    no sliding friction). Held fixed (``stop_gradient``): a count.
    """
    one_minus_rho = -jnp.expm1(L)
    denom = xs * one_minus_rho + xc * (2.0 - one_minus_rho)
    halts = denom > 0.0
    denom_safe = jnp.where(halts, denom, 1.0)
    L_safe = jnp.where(L == 0.0, -1.0, L)
    xc_safe = jnp.where(xc > 0.0, xc, 1.0)
    j_star = jnp.where(L == 0.0, (e0 - xs) / (2.0 * xc_safe),
                       jnp.log1p(one_minus_rho * (e0 - xs) / denom_safe) / (-L_safe))
    return jax.lax.stop_gradient(
        jnp.where(e0 <= xs, 0.0, jnp.where(halts, jnp.ceil(j_star - 1e-9), jnp.inf)))


def solve_coulomb_exact(osc: Oscillator, x0, v0) -> SwingSolution:
    """Exact solution of eq. 3 with sliding friction (and viscous damping), D = 0.

    Half-swing by half-swing from any initial state, including a start at rest inside the
    sticking band (the block stays there, for any b and D). Exact for mu >= 0,
    0 <= b < 2 sqrt(k m), D = 0; with D != 0 ``result`` is ``RESULTS.no_drag``.
    """
    sol = swings_from(osc, 0.0, x0, v0)
    drag = (osc.D != 0.0) & ~stuck_at_start(osc, x0, v0)
    return eqx.tree_at(lambda s: s.result, sol,
                       result_where(sol.valid & drag, RESULTS.no_drag, sol.result))


# ----------------------------------------------------------------------------------------------
# the ansatz with the exact Coulomb tail (eqs. 41, 52, 54)


class TailSolution(AbstractSolution):
    """The ansatz up to a turning point (t_s, x_s), the exact Coulomb (+ viscous) motion after.

    Eqs. 41 and 52 (``back=0``: the last turning point with |x| > xc) and 54 (``back=1``: the
    one before it), generalised to any number of swings and to viscous damping in the tail.
    """

    ansatz: AnsatzSolution
    tail: SwingSolution
    t_switch: Array
    n_before: Array  # ansatz turning points (t > 0) up to and including t_switch
    found: Array  # the search window bracketed the last turning point outside the band

    @property
    def model(self) -> str:
        """"matched_tail" (the registry name)."""
        return "matched_tail"

    def _atlas_start(self):
        return self.ansatz._atlas_start()

    @property
    def amplitude(self):
        return self.ansatz.amplitude

    @property
    def phase(self):
        return self.ansatz.phase

    @property
    def result(self) -> RESULTS:
        """The ansatz's reason, else the tail's, else whether the switch point was found."""
        return first_failure((~self.ansatz.valid, self.ansatz.result),
                             (~self.tail.valid, self.tail.result),
                             (~self.found, RESULTS.tail_not_bracketed))

    @property
    def halt_time(self):
        """The tail's halt time (NaN where the solution is not valid)."""
        return self._mask(self.tail.halt_time)

    @property
    def halt_position(self):
        """The tail's halt position (NaN where the solution is not valid)."""
        return self._mask(self.tail.halt_position)

    def _pick(self, t, head, tail):
        t = jnp.asarray(t, dtype=float)
        early = t <= self.t_switch
        t_head = jnp.where(early, t, 0.0)
        t_tail = jnp.where(early, self.t_switch, t)
        # NaN wherever the piecewise solution is not valid (e.g. the switch point was not
        # bracketed), even where its two parts are
        return jax.tree_util.tree_map(
            lambda h, s: jnp.where(self.valid, jnp.where(early, h, s), jnp.nan),
            head(t_head), tail(t_tail))

    def _x_energy(self, t, grid=None):
        x, v = self._pick(t, self.ansatz._state, self.tail._state)
        return x, self.ansatz.osc.energy(x, v)

    @jit_method
    def x(self, t) -> Array:
        """Displacement: ansatz before the switch, exact Coulomb motion after."""
        return self._pick(t, self.ansatz.x, self.tail.x)

    @jit_method
    def v(self, t) -> Array:
        """Velocity of the piecewise motion (eqs. 42, 53)."""
        return self._pick(t, self.ansatz.v, self.tail.v)

    @jit_method
    def energy(self, t) -> Array:
        """Energy k x^2/2 + m v^2/2 (eq. 4) of the piecewise motion."""
        return self.ansatz.osc.energy(self.x(t), self.v(t))

    @eqx.filter_jit
    def turning_points(self, n: int):
        """The ansatz's turning points up to the switch, then the exact tail's."""
        ta, xa = self.ansatz.turning_points(n)
        tt, xt = self.tail.turning_points(n)
        i = jnp.arange(n)
        k = self.n_before.astype(int)
        head = i < k
        idx = jnp.clip(i - k, 0, n - 1)
        in_tail = (i - k) < n
        ts = jnp.where(head, ta, jnp.where(in_tail, tt[idx], jnp.nan))
        xs = jnp.where(head, xa, jnp.where(in_tail, xt[idx], jnp.nan))
        return ts, xs


def with_coulomb_tail(sol: AnsatzSolution, osc: Oscillator, x0, v0, *, back: int = 0,
                      window: int = 8) -> TailSolution:
    """Attach the exact Coulomb tail to an ansatz solution (eqs. 41, 52, 54 generalised).

    The last turning point with |x| > xc is located without scanning: f(t*) = xc/A is inverted
    in closed form, which gives the half-period index, and Newton's method refines the few
    turning points around it. When ``back`` reaches before the first turning point, or no
    turning point lies outside the band, the exact motion starts at t = 0 from (x0, v0).
    """
    if back < 0:
        raise ValueError(f"back must be >= 0, got {back}")
    xc = osc.x_static  # the static band (the sliding band xc when mu_s is None)
    frozen = jax.lax.stop_gradient((sol.A, sol.a, sol.bp, sol.c, sol.phi, sol.omega0, xc))
    A_, a_, bp_, c_, ph_, w0_, xc_ = frozen
    F = jnp.clip(xc_ / jnp.where(A_ > 0.0, A_, 1.0), 0.0, 1.0)
    T_star = (1.0 - F) / (c_ + 0.5 * bp_ + (a_ + 0.5 * bp_) * F)
    t_star = jnp.where(F >= 1.0, 0.0, _atanc(0.25 * bp_ * bp_ - a_ * c_, T_star))
    n_first = sol._first_index()
    n_est = jnp.floor((w0_ * jnp.minimum(t_star, sol.tau) + ph_) / jnp.pi)
    n_lo = jnp.maximum(n_first, jnp.where(jnp.isfinite(n_est), n_est, n_first) - 3.0)
    ns = n_lo - back + jnp.arange(window + back, dtype=float)  # back reaches into the window
    ts = jax.vmap(sol._turning_newton)(ns)
    xs = sol.x(jnp.where(jnp.isfinite(ts), ts, 0.0))
    ok = (ts > 0.0) & (ts < sol.tau) & (jnp.abs(xs) > xc_)
    n_last = jnp.max(jnp.where(ok, ns, -jnp.inf))
    n_s = n_last - back
    from_start = ~(n_s >= n_first) | (xc_ <= 0.0)
    n_s_safe = jnp.where(from_start, n_first, n_s)
    t_s = sol._turning_refine(n_s_safe, ts[jnp.clip((n_s_safe - ns[0]).astype(int), 0,
                                                    window + back - 1)])
    x_s = sol.x(t_s)
    never = xc_ <= 0.0  # no Coulomb friction: the ansatz holds for all t
    t_switch = jnp.where(never, jnp.inf, jnp.where(from_start, 0.0, t_s))
    tail = swings_from(osc, jnp.where(from_start, 0.0, t_s), jnp.where(from_start, x0, x_s),
                       jnp.where(from_start, v0, 0.0))
    # estimate window must bracket the last admissible turning point
    bracketed = (~ok[-1]) & (ok[back] | (n_lo <= n_first) | from_start)
    n_before = jnp.where(from_start | never, jnp.where(never, 10**9, 0), n_s_safe - n_first + 1)
    return TailSolution(ansatz=sol, tail=tail, t_switch=t_switch, n_before=n_before,
                        found=bracketed | never)


# ----------------------------------------------------------------------------------------------
# Rizcallah's sinusoidal friction (docs/DESIGN.md 2.5)


class RizcallahSolution(_PiecewiseSolution):
    """x(t) = (A0 - d t) cos(w0 t + phi0) + (d/w0) cos(phi0) sin(w0 t), at rest after the halt.

    Rizcallah (2019) replaces the friction force by its first harmonic kappa mu m g
    sin(w0 t + phi0); d = kappa mu g/(2 w0). The halt is the first turning point with
    |x| <= xc (the exact solution's criterion); where the turning points jump over the band
    (kappa > 4/pi), the turning point nearest the band before the envelope's zero.
    """

    amplitude0: Array
    phase0: Array
    omega0: Array
    d: Array
    xc: Array
    t_halt: Array  # the halt, also where not valid (see ``halt_time``)
    x_halt: Array
    osc: Oscillator
    result: RESULTS

    @property
    def model(self) -> str:
        """"rizcallah" (the registry name)."""
        return "rizcallah"

    @property
    def halt_time(self) -> Array:
        """The first turning point inside the band (inf without friction); NaN where not
        valid."""
        return self._mask(self.t_halt)

    @property
    def halt_position(self) -> Array:
        """Where the block comes to rest; NaN where it never does or not valid."""
        return self._mask(self.x_halt)

    def _atlas_start(self):
        A0, ph = self.amplitude0, self.phase0
        # the atlas holds kappa = 4/pi only: kappa = 2 w0 d / (mu g)
        osc = self.osc
        kappa = 2.0 * self.omega0 * self.d / jnp.where(osc.mu > 0.0, osc.mu * osc.g, 1.0)
        same = (osc.mu == 0.0) | (jnp.abs(kappa - 4.0 / math.pi) < 1e-9)
        return (osc, jnp.where(same, A0 * jnp.cos(ph), jnp.nan),
                -self.omega0 * A0 * jnp.sin(ph))

    def _free(self, t):
        t = jnp.asarray(t, dtype=float)
        w0, d, ph = self.omega0, self.d, self.phase0
        # one cos and sin per time: those of w0 t + phi0 by the addition theorems
        sw, cw = sincos(w0 * t)
        cph, sph = jnp.cos(ph), jnp.sin(ph)
        cth, sth = cw * cph - sw * sph, sw * cph + cw * sph
        x = (self.amplitude0 - d * t) * cth + (d / w0) * cph * sw
        v = -d * cth - w0 * (self.amplitude0 - d * t) * sth + d * cph * cw
        return x, v

    def _state(self, t):
        t = jnp.asarray(t, dtype=float)
        done = t >= self.t_halt
        x, v = self._free(jnp.where(done, 0.0, t))
        x = jnp.where(done, self.x_halt, x)
        v = jnp.where(done, 0.0, v)
        bad = (t < 0.0) | ~self.valid
        return jnp.where(bad, jnp.nan, x), jnp.where(bad, jnp.nan, v)

    def _psi(self, t, params):
        """Angle psi(t) with v = 0 <=> w0 t = psi(t) + n pi, continuous in t.

        v = u_y cos(w0 t) - u_x sin(w0 t) with u(t) linear in t, so psi(t) - psi(0), the angle
        swept by u along a straight segment, is below pi and atan2 needs no unwrapping.
        """
        A0, ph, w0, d = params
        cph, sph = jnp.cos(ph), jnp.sin(ph)

        def u(t):
            P = (A0 - d * t) * cph
            Q = -(A0 - d * t) * sph + (d / w0) * cph
            return w0 * P - d * sph, -d * cph + w0 * Q

        ux0, uy0 = u(0.0)
        ux, uy = u(t)
        # cross(u0, u') = -w0 d^2 sin^2(phi0): from rest (or without friction) u runs through
        # the origin, where its angle jumps by pi; psi mod pi, all that matters, is constant
        line = (sph == 0.0) | (d == 0.0)
        swept = jnp.arctan2(ux0 * uy - uy0 * ux, ux0 * ux + uy0 * uy)
        return jnp.arctan2(uy0, ux0) + jnp.where(line, 0.0, swept)

    def _params(self):
        return (self.amplitude0, self.phase0, self.omega0, self.d)

    def _first_index(self):
        psi0 = self._psi(0.0, jax.lax.stop_gradient(self._params()))
        return jax.lax.stop_gradient(jnp.floor(-psi0 / jnp.pi + 1e-9) + 1.0)

    def _turning_time(self, n):
        """Turning point n: the root of G(t) = w0 t - psi(t) - n pi, by Newton's method."""
        params = self._params()
        frozen = jax.lax.stop_gradient(params)

        def G(t, p):
            return p[2] * t - self._psi(t, p) - n * jnp.pi

        def newton(_, t):
            val, der = jax.jvp(lambda s: G(s, frozen), (t,), (jnp.ones_like(t),))
            return t - val / der

        t = (n * jnp.pi + self._psi(0.0, frozen)) / frozen[2]
        t = jax.lax.fori_loop(0, 8, newton, t)
        val, der = jax.jvp(lambda s: G(s, params), (t,), (jnp.ones_like(t),))
        return t - val / der

    def _candidates(self, n_lo, count):
        ns = n_lo + jnp.arange(count, dtype=float)
        ts = jax.vmap(self._turning_time)(ns)
        xs = self._free(jnp.where(jnp.isfinite(ts), ts, 0.0))[0]
        return ts, xs

    @eqx.filter_jit
    def turning_points(self, n: int):
        """First n turning points with t > 0; the halting point is the last; NaN-padded."""
        ts, xs = self._candidates(self._first_index(), n + 1)
        eps = 1e-9 / self.omega0
        ok = (ts > eps) & (ts <= self.t_halt * (1 + 1e-12) + eps) & self.valid
        # past the envelope's zero Newton may land on an earlier root again: keep increasing t
        ok = ok & (ts > jnp.concatenate([jnp.array([-jnp.inf]), ts[:-1]]) + eps)
        return compact(ts, xs, ok, n)


def solve_rizcallah(osc: Oscillator, x0, v0, *, kappa: float = 4.0 / math.pi,
                    window: int = 8) -> RizcallahSolution:
    """Rizcallah's sinusoidal-friction solution for Coulomb damping (docs/DESIGN.md 2.5), any start.

    Arguments:
        osc: Oscillator with b = D = 0 (else ``valid`` is False).
        x0, v0: initial state.
        kappa: amplitude factor of the sinusoidal force: 4/pi (least squares, the paper's best),
            pi/2 (equal impulse) or sqrt(2) (equal rms).

    Returns:
        A :class:`RizcallahSolution`; for kappa = 4/pi and a start at rest its turning points
        at n pi/w0 equal the exact x_n = (-1)^n (x0 - 2 n xc). ``result`` is
        ``RESULTS.coulomb_only`` for b or D != 0, ``rizcallah_gains_energy`` where the model
        would come to rest beyond A0 (xc not small against A0), ``invalid_constants`` or
        ``nonfinite_state`` outside every model's domain; a start at rest inside the band stays
        there.
    """
    w0 = osc.omega0
    A0, phi0 = initial_amplitude_phase(osc, x0, v0)
    x0 = jnp.asarray(x0, dtype=float)
    v0 = jnp.asarray(v0, dtype=float)
    d = kappa * osc.mu * osc.g / (2.0 * w0)
    xc = osc.xc
    coulomb = (osc.b == 0.0) & (osc.D == 0.0)
    proto = RizcallahSolution(amplitude0=A0, phase0=phi0, omega0=w0, d=d, xc=xc,
                              t_halt=jnp.inf + 0.0 * A0, x_halt=jnp.nan + 0.0 * A0,
                              osc=osc, result=first_failure((~coulomb, RESULTS.coulomb_only)))
    # the envelope A0 - d t reaches xc near t*; search the turning points around it
    frozen = jax.lax.stop_gradient((A0, phi0, w0, d, xc))
    A0_, ph_, w0_, d_, xc_ = frozen
    halts = d_ > 0.0
    t_star = jnp.where(halts, jnp.clip(A0_ - xc_, 0.0, None) / jnp.where(halts, d_, 1.0), 0.0)
    n_first = proto._first_index()
    n_est = jnp.floor((w0_ * t_star - proto._psi(t_star, (A0_, ph_, w0_, d_))) / jnp.pi)
    n_lo = jnp.maximum(n_first, n_est - 3.0)
    ts, xs = proto._candidates(n_lo, window)
    eps = 1e-9 / w0_
    inside = (ts > eps) & (jnp.abs(xs) <= xc_)
    first = jnp.argmax(inside)
    found = jnp.any(inside)
    # kappa > 4/pi: the envelope loses kappa (pi/2) xc per half period, more than the band's
    # width 2 xc, so the turning points can jump over the band; the model then stops at the
    # turning point nearest the band, up to the first one after its envelope's zero A0/d
    # (after that its swings grow: Rizcallah's "unphysical artifact")
    t_zero = jnp.where(halts, A0_ / jnp.where(halts, d_, 1.0), jnp.inf)
    t_lim = jnp.min(jnp.where((ts > eps) & (ts >= t_zero), ts, jnp.inf))
    near = (ts > eps) & (ts <= t_lim) & jnp.isfinite(ts)
    nearest = jnp.argmin(jnp.where(near, jnp.abs(xs), jnp.inf))
    t_h = jnp.where(found, ts[first], jnp.where(jnp.any(near), ts[nearest], jnp.inf))
    x_h = jnp.where(found, xs[first], jnp.where(jnp.any(near), xs[nearest], jnp.nan))
    found = found | jnp.any(near)
    # a start at rest inside the band stays there
    stuck = (v0 == 0.0) & (jnp.abs(x0) <= osc.x_static)
    t_h = jnp.where(stuck, 0.0, t_h)
    x_h = jnp.where(stuck, x0, x_h)
    t_h = jnp.where(halts | stuck, t_h, jnp.inf)
    x_h = jnp.where(halts | stuck, x_h, jnp.nan)
    bracketed = found | stuck | ~halts
    # a start at rest inside the band is exact for any b and D: the block never moves
    # the exact motion only loses energy: a rest point beyond A0 is the model's artefact
    gains = ~stuck & (jnp.abs(x_h) > A0)
    ((cubic, no_cubic),) = cubic_checks(osc)
    result = first_failure(*input_checks(osc, x0, v0),
                           (cubic & ~stuck_at_start(osc, x0, v0), no_cubic),
                           (~(coulomb | stuck), RESULTS.coulomb_only),
                           (~bracketed, RESULTS.halt_not_found),
                           (gains, RESULTS.rizcallah_gains_energy))
    return eqx.tree_at(lambda s: (s.t_halt, s.x_halt, s.result), proto, (t_h, x_h, result))
