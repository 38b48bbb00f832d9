"""``load_trace`` and its :class:`Trace` (the package docstring says what it reads)."""

from __future__ import annotations

import dataclasses
import math
import numbers
import os
import re
import stat
import warnings

import jax
import numpy as np

from ._columns import (
    _SECONDS,
    _TIME_UNITS,
    _choose_columns,
    _column,
    _comment_header,
    _header,
    _name_and_unit,
    _normalise,
)
from ._text import (
    _SAMPLE_LINES,
    _choose_delimiter,
    _content_lines,
    _decimal_mark,
    _first_data_row,
    _is_header,
    _number,
    _numeric_columns,
    _refuse_split_decimals,
    _split,
)

__all__ = ["Trace", "load_trace"]

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


def load_trace(path, *, time=None, position=None, rate=None, delimiter=None,
               scale: float = 1.0) -> Trace:
    """Read a measured trace x(t) from a delimited text file.

    Accepts comma, semicolon, tab or whitespace separated columns (Excel's ``sep=;`` line
    too), quoted fields, with or without a header line: the names just above the first row
    of numbers, below a title or metadata, with a units row under them, or in the last
    comment line before the data (``# t x`` as ``numpy.savetxt`` writes it, where its names
    fit the columns and say what one of them holds); UTF-8, UTF-16 and cp1252; CRLF or LF
    line ends, comment lines (``#``), separator lines (``-----``), empty trailing fields;
    the decimal mark the numbers show (a point, or a comma with dots or a point grouping
    thousands: ``1.234,5``, ``1,234.5``), Fortran's ``1.0D-03``; clock times
    ``HH:MM:SS.fff`` and ISO date-times (read as seconds). Times are converted to seconds by
    their column's unit (``(ms)``, ``_ms``, ``, ms``, ``(minutes)``, Arduino's ``millis``;
    an unknown unit is warned about). A tab-separated row whose first field is empty is left
    out, not read shifted.

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
        # Excel's "Unicode text" is UTF-16 with its byte-order mark
        text = raw.decode("utf-16") if raw[:2] in (b"\xff\xfe", b"\xfe\xff") else \
            raw.decode("utf-8-sig")
    except UnicodeDecodeError:  # a Windows export: cp1252 ("°", "µ" were U+FFFD)
        text = raw.decode("cp1252", errors="replace")
    lines = _content_lines(text)
    if not lines:
        raise ValueError(f"{path_str}: no data (the file is empty or holds only comments)")
    if rate is not None and not (isinstance(rate, str) and rate == "auto") and not (
            isinstance(rate, numbers.Real) and not isinstance(rate, (bool, np.bool_))
            and math.isfinite(rate) and rate > 0):
        raise ValueError(f"rate must be a positive number or 'auto', got {rate!r}")
    rate = float(rate) if isinstance(rate, numbers.Real) else rate
    if not (isinstance(scale, numbers.Real) and not isinstance(scale, (bool, np.bool_))
            and math.isfinite(scale) and scale != 0):
        raise ValueError(f"scale must be a finite non-zero number, got {scale!r}")

    hint = re.fullmatch(r"sep=(.)", lines[0][1].strip(), flags=re.IGNORECASE)
    if hint:  # Excel's "sep=;" line
        lines = lines[1:]
        delimiter = hint.group(1) if delimiter is None else delimiter
        if not lines:
            raise ValueError(f"{path_str}: no data (the file holds only {hint.group(0)!r})")
    sample = [line for _, line in lines[:_SAMPLE_LINES]]
    if delimiter is None:
        delim = _choose_delimiter(sample)
    elif delimiter in (" ", "whitespace", "space"):
        delim = None
    elif delimiter in ("tab", "\\t"):
        delim = "\t"
    else:
        delim = delimiter
    rows = [_split(line, delim) for line in sample]
    start = _first_data_row(rows)
    if start == len(rows):  # not one number: the first line is the header where it reads so
        start = 1 if _is_header(rows[0], ".") else 0
    counts = [len(r) for r in rows[start:]] or [len(rows[0])]
    n_fields = max(set(counts), key=counts.count)
    mark = _decimal_mark([f for r in rows[start:] for f in r], delim)
    names = _header(rows[:start], sample[:start], n_fields, delim, mark)
    body = lines[start:]
    if names is not None:
        n_fields = max(n_fields, len(names))
    _refuse_split_decimals(rows[start - 1] if start and _is_header(rows[start - 1], mark)
                           else None, counts, delim, path_str)

    commented = names is None and (names := _comment_header(
        text, lines[min(start, len(lines) - 1)][0], delim, mark, n_fields)) is not None
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
    if names is None and (i_pos is None or (use_time and i_time is None)):
        # no header: the first two columns that hold numbers in most rows (an oscilloscope
        # writes its settings in the columns before the data)
        filled = _numeric_columns(rows[start:], n_fields, {i_time, i_pos} - {None})
        if i_time is None and use_time and filled:
            i_time = filled.pop(0)
        if i_pos is None and filled:
            i_pos = filled.pop(0)
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
    for r, (number, line) in enumerate(body):
        fields = _split(line, delim)
        if i_pos < len(fields):
            xs[r] = _number(fields[i_pos], mark)
        if i_time is not None and i_time < len(fields):
            times[r] = _number(fields[i_time], mark)
        if math.isnan(xs[r]) and names is not None and len(fields) == len(names):
            _same_header(fields, names, number, path_str)
    # a time column in ms, us or min (by its header's unit) is read in seconds
    unit = _name_and_unit(names[i_time])[1] \
        if i_time is not None and names is not None and i_time < len(names) else ""
    factor = _SECONDS.get(unit, 1.0)
    if unit and unit not in _TIME_UNITS:
        warnings.warn(f"{path_str}: the time column {names[i_time].strip()!r} is in "
                      f"{unit!r}, which is not a unit dampax converts: its times are read as "
                      "seconds (head it with s, ms, us, min or h)", UserWarning, stacklevel=2)
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

    _check_axes(t[keep], xs[keep], label(i_time) if i_time is not None else None,
                label(i_pos), path_str)
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


#: the share of a time column's steps that go back beyond which, with a position that rises
#: at every row, the two are taken for swapped (a clock that resets a few times goes back at
#: a few steps, an oscillation at every other half period)
BACKWARD_SHARE = 0.1


def _check_axes(t, x, time_name: str | None, position_name: str, path: str) -> None:
    """A ValueError where the time column goes back at more than :data:`BACKWARD_SHARE` of
    its steps while the position rises at every row: the columns are swapped (an
    oscilloscope's "X,CH1": its "X" is the time axis, and "x" a position's name); a warning
    where the position rises at every row (a time or a sample counter, not a free decay)."""
    if x.size < 10 or not np.all(np.diff(x) > 0):
        return  # (and below a hundred rows, a slow swing may rise throughout)
    if time_name is not None and np.mean(np.diff(t) < 0) > BACKWARD_SHARE:
        raise ValueError(f"{path}: the time column {time_name!r} goes back and forth while "
                         f"the position column {position_name!r} rises at every row: are "
                         "they swapped? Give the columns by name or index (load_trace(time="
                         "..., position=...), dampax fit --time ... --position ...)")
    if x.size < 100:
        return
    warnings.warn(f"{path}: the position column {position_name!r} rises at every row (a time "
                  "or a sample counter?): a free decay goes back and forth; choose it with "
                  "position=", UserWarning, stacklevel=3)


def _same_header(fields: list[str], names: list[str], number: int, path: str) -> None:
    """A ValueError where a row repeats the header with its columns in another order (a
    logger restarted mid-file: the rows after it were read by the first header's columns,
    the velocity as the position); a header repeated as it was is a row left out."""
    key = [_normalise(f) for f in fields]
    if key != [_normalise(n) for n in names] and sorted(key) == sorted(
            _normalise(n) for n in names):
        raise ValueError(f"{path}: line {number} repeats the header with its columns in "
                         f"another order ({', '.join(repr(f) for f in fields)}): a logger "
                         "restarted mid-file? Split the file there")
