"""dampax.load_trace chooses the time and position columns by what the header's names mean
(issue 36, item 5): a torsion export ``Timestamp, Time_Elapsed(s), Angle(deg)`` reads the angle
against the elapsed time (it read the elapsed time as the position), the caller's choice wins,
and a header that does not settle it is an error naming the columns."""

import math
from pathlib import Path

import numpy as np
import pytest

from dampax._trace import load_trace

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"

# the columns' numbers: the time, the position, and decoys (a clock, a velocity, an error)
N = 12
TIME = np.round(np.arange(N) * 0.01 + 5.0, 4)
POS = np.round(0.4 + 0.05 * np.cos(8.6 * TIME), 6)
VALUES = {
    "time": TIME,
    "pos": POS,
    "vel": np.round(-0.43 * np.sin(8.6 * TIME), 6),
    "err": np.full(N, 0.008),
    "clock": np.round(58558.125 + np.arange(N) * 0.004, 3),
    "other": np.round(np.linspace(1.0, 2.0, N), 6),
}


def _clock(seconds: float) -> str:
    h, rest = divmod(seconds, 3600.0)
    m, s = divmod(rest, 60.0)
    return f"{int(h):02d}:{int(m):02d}:{s:06.3f}"


def _write(tmp_path, header: list[str], kinds: list[str], sep: str = ",",
           name: str = "trace.csv"):
    """A file with that header and columns of ``VALUES`` (a clock column as H:MM:SS.fff)."""
    rows = []
    for i in range(N):
        fields = [_clock(VALUES[k][i]) if k == "clock" else f"{VALUES[k][i]:g}" for k in kinds]
        rows.append(sep.join(fields))
    path = tmp_path / name
    path.write_text(sep.join(header) + "\n" + "\n".join(rows) + "\n")
    return path


@pytest.mark.parametrize("header, kinds, sep", [
    # the torsion pendulum's export: a clock, the elapsed time, the angle
    (["Timestamp", " Time_Elapsed(s)", " Angle(deg)"], ["clock", "time", "pos"], ","),
    # the position first, then the time
    (["x [m]", "t [s]"], ["pos", "time"], "\t"),
    # a velocity and an acceleration around them, in a logger's order
    (["velocity (m/s)", "time", "acceleration (m/s^2)", "position"],
     ["vel", "time", "vel", "pos"], ";"),
    # error columns beside the value (the video-tracked pendulum's layout)
    (["t", "amplitude", "xerr", "yerr"], ["time", "pos", "err", "err"], " "),
    # units only, DIN style, and a counter column
    (["index", "Zeit / s", "Weg / mm"], ["other", "time", "pos"], ";"),
    # camel case and an angle in radians
    (["SampleNo", "ElapsedTime", "theta (rad)"], ["other", "time", "pos"], ","),
    # a clock stamp and a displacement: the clock is the only time
    (["Timestamp", "displacement (cm)"], ["clock", "pos"], ","),
    # a bare unit for the position, a name for the time
    (["time (s)", "Sensor 1 (mm)", "omega (rad/s)"], ["time", "pos", "vel"], ","),
])
def test_columns_by_meaning(tmp_path, header, kinds, sep):
    path = _write(tmp_path, header, kinds, sep)
    tr = load_trace(path)
    want_t = kinds.index("time") if "time" in kinds else kinds.index("clock")
    want_x = kinds.index("pos")
    assert tr.time_column == header[want_t].strip()
    assert tr.position_column == header[want_x].strip()
    np.testing.assert_array_equal(tr.x, POS)
    if kinds[want_t] == "clock":
        np.testing.assert_allclose(tr.t, VALUES["clock"], atol=1e-9)
    else:
        np.testing.assert_array_equal(tr.t, TIME)
    assert repr(header[want_x].strip()) in repr(tr)  # the repr names the columns
    assert f"position from column {header[want_x].strip()!r}" in tr.describe_columns()


