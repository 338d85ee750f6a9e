#!/bin/sh
# The paper's Figure 4 grid (issue #13), at the paper's sizes, with `ebmpc-experiment
# experiment`: every task's methods and episode counts as the issue lists them.
#
#   experiments/figure4.sh            # builds release binaries once, copies them aside, runs
#   nohup experiments/figure4.sh &    # the same in the background; re-run to resume
#
# The release binaries are copied to $BIN on the first call and used from there on, so a later
# rebuild of the tree cannot change an experiment half-way. Every experiment folder resumes:
# finished runs are skipped and half-finished ones continue from their stored replay buffer and
# newest checkpoint (see experiments/src/launcher.rs for what a resume does not reproduce
# exactly). Knobs: OUT (results/figure4), BIN ($OUT/bin), SEEDS (5), JOBS (2).
set -eu
ROOT=$(cd "$(dirname "$0")/.." && pwd)
OUT=${OUT:-$ROOT/results/figure4}
BIN=${BIN:-$OUT/bin}
SEEDS=${SEEDS:-5}
JOBS=${JOBS:-2}

if [ ! -x "$BIN/ebmpc-experiment" ]; then
    (cd "$ROOT" && cargo build --release --bins)
    mkdir -p "$BIN"
    for b in planner-service sim-bridge ebmpc-experiment; do
        cp "$ROOT/target/release/$b" "$BIN/$b"
    done
    (cd "$ROOT" && git rev-parse HEAD) > "$BIN/COMMIT"
fi

run() {
    task=$1 episodes=$2 methods=$3
    echo "== $task: $methods, $SEEDS seeds x $episodes episodes ($(date -u +%FT%TZ))"
    "$BIN/ebmpc-experiment" experiment --task "$task" --methods "$methods" --scale paper \
        --seeds "$SEEDS" --episodes "$episodes" --jobs "$JOBS" --out "$OUT/$task" --bin-dir "$BIN"
}

run cartpole 15 cem,cem+dae,cem+deen,pets,adam+dae
run reacher3d 15 cem,cem+dae,cem+deen,pets
run pusher 15 cem,cem+dae,cem+deen,pets
run ant 10 cem,cem+dae,cem+deen
run halfcheetah 20 cem,cem+dae,cem+deen,adam+dae,pets
