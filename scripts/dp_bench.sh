#!/usr/bin/env bash
# Data-parallel scaling on this machine: the reference world model post-trained on DojoSim with a
# global batch of 8, on one process (on one core; one OpenMP thread with OpenBLAS on every core, the
# default; all cores) and on 2 processes of one core each (`dojo launch --nproc 2`, which gives each
# process OMP_NUM_THREADS = OPENBLAS_NUM_THREADS = cores / 2), same data, init, steps and seed.
#
#   scripts/dp_bench.sh [OUT=/tmp/dp_bench] [STEPS=24]
#
# Throughput is the trainer's steady state (train_summary.json clips_per_second: steps after the
# first two). Scaling efficiency = 2-process clips/s / (2 x one-core clips/s). Also
# checks that the 2-process run ends where the one-process run with --accumulate 2 ends (largest
# weight difference). Prints a markdown table.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-/tmp/dp_bench}
STEPS=${2:-24}
DOJO=${DOJO:-build/dojo}
REF=models/reference
mkdir -p "$OUT"

[[ -f $OUT/robot/info.json ]] || $DOJO sim generate --embodiment robot --episodes 16 --seed 31 --out "$OUT/robot"
TRAIN="wm train --stage posttrain --data $OUT/robot --tokenizer $REF/tokenizer --init $REF/wm_posttrain
  --steps $STEPS --batch 8 --lr 1e-4 --warmup 0 --hop 4 --save-every $STEPS --seed 0"
run() {  # name, extra trainer arguments, then the command before `wm train`
  local name=$1 extra=$2
  shift 2
  if [[ ! -f $OUT/$name/train_summary.json ]]; then
    rm -rf "${OUT:?}/$name"
    mkdir -p "$OUT/$name"
    # One latent cache, built by the first run and copied in: every run times training alone.
    [[ -f $OUT/latents-0.safetensors ]] && cp "$OUT/latents-0.safetensors" "$OUT/$name/"
    # shellcheck disable=SC2086
    /usr/bin/time -v "$@" $TRAIN $extra --out "$OUT/$name" > "$OUT/$name.log" 2>&1
    [[ -f $OUT/latents-0.safetensors ]] || cp "$OUT/$name/latents-0.safetensors" "$OUT/"
  fi
}
run one_core "" env OPENBLAS_NUM_THREADS=1 $DOJO --threads 1
run one_thread "" $DOJO --threads 1
run all_cores "" $DOJO
run two_processes "" $DOJO launch --nproc 2 --master-port 29611 -- dojo --threads 1
run accumulate2 "--accumulate 2" $DOJO --threads 1

/usr/bin/python3 - "$OUT" <<'PY'
import json, os, re, struct, sys
import numpy as np
out = sys.argv[1]
def summary(name):
    return json.load(open(os.path.join(out, name, "train_summary.json")))
def peak_mib(name):  # the largest resident set among the run's processes (GNU time -v)
    log = open(os.path.join(out, name + ".log")).read()
    sizes = re.findall(r"Maximum resident set size \(kbytes\): (\d+)", log)
    return max(int(x) for x in sizes) / 1024 if sizes else float("nan")
def weights(name):  # model.safetensors as float32 arrays (u64 header size, JSON header, data)
    blob = open(os.path.join(out, name, "checkpoint", "model.safetensors"), "rb").read()
    n = struct.unpack("<Q", blob[:8])[0]
    header = json.loads(blob[8:8 + n])
    arrays = {}
    for key, info in header.items():
        if key == "__metadata__" or info["dtype"] != "F32":
            continue
        a, b = info["data_offsets"]
        arrays[key] = np.frombuffer(blob[8 + n + a:8 + n + b], dtype=np.float32)
    return arrays
wa, wb = weights("accumulate2"), weights("two_processes")
difference = max(float(np.abs(wa[k] - wb[k]).max()) for k in wa)
base = summary("one_core")["clips_per_second"]
print("| run | clips/s (steady state) | vs one core | peak resident memory (MiB) | last loss |")
print("|---|---|---|---|---|")
for name, label in [("one_core", "1 process on one core (1 thread, OpenBLAS 1 thread)"),
                    ("one_thread", "1 process, 1 thread (OpenBLAS on both cores: the default)"),
                    ("all_cores", "1 process, 2 threads"),
                    ("two_processes", "2 processes x 1 core (`dojo launch --nproc 2`)")]:
    s = summary(name)
    print(f"| {label} | {s['clips_per_second']:.2f} | {s['clips_per_second'] / base:.2f}x | "
          f"{peak_mib(name):.0f} | {s['last_loss']:.4f} |")
efficiency = summary("two_processes")["clips_per_second"] / (2 * base)
print(f"\nScaling efficiency, one core -> 2 processes on a core each: {efficiency:.0%}. Largest weight "
      f"difference, 2 processes vs 1 process with --accumulate 2: {difference:.2e}.")
PY
