"""A trace file's header: its names and units, what each column holds, and which are the
time and the position (``load_trace``'s choice by meaning)."""

from __future__ import annotations

import re

import numpy as np

from ._text import (
    _is_header,
    _pandas_header,
    _split,
)

#: seconds per unit of a time column's unit (the others are seconds)
_SECONDS = {**dict.fromkeys(("ms", "msec", "millisec", "millisecond", "milliseconds"), 1e-3),
            **dict.fromkeys(("us", "µs", "μs", "usec", "µsec", "μsec", "microsec",
                             "microsecond", "microseconds"), 1e-6),
            **dict.fromkeys(("ns", "nsec", "nanosecond", "nanoseconds"), 1e-9),
            **dict.fromkeys(("min", "mins", "minute", "minutes"), 60.0),
            **dict.fromkeys(("h", "hr", "hrs", "hour", "hours"), 3600.0)}


def _unit_token(field: str) -> str:
    return field.strip().strip('"').strip("'").strip("()[] ")


def _is_units_row(fields: list[str], mark: str) -> bool:
    """A line under the header that holds units: no number, short tokens, one of them a unit
    of time or position ("ms,mm", "[s] [deg]")."""
    units = [_unit_token(f) for f in fields if f.strip()]
    return _is_header(fields, mark) and all(len(u) <= 8 for u in units) and any(
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


def _header_names(fields: list[str], line: str, delim: str | None, n_fields: int) -> list[str]:
    """A header line's names: in a whitespace-separated file a unit token joined to its name
    ("Time [s]"), and names of several words kept whole where runs of two spaces or more
    separate the columns ("Cart Position   Cart Velocity": its four words read the velocity
    as the position)."""
    if delim is not None:
        return fields
    names = _join_units(fields)
    if len(names) != n_fields:
        wide = [n for n in re.split(r"\s{2,}|\t", line.strip()) if n]
        if len(wide) == n_fields:
            return wide
    return names


def _header(rows: list[list[str]], raw: list[str], n_fields: int, delim: str | None,
            mark: str) -> list[str] | None:
    """The names among the lines above the data (``rows`` split, ``raw`` as read), or None
    where none reads as a header. Of the lines of names just above the data with as many
    names as the data have columns (one more: a column the data leave empty; a title's
    words, Tracker's "mass A", are not names), below a title only those that say what a
    column holds, the one whose names say most (:func:`_meaning`; the first of equals),
    with a units row under it written into its names."""
    run = []
    for i in range(len(rows) - 1, -1, -1):
        fields = rows[i]
        if not (_is_header(fields, mark) or _pandas_header(fields)) or \
                (len(fields) < 2 <= n_fields):
            break
        run.insert(0, i)
    named = {i: _header_names(rows[i], raw[i], delim, n_fields) for i in run}
    # names as many as the columns (one more: a column the data leave empty); a title's words
    # are not names
    run = [i for i in run if n_fields <= len(named[i]) <= n_fields + 1 and (
        i == 0 or any(_meaning(n)[1] > 0 for n in named[i]))]  # (below a title: names)
    if not run:
        return None
    best = max(run, key=lambda i: (sum(_meaning(n)[1] for n in named[i]), -i))
    names = named[best]
    below = rows[best + 1] if best + 1 < len(rows) else None
    if below is not None and _is_units_row(below, mark):
        names = _with_units_row(names, below)
    return names


def _comment_header(text: str, first_data_line: int, delim: str | None, mark: str,
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
    meanings = [_meaning(f) for f in fields]
    if len(fields) != n_fields or not _is_header(fields, mark) or \
            not any(rank > 0 for _, rank in meanings) or not all(kind for kind, _ in meanings):
        return None  # ("# columns: time, position" is a sentence, not names)
    return fields


def _normalise(name: str) -> str:
    return re.sub(r"\s+", " ", name.strip().strip('"').strip("'")).lower()


# what a header's column names mean (``_meaning``): the words of a name (split at spaces,
# "_", "-", "." and case changes) and its unit, "(s)", "[deg]" or "/ m" after the name
_TIME_WORDS = frozenset({"t", "time", "times", "elapsed", "second", "seconds", "sec", "secs",
                         "zeit", "tempo", "temps", "tiempo", "tijd"})
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
_TIME_UNITS = frozenset({"s", "sec", "secs", "second", "seconds", *_SECONDS})
_POSITION_UNITS = frozenset({"m", "mm", "cm", "um", "µm", "nm", "in", "ft", "deg", "degree",
                             "degrees", "°", "rad", "radian", "radians", "mrad"})


#: units a name may end in after "_" ("time_ms", "x_mm"): not "min", "in", "ft", "s" or "m",
#: which end names of other things there ("x_min", "x_in", "x_s"); a name in seconds or metres
#: reads the same without its unit
_SUFFIX_UNITS = (_TIME_UNITS | _POSITION_UNITS) - {"min", "in", "ft", "s", "m", "h", "hr"}
#: names that are a time in a unit by themselves (Arduino's millis() and micros(), a column
#: headed only "ms")
_UNIT_NAMES = {"millis": "ms", "micros": "us", **{u: u for u in _SECONDS if len(u) > 1
                                                   and u not in ("min", "hr")}}


def _name_and_unit(name: str) -> tuple[list[str], str]:
    """(the words of a column name, its unit or ""), lower case: "Time_Elapsed(s)" ->
    (["time", "elapsed"], "s"); "x [m]" -> (["x"], "m"); "t / s" -> (["t"], "s");
    "time_ms" -> (["time"], "ms")."""
    text = name.strip().strip('"').strip("'").strip()
    text = re.sub(r"\s+run\s*#?\s*\d+\s*$", "", text, flags=re.IGNORECASE)  # PASCO's
    unit = ""
    found = re.search(r"[\(\[]\s*([^\)\]]*?)\s*[\)\]]\s*$", text)
    if found:
        unit, text = found.group(1), text[:found.start()]
    else:
        slash = re.fullmatch(r"(.*?\S)\s*[/,]\s*([^\s/,]+)", text)  # "t / s", "Time, ms"
        if slash and slash.group(2).lower() in _TIME_UNITS | _POSITION_UNITS:
            text, unit = slash.group(1), slash.group(2)
    if not unit and text.strip().lower() in _UNIT_NAMES:
        return ["time"], _UNIT_NAMES[text.strip().lower()]
    if text.strip().lower() == "x_value":  # LabVIEW's measurement files: the waveform's time
        return ["time"], unit.strip().lower()
    text = re.sub(r"([a-z])([A-Z])", r"\1 \2", text)  # TimeElapsed -> Time Elapsed
    words = [w for w in re.split(r"[\s_\-.:,;]+", text.lower()) if w]
    if not unit and len(words) >= 2 and words[-1] in _SUFFIX_UNITS and (
            re.search(r"_" + re.escape(words[-1]) + r"$", text.lower())
            or set(words[:-1]) & (_TIME_WORDS | _POSITION_WORDS)):
        words, unit = words[:-1], words[-1]  # "time_ms", "x_mm", "TimeMs", "angle deg"
    return words, unit.strip().lower()


def column_unit(name: str) -> str:
    """The unit a column's name gives, as the loader reads it ("x / mm", "Angle(deg)",
    '"x (mm)"' -> "mm", "deg", "mm"), or "": in lower case where the loader knows it, as
    written where not ("Channel A (mV)" -> "mV", not "mv")."""
    unit = _name_and_unit(name)[1]
    if not unit or unit in _TIME_UNITS | _POSITION_UNITS:
        return unit
    written = re.search(re.escape(unit), name, flags=re.IGNORECASE)
    return written.group(0) if written else unit


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
    """A column's name without its unit (and PASCO's " Run #1" after it), for a lookup by
    name: "Position (mm) Run #1" -> "Position"."""
    name = re.sub(r"\s+run\s*#?\s*\d+\s*$", "", name, flags=re.IGNORECASE)
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
