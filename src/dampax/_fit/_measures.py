"""What the checks of a trace fit measure on its residuals (``_assess``'s :data:`CHECKS`
share them): the residuals, their rms, the period, the intervals' covariance, the test
against AR(1) noise (:func:`measures`), and where structure in them sits: the half swing
whose residuals beyond the noise are largest against its amplitude (:func:`worst_swing`)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ._checks import residual_structure
from ._intervals import hac_covariance
from ._text import time_span


class Measures(NamedTuple):
    """What the later checks share: the residuals, the noise, the intervals' covariance (what
    conf_interval reports) and the residuals' test against AR(1) noise."""

    r: np.ndarray
    rms: float
    period: float
    cov: np.ndarray | None
    sd: dict
    st: dict


def measures(a) -> Measures:
    """:class:`Measures` of a fit that passed the checks up to :func:`absurd`."""
    r = a.x - a.curve
    period = 2.0 * math.pi / a.params["w0"]
    cov, sd = None, {}
    if a.jac is not None and a.rows is not None:
        try:
            cov, _ = hac_covariance(a.jac, a.rows, period_samples=period / float(
                np.median(np.diff(a.t))))
            sd = {n: float(math.sqrt(max(cov[i, i], 0.0))) for i, n in enumerate(a.varied)}
        except (ValueError, np.linalg.LinAlgError):
            cov = None
    return Measures(r, float(np.sqrt(np.mean(r * r))), period, cov, sd,
                    residual_structure(a.t, r, a.params["w0"]))


#: a half swing's residuals count as beyond the noise above this many noise sd (rms): only
#: where the report names the swing with the largest residuals (a description, no verdict
#: depends on it)
SWING_NOISE = 3.0


def worst_swing(a, m: Measures) -> tuple[float, float, float]:
    """The half swing (between the data's turning points) whose residuals are largest, among
    those beyond :data:`SWING_NOISE` times the noise: (start, end, its residual rms); the
    whole window where no swing's are."""
    edges = np.concatenate([[a.t[0]], np.asarray(a.an.ext_t, dtype=float), [a.t[-1]]])
    best, score = (float(a.t[0]), float(a.t[-1]), m.rms), -1.0
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        sel = (a.t >= lo) & (a.t <= hi)
        if np.count_nonzero(sel) < 4:
            continue
        rms = float(np.sqrt(np.mean(m.r[sel] ** 2)))
        if rms > SWING_NOISE * a.an.noise and rms > score:
            best, score = (float(lo), float(hi), rms), rms
    return best


def structure_text(a, m: Measures) -> str:
    """Where the structure sits and how large it is, for the reasons."""
    lo, hi, rms = worst_swing(a, m)
    noise, A = a.an.noise, a.derived["A"]
    times = f"{rms / noise:.0f} times the noise, " if noise > 0 else ""
    return (f"p = {m.st['p']:.1g}; largest in the swing at t = {time_span(lo, hi)}: rms "
            f"{rms:.3g} ({times}{100 * rms / A:.1f} % of the amplitude)")
