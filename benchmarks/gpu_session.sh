#!/usr/bin/env bash
# One prepared run on a lent GPU machine (issue 35: the fused kernel), about 6-8 minutes:
#   1. the environment (jax, its devices, whether dampax imports and which engine "auto" takes);
#   2. the kernel's tests natively (tests/reference/test_kernel.py: the same solutions as the
#      XLA engine to 1e-12, its self-check, one launch under vmap, an error map);
#   3. benchmarks/gpu.py: the default engine beside the XLA engine, error maps, the peer.
# The machine's image has jax, equinox, diffrax, optax, optimistix, xarray, scipy (no internet):
# dampax runs from src/ without installing. Results go to $OUT (the device tool brings it back).
#
#   bash benchmarks/gpu_session.sh          # on the device, from the repository's root
set -u
OUT=${OUT:-/tmp/dampax-gpu}
mkdir -p "$OUT"
export PYTHONPATH="$PWD/src:${PYTHONPATH:-}"
PY=${PYTHON:-python3}
{
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1
    $PY - <<'EOF'
import jax
print("jax", jax.__version__, jax.devices())
import dampax as dp
from dampax._reference._solve import resolve_engine
print("dampax", dp.__version__, "auto ->", resolve_engine("auto"))
EOF
} > "$OUT/env.txt" 2>&1
timeout 300 $PY -m pytest -q -x -p no:cacheprovider tests/reference/test_kernel.py \
    > "$OUT/kernel_tests.txt" 2>&1
echo "kernel tests: rc=$?" >> "$OUT/env.txt"
timeout 420 $PY benchmarks/gpu.py --n 4096 131072 --repeat 3 --json "$OUT/gpu.json" \
    > "$OUT/gpu.txt" 2>&1
echo "gpu.py: rc=$?" >> "$OUT/env.txt"
cat "$OUT/env.txt" "$OUT/gpu.txt"
tail -5 "$OUT/kernel_tests.txt"
