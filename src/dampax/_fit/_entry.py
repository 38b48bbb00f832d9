"""``dp.fit``: a single trace to :func:`~dampax._fit._api.fit`, a list of traces to the joint
fit :func:`~dampax._fit._joint.fit_joint` (kept apart so that ``_joint``, which fits each run
alone first, imports ``_api`` without a cycle)."""

from __future__ import annotations

import functools

from . import _api
from ._joint import fit_joint


@functools.wraps(_api.fit)
def fit(trace_or_t, x=None, **kwargs):
    if isinstance(trace_or_t, (list, tuple)) and x is None:
        if kwargs.get("p0") is not None:
            raise ValueError("p0: not supported by a joint fit of several runs")
        if kwargs.get("mu_s") is not None or "mu_s" in tuple(kwargs.get("free", ())):
            raise ValueError("mu_s: static friction is not supported by a joint fit of "
                             "several runs; fit each run alone")
        kwargs = {k: v for k, v in kwargs.items() if k not in ("p0", "mu_s")}
        return fit_joint(list(trace_or_t), **kwargs)
    return _api.fit(trace_or_t, x, **kwargs)
