"""The options of every ``dampax`` subcommand, defined without importing dampax or JAX.

:mod:`dampax_cli` answers ``--help`` and ``--version`` from these definitions alone, and
:mod:`dampax._cli` builds its parser from the same functions. The few names of dampax's
registries that the options list are copied here (dampax itself imports JAX);
``tests/cli/test_cli.py`` checks that they are the library's.
"""

from __future__ import annotations

import argparse

# copies of dampax's registries (tests/cli/test_cli.py::test_option_names_are_the_librarys)
#: dampax._models._registry.MODELS (names), the analytic ones first (its ANALYTIC)
ANALYTIC = ("matched", "undamped", "matched_tail", "rizcallah", "coulomb_exact")
MODELS = ANALYTIC + ("reference",)
#: dampax._studies._maps.DEFAULT_MODELS and REFERENCES
DEFAULT_MODELS = ("matched", "undamped", "matched_tail", "rizcallah")
REFERENCES = ("reference", "coulomb_exact")
#: dampax._studies._sensitivity.PARAMETERS and dampax._studies._global.QUANTITIES
PARAMETERS = ("m", "k", "mu", "b", "D", "g", "k3", "x0", "v0")
QUANTITIES = ("halt_time", "halt_position", "energy", "x", "max_error")
#: dampax._fit: the trace models (MODELS) with their FIT_MODELS descriptions, OPTIMIZERS with
#: their METHOD_NAMES, LOSSES
FIT_MODELS = {"ansatz": "the closed form of Lelas & Pezer (fast)",
              "reference": "eq. 3 integrated by DOP853, started from the ansatz fit"}
OPTIMIZERS = ("lm", "adam", "lbfgs")
METHOD_NAMES = {"lm": "Levenberg-Marquardt (optimistix's trust-region algorithm)",
                "adam": "adam (optax)", "lbfgs": "L-BFGS (optax)"}
LOSSES = ("linear", "soft_l1")

#: Grid and settings of ``dampax errormap`` (a few minutes on 2 cores with the reference) and
#: of ``--quick`` (a smoke run). The grids include d0 = 0 and d2 = 0 for the summary table.
ERRORMAP_DEFAULTS = dict(d0="0:0.1:16", d1="0", d2="0:0.75:16", phi0="0:7*pi/8:8",
                         periods=20.0, samples_per_period=64, chunk_size=None)
#: ``dampax errormap``: a grid of more points (about 10 minutes at the default window on a
#: 2-core machine) runs only with ``--yes``
ERRORMAP_CONFIRM_POINTS = 100_000
ERRORMAP_QUICK = dict(d0="0:0.1:4", d1="0", d2="0:0.75:4", phi0="0,pi/2",
                      periods=10.0, samples_per_period=32, chunk_size=32)

#: ``dampax errormap --plots``: the metrics (dampax._plot.ERROR_MAP_METRICS) drawn by each
#: choice (tests/cli/test_cli.py::test_launcher_names_are_the_librarys)
ERRORMAP_PLOTS = {"none": (), "summary": ("max_error",),
                  "all": ("max_error", "rms_error", "energy_error", "halt_time_error",
                          "halt_position_error")}


def add_oscillator_arguments(parser: argparse.ArgumentParser, *, mu: float = 0.0,
                             D: float = 0.0,
                             start_title: str = "initial state (default: the papers' block)"):
    """Options --m --k --mu --b --D --g --x0 --v0 shared by the subcommands."""
    osc = parser.add_argument_group("oscillator (m x'' = -k x - mu m g sgn(x') - b x' - D x'|x'|)")
    osc.add_argument("--m", type=float, default=1.0, help="mass [kg] (default: %(default)s)")
    osc.add_argument("--k", type=float, default=30.0,
                     help="spring stiffness [N/m] (default: %(default)s)")
    osc.add_argument("--mu", type=float, default=mu,
                     help="Coulomb friction coefficient (default: %(default)s)")
    osc.add_argument("--b", type=float, default=0.0,
                     help="viscous damping [kg/s] (default: %(default)s)")
    osc.add_argument("--D", type=float, default=D,
                     help="quadratic drag [kg/m] (default: %(default)s)")
    osc.add_argument("--g", type=float, default=9.81,
                     help="gravitational acceleration [m/s^2] (default: %(default)s)")
    osc.add_argument("--mu-s", dest="mu_s", type=float, default=None, metavar="MU_S",
                     help="static friction coefficient (>= mu): the block sticks at a turning "
                          "point where |k x| <= mu_s m g (default: mu_s = mu)")
    start = parser.add_argument_group(start_title)
    start.add_argument("--x0", type=float, default=0.2,
                       help="initial displacement [m] (default: %(default)s)")
    start.add_argument("--v0", type=float, default=0.0,
                       help="initial velocity [m/s] (default: %(default)s)")


