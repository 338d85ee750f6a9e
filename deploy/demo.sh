#!/usr/bin/env bash
# `make demo`: learn a task from scratch with both processes on loopback.
#
# Starts the planner daemon in the background (listening on a free loopback port, multicast
# scouting off), runs one sim-bridge in the foreground that connects to it, prints the return
# of every episode, and stops the daemon cleanly (SIGTERM) however the demo ends.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BIN="${BIN:-$ROOT/target/release}"
TASK="${TASK:-cartpole}"
EPISODES="${EPISODES:-10}"
SEED="${SEED:-0}"
METHOD="${METHOD:-cem+deen}"
STAMP="$(date +%Y%m%d-%H%M%S)"
DATA="$ROOT/var/demo/$STAMP"
RUN="demo-$TASK-s$SEED-$STAMP"
mkdir -p "$DATA"

PORT="$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])' 2>/dev/null || echo 17447)"
ENDPOINT="tcp/127.0.0.1:$PORT"

"$BIN/planner-service" serve --listen "$ENDPOINT" --data-dir "$DATA" --planner-id demo >"$DATA/planner.log" 2>&1 &
PLANNER=$!
stop_planner() {
    if kill -0 "$PLANNER" 2>/dev/null; then
        kill -TERM "$PLANNER" 2>/dev/null || true
        wait "$PLANNER" 2>/dev/null || true
    fi
}
trap stop_planner EXIT INT TERM

echo "planner daemon (pid $PLANNER) on $ENDPOINT; log: $DATA/planner.log"
echo "learning $TASK from scratch with $METHOD for $EPISODES episodes (seed $SEED)"
"$BIN/sim-bridge" run --task "$TASK" --run "$RUN" --agent bridge-0 --episodes "$EPISODES" --seed "$SEED" \
    --preset "$METHOD" --connect "$ENDPOINT" --out "$DATA/episodes.csv"
echo
echo "episode returns ($DATA/episodes.csv):"
column -s, -t <"$DATA/episodes.csv" 2>/dev/null || cat "$DATA/episodes.csv"
