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
import tempfile

_SESSION_DIR = "DAMPAX_TEST_SESSION_CACHE_DIR"  # set by the controller, read by its workers

if os.environ.get("PYTEST_XDIST_WORKER") and os.environ.get(_SESSION_DIR):
    os.environ["DAMPAX_CACHE_DIR"] = os.environ[_SESSION_DIR]
else:
    os.environ["DAMPAX_CACHE_DIR"] = tempfile.mkdtemp(prefix="dampax-test-cache-")
    os.environ[_SESSION_DIR] = os.environ["DAMPAX_CACHE_DIR"]

import dampax  # noqa: E402, F401  (jax_enable_x64 is set on import)

#: test files and notebooks by measured run time (an idle 2-core run with -n 2, issue 26), the
#: most expensive first; the rest follow in their usual order. Only the order of the files
#: under xdist changes.
COST_ORDER = (
    "tests/test_fit.py", "tests/test_cubic.py", "notebooks/04_fitting_real_data.ipynb",
    "tests/test_joint.py", "tests/test_reference.py", "tests/test_speed.py",
    "tests/test_posterior.py", "tests/test_sensitivity.py", "tests/test_static_friction.py",
    "tests/test_maps.py", "tests/test_models.py", "tests/test_results.py",
    "notebooks/05_sensitivity.ipynb", "tests/test_distributed.py",
    "notebooks/03_error_maps.ipynb", "tests/test_domain.py", "tests/test_global.py",
    "tests/test_lean_ansatz.py", "tests/test_atlas.py", "tests/test_gradients.py",
    "tests/test_reproduce.py", "tests/test_cli.py", "notebooks/01_quickstart.ipynb",
    "notebooks/02_paper_figures.ipynb", "tests/test_decay.py",
)


def pytest_collection_modifyitems(config, items):
    """Under xdist: the files in :data:`COST_ORDER` (the order within a file is kept)."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    rank = {path: i for i, path in enumerate(COST_ORDER)}

    def key(item):
        path = item.nodeid.split("::")[0]
        return rank.get(path, len(rank))

    items.sort(key=key)  # stable: the order within a file and of the unlisted files is kept
