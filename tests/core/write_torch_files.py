"""Writes real torch.save files with the system's PyTorch (Debian's python3-torch) for the reader
and converter tests: python3 write_torch_files.py OUT_DIR MARKER_PATH GOLDEN_DIR

OUT_DIR receives
  tensors_zip.pt, tensors_legacy.pt   every storage dtype, a 0-d tensor, an empty tensor, and views
                                      sharing one storage (a slice with an offset, a transpose)
  expected.json                       per tensor of those files: dtype, shape, values (row-major)
  values_p0.pkl .. values_p5.pkl      one plain value pickled with each protocol; values.json
                                      (no bytes: protocols 0-2 pickle them through _codecs.encode)
  bytes_p4.pkl                        b"\x00\x01abc" pickled with protocol 4
  lightning.ckpt                      a PyTorch Lightning-style checkpoint of the golden tiny LAM
                                      (state_dict beside optimizer, scheduler, callback and
                                      hyper-parameter state)
  wan_vae.pth                         the golden tiny Wan2.1 VAE as a flat dict (legacy format)
  dit_lora.pt                         the golden tiny DiT with PEFT adapters (rank 4, alpha 8) on
                                      q/k/v/output_proj and mlp.layer1/2, unmerged
  dit_action384_ema_bf16.pt           the tiny DiT with action MLPs reading the 384-d action layout,
                                      net.* in bf16 (a model_ema_bf16.pt as the release converts)
  prompt_embedding.pt                 a bare bf16 tensor [3, 4] (arange), as a prompt-embedding asset
  evil_*.pt                           files whose unpickling runs `touch MARKER_PATH`
"""
import collections
import json
import os
import pickle
import shutil
import struct
import subprocess
import sys

import torch

out, marker, golden = sys.argv[1], sys.argv[2], sys.argv[3]
torch.manual_seed(7)


def read_safetensors(path):
    dtypes = {"F32": torch.float32, "I64": torch.int64, "BF16": torch.bfloat16}
    with open(path, "rb") as f:
        n = struct.unpack("<Q", f.read(8))[0]
        header = json.loads(f.read(n))
        data = f.read()
    tensors = collections.OrderedDict()
    for name, info in header.items():
        if name == "__metadata__":
            continue
        begin, end = info["data_offsets"]
        t = torch.frombuffer(bytearray(data[begin:end]), dtype=dtypes[info["dtype"]])
        tensors[name] = t.reshape(info["shape"]).clone()
    return tensors


# --- every dtype, views and shared storages ---
base = torch.randn(4, 6)
tensors = collections.OrderedDict()
tensors["f32"] = torch.randn(3, 5)
tensors["f64"] = torch.randn(2, 3, dtype=torch.float64)
tensors["f16"] = torch.randn(7).half()
tensors["bf16"] = torch.randn(2, 4).bfloat16()
tensors["i64"] = torch.arange(-5, 7, dtype=torch.int64).reshape(3, 4)
tensors["i32"] = torch.arange(10, dtype=torch.int32) * -3
tensors["i16"] = torch.arange(4, dtype=torch.int16)
tensors["i8"] = torch.tensor([-128, 0, 127], dtype=torch.int8)
tensors["u8"] = torch.tensor([0, 200, 255], dtype=torch.uint8)
tensors["bool"] = torch.tensor([True, False, True])
tensors["scalar"] = torch.tensor(2.5)
tensors["empty"] = torch.zeros(0, 3)
tensors["base"] = base
tensors["rows_1_to_3"] = base[1:3]  # storage offset 6
tensors["transposed"] = base.t()  # strides (1, 6)
tensors["column"] = base[:, 2]  # offset 2, stride 6
nested = {"layer": {"weight": torch.randn(2, 2)}, "list": [torch.ones(1), torch.zeros(2)]}
tensors_and_nested = dict(tensors)
tensors_and_nested["nested"] = nested
torch.save(tensors_and_nested, os.path.join(out, "tensors_zip.pt"))
torch.save(tensors_and_nested, os.path.join(out, "tensors_legacy.pt"), _use_new_zipfile_serialization=False)
expected = {}
flat = dict(tensors)
flat["nested.layer.weight"] = nested["layer"]["weight"]
flat["nested.list.0"] = nested["list"][0]
flat["nested.list.1"] = nested["list"][1]
for name, t in flat.items():
    expected[name] = {
        "dtype": str(t.dtype).replace("torch.", ""),
        "shape": list(t.shape),
        "values": t.double().reshape(-1).tolist(),
    }
with open(os.path.join(out, "expected.json"), "w") as f:
    json.dump(expected, f)

# --- plain values with every protocol ---
value = {
    "ints": [0, 1, -1, 255, 256, 65535, 65536, -2**31, 2**31 - 1, 2**40, -2**63, 2**63 - 1],
    "floats": [0.5, -1.25, 1e300],
    "text": ["", "ascii", "\u00e9t\u00e9 \u2603"],
    "flags": [True, False, None],
    "tuple": (1, (2, 3), ()),
    "set": {3, 1, 2},
    "frozen": frozenset({"a"}),
    "nested": {"a": {"b": [1, {"c": 2}]}},
    "shared": [[7, 8]] * 2,
}
for protocol in range(6):
    with open(os.path.join(out, "values_p%d.pkl" % protocol), "wb") as f:
        pickle.dump(value, f, protocol=protocol)


