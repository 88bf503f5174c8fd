#!/usr/bin/env bash
# LoRA against full post-training on DojoSim, same init, data, steps, batch, learning rate and seed.
#
#   scripts/lora_bench.sh [OUT=/tmp/lora_bench] [STEPS=300] [RANKS="8 16 32"]
#
# Init: the reference world model (models/reference/wm_posttrain) with its recorded action ranges
# removed, so post-training treats it as a pretrained network meeting a new action space: both
# action MLPs' first layers are re-drawn and train in full, as in the release. Full post-training
# trains every weight; LoRA trains rank-r adapters (alpha = r) on every block's q/k/v/output and
# MLP layers plus the action MLPs, the rest frozen. Data: 48 fresh DojoSim robot episodes
# (seed 21; 42 train, 6 val). Scored with `dojo eval` on the val episodes (4 chunks, the trained
# sampler, true / shuffled / zero actions, the reference probe). Prints a markdown table: trainable
# parameters, AdamW state, step time, keypoint error and PSNR on the predicted frames.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-/tmp/lora_bench}
STEPS=${2:-300}
RANKS=${RANKS:-8 16 32}
DOJO=${DOJO:-build/dojo}
REF=models/reference
mkdir -p "$OUT"

[[ -f $OUT/robot/info.json ]] || $DOJO sim generate --embodiment robot --episodes 48 --seed 21 --out "$OUT/robot"
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
    # The clips are the same for every variant: encode them once.
    [[ -f $OUT/full/latents-0.safetensors && ! -f $OUT/$name/latents-0.safetensors ]] &&
      cp "$OUT/full/latents-0.safetensors" "$OUT/$name/"
    $DOJO --threads 1 wm train $COMMON "$@" --out "$OUT/$name" > "$OUT/$name/train.log" 2>&1
  fi
  if [[ ! -f $OUT/$name/eval.json ]]; then
    $DOJO --threads 1 eval --checkpoint "$OUT/$name/checkpoint" --tokenizer $REF/tokenizer --probe $REF/probe \
      --data "$OUT/robot" --split val --episodes 6 --chunks 4 --action-sensitivity --json \
      > "$OUT/$name/eval.out" 2> "$OUT/$name/eval.log"
    mv "$OUT/$name/eval.out" "$OUT/$name/eval.json"
  fi
}
run full
for r in $RANKS; do run "lora$r" --lora "$r" --lora-alpha "$r"; done

python3 - "$OUT" full $(for r in $RANKS; do echo "lora$r"; done) <<'EOF'
import json, os, re, struct, sys
out, names = sys.argv[1], sys.argv[2:]

def header(path):
    with open(path, "rb") as f:
        n = struct.unpack("<Q", f.read(8))[0]
        return json.loads(f.read(n))

def numel(shape):
    p = 1
    for d in shape:
        p *= d
    return p

print("| variant | trainable parameters | AdamW state (MB) | step time (s) | keypoint error px: true / shuffled / zero | PSNR (dB) | copy-frame px |")
print("|---|---|---|---|---|---|---|")
for name in names:
    d = os.path.join(out, name)
    state = header(os.path.join(d, "checkpoint", "trainer_state.safetensors"))
    moments = [v for k, v in state.items() if k.endswith(".exp_avg") or k.endswith(".exp_avg_sq")]
    trainable = sum(numel(v["shape"]) for k, v in state.items() if k.endswith(".exp_avg"))
    adam_mb = sum(numel(v["shape"]) * 4 for v in moments) / 1e6
    summary = json.load(open(os.path.join(d, "train_summary.json")))
    log = open(os.path.join(d, "train.log")).read()
    clips = re.search(r"([0-9.]+) clips/s", log)
    step_s = 8 / float(clips.group(1)) if clips else float("nan")
    text = open(os.path.join(d, "eval.json")).read()
    split = json.loads(text[text.index("{"):])["splits"][0]
    kp = lambda s: split[s].get("keypoint_error_px", float("nan"))
    print(f"| {name} | {trainable:,} | {adam_mb:.1f} | {step_s:.3f} | {kp('world_model'):.2f} / "
          f"{kp('shuffled_actions'):.2f} / {kp('zero_actions'):.2f} | {split['world_model']['psnr']:.2f} | "
          f"{kp('copy_frame'):.2f} |")
EOF
