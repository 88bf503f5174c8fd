#!/usr/bin/env bash
# Builds the Parquet reader alone with clang + libFuzzer + ASan/UBSan and fuzzes it.
#   scripts/fuzz_parquet.sh [SECONDS]            fuzz (default 600 s; needs clang, libclang-rt-14-dev)
#   UPDATE_CORPUS=1 scripts/fuzz_parquet.sh S    also rewrite fuzz/corpus/seeds and merge the inputs
#                                                the fuzzer kept for coverage into fuzz/corpus/inputs
# The committed corpus (fuzz/corpus/) is replayed by the test suite (Parquet.Fuzz*): seeds/ must
# decode, inputs/ and crashers/ must decode or fail with dojo::Error. A crash is written to
# build-fuzz/crashes/; once fixed, copy it into fuzz/corpus/crashers/.
set -euo pipefail
cd "$(dirname "$0")/.."
SECONDS_TO_RUN="${1:-600}"
OUT=build-fuzz
rm -rf "$OUT/corpus" "$OUT/merged"
mkdir -p "$OUT/corpus" "$OUT/crashes" "$OUT/seeds" "$OUT/merged"
CXX="${CXX_FUZZ:-clang++}"
FLAGS=(-std=c++17 -O1 -g -fno-omit-frame-pointer -Isrc -Ifuzz)
SAN=(-fsanitize=fuzzer,address,undefined -fno-sanitize-recover=undefined)
# The reader is parquet.cpp (ParquetFile) + parquet_thrift.cpp (footer metadata) + parquet_decode.cpp (pages).
READER=(src/io/parquet.cpp src/io/parquet_thrift.cpp src/io/parquet_decode.cpp)
"$CXX" "${FLAGS[@]}" "${SAN[@]}" fuzz/parquet_fuzz.cpp "${READER[@]}" -lsnappy -lzstd -o "$OUT/parquet_fuzz"
"$CXX" "${FLAGS[@]}" -fsanitize=address fuzz/parquet_seeds.cpp "${READER[@]}" src/io/parquet_writer.cpp \
  src/core/atomic_file.cpp -lsnappy -lzstd -o "$OUT/parquet_seeds"
"$OUT/parquet_seeds" "$OUT/seeds"
cp "$OUT"/seeds/* "$OUT/corpus/"
for d in inputs crashers; do cp fuzz/corpus/$d/* "$OUT/corpus/" 2>/dev/null || true; done
# One process (-jobs 1): the fuzzer shares the machine.
"$OUT/parquet_fuzz" "$OUT/corpus" -max_total_time="$SECONDS_TO_RUN" -rss_limit_mb=2048 -max_len=65536 \
  -artifact_prefix="$OUT/crashes/" -print_final_stats=1 2>&1 | tee "$OUT/fuzz.log" |
  grep -E "^#[0-9]+ +(pulse|DONE|NEW)|ERROR|stat::" | tail -40
if [[ "${UPDATE_CORPUS:-0}" == 1 ]]; then
  # The smallest set of inputs that keeps the coverage the fuzzer reached, minus the seeds.
  "$OUT/parquet_fuzz" -merge=1 "$OUT/merged" "$OUT/corpus" >/dev/null 2>&1
  mkdir -p fuzz/corpus/seeds fuzz/corpus/inputs fuzz/corpus/crashers
  rm -f fuzz/corpus/seeds/* fuzz/corpus/inputs/*
  cp "$OUT"/seeds/* fuzz/corpus/seeds/
  # libFuzzer names corpus files by the SHA-1 of their content.
  seed_hashes=" $(sha1sum "$OUT"/seeds/* | cut -d' ' -f1 | tr '\n' ' ')"
  for f in "$OUT"/merged/*; do
    [[ "$seed_hashes" == *" $(basename "$f") "* ]] || cp "$f" fuzz/corpus/inputs/
  done
  echo "fuzz/corpus: $(ls fuzz/corpus/seeds | wc -l) seeds, $(ls fuzz/corpus/inputs | wc -l) inputs," \
       "$(ls fuzz/corpus/crashers | wc -l) crashers"
fi
