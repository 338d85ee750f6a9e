#!/usr/bin/env bash
# How a plan scales with this machine's cores, and how far the cores themselves scale.
#
#   bench/cores/scaling.sh [PLANNER] [TASK]      (defaults: target/release/planner-service, halfcheetah)
#
# 1. The cores alone: the same `bench plan --threads 1` in N independent processes at once, each
#    pinned to its own core (taskset), for N = 1, 2, 4, ... up to the cores: no process waits for
#    another, so the plans per second of all of them together is what the cores deliver.
# 2. The planner's threads: `bench plan --threads T` for the same T, with the default chunks and
#    with one chunk per thread (`--chunks T`), in turns.
# Prints each cell's median ms per plan; a benchmark, it asserts nothing. Needs `taskset`
# (util-linux). Run it on an otherwise idle machine: other load makes cores unequal too.
set -euo pipefail
P=${1:-target/release/planner-service}
TASK=${2:-halfcheetah}
CORES=$(nproc)
CALLS=${CALLS:-6}
counts=()
for ((n = 1; n <= CORES; n *= 2)); do counts+=("$n"); done
((counts[-1] == CORES)) || counts+=("$CORES")
median() { tr -s ' ' | grep -oE 'per call [0-9.]+ ms median' | grep -oE '[0-9.]+' | head -1; }
echo "$(date -u '+%F %H:%M UTC'), $(lscpu | grep -m1 'Model name' | sed 's/.*: *//'), $CORES logical CPUs, $("$P" --version)"
echo "task $TASK + DEEN, CEM at Table 2's sizes, $CALLS timed calls after 1 warm-up per cell"
echo
echo "1. N one-thread processes at once, one per core"
for n in "${counts[@]}"; do
  dir=$(mktemp -d)
  pids=()
  for ((i = 0; i < n; i++)); do
    taskset -c "$i" "$P" bench plan --task "$TASK" --regularizer deen --threads 1 \
      --iterations-to-time "$CALLS" --warmup 1 > "$dir/$i.txt" 2>&1 &
    pids+=("$!")
  done
  wait "${pids[@]}"
  ms=$(for ((i = 0; i < n; i++)); do median < "$dir/$i.txt"; done)
  rate=$(awk '{s += 1000 / $1} END {printf "%.2f", s}' <<< "$ms")
  echo "   $n processes: $(tr '\n' ' ' <<< "$ms")ms per plan; together $rate plans/s"
  rm -r "$dir"
done
echo
echo "2. one process, T threads: default chunks / one chunk per thread (median ms per plan)"
for t in "${counts[@]}"; do
  d=$("$P" bench plan --task "$TASK" --regularizer deen --threads "$t" \
    --iterations-to-time "$CALLS" --warmup 1 2>&1 | median)
  o=$("$P" bench plan --task "$TASK" --regularizer deen --threads "$t" --chunks "$t" \
    --iterations-to-time "$CALLS" --warmup 1 2>&1 | median)
  echo "   $t threads: $d / $o"
done
