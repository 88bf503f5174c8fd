#!/usr/bin/env python3
"""The Python side of scripts/python_speed.sh: replays what `dojo wm step-speed --export DIR` ran,
first checking that it computes the same numbers from the same weights and random draws (the
training step's loss, gradient norm and updated weights, a sampling step's velocity, the
student's streamed latents), then timing the same steps the same number of times.

    /usr/bin/python3 scripts/python_reference/step_speed.py DIR [--mode eager|scripted] [--threads N]

Modes: eager is plain PyTorch; scripted is TorchScript by tracing (torch.jit.trace; for the
sampling and streaming steps also torch.jit.freeze, as for deployment). Prints one JSON report.
"""
import argparse
import ctypes
import json
import math
import os
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from dit import ActionDit, denoise_velocity, read_safetensors, rotate  # noqa: E402


def fail(message):
    print(f"step_speed.py: {message}", file=sys.stderr)
    sys.exit(1)


def openblas_facts():
    """Kernel set and thread count of the OpenBLAS this process mapped, if any."""
    with open("/proc/self/maps") as maps:
        paths = {line.split()[-1] for line in maps if "openblas" in line and "/" in line}
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
            lib.openblas_get_corename.restype = ctypes.c_char_p
            return {"library": path, "kernels": lib.openblas_get_corename().decode(),
                    "threads": lib.openblas_get_num_threads()}
        except (OSError, AttributeError):
            continue
    return {}