def test_caller_choice_wins(tmp_path):
    path = _write(tmp_path, ["Timestamp", "Time_Elapsed(s)", "Angle(deg)"],
                  ["clock", "time", "pos"])
    # the position chosen, the time by meaning from the rest
    tr = load_trace(path, position="Time_Elapsed(s)")
    assert tr.position_column == "Time_Elapsed(s)" and tr.time_column == "Timestamp"
    np.testing.assert_array_equal(tr.x, TIME)
    # the time chosen, the position by meaning
    tr = load_trace(path, time=0)
    assert tr.time_column == "Timestamp" and tr.position_column == "Angle(deg)"
    # both, by index (as before)
    tr = load_trace(path, time=1, position=2, scale=math.pi / 180)
    np.testing.assert_allclose(tr.x, POS * math.pi / 180)
    # rate given and no time: the position still by meaning, time from the index
    tr = load_trace(path, rate=100.0)
    assert tr.position_column == "Angle(deg)" and tr.time_column == "sample index"
    np.testing.assert_allclose(tr.t, np.arange(N) / 100.0)
    # rate="auto" reads the time column it chose
    tr = load_trace(path, rate="auto")
    assert tr.time_column == "Time_Elapsed(s)"
    assert tr.rate == pytest.approx((N - 1) / (TIME[-1] - TIME[0]))


def test_names_that_say_nothing(tmp_path):
    # two columns: the first is the time, the second the position (as without a header)
    tr = load_trace(_write(tmp_path, ["ch1", "ch2"], ["time", "pos"]))
    assert (tr.time_column, tr.position_column) == ("ch1", "ch2")
    # a trailing separator (an empty name, an empty field) is no candidate
    path = tmp_path / "trailing.csv"
    path.write_text("ch1;ch2;\n" + "".join(f"{a:g};{b:g};\n" for a, b in zip(TIME, POS,
                                                                              strict=True)))
    tr = load_trace(path)
    assert (tr.time_column, tr.position_column) == ("ch1", "ch2")
    np.testing.assert_array_equal(tr.x, POS)
    # a named time and one column that says nothing: that one is the position
    tr = load_trace(_write(tmp_path, ["time", "Channel A", "speed"], ["time", "pos", "vel"]))
    assert tr.position_column == "Channel A"
    np.testing.assert_array_equal(tr.x, POS)
    # no header at all: the first and second columns
    path = tmp_path / "nohead.txt"
    path.write_text("".join(f"{a:g} {b:g} {c:g}\n" for a, b, c in
                            zip(TIME, POS, VALUES["vel"], strict=True)))
    tr = load_trace(path)
    np.testing.assert_array_equal(tr.t, TIME)
    np.testing.assert_array_equal(tr.x, POS)


@pytest.mark.parametrize("header, kinds, what, names", [
    (["time", "x (m)", "y (m)"], ["time", "pos", "other"], "position", ["x (m)", "y (m)"]),
    (["t", "time", "x"], ["time", "other", "pos"], "time", ["t", "time"]),
    (["ch1", "ch2", "ch3"], ["time", "pos", "other"], "position", ["ch2", "ch3"]),
    (["time", "velocity", "acceleration"], ["time", "vel", "vel"], "position", []),
])
def test_ambiguous_headers_name_the_columns(tmp_path, header, kinds, what, names):
    path = _write(tmp_path, header, kinds, name="amb.csv")
    with pytest.raises(ValueError) as info:
        load_trace(path)
    text = str(info.value)
    assert text.startswith(f"{path}: which column is the {what}?"), text
    for name in names:
        assert repr(name) in text
    assert "the header has " + ", ".join(repr(h) for h in header) in text
    assert "load_trace(time=..., position=...)" in text and "--position" in text
    # the caller settles it
    tr = load_trace(path, time=0, position=1)
    np.testing.assert_array_equal(tr.t, TIME)


def test_no_usable_rows_names_the_columns(tmp_path):
    path = tmp_path / "text.csv"
    path.write_text("Time_Elapsed(s), Angle(deg)\n1.0, n/a\n2.0, n/a\n")
    with pytest.raises(ValueError, match=r"text\.csv: no usable rows: .* the time column "
                                         r"'Time_Elapsed\(s\)' and the position column "
                                         r"'Angle\(deg\)'"):
        load_trace(path)


@pytest.mark.skipif(not DATA.is_dir(), reason=f"measured data not found at {DATA} (the "
                    "shared data folder beside the checkout); skipping the real-file check")
