"""Tests of fitting (``dampax._fit``): single and joint fits, their checks and intervals
against generated families with known truth, the posterior, and reading measured traces.

Shared here: the folder of measured traces (``shared_data``; the tests that need it skip
without it) and the benchmark scripts whose generated families the calibration tests sample
(``benchmark_module``). Each file's compiled fits are module fixtures of one shape and setting
(the programs are shared through the session's compilation cache, tests/conftest.py).
"""

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: the measured traces beside the repository (../shared/data; never committed)
DATA = ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The folder of measured traces, or a skip where it is not beside the repository."""
    if not DATA.is_dir():
        pytest.skip(f"the measured traces are not at {DATA}")
    return DATA


@pytest.fixture(scope="session")
def benchmark_module():
    """``load(name)``: benchmarks/<name>.py as a module (loaded once per session)."""
    loaded = {}

    def load(name: str):
        if name not in loaded:
            spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            loaded[name] = module
        return loaded[name]

    return load


# ----------------------------------------------------------------------------------------------
# the golden record of scripts/fit_golden.py (issue 33): only when DAMPAX_FIT_GOLDEN_DIR is set

_CURRENT = {"test": None}


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """The test whose setup, call or teardown runs now (module fixtures count to the first
    test that uses them, as their fits run in its setup)."""
    _CURRENT["test"] = item.nodeid
    yield
    _CURRENT["test"] = None


def pytest_configure(config):
    """With DAMPAX_FIT_GOLDEN_DIR: record the to_dict() of every result dp.fit returns to its
    caller (``_entry.fit_flat``, single and joint), one JSON line per fit, per process."""
    import json
    import os

    folder = os.environ.get("DAMPAX_FIT_GOLDEN_DIR")
    if not folder:
        return
    from dampax._fit import _entry

    real = _entry.fit_flat
    depth = [0]
    part = Path(folder) / f"{os.environ.get('PYTEST_XDIST_WORKER', 'main')}.jsonl"

    def recorded(*args, **kwargs):
        depth[0] += 1
        try:
            res = real(*args, **kwargs)
        finally:
            depth[0] -= 1
        if depth[0] == 0 and hasattr(res, "to_dict"):
            line = json.dumps({"test": _CURRENT["test"], "fit": res.to_dict()}, default=str)
            with open(part, "a", encoding="utf-8") as fh:
                fh.write(line + "\n")
        return res

    _entry.fit_flat = recorded
