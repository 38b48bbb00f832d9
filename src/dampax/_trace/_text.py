"""The text of a trace file: its lines, fields and numbers (decimal marks, thousands
separators, clock times), where the data begin (``_columns`` reads the header above them)."""

from __future__ import annotations

import csv
import datetime
import math
import re

# candidate separators in the order they are tried when delimiter=None; None = whitespace
_DELIMITERS = (";", "\t", ",", None)
_SEPARATOR_LINE = re.compile(r"^[\s\-=_*~+|#.:]{3,}$")
_CLOCK = re.compile(r"^(\d{1,2}):(\d{2}):(\d{2}(?:\.\d*)?)$")
_SAMPLE_LINES = 200  # lines used to choose the delimiter and the header


#: a number with thousands separators: dots where the decimal mark is a comma ("1.234,5"),
#: commas where it is a point ("1,234.5")
_GROUPED = {",": re.compile(r"[+-]?\d{1,3}(?:\.\d{3})+(?:,\d*)?"),
            ".": re.compile(r"[+-]?\d{1,3}(?:,\d{3})+(?:\.\d*)?")}
#: Fortran's double-precision exponent ("1.0D-03")
_FORTRAN = re.compile(r"(?<=[\d.])[dD](?=[+-]?\d)")
_ISO = re.compile(r"\d{4}-\d{2}-\d{2}[ T]\d{2}:\d{2}")
_NUMERIC = re.compile(r"[+-]?[\d.,]*\d[\d.,]*(?:[eEdD][+-]?\d+)?")


def _clean(field: str) -> str:
    return field.strip().strip('"').strip("'").strip().replace("\u2212", "-")  # (U+2212)


def _number(field: str, mark: str) -> float:
    """A float from one field, whose decimal mark is ``mark`` ("." or ","; the other one
    groups thousands: "1.234,5" or "1,234.5"); Fortran's "1.0D-03"; clock times
    H:MM:SS(.fff) become seconds. NaN if unreadable."""
    text = _clean(field)
    if not text:
        return math.nan
    if mark == "," and _GROUPED[","].fullmatch(text):
        text = text.replace(".", "")
    for candidate in (text, text.replace(",", ".") if mark in ",?" and text.count(",") == 1
                      and "." not in text else None,
                      text.replace(",", "") if mark == "." and _GROUPED["."].fullmatch(text)
                      else None):
        if candidate is not None:
            try:
                return float(_FORTRAN.sub("e", candidate))
            except ValueError:
                pass
    clock = _CLOCK.match(text.replace(",", ".") if mark in ",?" else text)
    if clock:
        h, m, sec = clock.groups()
        return 3600.0 * int(h) + 60.0 * int(m) + float(sec)
    if _ISO.match(text):  # "2024-01-15 10:30:00.010": seconds of the epoch, as UTC
        try:
            stamp = datetime.datetime.fromisoformat(text.replace(",", "."))
        except ValueError:
            return math.nan
        if stamp.tzinfo is None:
            stamp = stamp.replace(tzinfo=datetime.UTC)
        return stamp.timestamp()
    return math.nan


def _decimal_mark(fields, delimiter: str | None) -> str:
    """The decimal mark of a file's numbers ("." or ","), from the fields that show it: a
    mark followed by other than three digits ("0,05", "1.5"), both marks ("1.234,5"), or one
    mark repeated ("1.234.567" groups with dots); where none does (every mark followed by
    three digits), "?" in a file not separated by commas (a point is the decimal mark, and
    so is a lone comma: "1.194" and "0,125" read as before), else "."."""
    votes = {",": 0, ".": 0}
    for field in fields:
        text = _clean(field)
        if not _NUMERIC.fullmatch(text) or ("," not in text and "." not in text):
            continue
        mantissa = re.split(r"[eEdD]", text)[0]
        if "," in mantissa and "." in mantissa:
            votes["," if mantissa.rfind(",") > mantissa.rfind(".") else "."] += 1
            continue
        for mark, other in ((",", "."), (".", ",")):
            if mantissa.count(mark) > 1:
                votes[other] += 1
            elif mantissa.count(mark) == 1 and len(mantissa.split(mark)[1]) != 3:
                votes[mark] += 1
    if votes[","] != votes["."]:
        return "," if votes[","] > votes["."] else "."
    return "?" if delimiter != "," else "."


