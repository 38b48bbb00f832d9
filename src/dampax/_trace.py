"""Reading measured free-decay traces from text files: :func:`load_trace` -> :class:`Trace`.

Real exports are messy: comma, semicolon, tab or whitespace separators, a header line or none,
Windows line ends, comment lines, separator lines ("-----"), empty trailing fields, a time
column that a data logger writes in buffers (many rows share one stamp). The reader accepts
all of that, and it never guesses silently: a row whose time or position cannot be read is
dropped and counted (``Trace.n_dropped``), and a file without usable rows is an error that
names the file and the columns.

With a header line the time and position columns are chosen by what their names mean (a
time: "t", "time", "Time_Elapsed(s)", a unit "(s)", before a clock "Timestamp"; a position:
"x", "position", "Angle(deg)", "displacement", a unit "(m)", "(deg)", "(rad)"; never a
velocity, an acceleration or an error column), so ``Timestamp, Time_Elapsed(s), Angle(deg)``
reads the angle against the elapsed time; a choice the names do not settle is a ValueError
naming the columns found. The chosen names are in ``Trace.time_column`` and
``Trace.position_column`` (and in its repr); columns given by the caller always win.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import stat
import warnings

import jax
import numpy as np

__all__ = ["Trace", "load_trace"]

# candidate separators in the order they are tried when delimiter=None; None = whitespace
_DELIMITERS = (";", "\t", ",", None)
_SEPARATOR_LINE = re.compile(r"^[\s\-=_*~+|#.:]{3,}$")
_CLOCK = re.compile(r"^(\d{1,2}):(\d{2}):(\d{2}(?:\.\d*)?)$")
_SAMPLE_LINES = 200  # lines used to choose the delimiter and the header
#: the largest trace file read (64 MiB, about 3 million rows of two columns, a minute or two of
#: parsing): a larger file, a FIFO, a device such as /dev/zero or a folder is refused at once
MAX_TRACE_BYTES = 64 * 1024 * 1024


def read_regular_file(path, *, max_bytes: int = MAX_TRACE_BYTES, what: str = "trace") -> bytes:
    """The bytes of a regular file of at most ``max_bytes``, without blocking.

    The file is opened non-blocking (a FIFO would wait for a writer forever) and checked on
    the open descriptor (no race with a file swapped in between): a FIFO, a device
    (``/dev/zero`` raised MemoryError), a socket or a folder, and a file larger than the limit,
    are refused with a ValueError naming the path.

    Arguments:
        path: the file.
        max_bytes: the size limit.
        what: what the file should hold, for the message.

    Returns:
        The file's contents.

    Raises:
        ValueError: not a regular file, or larger than ``max_bytes``.
        OSError: the file cannot be opened or read.
    """
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0)
    fd = os.open(path, flags)
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            kind = ("a FIFO (named pipe)" if stat.S_ISFIFO(info.st_mode) else
                    "a folder" if stat.S_ISDIR(info.st_mode) else
                    "a device" if stat.S_ISCHR(info.st_mode) or stat.S_ISBLK(info.st_mode)
                    else "a socket" if stat.S_ISSOCK(info.st_mode) else "not a regular file")
            raise ValueError(f"{path}: {kind}, not a {what} file: give a regular file")
        if info.st_size > max_bytes:
            raise ValueError(f"{path}: {info.st_size} bytes, more than the {max_bytes} "
                             f"({max_bytes / 2**20:.3g} MiB) a {what} file may hold here; cut "
                             f"it to the decay of interest (or decimate it)")
    except BaseException:
        os.close(fd)
        raise
    with os.fdopen(fd, "rb") as f:
        data = f.read(max_bytes + 1)
    if len(data) > max_bytes:  # it grew while being read
        raise ValueError(f"{path}: more than the {max_bytes} bytes a {what} file may hold "
                         f"here (it grew while being read)")
    return data


@dataclasses.dataclass(frozen=True)
class Trace:
    """A measured trace x(t): two float arrays and where they came from.

    A pytree (``t`` and ``x`` are its leaves; the rest is static metadata), so it passes
    through ``jax.jit`` and ``jax.tree_util`` functions.

    Attributes:
        t: sample times [s], float64 array.
        x: positions (times ``scale``), float64 array of the same length.
        n_dropped: data rows that could not be read (text or nothing in the time or position
            column, too few fields, non-finite numbers) and were left out.
        source: the file it was read from ("" if built by hand).
        time_column: name (or "#index") of the time column; "sample index" when time was
            rebuilt from ``rate`` alone.
        position_column: name (or "#index") of the position column.
        rate: the sample rate [1/s] used to rebuild time, or None when time was read as is.
        n_rows: data rows in the file (read or dropped).
        scale: the factor applied to the positions (``load_trace(scale=...)``): the position
            column's unit no longer names them (a fit says "1/scale unit" unless told).
        time_factor: seconds per unit of the time column (1e-3 for "time(ms)"): times are
            in seconds.
    """

    t: np.ndarray
    x: np.ndarray
    n_dropped: int = 0
    source: str = ""
    time_column: str = ""
    position_column: str = ""
    rate: float | None = None
    n_rows: int = 0
    scale: float = 1.0
    time_factor: float = 1.0

    def __len__(self) -> int:
        return int(np.shape(self.t)[0])

    def describe_columns(self) -> str:
        """Which columns of which file the trace was read from, for messages about the data.

        Returns:
            E.g. "time from column 'Time_Elapsed(s)' (rebuilt at 260.1 samples/s), position
            from column 'Angle(deg)' of release_60deg.txt"; "" for a trace built by hand
            (no column names).
        """
        if not (self.time_column or self.position_column):
            return ""
        if self.time_column == "sample index" and self.rate is not None:
            time = f"time from the sample index at {self.rate:.6g} samples/s"
        elif self.time_column:
            time = f"time from column {self.time_column!r}"
            if self.time_factor != 1.0:
                time += f" (x {self.time_factor:g} to seconds)"
            if self.rate is not None:
                time += f" (rebuilt at {self.rate:.6g} samples/s)"
        else:
            time = "time as given"
        where = f" of {os.path.basename(self.source)}" if self.source else ""
        return f"{time}, position from column {self.position_column!r}{where}"

    def __repr__(self) -> str:
        n = len(self)
        span = f"{float(self.t[0]):g} .. {float(self.t[-1]):g} s" if n else "empty"
        src = f", source={self.source!r}" if self.source else ""
        rate = f", rate={self.rate:.6g}" if self.rate is not None else ""
        cols = (f", columns t={self.time_column!r} x={self.position_column!r}"
                if self.time_column or self.position_column else "")
        return (f"Trace({n} samples, t = {span}, n_dropped={self.n_dropped}{rate}{cols}"
                f"{src})")


jax.tree_util.register_dataclass(
    Trace, data_fields=["t", "x"],
    meta_fields=["n_dropped", "source", "time_column", "position_column", "rate", "n_rows",
                 "scale", "time_factor"])

#: more unreadable rows than this share of a file's rows (and more than one: a units or
#: title line) are warned about: a column misread (thousands separators, U+2212 minus
#: signs dropped 600 of 800 and 2,497 of 5,000 rows of an audit's files without a word)
DROPPED_SHARE = 0.01

#: seconds per unit of a time column's unit (the others are seconds)
_SECONDS = {"ms": 1e-3, "msec": 1e-3, "us": 1e-6, "µs": 1e-6, "μs": 1e-6, "usec": 1e-6,
            "ns": 1e-9, "min": 60.0}


def _number(field: str, decimal_comma: bool) -> float:
    """A float from one field; clock times H:MM:SS(.fff) become seconds. NaN if unreadable."""
    text = field.strip().strip('"').strip("'").strip().replace("\u2212", "-")  # (U+2212)
    if not text:
        return math.nan
    try:
        return float(text)
    except ValueError:
        pass
    if decimal_comma and text.count(",") == 1 and "." not in text:
        try:
            return float(text.replace(",", "."))
        except ValueError:
            return math.nan
    clock = _CLOCK.match(text)
    if clock:
        h, m, s = clock.groups()
        return 3600.0 * int(h) + 60.0 * int(m) + float(s)
    return math.nan


def _unit_token(field: str) -> str:
    return field.strip().strip('"').strip("'").strip("()[] ")


def _is_units_row(fields: list[str], decimal_comma: bool) -> bool:
    """A line under the header that holds units: no number, short tokens, one of them a unit
    of time or position ("ms,mm", "[s] [deg]")."""
    units = [_unit_token(f) for f in fields if f.strip()]
    return _is_header(fields, decimal_comma) and all(len(u) <= 8 for u in units) and any(
        u.lower() in _TIME_UNITS | _POSITION_UNITS for u in units)


def _with_units_row(names: list[str], units: list[str]) -> list[str]:
    """The header's names with a units row under them ("t,x" then "ms,mm" or "[ms],[mm]")
    written into them ("t (ms)", "x (mm)"), as the loader reads units: it was dropped as an
    unreadable row, and times in ms were read as seconds."""
    out = list(names)
    for i, unit in enumerate(units[:len(out)]):
        unit = _unit_token(unit)
        if unit:
            out[i] = f"{out[i]} ({unit})"
    return out


def _join_units(fields: list[str]) -> list[str]:
    """A whitespace-split header's names with each token that is only a unit, "(s)", "[deg]",
    "/ mm" (two tokens), joined to the name before it: "Time [s]   Angle [deg]" split into
    four tokens, and position "Angle" read the third data column (a velocity)."""
    out: list[str] = []
    i = 0
    while i < len(fields):
        tok = fields[i]
        if out and re.fullmatch(r"[\(\[][^\)\]]*[\)\]]", tok):
            out[-1] += " " + tok
        elif out and tok == "/" and i + 1 < len(fields):
            out[-1] += " / " + fields[i + 1]
            i += 1
        else:
            out.append(tok)
        i += 1
    return out


def _split(line: str, delimiter: str | None) -> list[str]:
    if delimiter is None:
        return line.split()
    return [f.strip() for f in line.split(delimiter)]


def _content_lines(text: str) -> list[tuple[int, str]]:
    """(line number, line) of every line that is not empty, a comment or a separator line."""
    out = []
    for i, raw in enumerate(text.splitlines()):
        line = raw.strip().lstrip("\ufeff")
        if not line or line.startswith("#") or line.startswith("%"):
            continue
        if _SEPARATOR_LINE.match(line) and not any(ch.isdigit() for ch in line):
            continue
        out.append((i + 1, line))
    return out


def _choose_delimiter(lines: list[str]) -> str | None:
    """The separator giving the most lines with >= 2 fields and a consistent field count."""
    best, best_score = None, (-1, -1)
    for delim in _DELIMITERS:
        counts = [len(_split(line, delim)) for line in lines]
        multi = [c for c in counts if c >= 2]
        if not multi:
            continue
        common = max(set(multi), key=multi.count)
        score = (len(multi), multi.count(common))
        if score > best_score:
            best, best_score = delim, score
    return best


def _is_header(fields: list[str], decimal_comma: bool) -> bool:
    """A line is a header when it has text and no field is a number (a data row with text in
    one column is a row to drop, not a header)."""
    filled = [f for f in fields if f.strip()]
    return bool(filled) and all(math.isnan(_number(f, decimal_comma)) for f in filled)


def _comment_header(text: str, first_data_line: int, delim: str | None, decimal_comma: bool,
                    n_fields: int) -> list[str] | None:
    """The names in the last comment line before the data ("# t x" of ``numpy.savetxt``,
    "# time [s]<tab>position [mm]") where it reads as the header of the data's columns: as
    many names as fields, none a number, one at least saying what its column holds (a time or
    a position, by name or unit); else None (a comment, skipped as before). Its units count:
    a time in ms was read as seconds."""
    before = text.splitlines()[:first_data_line - 1]
    comments = [line.strip().lstrip("\ufeff") for line in before]
    comments = [line for line in comments if line.startswith(("#", "%"))]
    if not comments:
        return None
    fields = _split(comments[-1].lstrip("#%").strip(), delim)
    if delim is None:
        fields = _join_units(fields)
    if len(fields) != n_fields or not _is_header(fields, decimal_comma) or \
            not any(_meaning(f)[1] > 0 for f in fields):
        return None
    return fields


def _normalise(name: str) -> str:
    return re.sub(r"\s+", " ", name.strip().strip('"').strip("'")).lower()


# what a header's column names mean (``_meaning``): the words of a name (split at spaces,
# "_", "-", "." and case changes) and its unit, "(s)", "[deg]" or "/ m" after the name
_TIME_WORDS = frozenset({"t", "time", "times", "elapsed", "seconds", "sec", "secs", "zeit",
                         "tempo", "temps", "tiempo", "tijd"})
_CLOCK_WORDS = frozenset({"timestamp", "timestamps", "stamp", "clock", "date", "datetime",
                          "daytime"})
_POSITION_WORDS = frozenset({"x", "y", "z", "pos", "position", "positions", "displacement",
                             "disp", "angle", "theta", "phi", "deflection", "elongation",
                             "extension", "amplitude", "height", "distance", "posizione",
                             "angolo", "spostamento", "auslenkung", "winkel", "weg"})
#: names of other quantities (never the position): derivatives, errors, counters, ...
_OTHER_WORDS = frozenset({"vel", "velocity", "speed", "omega", "acc", "accel", "acceleration",
                          "err", "error", "errors", "xerr", "yerr", "terr", "sigma", "std",
                          "stdev", "uncertainty", "unc", "index", "idx", "sample", "samples",
                          "count", "frame", "force", "energy", "frequency", "freq",
                          "temperature", "voltage", "current", "velocita", "velocità",
                          "accelerazione", "geschwindigkeit", "beschleunigung"})
#: short names of other quantities, when they are the whole name ("v", but "Channel A" says
#: nothing)
_OTHER_ALONE = frozenset({"v", "vx", "vy", "vz", "a", "ax", "ay", "az", "n", "no", "i"})
_TIME_UNITS = frozenset({"s", "sec", "secs", "second", "seconds", "ms", "msec", "us", "µs",
                         "μs", "usec", "ns", "min"})
_POSITION_UNITS = frozenset({"m", "mm", "cm", "um", "µm", "nm", "in", "ft", "deg", "degree",
                             "degrees", "°", "rad", "radian", "radians", "mrad"})


#: units a name may end in after "_" ("time_ms", "x_mm"): not "min", "in", "ft", "s" or "m",
#: which end names of other things there ("x_min", "x_in", "x_s"); a name in seconds or metres
#: reads the same without its unit
_SUFFIX_UNITS = (_TIME_UNITS | _POSITION_UNITS) - {"min", "in", "ft", "s", "m"}


def _name_and_unit(name: str) -> tuple[list[str], str]:
    """(the words of a column name, its unit or ""), lower case: "Time_Elapsed(s)" ->
    (["time", "elapsed"], "s"); "x [m]" -> (["x"], "m"); "t / s" -> (["t"], "s");
    "time_ms" -> (["time"], "ms")."""
    text = name.strip().strip('"').strip("'").strip()
    unit = ""
    found = re.search(r"[\(\[]\s*([^\)\]]*?)\s*[\)\]]\s*$", text)
    if found:
        unit, text = found.group(1), text[:found.start()]
    else:
        slash = re.fullmatch(r"(.*?\S)\s*/\s*([^\s/]+)", text)
        if slash and slash.group(2).lower() in _TIME_UNITS | _POSITION_UNITS:
            text, unit = slash.group(1), slash.group(2)
    text = re.sub(r"([a-z])([A-Z])", r"\1 \2", text)  # TimeElapsed -> Time Elapsed
    words = [w for w in re.split(r"[\s_\-.:,;]+", text.lower()) if w]
    if not unit and len(words) >= 2 and words[-1] in _SUFFIX_UNITS and \
            re.search(r"_" + re.escape(words[-1]) + r"$", text.lower()):
        words, unit = words[:-1], words[-1]  # "time_ms", "x_mm", "angle_deg"
    return words, unit.strip().lower()


def column_unit(name: str) -> str:
    """The unit a column's name gives, as the loader reads it ("x / mm", "Angle(deg)",
    '"x (mm)"' -> "mm", "deg", "mm"), or ""."""
    return _name_and_unit(name)[1]


def _meaning(name: str) -> tuple[str, int]:
    """What a column holds by its header name: ("time", 2) for a time by name ("t", "time",
    "Time_Elapsed(s)", "seconds"), ("time", 1) for a clock ("Timestamp") or a bare time
    unit ("Channel (s)"); ("position", 2) for a position by name ("x", "position", "Angle",
    "displacement"), ("position", 1) for a bare position unit ("Sensor (mm)", "(deg)");
    ("other", 0) for another quantity (a velocity, an acceleration, an error column, a rate
    unit such as "m/s"); ("", 0) for a name that says nothing."""
    words, unit = _name_and_unit(name)
    rate_unit = "/" in unit or "per" in unit.split()
    if words and (set(words) & _OTHER_WORDS or words[-1].endswith(("err", "error"))
                  or (len(words) == 1 and words[0] in _OTHER_ALONE) or rate_unit):
        return "other", 0
    if set(words) & _CLOCK_WORDS:
        return "time", 1
    if set(words) & _TIME_WORDS and unit not in _POSITION_UNITS:
        return "time", 2
    if set(words) & _POSITION_WORDS and unit not in _TIME_UNITS:
        return "position", 2
    if rate_unit:
        return "other", 0
    if unit in _TIME_UNITS:
        return "time", 1
    if unit in _POSITION_UNITS:
        return "position", 1
    return "", 0


def _listed(names, indices) -> str:
    """'a', 'b' and 'c': the header names of some columns, for messages."""
    quoted = [repr(names[i].strip()) for i in indices]
    return quoted[0] if len(quoted) == 1 else ", ".join(quoted[:-1]) + " and " + quoted[-1]


def _choose_columns(names: list[str], i_time: int | None, i_pos: int | None, need_time: bool,
                    path: str) -> tuple[int | None, int]:
    """(time column, position column) of a file with a header, by what the names mean.

    A column the caller chose is kept; the others are chosen among the remaining columns:
    the time as the one column of the best rank of :func:`_meaning` ("t", "time",
    "Time_Elapsed(s)" before a clock "Timestamp"), else the first column whose name says
    nothing; the position as the one position-like column of the best rank ("x", "position",
    "Angle(deg)" before a bare unit "(mm)"), else the one column whose name says nothing.
    Two candidates of the same rank, or none, are a ValueError that names the columns found
    and how to choose.
    """
    meaning = [_meaning(n) for n in names]
    found = ", ".join(repr(n.strip()) for n in names)
    how = ("give the columns by name or index (load_trace(time=..., position=...), "
           "dampax fit --time ... --position ...)")

    def best(kind, exclude):
        ranked = [i for i, (k, _) in enumerate(meaning) if k == kind and i not in exclude]
        top = max((meaning[i][1] for i in ranked), default=0)
        return [i for i in ranked if meaning[i][1] == top]

    def unknown(exclude):  # named columns whose names say nothing (an empty name: no column)
        return [i for i, (k, _) in enumerate(meaning)
                if not k and names[i].strip() and i not in exclude]

    if i_time is None and need_time:
        timed = best("time", {i_pos})
        if len(timed) > 1:
            raise ValueError(f"{path}: which column is the time? {_listed(names, timed)} "
                             f"all look like times (the header has {found}); {how}")
    else:
        timed = []
    if i_pos is None:
        placed = best("position", {i_time, *timed[:1]})
        if len(placed) > 1:
            raise ValueError(f"{path}: which column is the position? "
                             f"{_listed(names, placed)} all look like positions (the header "
                             f"has {found}); {how}")
        if not placed:
            rest = unknown({i_time, *timed[:1]})
            if i_time is None and need_time and not timed:
                rest = rest[1:]  # the first unnamed column is the time (below)
            if len(rest) != 1:
                which = (f"{_listed(names, rest)} could each be it" if rest else
                         "no column is named like one (x, position, angle, displacement, "
                         "or a unit such as (m) or (deg))")
                raise ValueError(f"{path}: which column is the position? {which} (the header "
                                 f"has {found}); {how}")
            placed = rest
        i_pos = placed[0]
    if i_time is None and need_time:
        if not timed:
            timed = unknown({i_pos})[:1]
        if not timed:
            raise ValueError(f"{path}: which column is the time? No column is named like "
                             f"one (t, time, elapsed, or a unit such as (s)) (the header has "
                             f"{found}); {how}, or rebuild time from the sample rate "
                             "(load_trace(rate=...), dampax fit --rate)")
        i_time = timed[0]
    return i_time, i_pos


def _strip_unit(name: str) -> str:
    return re.sub(r"\s*[\(\[].*?[\)\]]\s*$", "", name).strip()


def _column(spec, names: list[str] | None, n_fields: int, what: str, path: str) -> int:
    """Index of a column given by index (int or digit string) or by header name."""
    if isinstance(spec, (int, np.integer)) and not isinstance(spec, bool):
        index = int(spec)
    elif isinstance(spec, str) and re.fullmatch(r"-?\d+", spec.strip()):
        index = int(spec.strip())
    elif isinstance(spec, str):
        if names is None:
            raise ValueError(f"{path}: {what} column {spec!r} given by name, but the file has "
                             "no header line; give the column index instead")
        wanted = _normalise(spec)
        normal = [_normalise(n) for n in names]
        stripped = [_strip_unit(n) for n in normal]
        for candidates in (normal, stripped):
            if wanted in candidates:
                return candidates.index(wanted)
        if _strip_unit(wanted) in stripped:
            return stripped.index(_strip_unit(wanted))
        raise ValueError(f"{path}: no {what} column named {spec!r}; the header has "
                         f"{', '.join(repr(n) for n in names)}")
    else:
        raise ValueError(f"{what} must be a column name or index, got {spec!r}")
    if not -n_fields <= index < n_fields:
        raise ValueError(f"{path}: {what} column index {index} is out of range; the file has "
                         f"{n_fields} columns")
    return index % n_fields


def load_trace(path, *, time=None, position=None, rate=None, delimiter=None,
               scale: float = 1.0) -> Trace:
    """Read a measured trace x(t) from a delimited text file.

    Accepts comma, semicolon, tab or whitespace separated columns, with or without a header
    line (or with the header in the last comment line before the data, ``# t x`` as
    ``numpy.savetxt`` writes it, where its names fit the columns and say what one of them
    holds), CRLF or LF line ends, comment lines (``#``), separator lines (``-----``), empty
    trailing fields, decimal commas in semicolon/tab/space separated files and clock-time
    stamps ``HH:MM:SS.fff`` (read as seconds).

    Arguments:
        path: the file.
        time: the time column, by header name or index. Default: with a header, the column
            whose name means a time ("t", "time", "elapsed", "seconds", a unit "(s)"; a
            clock "Timestamp" only when there is no other), else the first column whose
            name says nothing; without a header, the first column. Not read when ``rate``
            is a number and ``time`` is not given: time is then rebuilt from the sample
            index.
        position: the position column, by name or index. Default: with a header, the one
            column whose name means a position ("x", "position", "angle", "theta",
            "displacement", "amplitude", or a unit "(m)", "(mm)", "(deg)", "(rad)"), never a
            velocity, acceleration or error column, else the one column whose name says
            nothing; without a header, the second column (the only one when ``rate`` is a
            number and the file has a single column).
        rate: None (read time as is); a sample rate [1/s] (time = t_first + i / rate with i
            the data-row index, dropped rows included; t_first = 0 without a time column);
            or "auto" for buffered time stamps (many rows share one stamp): the rate is
            (rows - 1) / (last stamp - first stamp), from the first and last readable stamps
            and the rows between them, and time is rebuilt from the row index.
        delimiter: the separator; None detects ";", tab, "," or whitespace.
        scale: factor applied to the positions (e.g. ``math.pi / 180`` for degrees).

    Returns:
        A :class:`Trace` with float64 ``t`` and ``x``; ``n_dropped`` counts the rows left out;
        ``time_column`` and ``position_column`` name the columns read.

    Raises:
        ValueError: not a regular file or larger than :data:`MAX_TRACE_BYTES`; the file has
            no data, only one column (and no ``rate``), no usable rows
            (every row has text or nothing in the chosen columns), an unknown column name,
            an index out of range, or a bad ``rate``; the header does not say which column
            is the time or the position (two alike, or none: give ``time`` / ``position``).
            The message names the file (and the columns).
        OSError: the file cannot be read.

    A FIFO, a device, a folder or a file larger than :data:`MAX_TRACE_BYTES` is refused before
    reading (ValueError naming the file).
    """
    path_str = str(path)
    raw = read_regular_file(path)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:  # a Windows export: cp1252 ("°", "µ" were U+FFFD)
        text = raw.decode("cp1252", errors="replace")
    lines = _content_lines(text)
    if not lines:
        raise ValueError(f"{path_str}: no data (the file is empty or holds only comments)")
    if rate is not None and not (rate == "auto" or (
            isinstance(rate, (int, float)) and not isinstance(rate, bool)
            and math.isfinite(rate) and rate > 0)):
        raise ValueError(f"rate must be a positive number or 'auto', got {rate!r}")
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale != 0):
        raise ValueError(f"scale must be a finite non-zero number, got {scale!r}")

    sample = [line for _, line in lines[:_SAMPLE_LINES]]
    if delimiter is None:
        delim = _choose_delimiter(sample)
    elif delimiter in (" ", "whitespace", "space"):
        delim = None
    elif delimiter in ("tab", "\\t"):
        delim = "\t"
    else:
        delim = delimiter
    decimal_comma = delim != ","
    first = _split(lines[0][1], delim)
    header = _is_header(first, decimal_comma)
    if header and delim is None:  # "Time [s]  Angle [deg]": a unit token is its name's
        first = _join_units(first)
    names = first if header else None
    body = lines[1:] if header else lines
    if header and body and _is_units_row(_split(body[0][1], delim), decimal_comma):
        names, body = _with_units_row(names, _split(body[0][1], delim)), body[1:]
    counts = [len(_split(line, delim)) for _, line in body[:_SAMPLE_LINES]] or [len(first)]
    n_fields = max(len(first), max(set(counts), key=counts.count))

    commented = names is None and (names := _comment_header(
        text, lines[0][0], delim, decimal_comma, n_fields)) is not None
    from_rate = rate is not None and rate != "auto"
    if n_fields < 2 and not from_rate:
        raise ValueError(f"{path_str}: only one column (delimiter "
                         f"{'whitespace' if delim is None else repr(delim)}); a trace needs a "
                         "time and a position column, or pass rate=<samples per second> to "
                         "build time from the sample index")
    use_time = not from_rate or time is not None
    i_pos = None if position is None else _column(position, names, n_fields, "position",
                                                  path_str)
    i_time = None if time is None else _column(time, names, n_fields, "time", path_str)
    if names is not None and (i_pos is None or (use_time and i_time is None)):
        try:
            i_time, i_pos = _choose_columns(names, i_time, i_pos, use_time, path_str)
        except ValueError:
            if not commented:
                raise
            names = None  # a comment that does not settle the columns: read by position
    if i_pos is None:  # no header: the second column (the only one with a rate)
        i_pos = 1 if n_fields >= 2 else 0
    if i_time is None and use_time:  # no header: the first column
        i_time = 0
    if i_time is not None and i_time == i_pos:
        raise ValueError(f"{path_str}: the time and position columns are the same "
                         f"(column {i_pos})")

    n_rows = len(body)
    times = np.full(n_rows, np.nan)
    xs = np.full(n_rows, np.nan)
    for r, (_, line) in enumerate(body):
        fields = _split(line, delim)
        if i_pos < len(fields):
            xs[r] = _number(fields[i_pos], decimal_comma)
        if i_time is not None and i_time < len(fields):
            times[r] = _number(fields[i_time], decimal_comma)
    # a time column in ms, us or min (by its header's unit) is read in seconds
    factor = _SECONDS.get(_name_and_unit(names[i_time])[1], 1.0) \
        if i_time is not None and names is not None and i_time < len(names) else 1.0
    times = times * factor
    finite_x = np.isfinite(xs)
    finite_t = np.isfinite(times) if i_time is not None else np.ones(n_rows, bool)
    index = np.arange(n_rows, dtype=float)

    rate_used = None
    if rate == "auto":
        ok_t = np.flatnonzero(finite_t)
        if ok_t.size < 2 or times[ok_t[-1]] <= times[ok_t[0]]:
            raise ValueError(f"{path_str}: rate='auto' needs at least two different readable "
                             "time stamps")
        rate_used = float((ok_t[-1] - ok_t[0]) / (times[ok_t[-1]] - times[ok_t[0]]))
        t = times[ok_t[0]] + (index - ok_t[0]) / rate_used
        keep = finite_x
    elif from_rate:
        rate_used = float(rate)
        t0 = 0.0
        if i_time is not None:
            ok_t = np.flatnonzero(finite_t)
            t0 = float(times[ok_t[0]]) if ok_t.size else 0.0
        t = t0 + index / rate_used
        keep = finite_x
    else:
        t = times
        keep = finite_x & finite_t
    n_keep = int(np.sum(keep))
    def label(i):
        if i is None:
            return "sample index"
        return names[i].strip() if names is not None and i < len(names) else f"#{i}"

    if n_keep == 0:
        cols = (f"the position column {label(i_pos)!r}" if i_time is None else
                f"the time column {label(i_time)!r} and the position column {label(i_pos)!r}")
        raise ValueError(f"{path_str}: no usable rows: none of the {n_rows} data rows has "
                         f"numbers in {cols} (text, empty fields or a wrong delimiter? choose "
                         "the columns: load_trace(time=..., position=...), dampax fit --time "
                         "... --position ...)")

    dropped = n_rows - n_keep
    if dropped > max(1, DROPPED_SHARE * n_rows):  # (a note in dampax fit; silent here before)
        warnings.warn(f"{path_str}: {dropped} of {n_rows} data rows have no number in the time "
                      f"or position column and were left out (a thousands separator, text, "
                      f"an empty field?)", UserWarning, stacklevel=2)
    return Trace(t=np.asarray(t[keep], dtype=float),
                 x=np.asarray(xs[keep], dtype=float) * float(scale),
                 n_dropped=n_rows - n_keep, source=path_str, time_column=label(i_time),
                 position_column=label(i_pos), rate=rate_used, n_rows=n_rows,
                 scale=float(scale), time_factor=factor)
