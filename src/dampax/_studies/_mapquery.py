"""Error maps at the edges: the command line's axes ("START:STOP:N" and plain numbers, parsed
without eval and bounded) and the questions the command asks of a finished map (the largest
ratio below an error, the worst point in a box)."""

from __future__ import annotations

import ast
import math
import operator

import numpy as np

#: the most values one axis of the command line takes ("START:STOP:N")
MAX_AXIS_POINTS = 1_000_000


def parse_axis(text: str, name: str) -> np.ndarray:
    """Grid axis from the command line: "START:STOP:N" (linspace, both ends), "a,b,c" or "a".

    Numbers may be arithmetic with pi, e.g. "0:7*pi/8:8". ValueError names ``name``.
    """
    try:
        parts = text.split(":")
        if len(parts) == 3:
            n = int(parts[2])
            if not 1 <= n <= MAX_AXIS_POINTS:
                raise ValueError(f"N must be between 1 and {MAX_AXIS_POINTS}")
            return np.linspace(_number(parts[0]), _number(parts[1]), n)
        if len(parts) == 1:
            return np.array([_number(p) for p in parts[0].split(",")], dtype=float)
        raise ValueError("expected START:STOP:N, a,b,c or a single number")
    except (ValueError, SyntaxError, TypeError, ArithmeticError, MemoryError,
            RecursionError) as err:
        raise ValueError(f"{name}: cannot read {text!r} ({err}); use START:STOP:N, "
                         "a comma list or a number (pi allowed, e.g. 0:7*pi/8:8)") from None


_OPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul,
        ast.Div: operator.truediv, ast.USub: operator.neg, ast.UAdd: operator.pos}


def _number(text: str) -> float:
    """A float from simple arithmetic on numbers and ``pi`` (no names, no calls)."""
    def ev(node):
        if isinstance(node, ast.Expression):
            return ev(node.body)
        if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)):
            return float(node.value)
        if isinstance(node, ast.Name) and node.id == "pi":
            return math.pi
        if isinstance(node, ast.BinOp) and type(node.op) in _OPS:
            return _OPS[type(node.op)](ev(node.left), ev(node.right))
        if isinstance(node, ast.UnaryOp) and type(node.op) in _OPS:
            return _OPS[type(node.op)](ev(node.operand))
        raise ValueError(f"not a number: {text.strip()!r}")

    text = text.strip()
    if text.lower() in ("nan", "inf", "-inf", "+inf"):
        return float(text)
    return ev(ast.parse(text, mode="eval"))


def largest_ratio_below(ds, threshold: float, *, along: str, model: str,
                        metric: str = "max_error") -> float | None:
    """Largest value of axis ``along`` up to which ``metric`` stays below ``threshold``.

    The other two ratio axes are held at 0 and the worst case over phi0 is taken; the scan
    goes up the axis from its first value and stops before the first point at or above the
    threshold (or where the model or the reference is not valid).

    Returns:
        The ratio; NaN when even the first point fails; None when the grid has no 0 on one of
        the other ratio axes.
    """
    sel = {}
    for axis in ("d0_ratio", "d1_ratio", "d2_ratio"):
        if axis == along:
            continue
        zero = np.flatnonzero(np.asarray(ds[axis]) == 0.0)
        if zero.size == 0:
            return None
        sel[axis] = int(zero[0])
    da = ds[metric].sel(model=model).isel(sel)
    worst = np.asarray(np.abs(da).max("phi0", skipna=False))
    values = np.asarray(ds[along])
    order = np.argsort(values)
    ok = np.isfinite(worst[order]) & (worst[order] < threshold)
    if not ok[0]:
        return math.nan
    bad = np.flatnonzero(~ok)
    return float(values[order][-1] if bad.size == 0 else values[order][bad[0] - 1])


def worst_in_box(ds, *, model: str, d0_max: float, d2_max: float,
                 metric: str = "max_error") -> float:
    """Largest ``metric`` over d0 <= d0_max, d2 <= d2_max, d1 = 0 and every phi0.

    NaN when the grid has no such point, no d1 = 0, or the model is not valid everywhere
    in that box.
    """
    d1 = np.asarray(ds["d1_ratio"])
    if not np.any(d1 == 0.0):
        return math.nan
    box = ds[metric].sel(model=model).isel(d1_ratio=int(np.flatnonzero(d1 == 0.0)[0]))
    box = box.where((box["d0_ratio"] <= d0_max) & (box["d2_ratio"] <= d2_max), drop=True)
    values = np.abs(np.asarray(box, dtype=float))
    if values.size == 0 or not np.all(np.isfinite(values)):
        return math.nan
    return float(values.max())
