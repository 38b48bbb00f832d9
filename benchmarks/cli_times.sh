#!/usr/bin/env bash
# First and repeated wall time of every dampax command, with a fresh compilation cache:
#     bash benchmarks/cli_times.sh            (from the repository root, dampax installed)
# The first call of each command compiles (and writes the cache); the second re-uses it.
set -euo pipefail
cache=$(mktemp -d); out=$(mktemp -d)
export DAMPAX_CACHE_DIR="$cache"
run() {
  local label=$1; shift
  local times=()
  for _ in 1 2; do
    local start=$(date +%s.%N)
    (cd "$out" && dampax "$@" >/dev/null 2>&1)
    times+=("$(echo "$(date +%s.%N) - $start" | bc)")
  done
  printf '| `dampax %s` | %.1f s | %.1f s | %.2f |\n' "$label" "${times[0]}" "${times[1]}" \
    "$(echo "${times[1]} / ${times[0]}" | bc -l)"
}
echo "| command | first run | repeated | repeated / first |"
echo "|---|---|---|---|"
run "errormap --quick" errormap --quick --no-progress --out q
run "errormap" errormap --no-progress --out full
run "solve --mu 0.0288 --D 2.95" solve --mu 0.0288 --D 2.95
run "fit --example" fit --example
run "sensitivity --mu 0.0288 --D 2.95" sensitivity --mu 0.0288 --D 2.95
rm -rf "$cache" "$out"