def add_solve_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``dampax solve``."""
    add_oscillator_arguments(parser)
    out = parser.add_argument_group("output")
    out.add_argument("--turning", type=int, default=6, metavar="N",
                     help="turning points of the matched ansatz to print (default: %(default)s)")
    out.add_argument("--digits", type=int, default=4, metavar="N",
                     help="significant digits printed (default: %(default)s)")
    out.add_argument("--plot", metavar="FILE.png",
                     help="also save x(t) and E(t) of every model to this file")
    out.add_argument("--t-end", type=float, default=None, metavar="SECONDS",
                     help="time span of the plot and the reference integration "
                          "(default: a bit past the latest halt, or 6 undamped periods)")
    out.add_argument("--no-reference", action="store_true",
                     help="skip the reference integrator (DOP853)")


def add_errormap_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``dampax errormap``."""
    grid = parser.add_argument_group(
        "grid of dimensionless ratios (START:STOP:N = N values, both ends included; or a "
        "comma list; pi allowed, e.g. 0:7*pi/8:8; write a negative start as --phi0=-pi:0:5)")
    d = ERRORMAP_DEFAULTS
    q = ERRORMAP_QUICK
    grid.add_argument("--d0", metavar="START:STOP:N",
                      help=f"Coulomb ratio d0/(w0 A0) (default: {d['d0']}; quick: {q['d0']})")
    grid.add_argument("--d2", metavar="START:STOP:N",
                      help=f"quadratic ratio d2 A0/w0 (default: {d['d2']}; quick: {q['d2']})")
    grid.add_argument("--phi0", metavar="START:STOP:N",
                      help=f"initial phase [rad] (default: {d['phi0']}; quick: {q['phi0']}; "
                           "phi0 + pi gives the mirror-image motion)")
    grid.add_argument("--d1", metavar="START:STOP:N",
                      help=f"viscous ratio d1/w0 (default: {d['d1']})")
    grid.add_argument("--quick", action="store_true",
                      help="a 4 x 4 x 2 smoke run over 10 periods (explicit options win)")
    grid.add_argument("--yes", action="store_true",
                      help=f"run a grid of more than {ERRORMAP_CONFIRM_POINTS} points (without "
                           "it such a grid is refused with its memory and time estimate)")
    run = parser.add_argument_group("models and reference")
    run.add_argument("--models", default=",".join(DEFAULT_MODELS),
                     help=f"comma list of {', '.join(ANALYTIC)} (default: %(default)s)")
    run.add_argument("--reference", default="reference", choices=REFERENCES,
                     help="DOP853 integration of eq. 3, or the exact half-swings (D = 0 only, "
                          "fast) (default: %(default)s)")
    run.add_argument("--periods", type=float,
                     help=f"time window cap in undamped periods (default: {d['periods']:g}; "
                          f"quick: {q['periods']:g})")
    run.add_argument("--samples-per-period", type=int, metavar="N",
                     help=f"time samples per period (default: {d['samples_per_period']}; "
                          f"quick: {q['samples_per_period']})")
    run.add_argument("--chunk-size", type=int, metavar="N",
                     help="grid points per device evaluated at once (default: from the "
                          "device and its memory: 128 on a CPU, up to 32768 on a GPU; any value "
                          "is clipped to the grid and to a quarter of the device's memory)")
    out = parser.add_argument_group("output")
    out.add_argument("--out", default="errormap", metavar="DIR",
                     help="folder for errormap.nc and the heat maps (default: %(default)s)")
    out.add_argument("--plots", default="summary", choices=tuple(ERRORMAP_PLOTS),
                     help="heat maps written beside errormap.nc: summary: max_error.png, the "
                          "metric of the summary table; all: also rms_error, energy_error, "
                          "halt_time_error and halt_position_error (.png, about a second "
                          "each); none: no figure (default: %(default)s)")
    out.add_argument("--no-progress", action="store_true",
                     help="no progress bar (there is none when stderr is not a terminal)")
    par = parser.add_argument_group(
        "several processes (jax.distributed: each process computes a share of the map, "
        "process 0 gathers them and writes the files)")
    par.add_argument("--processes", type=int, metavar="N",
                     help="start N local worker processes on this machine (127.0.0.1, a free "
                          "port) and gather their shares (default: this process alone)")
    par.add_argument("--cluster", action="store_true",
                     help="join a run launched by Slurm (srun) or Open MPI (mpirun): "
                          "jax.distributed.initialize() reads the job's environment")
    par.add_argument("--coordinator", metavar="HOST:PORT",
                     help="join a run: process 0's address and a free port, the same in "
                          "every process (with --process-id and --num-processes)")
    par.add_argument("--process-id", type=int, metavar="I",
                     help="with --coordinator: this process's index, 0 .. N-1")
    par.add_argument("--num-processes", type=int, metavar="N",
                     help="with --coordinator: the number of processes")
    par.add_argument("--timeout", type=float, default=300.0, metavar="SECONDS",
                     help="for the processes to connect, and for each to wait for the others "
                          "at the gather; a process that dies ends the run sooner "
                          "(default: %(default)g)")
    parser.epilog = ("Exit status: 0 ok, 2 invalid input, 3 a run of several processes failed "
                     "(a process died, failed or timed out; nothing is written), "
                     "130 interrupted.")


