"""The ``dampax`` command line, in process (capsys) and once through the installed script.

The console-script run starts at the first test of this module and runs beside the in-process
tests (the 2-core test machine compiles in both at once); its test collects it at the end.
"""

import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from dampax._cli import main

W0 = math.sqrt(30.0)  # m = 1 kg, k = 30 N/m
G = 9.81
X0 = 0.2
# mu for d0/(w0 A0) = 0.05 at A0 = 0.2 m (inverts d0 = 2 mu g/(pi w0), eq. 21)
MU_005 = 0.05 * W0 * X0 * math.pi * W0 / (2.0 * G)
# in process only the analytic models (a stand-in for the reference below): the diffrax
# reference integrator compiles for ~10 s; the console-script run covers the real one
FAST = ["--no-reference"]


def _value(out: str, name: str) -> str:
    """The printed value of a ``name = value`` line of the summary."""
    match = re.search(rf"^\s*{re.escape(name)}\s+=\s+(\S+)", out, re.MULTILINE)
    assert match, f"no line '{name} = ...' in:\n{out}"
    return match.group(1)


def _row(out: str, label: str) -> list[str]:
    """The halt time and halt position printed in the model table for ``label``."""
    line = next((ln for ln in out.splitlines() if ln.strip().startswith(label)), None)
    assert line is not None, f"no row {label!r} in:\n{out}"
    return re.split(r"\s{2,}", line.strip())[1:]  # columns are 2+ spaces apart


