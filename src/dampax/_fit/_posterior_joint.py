"""The joint posterior's pieces (``_posterior``, where the model and the priors are described):
the set-up of a joint fit's residuals, priors and starts for the sampler (one AR(1) noise series
per run) and the xarray groups of its draws (shared parameters over (chain, draw), each run's
own over (chain, draw, run))."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ._core import ReferenceOptions
from ._joint_result import JointResidual
from ._params import DAMPING
from ._sampler import (
    PRIORS,
    REFERENCE_ATOL,
    REFERENCE_RTOL,
    Draws,
    Layout,
    _base,
    physical,
)


def _joint_setup(res, stride: int):
    """(residual, args, layout, centre, width, theta0, mask) of the joint fit ``res`` (a
    :class:`~dampax._fit._joint_result.JointResult`): the joint problem's residuals of every run,
    thinned by ``stride``, its padding masked out, one AR(1) noise series per run; the priors
    of :data:`PRIORS` per parameter (a shared one centred on the runs' median)."""

    pr = res.problem()
    lay = pr.residual.layout
    opts = pr.residual.opts
    if opts is not None:
        opts = ReferenceOptions(opts.max_swings, REFERENCE_RTOL, REFERENCE_ATOL)
    a = pr.args
    # the padding beyond the longest run dropped (to a power of two: similar sets share the
    # compiled sampler), then every stride-th sample
    n_max = int(np.max(np.sum(pr.mask, axis=1)))
    keep = min(a.tau.shape[1], max(256, 1 << int(math.ceil(math.log2(max(n_max, 1))))))
    args = a._replace(tau=a.tau[:, :keep:stride], x=a.x[:, :keep:stride],
                      weight=a.weight[:, :keep:stride])
    mask = np.asarray(args.weight) > 0.0
    residual = JointResidual(lay, opts)
    singles, runs = res.singles, res.runs
    amp = [max(float(s.derived["A"]), 1e-300) for s in singles]
    w_turn = [s.params["w0"] / (1.0 + float(s.diagnostics.get("w0/turning - 1", 0.0)))
              for s in singles]
    m = float(runs[0].fixed["m"])
    names, log, centre, width, theta0 = [], [], [], [], []
    for name, v in zip(pr.names, np.asarray(pr.p0, dtype=float), strict=True):
        base = _base(name)
        j = int(name[len(base) + 1:-1]) if "[" in name else None
        if base in DAMPING:
            guesses = [max(float(s.init.get(base, s.params[base])), 1e-30)
                       for s in (singles if j is None else [singles[j]])]
            guess = float(np.median(guesses))
            c, w, start, is_log = math.log(guess), 3.0, math.log(max(v, guess * 1e-6)), True
        elif base == "w0":
            wt = float(np.median(w_turn)) if j is None else w_turn[j]
            c, w, start, is_log = wt, 0.05 * wt, v, False
        elif base == "k3":  # k3 A^2/(m w0^2) ~ N(0, 0.5) at the runs' median
            scale = m * float(np.median([r.params["w0"] for r in runs])) ** 2
            c, w, start, is_log = 0.0, 0.5 * scale / float(np.median(amp)) ** 2, v, False
        elif base == "offset":
            c, w, start, is_log = v, amp[j], v, False
        elif base == "x0":
            c, w, start, is_log = v, 2 * amp[j], v, False
        else:  # v0
            c, w, start, is_log = v, 2 * amp[j] * runs[j].params["w0"], v, False
        names.append(name)
        log.append(is_log)
        centre.append(c)
        width.append(w)
        theta0.append(start)
    r = np.asarray(residual(jnp.asarray(pr.p0, dtype=float), args))
    log_rms, log_sig, atanh_phi = _noise_starts(r, mask)
    n = len(runs)
    centre += log_rms + [0.0] * n
    width += [2.0] * (2 * n)
    theta0 += log_sig + atanh_phi
    layout = Layout(tuple(names), tuple(log), noise=n)
    return residual, args, layout, centre, width, theta0, mask


def _noise_starts(r, mask) -> tuple[list, list, list]:
    """Each run's AR(1) noise at the start: (log rms, log sigma, atanh phi_n) of its residuals.

    Arguments:
        r: the residuals of every run (n_runs, n), thinned.
        mask: the samples that are data (n_runs, n).

    Returns:
        The three lists, one entry per run (the centre of log sigma's prior, and the start of
        log sigma and atanh phi_n).
    """
    log_rms, log_sig, atanh_phi = [], [], []
    for j in range(len(r)):
        rj = r[j][mask[j]]
        phi_hat = float(np.clip(np.corrcoef(rj[:-1], rj[1:])[0, 1], -0.9, 0.995))
        log_rms.append(math.log(float(np.sqrt(np.mean(rj * rj))) or 1e-12))
        log_sig.append(math.log(float(np.std(rj[1:] - phi_hat * rj[:-1])) or 1e-12))
        atanh_phi.append(math.atanh(phi_hat))
    return log_rms, log_sig, atanh_phi


def _joint_groups(out: Draws, layout: Layout, res, stride: int) -> tuple:
    """The posterior group and the observed data of a joint fit's posterior (xarray
    Datasets): the shared parameters over (chain, draw), each run's own (and its noise) over
    (chain, draw, run), the fixed ones as attributes; the runs' windows NaN-padded.

    Arguments:
        out: the sampler's draws.
        layout: the sampled parameters' layout (one noise series per run).
        res: the joint start fit (a ``JointResult``).
        stride: the likelihood's thinning.

    Returns:
        (draws, observed).
    """
    import xarray as xr

    model = res.model
    n_runs = len(res.runs)
    nch, nd, dim = out.theta.shape
    flat = jnp.asarray(out.theta.reshape(-1, dim))
    P, sigma, phi_n = (np.asarray(v) for v in jax.vmap(lambda th: physical(th, layout))(flat))
    coords = {"chain": np.arange(nch), "draw": np.arange(nd), "run": np.arange(n_runs)}
    data = {}
    shared_names = [nm for nm in layout.names if "[" not in nm]
    for nm in shared_names:
        data[nm] = (("chain", "draw"), P[:, layout.names.index(nm)].reshape(nch, nd))
    per_run = [_base(nm) for nm in layout.names if nm.endswith("[0]")]
    for base in per_run:
        cols = [layout.names.index(f"{base}[{j}]") for j in range(n_runs)]
        data[base] = (("chain", "draw", "run"), P[:, cols].reshape(nch, nd, n_runs))
    data["sigma"] = (("chain", "draw", "run"), sigma.reshape(nch, nd, n_runs))
    data["phi_noise"] = (("chain", "draw", "run"), phi_n.reshape(nch, nd, n_runs))
    r0 = res.runs[0]
    sampled = set(shared_names) | set(per_run)
    fixed = {f"fixed_{nm}": float(r0.params[nm]) for nm in (*DAMPING, "w0")
             if nm not in sampled}
    fixed.update(fixed_m=float(r0.fixed["m"]), fixed_g=float(r0.fixed["g"]))
    attrs = {"inference_library": "blackjax", "sampler": "NUTS, window adaptation",
             "model": f"joint {model} fit of {n_runs} runs + AR(1) noise per run",
             "units": res.units, "per_mass": int(res.per_mass), "free": ",".join(res.free),
             "shared": ",".join(res.shared), "stride": stride,
             "t_start": [float(r.t[0]) for r in res.runs],
             "priors": "; ".join(f"{k}: {v}" for k, v in PRIORS.items()), **fixed}
    draws = xr.Dataset(data, coords=coords, attrs=attrs)
    n_max = max(r.ndata for r in res.runs)
    tt = np.full((n_runs, n_max), np.nan)
    xx = np.full((n_runs, n_max), np.nan)
    for j, r in enumerate(res.runs):
        tt[j, :r.ndata] = r.t
        xx[j, :r.ndata] = r.x
    observed = xr.Dataset({"x": (("run", "sample"), xx), "t": (("run", "sample"), tt)},
                          coords={"run": np.arange(n_runs), "sample": np.arange(n_max)},
                          attrs={"units": res.units, "stride": stride,
                                 "sources": [str(r.source) for r in res.runs],
                                 "padding": "NaN after each run's last sample"})
    return draws, observed
