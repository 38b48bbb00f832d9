"""Why a solution failed (:class:`RESULTS`) and the base every solution shares.

As in diffrax, a solution carries ``result``, a member of one enumeration whose message says
what went wrong and what to do about it. ``valid`` is ``result == RESULTS.successful``; under
``jit`` and ``vmap`` an invalid solution holds NaN values and its reason, and
``dampax.solve(..., throw=True)`` raises that reason at run time (``equinox.error_if``), even
inside ``jit``. Called eagerly, ``dampax.solve`` raises a ``ValueError`` with the message.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._oscillator import _value_text, unconfined
from ._atlas import estimate

Array = jax.Array


class RESULTS(eqx.Enumeration):
    """Outcome of a solve: ``successful`` or the reason the model gives no values here.

    Each member's message names the cause and the fix.
    """

    successful = ""
    nonfinite_state = "x0, v0: the initial state must be finite"
    no_amplitude = (
        "x0, v0: no admissible amplitude A of eq. 22 for this oscillator and initial state "
        "(the root branch connected to A0 ends in a fold; e.g. d2 |x0| >= w0 for quadratic "
        "damping): the matched ansatz does not exist here; use method='reference'")
    coulomb_only = ("b, D: Rizcallah's model is for Coulomb damping only (b = D = 0); use "
                    "method='ansatz' or 'reference'")
    no_drag = ("D: the exact half-swing solution has no quadratic drag (D must be 0); use "
               "method='reference'")
    overdamped = ("b: the exact half-swings need underdamping, b < 2 sqrt(k m); use "
                  "method='reference'")
    tail_not_bracketed = (
        "the Coulomb tail's search window did not bracket the last turning point outside the "
        "band |x| <= xc; use method='reference'")
    halt_not_found = (
        "Rizcallah's model: no turning point near the band |x| <= xc was found in the search "
        "window; use method='reference'")
    max_swings_reached = (
        "the reference ran out of its budget before t_end or the halt: increase max_swings or "
        "max_steps_per_swing, or shorten t_end")
    solver_failed = ("the reference's ODE solver failed (non-finite state or step size too "
                     "small); check the oscillator's parameters")
    invalid_constants = (
        "m, k, g must be finite and > 0; mu, b, D finite and >= 0; k3 finite: fix the "
        "Oscillator's fields")
    ansatz_overdamped = (
        "b: the ansatz oscillates at w0 and needs underdamping, d1 = b/(2m) < w0 = sqrt(k/m) "
        "(b < 2 sqrt(k m)); use method='reference'")
    invalid_t_end = "t_end: the reference's end time must be finite and > 0"
    rizcallah_gains_energy = (
        "mu: Rizcallah's model comes to rest farther out than its undamped amplitude A0, with "
        "more energy than it started with (friction too strong for the amplitude: xc is not "
        "small against A0); use method='reference'")
    unconfined = (
        "k3, x0, v0: the softening spring (k3 < 0) does not hold the block: the start lies at "
        "or beyond the potential's maximum |x| = sqrt(k/|k3|), or its energy reaches the "
        "barrier k^2/(4 |k3|), and the block escapes; start lower or use a smaller |k3|")
    no_cubic = (
        "k3: this model has no cubic stiffness (k3 must be 0); use method='ansatz' (matched "
        "phase, no tail) or method='reference'")
    static_friction = (
        "mu_s: static friction differs from sliding friction; this model assumes mu_s = mu: "
        "use method='reference', method='coulomb_exact' or tail='coulomb'")


def result_where(pred, a: RESULTS, b: RESULTS) -> RESULTS:
    """``a`` where ``pred`` holds, else ``b``; elementwise for an array ``pred``.

    (``RESULTS.where`` takes only a scalar predicate; solutions of an Oscillator with array
    fields carry an array of results.)
    """
    return eqx.tree_at(lambda r: r._value, a, jnp.where(pred, a._value, b._value))


def first_failure(*checks: tuple[Array, RESULTS]) -> RESULTS:
    """The result of a list of (failed, reason) checks: the first reason that holds.

    Arguments:
        checks: pairs of a boolean (array) that is True where the check fails and the
            :class:`RESULTS` member to report then, most fundamental first.

    Returns:
        ``RESULTS.successful`` where no check fails, else the first failing check's reason.
    """
    out = RESULTS.successful
    for failed, reason in reversed(checks):
        out = result_where(failed, reason, out)
    return out


def constants_ok(osc) -> Array:
    """True where the oscillator's constants are in every model's domain (elementwise).

    m, k and g must be finite and > 0; mu, b, D (and mu_s) finite and >= 0; k3 finite.
    Works on traced fields (under ``jit``/``vmap``), where the Oscillator's construction
    checks nothing.
    """
    ok = jnp.asarray(True)
    for value in (osc.m, osc.k, osc.g):
        ok = ok & jnp.isfinite(value) & (value > 0.0)
    for value in (osc.mu, osc.b, osc.D) + (() if osc.mu_s is None else (osc.mu_s,)):
        ok = ok & jnp.isfinite(value) & (value >= 0.0)
    return ok & jnp.isfinite(osc.k3)


def input_checks(osc, x0, v0) -> tuple[tuple[Array, RESULTS], ...]:
    """The (failed, reason) checks every model starts with (see :func:`first_failure`).

    Arguments:
        osc: the Oscillator; x0, v0: the initial state.

    Returns:
        ((constants out of domain, ``RESULTS.invalid_constants``), (x0 or v0 not finite,
        ``RESULTS.nonfinite_state``), (a softening spring that does not hold the block,
        ``RESULTS.unconfined``; see :func:`dampax._oscillator.unconfined`)).
    """
    x0 = jnp.asarray(x0, dtype=float)
    v0 = jnp.asarray(v0, dtype=float)
    return ((~constants_ok(osc), RESULTS.invalid_constants),
            (~(jnp.isfinite(x0) & jnp.isfinite(v0)), RESULTS.nonfinite_state),
            (unconfined(osc, x0, v0), RESULTS.unconfined))


def static_checks(osc, stuck) -> tuple[tuple[Array, RESULTS], ...]:
    """The check of the models that assume mu_s = mu: ((mu_s > mu and not at rest from the
    start, ``RESULTS.static_friction``),); no check at all when mu_s is None."""
    if osc.mu_s is None:
        return ()
    return ((osc.static_differs & ~stuck, RESULTS.static_friction),)


def cubic_checks(osc) -> tuple[tuple[Array, RESULTS], ...]:
    """The check of the models without a cubic stiffness: ((k3 != 0, ``RESULTS.no_cubic``),)."""
    return ((osc.k3 != 0.0, RESULTS.no_cubic),)


def stuck_at_start(osc, x0, v0) -> Array:
    """True where the block starts at rest inside the sticking band and never moves.

    v0 = 0 and |k x0 + k3 x0^3| <= mu_s m g (static friction holds the spring's pull;
    :meth:`Oscillator.sticks`, exactly |x0| <= xc = mu m g / k when k3 = 0); only where
    the constants are in the domain (:func:`constants_ok`). Every model then gives the trivial
    answer: x(t) = x0, v = 0, halt_time 0, halt_position x0.
    """
    x0 = jnp.asarray(x0, dtype=float)
    v0 = jnp.asarray(v0, dtype=float)
    return constants_ok(osc) & (v0 == 0.0) & osc.sticks(x0)


def is_successful(result: RESULTS) -> Array:
    """True where ``result`` is ``RESULTS.successful`` (the solution's ``valid``)."""
    return result == RESULTS.successful


def message(result: RESULTS) -> str:
    """The message of a concrete result: the first failure's, or "" when all succeeded."""
    values = np.asarray(result._value).ravel()
    failed = values[values != np.asarray(RESULTS.successful._value)]
    if failed.size == 0:
        return ""
    return RESULTS[eqx.tree_at(lambda r: r._value, RESULTS.successful, jnp.asarray(failed[0]))]


class AbstractSolution(eqx.Module):
    """What every solution of :func:`dampax.solve` offers.

    Subclasses provide ``result`` (a :class:`RESULTS`, a field or a property), ``x(t)``,
    ``v(t)``, ``energy(t)``, ``halt_time``, ``halt_position`` and ``turning_points(n)``.
    """

    @property
    def valid(self) -> Array:
        """True where the model gives values (``result`` is successful); else they are NaN."""
        return is_successful(self.result)

    def _mask(self, value):
        """``value`` where the solution is valid, NaN elsewhere (every model's values)."""
        return jnp.where(self.valid, value, jnp.nan)

    @property
    def model(self) -> str:
        """The registry name of the model (``dampax.MODELS``), e.g. "matched_tail"."""
        raise NotImplementedError(f"{type(self).__name__} names no model")

    def _atlas_start(self):
        """(oscillator, x0, v0) the atlas is read at for this solution, or None where it holds
        no estimate (the reference itself)."""
        return None

    @property
    def error_estimate(self) -> Array:
        """Expected max |x - x_ref| / A0 of this model for this oscillator and initial state.

        Interpolated from the error atlas shipped with dampax (``dampax._models._atlas``: error maps
        against the reference over d0/(w0 A0) <= 0.2, d1/w0 <= 0.4, d2 A0/w0 <= 1 and every
        phi0; the error over the motion up to the reference's halt, at most 20 undamped
        periods). NaN outside the atlas, where the model does not exist, and for the reference
        itself. Works under jit and vmap.
        """
        return solution_estimate(self)

    def _x_energy(self, t, grid=None) -> tuple[Array, Array]:
        """(x(t), energy(t)) together; subclasses share the work of the two (error maps).

        ``grid`` = (start, step) says that 1-D t is uniform; models that cannot use it ignore it.
        """
        return self.x(t), self.energy(t)

    @property
    def message(self) -> str:
        """Why the solution is not valid ("" when it is), for a concrete solution."""
        return message(self.result)

    def __repr__(self) -> str:
        names = [n for n in ("amplitude", "phase", "halt_time", "halt_position")
                 if hasattr(type(self), n) or n in self.__dataclass_fields__]
        body = [f"{n}={_value_text(getattr(self, n))}" for n in names]
        if isinstance(self.result._value, jax.core.Tracer):
            body.append("result=<traced>")
        else:
            body.append(f"result={self.message or 'successful'!r}")
        return f"{type(self).__name__}({', '.join(body)})"


def solution_estimate(sol: AbstractSolution, *, bound: bool = False) -> Array:
    """Expected (or, with ``bound``, upper) max |x - x_ref| / A0 of a solution: the atlas
    (``dampax._models._atlas``, data the models read) at the solution's start. NaN for the
    reference, off the atlas and for k3 != 0; 0 for a start at rest inside the band (exact)."""
    start = sol._atlas_start()
    if start is None:
        return jnp.asarray(jnp.nan)
    value = estimate(sol.model, *start, bound=bound)
    # the atlas holds the linear spring only (k3 = 0): no estimate with a cubic stiffness
    value = jnp.where(start[0].k3 != 0.0, jnp.nan, value)
    if start[0].mu_s is not None:  # nor with static friction above the sliding friction
        value = jnp.where(start[0].static_differs, jnp.nan, value)
    head = sol.ansatz if hasattr(sol, "ansatz") else sol
    if hasattr(head, "stuck"):  # at rest inside the band from the start: the answer is exact
        value = jnp.where(head.stuck, 0.0, value)
    return value
