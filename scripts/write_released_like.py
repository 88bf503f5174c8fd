"""Writes a checkpoint file in the released layout with random weights, for timing `dojo convert`
on a full-size model: python3 scripts/write_released_like.py KEYS.tsv OUT.pt [--dtype bf16|fp32]
[--legacy]. KEYS.tsv is a released key list (tests/golden/keys/dit_2B_action384_keys.tsv): one
`name<TAB>[shape]<TAB>dtype` per line. Needs Python's torch (Debian's python3-torch will do)."""
import argparse
import collections
import json

import torch

parser = argparse.ArgumentParser()
parser.add_argument("keys")
parser.add_argument("out")
parser.add_argument("--dtype", default="bf16", choices=["bf16", "fp32"])
parser.add_argument("--legacy", action="store_true")
args = parser.parse_args()
dtype = torch.bfloat16 if args.dtype == "bf16" else torch.float32
torch.manual_seed(0)
state = collections.OrderedDict()
for line in open(args.keys):
    name, shape, kind = line.rstrip("\n").split("\t")
    shape = json.loads(shape)
    if kind == "int64":
        state[name] = torch.zeros(shape, dtype=torch.int64)
    else:
        fan_in = shape[1] if len(shape) == 2 else 1
        state[name] = (torch.randn(shape) / fan_in ** 0.5).to(dtype)
torch.save(state, args.out, _use_new_zipfile_serialization=not args.legacy)
print(args.out, sum(t.numel() for t in state.values()), "parameters")
