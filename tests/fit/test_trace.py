"""dampax.load_trace: every format the measured files come in, and clear errors for bad ones."""

import dataclasses
import math
from pathlib import Path

import jax
import numpy as np
import pytest

from dampax._trace import Trace, load_trace

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
needs_data = pytest.mark.skipif(
    not DATA.is_dir(), reason=f"measured data not found at {DATA} (the shared data folder "
                              "beside the checkout); skipping the real-file reader checks")

T = np.round(np.arange(8) * 0.01, 4)
X = np.round(0.4 + 0.05 * np.cos(8.6 * T), 6)


def _write(tmp_path, text, name="trace.txt", newline="\n"):
    path = tmp_path / name
    path.write_bytes(text.replace("\n", newline).encode())
    return path


def _rows(sep, t=T, x=X, extra=""):
    return "".join(f"{a:g}{sep}{b:g}{extra}\n" for a, b in zip(t, x, strict=True))


@pytest.mark.parametrize("sep, header, newline", [
    (";", "time;position\n", "\r\n"),
    (",", "time,position\n", "\n"),
    ("\t", "time\tposition\n", "\r\n"),
    (" ", "time position\n", "\n"),
    ("   ", "", "\n"),
    (", ", "t, x\n", "\r\n"),
    (";", "", "\r\n"),
])
def test_separators_headers_line_ends(tmp_path, sep, header, newline):
    path = _write(tmp_path, header + _rows(sep), newline=newline)
    tr = load_trace(path)
    np.testing.assert_array_equal(tr.t, T)
    np.testing.assert_array_equal(tr.x, X)
    assert tr.n_dropped == 0 and tr.n_rows == len(T)
    assert tr.source == str(path)
    if header:
        assert tr.time_column == header.replace(sep.strip() or " ", " ").split()[0].strip(",;")


def test_comments_separator_lines_trailing_empty_fields(tmp_path):
    text = ("# exported by the logger\n"
            "Timestamp; time; position; velocity; acceleration\n"
            "-------------------------------------\n"
            "\n"
            + "".join(f"12:00:{i:02d}.000; {a:g}; {b:g}; 0.1; -0.2\n" for i, (a, b)
                      in enumerate(zip(T[:-2], X[:-2], strict=True)))
            + "# a comment in the middle\n"
            + f"12:00:06.000; {T[-2]:g}; {X[-2]:g}; 0.1;\n"     # empty trailing field
            + f"12:00:07.000; {T[-1]:g}; {X[-1]:g};;\n")      # two empty trailing fields
    path = _write(tmp_path, text, newline="\r\n")
    tr = load_trace(path, time="time", position="position")
    np.testing.assert_array_equal(tr.t, T)
    np.testing.assert_array_equal(tr.x, X)
    assert tr.n_dropped == 0
    # the same columns by index; a clock-time column reads as seconds
    tr2 = load_trace(path, time=0, position=2)
    np.testing.assert_allclose(tr2.t - tr2.t[0], np.arange(len(T)))
    np.testing.assert_array_equal(tr2.x, X)
    # an empty field in the chosen column drops the row (and counts it)
    tr3 = load_trace(path, time=1, position=3)
    assert len(tr3) == len(T) - 1 and tr3.n_dropped == 1
    with pytest.warns(UserWarning, match="2 of 8 data rows have no number"):  # (> 1 %)
        tr4 = load_trace(path, time=1, position="acceleration")
    assert len(tr4) == len(T) - 2 and tr4.n_dropped == 2


def test_column_by_name_ignores_case_and_units(tmp_path):
    text = "Time_Elapsed(s), Angle(deg), other\n" + _rows(", ", extra=", 7")
    path = _write(tmp_path, text)
    for name in ("Angle(deg)", "angle", "ANGLE (deg)"):
        tr = load_trace(path, time="time_elapsed", position=name, scale=math.pi / 180)
        np.testing.assert_allclose(tr.x, X * math.pi / 180)
        assert tr.position_column == "Angle(deg)"
    with pytest.raises(ValueError, match="no position column named 'speed'.*Angle"):
        load_trace(path, position="speed")
    with pytest.raises(ValueError, match="out of range"):
        load_trace(path, position=5)


def test_negative_index_and_decimal_comma(tmp_path):
    text = "t;a;x\n" + "".join(f"{a:g};1;{b:g}\n".replace(".", ",")
                               for a, b in zip(T, X, strict=True))
    tr = load_trace(_write(tmp_path, text), position=-1)
    np.testing.assert_allclose(tr.x, X)
    np.testing.assert_allclose(tr.t, T)


