#!/usr/bin/env bash
# The reference model set trained on a GPU: builds the trainers without media libraries
# (scripts/gpu_train.sh's configuration), unpacks the datasets scripts/gpu_data.sh made
# (DOJO_GPU_DATA, default .gpu_data), then trains scripts/train_reference.sh's recipe there: LAM,
# tokenizer, keypoint probe, world model (pretrain on human video with latent actions, post-train
# on robot actions), the student (4-chunk warm-up, Self-Forcing) and its fast decoder; exports them
# in bf16 and scores teacher and student on the three robot splits. Every trainer runs with
# --device / --precision (DOJO_DEVICE, default cuda; DOJO_PRECISION, default bf16). Step counts are
# the CPU recipe's (DOJO_STEPS_SCALE, a whole number, multiplies them); DOJO_REF_QUICK=1 runs 3 steps a stage and
# 2 episodes a split, to check the script itself on any machine.
#
#   scripts/gpu_train_reference.sh [OUT_DIR=gpu_reference]
#
# Writes to OUT_DIR (8 files): gpu.txt, build.log, train.log, stages.tsv (seconds per stage),
# reference.tgz.part-aa.. (the exported set, ~40 MB in 15 MiB parts) and evals.tgz (each
# evaluation's metrics.json and .md).
set -euo pipefail
out=${1:-gpu_reference}
mkdir -p "$out"
out=$(cd "$out" && pwd)
# The caller's DOJO_GPU_DATA, before leaving its directory.
data=$(cd "${DOJO_GPU_DATA:-$(dirname "$0")/../.gpu_data}" && pwd)
cd "$(dirname "$0")/.."

device=${DOJO_DEVICE:-cuda}
precision=${DOJO_PRECISION:-bf16}
scale=${DOJO_STEPS_SCALE:-1}
quick=${DOJO_REF_QUICK:-0}
build=$(mkdir -p "${DOJO_BUILD_DIR:-build-train}" && cd "${DOJO_BUILD_DIR:-build-train}" && pwd)

DOJO_SKIP_TESTS=1 DOJO_BUILD_DIR=$build scripts/gpu_train.sh "$out"
dojo=$build/dojo
work=${DOJO_WORK_DIR:-$PWD/gpu_ref_work}
mkdir -p "$work"
for set in human robot robot_ood_objects robot_counterfactual; do
  [[ -d $work/$set ]] || tar -C "$work" -xzf "$data/$set.tgz"
done

steps() { if [[ $quick == 1 ]]; then echo 3; else echo $(($1 * scale)); fi; }
episodes=8
if [[ $quick == 1 ]]; then episodes=2; fi
on=(--device "$device" --precision "$precision")
log=$out/train.log
: > "$out/stages.tsv"
stage() {  # name command...: runs it, logs its output, records its seconds
  local name=$1 start
  shift
  start=$(date +%s%N)
  echo "== $name: $*" >> "$log"
  if ! "$@" >> "$log" 2>&1; then
    tail -20 "$log"
    echo "stage $name failed (the whole output: $log)"
    exit 1
  fi
  local tenths=$((($(date +%s%N) - start) / 100000000))
  printf '%s\t%d.%d\n' "$name" $((tenths / 10)) $((tenths % 10)) | tee -a "$out/stages.tsv"
}

W=$work
stage lam "$dojo" lam train --data "$W/human" --data "$W/robot" --lr 3e-4 --batch 8 --steps "$(steps 1500)" \
  --save-every 100 --out "$W/lam" "${on[@]}"
stage tokenizer "$dojo" tokenizer train --data "$W/human" --data "$W/robot" --batch 4 --image-batch 8 \
  --warmup 20 --steps "$(steps 2700)" --save-every 100 --workers 2 --out "$W/tokenizer" "${on[@]}"
stage probe "$dojo" probe train --data "$W/robot" --data "$W/human" --steps "$(steps 600)" --out "$W/probe" "${on[@]}"
stage pretrain "$dojo" wm train --stage pretrain --data "$W/human" --split all --tokenizer "$W/tokenizer" \
  --lam "$W/lam/checkpoint" --out "$W/pretrain" --steps "$(steps 3500)" --batch 8 --lr 3e-4 --grad-clip 1 \
  --warmup 50 --hop 4 --max-clips 768 --save-every 250 "${on[@]}"
stage posttrain "$dojo" wm train --stage posttrain --data "$W/robot" --tokenizer "$W/tokenizer" \
  --init "$W/pretrain/checkpoint" --out "$W/posttrain" --steps "$(steps 5000)" --batch 8 --lr 3e-4 \
  --grad-clip 1 --warmup 50 --hop 4 --max-clips 0 --condition-noise 0.3 --save-every 500 "${on[@]}"
distill=(--teacher "$W/posttrain/checkpoint" --tokenizer "$W/tokenizer" --data "$W/robot" --hop 4 --max-clips 192
         --window 12 --sink-frames 1 --lr 1.6e-4 "${on[@]}")
stage student_warmup "$dojo" distill --stage warmup "${distill[@]}" --warmup-chunks 4 --batch 4 \
  --steps "$(steps 300)" --save-every 100 --out "$W/student_warmup"
stage student "$dojo" distill --stage self-forcing "${distill[@]}" --init "$W/student_warmup/checkpoint" \
  --batch 2 --steps "$(steps 300)" --save-every 50 --out "$W/student"
stage fast_decoder "$dojo" tokenizer fast-decoder --tokenizer "$W/tokenizer" --data "$W/robot" \
  --steps "$(steps 600)" --batch 4 --max-clips 192 --out "$W/fast_decoder" "${on[@]}"

ref=$W/reference
rm -rf "$ref" && mkdir -p "$ref/fast_decoder"
cp "$W/fast_decoder/checkpoint/"{config.json,model.safetensors} "$ref/fast_decoder/"
for pair in "lam $W/lam/checkpoint" "tokenizer $W/tokenizer" "probe $W/probe/checkpoint" \
            "wm_posttrain $W/posttrain/checkpoint" "student $W/student/checkpoint"; do
  set -- $pair
  stage "export_$1" "$dojo" ckpt export "$2" "$ref/$1" --dtype bf16
done
for split in "val robot val" "ood robot_ood_objects all" "cf robot_counterfactual all"; do
  set -- $split
  stage "eval_$1" "$dojo" eval -c "$ref/wm_posttrain" --tokenizer "$ref/tokenizer" --probe "$ref/probe" \
    --data "$W/$2" --split "$3" -n "$episodes" --action-sensitivity --videos 0 --out "$W/eval_$1" "${on[@]}"
  stage "eval_student_$1" "$dojo" eval --student -c "$ref/student" --tokenizer "$ref/tokenizer" \
    --probe "$ref/probe" --data "$W/$2" --split "$3" -n "$episodes" --action-sensitivity --videos 0 \
    --out "$W/eval_student_$1" "${on[@]}"
done
# In parts of at most 15 MiB, a size any transfer takes: cat reference.tgz.part-* | tar -xz
rm -f "$out"/reference.tgz.part-*
tar -C "$W" -czf - reference | split -b 15m - "$out/reference.tgz.part-"
tar -C "$W" -czf "$out/evals.tgz" $(cd "$W" && ls -d eval_*/metrics.*)
du -sh "$out"/reference.tgz.part-* "$out/evals.tgz"
