#!/usr/bin/env bash
# A two-view world model (ego + side, tiled side by side) against the single-view one, on the same
# DojoSim episodes, from the same init, with the same steps, batch, learning rate and seed.
#
#   scripts/multi_view_bench.sh [OUT=/tmp/multi_view_bench] [STEPS=600]
#
# Init: the reference world model (models/reference/wm_posttrain) with its recorded action ranges
# removed (as scripts/lora_bench.sh: both action MLPs' first layers re-drawn). Data: 48 fresh DojoSim
# robot episodes recorded by both cameras (seed 21; 42 train, 6 val). Tokenizer: the reference one
# (trained on ego views; convolutional, so it encodes the 64x128 canvas as it is). Scored with
# `dojo eval` on the val episodes (4 chunks, the trained sampler, true / shuffled / zero actions, the
# reference probe on the ego view). Prints a markdown table: per-camera PSNR, the ego view's keypoint
# error with each action set, the tokenizer's round trip per camera, step time.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-/tmp/multi_view_bench}
STEPS=${2:-600}
DOJO=${DOJO:-build/dojo}
REF=models/reference
mkdir -p "$OUT"

[[ -f $OUT/robot/info.json ]] ||
  $DOJO sim generate --embodiment robot --episodes 48 --seed 21 --cameras side --out "$OUT/robot"
if [[ ! -f $OUT/init/config.json ]]; then
  rm -rf "$OUT/init" && cp -r $REF/wm_posttrain "$OUT/init"
  python3 - "$OUT/init/config.json" <<'EOF'
import json, sys
path = sys.argv[1]
config = json.load(open(path))
config.pop("actions", None)  # a network that has not met this action space
json.dump(config, open(path, "w"), indent=2)
EOF
fi

COMMON="--stage posttrain --data $OUT/robot --tokenizer $REF/tokenizer --init $OUT/init --steps $STEPS
  --batch 8 --lr 3e-4 --grad-clip 1 --warmup 50 --hop 4 --save-every $STEPS --seed 0"
run() {  # name, extra wm train arguments
  local name=$1
  shift
  if [[ ! -f $OUT/$name/train_summary.json ]]; then
    mkdir -p "$OUT/$name"
    $DOJO --threads 1 wm train $COMMON "$@" --out "$OUT/$name" > "$OUT/$name/train.log" 2>&1
  fi
  if [[ ! -f $OUT/$name/eval.json ]]; then
    $DOJO --threads 1 eval --checkpoint "$OUT/$name/checkpoint" --tokenizer $REF/tokenizer --probe $REF/probe \
      --data "$OUT/robot" --split val --episodes 6 --chunks 4 --action-sensitivity --json \
      > "$OUT/$name/eval.out" 2> "$OUT/$name/eval.log"
    mv "$OUT/$name/eval.out" "$OUT/$name/eval.json"
  fi
}
run single_view
run two_views --views ego,side

python3 - "$OUT" <<'EOF'
import json, os, re, sys
out = sys.argv[1]

def split_of(name):
    text = open(os.path.join(out, name, "eval.json")).read()
    return json.loads(text[re.search(r"^\{", text, re.M).start():])["splits"][0]  # after any log line

def step_time(name):
    clips = re.search(r"([0-9.]+) clips/s", open(os.path.join(out, name, "train.log")).read())
    return 8 / float(clips.group(1)) if clips else float("nan")

kp = lambda s, source: s[source].get("keypoint_error_px", float("nan"))
single, two = split_of("single_view"), split_of("two_views")
ego, side = two["views"]["ego"], two["views"]["side"]
print("| model | step time (s) | ego PSNR: model / copy-frame / tokenizer | side PSNR: model / copy-frame / tokenizer "
      "| ego keypoint error px: true / shuffled / zero | copy-frame px |")
print("|---|---|---|---|---|---|")
print(f"| single view (ego) | {step_time('single_view'):.3f} | {single['world_model']['psnr']:.2f} / "
      f"{single['copy_frame']['psnr']:.2f} / {single['tokenizer']['psnr']:.2f} | - | "
      f"{kp(single, 'world_model'):.2f} / {kp(single, 'shuffled_actions'):.2f} / {kp(single, 'zero_actions'):.2f} | "
      f"{kp(single, 'copy_frame'):.2f} |")
print(f"| two views (ego + side) | {step_time('two_views'):.3f} | {ego['world_model']['psnr']:.2f} / "
      f"{ego['copy_frame']['psnr']:.2f} / {ego['tokenizer']['psnr']:.2f} | {side['world_model']['psnr']:.2f} / "
      f"{side['copy_frame']['psnr']:.2f} / {side['tokenizer']['psnr']:.2f} | "
      f"{kp(ego, 'world_model'):.2f} / {kp(ego, 'shuffled_actions'):.2f} / {kp(ego, 'zero_actions'):.2f} | "
      f"{kp(ego, 'copy_frame'):.2f} |")
EOF
