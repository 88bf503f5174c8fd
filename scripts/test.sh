#!/usr/bin/env bash
# Builds (incrementally) and runs the whole test suite through CTest.
#   scripts/test.sh              all tests
#   scripts/test.sh -R Video     CTest arguments pass through
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ ! -f build/build.ninja ]]; then
  cmake -S . -B build -G Ninja -DCMAKE_BUILD_TYPE=Release
fi
cmake --build build -j "${JOBS:-$(nproc)}"
cd build
ctest --output-on-failure --timeout 900 -j "${JOBS:-$(nproc)}" "$@"
