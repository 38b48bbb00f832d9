"""``dampax errormap``: the analytic models against the reference over a grid of ratios."""

from __future__ import annotations

import argparse
import contextlib
import math
import sys

import numpy as np

from dampax_cli._arguments import (
    ERRORMAP_CONFIRM_POINTS,
    ERRORMAP_DEFAULTS,
    ERRORMAP_PLOTS,
    ERRORMAP_QUICK,
)
from dampax_cli._arguments import add_errormap_arguments as add_arguments  # noqa: F401 (SUBCOMMANDS)

from .._models._registry import ANALYTIC, MODELS, check_models
from .._studies._maps import largest_ratio_below, worst_in_box
from ._common import PROG, beside, compile_clock, error, fmt, prepare_out_dir, show_progress


def _ratio_text(value) -> str:
    if value is None:
        return "n/a"
    return fmt(value, 3, nan="none")


def _defined_along(ds, model: str, along: str) -> bool:
    """Whether the model, and the reference it is compared with, are valid beyond the first
    point of ``along`` (other ratios at 0): the closed-form reference "coulomb_exact" does not
    exist at d2 > 0, where the scan read "0" as if the model failed there."""
    sel = {}
    for axis in ("d0_ratio", "d1_ratio", "d2_ratio"):
        if axis != along:
            zero = np.flatnonzero(np.asarray(ds[axis]) == 0.0)
            if zero.size == 0:
                return True
            sel[axis] = int(zero[0])
    valid = ds["valid"].sel(model=model)
    if "reference_valid" in ds:
        valid = valid & ds["reference_valid"]
    valid = np.asarray(valid.isel(sel).all("phi0"))
    return valid.size < 2 or bool(np.any(valid[1:]))


def _print_errormap_summary(ds) -> None:
    """Per model: the largest d2 (at d0 = 0) and d0 (at d2 = 0) with max error < 1 % / 5 %."""

    def step(axis: str) -> str:
        values = np.unique(np.asarray(ds[axis], dtype=float))
        return fmt(float(np.min(np.diff(values))), 3) if values.size > 1 else "-"

    models = [str(m) for m in np.asarray(ds["model"])]
    w = max(13, *(len(m) for m in models))
    group = 8 + 1 + 8 + 1 + 14
    print("  Largest ratio up to which max |x - x_ref| / A0 stays below 1 % and 5 % for every "
          "phi0 (d1/w0 = 0),")
    print(f"  on grid steps of {step('d2_ratio')} in d2 A0/w0 and {step('d0_ratio')} in "
          "d0/(w0 A0); beside the paper's stated ranges (section):")
    print()
    print(f"  {'':<{w}}  {'d2 A0/w0 at d0 = 0':^{group}}  {'d0/(w0 A0) at d2 = 0':^{group}}  "
          f"{'worst max error':>17}")
    print(f"  {'model':<{w}}  {'< 1 %':>8} {'< 5 %':>8} {'paper':>14}  {'< 1 %':>8} "
          f"{'< 5 %':>8} {'paper':>14}  {'d0<=0.03,d2<=0.25':>17}")
    for model in models:
        cells = []
        for along in ("d2_ratio", "d0_ratio"):
            defined = _defined_along(ds, model, along)
            for level in (0.01, 0.05):
                value = largest_ratio_below(ds, level, along=along, model=model)
                cells.append(_ratio_text(value) if defined else "-")
        paper = MODELS[model].paper_ranges
        box = worst_in_box(ds, model=model, d0_max=0.03 + 1e-12, d2_max=0.25 + 1e-12)
        box_text = "-" if math.isnan(box) else f"{100 * box:.2g} %"
        print(f"  {model:<{w}}  {cells[0]:>8} {cells[1]:>8} {paper[0]:>14}  "
              f"{cells[2]:>8} {cells[3]:>8} {paper[1]:>14}  {box_text:>17}")
    print()
    for line in (
            "paper (Lelas & Pezer, Part I): quadratic damping, matched ansatz \"excellent\" up to",
            "d2 A0/w0 = 0.5 (III); Coulomb damping, matched + Coulomb tail up to d0/(w0 A0) = "
            "0.05 (IV;",
            "* the plain ansatz there \"until the last few half-periods\"); combined damping, "
            "good for",
            "d0/(w0 A0) <= 0.03 with d2 A0/w0 <= 0.25 (V; last column: the worst grid point in "
            "that box);",
            "undamped-phase ansatz (earlier approach) for d0/(w0 A0) <~ 0.03, d2 A0/w0 <~ 0.1 "
            "(eq. 25).",
            "\"none\": not even the first grid value; \"-\": the model (or the reference) is "
            "not defined",
            "there; \"n/a\": no 0 on the other axis of the grid."):
        print(f"  {line}")


def _leave(status: int) -> None:
    """End this process of a failed ``jax.distributed`` run now: JAX's exit handler would wait
    at the run's shutdown barrier for the processes that died, then abort."""
    import os

    for stream in (sys.stdout, sys.stderr, sys.__stdout__, sys.__stderr__):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(status)


def _give_up(message: str) -> None:
    """Connecting took longer than --timeout: one line, status 3 (from the watchdog thread)."""
    error(f"{PROG}: error: {message}")
    _leave(3)


def _import_outputs(figures: bool) -> None:
    """Import what writes the map's files (xarray, scipy's netCDF writer) and, for
    ``figures``, matplotlib's Agg canvas with its font list."""
    import scipy.io  # noqa: F401 (xarray's "scipy" engine)
    import xarray  # noqa: F401

    if figures:
        from .._plot import warm_figures

        warm_figures()


