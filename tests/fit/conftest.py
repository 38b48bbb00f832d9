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

