#!/usr/bin/env bash
# One prepared run on a lent GPU machine (issue 35: the fused kernel), at most about 7 minutes:
#   1. the environment (jax, its devices, whether dampax imports and which engine "auto" takes);
#   2. benchmarks/gpu.py: the default engine beside the XLA engine, error maps, the peer
#      (first: the figures are what a session with a lent GPU is for);
#   3. the kernel's tests natively (tests/reference/test_kernel.py: the same solutions as the
#      XLA engine to 1e-12, its self-check, one launch under vmap, an error map).
# The machine's image has jax, equinox, diffrax, optax, optimistix, xarray, scipy (no internet),
# but neither nbmake nor the project's pytest options: dampax runs from src/ without
# installing, pytest with `-o addopts=`. Each step writes to $OUT as it goes (the device tool
# brings it back, also when the call runs past its limit).
#
#   bash benchmarks/gpu_session.sh          # on the device, from the repository's root
set -u
OUT=${OUT:-/tmp/dampax-gpu}
mkdir -p "$OUT"
export PYTHONPATH="$PWD/src:${PYTHONPATH:-}" PYTHONUNBUFFERED=1
PY=${PYTHON:-python3}
{
    nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm --format=csv 2>&1
    $PY - <<'PYEOF'
import importlib.metadata as md
def version(name):
    try:
        return md.version(name)
    except md.PackageNotFoundError:
        return None
print({n: version(n) for n in ("jax", "jaxlib", "equinox", "diffrax", "optimistix", "numpy",
                               "scipy", "triton")})
import time
a = time.perf_counter()
import jax
print("jax", jax.__version__, jax.devices())
import dampax as dp
from dampax._reference._solve import resolve_engine
print("dampax", dp.__version__, "auto ->", resolve_engine("auto"),
      f"(import and self-check {time.perf_counter() - a:.1f} s)")
PYEOF
} > "$OUT/env.txt" 2>&1
cat "$OUT/env.txt"
timeout "${GPU_BENCH_S:-270}" $PY benchmarks/gpu.py --n 4096 131072 --repeat 3 \
    --json "$OUT/gpu.json" 2>&1 | tee "$OUT/gpu.txt"
echo "gpu.py: rc=${PIPESTATUS[0]}" | tee -a "$OUT/env.txt"
timeout "${GPU_TESTS_S:-150}" $PY -m pytest -q -x -p no:cacheprovider -o addopts= -ra \
    tests/reference/test_kernel.py > "$OUT/kernel_tests.txt" 2>&1
echo "kernel tests: rc=$?" | tee -a "$OUT/env.txt"
tail -15 "$OUT/kernel_tests.txt"
