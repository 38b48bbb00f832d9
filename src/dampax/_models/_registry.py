"""The one registry of models: name, ``solve`` options, label, paper equations, domain, style.

Every part of dampax that names a model reads :data:`MODELS`: ``solve`` (its methods and
their domains), ``error_map``, ``sensitivity``, the plots, every ``dampax`` command and the
tests. A new model is one entry here (plus its solver behind ``dampax.solve``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from .._oscillator import Oscillator, as_float, check_choices


def _always(osc: Oscillator) -> bool:
    return True


def _has_friction(osc: Oscillator) -> bool:
    return as_float(osc.mu) > 0.0


def _underdamped(osc: Oscillator) -> bool:
    return as_float(osc.gamma) < as_float(osc.omega0)


def _tail_applies(osc: Oscillator) -> bool:
    return _has_friction(osc) and _underdamped(osc)


def _coulomb_only(osc: Oscillator) -> bool:
    return _has_friction(osc) and as_float(osc.b) == 0.0 and as_float(osc.D) == 0.0


def _exact_applies(osc: Oscillator) -> bool:
    return (_has_friction(osc) and as_float(osc.D) == 0.0
            and as_float(osc.gamma) < as_float(osc.omega0))


@dataclasses.dataclass(frozen=True)
class Model:
    """One model of :func:`dampax.solve`.

    Attributes:
        name: the one spelling used by the API, every command and the error maps.
        label: legend and table label.
        options: keyword arguments of :func:`dampax.solve` that select the model.
        equations: where it is in the papers.
        domain: in words, where the model is defined and worth drawing (``applies`` tests
            it). Every model also needs m, k, g finite and > 0, mu, b, D finite and >= 0 and a
            finite start; outside, ``solve`` sets ``valid = False`` with a ``RESULTS`` reason
            (ValueError eagerly). A start at rest inside the band (v0 = 0, k |x0| <= mu m g)
            is answered exactly by every model: the block stays at x0.
        applies: a concrete, scalar Oscillator -> whether the model is meant for it (the
            commands and plots leave the others out; ``solve`` still flags what it cannot do
            with ``result``).
        paper_ranges: the papers' stated ranges of validity (d2 A0/w0 at d0 = 0, d0/(w0 A0) at
            d2 = 0), for the error-map summary.
        color, linestyle, linewidth, zorder: how it is drawn (the papers' colour code: matched
            ansatz solid red, undamped phase solid blue, reference black dotted).
        lacks: the constants of the oscillator its equations leave out (held at 0: a
            derivative in them is no derivative of x, ``sensitivity`` refuses it).
    """

    name: str
    label: str
    options: tuple[tuple[str, object], ...]
    equations: str
    domain: str
    applies: Callable[[Oscillator], bool]
    color: str
    linestyle: str | tuple
    linewidth: float = 1.4
    zorder: float = 2.0
    paper_ranges: tuple[str, str] = ("-", "-")
    lacks: tuple[str, ...] = ()

    @property
    def solve_options(self) -> dict:
        """The keyword arguments of :func:`dampax.solve` as a dict."""
        return dict(self.options)

    @property
    def method(self) -> str:
        """The ``method`` of :func:`dampax.solve`."""
        return self.solve_options["method"]

    @property
    def style(self) -> dict:
        """matplotlib line properties (with the label)."""
        return dict(color=self.color, linestyle=self.linestyle, linewidth=self.linewidth,
                    zorder=self.zorder, label=self.label)


#: Every model, in table and legend order; ``reference`` is the DOP853 integrator of eq. 3.
MODELS: dict[str, Model] = {m.name: m for m in (
    Model("matched", "matched ansatz (eqs. 22-23)", (("method", "ansatz"),),
          "Lelas & Pezer eqs. 11, 20-23",
          "underdamped (b < 2 sqrt(k m)); needs an admissible root of eq. 22",
          _underdamped, "tab:red", "-", 2.0, 3.0, ("0.5 (III)", "0.05 (IV)*")),
    Model("undamped", "undamped-phase ansatz (eqs. 8-10)",
          (("method", "ansatz"), ("phase", "undamped")),
          "Lelas & Pezer eqs. 8-10", "underdamped (b < 2 sqrt(k m))", _underdamped, "tab:blue",
          "-", 1.6, 2.5,
          ("0.1 (eq. 25)", "0.03 (eq. 25)"), ("k3",)),
    Model("matched_tail", "matched + Coulomb tail (eqs. 41, 52)",
          (("method", "ansatz"), ("tail", "coulomb")),
          "Lelas & Pezer eqs. 41, 52, 54",
          "sliding friction (mu > 0), underdamped (b < 2 sqrt(k m))", _tail_applies,
          "tab:green", "-.", 1.6, 2.8, ("0.5 (III)", "0.05 (IV)"), ("k3",)),
    Model("rizcallah", "Rizcallah, sinusoidal friction (b = D = 0)", (("method", "rizcallah"),),
          "Rizcallah (2019)",
          "sliding friction only (mu > 0, b = D = 0), 0 < kappa <= 2; at rest no farther out "
          "than A0", _coulomb_only,
          "tab:orange", (0, (5, 2)), 1.4, 2.2, ("-", "-"), ("b", "D", "k3")),
    Model("coulomb_exact", "exact half-swings (D = 0)", (("method", "coulomb_exact"),),
          "Lelas & Pezer eq. 54 generalised; docs/DESIGN.md 2.6",
          "sliding friction, D = 0, underdamped (b < 2 sqrt(k m))", _exact_applies,
          "tab:purple", (0, (8, 3, 2, 3)), 1.4, 2.1, ("-", "exact"), ("D", "k3")),
    Model("reference", "reference (DOP853)", (("method", "reference"),),
          "eq. 3 integrated swing by swing (docs/DESIGN.md 2.6)", "every oscillator", _always,
          "black", ":", 2.0, 4.0),
)}

#: The analytic models (everything but the reference).
ANALYTIC = tuple(name for name, m in MODELS.items() if m.method != "reference")
#: The ``method`` names of :func:`dampax.solve`, in registry order.
METHODS = tuple(dict.fromkeys(m.method for m in MODELS.values()))


def check_models(models, name: str = "models", *, allowed=None) -> tuple[str, ...]:
    """Validate model names (a comma string or a sequence) against the registry.

    Arguments:
        models: "matched,reference" or ("matched", "reference").
        name: the argument or option named in the error (e.g. "--models").
        allowed: the names accepted here (default: all of :data:`MODELS`).

    Returns:
        The names as a tuple.

    Raises:
        ValueError: naming ``name``, for unknown, repeated or no names.
    """
    if isinstance(models, str):
        models = [s.strip() for s in models.split(",") if s.strip()]
    return check_choices(name, models, tuple(MODELS) if allowed is None else allowed)


def applicable_models(osc: Oscillator, *, reference: bool = True) -> tuple[str, ...]:
    """Names of the models meant for this (scalar) oscillator, in table order.

    Arguments:
        osc: a scalar :class:`~dampax.Oscillator`.
        reference: include the reference integrator.

    Returns:
        Keys of :data:`MODELS`: both ansatz phases when b < 2 sqrt(k m); the Coulomb tail
        when also mu > 0; Rizcallah's model when mu > 0 and b = D = 0; the exact half-swings
        when mu > 0, D = 0 and b < 2 sqrt(k m); the reference when asked for.
    """
    return tuple(k for k, m in MODELS.items()
                 if (k != "reference" or reference) and m.applies(osc))
