"""Where the test suite's XLA compiling goes: every compilation, by test, function and program.

    python scripts/suite_census.py run [pytest args]   # the suite as the README runs it
    python scripts/suite_census.py report [folder]     # the tables of a run

``run`` runs ``pytest -q -n 2`` (plus the given arguments) with this module as a plugin
(``-p suite_census``) and ``jax_log_compiles`` on: each worker writes one JSON line per
compilation (test, function, seconds, the persistent cache's key of the program) and per test
(its wall time) to ``DAMPAX_CENSUS_DIR`` (default ``/tmp/dampax-census``). ``report`` prints
the compiling time by test file and by function, and the programs compiled more than once
(the same cache key: the only compiling that sharing settings cannot avoid is the first of
each program). The notebooks' kernels are not counted. Eighteenth session (benchmarks/
README.md): 2,036 compilations, 1,144 s; 81 programs compiled twice or more, 8 s.
"""

from __future__ import annotations

import collections
import json
import logging
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

FOLDER = Path(os.environ.get("DAMPAX_CENSUS_DIR", "/tmp/dampax-census"))
_DONE = re.compile(r"Finished XLA compilation of (.*) in ([0-9.e-]+) sec")
_KEY = re.compile(r"PERSISTENT COMPILATION CACHE (?:MISS|HIT) for '.*?' with key '(.*?)'")
_STATE = {"test": None, "key": None, "out": None}


class _Handler(logging.Handler):
    """JAX's compile log lines, as JSON lines of the running test."""

    def emit(self, record):
        msg, out = record.getMessage(), _STATE["out"]
        key = _KEY.search(msg)
        if key:
            _STATE["key"] = key.group(1)
            return
        done = _DONE.search(msg)
        if done and out is not None:
            out.write(json.dumps({"test": _STATE["test"], "fn": done.group(1),
                                  "s": float(done.group(2)), "key": _STATE["key"]}) + "\n")
            _STATE["key"] = None


def pytest_configure(config):
    import jax

    jax.config.update("jax_log_compiles", True)
    FOLDER.mkdir(parents=True, exist_ok=True)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    _STATE["out"] = open(FOLDER / f"{worker}.jsonl", "a", buffering=1)  # noqa: SIM115
    handler = _Handler(level=logging.DEBUG)
    for name in ("jax._src.dispatch", "jax._src.compiler"):
        log = logging.getLogger(name)
        log.addHandler(handler)
        log.setLevel(logging.DEBUG)
        log.propagate = False


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _STATE["test"] = item.nodeid
    began = time.perf_counter()
    yield
    if _STATE["out"] is not None:
        _STATE["out"].write(json.dumps({"test": item.nodeid, "wall": time.perf_counter() -
                                        began}) + "\n")


def report(folder: Path) -> None:
    """The tables of a run's JSON lines (see the module docstring)."""
    rows = [json.loads(line) for part in sorted(folder.glob("*.jsonl"))
            for line in part.read_text().splitlines() if line]
    compiles = [r for r in rows if "fn" in r]
    wall, by_file, by_fn = collections.Counter(), collections.Counter(), collections.Counter()
    count, keys = collections.Counter(), collections.defaultdict(list)
    for r in rows:
        name = (r["test"] or "?").split("::")[0]
        if "wall" in r:
            wall[name] += r["wall"]
        else:
            by_file[name] += r["s"]
            by_fn[r["fn"]] += r["s"]
            count[r["fn"]] += 1
            if r.get("key"):
                keys[r["key"]].append(r["s"])
    print(f"{len(compiles)} compilations, {sum(by_fn.values()):.0f} s; tests "
          f"{sum(wall.values()):.0f} s")
    print("\nby file: test s, compiling s")
    for name, s in wall.most_common(20):
        print(f"{s:8.1f} {by_file[name]:8.1f}  {name}")
    print("\nby function: compiling s, programs")
    for fn, s in by_fn.most_common(20):
        print(f"{s:8.1f} {count[fn]:5d}  {fn}")
    again = {k: v for k, v in keys.items() if len(v) > 1}
    print(f"\nprograms compiled more than once: {len(again)}, "
          f"{sum(sum(v[1:]) for v in again.values()):.1f} s of repeats")


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in ("run", "report"):
        print(__doc__)
        return 2
    if argv[0] == "report":
        report(Path(argv[1]) if len(argv) > 1 else FOLDER)
        return 0
    for part in FOLDER.glob("*.jsonl"):
        part.unlink()
    here = Path(__file__).resolve().parent
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        filter(None, [str(here), os.environ.get("PYTHONPATH", "")]))}
    code = subprocess.call([sys.executable, "-m", "pytest", "-q", "-n", "2", "-p",
                            "suite_census", *argv[1:]], cwd=here.parent, env=env)
    report(FOLDER)
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
