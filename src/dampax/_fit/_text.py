"""Numbers in the fit's one-line messages, written so that they say what the sentence claims:
two costs that differ print different digits, and a stretch of time prints two different
ends (issue 36: "found a lower cost (0.03239 < 0.03239)", "worst around t = 2333-2333 s")."""

from __future__ import annotations

import math
import sys
import warnings


def _digits(a: float, b: float, least: int = 4) -> int:
    """Significant digits that tell a and b apart (at least ``least``, at most 15)."""
    if not (math.isfinite(a) and math.isfinite(b)) or a == b:
        return least
    size = max(abs(a), abs(b))
    return min(max(least, int(math.ceil(math.log10(size / abs(a - b)))) + 1), 15)


def lower_cost(new: float, old: float) -> str:
    """"new < old (x % lower)" with the digits that tell them apart."""
    d = _digits(new, old)
    rel = f", {100.0 * (old - new) / old:.2g} % lower" if old > 0 and math.isfinite(old) else ""
    return f"{new:.{d}g} < {old:.{d}g}{rel}"


def time_span(lo: float, hi: float) -> str:
    """"lo-hi s" with the digits that tell the ends apart (one time where they coincide)."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo == hi:
        return f"{lo:.6g} s"
    d = _digits(lo, hi)
    return f"{lo:.{d}g}-{hi:.{d}g} s"


def warn_user(message: str) -> None:
    """``warnings.warn(message)`` attributed to the first frame outside dampax: the user's
    line that called ``dp.fit`` (a fixed ``stacklevel`` pointed into dampax, e.g.
    ``_linalg.py``, as the depth of the call differs by path); in a thread that dampax
    started, its outermost frame."""
    frame, level = sys._getframe(1), 2
    while frame.f_back is not None and _ours(frame.f_globals.get("__name__", "")):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, stacklevel=level)


def _ours(module: str) -> bool:
    """Whether ``module`` is dampax's (not a user's module that only starts with its name)."""
    return module == "dampax" or module.startswith("dampax.")


#: the words of ``_assess.standard_errors``' failure where w0's interval reaches 0 (the k3
#: search reads them: ``_stiffness.fit_k3``)
NO_FREQUENCY = "the window does not determine the frequency"
