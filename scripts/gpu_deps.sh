#!/usr/bin/env bash
# What a bare GPU machine (a compiler, CMake and PyTorch, no package registry) lacks to build the
# trainers without media (scripts/gpu_train.sh) and the engine's tests (scripts/gpu_tests.sh):
# the headers of nlohmann-json and CLI11, GoogleTest's sources, snappy and zstd (Parquet pages).
# Run here, on Debian 12 with apt: downloads those Debian packages and unpacks them (dpkg -x) into
# DIR (default .deps, git-ignored), about 5 MB; carry DIR with the tree and point the scripts at
# it with DOJO_DEPS_PREFIX=DIR/usr DOJO_GTEST_SOURCE_DIR=DIR/usr/src/googletest.
#
#   scripts/gpu_deps.sh [DIR]
set -euo pipefail
dir=${1:-.deps}
mkdir -p "$dir"
dir=$(cd "$dir" && pwd)
packages=(nlohmann-json3-dev libcli11-dev googletest libsnappy-dev libsnappy1v5 libzstd-dev libzstd1)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
(cd "$work" && apt-get -o APT::Sandbox::User=root download "${packages[@]}" > /dev/null)
for deb in "$work"/*.deb; do dpkg -x "$deb" "$dir"; done
# The unpacked development symlinks point at the runtime libraries beside them; nothing else
# from the packages is needed.
rm -rf "$dir/usr/share/doc" "$dir/usr/share/man"
find "$dir" -name '*.a' -delete  # linked as shared libraries
du -sh "$dir"
