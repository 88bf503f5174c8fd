#!/usr/bin/env bash
# Builds the checkpoint readers (ZIP, pickle, torch.save) with clang + libFuzzer + ASan/UBSan and
# fuzzes them.
#   scripts/fuzz_torch_file.sh [SECONDS]           fuzz (default 600 s; needs clang, libclang-rt-14-dev)
#   UPDATE_CORPUS=1 scripts/fuzz_torch_file.sh S   also merge the inputs the fuzzer kept for coverage
#                                                  into fuzz/corpus/torch_file/inputs
# The committed corpus (fuzz/corpus/torch_file/) is replayed by the test suite
# (TorchFile.FuzzCorpusReadsOrFailsCleanly): every input must read or fail with dojo::Error.
# A crash is written to build-fuzz-torch/crashes/; once fixed, copy it into .../crashers/.
set -euo pipefail
cd "$(dirname "$0")/.."
SECONDS_TO_RUN="${1:-600}"
OUT=build-fuzz-torch
rm -rf "$OUT/corpus" "$OUT/merged"
mkdir -p "$OUT/corpus" "$OUT/crashes" "$OUT/merged"
CXX="${CXX_FUZZ:-clang++}"
TORCH_INCLUDE=(-I/usr/include/torch/csrc/api/include)
FLAGS=(-std=c++17 -O1 -g -fno-omit-frame-pointer -D_GLIBCXX_USE_CXX11_ABI=1 -Isrc -Ifuzz "${TORCH_INCLUDE[@]}")
SAN=(-fsanitize=fuzzer,address,undefined -fno-sanitize-recover=undefined)
READER=(src/core/zip_archive.cpp src/core/pickle.cpp src/core/torch_file.cpp src/core/mapped_file.cpp)
"$CXX" "${FLAGS[@]}" "${SAN[@]}" fuzz/torch_file_fuzz.cpp "${READER[@]}" -ltorch -ltorch_cpu -lc10 \
  -o "$OUT/torch_file_fuzz"
for d in seeds inputs crashers; do cp fuzz/corpus/torch_file/$d/* "$OUT/corpus/" 2>/dev/null || true; done
"$OUT/torch_file_fuzz" "$OUT/corpus" -max_total_time="$SECONDS_TO_RUN" -rss_limit_mb=2048 -max_len=131072 \
  -artifact_prefix="$OUT/crashes/" -print_final_stats=1 2>&1 | tee "$OUT/fuzz.log" |
  grep -E "^#[0-9]+ +(pulse|DONE|NEW)|ERROR|stat::" | tail -40
if [[ "${UPDATE_CORPUS:-0}" == 1 ]]; then
  "$OUT/torch_file_fuzz" -merge=1 "$OUT/merged" "$OUT/corpus" >/dev/null 2>&1
  mkdir -p fuzz/corpus/torch_file/inputs
  rm -f fuzz/corpus/torch_file/inputs/*
  seed_hashes=" $(sha1sum fuzz/corpus/torch_file/seeds/* | cut -d' ' -f1 | tr '\n' ' ')"
  for f in "$OUT"/merged/*; do
    [[ "$seed_hashes" == *" $(basename "$f") "* ]] || cp "$f" fuzz/corpus/torch_file/inputs/
  done
  echo "fuzz/corpus/torch_file: $(ls fuzz/corpus/torch_file/seeds | wc -l) seeds, $(ls fuzz/corpus/torch_file/inputs | wc -l) inputs"
fi