def jsonable(v):
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, (set, frozenset)):
        return sorted(jsonable(x) for x in v)
    if isinstance(v, (list, tuple)):
        return [jsonable(x) for x in v]
    if isinstance(v, bytes):
        return v.decode("latin-1")
    return v


with open(os.path.join(out, "values.json"), "w") as f:
    json.dump(jsonable(value), f)
with open(os.path.join(out, "bytes_p4.pkl"), "wb") as f:
    pickle.dump(b"\x00\x01abc", f, protocol=4)

# --- a Lightning-style LAM checkpoint ---
lam = read_safetensors(os.path.join(golden, "lam_tiny_weights.safetensors"))
ckpt = {
    "epoch": 3,
    "global_step": 400000,
    "pytorch-lightning_version": "2.1.0",
    "state_dict": collections.OrderedDict((k, v) for k, v in lam.items()),
    "loops": {"fit_loop": {"state_dict": {}, "epoch_progress": {"total": {"ready": 4, "completed": 3}}}},
    "callbacks": {"ModelCheckpoint{'monitor': None}": {"best_model_score": torch.tensor(0.25), "dirpath": "/ckpt"}},
    "optimizer_states": [{
        "state": {0: {"step": torch.tensor(5.0), "exp_avg": torch.randn(3), "exp_avg_sq": torch.rand(3)}},
        "param_groups": [{"lr": 1e-4, "betas": (0.9, 0.999), "eps": 1e-8, "weight_decay": 0.0, "params": [0]}],
    }],
    "lr_schedulers": [{"base_lrs": [1e-4], "last_epoch": 3, "_step_count": 4}],
    "hparams_name": "kwargs",
    "hyper_parameters": {"lr": 1e-4, "model_dim": 64, "patch_size": 8, "betas": (0.9, 0.999)},
}
torch.save(ckpt, os.path.join(out, "lightning.ckpt"))

# --- the Wan2.1 VAE as a flat legacy-format dict ---
vae = read_safetensors(os.path.join(golden, "wan21_vae_tiny_weights.safetensors"))
torch.save(vae, os.path.join(out, "wan_vae.pth"), _use_new_zipfile_serialization=False)

# --- the tiny DiT with unmerged PEFT adapters: base = W - alpha/r B A, so merging gives W back ---
dit = read_safetensors(os.path.join(golden, "dit_tiny_weights.safetensors"))
rank, alpha = 4, 8.0
lora = collections.OrderedDict()
for name, w in dit.items():
    key = name if name.startswith("net.") else "net." + name
    layer = key[: -len(".weight")]
    if key.endswith(".weight") and any(layer.endswith(t) for t in
                                       ("q_proj", "k_proj", "v_proj", "output_proj", "mlp.layer1", "mlp.layer2")):
        a = torch.randn(rank, w.shape[1]) * 0.1
        b = torch.randn(w.shape[0], rank) * 0.1
        lora[layer + ".base_layer.weight"] = w - (alpha / rank) * (b @ a)
        lora[layer + ".lora_A.default.weight"] = a
        lora[layer + ".lora_B.default.weight"] = b
    else:
        lora[key] = w
torch.save(lora, os.path.join(out, "dit_lora.pt"))

# --- the tiny DiT reading the released 384-d action vector (4 rows per latent frame), as the
# official converter writes model_ema_bf16.pt: net.* in bf16. Rolls out on robot data. ---
dit384 = collections.OrderedDict()
for name, w in dit.items():
    key = name if name.startswith("net.") else "net." + name
    if key.endswith("fc1.weight") and "action_embedder" in key:
        w = torch.randn(w.shape[0], 384 * 4) / (384 * 4) ** 0.5
    dit384[key] = w.bfloat16() if w.is_floating_point() else w
torch.save(dit384, os.path.join(out, "dit_action384_ema_bf16.pt"))


# --- a prompt embedding saved as a bare tensor (as the released empty-prompt asset is) ---
torch.save(torch.arange(12.0).reshape(3, 4).bfloat16(), os.path.join(out, "prompt_embedding.pt"))

# --- files that run a command when Python unpickles them ---
class RunsACommand:
    def __init__(self, fn, args):
        self.fn, self.args = fn, args

    def __reduce__(self):
        return self.fn, self.args


touch = "touch " + marker
evil = {
    "os_system": RunsACommand(os.system, (touch,)),
    "builtins_eval": RunsACommand(eval, ("__import__('os').system(%r)" % touch,)),
    "subprocess_popen": RunsACommand(subprocess.Popen, (["touch", marker],)),
    "other_global": RunsACommand(shutil.rmtree, (marker + ".missing_dir", True)),
}
for name, payload in evil.items():
    torch.save({"weight": torch.zeros(2), "payload": payload}, os.path.join(out, "evil_%s.pt" % name))
torch.save({"weight": torch.zeros(2), "payload": evil["os_system"]}, os.path.join(out, "evil_legacy.pt"),
           _use_new_zipfile_serialization=False)
with open(os.path.join(out, "evil_metadata.pkl"), "wb") as f:
    pickle.dump(evil["os_system"], f, protocol=4)
