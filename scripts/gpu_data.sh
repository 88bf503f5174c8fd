#!/usr/bin/env bash
# The datasets scripts/gpu_train_reference.sh trains on, made here (DojoSim needs MuJoCo, which
# GPU machines lack): the demo's four sets (`dojo demo`'s episodes, splits and seeds: human 32,
# robot 40 with 8 held out, ood-objects 8, counterfactual 8; 64 frames) in raw frames
# (--video-format raw), each packed as DIR/<name>.tgz (about 2.5 MB a set at 64x64: flat renders
# compress ~13x). Carry DIR with the tree.
#
#   scripts/gpu_data.sh [DIR=.gpu_data]     (DOJO_GPU_SIZE=HxW, default 64x64; DOJO=build/dojo)
set -euo pipefail
dir=${1:-.gpu_data}
size=${DOJO_GPU_SIZE:-64x64}
dojo=${DOJO:-build/dojo}
mkdir -p "$dir"
dir=$(cd "$dir" && pwd)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
generate() {  # name embodiment split episodes seed [val_fraction]
  "$dojo" --quiet sim generate -o "$work/$1" --embodiment "$2" --split "$3" -n "$4" --seed "$5" \
    --val-fraction "${6:-0}" --frames 64 --size "$size" --video-format raw > /dev/null
  tar -C "$work" -czf "$dir/$1.tgz" "$1"
}
generate human human train 32 0
generate robot robot train 40 1 0.2
generate robot_ood_objects robot ood-objects 8 2
generate robot_counterfactual robot counterfactual 8 3
ls -l "$dir"
