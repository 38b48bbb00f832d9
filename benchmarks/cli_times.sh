#!/usr/bin/env bash
# Wall time of the dampax commands of issue 26 against its latency targets: the first run with
# a fresh cache (it compiles and fills the cache) and repeated runs (the cache warm; the median
# of REPEATS runs). From the repository root, dampax installed:
#     bash benchmarks/cli_times.sh                      (REPEATS=3 by default)
#     DAMPAX="python -m dampax_cli" REPEATS=5 bash benchmarks/cli_times.sh
# The targets are those of a 2-core machine with nothing else running; the load average
# (uptime) is printed before and after, since other work on the machine inflates every time.
set -euo pipefail
dampax=${DAMPAX:-dampax}
repeats=${REPEATS:-3}
cache=$(mktemp -d)
out=$(mktemp -d)
trap 'rm -rf "$cache" "$out"' EXIT
export DAMPAX_CACHE_DIR="$cache"  # a fresh cache: the first run of each command compiles

seconds() {  # wall seconds of one run of dampax with these arguments (in $out, quiet)
  local start end
  start=$(date +%s.%N)
  (cd "$out" && $dampax "$@" >/dev/null 2>&1) || echo "dampax $* failed" >&2
  end=$(date +%s.%N)
  echo "$end - $start" | bc -l
}

row() {  # row LABEL FIRST_TARGET REPEATED_TARGET ARGS...
  local label=$1 first_target=$2 repeat_target=$3
  shift 3
  local first times=() median
  first=$(seconds "$@")
  for ((i = 0; i < repeats; i++)); do times+=("$(seconds "$@")"); done
  median=$(printf '%s\n' "${times[@]}" | sort -g | awk '{a[NR] = $1} END {print a[int((NR + 1) / 2)]}')
  printf '| `dampax %s` | %.1f s | <= %s s | %.2f s | <= %s s |\n' "$label" "$first" \
    "$first_target" "$median" "$repeat_target"
}

echo "load before: $(uptime | sed 's/.*load average: //') (1, 5, 15 min); $(nproc) cores"
echo
echo "| command | first run (fresh cache) | target | repeated (median of $repeats) | target |"
echo "|---|---|---|---|---|"
row "--version" "-" 0.3 --version
row "--help" "-" 0.3 --help
row "errormap --quick" 31.5 3 errormap --quick --out quick
row "solve" 10.5 2 solve
row "fit --example" 22.5 3 fit --example --out fit
row "sensitivity" 18.5 3 sensitivity
echo
echo "load after: $(uptime | sed 's/.*load average: //')"
