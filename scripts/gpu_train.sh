#!/usr/bin/env bash
# The trainers on a GPU machine: builds the configuration without media libraries (CMake option
# DOJO_WITH_MEDIA=OFF: no FFmpeg, JPEG, HDF5, DojoSim or server; datasets of raw frames) against
# the libtorch inside the machine's PyTorch package, then runs the tests of the trainers and the
# engine there, the *_CUDA ones among them (each trainer on --device cuda against the CPU, and in
# bf16). Anyone with a CUDA GPU, CMake, a C++17 compiler and python3 with a CUDA torch can run it.
#
#   scripts/gpu_train.sh [OUT_DIR]
#
# Headers and libraries the machine lacks: DOJO_DEPS_PREFIX (nlohmann-json, CLI11, snappy, zstd)
# and DOJO_GTEST_SOURCE_DIR (GoogleTest's sources), as scripts/gpu_deps.sh unpacks them. Writes
# gpu.txt, build.log, tests.log and tests.xml to OUT_DIR (default gpu_train). Exits non-zero when
# the build or a test fails, or when no GPU test ran. DOJO_TEST_FILTER narrows the tests (a
# GoogleTest filter; default: all of this build's); DOJO_SKIP_TESTS=1 builds only.
set -euo pipefail
out=${1:-gpu_train}
mkdir -p "$out"
out=$(cd "$out" && pwd)  # before leaving the caller's directory
cd "$(dirname "$0")/.."
source scripts/gpu_common.sh

gpu_facts "$out"
build=${DOJO_BUILD_DIR:-build-train}
tests=ON  # the build alone needs no GoogleTest
if [[ ${DOJO_SKIP_TESTS:-0} == 1 ]]; then tests=OFF; fi
gpu_build "$out" "$build" -DCMAKE_BUILD_TYPE=Release -DDOJO_WITH_MEDIA=OFF -DDOJO_UNITY_BUILD=ON \
  -DDOJO_BUILD_TESTS=$tests -DDOJO_GTEST_SOURCE_DIR="${DOJO_GTEST_SOURCE_DIR:-}"
if [[ ${DOJO_SKIP_TESTS:-0} == 1 ]]; then exit 0; fi  # the build alone (gpu_train_reference.sh)

status=0
"$build/dojo_tests" --gtest_filter="${DOJO_TEST_FILTER:-*}" --gtest_output="xml:$out/tests.xml" \
  > "$out/tests.log" 2>&1 || status=$?
grep -E "^\[  (PASSED|FAILED|SKIPPED) " "$out/tests.log" || true
grep -E "_CUDA" "$out/tests.log" | grep -E "OK|FAILED|SKIPPED" || true
tail -3 "$out/tests.log"
if ! grep -qE "^\[       OK \] .*_CUDA" "$out/tests.log"; then
  echo "no GPU test ran (no CUDA device, or a libtorch without CUDA)"
  status=1
fi
exit $status
