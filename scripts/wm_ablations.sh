#!/usr/bin/env bash
# The paper's world-model experiments at DojoSim scale, on the data and models `dojo demo` left in
# DEMO_DIR (datasets, LAM, tokenizer, keypoint probe). Every variant trains an equal number of
# steps per stage for each seed, then is scored with `dojo eval` (PSNR and keypoint error) on the
# held-out (val), out-of-distribution-object and counterfactual splits; results are mean ± std over
# the seeds.
#
#   scripts/wm_ablations.sh [DEMO_DIR=dojo_demo] [STEPS=1000] [OUT=DEMO_DIR/ablations]
#
# Action conditioning (pretraining on human video, then post-training on robot actions):
#   scratch        no pretraining
#   none           action-free pretraining
#   latent         latent-action pretraining (the paper's method)
#   ground-truth   pretraining on the human hand's true motion
# Design (each against `latent`):
#   absolute       post-train on absolute instead of chunk-relative actions
#   whole-clip     one embedding of all 12 actions for every frame (pretrain + post-train)
#   no-temporal    temporal-consistency loss off (pretrain + post-train)
#   temporal-channel   the temporal loss taken along the channel axis instead of time
# Environment: VARIANTS="scratch none latent" runs only those; SEEDS="0 1 2" (default); THREADS
# sets the intra-op thread count (default 1); EPISODES evaluation episodes per split (default 8);
# EXTRA holds `wm train` arguments every run gets (the demo's recipe: see src/recipes/demo.cpp).
# Results: OUT/results.md, OUT/<variant>/seed<k>/eval_<split>/metrics.json. Re-running resumes:
# finished trainings and evaluations are kept.
set -euo pipefail
cd "$(dirname "$0")/.."
DEMO=${1:-dojo_demo}
STEPS=${2:-1000}
OUT=${3:-$DEMO/ablations}
DOJO=${DOJO:-build/dojo}
# One OpenMP thread: OpenBLAS threads do the matmuls, and a second OpenMP thread made the DiT
# 2.7x slower on 2 cores (docs/benchmarks.md, session 4).
THREADS=${THREADS:-1}
SEEDS=${SEEDS:-0 1 2}
EPISODES=${EPISODES:-8}
read -r -a EXTRA_ARGS <<< "${EXTRA:-}"
TOK=$DEMO/tokenizer/checkpoint
LAM=$DEMO/lam/checkpoint
PROBE=$DEMO/probe/checkpoint
for need in "$TOK" "$LAM" "$PROBE" "$DEMO/human" "$DEMO/robot"; do
  [[ -e $need ]] || { echo "error: $need missing: run 'build/dojo demo --out $DEMO' first" >&2; exit 1; }
done
mkdir -p "$OUT"
COMMON=(--tokenizer "$TOK" --steps "$STEPS" --lr 3e-4 --grad-clip 1 --warmup 50 --hop 4 --max-clips 192
        --save-every 500 "${EXTRA_ARGS[@]}")

pretrain() {  # dir, seed, extra args...
  local dir=$1 seed=$2; shift 2
  "$DOJO" --threads "$THREADS" wm train --stage pretrain --data "$DEMO/human" --split all --lam "$LAM" \
    "${COMMON[@]}" --seed "$seed" --out "$dir/pretrain" "$@"
}
posttrain() {  # dir, seed, init ("" = scratch), extra args...
  local dir=$1 seed=$2 init=$3; shift 3
  if [[ -n $init ]]; then
    "$DOJO" --threads "$THREADS" wm train --stage posttrain --init "$init" --data "$DEMO/robot" "${COMMON[@]}" \
      --seed "$seed" --out "$dir/posttrain" "$@"
  else
    "$DOJO" --threads "$THREADS" wm train --stage scratch --data "$DEMO/robot" "${COMMON[@]}" --seed "$seed" \
      --out "$dir/posttrain" "$@"
  fi
}
evaluate() {  # dir
  local dir=$1 ck=$1/posttrain/checkpoint
  for split in "val robot val" "ood robot_ood_objects all" "cf robot_counterfactual all"; do
    set -- $split
    [[ -e $dir/eval_$1/metrics.json ]] && continue
    "$DOJO" --threads "$THREADS" eval -c "$ck" --tokenizer "$TOK" --data "$DEMO/$2" --split "$3" -n "$EPISODES" \
      --probe "$PROBE" --videos 0 --out "$dir/eval_$1" --json > /dev/null
  done
}

