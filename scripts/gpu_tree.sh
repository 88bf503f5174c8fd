#!/usr/bin/env bash
# What a call to the GPU machine sends: the checkout's working tree (tracked and untracked,
# not-ignored files on disk) plus the folders it carries, at most 64 MiB together. The reference
# model set (models/reference, ~58 MB) alone puts this tree past that, and nothing built or run
# on the GPU machine reads it (the GPU scripts train, test and time their own models). So:
#
#   scripts/gpu_tree.sh slim [CARRIED ...]   move models/reference beside the checkout
#                                            (../.dojo_gpu_held/<checkout name>/), then print
#                                            what would travel, failing past 64 MiB
#   scripts/gpu_tree.sh size [CARRIED ...]   print what would travel, failing past 64 MiB
#   scripts/gpu_tree.sh restore              move it back (git status is clean again)
#   scripts/gpu_tree.sh check                what slim would leave to travel, moving nothing,
#                                            failing past 48 MiB: 16 left for the carried folders
#                                            (.deps and .gpu_data are 12); a CTest case, so the
#                                            tree cannot outgrow a GPU call unnoticed
#
# CARRIED: the ignored folders the call will name in `carry` (e.g. .deps .gpu_data). Between slim
# and restore git sees the set as deleted: restore before committing.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD
held=$(dirname "$root")/.dojo_gpu_held/$(basename "$root")
limit=$((64 * 1024 * 1024))
moved=(models/reference)
excluded=""  # check: a grep pattern of the paths slim would move

size() {
  local total bytes
  # Files on disk that git tracks or would track (a tracked file moved away is not sent).
  total=$(git ls-files -z --cached --others --exclude-standard | { grep -zv "${excluded:-^$}" || true; } |
          { xargs -0 stat -c '%F %s' 2>/dev/null || true; } | awk '$1 == "regular" {n += $NF} END {print n + 0}')
  for dir in "$@"; do
    [[ -e $dir ]] || { echo "gpu_tree: $dir: no such folder to carry" >&2; exit 2; }
    bytes=$(du -sb "$dir" | cut -f1)
    total=$((total + bytes))
    echo "carried $dir: $((bytes / 1024)) KiB"
  done
  echo "would travel: $((total / 1024 / 1024)) MiB of $((limit / 1024 / 1024)) MiB"
  ((total <= limit)) || { echo "gpu_tree: over $((limit / 1024 / 1024)) MiB: the call would be refused" >&2; exit 1; }
}

case "${1:-}" in
  slim)
    shift
    [[ ! -e $held ]] || { echo "gpu_tree: $held exists: run 'scripts/gpu_tree.sh restore' first" >&2; exit 2; }
    for path in "${moved[@]}"; do
      [[ -z $(git status --porcelain -- "$path") ]] ||
        { echo "gpu_tree: $path has uncommitted changes: commit or stash them first" >&2; exit 2; }
      mkdir -p "$held/$(dirname "$path")"
      mv "$path" "$held/$path"
      echo "moved $path -> $held/$path"
    done
    size "$@"
    ;;
  size)
    shift
    size "$@"
    ;;
  check)
    shift
    limit=$((48 * 1024 * 1024))
    excluded=$(printf '^%s/\\|' "${moved[@]}")
    excluded=${excluded%\\|}
    size "$@"
    ;;
  restore)
    [[ -e $held ]] || { echo "gpu_tree: nothing held in $held" >&2; exit 2; }
    for path in "${moved[@]}"; do
      [[ ! -e $path ]] || { echo "gpu_tree: $path exists again; $held/$path left where it is" >&2; exit 2; }
      mv "$held/$path" "$path"
      echo "restored $path"
    done
    rm -rf "$held"
    [[ -z $(git status --porcelain -- "${moved[@]}") ]] || { echo "gpu_tree: the restored set differs from git's" >&2; exit 1; }
    ;;
  *)
    echo "usage: scripts/gpu_tree.sh slim [CARRIED ...] | size [CARRIED ...] | restore" >&2
    exit 2
    ;;
esac
