#!/usr/bin/env bash
# The server under load (docs/benchmarks.md, "The server under load"): on loopback,
#   1. step sessions (policy round trips) at 8, 32 and 128 against the reference set's student,
#      with the session cap at 64: latency percentiles, sessions refused at the cap, memory;
#   2. study voters at 8, 32 and 128 against a study server (clips from DojoSim episodes):
#      votes/s, vote latency, busy answers (503, retried), memory;
#   3. a SIGKILL of the study server while 32 voters vote: every vote it acknowledged must be in
#      the database afterwards (votes lost = acknowledged answers - stored rows, must be <= 0), and
#      the restarted server must take votes again.
#   scripts/bench_serve_scale.sh [SECONDS_PER_ROW]     (default 20; DOJO: the binary; OUT: a
#                                                       directory to keep the JSON rows in)
set -euo pipefail
cd "$(dirname "$0")/.."
SECONDS_PER_ROW=${1:-20}
DOJO=${DOJO:-build/dojo}
TMP=$(mktemp -d)
OUT=${OUT:-$TMP/rows}
mkdir -p "$OUT"
SERVER=
trap '[ -n "$SERVER" ] && kill -9 $SERVER 2>/dev/null; rm -rf "$TMP"' EXIT

wait_up() {  # port, pid
  for _ in $(seq 900); do
    curl -sf "http://127.0.0.1:$1/health" > /dev/null && return 0
    kill -0 "$2" 2> /dev/null || return 1
    sleep 0.2
  done
  return 1
}
row() {  # label, then serve-load options; prints one JSON line and keeps it
  local label=$1
  shift
  $DOJO -q serve-load "$@" --json | tee "$OUT/$label.json" || true
}

echo "# machine: $(nproc) cores, $($DOJO version --json | tr -d '\n ' | head -c 200)"
echo "# 1. step sessions, reference student, cap 64, $SECONDS_PER_ROW s"
PORT=18801
$DOJO serve --port $PORT --max-sessions 64 --recordings "$TMP/rec" 2> "$TMP/serve.log" &
SERVER=$!
wait_up $PORT $SERVER || { cat "$TMP/serve.log"; exit 1; }
for n in 8 32 128; do
  row "step_$n" --port $PORT --mode step --sessions $n --seconds "$SECONDS_PER_ROW"
done
kill $SERVER
wait $SERVER 2> /dev/null || true

echo "# 2. study voters, $SECONDS_PER_ROW s"
$DOJO sim generate -o "$TMP/episodes" --episodes 4 --frames 16 --seed 5 -j 1 > /dev/null 2>&1
for e in 0 1 2 3; do
  mkdir -p "$TMP/clips/ep-$e"
  for name in truth a b; do cp "$TMP/episodes/episodes/00000$e/video.mp4" "$TMP/clips/ep-$e/$name.mp4"; done
done
$DOJO -q study create "$TMP/study" --videos "$TMP/clips" --models a b --name load > /dev/null
PORT=18802
start_study() {
  $DOJO serve --study "$TMP/study" --port $PORT 2>> "$TMP/study.log" &
  SERVER=$!
  wait_up $PORT $SERVER || { cat "$TMP/study.log"; exit 1; }
}
start_study
for n in 8 32 128; do
  row "study_$n" --port $PORT --mode study --sessions $n --seconds "$SECONDS_PER_ROW"
done

echo "# 3. SIGKILL during voting (32 voters)"
$DOJO -q study report "$TMP/study" --json "$TMP/before.json" > /dev/null
$DOJO -q serve-load --port $PORT --mode study --sessions 32 --seconds 30 --json > "$OUT/sigkill.json" &
LOADER=$!
sleep 5
kill -9 $SERVER
wait $SERVER 2> /dev/null || true
SERVER=
wait $LOADER || true
$DOJO -q study report "$TMP/study" --json "$TMP/after.json" > /dev/null
start_study
row "after_restart" --port $PORT --mode study --sessions 8 --seconds 5 > /dev/null
/usr/bin/env python3 - "$TMP/before.json" "$TMP/after.json" "$OUT/sigkill.json" "$OUT/after_restart.json" << 'PY'
import json, sys
before, after, kill, again = (json.load(open(p)) for p in sys.argv[1:])
stored = after["votes"] - before["votes"]
acked = kill["answers_acknowledged"]
print(json.dumps({"sigkill": {"answers_acknowledged": acked, "rows_stored": stored, "lost": max(0, acked - stored),
                              "voters_cut": kill["failed_sessions"]},
                  "after_restart_votes": again["votes_acknowledged"]}))
sys.exit(1 if acked > stored or again["votes_acknowledged"] == 0 else 0)
PY
kill $SERVER
wait $SERVER 2> /dev/null || true
SERVER=