VARIANTS=${VARIANTS:-scratch none latent ground-truth absolute whole-clip no-temporal temporal-channel}
want() { [[ " $VARIANTS " == *" $1 "* ]]; }
done_training() { [[ -e $1/posttrain/train_summary.json ]] && grep -q "\"steps\": $STEPS" "$1/posttrain/train_summary.json"; }

for seed in $SEEDS; do
  if want scratch; then
    d=$OUT/scratch/seed$seed
    done_training "$d" || posttrain "$d" "$seed" ""
    evaluate "$d"
  fi
  for mode in none latent ground-truth; do
    want "$mode" || continue
    d=$OUT/$mode/seed$seed
    done_training "$d" || { pretrain "$d" "$seed" --actions "$mode" && posttrain "$d" "$seed" "$d/pretrain/checkpoint"; }
    evaluate "$d"
  done
  if want absolute; then
    d=$OUT/absolute/seed$seed
    [[ -e $OUT/latent/seed$seed/pretrain/checkpoint ]] || pretrain "$OUT/latent/seed$seed" "$seed" --actions latent
    done_training "$d" || posttrain "$d" "$seed" "$OUT/latent/seed$seed/pretrain/checkpoint" --absolute-actions
    evaluate "$d"
  fi
  for variant in whole-clip no-temporal temporal-channel; do
    want "$variant" || continue
    case $variant in
      whole-clip) args=(--whole-clip-actions) ;;
      no-temporal) args=(--temporal-weight 0) ;;
      temporal-channel) args=(--temporal-axis channel) ;;
    esac
    d=$OUT/$variant/seed$seed
    done_training "$d" || { pretrain "$d" "$seed" --actions latent "${args[@]}" &&
                            posttrain "$d" "$seed" "$d/pretrain/checkpoint" "${args[@]}"; }
    evaluate "$d"
  done
done

python3 - "$OUT" <<'PY'
import json, os, statistics, sys
out = sys.argv[1]
def stat(values, digits=2):
    values = [v for v in values if v is not None]
    if not values: return "-"
    if len(values) == 1: return f"{values[0]:.{digits}f}"
    return f"{statistics.mean(values):.{digits}f} ± {statistics.stdev(values):.{digits}f}"
rows = ["| variant | seeds | val PSNR | val keypoint error (px) | OOD PSNR | OOD keypoint error | cf PSNR | cf keypoint error |",
        "|---|---|---|---|---|---|---|---|"]
reference = None
for v in ["scratch", "none", "latent", "ground-truth", "absolute", "whole-clip", "no-temporal", "temporal-channel"]:
    runs = []
    vdir = os.path.join(out, v)
    if not os.path.isdir(vdir): continue
    for seed in sorted(os.listdir(vdir)):
        try:
            runs.append({k: json.load(open(os.path.join(vdir, seed, "eval_" + k, "metrics.json")))["splits"][0]
                         for k in ("val", "ood", "cf")})
        except OSError:
            pass
    if not runs: continue
    reference = reference or runs[0]
    cells = []
    for k in ("val", "ood", "cf"):
        cells.append(stat([r[k]["world_model"]["psnr"] for r in runs]))
        cells.append(stat([r[k]["world_model"].get("keypoint_error_px") for r in runs], 1))
    rows.append(f"| {v} | {len(runs)} | " + " | ".join(cells) + " |")
if reference:
    cells = []
    for k in ("val", "ood", "cf"):
        cells += [f"{reference[k]['copy_frame']['psnr']:.2f}", f"{reference[k]['copy_frame'].get('keypoint_error_px', float('nan')):.1f}"]
    rows.append("| copy-frame baseline | | " + " | ".join(cells) + " |")
open(os.path.join(out, "results.md"), "w").write("\n".join(rows) + "\n")
print("\n".join(rows))
PY