def test_shared_torsion_file_reads_the_angle():
    """The torsion release's angle, not its elapsed time, with no column named by the caller;
    with rate="auto" the same columns as named by hand."""
    path = DATA / "torsion_pendulum_friction" / "release_100deg.txt"
    tr = load_trace(path)
    assert (tr.time_column, tr.position_column) == ("Time_Elapsed(s)", "Angle(deg)")
    assert np.max(np.abs(tr.x)) <= 180.0 and np.ptp(tr.x) > 100.0  # degrees, swinging
    # the elapsed time, read as the position before, is monotone: the angle swings
    assert np.sum(np.diff(np.sign(tr.x - np.median(tr.x))) != 0) > 20
    auto = load_trace(path, rate="auto")
    named = load_trace(path, time="Time_Elapsed(s)", position="Angle(deg)", rate="auto")
    np.testing.assert_array_equal(auto.t, named.t)
    np.testing.assert_array_equal(auto.x, named.x)
    assert 255 < auto.rate < 265
    spring = load_trace(DATA / "spring_mass_airdrag" / "run1.csv")
    assert (spring.time_column, spring.position_column) == ("time", "position")


@pytest.mark.parametrize("unit, factor", [("ms", 1e-3), ("us", 1e-6), ("min", 60.0),
                                          ("s", 1.0)])
def test_a_time_column_in_other_units_is_read_in_seconds(tmp_path, unit, factor):
    """A time column headed in ms, us or min is converted to seconds (it was read as seconds:
    a fit of a trace timed in ms gave w0 1000 times too small, called a success)."""
    header = [f"time({unit})", "x(m)"]
    path = tmp_path / "t.csv"
    path.write_text(",".join(header) + "\n" + "".join(
        f"{float(t) / factor!r},{float(x)!r}\n" for t, x in zip(TIME, POS, strict=True)))
    trace = load_trace(path)
    np.testing.assert_allclose(trace.t, TIME, rtol=1e-12)
    assert trace.time_factor == factor
    assert ("to seconds" in trace.describe_columns()) == (factor != 1.0)


def test_scaled_positions_are_not_named_by_the_columns_unit(tmp_path):
    """load_trace(scale=...) converts the positions; the fit's unit is then one of 1/scale
    column units, not the column's unit (a trace in degrees scaled to radians was reported in
    degrees)."""
    from dampax._fit._problem import units_of

    path = _write(tmp_path, ["t(s)", "Angle(deg)"], ["time", "pos"])
    assert units_of(load_trace(path), None) == "deg"
    scaled = load_trace(path, scale=math.pi / 180.0)
    np.testing.assert_allclose(scaled.x, np.radians(POS), rtol=1e-12)
    assert units_of(scaled, None) == "(57.2958 deg)" and units_of(scaled, "rad") == "rad"


MINUS = "\u2212"
PAIRS = list(zip(TIME.tolist(), POS.tolist(), strict=True))


