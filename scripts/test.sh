#!/usr/bin/env bash
# Builds (incrementally) and runs the whole test suite through CTest.
#   scripts/test.sh              all tests
#   scripts/test.sh -R Video     CTest arguments pass through
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ ! -f build/build.ninja ]]; then
  cmake -S . -B build -G Ninja -DCMAKE_BUILD_TYPE=Release -DDOJO_UNITY_BUILD=ON
fi
cmake --build build -j "${JOBS:-$(nproc)}"
# A fresh build directory has no record of how long each test takes, so CTest would start them in
# the order they were declared and the longest could start last. Seed its record from
# tests/test_costs.txt (seconds on 2 cores) so those start first; CTest keeps it up to date.
costs=build/Testing/Temporary/CTestCostData.txt
if [[ ! -f $costs ]]; then
  mkdir -p "$(dirname "$costs")"
  { awk '!/^#/ && NF == 2 { print $1, 1, $2 }' tests/test_costs.txt; echo ---; } >"$costs"
fi
cd build
ctest --output-on-failure --timeout 900 -j "${JOBS:-$(nproc)}" "$@"
