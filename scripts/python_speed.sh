#!/usr/bin/env bash
# The engine against Python PyTorch on this machine, in one run (docs/benchmarks.md, "C++ against
# Python PyTorch"): the small DiT's training step (batch 8, 13-frame clips at 64x64), one step of
# the teacher's sampler (batch 4) and one streaming step of the student (window 12 + a 1-frame
# sink, 4 hops, batch 1), timed by `dojo wm step-speed` and by the Python reference
# (scripts/python_reference/) on Debian's python3-torch, eager and TorchScript, with the same
# threads, the same OpenBLAS and the same weights and inputs. The Python side first checks that
# it computes the engine's numbers (tolerances below) and the run fails when it does not.
# Rounds alternate the implementations so that a busy minute hits all of them.
#
#   scripts/python_speed.sh [OUT_DIR]     (DOJO_SPEED_ROUNDS rounds, default 3; DOJO: the binary)
set -euo pipefail
out=${1:-python_speed}
rounds=${DOJO_SPEED_ROUNDS:-3}
repeats=${DOJO_SPEED_REPEATS:-20}
here=$(cd "$(dirname "$0")" && pwd)
dojo=${DOJO:-$here/../build/dojo}
python=${DOJO_PYTHON:-/usr/bin/python3}
"$python" -c "import torch" 2> /dev/null || {
  echo "python_speed.sh: $python has no torch (Debian: apt-get install python3-torch)" >&2
  exit 1
}
mkdir -p "$out"
# The same OpenBLAS kernels for both: dojo replaces a set older than the CPU when it starts
# (src/core/blas_kernels.h), where Python would keep it.
if [ -z "${OPENBLAS_CORETYPE:-}" ]; then
  kernels=$("$dojo" -q version --json | "$python" -c 'import json, sys; print(json.load(sys.stdin).get("blas_kernels", ""))')
  [ -z "$kernels" ] || export OPENBLAS_CORETYPE=$kernels
fi
options=(--repeats "$repeats" --stream-steps "$((2 * repeats))")
"$dojo" -q wm step-speed "${options[@]}" --export "$out/export" --json > "$out/cpp_0.json"
# dojo keeps freed memory in its heap (src/core/heap.h); the same settings for Python, by glibc's
# environment variables, make a fourth column.
heap=(MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=1073741824 MALLOC_TOP_PAD_=268435456)
for ((r = 0; r < rounds; ++r)); do
  echo "round $((r + 1)) of $rounds"
  [ $r -eq 0 ] || "$dojo" -q wm step-speed "${options[@]}" --json > "$out/cpp_$r.json"
  "$python" "$here/python_reference/step_speed.py" "$out/export" --mode eager > "$out/eager_$r.json"
  env "${heap[@]}" "$python" "$here/python_reference/step_speed.py" "$out/export" --mode eager \
    > "$out/eager_heap_$r.json"
  "$python" "$here/python_reference/step_speed.py" "$out/export" --mode scripted > "$out/scripted_$r.json"
done
"$python" - "$out" "$rounds" << 'EOF_PY'
import json, statistics, sys
out, rounds = sys.argv[1], int(sys.argv[2])
load = lambda name: [json.load(open(f"{out}/{name}_{r}.json")) for r in range(rounds)]
runs = {"C++ (dojo)": load("cpp"), "Python eager": load("eager"),
        "Python eager, dojo's heap": load("eager_heap"), "Python TorchScript": load("scripted")}
bad = []
for name in ("eager", "eager_heap", "scripted"):
    for r, run in enumerate(load(name)):
        c = run["checks"]
        if c["sample_velocity_max_abs_diff"] > 1e-4 or c["stream_latents_max_abs_diff"] > 1e-4 \
                or c["train_loss_rel_diff"] > 1e-5 or c["train_grad_norm_rel_diff"] > 1e-4 \
                or c["train_weights_max_abs_diff"] > 1e-2 * c["train_update_max_abs"] \
                or c["train_ema_max_abs_diff"] > 1e-2 * c["train_update_max_abs"]:
            bad.append(f"{name} round {r}: {c}")
if bad:
    sys.exit("python_speed.sh: the Python reference does not compute the engine's numbers:\n" + "\n".join(bad))
cpp = runs["C++ (dojo)"][0]
machine = cpp["machine"]
print(f"dojo {machine.get('version', '?')} ({machine.get('git_commit', '?')}), libtorch {machine.get('torch_version', '?')}, "
      f"{machine.get('blas', '?')} {machine.get('blas_kernels', '?')}, one intra-op thread; Python "
      f"{runs['Python eager'][0]['python']}, torch {runs['Python eager'][0]['torch']}, OpenBLAS "
      f"{runs['Python eager'][0]['openblas'].get('kernels', '?')} x{runs['Python eager'][0]['openblas'].get('threads', '?')}")
print(f"{rounds} rounds; per step the median over rounds of each round's mean; checks passed "
      f"(velocity, latents <= 1e-4, loss <= 1e-5 relative, weights after a step <= 1% of the step)\n")
steps = [("train", "training step (batch 8)"), ("sample", "sampling step (batch 4)"),
         ("stream", "streaming step (batch 1)")]
print("| step | " + " | ".join(f"{k} ms" for k in runs) +
      " | C++ vs eager (rounds) | vs eager, same heap | vs TorchScript |")
print("|---" * (len(runs) + 4) + "|")
for key, label in steps:
    ms = {k: statistics.median(run[key]["ms_mean"] for run in v) for k, v in runs.items()}
    c = ms["C++ (dojo)"]
    per_round = [e[key]["ms_mean"] / p[key]["ms_mean"] for e, p in zip(runs["Python eager"], runs["C++ (dojo)"])]
    print(f"| {label} | " + " | ".join(f"{m:.1f}" for m in ms.values()) +
          f" | {ms['Python eager'] / c:.2f}x ({min(per_round):.2f}-{max(per_round):.2f}) | "
          f"{ms['Python eager, dojo' + chr(39) + 's heap'] / c:.2f}x | {ms['Python TorchScript'] / c:.2f}x |")
EOF_PY
