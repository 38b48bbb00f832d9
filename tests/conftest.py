"""Test configuration: importing dampax enables float64 in JAX once, for every test module.

The tests get a cache folder of their own (``DAMPAX_CACHE_DIR``, a fresh temporary directory
per session), set before dampax is imported: nothing from the user's ``~/.cache/dampax`` (or an
earlier run of ``dampax errormap``) is re-used, so compilation counts mean what they say, and
the suite writes nothing there.

Under pytest-xdist (``pytest -n 2``, as README.md runs it) the session is the controller and its
workers: the controller makes the folder and the workers, started by it, use the same one (as
the tests of one serial session share one folder), so a program compiled by one worker is
found by the other and by the notebooks' kernels. Each test file (each notebook) runs whole on
one worker (``--dist loadfile`` in pyproject.toml: its module-scoped fixtures are made once),
the files in :data:`COST_ORDER`, the most expensive first, so that the two workers finish
together.
"""

import os
import sys
import tempfile
from importlib import metadata
from pathlib import Path

# the tests live in one folder per layer (models/, reference/, studies/, fit/, cli/); their
# shared helpers (tests/helpers.py) are imported as ``helpers`` from every folder
sys.path.insert(0, str(Path(__file__).resolve().parent))

_SESSION_DIR = "DAMPAX_TEST_SESSION_CACHE_DIR"  # set by the controller, read by its workers

#: the folder this process made (the controller's, or a serial session's): removed when its
#: session ends (:func:`pytest_sessionfinish`); each run left about 230 MB in the temporary
#: folder before
_MADE_HERE = None
if os.environ.get("PYTEST_XDIST_WORKER") and os.environ.get(_SESSION_DIR):
    os.environ["DAMPAX_CACHE_DIR"] = os.environ[_SESSION_DIR]
else:
    _MADE_HERE = os.environ["DAMPAX_CACHE_DIR"] = tempfile.mkdtemp(prefix="dampax-test-cache-")
    os.environ[_SESSION_DIR] = os.environ["DAMPAX_CACHE_DIR"]

#: the tests' own ``jax.jit`` programs (gradients through the reference, vmapped solves, maps)
#: compile with XLA's loop-fusion emitter, as dampax's kept programs do on a CPU
#: (``dampax._cache.CPU_COMPILER_OPTIONS``): more than half of the suite's time is XLA
#: compiling, and this takes a third off the largest programs (benchmarks/README.md, eleventh
#: session). Set before JAX starts its backend; a flag the user set is kept. jaxlib 0.11
#: removed the flag, and XLA aborts the process on a flag it does not know: not set there.
FUSION_FLAG = "--xla_cpu_use_fusion_emitters=false"
_JAXLIB = tuple(int(p) for p in metadata.version("jaxlib").split(".")[:2])
if _JAXLIB < (0, 11) and "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {FUSION_FLAG}".strip()

import pytest  # noqa: E402

import dampax  # noqa: E402, F401  (jax_enable_x64 is set on import)
from dampax._reference._solve import resolve_engine  # noqa: E402

# on a CUDA GPU the default engine's one-time self-check compiles the fused kernel and the XLA
# engine for a small batch: done here, so that no test's count of compiled programs sees it
# (elsewhere this returns at once)
resolve_engine("auto")

#: test files and notebooks by measured run time (an idle 2-core run with -n 2, issue 26), the
#: most expensive first; the rest follow in their usual order. Only the order of the files
#: under xdist changes.
COST_ORDER = (
    "tests/fit/test_fit.py", "tests/models/test_cubic.py",
    "notebooks/04_fitting_real_data.ipynb", "tests/fit/test_joint.py",
    "tests/reference/test_reference.py", "tests/reference/test_speed.py",
    "tests/fit/test_posterior.py", "tests/studies/test_sensitivity.py",
    "tests/reference/test_diffrax_engine.py", "tests/reference/test_kernel.py",
    "tests/reference/test_static_friction.py", "tests/studies/test_maps.py",
    "tests/models/test_models.py", "tests/models/test_results.py",
    "notebooks/05_sensitivity.ipynb", "tests/studies/test_distributed.py",
    "notebooks/03_error_maps.ipynb", "tests/models/test_domain.py",
    "tests/studies/test_global.py", "tests/models/test_lean_ansatz.py",
    "tests/models/test_atlas.py", "tests/models/test_gradients.py",
    "tests/cli/test_reproduce.py", "tests/cli/test_cli.py", "notebooks/01_quickstart.ipynb",
    "notebooks/02_paper_figures.ipynb", "tests/models/test_decay.py",
)


def pytest_sessionfinish(session, exitstatus):
    """Remove the session's cache folder where this process made it (the workers and the
    notebooks' kernels have finished by the time the controller's session ends)."""
    if _MADE_HERE is not None:
        import shutil

        shutil.rmtree(_MADE_HERE, ignore_errors=True)


def pytest_collection_modifyitems(config, items):
    """Under xdist: the files in :data:`COST_ORDER` (the order within a file is kept)."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    rank = {path: i for i, path in enumerate(COST_ORDER)}

    def key(item):
        path = item.nodeid.split("::")[0]
        return rank.get(path, len(rank))

    items.sort(key=key)  # stable: the order within a file and of the unlisted files is kept


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