def add_sensitivity_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``dampax sensitivity``."""
    add_oscillator_arguments(parser, mu=0.05, D=1.0, start_title="initial state")
    what = parser.add_argument_group("sensitivities")
    what.add_argument("--wrt", default="mu,D", metavar="NAMES",
                      help=f"comma-separated parameters to differentiate with respect to, from "
                           f"{','.join(PARAMETERS)} (default: %(default)s)")
    what.add_argument("--models", default=None, metavar="NAMES",
                      help=f"comma-separated models: {', '.join(MODELS)} "
                           "(default: matched,reference; with --global: matched)")
    what.add_argument("--t-end", type=float, default=None, metavar="SECONDS",
                      help="time span of the plot (default: half an undamped period past the "
                           "matched ansatz's halt, 2 to 12 periods; 4 periods if it never halts)")
    what.add_argument("--samples", type=int, default=400, metavar="N",
                      help="time samples of the plot (default: %(default)s)")
    what.add_argument("--window", type=float, default=0.05, metavar="W",
                      help="relative half-width of the trend window: the trend derivative is "
                           "the least-squares slope of the halt time (position) over "
                           "theta (1 - W) ... theta (1 + W), 0 < W < 1 (default: %(default)s, "
                           "i.e. +-5 %%)")
    what.add_argument("--window-points", type=int, default=41, metavar="N",
                      help="parameter values per trend window, >= 3 (default: %(default)s)")
    what.add_argument("--swings", action="store_true",
                      help="also count the swings (turning points before the halt, the rest "
                           "point included) and give their trend over the window; the local "
                           "derivative of a count is 0, so a non-zero trend is flagged: a swing "
                           "is lost or gained inside the window (costs compilation time)")
    what.add_argument("--turning-points", type=int, default=0, metavar="N",
                      help="also give the first N turning points (t_n, x_n: v = 0, t > 0) with "
                           "their local and trend derivatives; the trend is fitted over the "
                           "window points where turning point n exists, '-' where fewer than 3 "
                           "have it (default: %(default)s, none; costs compilation time)")
    glob = parser.add_argument_group(
        "global sensitivity (Sobol' indices over ranges instead of derivatives at a point)")
    glob.add_argument("--global", dest="global_spec", default=None, metavar="SPEC",
                      help="ranges of the parameters, e.g. \"mu=0.01:0.05,D=0.5:3\" (names "
                           f"from {','.join(PARAMETERS)}): prints Sobol' S1, ST with "
                           "bootstrap 95%% half-widths and DGSM, and draws them as bars "
                           "(--plot); the other parameters are those of the options above")
    glob.add_argument("--quantity", default="halt_time", choices=QUANTITIES,
                      help="quantity of the global study: halt time, halt position, energy or "
                           "x at --time, or max_error (max |x - x_ref|/A0 of the model against "
                           "the reference on [0, --time]) (default: %(default)s)")
    glob.add_argument("--time", type=float, default=None, metavar="SECONDS",
                      help="time of --quantity energy or x (required there); end of the "
                           "max_error window (default: 10 undamped periods)")
    glob.add_argument("--n", type=int, default=4096, metavar="N",
                      help="base samples of the Saltelli design, >= 16, a power of 2 is best "
                           "(N (k + 2) model evaluations for k parameters; default: "
                           "%(default)s)")
    glob.add_argument("--seed", type=int, default=0, metavar="SEED",
                      help="seed of the design and the bootstrap (default: %(default)s)")
    out = parser.add_argument_group("output")
    out.add_argument("--digits", type=int, default=4, metavar="N",
                     help="significant digits printed (default: %(default)s)")
    out.add_argument("--plot", metavar="FILE.png", default="sensitivity.png",
                     help="where to save the plot of dx/dtheta, or with --global the bar "
                          "chart of S1 and ST (default: %(default)s)")
    out.add_argument("--trend-plot", metavar="FILE.png", default=None,
                     help="where to save the plot of the halt time and position over each "
                          "parameter's trend window (default: --plot's name with _trend, e.g. "
                          "sensitivity_trend.png; not drawn with --global)")


def add_fit_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``dampax fit``."""
    parser.epilog = (
        "Without --k the fit is per unit mass: w0 is fitted, b/m [1/s] and D/m [1/unit].\n"
        "exit status:\n"
        "  0  the fit succeeded and the model describes the data\n"
        "  2  invalid input, one line on stderr (also a trace without a free decay in it)\n"
        "  3  the fit failed (the reason is the report's first line)\n"
        "  4  the fit converged but the model does not describe the data\n"
        "The results are written in every case but 2.")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("path", nargs="*", help="text file with the trace (time and position "
                        "columns), or with a table of maxima for --envelope; several files: "
                        "a joint fit of runs of one apparatus (see --shared)")
    parser.add_argument("--example", action="store_true",
                        help="fit a synthetic trace with known constants (m = 0.2 kg, "
                             "k = 15 N/m, mu = 0.002, D = 0.02 kg/m, noise 0.2 mm)")
    read = parser.add_argument_group("reading the file")
    read.add_argument("--time", metavar="COL",
                      help="time column, name or index (default: the column the header names "
                           "a time, e.g. 'time', 'Time_Elapsed(s)'; without a header the "
                           "first)")
    read.add_argument("--position", metavar="COL",
                      help="position column, name or index (default: the column the header "
                           "names a position, e.g. 'x', 'position', 'Angle(deg)'; without a "
                           "header the second)")
    read.add_argument("--rate", metavar="HZ|auto",
                      help="rebuild time from the sample index: a rate [1/s], or 'auto' for "
                           "buffered time stamps")
    read.add_argument("--delimiter", help="column separator (default: detected)")
    read.add_argument("--scale", type=float, default=1.0,
                      help="factor applied to the positions (default: %(default)s)")
    read.add_argument("--units", default=None,
                      help="unit of the positions, for the report (m, cm, mm, deg, rad, ...; "
                           "default: the unit in the position column's name, e.g. "
                           "'Angle(deg)', else m)")
    osc = parser.add_argument_group(
        "oscillator (fixed constants; without --k the fit is per unit mass: w0 fitted, "
        "b/m in 1/s and D/m in 1/unit)")
    osc.add_argument("--m", type=float, default=None,
                     help="mass [kg]; with it b and D are reported in kg/s and kg/m (positions "
                          "in lengths); default: unit mass, per-mass b/m and D/m")
    osc.add_argument("--k", type=float, default=None,
                     help="stiffness [N/m] (needs --m): w0 = sqrt(k/m) fixed unless "
                          "--fit-omega0; default: w0 fitted from the data")
    osc.add_argument("--g", type=float, default=9.81,
                     help="gravitational acceleration [m/s^2], converts the Coulomb term d0 "
                          "to mu (default: %(default)s)")
    model = parser.add_argument_group("model and fit")
    model.add_argument("--free", default="mu,D",
                       help="constants to fit, comma list of mu, b, D, k3 (the cubic "
                            "stiffness, profiled; trace fits only) and mu_s (static friction, "
                            "searched by the halt it gives; --model reference) (default: "
                            "%(default)s)")
    model.add_argument("--mu-s", dest="mu_s", type=float, default=None, metavar="MU_S",
                       help="hold the static friction coefficient at this value (>= mu; "
                            "--model reference; default: mu_s = mu)")
    model.add_argument("--shared", default=None, metavar="LIST",
                       help="several files: the parameters common to all runs, comma list of "
                            "mu, b, D, w0 and k3 (default: the --free constants); each run "
                            "keeps its own start, offset and window")
    model.add_argument("--model", default="auto", choices=("auto", *FIT_MODELS),
                       help="auto: the exact model's answer, given by the ansatz where one "
                            "Gauss-Newton step of the exact model moves no parameter by more "
                            "than 0.1 interval sd (the report says which model answered); "
                            + "; ".join(f"{name}: {FIT_MODELS[name]}" for name in FIT_MODELS)
                            + " (default: %(default)s)")
    model.add_argument("--fit-omega0", action="store_true",
                       help="with --m and --k: also fit w0 (k = m w0^2), needed when k/m is not "
                            "known exactly (without --k w0 is always fitted)")
    model.add_argument("--no-offset", action="store_true",
                       help="do not fit the equilibrium offset (envelope fits have none)")
    model.add_argument("--loss", default="linear", choices=LOSSES,
                       help="soft_l1 for traces with outliers (default: %(default)s)")
    model.add_argument("--optimizer", default="lm", choices=OPTIMIZERS,
                       help="; ".join(f"{name}: {METHOD_NAMES[name]}" for name in OPTIMIZERS)
                            + " (default: %(default)s)")
    model.add_argument("--start", default="auto",
                       help="fit start: auto (the first sample of a record that moves from "
                            "it, else the first extreme after the largest excursion), data "
                            "(first sample) or a time [s] (default: %(default)s)")
    model.add_argument("--end", type=float, default=None, help="fit end time [s]")
    model.add_argument("--envelope", action="store_true",
                       help="the file holds successive maxima (t, amplitude): envelope fit")
    model.add_argument("--omega0", type=float, default=None,
                       help="--envelope: angular frequency (default: from the peak spacing)")
    model.add_argument("--no-compare", action="store_true",
                       help="skip the ranking of candidate damping models")
    model.add_argument("--starts", type=int, default=32,
                       help="global starts: jittered starts around the turning-point guess, "
                            "optimised in one vmapped batch (default: %(default)s; 1: the "
                            "guess alone)")
    model.add_argument("--seed", type=int, default=0,
                       help="seed of the jittered starts and of the posterior's chains "
                            "(default: %(default)s)")
    model.add_argument("--max-steps", type=int, default=None,
                       help="optimizer step budget per optimisation (default: 256 for lm)")
    unc = parser.add_argument_group("uncertainty")
    unc.add_argument("--intervals", action="store_true",
                     help="print confidence intervals that allow for correlated residuals "
                          "(FitResult.conf_interval: Newey-West sandwich) at --level")
    unc.add_argument("--level", type=float, default=0.95,
                     help="two-sided level of --intervals and of the posterior summary "
                          "(default: %(default)s)")
    unc.add_argument("--posterior", action="store_true",
                     help="also sample the posterior with NUTS (blackjax, AR(1) noise) of "
                          "--model and write posterior.nc (ArviZ InferenceData: "
                          "arviz.from_netcdf opens it) and corner.png; with several files, "
                          "of the joint fit (shared and per-run parameters, noise per run)")
    unc.add_argument("--draws", type=int, default=1000,
                     help="--posterior: draws per chain (default: %(default)s)")
    unc.add_argument("--chains", type=int, default=4,
                     help="--posterior: chains (default: %(default)s)")
    unc.add_argument("--warmup", type=int, default=500,
                     help="--posterior: warm-up steps per chain (blackjax window adaptation; "
                          "default: %(default)s)")
    out = parser.add_argument_group("output")
    out.add_argument("--out", metavar="DIR", default="fit",
                     help="folder for fit.json and fit.png (default: %(default)s)")