def run(args: argparse.Namespace) -> int:
    """Error maps of the analytic models against the reference over a grid of damping ratios."""
    import time

    from .._io import all_or_nothing, write_netcdf
    from .._studies._distributed import DistributedError, check_processes, check_timeout, initialize
    from .._studies._maps import (
        _axis,
        check_map_size,
        duration_text,
        error_map,
        map_cost,
        parse_axis,
    )

    preset = ERRORMAP_QUICK if args.quick else ERRORMAP_DEFAULTS

    def pick(name):
        value = getattr(args, name)
        return preset[name] if value is None else value

    axes = {}
    for flag, name, ratio in (("--d0", "d0", True), ("--d1", "d1", True), ("--d2", "d2", True),
                              ("--phi0", "phi0", False)):
        axes[name] = _axis(flag, parse_axis(pick(name), flag), ratio=ratio)
    models = check_models(args.models, "--models", allowed=ANALYTIC)
    periods = pick("periods")
    spp = pick("samples_per_period")
    chunk = pick("chunk_size")
    for flag, value, low in (("--periods", periods, 0.0), ("--samples-per-period", spp, 1),
                             ("--chunk-size", chunk, 0)):
        if value is not None and not (math.isfinite(value) and value > low):
            raise ValueError(f"{flag} must be > {low:g}, got {value}")
    # the size first: a grid beyond the memory is refused, a long one needs --yes (issue 37)
    sizes = {flag: axes[name].size for flag, name in
             (("--d0", "d0"), ("--d1", "d1"), ("--d2", "d2"), ("--phi0", "phi0"))}
    n = check_map_size(sizes, len(models), periods, spp)
    need, seconds = map_cost(n, len(models), periods, spp)
    if n > ERRORMAP_CONFIRM_POINTS and not args.yes:
        raise ValueError(f"{', '.join(sizes)}: a grid of {n} points needs about "
                         f"{need / 2**20:.0f} MiB of memory and about {duration_text(seconds)} "
                         f"on a 2-core machine; pass --yes to run it (more than "
                         f"{ERRORMAP_CONFIRM_POINTS} points), or use coarser axes")
    processes = check_processes(args.processes, "--processes")
    timeout = check_timeout(args.timeout, "--timeout")
    explicit = (args.coordinator, args.process_id, args.num_processes)
    joining = args.cluster or any(v is not None for v in explicit)
    if processes is not None and joining:
        raise ValueError("--processes starts local workers; it does not go with --cluster or "
                         "--coordinator (which join a run started elsewhere)")
    if args.cluster and any(v is not None for v in explicit):
        raise ValueError("--cluster reads the run from the environment; give it without "
                         "--coordinator, --process-id and --num-processes")
    out = prepare_out_dir(args.out)

    rank, size = 0, processes or 1
    if joining:  # before any JAX computation in this process
        try:
            rank, size = initialize(*explicit, timeout=timeout,
                                    names=("--coordinator", "--process-id", "--num-processes"),
                                    on_timeout=_give_up)
        except DistributedError as err:
            error(f"{PROG}: error: {err}")
            return 3
    if rank == 0:
        print(f"{PROG} errormap: {n} points ({axes['d0'].size} d0 x {axes['d1'].size} d1 x "
              f"{axes['d2'].size} d2 x {axes['phi0'].size} phi0; about "
              f"{duration_text(seconds)}, {need / 2**20:.2g} MiB), models "
              f"{', '.join(models)}; reference: {args.reference}; window <= {periods:g} "
              f"periods, {spp} samples/period" + (f"; {size} processes" if size > 1 else ""))
    start = time.perf_counter()
    try:
        # the outputs' libraries are imported while the map computes (its programs release
        # Python's lock and leave a core free): 2.94 -> 2.47 s repeated on 2 cores
        with compile_clock() as clock, \
                beside(_import_outputs, bool(ERRORMAP_PLOTS[args.plots]) and rank == 0):
            ds = error_map(d0_ratio=axes["d0"], d1_ratio=axes["d1"], d2_ratio=axes["d2"],
                           phi0=axes["phi0"], models=models, periods=periods,
                           samples_per_period=spp, chunk_size=chunk, reference=args.reference,
                           progress=show_progress(args), processes=processes,
                           timeout=timeout)
    except DistributedError as err:
        error(f"{PROG}: error: {err}")
        if joining:  # the run is broken: jax's shutdown at exit would wait for the dead
            _leave(3)
        return 3
    elapsed = time.perf_counter() - start
    if rank != 0:  # process 0 writes the files and the summary
        print(f"{PROG} errormap: process {rank} of {size}: share done in {elapsed:.1f} s")
        return 0
    bad_ref = int((~ds["reference_valid"]).sum())
    if bad_ref:
        print(f"{PROG}: note: the reference is not valid at {bad_ref} of {n} points (budget or "
              "not defined there); their metrics are NaN", file=sys.stderr)
    metrics = ERRORMAP_PLOTS[args.plots]
    with all_or_nothing():  # the whole new set of outputs, or the whole earlier one
        written = [write_netcdf(ds, out / "errormap.nc")]
        if metrics:  # matplotlib is imported only here
            from .._plot import plot_error_map

            written += [plot_error_map(ds, metric, out / f"{metric}.png") for metric in metrics]
    print(f"  {n} points in {elapsed:.1f} s{clock.text()}; written: "
          + ", ".join(str(p) for p in written))
    print()
    _print_errormap_summary(ds)
    return 0
