# Shared by the scripts that build on a GPU machine (sourced, not run): the machine's facts and the
# build against the libtorch inside its PyTorch package.

# gpu_facts OUT_DIR: the GPU, torch, compiler and cores, on the terminal and into OUT_DIR/gpu.txt.
gpu_facts() {
  {
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
    python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)" || true
    c++ --version | head -1
    nproc
  } 2>&1 | tee "$1/gpu.txt"
}

# gpu_build OUT_DIR BUILD_DIR CMAKE_ARGS...: configures BUILD_DIR (ninja when present) with the
# machine's libtorch (or DOJO_TORCH_PREFIX) and DOJO_DEPS_PREFIX, builds it on every core, logs
# into OUT_DIR/build.log; on failure prints the errors and exits. Records the time and `dojo
# version` in OUT_DIR/gpu.txt.
gpu_build() {
  local out=$1 build=$2
  shift 2
  local torch_prefix generator=() start
  torch_prefix=${DOJO_TORCH_PREFIX:-$(python3 -c "import torch.utils; print(torch.utils.cmake_prefix_path)")}
  if command -v ninja > /dev/null; then generator=(-G Ninja); fi
  start=$(date +%s)
  if ! cmake -S . -B "$build" "${generator[@]}" "$@" \
    -DCMAKE_PREFIX_PATH="$torch_prefix;${DOJO_DEPS_PREFIX:-}" > "$out/build.log" 2>&1; then
    tail -40 "$out/build.log"
    exit 1
  fi
  if ! cmake --build "$build" -j "$(nproc)" >> "$out/build.log" 2>&1; then
    grep -E "error|Error" "$out/build.log" | head -60
    exit 1
  fi
  echo "built in $(($(date +%s) - start)) s" | tee -a "$out/gpu.txt"
  "$build/dojo" version | tee -a "$out/gpu.txt"
}
