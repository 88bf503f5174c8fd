#!/usr/bin/env bash
# Builds the Parquet reader alone with clang + libFuzzer + ASan/UBSan and fuzzes it.
#   scripts/fuzz_parquet.sh [SECONDS]      (default 600; needs clang and libclang-rt-14-dev)
# Crashes are written to build-fuzz/crashes/; copy a fixed one to fuzz/regressions/ so that
# ParquetFuzzRegressions replays it in the normal test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
SECONDS_TO_RUN="${1:-600}"
OUT=build-fuzz
mkdir -p "$OUT/corpus" "$OUT/crashes"
CXX="${CXX_FUZZ:-clang++}"
FLAGS=(-std=c++17 -O1 -g -fno-omit-frame-pointer -Isrc)
SAN=(-fsanitize=fuzzer,address,undefined -fno-sanitize-recover=undefined)
# The reader is parquet.cpp (ParquetFile) + parquet_thrift.cpp (footer metadata) + parquet_decode.cpp (pages).
READER=(src/io/parquet.cpp src/io/parquet_thrift.cpp src/io/parquet_decode.cpp)
"$CXX" "${FLAGS[@]}" "${SAN[@]}" fuzz/parquet_fuzz.cpp "${READER[@]}" -lsnappy -lzstd -o "$OUT/parquet_fuzz"
"$CXX" "${FLAGS[@]}" -fsanitize=address fuzz/parquet_seeds.cpp "${READER[@]}" src/io/parquet_writer.cpp \
  src/core/atomic_file.cpp -lsnappy -lzstd -o "$OUT/parquet_seeds"
"$OUT/parquet_seeds" "$OUT/corpus"
cp fuzz/regressions/* "$OUT/corpus/" 2>/dev/null || true
# One process (-jobs 1): the fuzzer shares the machine.
"$OUT/parquet_fuzz" "$OUT/corpus" -max_total_time="$SECONDS_TO_RUN" -rss_limit_mb=2048 -max_len=65536 \
  -artifact_prefix="$OUT/crashes/" -print_final_stats=1 2>&1 | tee "$OUT/fuzz.log" | grep -E "^#[0-9]+ +(pulse|DONE|NEW)|ERROR|stat::" | tail -40
