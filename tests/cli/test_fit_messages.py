"""What ``dampax fit`` and ``dampax errormap`` tell the experimenter (issue 36, item 5): the
time spent compiling only when this process compiled something (a repeated command that reuses
the cached programs says nothing of it), and the columns read from the file in an error about
the data."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import dampax
from dampax._cli import main

#: the source folder of the dampax under test, for the subprocesses
SRC = str(Path(dampax.__file__).resolve().parents[1])


def _run_twice(args, cache: Path) -> list[str]:
    """The stdout of the command run twice in fresh processes on one (empty) cache folder."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("DAMPAX_CACHE", "JAX_COMPILATION_CACHE_DIR")}
    env.update(DAMPAX_CACHE_DIR=str(cache),
               PYTHONPATH=os.pathsep.join([SRC, *filter(None, [env.get("PYTHONPATH")])]))
    outs = []
    for _ in range(2):
        proc = subprocess.run([sys.executable, "-m", "dampax._cli", *args], env=env,
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        outs.append(proc.stdout)
    return outs


def test_compile_clock_counts_what_this_process_compiles():
    """A new program counts; the same one again (in memory) and one read back from JAX's
    persistent cache (after jax.clear_caches()) do not."""
    import jax
    import jax.numpy as jnp

    from dampax._cache import keep_every_program
    from dampax._cli._common import compile_clock

    salt = float(np.random.default_rng().integers(1, 10**9))  # a program no one compiled

    @jax.jit
    def f(x):
        return jnp.sin(x) * salt + 1.0

    x = jnp.arange(3.0)
    with keep_every_program() as kept:  # written to the session's cache, however quick
        with compile_clock() as first:
            f(x).block_until_ready()
        with compile_clock() as again:
            f(x).block_until_ready()
        jax.clear_caches()
        with compile_clock() as cached:
            f(x).block_until_ready()
    assert first.count >= 1 and first.seconds > 0.0
    assert re.fullmatch(r" \(\d[\d.e-]* s compiling\)", first.text()), first.text()
    assert again.count == 0 and again.text() == ""
    if kept:
        assert cached.count == 0 and cached.text() == ""


def test_errormap_says_compiling_only_when_it_compiled(tmp_path):
    args = ["errormap", "--d0", "0:0.1:2", "--d2", "0", "--phi0", "0", "--models", "matched",
            "--reference", "coulomb_exact", "--periods", "5", "--plots", "none",
            "--no-progress", "--out", str(tmp_path / "maps")]
    cold, warm = _run_twice(args, tmp_path / "cache")
    timing = r"  2 points in [\d.]+ s"
    assert re.search(timing + r" \([\d.]+ s compiling\); written: ", cold), cold
    assert re.search(timing + "; written: ", warm), warm
    assert "s compiling)" not in warm


def test_fit_says_compiling_only_when_it_compiled(tmp_path):
    t = np.arange(0.0, 3.0, 0.005)
    x = 0.2 * np.exp(-0.3 * t) * np.cos(5.4 * t) + 1e-3 * np.random.default_rng(1).normal(
        size=t.size)
    path = tmp_path / "decay.txt"
    path.write_text("time position\n" + "".join(f"{a:.3f} {b:.6f}\n" for a, b in zip(t, x,
                                                                                  strict=True)))
    args = ["fit", "--model", "ansatz",
            str(path), "--free", "b", "--no-compare", "--starts", "1", "--out",
            str(tmp_path / "out")]
    cold, warm = _run_twice(args, tmp_path / "cache")
    assert re.search(r"\n  [\d.]+ s \([\d.]+ s compiling\); written: ", cold), cold
    assert re.search(r"\n  [\d.]+ s; written: ", warm), warm
    assert "s compiling)" not in warm


def test_fit_error_about_the_data_names_the_columns(tmp_path, capsys):
    """A torsion export read without --rate: its buffered time stamps are refused, and the
    message says which columns of which file were read (chosen by the header's meaning)."""
    n = 520
    i = np.arange(n)
    stamps = 100.0 + np.floor(i / 26) * 0.1
    angle = 40.0 * np.exp(-0.2 * i / 260) * np.cos(2 * np.pi * 4 * i / 260)
    path = tmp_path / "torsion.txt"
    path.write_text("Timestamp, Time_Elapsed(s), Angle(deg)\n" + "-" * 30 + "\n" + "".join(
        f"16:15:58.{k % 1000:03d}, {s:.3f}, {a:.2f}\n" for k, s, a in zip(i, stamps, angle,
                                                                           strict=True)))
    assert main(["fit", "--model", "ansatz", str(path), "--free", "mu,b", "--no-compare", "--out",
                 str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dampax: error: t: ") and err.count("\n") == 1
    assert ("(data: time from column 'Time_Elapsed(s)', position from column 'Angle(deg)' of "
            "torsion.txt; choose other columns with --time and --position)") in err
    assert "load_trace" not in err  # the command's flags, not the library's arguments


def test_fit_envelope_file_gives_coulomb_friction_from_its_exact_decrement(tmp_path, capsys):
    """``dampax fit FILE --envelope`` (a table of maxima, the command's envelope path end to
    end): the maxima of a Coulomb decay fall by exactly 4 mu g / w0^2 per period (the
    stick-slip decrement of the exact motion), the straight line the envelope E' = -d0 holds;
    the command's mu, in its report and fit.json, is that decrement's to 1e-6, its ranking
    puts mu alone first, and fit.png is drawn. Nine maxima are enough (a trace fit's floor of
    10 samples refused them before)."""
    import json
    import math

    m, k, mu, g = 0.5, 20.0, 0.01, 9.81
    w0 = math.sqrt(k / m)
    n = np.arange(9)
    t = 0.3 + n * 2.0 * math.pi / w0
    amp = 0.1 - n * 4.0 * mu * g / w0**2
    path = tmp_path / "maxima.csv"
    np.savetxt(path, np.column_stack([t, amp]), fmt="%.17g", delimiter=",",
               header="t,amplitude", comments="")
    out = tmp_path / "out"
    status = main(["fit", str(path), "--envelope", "--free", "mu", "--m", str(m), "--k",
                   str(k), "--out", str(out)])
    text = capsys.readouterr().out
    assert status == 0, text
    summary = json.loads((out / "fit.json").read_text())
    assert summary["fit"]["params"]["mu"] == pytest.approx(mu, rel=1e-6), summary["fit"]
    assert summary["ranking"]["supported"] == ["mu"], summary["ranking"]
    # a mass without k: w0 from the maxima's spacing (the placeholder k = m gave w0 = 1)
    assert main(["fit", str(path), "--envelope", "--free", "mu", "--m", str(m), "--no-compare",
                 "--out", str(out)]) == 0
    capsys.readouterr()
    fitted = json.loads((out / "fit.json").read_text())["fit"]["params"]["mu"]
    assert fitted == pytest.approx(mu, rel=1e-6)
    assert "Model ranking by BIC" in text and (out / "fit.png").stat().st_size > 0
    # a short table is refused by what the envelope needs (A and mu: 3 maxima), not by a
    # trace fit's 10 samples
    with pytest.raises(ValueError, match="envelope fit of 2 parameters needs at least 3 "
                                         "finite maxima, got 2"):
        dampax.fit_envelope(t[:2], amp[:2], free=("mu",))
    # four maxima: the asked fit is made, and the ranking, whose largest candidate (A, mu, b
    # and D) needs five, ranks the others and names that one (it stopped the command before)
    np.savetxt(path, np.column_stack([t[:4], amp[:4]]), fmt="%.17g", delimiter=",",
               header="t,amplitude", comments="")
    status = main(["fit", str(path), "--envelope", "--free", "mu", "--m", str(m), "--k",
                   str(k), "--out", str(out)])
    text = capsys.readouterr().out
    assert status == 0, text
    ranking = json.loads((out / "fit.json").read_text())["ranking"]
    assert ranking["skipped"] == {"mu,b,D": "an envelope fit of 4 parameters needs at least 5 "
                                            "finite maxima, got 4"}, ranking
    assert len(ranking["ranking"]) == 6 and "left out (not fitted): mu,b,D: an envelope" in text


@pytest.mark.parametrize("args, words", [
    (["--example", "--envelope"], "--envelope: not used by --example"),
    (["--example", "--m", "1", "--scale", "2"], "--m, --scale: not used by --example"),
    (["PATH", "--envelope", "--start", "3", "--seed", "2"],
     "--start, --seed: not used by --envelope"),
    (["PATH", "--omega0", "3"], "--omega0: not used by a trace fit"),
    (["PATH", "--g", "1.62"], "--g needs --m"),
    (["PATH", "PATH", "--mu-s", "0.5"], "--mu-s: static friction is not supported by a joint"),
    (["PATH", "PATH", "--level", "2"], "--level must be in"),
])
def test_flags_a_fit_would_ignore_are_refused(tmp_path, capsys, args, words):
    """Flags that a kind of fit does not use end the command with status 2 and their names,
    before any work (they were ignored: the example's --m, --envelope's window, a joint fit's
    --mu-s; --g without --m reported a per-unit-mass fit in kg/s)."""
    path = tmp_path / "x.csv"
    path.write_text("t,x\n" + "".join(f"{i * 0.01},{np.cos(i * 0.1)}\n" for i in range(50)))
    argv = ["fit", *[str(path) if a == "PATH" else a for a in args], "--out",
            str(tmp_path / "out")]
    assert main(argv) == 2
    assert words in capsys.readouterr().err
