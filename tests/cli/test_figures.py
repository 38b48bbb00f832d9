"""``dampax fit``'s figure drawn by a process forked before dampax loads (``dampax_cli._figures``,
issue 36): the same PNG, byte for byte, as the command draws in its own process; the drawing
module loads without JAX; a worker that cannot draw answers so (the command then draws) and
never creates a file the command did not make. Each case runs in a fresh interpreter: a worker
is forked only where nothing but the launcher is loaded."""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dampax_cli import _figures

pytestmark = pytest.mark.skipif(not hasattr(os, "fork") or sys.platform == "darwin",
                                reason="the figure process needs fork (not macOS)")


def _python(code: str, *args, env=None) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True,
                          text=True, timeout=240, env=env)
    assert proc.returncode == 0, proc.stderr
    return proc


def test_the_figure_module_loads_without_jax():
    """The worker's import of ``dampax._plot_fit`` (and ``dampax._io``) runs neither
    dampax's ``__init__`` nor JAX: what it saves is the import of both."""
    out = _python("import sys; from dampax_cli import _figures\n"
                  "m = _figures._figure_module()\n"
                  "print(callable(m.fit_figure), 'jax' in sys.modules, "
                  "'dampax._oscillator' in sys.modules)").stdout.split()
    assert out == ["True", "False", "False"]


def _maxima(folder: Path) -> Path:
    """Nine maxima of a Coulomb decay (those of test_fit_messages.py's envelope fit)."""
    m, k, mu, g = 0.5, 20.0, 0.01, 9.81
    w0 = math.sqrt(k / m)
    n = np.arange(9)
    path = folder / "maxima.csv"
    np.savetxt(path, np.column_stack([0.3 + n * 2.0 * math.pi / w0,
                                      0.1 - n * 4.0 * mu * g / w0**2]),
               fmt="%.17g", delimiter=",", header="t,amplitude", comments="")
    return path


#: the console script, with ``_figures.draw`` noting in $MARK that the worker drew
_CONSOLE = """
import os, sys, dampax_cli
from dampax_cli import _figures
real = _figures.draw
def draw(*args):
    out = real(*args)
    with open(os.environ["MARK"], "w") as fh:
        fh.write("drawn")
    return out
_figures.draw = draw
sys.argv = ["dampax"] + sys.argv[1:]
dampax_cli.console()
"""


def test_the_console_script_draws_the_same_figure_in_its_worker(tmp_path):
    """``dampax fit FILE --envelope`` through the console script, with its figure process and
    without (``DAMPAX_FIGURE_PROCESS=0``): the worker draws (it is not the command's own
    drawing after a failure), the same fit.png byte for byte and the same report, its log
    messages (matplotlib's "findfont", from a matplotlibrc naming a font that does not exist)
    on the command's stderr, and no temporary file left; with the command's stdin and stderr
    closed the worker still draws (a closed stderr ended the command with status 1, a closed
    stdin's number taken by a pipe stopped the worker)."""
    path = _maxima(tmp_path)
    (tmp_path / "mpl").mkdir()
    (tmp_path / "mpl" / "matplotlibrc").write_text("font.family: NoSuchFontFamily\n")
    args = ["fit", str(path), "--envelope", "--free", "mu", "--m", "0.5", "--k", "20",
            "--no-compare", "--out"]
    outputs = {}
    for worker in ("1", "0"):
        out, mark = tmp_path / f"out{worker}", tmp_path / f"mark{worker}"
        env = {**os.environ, "DAMPAX_FIGURE_PROCESS": worker, "MARK": str(mark),
               "MPLCONFIGDIR": str(tmp_path / "mpl")}
        proc = _python(_CONSOLE, *args, out, env=env)
        assert sorted(p.name for p in out.iterdir()) == ["fit.json", "fit.png"]
        assert mark.exists() == (worker == "1")
        assert "findfont: Font family 'NoSuchFontFamily' not found" in proc.stderr
        outputs[worker] = ((out / "fit.png").read_bytes(),
                           [line for line in proc.stdout.splitlines() if "written:" not in line])
    assert outputs["1"][0][:8] == b"\x89PNG\r\n\x1a\n"
    assert outputs["1"] == outputs["0"]
    out, mark = tmp_path / "closed", tmp_path / "mark-closed"
    code = _CONSOLE.replace('"', "'")
    command = " ".join([sys.executable, "-c", f'"{code}"', *args, str(out), "<&- 2>&-"])
    proc = subprocess.run(["bash", "-c", command], capture_output=True, text=True, timeout=240,
                          env={**os.environ, "MARK": str(mark)})
    assert proc.returncode == 0 and mark.exists()
    assert (out / "fit.png").read_bytes() == outputs["0"][0]


_FAILING = """
import os, sys, types
from dampax_cli import _figures
assert _figures.start() and _figures.running()
missing = sys.argv[1]
try:
    _figures.draw(types.SimpleNamespace(kind="trace"), missing)
except _figures.Unavailable as err:
    print("1:", err)
print("exists:", os.path.exists(missing), "running:", _figures.running())
try:
    _figures.draw(types.SimpleNamespace(), missing)
except _figures.Unavailable as err:
    print("2:", err)
"""


def test_a_worker_that_cannot_draw_says_why_and_creates_nothing(tmp_path):
    """A figure the worker cannot draw (here: data without its fields, into a file the command
    has removed) is :class:`_figures.Unavailable` with the reason, the file is not created,
    and the worker is gone: the next figure is the command's own."""
    missing = tmp_path / ".fit.removed.part.png"
    lines = _python(_FAILING, missing).stdout.splitlines()
    assert lines[0].startswith("1: the figure process could not draw: AttributeError")
    assert lines[1] == "exists: False running: False"
    assert lines[2] == "2: there is no figure process"
    assert not missing.exists()


def test_which_commands_have_a_worker(monkeypatch):
    """A fit of one trace or table of maxima (or the example) has a worker; a joint fit of
    several files, another command, or ``DAMPAX_FIGURE_PROCESS=0`` has none."""
    def args(command="fit", path=None):
        return argparse.Namespace(command=command, path=path)

    monkeypatch.delenv("DAMPAX_FIGURE_PROCESS", raising=False)
    assert _figures.wanted(args(path=[])) and _figures.wanted(args(path=["a.csv"]))
    assert not _figures.wanted(args(path=["a.csv", "b.csv"]))
    assert not _figures.wanted(args("errormap"))
    monkeypatch.setenv("DAMPAX_FIGURE_PROCESS", "0")
    assert not _figures.wanted(args(path=["a.csv"]))
    # in a process that has loaded numpy (this one) no worker is forked
    assert not _figures.start() and not _figures.running()
    with pytest.raises(_figures.Unavailable, match="there is no figure process"):
        _figures.draw(None, "unused.png")