def add_reproduce_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``dampax reproduce``."""
    parser.add_argument("--out", default="reproduce", metavar="DIR",
                        help="output folder (default: %(default)s)")
    parser.add_argument("--figures", default="all", metavar="LIST",
                        help="figures to draw: numbers 2-21, ranges (8-10), 'rizcallah', "
                             "'all' or 'none', comma-separated (default: %(default)s)")
    parser.add_argument("--no-numbers", action="store_true",
                        help="skip numbers.csv / numbers.md")
    parser.add_argument("--format", default="png", metavar="EXT",
                        help="image format: png, pdf, svg, ... (default: %(default)s)")
    parser.add_argument("--dpi", type=int, default=110, help="resolution (default: %(default)s)")
    parser.add_argument("--no-progress", action="store_true",
                        help="no progress bar (there is none when stderr is not a terminal)")


#: name -> (one-line summary, add_arguments(parser)), in the order of ``dampax --help``
COMMANDS = {
    "solve": ("Print the amplitudes, damping ratios, halt times and turning points of every "
              "model.", add_solve_arguments),
    "errormap": ("Error maps of the analytic models against the reference over a grid of "
                 "damping ratios.", add_errormap_arguments),
    "sensitivity": ("Print how the halt time and position depend on the parameters; plot "
                    "d x(t)/d theta.", add_sensitivity_arguments),
    "fit": ("Fit damping constants to a measured trace; print the report and the model "
            "ranking.", add_fit_arguments),
    "reproduce": ("Redraw Figures 2-21 of Lelas & Pezer and Rizcallah's comparison; recompute "
                  "quoted numbers.", add_reproduce_arguments),
}