def _split(line: str, delimiter: str | None) -> list[str]:
    """The fields of a line: quoted ones whole ("1,000.5" in a comma-separated file; the
    delimiter inside quotes split them, without a word), their quotes removed."""
    if delimiter is None:
        return line.split()
    if '"' in line and len(delimiter) == 1:
        try:
            return [f.strip() for f in next(csv.reader([line], delimiter=delimiter))]
        except (csv.Error, StopIteration):
            pass
    return [f.strip() for f in line.split(delimiter)]


def _content_lines(text: str) -> list[tuple[int, str]]:
    """(line number, line) of every line that is not empty, a comment or a separator line."""
    out = []
    for i, raw in enumerate(text.splitlines()):
        line = raw.rstrip().lstrip(" \ufeff")  # (a leading tab is an empty first field)
        bare = line.strip()
        if not bare or bare.startswith("#") or bare.startswith("%"):
            continue
        if _SEPARATOR_LINE.match(bare) and not any(ch.isdigit() for ch in bare):
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


def _is_header(fields: list[str], mark: str) -> bool:
    """A line is a header when it has text and no field is a number (a data row with text in
    one column is a row to drop, not a header)."""
    filled = [f for f in fields if f.strip()]
    return bool(filled) and all(math.isnan(_number(f, mark)) for f in filled)


def _pandas_header(fields: list[str]) -> bool:
    """pandas' ``to_csv`` header of a frame with unnamed columns: an empty name (the index),
    then 0, 1, ... (read as numbers, it made the index the time and the time the position)."""
    return len(fields) >= 3 and not fields[0].strip() and \
        [_clean(f) for f in fields[1:]] == [str(i) for i in range(len(fields) - 1)]


def _numeric(field: str) -> bool:
    text = _clean(field)
    return bool(_NUMERIC.fullmatch(text) or _CLOCK.match(text) or _ISO.match(text))


def _first_data_row(rows: list[list[str]]) -> int:
    """Index of the first row of numbers: two fields or more that read as numbers (else one;
    a pandas header is not one); ``len(rows)`` where no row holds a number."""
    for need in (2, 1):
        for i, fields in enumerate(rows):
            if not _pandas_header(fields) and sum(map(_numeric, fields)) >= need:
                return i
    return len(rows)


def _numeric_columns(rows: list[list[str]], n_fields: int, taken: set) -> list[int]:
    """The columns (not ``taken``) whose fields are numbers in most of ``rows``, in order."""
    if any(re.search(r"\d\s+[\d+-]", f) for r in rows for f in r):
        return []  # numbers split across fields by a wrong delimiter: no guess
    share = [sum(j < len(r) and _numeric(r[j]) for r in rows) / max(len(rows), 1)
             for j in range(n_fields)]
    return [j for j in range(n_fields) if share[j] > 0.5 and j not in taken]


def _refuse_split_decimals(names, counts: list[int], delim: str | None, path: str) -> None:
    """A ValueError where a comma-separated file's rows hold twice the header's columns:
    decimal commas unquoted ("0,05,1,25"), which split every number in two."""
    if delim == "," and names is not None and len(names) >= 2 and counts and \
            max(set(counts), key=counts.count) == 2 * len(names):
        raise ValueError(f"{path}: the header names {len(names)} columns and the rows have "
                         f"{2 * len(names)} fields: numbers with decimal commas in a "
                         "comma-separated file? Save it with ';' as the separator (or quote "
                         "the numbers), or pass delimiter=")
