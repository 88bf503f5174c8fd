#!/usr/bin/env bash
# Server benchmarks (docs/benchmarks.md "Serving"): one `dojo serve` on loopback, then
#   dojo serve-load in step mode (policy round trips) and live mode (teleoperation), 1, 2 and 4
#   sessions; the browser's own view (frames/s, input-to-frame latency) through chromium.
#   scripts/bench_serve.sh [SECONDS]      default 15 s per row; models: the demo's if dojo_demo/
#                                         has them, else the reference set (teacher streamed as student)
set -euo pipefail
cd "$(dirname "$0")/.."
SECONDS_PER_ROW="${1:-15}"
DOJO=build/dojo
TMP=$(mktemp -d)
trap 'kill $SERVER 2>/dev/null || true; rm -rf "$TMP"' EXIT
if [[ -d dojo_demo/student/checkpoint ]]; then
  MODELS=(--demo dojo_demo --no-teacher)
else
  $DOJO sim generate -o "$TMP/robot" --episodes 3 --frames 32 --seed 3 -j 1 >/dev/null 2>&1
  MODELS=(--student models/reference/wm_posttrain --no-teacher --tokenizer models/reference/tokenizer
          --data "$TMP/robot" --split all)
fi
PORT=18765
$DOJO serve "${MODELS[@]}" --port $PORT --max-sessions 8 --recordings "$TMP/rec" 2>"$TMP/serve.log" &
SERVER=$!
for _ in $(seq 600); do  # up to 2 minutes for the models to load
  curl -sf http://127.0.0.1:$PORT/health >/dev/null && break
  kill -0 $SERVER 2>/dev/null || { echo "the server exited:"; cat "$TMP/serve.log"; exit 1; }
  sleep 0.2
done
curl -sf http://127.0.0.1:$PORT/health >/dev/null || { echo "the server did not load"; exit 1; }
echo "# models: ${MODELS[*]}"
for mode in step live; do
  for n in 1 2 4; do
    $DOJO serve-load --port $PORT --mode $mode --sessions $n --seconds "$SECONDS_PER_ROW" --json
  done
done
kill $SERVER; wait $SERVER 2>/dev/null || true
if command -v node >/dev/null && [[ -d tests/browser/node_modules/playwright-core ]]; then
  for n in 1 2 4; do
    DOJO_EXE=$DOJO node tests/browser/serve_browser_test.mjs --bench "$SECONDS_PER_ROW" --sessions $n | tail -1
  done
fi
