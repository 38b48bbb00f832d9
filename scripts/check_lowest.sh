#!/usr/bin/env bash
# Are pyproject.toml's lower bounds true? A fresh virtual environment with the lowest versions
# the bounds allow (uv's --resolution lowest-direct: every direct dependency at its lower bound,
# the test tools at theirs too), then a fast subset of the suite: the models, the reference,
# two error maps (one through the CLI: netCDF and figures), one fit, one posterior (blackjax,
# checked against ArviZ) and the kept (jax.export) programs: 286 tests, about 5 minutes on a
# loaded 2-core machine (the environment's download and install besides).
#
#   bash scripts/check_lowest.sh                     # the bounds as they are
#   bash scripts/check_lowest.sh "jax==0.6.2" ...    # the same with some versions forced
#                                                    # (overrides: to bisect a bound)
#
# The environment goes to $DAMPAX_LOWEST_VENV (default: a folder under ${TMPDIR:-/tmp}), never
# into the checkout; uv is taken from PATH, else installed into a venv beside it. The Python is
# $DAMPAX_LOWEST_PYTHON (default 3.11, the lowest requires-python allows). Exit status: pytest's.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
base=${DAMPAX_LOWEST_VENV:-${TMPDIR:-/tmp}/dampax-lowest}
python=${DAMPAX_LOWEST_PYTHON:-3.11}

if command -v uv >/dev/null 2>&1; then
    uv=uv
else
    [ -x "$base-uv/bin/uv" ] || { python3 -m venv "$base-uv" && "$base-uv/bin/pip" install -q uv; }
    uv="$base-uv/bin/uv"
fi

rm -rf "$base"
"$uv" venv -q --python "$python" "$base"
overrides=$(mktemp)
trap 'rm -f "$overrides"' EXIT
printf '%s\n' "$@" >"$overrides"
# the package's dependencies and the test tools the subset needs, each at its lowest
"$uv" pip install -q --python "$base/bin/python" --resolution lowest-direct \
    --override "$overrides" -e "$root" "pytest>=8" "hypothesis>=6.100" "pytest-xdist>=3.5" \
    "arviz>=0.20"
"$uv" pip list -q --python "$base/bin/python" 2>/dev/null \
    | grep -E -i '^(jax|jaxlib|equinox|optax|optimistix|lineax|numpy|scipy|matplotlib|xarray|h5netcdf|tqdm|blackjax|flatbuffers|pytest|hypothesis|arviz|pandas) '

cd "$root"
# -o addopts=: no --nbmake (the notebooks are not part of the subset); -n 0: one process
"$base/bin/python" -m pytest -q -n 0 -o addopts= -p no:cacheprovider \
    tests/models/test_models.py tests/models/test_decay.py tests/models/test_lean_ansatz.py \
    tests/models/test_paper_numbers.py \
    "tests/reference/test_reference.py" \
    "tests/studies/test_maps.py::test_chunk_size_does_not_change_the_map" \
    "tests/studies/test_maps.py::test_cli_quick" \
    "tests/fit/test_fit.py::test_named_failures_undamped_and_max_steps" \
    "tests/fit/test_posterior.py::test_posterior_covers_the_truth" \
    "tests/reference/test_speed.py::test_traced_error_map_step_is_reused_across_processes"