@pytest.mark.parametrize("name, text, time_factor, unit", [
    ("aligned", "Time [s]   Angle [deg]   Velocity [deg/s]\n{rows_ws3}", 1.0, "deg"),
    ("slash", "t / s,x / mm\n{rows_csv}", 1.0, "mm"),
    ("quoted", '"t (s)","x (mm)"\n{rows_csv}', 1.0, "mm"),
    ("units_row", "t,x\nms,mm\n{rows_ms}", 1e-3, "mm"),
    ("greek_mu", "Time (\u03bcs),x (mm)\n{rows_us}", 1e-6, "mm"),
    ("minus", "t;x\n{rows_minus}", 1.0, "m"),
    ("suffix", "time_ms,x_mm\n{rows_ms}", 1e-3, "mm"),
    ("savetxt", "# t x_mm\n{rows_ws}", 1.0, "mm"),
    ("comment_header", "# logger v2, run 7\n# time [ms]\tposition [mm]\n{rows_ms_tab}", 1e-3,
     "mm"),
])
def test_lab_files_read_as_written(tmp_path, name, text, time_factor, unit):
    """Files as lab software writes them read the numbers written, in seconds, with the
    position unit the header names (each was misread without a word: an aligned header
    with spaces in its names read the velocity as the angle; "x / mm" and '"x (mm)"' were
    reported in metres; a units row was dropped and ms read as s; "\u03bcs" (Greek mu) was
    seconds; U+2212 minus signs dropped every negative sample; "time_ms" was read in seconds;
    a header in the last comment line, as numpy.savetxt writes it, was skipped with its
    units)."""
    from dampax._fit._problem import units_of

    rows = {
        "rows_ws3": "".join(f"{t:.4f}   {x:.6f}   {-8 * x:.6f}\n" for t, x in PAIRS),
        "rows_csv": "".join(f"{t!r},{x!r}\n" for t, x in PAIRS),
        "rows_ms": "".join(f"{t * 1e3!r},{x!r}\n" for t, x in PAIRS),
        "rows_ws": "".join(f"{t!r} {x!r}\n" for t, x in PAIRS),
        "rows_ms_tab": "".join(f"{t * 1e3!r}\t{x!r}\n" for t, x in PAIRS),
        "rows_us": "".join(f"{t * 1e6!r},{x!r}\n" for t, x in PAIRS),
        "rows_minus": "".join(f"{t!r};{-x!r}\n".replace("-", MINUS).replace(".", ",")
                              for t, x in PAIRS),
    }
    path = tmp_path / f"{name}.txt"
    path.write_text(text.format(**rows), encoding="utf-8")
    trace = load_trace(path)
    want_x = -POS if name == "minus" else POS
    np.testing.assert_allclose(trace.t, TIME, rtol=1e-9)
    np.testing.assert_allclose(trace.x, want_x, rtol=1e-9)
    assert trace.time_factor == time_factor and trace.n_dropped == 0
    assert units_of(trace, None) == unit


@pytest.mark.parametrize("comment", ["# sample data", "# x y z", "# run 1 of 3", "% a b"])
def test_a_comment_that_is_not_the_header_stays_a_comment(tmp_path, comment):
    """A comment before headerless data that does not name its columns (other words, another
    count of names, numbers) is skipped as before: the first column is the time, the second
    the position."""
    path = tmp_path / "c.txt"
    path.write_text(comment + "\n" + "".join(f"{t!r} {x!r}\n" for t, x in PAIRS))
    trace = load_trace(path)
    np.testing.assert_allclose(trace.t, TIME, rtol=1e-12)
    np.testing.assert_allclose(trace.x, POS, rtol=1e-12)
    assert (trace.time_column, trace.position_column) == ("#0", "#1")


def test_a_windows_file_is_read_in_its_code_page(tmp_path):
    """A cp1252 export (not UTF-8): its "\u00b0" and "\u00b5s" headers are read, not U+FFFD
    (the unit came out as "\ufffd", and \u00b5s times as seconds)."""
    from dampax._fit._problem import units_of

    path = tmp_path / "latin.csv"
    path.write_bytes(("Zeit (\u00b5s);Winkel (\u00b0)\n" + "".join(
        f"{t * 1e6!r};{x!r}\n".replace(".", ",") for t, x in PAIRS)
    ).encode("cp1252"))
    trace = load_trace(path)
    np.testing.assert_allclose(trace.t, TIME, rtol=1e-9)
    assert units_of(trace, None) == "\u00b0"


def _rows(fmt, scale_t=1.0, scale_x=1.0):
    return "".join(fmt(t * scale_t, x * scale_x) for t, x in PAIRS)


def _de(value: float, digits: int) -> str:
    return f"{value:.{digits}f}".replace(".", ",")


