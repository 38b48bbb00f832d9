#!/usr/bin/env bash
# One prepared run on a lent GPU machine (issue 35 item 2: where the fused kernel's time goes),
# at most about 7 minutes:
#   1. the environment (jax, its devices, ptxas, ncu);
#   2. benchmarks/gpu_kernel.py at 4,096 and 131,072 trajectories, every variant and the XLA
#      engine;
#   3. where ncu is present and allowed: its counters on one launch of the kernel without rows.
# dampax runs from src/ under the image's packages (see benchmarks/gpu_session.sh).
#
#   bash benchmarks/gpu_kernel_session.sh          # on the device, from the repository's root
set -u
OUT=${OUT:-/tmp/dampax-gpu}
mkdir -p "$OUT"
export PYTHONPATH="$PWD/src:$PWD/benchmarks:${PYTHONPATH:-}" PYTHONUNBUFFERED=1
PY=${PYTHON:-python3}
{
    nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv 2>&1
    $PY -c "import jax, jaxlib; print('jax', jax.__version__, jax.devices())" 2>&1
    echo "ncu: $(command -v ncu || echo none)  nsys: $(command -v nsys || echo none)"
} > "$OUT/env.txt" 2>&1
cat "$OUT/env.txt"
timeout "${GPU_KERNEL_S:-300}" $PY benchmarks/gpu_kernel.py --n 4096 131072 --repeat 3 \
    --json "$OUT/kernel.json" 2>&1 | tee "$OUT/kernel.txt"
echo "gpu_kernel.py: rc=${PIPESTATUS[0]}" | tee -a "$OUT/env.txt"
if command -v ncu >/dev/null; then
    timeout "${GPU_NCU_S:-100}" ncu --target-processes all -k regex:kernel --launch-count 1 \
        --section SpeedOfLight --section MemoryWorkloadAnalysis --section LaunchStats \
        --section Occupancy --section WarpStateStats \
        --metrics l1tex__t_bytes_pipe_lsu_mem_local_op_ld.sum,l1tex__t_bytes_pipe_lsu_mem_local_op_st.sum,smsp__inst_executed.sum,smsp__sass_thread_inst_executed_op_dfma_pred_on.sum \
        $PY benchmarks/gpu_kernel.py --n 4096 --variants norows-b32-spp2 --repeat 0 \
        > "$OUT/ncu.txt" 2>&1
    echo "ncu: rc=$?" | tee -a "$OUT/env.txt"
    tail -80 "$OUT/ncu.txt"
fi
