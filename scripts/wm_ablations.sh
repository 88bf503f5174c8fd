#!/usr/bin/env bash
# The paper's world-model experiments at DojoSim scale, on the data and models `dojo demo` left in
# DEMO_DIR (datasets, LAM, tokenizer). Every variant trains for MINUTES per stage, then is scored
# with `dojo eval` on the held-out (val), out-of-distribution-object and counterfactual splits.
#
#   scripts/wm_ablations.sh [DEMO_DIR=dojo_demo] [MINUTES=8] [OUT=DEMO_DIR/ablations]
#
# Action conditioning (pretraining on human video, then post-training on robot actions):
#   scratch        no pretraining
#   none           action-free pretraining
#   latent         latent-action pretraining (the paper's method)
#   ground-truth   pretraining on the human hand's true motion
# Design (each against `latent`, same pretraining checkpoint where possible):
#   absolute       post-train on absolute instead of chunk-relative actions
#   whole-clip     one embedding of all 12 actions for every frame (pretrain + post-train)
#   no-temporal    temporal-consistency loss off (pretrain + post-train)
# Results: OUT/results.md (one table), OUT/<variant>/eval/metrics.json. Re-running resumes.
# VARIANTS="scratch none latent" (environment) runs only those, in the order above; THREADS sets
# the intra-op thread count (default 1).
set -euo pipefail
cd "$(dirname "$0")/.."
DEMO=${1:-dojo_demo}
MINUTES=${2:-8}
OUT=${3:-$DEMO/ablations}
DOJO=${DOJO:-build/dojo}
# One OpenMP thread: OpenBLAS threads do the matmuls, and a second OpenMP thread made the DiT
# 2.7x slower on 2 cores (docs/benchmarks.md, session 4).
THREADS=${THREADS:-1}
TOK=$DEMO/tokenizer/checkpoint
LAM=$DEMO/lam/checkpoint
for need in "$TOK" "$LAM" "$DEMO/human" "$DEMO/robot"; do
  [[ -e $need ]] || { echo "error: $need missing: run 'build/dojo demo --out $DEMO' first" >&2; exit 1; }
done
mkdir -p "$OUT"
COMMON=(--tokenizer "$TOK" --minutes "$MINUTES" --steps 1000000 --lr 3e-4 --grad-clip 1 --warmup 50
        --hop 4 --max-clips 192 --save-every 100)

pretrain() {  # name, extra args...
  local name=$1; shift
  "$DOJO" --threads "$THREADS" wm train --stage pretrain --data "$DEMO/human" --split all --lam "$LAM" "${COMMON[@]}" \
    --out "$OUT/$name/pretrain" "$@"
}
posttrain() {  # name, init, extra args...
  local name=$1 init=$2; shift 2
  if [[ -n $init ]]; then
    "$DOJO" --threads "$THREADS" wm train --stage posttrain --init "$init" --data "$DEMO/robot" "${COMMON[@]}" --out "$OUT/$name/posttrain" "$@"
  else
    "$DOJO" --threads "$THREADS" wm train --stage scratch --data "$DEMO/robot" "${COMMON[@]}" --out "$OUT/$name/posttrain" "$@"
  fi
}
evaluate() {  # name
  local name=$1 ck=$OUT/$1/posttrain/checkpoint
  "$DOJO" --threads "$THREADS" eval -c "$ck" --tokenizer "$TOK" --data "$DEMO/robot" --split val --out "$OUT/$name/eval_val" --json > /dev/null
  "$DOJO" --threads "$THREADS" eval -c "$ck" --tokenizer "$TOK" --data "$DEMO/robot_ood_objects" --split all --out "$OUT/$name/eval_ood" --json > /dev/null
  "$DOJO" --threads "$THREADS" eval -c "$ck" --tokenizer "$TOK" --data "$DEMO/robot_counterfactual" --split all --out "$OUT/$name/eval_cf" --json > /dev/null
}

VARIANTS=${VARIANTS:-scratch none latent ground-truth absolute whole-clip no-temporal}
want() { [[ " $VARIANTS " == *" $1 "* ]]; }

if want scratch; then posttrain scratch "" && evaluate scratch; fi
for mode in none latent ground-truth; do
  want "$mode" || continue
  pretrain "$mode" --actions "$mode"
  posttrain "$mode" "$OUT/$mode/pretrain/checkpoint"
  evaluate "$mode"
done
if want absolute; then
  [[ -e $OUT/latent/pretrain/checkpoint ]] || pretrain latent --actions latent
  posttrain absolute "$OUT/latent/pretrain/checkpoint" --absolute-actions && evaluate absolute
fi
if want whole-clip; then
  pretrain whole-clip --actions latent --whole-clip-actions
  posttrain whole-clip "$OUT/whole-clip/pretrain/checkpoint" --whole-clip-actions && evaluate whole-clip
fi
if want no-temporal; then
  pretrain no-temporal --actions latent --temporal-weight 0
  posttrain no-temporal "$OUT/no-temporal/pretrain/checkpoint" --temporal-weight 0 && evaluate no-temporal
fi

python3 - "$OUT" <<'PY' 2>/dev/null || true
import json, sys, os
out = sys.argv[1]
rows = ["| variant | val PSNR | val SSIM | OOD-objects PSNR | counterfactual PSNR | copy-frame PSNR (val / OOD / cf) | tokenizer ceiling (val) |",
        "|---|---|---|---|---|---|---|"]
for v in ["scratch", "none", "latent", "ground-truth", "absolute", "whole-clip", "no-temporal"]:
    try:
        m = {k: json.load(open(os.path.join(out, v, "eval_" + k, "metrics.json")))["splits"][0]
             for k in ("val", "ood", "cf")}
    except OSError:
        continue
    rows.append("| %s | %.2f | %.3f | %.2f | %.2f | %.2f / %.2f / %.2f | %.2f |" % (
        v, m["val"]["psnr"], m["val"]["ssim"], m["ood"]["psnr"], m["cf"]["psnr"],
        m["val"]["copy_first_frame"]["psnr"], m["ood"]["copy_first_frame"]["psnr"],
        m["cf"]["copy_first_frame"]["psnr"], m["val"]["tokenizer_round_trip"]["psnr"]))
open(os.path.join(out, "results.md"), "w").write("\n".join(rows) + "\n")
print("\n".join(rows))
PY