def test_buffered_time_rate_auto(tmp_path):
    # 260 samples/s, but the elapsed-time column advances in buffers of 26 rows
    n, rate = 520, 260.0
    i = np.arange(n)
    stamps = 100.0 + np.floor(i / 26) * 26 / rate
    stamps[-1] = 100.0 + (n - 1) / rate  # the last buffer stamp closes the record
    x = np.sin(2 * np.pi * 4 * i / rate)
    text = "Timestamp, Time_Elapsed(s), Angle(deg)\n" + "-" * 30 + "\n" + "".join(
        f"16:15:58.125, {s:.6f}, {v:.5f}\n" for s, v in zip(stamps, x, strict=True))
    path = _write(tmp_path, text)
    tr = load_trace(path, time="Time_Elapsed(s)", position="Angle(deg)", rate="auto")
    assert tr.rate == pytest.approx(rate, rel=1e-6)
    np.testing.assert_allclose(tr.t, 100.0 + i / rate, atol=1e-9)
    assert np.all(np.diff(tr.t) > 0)
    # without rate the buffered stamps come back as they are (repeated values)
    raw = load_trace(path, time=1, position=2)
    assert len(np.unique(raw.t)) < n // 10
    # a fixed rate: time = first stamp + index / rate
    tr2 = load_trace(path, time=1, position=2, rate=130.0)
    np.testing.assert_allclose(tr2.t, 100.0 + i / 130.0)


def test_rate_without_time_column(tmp_path):
    path = _write(tmp_path, "".join(f"{v:g}\n" for v in X))
    tr = load_trace(path, rate=100.0)
    np.testing.assert_allclose(tr.t, np.arange(len(X)) / 100.0)
    np.testing.assert_array_equal(tr.x, X)
    assert tr.time_column == "sample index"


def test_text_in_numeric_columns_dropped_and_counted(tmp_path):
    lines = _rows(";").splitlines()
    lines[2] = "0.02;ERROR"
    lines[5] = "n/a;0.41"
    lines[6] = "0.06;nan"
    path = _write(tmp_path, "time;position\n" + "\n".join(lines) + "\n")
    with pytest.warns(UserWarning, match="3 of 8 data rows have no number"):
        tr = load_trace(path)
    assert len(tr) == len(T) - 3 and tr.n_dropped == 3 and tr.n_rows == len(T)
    keep = np.ones(len(T), bool)
    keep[[2, 5, 6]] = False
    np.testing.assert_array_equal(tr.x, X[keep])
    # time rebuilt from the row index keeps the dropped rows' slots
    with pytest.warns(UserWarning, match="2 of 8 data rows"):
        tr2 = load_trace(path, rate=100.0)
    np.testing.assert_allclose(tr2.t[2], 0.03)


def test_bad_files_give_clear_errors(tmp_path):
    empty = _write(tmp_path, "", "empty.csv")
    with pytest.raises(ValueError, match=r"empty\.csv: no data"):
        load_trace(empty)
    comments = _write(tmp_path, "# nothing\n\n-----\n", "comments.csv")
    with pytest.raises(ValueError, match=r"comments\.csv: no data"):
        load_trace(comments)
    one = _write(tmp_path, "position\n0.1\n0.2\n0.3\n", "one.csv")
    with pytest.raises(ValueError, match=r"one\.csv: only one column.*rate"):
        load_trace(one)
    text = _write(tmp_path, "time;position\na;b\nc;d\n", "text.csv")
    with pytest.raises(ValueError, match=r"text\.csv: no usable rows: none of the 2 data rows"):
        load_trace(text)
    with pytest.raises(ValueError, match="no header line"):
        load_trace(_write(tmp_path, _rows(";"), "nohead.csv"), position="x")
    with pytest.raises(ValueError, match="rate must be"):
        load_trace(_write(tmp_path, _rows(";"), "r.csv"), rate=-1)
    with pytest.raises(OSError):
        load_trace(tmp_path / "missing.csv")


def test_trace_is_a_pytree():
    tr = Trace(t=np.arange(3.0), x=np.ones(3), n_dropped=2, source="s")
    leaves, treedef = jax.tree_util.tree_flatten(tr)
    assert len(leaves) == 2
    back = jax.tree_util.tree_unflatten(treedef, [2 * a for a in leaves])
    assert back.n_dropped == 2 and back.source == "s"
    np.testing.assert_array_equal(back.t, 2 * np.arange(3.0))
    with pytest.raises(dataclasses.FrozenInstanceError):
        tr.t = None  # immutable


@needs_data
def test_real_files():
    spring = load_trace(DATA / "spring_mass_airdrag" / "run1.csv")
    assert len(spring) > 11000 and spring.n_dropped == 0
    assert spring.time_column == "time" and spring.position_column == "position"
    assert np.all(np.diff(spring.t) > 0) and 0.3 < np.median(spring.x) < 0.5
    torsion = load_trace(DATA / "torsion_pendulum_friction" / "release_60deg.txt",
                         time="Time_Elapsed(s)", position="Angle(deg)", rate="auto")
    assert 255 < torsion.rate < 265 and np.all(np.diff(torsion.t) > 0)
    peaks = load_trace(DATA / "pendulum_airdrag" / "AAAtopPts.txt")
    assert len(peaks) == 155 and peaks.position_column == "amplitude"
