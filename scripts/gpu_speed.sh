#!/usr/bin/env bash
# The GPU rows of docs/benchmarks.md: builds the engine-only configuration (CMake option
# DOJO_ENGINE_ONLY) against the libtorch inside the machine's PyTorch package, then times the
# streaming student on the 2B architecture at 480x640 in bf16, batch 1, 4 hops, with random
# weights: the DiT alone, with the fast decoder and with the Wan decoder, at the released window
# (3) and at ours (12 + a 1-frame sink), each with the hops dispatched op by op (*_eager) and
# replayed as CUDA graphs (the default, when the build has them); and without inference mode.
# DOJO_SPEED_STEPS sets the timed steps per row (default 40).
#
#   scripts/gpu_speed.sh [OUT_DIR]
#
# Needs CMake, a C++17 compiler, python3 with a CUDA build of torch, and the headers of
# nlohmann-json and CLI11 (system-wide, or under the prefix named by DOJO_DEPS_PREFIX).
# Writes gpu.txt, build.log, speed.log, utilization.csv and one JSON report per run to OUT_DIR
# (default gpu_speed).
set -euo pipefail
out=${1:-gpu_speed}
steps=${DOJO_SPEED_STEPS:-40}
mkdir -p "$out"
out=$(cd "$out" && pwd)  # before leaving the caller's directory
cd "$(dirname "$0")/.."

{
  nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv,noheader || true
  python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)"
  c++ --version | head -1
  cmake --version | head -1
  nproc
} 2>&1 | tee "$out/gpu.txt"

torch_prefix=$(python3 -c "import torch.utils; print(torch.utils.cmake_prefix_path)")
generator=() keep_going=(-k)
if command -v ninja > /dev/null; then generator=(-G Ninja) keep_going=(-k 0); fi
build=build-engine
start=$(date +%s)
if ! cmake -S . -B "$build" "${generator[@]}" -DDOJO_ENGINE_ONLY=ON \
  -DCMAKE_PREFIX_PATH="$torch_prefix;${DOJO_DEPS_PREFIX:-}" > "$out/build.log" 2>&1; then
  tail -40 "$out/build.log"
  exit 1
fi
graphs=1
if ! cmake --build "$build" -j "$(nproc)" -- "${keep_going[@]}" >> "$out/build.log" 2>&1; then
  grep -E "error|Error" "$out/build.log" | head -80
  # Whatever failed, a build without CUDA graph capture (the one file that sees CUDA headers)
  # still gives the eager rows.
  echo "build failed; again without CUDA graphs (DOJO_CUDA_GRAPHS=OFF)"
  graphs=0
  cmake -S . -B "$build" -DDOJO_CUDA_GRAPHS=OFF >> "$out/build.log" 2>&1
  if ! cmake --build "$build" -j "$(nproc)" -- "${keep_going[@]}" >> "$out/build.log" 2>&1; then
    grep -E "error|Error" "$out/build.log" | tail -40
    exit 1
  fi
fi
echo "built in $(($(date +%s) - start)) s"
"$build/dojo" version | tee -a "$out/gpu.txt"

speed() {  # name, then `dojo wm speed` options
  local name=$1
  shift
  echo "== $name: $*"
  "$build/dojo" wm speed --arch student_2b --size 480x640 --device cuda --steps "$steps" \
    "$@" --json > "$out/$name.json" 2>> "$out/speed.log" || { tail -20 "$out/speed.log"; return 1; }
  python3 - "$out/$name.json" << 'EOF'
import json, sys
r = json.load(open(sys.argv[1]))
if r.get("cuda_graphs"):
    print(f'CUDA graphs: largest latent difference against eager {r["cuda_graphs_max_abs_diff"]:.3g}')
for row in r["rows"]:
    print(f'{row["decoder"]:>5}: {row["steady_frames_per_second"]:7.1f} frames/s  step p50 {row["step_ms_p50"]:7.1f} '
          f'p95 {row["step_ms_p95"]:7.1f} ms  denoise {row["denoise_ms_mean"]:6.1f} re-cache {row["recache_ms_mean"]:5.1f} '
          f'decode {row["decode_ms_mean"]:6.1f} ms  KV {row["kv_cache_mib"]:.0f} MiB  graph replays {row.get("cuda_graph_replays", 0)}')
EOF
}
# GPU load while the rows run: how much of the wall time the card is busy.
nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv -lms 500 > "$out/utilization.csv" &
monitor=$!
trap 'kill $monitor 2> /dev/null || true' EXIT
speed window3_eager --precision bf16 --window 3 --sink-frames 0 --decoders none fast wan --no-cuda-graphs
if [ $graphs = 1 ]; then
  speed window3 --precision bf16 --window 3 --sink-frames 0 --decoders none fast wan ||
    echo "(the CUDA graph rows failed: speed.log)"
fi
speed window12_sink1_eager --precision bf16 --window 12 --sink-frames 1 --decoders none fast --no-cuda-graphs
if [ $graphs = 1 ]; then
  speed window12_sink1 --precision bf16 --window 12 --sink-frames 1 --decoders none fast ||
    echo "(the CUDA graph rows failed: speed.log)"
fi
speed window3_no_inference_mode --precision bf16 --no-inference-mode --no-cuda-graphs --window 3 --sink-frames 0 \
  --decoders none