#: files as instruments and spreadsheets write them (a helper's audit of the loader found each
#: misread without a word, or refused): (name, content, time factor, position unit)
EXPORTS = [
    ("excel_us_thousands", "Time (ms),Position (mm)\n" + _rows(
        lambda t, x: f'"{t:,.1f}",{x:.6f}\n', 1e3, 1e3), 1e-3, "mm"),
    ("quoted_decimal_commas", "temps (s),position (m)\n" + _rows(
        lambda t, x: f'"{_de(t, 4)}","{_de(x, 6)}"\n'), 1.0, "m"),
    ("arduino_millis", "millis,angle\n" + _rows(lambda t, x: f"{t:.0f},{x:.6f}\n", 1e3), 1e-3,
     "m"),
    ("pasco_runs", "Time (ms) Run #1,Position (mm) Run #1\n" + _rows(
        lambda t, x: f"{t:.1f},{x:.6f}\n", 1e3, 1e3), 1e-3, "mm"),
    ("gost_units", "Time, ms;Position, mm\n" + _rows(
        lambda t, x: f"{_de(t, 1)};{_de(x, 6)}\n", 1e3, 1e3), 1e-3, "mm"),
    ("pandas_unnamed", ",0,1\n" + "".join(f"{i},{t!r},{x!r}\n" for i, (t, x) in
                                         enumerate(PAIRS)), 1.0, "m"),
    ("excel_de_thousands", "Zeit (ms);Winkel (°)\n" + _rows(
        lambda t, x: f"{t:,.0f}".replace(",", ".") + f";{_de(x, 6)}\n", 1e3), 1e-3, "°"),
    ("tab_us_thousands", "Time (ms)\tPosition (mm)\n" + _rows(
        lambda t, x: f"{t:,.0f}\t{x:.6f}\n", 1e3, 1e3), 1e-3, "mm"),
    ("tracker_title", "mass A\nt,x\n" + _rows(lambda t, x: f"{t!r},{x!r}\n"), 1.0, "m"),
    ("title_above_tabs", "Pendulum experiment\nTime (s)\tVelocity (m/s)\tPosition (m)\n" +
     _rows(lambda t, x: f"{t!r}\t{-8 * x!r}\t{x!r}\n"), 1.0, "m"),
    ("vernier_units_row", "Latest\nTime\tPosition\n(s)\t(mm)\n" + _rows(
        lambda t, x: f"{t!r}\t{x!r}\n", 1.0, 1e3), 1.0, "mm"),
    ("excel_sep_hint", "sep=;\nZeit (s);Weg (mm)\n" + _rows(
        lambda t, x: f"{_de(t, 4)};{_de(x, 6)}\n", 1.0, 1e3), 1.0, "mm"),
    ("fortran_exponents", _rows(lambda t, x: f"{t:.8E}  {x:.8E}\n".replace("E", "D")), 1.0,
     "m"),
    ("clock_decimal_comma", "Uhrzeit;Winkel (°)\n" + _rows(
        lambda t, x: f"00:00:{_de(t, 3).zfill(6)};{_de(x, 6)}\n"), 1.0, "°"),
    ("oscilloscope_settings", "".join(
        (f"Record Length,{N},Points," if i == 0 else ",,,") + f"{t!r},{x!r},\n"
        for i, (t, x) in enumerate(PAIRS)), 1.0, "m"),
    ("labview", "LabVIEW Measurement\nWriter_Version\t2\n***End_of_Header***\n"
     "X_Value\tVelocity\tDisplacement\tComment\n" + _rows(
         lambda t, x: f"{t!r}\t{-8 * x!r}\t{x!r}\n"), 1.0, "m"),
    ("aligned_words", "      Time   Cart Position   Cart Velocity\n" + _rows(
        lambda t, x: f"{t:10.4f}{x:16.6f}{-8 * x:16.6f}\n"), 1.0, "m"),
    ("millivolts", "Time (s),Channel A (mV)\n" + _rows(lambda t, x: f"{t!r},{x!r}\n"), 1.0,
     "mV"),
]


