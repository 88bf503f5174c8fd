#!/usr/bin/env bash
# Trains the DojoSim reference model set and exports it (bf16, no trainer state) into
# models/reference, then scores it. About 2.7 hours on 2 CPU cores.
#
#   scripts/train_reference.sh [WORK_DIR=ref_work]
#
# 1. `dojo demo` makes the datasets, the LAM, the tokenizer, the keypoint probe and a pretrained
#    world model (its stage budgets; --tokenizer train so it trains its own tokenizer rather than
#    copying the shipped one; --reference none so it does not score an older set).
# 2. Pretraining continues to 3500 steps on 768 human clips (the demo caches 192).
# 3. Post-training from that checkpoint: 5000 steps on every robot training clip, conditioning
#    noise 0.3 (docs/action_following.md).
# 4. The real-time student distilled from the post-trained model (window 12 + sink 1): teacher
#    trajectories of 4 chained chunks anchored on re-encoded frames, from the robot set's training
#    clips and 256 more scripted episodes (seed 4001: no held-out seed), 3600 warm-up steps with half
#    the clips on a clean context, no Self-Forcing (it cost held-out accuracy at every budget tried:
#    docs/benchmarks.md); and a fast decoder of the tokenizer (600 steps).
# 5. `dojo ckpt export` of the models into models/reference (the pretrained world model is not
#    shipped: no default uses it; it stays in WORK/ref_pretrain); `dojo eval` of the teacher and
#    the student on the demo's three robot splits (8 episodes each, probe, action sensitivity).
# Re-running resumes: finished demo stages and trainings are kept.
set -euo pipefail
cd "$(dirname "$0")/.."
WORK=${1:-ref_work}
DOJO=${DOJO:-build/dojo}
REF=models/reference

"$DOJO" demo --out "$WORK" --tokenizer train --reference none
if [[ ! -d $WORK/ref_pretrain ]]; then  # resume the demo's pretraining in a copy (optimizer state and all)
  mkdir -p "$WORK/ref_pretrain" && cp -r "$WORK/wm_pretrain/checkpoint" "$WORK/ref_pretrain/"
fi
"$DOJO" wm train --stage pretrain --data "$WORK/human" --split all --tokenizer "$WORK/tokenizer/checkpoint" \
  --lam "$WORK/lam/checkpoint" --out "$WORK/ref_pretrain" --steps 3500 \
  --batch 8 --lr 3e-4 --grad-clip 1 --warmup 50 --hop 4 --max-clips 768 --save-every 250
"$DOJO" wm train --stage posttrain --data "$WORK/robot" --tokenizer "$WORK/tokenizer/checkpoint" \
  --init "$WORK/ref_pretrain/checkpoint" --out "$WORK/ref_posttrain" --steps 5000 --batch 8 --lr 3e-4 \
  --grad-clip 1 --warmup 50 --hop 4 --max-clips 0 --condition-noise 0.3 --save-every 500

# Distillation data: the robot set's training clips and 256 more scripted episodes of their own seed.
[[ -f $WORK/robot_distill/info.json ]] || "$DOJO" sim generate -o "$WORK/robot_distill" --embodiment robot \
  --split train -n 256 --frames 64 --seed 4001 --val-fraction 0
"$DOJO" distill --stage warmup --teacher "$WORK/ref_posttrain/checkpoint" --tokenizer "$WORK/tokenizer/checkpoint" \
  --data "$WORK/robot" --data "$WORK/robot_distill" --hop 12 --max-clips 0 --window 12 --sink-frames 1 --lr 1.6e-4 \
  --warmup-chunks 4 --warmup-anchor reencoded --clean-context-share 0.5 --batch 4 --steps 3600 --save-every 200 \
  --out "$WORK/ref_student"
"$DOJO" tokenizer fast-decoder --tokenizer "$WORK/tokenizer/checkpoint" --data "$WORK/robot" --steps 600 \
  --batch 4 --max-clips 192 --out "$WORK/ref_fast_decoder"

mkdir -p "$REF"
rm -rf "$REF/fast_decoder" && mkdir -p "$REF/fast_decoder"  # fp32, 1.3 MB: its weights without trainer state
cp "$WORK/ref_fast_decoder/checkpoint/"{config.json,model.safetensors} "$REF/fast_decoder/"
for pair in "lam $WORK/lam/checkpoint" "tokenizer $WORK/tokenizer/checkpoint" "probe $WORK/probe/checkpoint" \
            "wm_posttrain $WORK/ref_posttrain/checkpoint" "student $WORK/ref_student/checkpoint"; do
  set -- $pair
  rm -rf "$REF/$1.new" && "$DOJO" ckpt export "$2" "$REF/$1.new" --dtype bf16
  rm -rf "$REF/$1" && mv "$REF/$1.new" "$REF/$1"
done
for split in "val robot val" "ood robot_ood_objects all" "cf robot_counterfactual all"; do
  set -- $split
  "$DOJO" eval --data "$WORK/$2" --split "$3" -n 8 --action-sensitivity --out "$WORK/ref_eval_$1" --videos 2
  # The student alone, decoded by the Wan decoder (an explicit --tokenizer: no fast decoder).
  "$DOJO" eval --student --checkpoint "$REF/student" --tokenizer "$REF/tokenizer" --data "$WORK/$2" --split "$3" \
    -n 8 --action-sensitivity --out "$WORK/ref_student_eval_$1" --videos 2
done
