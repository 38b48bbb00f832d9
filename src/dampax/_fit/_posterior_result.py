"""The result of :func:`~dampax._fit._posterior.posterior`: :class:`Posterior` (draws as
xarray, summary with rank-normalised split R-hat and ESS, corner plot, ArviZ InferenceData)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._plot_fit import plot_corner
from ._mcmc import ess_bulk, ess_tail, rhat, write_inference_data
from ._params import (
    DAMPING,
    unit_of,
)
from ._sampler import PRIORS, _base

# ----------------------------------------------------------------------------------------------
# the result


@dataclass
class Posterior:
    """Posterior draws of a trace fit or of a joint fit of several runs (:func:`posterior`).

    Attributes:
        draws: xarray Dataset, one variable per sampled parameter (the free damping constants,
            k3 when free, w0 and offset when fitted, x0, v0, sigma, phi_noise), dims (chain,
            draw): the ``posterior`` group of ArviZ; the fixed parameters are its attributes
            ``fixed_<name>``. Of a joint fit: the shared parameters (chain, draw), each run's
            own (x0, v0, offset, sigma, phi_noise, ...) (chain, draw, run).
        sample_stats: xarray Dataset of the sampler's statistics per draw (:data:`SAMPLE_STATS`:
            lp, diverging, energy, step_size, tree_depth, acceptance_rate, n_steps).
        observed_data: xarray Dataset of the fit window: x over the coordinate t (of a joint
            fit: x and t over (run, sample), NaN after each run's last sample).
        free: the sampled constants (the damping constants, then k3 when free).
        fit: the least-squares :class:`FitResult` (``JointResult``) it started from.
        model: the fit model sampled ("ansatz" or "reference").
        units, per_mass: as the fit's.
        accept_rate, divergences, step_size: sampler diagnostics (means over chains and
            draws; the step size averaged over the chains).
        seconds: wall time of :func:`posterior` (the start fit included when it ran).
        seconds_chains: wall time of the warm-up and sampling program (compilation included
            on its first call for a shape).
        stride: the likelihood uses 1 sample in ``stride`` of the window.
        narrow: {name: posterior sd / the start fit's HAC sd} where that is below
            ``_posterior.NARROW``: the AR(1) noise model is too simple for the residuals
            (their correlation, which the fit's intervals allow for): quote the fit's
            intervals for those (the report and a warning say so). Empty when none.
    """

    draws: object
    free: tuple
    fit: object
    sample_stats: object = None
    observed_data: object = None
    model: str = "ansatz"
    units: str = "m"
    per_mass: bool = False
    accept_rate: float = math.nan
    divergences: int = 0
    step_size: float = math.nan
    seconds: float = math.nan
    seconds_chains: float = math.nan
    stride: int = 1
    priors: dict = field(default_factory=lambda: dict(PRIORS))
    narrow: dict = field(default_factory=dict)

    def summary(self, level: float = 0.95) -> dict:
        """Posterior summary per sampled parameter.

        Arguments:
            level: the two-sided level of the central interval.

        Returns:
            {name: {"mean", "sd", "lo", "hi", "r_hat", "ess_bulk", "ess_tail", "ess"}}: the
            mean, standard deviation, the central ``level`` interval, the rank-normalised
            split R-hat and the bulk and tail effective sample sizes, as ``arviz.rhat`` and
            ``arviz.ess`` compute them (``_mcmc``; Vehtari et al. 2021); "ess" is the bulk
            ESS. R-hat is NaN for one chain.
        """

        if not 0.0 < level < 1.0:
            raise ValueError(f"level must be in (0, 1), got {level!r}")
        out = {}
        for var in self.draws.data_vars:
            v = self.draws[var]
            if "run" in v.dims:  # a joint posterior's per-run parameter: name[j]
                v = v.transpose("chain", "draw", "run")
                items = [(f"{var}[{j}]", v.values[..., j]) for j in range(v.sizes["run"])]
            else:
                items = [(var, v.values)]
            for name, a in items:
                a = np.asarray(a, dtype=float)
                q = np.quantile(a, [0.5 - 0.5 * level, 0.5 + 0.5 * level])
                bulk = ess_bulk(a)
                out[name] = {"mean": float(a.mean()), "sd": float(a.std(ddof=1)),
                             "lo": float(q[0]), "hi": float(q[1]), "r_hat": rhat(a),
                             "ess_bulk": bulk, "ess_tail": ess_tail(a), "ess": bulk}
        return out

    def report(self, level: float = 0.95) -> str:
        """The summary as text, with the sampler's diagnostics."""
        s = self.summary(level)
        nc, nd = self.draws.sizes["chain"], self.draws.sizes["draw"]
        joint = "run" in self.draws.dims
        what = (f"joint {self.model} fit of {self.draws.sizes['run']} runs"
                if joint else f"{self.model} model")
        lines = [f"[[Posterior]] NUTS (blackjax, window adaptation), {what}, "
                 f"{nc} chains x {nd} draws, AR(1) noise{' per run' if joint else ''}; "
                 f"accept rate "
                 f"{self.accept_rate:.2f}, {self.divergences} divergences, "
                 f"{self.seconds:.1f} s"
                 + (f"; 1 sample in {self.stride}" if self.stride > 1 else ""),
                 f"    {'':<10} {'mean':>12} {f'{100 * level:g} % interval':>28} "
                 f"{'r_hat':>6} {'ess_bulk':>8} {'ess_tail':>8}"]
        for name, row in s.items():
            base = _base(name)
            unit = unit_of(base, self.units, self.per_mass) if base in DAMPING or base in (
                "w0", "offset", "x0", "v0", "k3") else ("" if base == "phi_noise"
                                                        else self.units)
            lines.append(f"    {name + ':':<10} {row['mean']:>12.6g} [{row['lo']:>12.6g}, "
                         f"{row['hi']:>12.6g}] {row['r_hat']:>6.3f} {row['ess_bulk']:>8.0f} "
                         f"{row['ess_tail']:>8.0f} {unit}".rstrip())
        attrs = self.draws.attrs
        if "fixed_mu_s" in attrs:  # static friction: held, not sampled (static_friction)
            held = f"    mu_s held at {attrs['fixed_mu_s']:.6g}"
            if "mu_s_interval" in attrs:
                lo, hi = attrs["mu_s_interval"]
                held += (f" (the fit's; every value in [{lo:.6g}, {hi:.6g}) gives the same "
                         "halt): the draws are conditional on that halt")
            lines.append(held)
        if self.narrow:
            lines.append(f"    warning: {narrow_text(self.narrow)}")
        bad = [n for n, row in s.items() if not row["r_hat"] < 1.01] if nc > 1 else []
        if bad:
            lines.append(f"    warning: r_hat >= 1.01 for {', '.join(bad)}: the chains "
                         "disagree (more warm-up or draws)")
        return "\n".join(lines)

    def to_netcdf(self, path) -> Path:
        """Write an ArviZ InferenceData file: groups posterior (:attr:`draws`), sample_stats
        and observed_data (netCDF-4, ``arviz.from_netcdf`` opens it; ArviZ is not needed to
        write it). Returns the path."""

        return write_inference_data({"posterior": self.draws,
                                     "sample_stats": self.sample_stats,
                                     "observed_data": self.observed_data}, path)

    def corner(self, path, *, names=None) -> Path:
        """Save a corner plot (pairwise scatter and histograms) of the damping constants (or
        ``names``); ``dampax._plot_fit.plot_corner``."""

        if names is None:  # of a joint posterior: the shared constants
            names = [n for n in self.free if n in self.draws.data_vars
                     and self.draws[n].dims == ("chain", "draw")]
        names = list(names)
        return plot_corner(self.draws, names, path,
                           units={n: unit_of(n, self.units, self.per_mass) for n in names})


#: a posterior sd below this fraction of the fit's interval is draws that never moved (a
#: sampler stuck at its start), not a posterior narrower than the residuals allow. Chains that
#: move give 0.81-1.97 on the generated family of benchmarks/posterior_narrow.py (the
#: ``_posterior.NARROW`` note), and 0.05 where AR(1) noise misdescribes the residuals (w0 of
#: spring run 1); draws that never moved give 0, or their rounding (3e-14: D of the example
#: with 20 warm-up steps): any threshold between those decides the same
STILL = 1e-6


def narrow_text(narrow: dict) -> str:
    """One line on the parameters whose posterior is narrower than the fit's intervals; a
    ratio below :data:`STILL` (draws that never moved: ``dampax fit --example --posterior
    --draws 20 --warmup 20 --chains 1`` divided by 0, and called D 3e13x narrower) is said
    as such."""
    items = ", ".join(f"{n} {1.0 / r:.3g}x" for n, r in narrow.items() if r > STILL)
    still = [n for n, r in narrow.items() if not r > STILL]
    parts = [f"the posterior is narrower than the fit's interval ({items}): the AR(1) noise "
             "model is too simple for these residuals, whose correlation the fit's intervals "
             "allow for; quote the fit's intervals (conf_interval) for those"] if items else []
    if still:
        parts.append(f"the draws of {', '.join(still)} never moved (the sampler's steps were "
                     "refused or vanishingly small: too few warm-up steps to adapt them, "
                     "num_warmup); these draws are not a posterior")
    return "; ".join(parts)