@pytest.mark.parametrize("name, text, time_factor, unit", EXPORTS, ids=[e[0] for e in EXPORTS])
def test_instrument_exports_read_as_written(tmp_path, name, text, time_factor, unit):
    """Every sample read as written, in seconds, with the position unit named: quoted fields
    with the separator or a decimal comma inside, thousands separators (1,000.5 and 1.000),
    Arduino's millis, PASCO's "(ms) Run #1", "Time, ms", pandas' unnamed columns, a title or
    metadata above the header, Excel's "sep=;", Fortran's D exponents, clock times with a
    decimal comma, an oscilloscope's settings in the columns before the data, LabVIEW's
    X_Value, names of several words in aligned columns, and units kept as written (mV)."""
    from dampax._fit._problem import units_of

    path = tmp_path / f"{name}.txt"
    path.write_text(text, encoding="utf-8")
    trace = load_trace(path)
    scale_x = 1e3 if unit == "mm" else 1.0
    np.testing.assert_allclose(trace.t, TIME, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(trace.x, POS * scale_x, rtol=1e-6)
    assert trace.time_factor == time_factor and trace.n_dropped == 0, trace
    assert units_of(trace, None) == unit


def test_utf16_and_iso_timestamps(tmp_path):
    """Excel's "Unicode text" (UTF-16 with its byte-order mark) and ISO date-times (seconds
    of the epoch, so differences are the elapsed time)."""
    path = tmp_path / "u16.txt"
    path.write_text("time (s)\tx (mm)\n" + _rows(lambda t, x: f"{t!r}\t{x!r}\n"),
                    encoding="utf-16")
    trace = load_trace(path)
    np.testing.assert_allclose(trace.t, TIME, rtol=1e-12)
    assert trace.position_column == "x (mm)"
    path = tmp_path / "iso.csv"
    path.write_text("Timestamp,Position (mm)\n" + _rows(
        lambda t, x: f"2024-01-15 10:30:{t:06.3f},{x!r}\n"))
    trace = load_trace(path)
    np.testing.assert_allclose(trace.t - trace.t[0], TIME - TIME[0], atol=1e-6)


def test_rows_that_lost_a_field_are_dropped_not_shifted(tmp_path):
    """A missing time (a leading tab) leaves the row out: the fields after it were read one
    column to the left (the velocity as the position)."""
    lines = [f"{t!r}\t{x!r}\t{-8 * x!r}\n" for t, x in PAIRS]
    lines[3] = f"\t{POS[3]!r}\t{-8 * POS[3]!r}\n"
    path = tmp_path / "tab.txt"
    path.write_text("time\tposition\tvelocity\n" + "".join(lines))
    trace = load_trace(path)
    assert trace.n_dropped == 1 and len(trace) == N - 1
    np.testing.assert_allclose(trace.x, np.delete(POS, 3), rtol=1e-12)


def test_files_that_cannot_be_read_right_say_why(tmp_path):
    """Decimal commas in a comma-separated file (every number split in two), an
    oscilloscope's "X,CH1" (its X is the time: the time column goes back and forth while the
    position rises at every row), a logger's second header with the columns in another order
    (the velocity was read as the position after it) and a time unit the loader does not
    convert are said, not read wrong; numpy scalars are numbers."""
    path = tmp_path / "cc.csv"
    path.write_text("t,x\n" + _rows(lambda t, x: f"{_de(t, 2)},{_de(x, 6)}\n"))
    with pytest.raises(ValueError, match="the header names 2 columns and the rows have 4 "
                                         "fields: numbers with decimal commas"):
        load_trace(path)
    t = np.arange(200) * 0.01
    path.write_text("X,CH1\n" + "".join(f"{a:.2f},{b:.6f}\n" for a, b in
                                        zip(t, np.cos(8.0 * t), strict=True)))
    with pytest.raises(ValueError, match="the time column 'CH1' goes back and forth while the "
                                         "position column 'X' rises at every row"):
        load_trace(path)
    rows = [f"{t!r},{x!r},{-8 * x!r}\n" for t, x in PAIRS]
    path.write_text("time,position,velocity\n" + "".join(rows[:6]) + "time,velocity,position\n"
                    + "".join(f"{t!r},{-8 * x!r},{x!r}\n" for t, x in PAIRS[6:]))
    with pytest.raises(ValueError, match="line 8 repeats the header with its columns in "
                                         "another order"):
        load_trace(path)
    path.write_text("time,position,velocity\n" + "".join(rows[:6]) +
                    "time,position,velocity\n" + "".join(rows[6:]))  # (repeated as it was)
    assert load_trace(path).n_dropped == 1
    path.write_text("Time (1e-3 s),x\n" + _rows(lambda t, x: f"{t!r},{x!r}\n"))
    with pytest.warns(UserWarning, match="is in '1e-3 s', which is not a unit dampax converts"):
        load_trace(path)
    path.write_text("x\n" + _rows(lambda t, x: f"{x!r}\n"))
    assert load_trace(path, rate=np.float32(100.0), scale=np.float64(2.0)).rate == 100.0
    # a PASCO column by its name alone
    path.write_text("Time (s) Run #1,Position (mm) Run #1,Velocity (m/s) Run #1\n" +
                    _rows(lambda t, x: f"{t!r},{x!r},0.0\n"))
    assert load_trace(path, time="Time", position="Position").position_column == \
        "Position (mm) Run #1"