@pytest.fixture(scope="module", autouse=True)
def console_script():
    """``dampax solve --mu 0.1`` through the installed entry point, started early."""
    script = Path(sys.executable).with_name("dampax")
    assert script.exists(), f"console script not installed next to {sys.executable}"
    proc = subprocess.Popen([str(script), "solve", "--mu", "0.1"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    yield proc
    if proc.poll() is None:
        proc.kill()
        proc.communicate()


def test_default_case_undamped(capsys):
    assert main(["solve", *FAST]) == 0
    out = capsys.readouterr().out
    # no damping: the matched amplitude and phase are the undamped ones, nothing halts
    assert _value(out, "A") == "0.2"
    assert _value(out, "phi") == "0"
    assert _value(out, "A0") == "0.2"
    assert _value(out, "d0/(w0 A0)") == "0"
    assert _value(out, "xc") == "0"
    assert _row(out, "matched ansatz") == ["never", "-"]
    assert _row(out, "undamped-phase ansatz") == ["never", "-"]
    assert "Rizcallah" not in out and "Coulomb tail" not in out
    # turning points at n pi / w0, alternating +-x0
    t6 = f"{6 * math.pi / W0:.4g}"
    assert re.search(rf"^\s*6\s+{re.escape(t6)}\s+0\.2\s+1\s*$", out, re.MULTILINE), out


def test_coulomb_005_matches_eq_40(capsys):
    assert main(["solve", "--mu", repr(MU_005), *FAST]) == 0
    out = capsys.readouterr().out
    d0 = 2.0 * MU_005 * G / (math.pi * W0)
    # eq. 40: the Coulomb case of the quartic, started at rest
    A = math.sqrt((X0**2 + math.sqrt(X0**4 + 4.0 * (d0 * X0 / W0) ** 2)) / 2.0)
    phi = math.atan(-d0 / (W0 * A))
    assert _value(out, "A") == f"{A:.4g}" == "0.2002"
    assert _value(out, "phi") == f"{phi:.4g}" == "-0.0499"
    assert _value(out, "d0/(w0 A0)") == "0.05"
    xc = MU_005 * G / W0**2
    assert _value(out, "xc") == f"{xc:.4g}"
    # exact Coulomb motion from rest: x_n = (-1)^n (x0 - 2 n xc) until |x_n| <= xc
    n = math.ceil((X0 - xc) / (2.0 * xc))
    expected = [f"{n * math.pi / W0:.4g}", f"{(-1) ** n * (X0 - 2 * n * xc):.4g}"]
    assert _row(out, "exact half-swings") == expected
    assert _row(out, "Rizcallah") == expected
    assert _row(out, "matched ansatz")[1] == "0"


def test_plot_writes_png(tmp_path, capsys):
    path = tmp_path / "fig.png"
    # same options as above but --plot: the solve is compiled already
    assert main(["solve", "--mu", repr(MU_005), "--plot", str(path), *FAST]) == 0
    assert str(path) in capsys.readouterr().out
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    import matplotlib.image

    image = matplotlib.image.imread(path)
    assert image.shape[0] >= 300 and image.shape[1] >= 400
    assert image[..., :3].std() > 0.05  # something was drawn


@pytest.mark.parametrize("argv, field", [(["--m", "-1"], "m"), (["--mu", "-0.1"], "mu"),
                                         (["--x0", "nan"], "x0")])
def test_bad_input_exits_2(argv, field, capsys):
    assert main(["solve", *argv, *FAST]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert "\n" not in err and captured.out == ""
    assert re.match(rf"dampax: error: (--)?{field}\b", err), err  # the field or its flag


def test_bad_plot_path_fails_before_solving(tmp_path, capsys):
    assert main(["solve", "--plot", str(tmp_path / "nowhere" / "fig.png")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_syntax_error_exits_2(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["solve", "--m", "abc"])
    assert exc.value.code == 2
    with pytest.raises(SystemExit) as exc:
        main([])
    assert exc.value.code == 2


def _fake_reference(monkeypatch, behaviour):
    """Replace the DOP853 reference by the exact half-swings, or make it fail."""
    import dampax._studies._summary as summary

    real = summary.solve_checked  # run_models checked its input; the reference's solve
    seen = {}

    def solve(osc, x0, v0, **options):
        if options.get("method") != "reference":
            return real(osc, x0, v0, **options)
        seen.update(options)
        if behaviour == "fails":
            raise ValueError("the reference ran out of its budget (a stand-in failure)")
        return real(osc, x0, v0, method="coulomb_exact")

    monkeypatch.setattr(summary, "solve_checked", solve)
    return seen


def test_reference_row_and_curve(monkeypatch, tmp_path, capsys):
    # the CLI's plumbing for the reference, with the exact solution standing in for diffrax
    seen = _fake_reference(monkeypatch, "exact")
    path = tmp_path / "ref.png"
    assert main(["solve", "--mu", repr(MU_005), "--t-end", "4", "--plot", str(path)]) == 0
    captured = capsys.readouterr()
    assert seen == {"method": "reference", "t_end": 4.0}
    assert _row(captured.out, "reference (DOP853)") == _row(captured.out, "exact half-swings")
    assert captured.err == "" and path.stat().st_size > 0


def test_failed_reference_is_a_note(monkeypatch, capsys):
    _fake_reference(monkeypatch, "fails")
    assert main(["solve", "--mu", repr(MU_005)]) == 0
    captured = capsys.readouterr()
    assert "dampax: note: reference integrator failed, skipped: the reference ran out" in \
        captured.err
    assert _row(captured.out, "reference (DOP853)") == ["not available"]
    assert _value(captured.out, "A") == "0.2002"


def test_console_script(console_script):
    out, err = console_script.communicate(timeout=300)
    assert console_script.returncode == 0, err
    assert _value(out, "d0/(w0 A0)") == "0.1041"
    for label in ("matched ansatz", "undamped-phase ansatz", "matched + Coulomb tail",
                  "Rizcallah", "exact half-swings", "reference"):
        assert _row(out, label), label
    # the reference integrator is either there and agrees with the exact half-swings
    # (rest after 3 half-swings at x0 - 6 xc = -0.0038 m), or it is reported missing
    ref = _row(out, "reference")
    exact = [float(v) for v in _row(out, "exact half-swings")]
    assert exact == pytest.approx([3 * math.pi / W0, -(X0 - 6 * 0.1 * G / W0**2)], abs=1e-3)
    if ref != ["not available"]:
        assert [float(v) for v in ref] == pytest.approx(exact, abs=1e-4), out


def test_console_script_leaves_with_the_status_and_every_line():
    """The console script ends the process with ``os._exit`` after a command
    (``dampax_cli.leave``): the command's status and its last line still arrive through a
    pipe (the streams are flushed first), and atexit handlers run."""
    code = ("import atexit, sys; from dampax_cli import leave; "
            "atexit.register(lambda: print('atexit ran', file=sys.stderr)); "
            "print('last line', end=''); leave(3)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 3 and proc.stdout == "last line"
    assert proc.stderr.strip() == "atexit ran"
    proc = subprocess.run([sys.executable, "-m", "dampax_cli", "solve", "--m", "-1"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stderr.startswith("dampax: error: ")
    assert proc.stderr.count("\n") == 1


def test_console_script_holds_blas_to_one_thread_unless_told():
    """The console script's process runs numpy's BLAS on one thread (OpenBLAS's idle worker
    would spin on the core XLA needs) and collects cycles every 100,000 allocations; a user's
    OPENBLAS_NUM_THREADS stands. Read from the library itself (threadpoolctl) in the process
    of ``dampax_cli.console`` with its command replaced."""
    code = ("import gc, dampax_cli\n"
            "def main(**kwargs):\n"
            "    import numpy\n"
            "    from threadpoolctl import threadpool_info\n"
            "    print(sorted({d['num_threads'] for d in threadpool_info()"
            " if d['user_api'] == 'blas'}), gc.get_threshold()[0])\n"
            "    return 0\n"
            "dampax_cli.main = main\n"
            "dampax_cli.console()\n")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    for given, expected in ((None, 1), ("2", 2)):
        if given is not None:
            env["OPENBLAS_NUM_THREADS"] = given
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              timeout=60, env=env)
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.split() == [f"[{expected}]", "100000"], (given, proc.stdout)


@pytest.mark.parametrize("argv, flag", [
    (["solve", "--plot", "/proc/dampax-test.png"], "--plot"),
    (["sensitivity", "--plot", "/proc/dampax-test.png"], "--plot"),
    (["errormap", "--quick", "--out", "/proc/dampax-test"], "--out"),
    (["reproduce", "--out", "/proc/dampax-test"], "--out"),
])
def test_unwritable_output_fails_before_computing(argv, flag, capsys):
    """/proc exists but no file can be created there (not even by root): the command stops at
    once with one line naming the option, before any computing (no progress bar, no result)."""
    if not Path("/proc").is_dir():
        pytest.skip("needs /proc")
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert err.startswith(f"dampax: error: {flag}: cannot ") and err.count("\n") == 1
    assert "error map" not in err and out == ""


@pytest.mark.parametrize("cache", ["fresh", "warm"])
def test_ctrl_c_exits_130_in_one_line_without_partial_files(tmp_path, cache):
    """SIGINT during `dampax errormap` (while compiling, with a fresh cache; while computing,
    with a warm one): exit status 130 at once, one line, no traceback, and neither errormap.nc
    nor a temporary file in the output folder."""
    import os
    import signal
    import time

    out = tmp_path / "maps"
    env = dict(os.environ)
    if cache == "fresh":
        env["DAMPAX_CACHE_DIR"] = str(tmp_path / "cache")
    proc = subprocess.Popen([sys.executable, "-u", "-m", "dampax._cli", "errormap", "--out",
                             str(out), "--no-progress"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    header = proc.stdout.readline()  # printed just before the map starts
    assert header.startswith("dampax errormap: 2048 points"), header
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)  # not after a compilation or the whole map
    assert proc.returncode == 130, err
    assert err.strip() == "dampax: interrupted"
    assert list(out.iterdir()) == []


def test_partial_outputs_are_removed(tmp_path):
    """What the Ctrl-C watcher relies on: an unfinished write is a registered temporary file,
    removed on request or on an exception, and the final file appears only when complete."""
    from dampax import _io

    target = tmp_path / "out.nc"
    with pytest.raises(RuntimeError):
        with _io.atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("stop")
    assert list(tmp_path.iterdir()) == []
    with _io.atomic_path(target) as tmp:
        tmp.write_text("half")
        assert tmp in _io.PARTIAL and not target.exists()
        _io.remove_partial_files()
        assert not tmp.exists()
        tmp.write_text("whole")
    assert target.read_text() == "whole" and list(tmp_path.iterdir()) == [target]


def test_netcdf_files_have_no_fill_value_on_coordinates(tmp_path):
    """dampax._io.write_netcdf, behind errormap.nc and posterior.nc: CF allows no _FillValue on
    a coordinate variable, which xarray gives every float variable (NaN) unless told not to;
    data variables keep theirs."""
    import numpy as np
    import xarray as xr
    from helpers import check_cf_file

    from dampax._io import write_netcdf

    ds = xr.Dataset({"D": (("chain", "draw"), np.array([[0.1, np.nan, 0.3]] * 2)),
                     "w": ("x", [1.0, 2.0])},
                    coords={"chain": np.arange(2), "draw": np.arange(3), "x": [0.0, 0.5]})
    plain = tmp_path / "plain.nc"
    ds.to_netcdf(plain, engine="scipy")
    with pytest.raises(AssertionError, match="coordinate x has a _FillValue"):
        check_cf_file(plain)
    path = write_netcdf(ds, tmp_path / "clean.nc")
    assert path == tmp_path / "clean.nc" and sorted(p.name for p in tmp_path.iterdir()) == [
        "clean.nc", "plain.nc"]
    attrs = check_cf_file(path)
    assert np.isnan(attrs["D"]["_FillValue"]) and np.isnan(attrs["w"]["_FillValue"])
    xr.testing.assert_identical(xr.load_dataset(path, engine="scipy"), ds)


# -- the launcher (dampax_cli), --quiet and progress bars (issue 26) --------------------------

LIGHT = [["--version"], ["--help"], ["solve", "--bogus"]] + [
    [name, "--help"] for name in ("solve", "errormap", "sensitivity", "fit", "reproduce")]


def test_help_and_version_do_not_import_jax():
    """`dampax --version`, `--help`, `dampax SUBCOMMAND --help` and a syntax error are answered
    by the console script's launcher without importing dampax, JAX or numpy (-X importtime
    lists every module the interpreter imported)."""
    import tomllib

    import dampax
    from dampax import _cli

    pyproject = Path(__file__).resolve().parents[2] / "pyproject.toml"
    scripts = tomllib.loads(pyproject.read_text())["project"]["scripts"]
    assert scripts == {"dampax": "dampax_cli:console"}
    for argv in LIGHT:
        proc = subprocess.run([sys.executable, "-X", "importtime", "-m", "dampax_cli", *argv],
                              capture_output=True, text=True, timeout=60)
        imported = {line.split("|")[-1].strip() for line in proc.stderr.splitlines()
                    if line.startswith("import time:")}
        assert "dampax_cli" in imported and "argparse" in imported, argv
        heavy = {m for m in imported if m.split(".")[0] in ("dampax", "jax", "jaxlib", "numpy")}
        assert heavy == set(), (argv, sorted(heavy))
        if argv == ["--version"]:
            assert (proc.returncode, proc.stdout) == (0, f"dampax {dampax.__version__}\n")
        elif argv == ["--help"]:
            assert proc.returncode == 0
            assert all(re.search(rf"^\s+{name}\b", proc.stdout, re.MULTILINE)
                       for name in _cli.SUBCOMMANDS), proc.stdout
        elif argv[-1] == "--help":
            assert proc.returncode == 0 and proc.stdout.startswith(f"usage: dampax {argv[0]}")
            assert "-q, --quiet" in proc.stdout
        else:
            assert proc.returncode == 2 and "unrecognized arguments: --bogus" in proc.stderr


def test_launcher_names_are_the_librarys():
    """The option definitions of dampax_cli copy a few names of dampax's registries (it must
    not import dampax): they are the library's."""
    from dampax import _fit, _plot
    from dampax._fit import _core
    from dampax._models import _registry as _models
    from dampax._studies import _global, _maps, _sensitivity
    from dampax_cli import _arguments as a

    assert a.ANALYTIC == _models.ANALYTIC and a.MODELS == tuple(_models.MODELS)
    assert (a.DEFAULT_MODELS, a.REFERENCES) == (_maps.DEFAULT_MODELS, _maps.REFERENCES)
    assert (a.PARAMETERS, a.QUANTITIES) == (_sensitivity.PARAMETERS, _global.QUANTITIES)
    assert a.FIT_MODELS == {name: _core.FIT_MODELS[name].description for name in _fit.MODELS}
    assert (a.OPTIMIZERS, a.METHOD_NAMES, a.LOSSES) == (
        _fit.OPTIMIZERS, _fit.METHOD_NAMES, _fit.LOSSES)
    assert a.ERRORMAP_PLOTS["all"] == tuple(_plot.ERROR_MAP_METRICS)
    assert set(a.ERRORMAP_PLOTS["summary"]) <= set(_plot.ERROR_MAP_METRICS)


def test_launcher_runs_the_command_quietly(monkeypatch, capsys):
    """dampax_cli.main hands a parsed command to dampax._cli; --quiet prints nothing but
    errors: not the results, not the notes on stderr, but the one line of invalid input."""
    import dampax_cli

    assert dampax_cli.main(["solve", *FAST, "--quiet"]) == 0  # compiled by the first test
    assert capsys.readouterr() == ("", "")
    assert dampax_cli.main(["solve", *FAST]) == 0
    assert _value(capsys.readouterr().out, "A") == "0.2"
    assert dampax_cli.main(["solve", "--m", "-1", "-q", *FAST]) == 2
    out, err = capsys.readouterr()
    assert out == "" and re.fullmatch(r"dampax: error: m\b[^\n]*\n", err), err
    _fake_reference(monkeypatch, "fails")  # a note on stderr without --quiet (test above)
    assert main(["solve", "--mu", repr(MU_005), "--quiet"]) == 0
    assert capsys.readouterr() == ("", "")


def test_quiet_keeps_error_lines_only(capsys):
    """What --quiet silences (dampax._cli._common.silenced): stdout, stderr, Python warnings
    and logging below ERROR; the lines of _common.error (a failed fit) still reach stderr,
    and everything is back after the block."""
    import logging
    import warnings

    from dampax._cli._common import error, silenced

    with silenced(True):
        print("a result")
        print("dampax: note: something", file=sys.stderr)
        warnings.warn("a warning", UserWarning, stacklevel=1)
        logging.getLogger("jax").warning("a log warning")
        error("dampax: fit failed: the reason")
    assert capsys.readouterr() == ("", "dampax: fit failed: the reason\n")
    with silenced(False):
        print("a result")
        error("dampax: fit failed")
    assert capsys.readouterr() == ("a result\n", "dampax: fit failed\n")
    assert logging.root.manager.disable == logging.NOTSET


def test_progress_bars_only_on_a_terminal(monkeypatch, tmp_path, capsys):
    """Progress bars are drawn only when stderr is a terminal (a pseudo-terminal here) and
    neither --no-progress nor --quiet is given; errormap and reproduce pass that on."""
    import argparse
    import os

    import dampax._paper._reproduce
    import dampax._studies._maps
    from dampax._cli._common import show_progress

    master, slave = os.openpty()
    with os.fdopen(slave, "w") as tty, open(tmp_path / "log", "w") as log:
        assert tty.isatty() and not log.isatty()
        for no_progress, quiet, stream, expected in [
                (False, False, tty, True), (False, False, log, False),
                (True, False, tty, False), (False, True, tty, False)]:
            args = argparse.Namespace(no_progress=no_progress, quiet=quiet)
            assert show_progress(args, stream) is expected
    os.close(master)

    seen = []

    def fake(*args, progress, **kwargs):
        seen.append(progress)
        raise ValueError("stop here")

    monkeypatch.setattr(dampax._studies._maps, "error_map", fake)
    monkeypatch.setattr(dampax._paper._reproduce, "reproduce", fake)
    for command in (["errormap", "--quick"], ["reproduce", "--figures", "none"]):
        for terminal, extra, expected in [(False, [], False), (True, [], True),
                                          (True, ["--no-progress"], False),
                                          (True, ["--quiet"], False)]:
            # stderr is pytest's capture (no terminal) unless told otherwise
            monkeypatch.setattr(sys.stderr, "isatty", lambda terminal=terminal: terminal)
            assert main([*command, "--out", str(tmp_path / command[0]), *extra]) == 2
            assert seen.pop() is expected, (command, terminal, extra)
    assert seen == []
    assert capsys.readouterr().err.count("dampax: error: stop here") == 8


def test_errormap_plots_option(tmp_path, capsys):
    """``errormap --plots``: summary (the default) writes max_error.png beside errormap.nc,
    none no figure; an unknown choice is a syntax error. (``--plots all``, every metric's
    heat map: tests/studies/test_maps.py::test_cli_quick.)"""
    # the grid and settings of tests/models/test_results.py::test_one_spelling_in_every_command
    grid = ["--models", "matched_tail", "--reference", "coulomb_exact", "--d0", "0.05",
            "--d2", "0", "--phi0", "0", "--periods", "3", "--samples-per-period", "16",
            "--no-progress"]
    for extra, figures in (([], ["max_error.png"]), (["--plots", "none"], [])):
        out = tmp_path / (extra[-1] if extra else "default")
        assert main(["errormap", *grid, "--out", str(out), *extra]) == 0
        assert sorted(p.name for p in out.iterdir()) == sorted(["errormap.nc", *figures])
        for name in figures:
            assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        written = capsys.readouterr().out
        assert ("max_error.png" in written) == bool(figures), written
    with pytest.raises(SystemExit) as exc:
        main(["errormap", "--plots", "some", "--out", str(tmp_path / "x")])
    assert exc.value.code == 2
    assert "--plots" in capsys.readouterr().err


def test_import_dampax_leaves_the_optional_stacks_out():
    """``import dampax`` (and the command line's module) import neither the fitting stack nor
    plotting, netCDF or sampling libraries: ``dampax solve`` does not pay for them (issue 26),
    nor the fused GPU kernel and Pallas's Triton backend off a GPU (50-100 ms of every import).
    The lazy names still resolve, with ``from dampax import fit``, and ``dir()`` lists them."""
    heavy = ("dampax._fit", "dampax._studies._global", "dampax._studies._maps", "optimistix",
             "optax", "lineax", "blackjax", "matplotlib", "xarray", "arviz", "scipy",
             "dampax._reference._kernel", "jax.experimental.pallas.triton")
    code = ("import sys, dampax, dampax._cli; "
            f"print(sorted(m for m in sys.modules if m.split('.')[0] in {heavy!r} "
            f"or m in {heavy!r})); "
            "names = dir(dampax); from dampax import fit, error_map; import dampax as d; "
            "print(fit is d._fit.fit, 'fit' in names, 'global_sensitivity' in names, "
            "d.error_map is d._studies._maps.error_map, 'fit' in d.__all__)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "DAMPAX_CACHE": "0"})
    assert proc.returncode == 0, proc.stderr
    imported, resolved = proc.stdout.splitlines()
    assert imported == "[]", imported
    assert resolved == "True True True True True"
    import dampax

    with pytest.raises(AttributeError, match="no_such_name"):
        dampax.no_such_name  # noqa: B018
