"""What the checks of a trace fit measure on its residuals (``_assess``'s :data:`CHECKS`
share them): the residuals, their rms, the period, the intervals' covariance, the test
against AR(1) noise (:func:`measures`), and where structure in them sits: the half swing
whose residuals beyond the noise are largest against its amplitude (:func:`worst_swing`).
Also what each check returns (:class:`Finding`) and the findings so far (:class:`Verdict`)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ._checks import motion_end, residual_structure
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


class Finding(NamedTuple):
    """What one check found: failures, inadequacies (one-line reasons), measured numbers, and
    whether the later checks no longer apply."""

    fails: tuple = ()
    bad: tuple = ()
    diag: dict = {}
    stop: bool = False


class Verdict(NamedTuple):
    """The findings so far (what a check may consult)."""

    fails: tuple
    bad: tuple
    diag: dict

    def add(self, f: Finding) -> Verdict:
        return Verdict(self.fails + f.fails, self.bad + f.bad, {**self.diag, **f.diag})

    @property
    def converged(self) -> bool:
        return "note_steps" in self.diag


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
            f"{rms:.3g} ({times}{100 * rms / A:.1f} % of the amplitude)" + level_text(a, m))


#: where the offset is held, a mean of the residuals above this share of their rms is named
#: as a level the data sit about (a description: no verdict depends on it)
LEVEL_SHARE = 0.5


def level_text(a, m: Measures) -> str:
    """A level the residuals sit about where the fit holds the offset, else ""."""
    mean = float(np.mean(m.r))
    if "offset" in a.varied or not abs(mean) > LEVEL_SHARE * m.rms:
        return ""
    held = float(a.params.get("offset", 0.0))
    return (f"; the residuals' mean {mean:.3g} is {100 * abs(mean) / m.rms:.0f} % of their rms: "
            f"the data sit about a level the fit holds at {held:.3g} (offset=True fits it)")


#: |t| of the half periods' trend with the squared amplitude above which the data's frequency
#: moves with the amplitude (a suggestion, made only where the exact model is inadequate).
#: Measured: spring run 1 t = 6.7 (k3 takes its phase drift: notebook 04), run 2 below 5,
#: torsion 60/80/100 deg 10.8/15.1/43.1 (100 deg: k3 takes the rms from 4.35 to 1.62 deg); a
#: reference trace with k3 A^2/k = 0.05 is hinted and the same linear trace is not
#: (tests/models/test_cubic.py); 5 is far beyond a normal t's noise, as a hint needs. On the
#: generated families (fit_calibration.py, benchmarks/README.md): no hint in the 200 draws of
#: the default table (130 without k3), 2 in the 11 structured fits that lack k3 (the hint
#: needs 8 turning points and a trend above the noise of their times)
AMPLITUDE_T = 5.0


def k3_hint(an, t, x) -> str:
    """A suggestion when the data's frequency follows the amplitude (what a cubic stiffness
    gives: w(a)^2 = w0^2 + (3/4)(k3/m) a^2, docs/cubic_stiffness.md): the half periods between
    the data's turning points regressed on their squared amplitude, the trend's t statistic
    beyond :data:`AMPLITUDE_T`; else "".

    Arguments:
        an: the window's ``_analysis.Analysis`` (the rest point, when the data halt, left out).
        t, x: the window's samples: each turning point's time is the vertex of a parabola
            fitted to the samples within a quarter of a half period of it (the samples alone
            quantise a half period to dt; three of them leave the noise over the curvature).
    """
    t, x = np.asarray(t, dtype=float), np.asarray(x, dtype=float)
    dt = float(np.median(np.diff(t)))
    k = max(2, int(0.25 * math.pi / an.omega / dt)) if an.omega > 0 else 2
    i = np.asarray(an.ext_i, dtype=int)[:-1 if an.halted else None]
    i = i[(i >= k) & (i < t.size - k)]
    if i.size < 8:
        return ""
    idx = i[:, None] + np.arange(-k, k + 1)[None, :]
    u = t[idx] - t[i][:, None]
    V = np.stack([np.ones_like(u), u, u * u], axis=-1)  # (turning point, sample, 3)
    c = np.linalg.solve(np.einsum("nki,nkj->nij", V, V),
                        np.einsum("nki,nk->ni", V, x[idx])[..., None])[..., 0]
    ok = c[:, 2] != 0.0
    te = t[i] + np.where(ok, np.clip(-c[:, 1] / np.where(ok, 2.0 * c[:, 2], 1.0), -k * dt,
                                     k * dt), 0.0)
    y1 = x[i]
    a = np.abs(y1 - an.offset)
    h, a2 = np.diff(te), (0.5 * (a[1:] + a[:-1])) ** 2
    # weighted by a^2: a turning point's time is as uncertain as noise / (a w^2 dt) allows
    w = np.sqrt(a2 / a2.max())
    X = np.column_stack([np.ones_like(a2), a2 - np.average(a2, weights=w * w)]) * w[:, None]
    coef, *_ = np.linalg.lstsq(X, h * w, rcond=None)
    r = h * w - X @ coef
    s2 = float(r @ r) / max(h.size - 2, 1)
    cov = s2 * np.linalg.pinv(X.T @ X)
    tstat = coef[1] / math.sqrt(cov[1, 1]) if cov[1, 1] > 0 else 0.0
    if not abs(tstat) > AMPLITUDE_T:
        return ""
    way = "falls" if coef[1] > 0 else "rises"
    return (f"; the data's frequency {way} with the amplitude (half periods against the squared "
            f"amplitude: t = {tstat:.3g}): a cubic stiffness may take it up (free=(..., \"k3\"))")


#: the exact model's search settles on its best optimum when at least this share of its starts
#: (and two) end within SETTLE_RTOL of the best cost: its starts run a budget of steps on a
#: thinned trace, so on structured residuals they stop short of the optimum by a little. On
#: the shared traces the spring runs settle 32 of 32, the torsion releases of 60, 70, 80, 90
#: and 100 deg 16, 24, 15, 17 and 17 of 32 within 1 % (60 deg's next best 0.014 % above:
#: "reached" within 1e-4 counted 1); a start in another basin costs more by a structure's share.
#: Calibrated on a generated family that lacks a term (``fit_calibration.py --models default
#: --lacking k3``: 70 traces with a hardening spring fitted without it): of the 8 fits whose
#: optimum it let stand, none had a lower cost from the truth's start; 3 it did not settle
#: (failed as a possible local optimum) had none either (benchmarks/README.md, issue 36)
SETTLE_SHARE = 0.25
SETTLE_RTOL = 0.01


def settles(search) -> bool:
    """Whether a search of starts (``_starts.Starts`` or None) settled on its best cost
    (:data:`SETTLE_SHARE` of its starts, and two, within :data:`SETTLE_RTOL`)."""
    return search is not None and settled_starts(search.costs) >= max(2, SETTLE_SHARE *
                                                                       search.n)


def gross_ends(t, x, curve, r, period: float, level: tuple, tol_periods: float):
    """Where the data's and the model's swings above a level end, and the tolerance between
    them: (model end, data end, tol). ``level``: (noise, amplitude, structured); the level is
    max(6 noise, A/50), the noise the robust scale of the residuals r where they are not
    structured (the noise from second differences misses most of correlated noise; structured
    residuals hold the model's error and say nothing about the noise); tol is
    ``tol_periods`` periods or a tenth of the window."""
    noise, A, structured = level
    scale = noise if structured else \
        max(noise, 1.4826 * float(np.median(np.abs(r - np.median(r)))))
    cut = max(6.0 * scale, 0.02 * A)
    tol = max(tol_periods * period, 0.1 * float(t[-1] - t[0]))
    return motion_end(t, curve, period, cut), motion_end(t, x, period, cut), tol


def settled_starts(costs) -> int:
    """How many of a search's starts end within :data:`SETTLE_RTOL` of its best cost."""
    c = np.asarray(costs, dtype=float)
    c = c[np.isfinite(c)]
    return int(np.sum(c <= c.min() * (1.0 + SETTLE_RTOL))) if c.size else 0
