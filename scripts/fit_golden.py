"""Golden record of every fit the tests of tests/fit make, for the fit layer's refactor (issue 33).

    python scripts/fit_golden.py record   # before the change: writes tests/fit/golden_fits.json
    python scripts/fit_golden.py check    # after it: the same fits, compared (1e-12 relative)

Each mode runs ``pytest`` on :data:`FILES` (tests/fit, and the k3 and mu_s searches' tests;
two processes) with ``DAMPAX_FIT_GOLDEN_DIR`` set: the
conftest of tests/fit then records the ``to_dict()`` of every result that ``dp.fit`` (single
and joint, through ``_entry.fit_flat``) returns to its caller, by test and in call order, and
of ``dp.fit(dp.example_trace())``. ``check`` compares them with the golden file: every number
to 1e-12 relative (NaN where NaN), every string (success, reason, message) equal; it prints
the differences and exits 1 if there are any. The test run's own verdicts are not the point
here (they are the suite's), but a failing test is reported.

The record depends on the machine: another CPU rounds differently (XLA's code for it), and the
fits that sit on a jump of the halt or in a flat valley then move by more than rounding (the
nineteenth session's machine: 943 differences from the record on unchanged code, all at the
rounding level but the covariances of two real-trace fits, no verdict changed). On a machine
other than the record's, ``record`` at the base commit first, then ``check`` the change.
"""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = ROOT / "tests" / "fit" / "golden_fits.json"
RTOL = 1e-12
#: pytest's temporary folders differ from run to run (a file's source names one)
_TMP = re.compile(r"/tmp/pytest-of-[^/]+/pytest-\d+/(popen-gw\d+/)?")
#: the tests whose fits are recorded: the fit layer's own, and those of the k3 and mu_s searches
FILES = ("tests/fit", "tests/models/test_cubic.py", "tests/reference/test_static_friction.py")


def _collect(folder: Path) -> dict:
    records: dict = {}
    for part in sorted(folder.glob("*.jsonl")):
        for line in part.read_text().splitlines():
            item = json.loads(line)
            records.setdefault(item["test"], []).append(item["fit"])
    return records


def _example() -> list:
    """The example trace's fits (``dampax fit --example``'s call, and with the exact model),
    in a fresh process (the code on this process's path)."""
    code = ("import json, dampax as dp; tr, tru = dp.example_trace(); "
            "osc = dp.Oscillator(m=tru['m'], k=tru['k']); "
            "print(json.dumps([dp.fit(tr, oscillator=osc, model=m).to_dict() "
            "for m in ('ansatz', 'reference')], default=str))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True,
                         capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def _diff(a, b, where: str, out: list) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            if key not in a or key not in b:
                out.append(f"{where}.{key}: only in {'golden' if key in a else 'new'}")
            else:
                _diff(a[key], b[key], f"{where}.{key}", out)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            out.append(f"{where}: length {len(a)} -> {len(b)}")
        for i, (x, y) in enumerate(zip(a, b, strict=False)):
            _diff(x, y, f"{where}[{i}]", out)
    elif isinstance(a, float) and isinstance(b, float | int) and not isinstance(b, bool):
        if not (a == b or (math.isnan(a) and math.isnan(b))
                or abs(a - b) <= RTOL * max(abs(a), abs(b))):
            out.append(f"{where}: {a!r} -> {b!r}")
    elif a != b and not (isinstance(a, str) and isinstance(b, str)
                         and _TMP.sub("", a) == _TMP.sub("", b)):
        out.append(f"{where}: {a!r} -> {b!r}")


def main(mode: str) -> int:
    if mode not in ("record", "check"):
        print(__doc__)
        return 2
    with tempfile.TemporaryDirectory(prefix="dampax-golden-") as folder:
        env = dict(os.environ, DAMPAX_FIT_GOLDEN_DIR=folder)
        run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "2", *FILES,
                              "-p", "no:cacheprovider"], cwd=ROOT, env=env)
        records = _collect(Path(folder))
    records["example_trace"] = _example()
    if run.returncode:
        print(f"note: pytest tests/fit exited with {run.returncode}")
    if mode == "record":
        GOLDEN.write_text(json.dumps(records, indent=1, sort_keys=True) + "\n")
        print(f"{sum(map(len, records.values()))} fits of {len(records)} tests -> {GOLDEN}")
        return 0
    golden = json.loads(GOLDEN.read_text())
    # tests written after the recording have no golden fits: listed, not differences
    added = sorted(set(records) - set(golden))
    for name in added:
        print(f"{name}: a test newer than the golden file (not compared)")
    out: list[str] = []
    _diff(golden, {k: v for k, v in records.items() if k in golden}, "", out)
    for line in out:
        print(line)
    print(f"{len(out)} differences over {sum(map(len, golden.values()))} golden fits")
    return 1 if out else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else ""))
