#!/usr/bin/env bash
# The engine's tests on a GPU machine: builds the engine-only configuration with its tests
# (CMake options DOJO_ENGINE_ONLY and DOJO_ENGINE_TESTS: tests/{core,models,diffusion,infer}, the
# *_CUDA ones included) against the libtorch inside the machine's PyTorch package, then runs them.
# The full suite needs the video, data, simulator and server libraries, which such machines often
# lack; these tests need only libtorch, nlohmann-json, CLI11 and GoogleTest.
#
#   scripts/gpu_tests.sh [OUT_DIR]
#
# GoogleTest comes from find_package, or is built from the sources named by DOJO_GTEST_SOURCE_DIR
# (e.g. a copy of Debian's /usr/src/googletest); nlohmann-json and CLI11 system-wide or under
# DOJO_DEPS_PREFIX. Writes gpu.txt, build.log, tests.log and tests.xml (GoogleTest's report) to
# OUT_DIR (default gpu_tests). Exits non-zero when the build or a test fails, or when no GPU test
# ran (a *_CUDA test skips itself when the libtorch sees no GPU or the build has no CUDA graphs).
set -euo pipefail
out=${1:-gpu_tests}
mkdir -p "$out"
out=$(cd "$out" && pwd)  # before leaving the caller's directory
cd "$(dirname "$0")/.."
source scripts/gpu_common.sh

gpu_facts "$out"
build=build-engine-tests
gpu_build "$out" "$build" -DDOJO_ENGINE_ONLY=ON -DDOJO_ENGINE_TESTS=ON \
  -DDOJO_GTEST_SOURCE_DIR="${DOJO_GTEST_SOURCE_DIR:-}"

status=0
"$build/dojo_engine_tests" --gtest_output="xml:$out/tests.xml" > "$out/tests.log" 2>&1 || status=$?
grep -E "^\[  (PASSED|FAILED|SKIPPED) " "$out/tests.log" || true
grep -E "_CUDA" "$out/tests.log" | grep -E "OK|FAILED|SKIPPED" || true
tail -3 "$out/tests.log"
if grep -qE "^\[  SKIPPED \] .*_CUDA" "$out/tests.log"; then
  grep -B2 -E "^\[  SKIPPED \] .*_CUDA" "$out/tests.log" | head -20
  echo "a GPU test skipped itself (its reason above)"
  status=1
fi
exit $status