def summarize(ms, items, unit):
    ms = sorted(ms)
    mean = sum(ms) / len(ms)
    return {"steps": len(ms), "ms_mean": mean, "ms_p50": ms[len(ms) // 2], "ms_min": ms[0],
            f"{unit}_per_second": 1000.0 * items / mean}


def timed(fn, warmup, repeats):
    ms = []
    for i in range(warmup + repeats):
        start = time.perf_counter()
        fn()
        if i >= warmup:
            ms.append(1000.0 * (time.perf_counter() - start))
    return ms


def frame0_mask(x0):
    mask = torch.zeros(x0.shape[0], 1, *x0.shape[2:])
    mask[:, :, 0] = 1
    return mask


class Velocity(torch.nn.Module):
    """denoise_velocity as one module, so that tracing sees the whole step."""

    def __init__(self, net):
        super().__init__()
        self.net = net

    def forward(self, x_t, x0, noise, mask, timesteps, actions):
        return denoise_velocity(self.net, x_t, x0, noise, mask, timesteps, actions)


class Frame(torch.nn.Module):
    """ActionDit.forward_frame as a module's forward, for tracing."""

    def __init__(self, net):
        super().__init__()
        self.net = net

    def forward(self, x, timesteps, actions, context, cos, sin, k_cache, v_cache):
        return self.net.forward_frame(x, timesteps, actions, context, cos, sin, k_cache, v_cache)


def freeze(module, example):
    traced = torch.jit.trace(module.eval(), example, check_trace=False)
    return torch.jit.freeze(traced)


# --- sampling ---------------------------------------------------------------------------------
def sampling(net, report, args, out):
    s = read_safetensors(os.path.join(args.dir, "sample.safetensors"))
    sigma = s["sigma"]
    x_t = sigma.view(-1, 1, 1, 1, 1) * s["noise"] + (1 - sigma.view(-1, 1, 1, 1, 1)) * s["x0"]
    inputs = (x_t, s["x0"], s["noise"], frame0_mask(s["x0"]), sigma * 1000.0, s["actions"])
    with torch.inference_mode():
        fn = Velocity(net).eval() if args.mode == "eager" else None
    if args.mode == "scripted":
        with torch.no_grad():
            fn = freeze(Velocity(net), inputs)
    with torch.no_grad() if args.mode == "scripted" else torch.inference_mode():
        diff = (fn(*inputs) - s["velocity"]).abs().max().item()
        out["checks"]["sample_velocity_max_abs_diff"] = diff
        ms = timed(lambda: fn(*inputs), report["warmup"], report["repeats"])
    out["sample"] = summarize(ms, x_t.shape[0], "clips")


# --- streaming --------------------------------------------------------------------------------
class Stream:
    """The student's stream as the engine runs it (src/infer/streaming.cpp, training alignment):
    per latent frame 4 hops over the cached window, then the clean pass that stores the frame.
    The window keeps the last `window` frames, the first `sink` of them for good (moved in time
    to the window's oldest positions)."""

    def __init__(self, net, frame_fn, student, z0, seed):
        if student["sink_position"] != "window_edge" or student["action_alignment"] != "training":
            fail("only the window_edge sink and the training alignment are replayed")
        self.net, self.frame_fn = net, frame_fn
        self.window, self.sink = student["window_frames"], student["sink_frames"]
        self.schedule = student["schedule"]
        self.gen = torch.Generator().manual_seed(seed)
        self.shape = z0.shape
        self.hp, self.wp = z0.shape[3] // net.c["patch_spatial"], z0.shape[4] // net.c["patch_spatial"]
        self.context = net.project_context(torch.zeros(z0.shape[0], 1, net.c["crossattn_emb_channels"]))
        k, v = net.first_frame_keys(z0, self.context)  # [blocks, B, heads, S, d]
        self.keys, self.values = [k], [v]
        self.frames = 1

    def window_kv(self):
        keys = list(self.keys)
        target = max(0, self.frames - self.window)
        if self.sink > 0 and target > 0:
            cos, sin = self.net.temporal_shift(target)
            keys[:self.sink] = [rotate(k, cos, sin) for k in keys[:self.sink]]
        return torch.cat(keys, 3), torch.cat(self.values, 3)

    def step(self, actions):
        noise = torch.randn(self.shape, generator=self.gen)
        k_cache, v_cache = self.window_kv()
        cos, sin = self.net.rope_cos_sin(1, self.hp, self.wp, self.frames)
        b = noise.shape[0]
        x = noise
        for i, hop in enumerate(self.schedule):
            t = torch.full((b, 1), 1000.0 * hop["c_noise"])
            v = self.frame_fn(x * hop["c_in"], t, actions, self.context, cos, sin, k_cache, v_cache)[0]
            x0 = x * hop["c_skip"] + v * hop["c_out"]
            if i + 1 < len(self.schedule):
                t_next = self.schedule[i + 1]["trigflow_t"]
                x = x0 * math.cos(t_next) + noise * math.sin(t_next)
        _, k, v = self.frame_fn(x0, torch.zeros(b, 1), actions, self.context, cos, sin, k_cache, v_cache)
        self.keys.append(k)
        self.values.append(v)
        if len(self.keys) > self.window:
            keep = self.window - self.sink
            self.keys = self.keys[:self.sink] + self.keys[len(self.keys) - keep:]
            self.values = self.values[:self.sink] + self.values[len(self.values) - keep:]
        self.frames += 1
        if self.frames > self.net.pos_embedder.seq.shape[0]:
            fail("the stream left the RoPE table (the engine would rebase; time fewer steps)")
        return x0


def streaming(net, report, args, out):
    s = read_safetensors(os.path.join(args.dir, "stream.safetensors"))
    student = report["student"]
    with torch.inference_mode():
        frame_fn = Frame(net).eval()
        if args.mode == "scripted":
            # Traced at the steady state's shapes (a full window); the traced graph keeps the cache
            # length symbolic, so the steps that fill the window run through it too.
            probe = Stream(net, frame_fn, student, s["z0"], report["stream"]["stream_seed"])
            k, v = probe.window_kv()
            full_k = k.repeat(1, 1, 1, student["window_frames"], 1)
            full_v = v.repeat(1, 1, 1, student["window_frames"], 1)
            cos, sin = net.rope_cos_sin(1, probe.hp, probe.wp, 1)
            example = (torch.randn(s["z0"].shape), torch.zeros(1, 1), s["actions"][0], probe.context, cos, sin,
                       full_k, full_v)
    if args.mode == "scripted":
        with torch.no_grad():
            frame_fn = freeze(Frame(net), tuple(t.clone() for t in example))
    guard = torch.no_grad if args.mode == "scripted" else torch.inference_mode
    with guard():
        stream = Stream(net, frame_fn, student, s["z0"], report["stream"]["stream_seed"])
        worst = 0.0
        for i in range(s["actions"].shape[0]):
            worst = max(worst, (stream.step(s["actions"][i]) - s["latents"][i]).abs().max().item())
        out["checks"]["stream_latents_max_abs_diff"] = worst
        step_actions = s["actions"][0]
        ms = timed(lambda: stream.step(step_actions), report["warmup"], report["stream"]["steps"])
    out["stream"] = summarize(ms, 4, "frames")


# --- training ---------------------------------------------------------------------------------
class Trainer:
    """WmTrainer::step (src/train/wm_train.cpp) with the released defaults: the flow-matching loss
    with the temporal term, AdamW with a linear warm-up, global-norm clipping, the power EMA."""

    def __init__(self, forward, params, options, gamma, grid):
        self.forward, self.params, self.o, self.gamma, self.grid = forward, params, options, gamma, grid
        for key in ("condition_noise", "motion_weight", "action_dropout"):
            if options.get(key, 0) != 0:
                fail(f"training option {key} is not replayed")
        flow = options["flow"]
        if flow.get("high_sigma_prob", 0) != 0 or flow.get("temporal_axis", "time") != "time":
            fail("only the plain logit-normal times and the temporal axis 'time' are replayed")
        self.flow = flow
        self.ema = [p.detach().clone() for p in params]
        self.opt = torch.optim.AdamW(params, lr=options["lr"], weight_decay=options["weight_decay"])
        self.steps = 0

    def step(self, x0, actions, gen):
        o, flow = self.o, self.flow
        lr = o["lr"] * min(1.0, (self.steps + 1) / o["warmup_steps"]) if o["warmup_steps"] > 0 else o["lr"]
        for group in self.opt.param_groups:
            group["lr"] = lr
        self.opt.zero_grad()
        b = x0.shape[0]
        u = torch.sigmoid(torch.randn(b, generator=gen, dtype=torch.float64))
        index = (u * self.grid).long().clamp(0, self.grid - 1).double()
        s = (self.grid - index) / self.grid
        sigma = (flow["shift"] * s / (1.0 + (flow["shift"] - 1.0) * s)).float()
        timesteps = (1000.0 * (flow["shift"] * s / (1.0 + (flow["shift"] - 1.0) * s))).float()
        noise = torch.randn(x0.shape, generator=gen, dtype=torch.float32)
        sv = sigma.view(b, 1, 1, 1, 1)
        x_t = sv * noise + (1 - sv) * x0
        target = noise - x0
        v = self.forward(x_t, x0, noise, frame0_mask(x0), timesteps.view(b, 1), actions)
        loss = (v - target).pow(2).reshape(b, -1).mean(1)
        if flow["temporal_weight"] != 0 and x0.shape[2] > 1:
            dv, dt = v[:, :, 1:] - v[:, :, :-1], target[:, :, 1:] - target[:, :, :-1]
            loss = loss + flow["temporal_weight"] * (dv - dt).pow(2).reshape(b, -1).mean(1)
        loss = loss.mean()
        loss.backward()
        value = loss.item()
        clip = o["grad_clip"] if o["grad_clip"] > 0 else float("inf")
        grad_norm = torch.nn.utils.clip_grad_norm_(self.params, clip).item()
        self.opt.step()
        self.steps += 1
        beta = (1.0 - 1.0 / (self.steps + 1)) ** (self.gamma + 1)
        with torch.no_grad():
            for e, p in zip(self.ema, self.params):
                e.mul_(beta).add_(p.detach(), alpha=1.0 - beta)
        return value, grad_norm


def training(net, report, args, out):
    t = read_safetensors(os.path.join(args.dir, "train.safetensors"))
    x0, actions = t["x0"], t["actions"]
    net.train()
    forward = Velocity(net)
    if args.mode == "scripted":
        example = (torch.randn(x0.shape), x0, torch.randn(x0.shape), frame0_mask(x0), torch.rand(x0.shape[0], 1),
                   actions)
        forward = torch.jit.trace(forward, example, check_trace=False)
    params = [p for p in net.parameters() if p.requires_grad]
    trainer = Trainer(forward, params, report["train"]["options"], report["train"]["ema_gamma"],
                      report["train"]["flow_grid"])
    seed = report["train"]["step_seed"]
    init = {name: p.detach().clone() for name, p in net.named_parameters()}
    loss, grad_norm = trainer.step(x0, actions, torch.Generator().manual_seed(seed))
    checks = out["checks"]
    checks["train_loss"] = [loss, t["loss"].item()]
    checks["train_loss_rel_diff"] = abs(loss - t["loss"].item()) / abs(t["loss"].item())
    checks["train_grad_norm_rel_diff"] = abs(grad_norm - t["grad_norm"].item()) / abs(t["grad_norm"].item())
    # The weights after one AdamW step, against the size of the step itself.
    update = max((t["after." + n] - init[n]).abs().max().item() for n in init)
    diff = max((p.detach() - t["after." + n]).abs().max().item() for n, p in net.named_parameters())
    ema = dict(zip([n for n, p in net.named_parameters() if p.requires_grad], trainer.ema))
    ema_diff = max((e - t["ema." + n]).abs().max().item() for n, e in ema.items())
    checks["train_update_max_abs"] = update
    checks["train_weights_max_abs_diff"] = diff
    checks["train_ema_max_abs_diff"] = ema_diff
    step = [1]

    def one():
        trainer.step(x0, actions, torch.Generator().manual_seed(seed + step[0]))
        step[0] += 1
    ms = timed(one, report["warmup"] - 1, report["repeats"])  # the checked step was the first warm-up
    out["train"] = summarize(ms, x0.shape[0], "clips")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dir", help="the directory `dojo wm step-speed --export` wrote")
    parser.add_argument("--mode", choices=["eager", "scripted"], default="eager")
    parser.add_argument("--threads", type=int, default=1, help="intra-op threads (dojo: 1 for these steps)")
    parser.add_argument("--only", nargs="*", default=["sample", "stream", "train"])
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    with open(os.path.join(args.dir, "config.json")) as f:
        report = json.load(f)
    report["repeats"] = report["train"]["steps"]
    c = report["model"]
    if c.get("action_scale") or c.get("whole_clip_actions", 0) or "lora" in c:
        fail("the model uses action scaling, whole-clip actions or LoRA, which the reference does not replay")
    net = ActionDit(c)
    net.load_state_dict(read_safetensors(os.path.join(args.dir, "weights.safetensors")), strict=True)
    out = {"mode": args.mode, "threads": torch.get_num_threads(), "torch": torch.__version__,
           "python": sys.version.split()[0], "openblas": openblas_facts(), "checks": {}}
    steps = {"sample": sampling, "stream": streaming, "train": training}
    for name in args.only:
        fresh = ActionDit(c)
        fresh.load_state_dict(net.state_dict(), strict=True)
        steps[name](fresh, report, args, out)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
