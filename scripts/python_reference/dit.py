"""The action-conditioned DiT of this engine (src/models/dit.{h,cpp}) written again in plain
PyTorch, as a user of the Python release would run it: the speed reference that
scripts/python_speed.sh times beside the C++ engine. Parameter names equal the engine's state
dict, so the weights `dojo wm step-speed --export` writes load strictly; step_speed.py checks that
both compute the same numbers before it times anything.

Everything here runs with Debian 12's python3-torch (1.13) and its standard library alone.
"""
import json
import math
import struct

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

_DTYPES = {"F32": np.float32, "F64": np.float64, "I64": np.int64, "U8": np.uint8,
           "BOOL": np.bool_, "I32": np.int32}


def read_safetensors(path):
    """Tensors of a .safetensors file by name (no code runs from the file: a JSON header and raw
    little-endian arrays)."""
    with open(path, "rb") as f:
        data = f.read()
    (header_len,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8:8 + header_len])
    base = 8 + header_len
    out = {}
    for name, spec in header.items():
        if name == "__metadata__":
            continue
        start, end = spec["data_offsets"]
        array = np.frombuffer(data, dtype=_DTYPES[spec["dtype"]], count=(end - start) //
                              np.dtype(_DTYPES[spec["dtype"]]).itemsize, offset=base + start)
        out[name] = torch.from_numpy(array.copy()).reshape(spec["shape"])
    return out


class RmsNorm(nn.Module):
    def __init__(self, dim, eps=1e-6):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(dim))
        self.eps = eps

    def forward(self, x):
        return x * torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + self.eps) * self.weight


def rotate(x, cos, sin):
    """Non-interleaved rotate-half RoPE: x [..., L, heads, d], cos/sin broadcastable."""
    half = x.shape[-1] // 2
    return x * cos + torch.cat([-x[..., half:], x[..., :half]], -1) * sin


def attention(q, k, v):
    scores = torch.matmul(q, k.transpose(-2, -1)) * (1.0 / math.sqrt(q.shape[-1]))
    return torch.matmul(torch.softmax(scores, -1), v)


class Attention(nn.Module):
    def __init__(self, dim, context_dim, heads, head_dim):
        super().__init__()
        inner = heads * head_dim
        self.heads, self.head_dim = heads, head_dim
        self.q_proj = nn.Linear(dim, inner, bias=False)
        self.q_norm = RmsNorm(head_dim)
        self.k_proj = nn.Linear(context_dim, inner, bias=False)
        self.k_norm = RmsNorm(head_dim)
        self.v_proj = nn.Linear(context_dim, inner, bias=False)
        self.output_proj = nn.Linear(inner, dim, bias=False)

    def split(self, x):  # [B, L, h·d] -> [B, L, h, d]
        return x.view(x.shape[0], x.shape[1], self.heads, self.head_dim)

    def merge(self, o):  # [B, h, L, d] -> [B, L, h·d]
        return self.output_proj(o.transpose(1, 2).reshape(o.shape[0], o.shape[2], -1))

    def self_attention(self, x, cos, sin, k_cache=None, v_cache=None):
        """-> output [B, L, D] and this call's keys (after RoPE) and values [B, h, L, d]."""
        q = rotate(self.q_norm(self.split(self.q_proj(x))), cos, sin).transpose(1, 2)
        k = rotate(self.k_norm(self.split(self.k_proj(x))), cos, sin).transpose(1, 2)
        v = self.split(self.v_proj(x)).transpose(1, 2)
        k_all, v_all = k, v
        if k_cache is not None:
            k_all, v_all = torch.cat([k_cache, k], 2), torch.cat([v_cache, v], 2)
        return self.merge(attention(q, k_all, v_all)), k, v

    def cross_attention(self, x, context):
        q = self.q_norm(self.split(self.q_proj(x))).transpose(1, 2)
        k = self.k_norm(self.split(self.k_proj(context))).transpose(1, 2)
        v = self.split(self.v_proj(context)).transpose(1, 2)
        return self.merge(attention(q, k, v))


class Mlp(nn.Module):
    def __init__(self, dim, hidden):
        super().__init__()
        self.layer1 = nn.Linear(dim, hidden, bias=False)
        self.layer2 = nn.Linear(hidden, dim, bias=False)

    def forward(self, x):
        return self.layer2(F.gelu(self.layer1(x)))


def modulation(dim, lora_dim, out):
    """adaLN-LoRA: (SiLU, down, up); called on an already SiLU'd embedding as up(down(.))."""
    return nn.Sequential(nn.SiLU(), nn.Linear(dim, lora_dim, bias=False), nn.Linear(lora_dim, out, bias=False))


def modulate(x, shift, scale):
    return F.layer_norm(x, (x.shape[-1],), eps=1e-6) * (1 + scale) + shift


class Block(nn.Module):
    def __init__(self, c):
        super().__init__()
        d, heads = c["model_channels"], c["num_heads"]
        cross = c["crossattn_proj_dim"] if c["use_crossattn_projection"] else c["crossattn_emb_channels"]
        self.self_attn = Attention(d, d, heads, d // heads)
        self.cross_attn = Attention(d, cross, heads, d // heads)
        self.mlp = Mlp(d, int(d * c["mlp_ratio"]))
        self.adaln_modulation_self_attn = modulation(d, c["adaln_lora_dim"], 3 * d)
        self.adaln_modulation_cross_attn = modulation(d, c["adaln_lora_dim"], 3 * d)
        self.adaln_modulation_mlp = modulation(d, c["adaln_lora_dim"], 3 * d)

    def forward(self, x, silu_emb, adaln_lora, cos, sin, context, k_cache=None, v_cache=None):
        """x [B, T, S, D] -> same, and this call's keys and values."""
        b, t, s, d = x.shape

        def mod(m):
            return (m[2](m[1](silu_emb)) + adaln_lora).unsqueeze(2).chunk(3, -1)

        sa, ca, ml = mod(self.adaln_modulation_self_attn), mod(self.adaln_modulation_cross_attn), \
            mod(self.adaln_modulation_mlp)
        r, k, v = self.self_attn.self_attention(modulate(x, sa[0], sa[1]).view(b, t * s, d), cos, sin,
                                                k_cache, v_cache)
        x = x + sa[2] * r.view(b, t, s, d)
        r = self.cross_attn.cross_attention(modulate(x, ca[0], ca[1]).view(b, t * s, d), context)
        x = r.view(b, t, s, d) * ca[2] + x
        return x + ml[2] * self.mlp(modulate(x, ml[0], ml[1])), k, v


class TimestepEmbedding(nn.Module):
    def __init__(self, dim):
        super().__init__()
        self.linear_1 = nn.Linear(dim, dim, bias=False)
        self.linear_2 = nn.Linear(dim, 3 * dim, bias=False)

    def forward(self, x):
        return self.linear_2(F.silu(self.linear_1(x)))


class ActionMlp(nn.Module):
    def __init__(self, inp, hidden, out):
        super().__init__()
        self.fc1 = nn.Linear(inp, hidden)
        self.fc2 = nn.Linear(hidden, out)

    def forward(self, x):
        return self.fc2(F.gelu(self.fc1(x), approximate="tanh"))


class FinalLayer(nn.Module):
    def __init__(self, c):
        super().__init__()
        d, p = c["model_channels"], c["patch_spatial"]
        self.linear = nn.Linear(d, p * p * c["out_channels"], bias=False)
        self.adaln_modulation = modulation(d, c["adaln_lora_dim"], 2 * d)


class RopeBuffers(nn.Module):
    def __init__(self, c):
        super().__init__()
        head_dim = c["model_channels"] // c["num_heads"]
        hw = head_dim // 6 * 2
        seq = max(c["max_img_h"] // c["patch_spatial"], c["max_img_w"] // c["patch_spatial"], c["max_frames"])
        self.register_buffer("seq", torch.arange(seq, dtype=torch.float32))
        self.register_buffer("dim_spatial_range", torch.zeros(hw // 2))
        self.register_buffer("dim_temporal_range", torch.zeros((head_dim - 2 * hw) // 2))


def rope_freqs(rng, ratio):
    dim = rng.shape[0] * 2
    return torch.reciprocal(torch.pow(10000.0 * ratio ** (dim / (dim - 2.0)), rng))


class ActionDit(nn.Module):
    def __init__(self, c):
        super().__init__()
        self.c = c
        d = c["model_channels"]
        for name in ("accum_video_sample_counter", "accum_image_sample_counter", "accum_iteration"):
            self.register_buffer(name, torch.zeros((), dtype=torch.int64))
        self.register_buffer("accum_train_in_hours", torch.zeros(()))
        p = c["patch_spatial"]
        patch_in = (c["in_channels"] + 1 + (1 if c["concat_padding_mask"] else 0)) * p * p
        self.x_embedder = nn.Module()
        self.x_embedder.proj = nn.ModuleList([nn.Identity(), nn.Linear(patch_in, d, bias=False)])
        self.pos_embedder = RopeBuffers(c)
        self.t_embedder = nn.ModuleList([nn.Identity(), TimestepEmbedding(d)])
        self.blocks = nn.ModuleList([Block(c) for _ in range(c["num_blocks"])])
        self.final_layer = FinalLayer(c)
        self.t_embedding_norm = RmsNorm(d)
        if c["use_crossattn_projection"]:
            self.crossattn_proj = nn.Sequential(nn.Linear(c["crossattn_emb_channels"], c["crossattn_proj_dim"]),
                                                nn.GELU())
        action_in = c["actions_per_latent_frame"] * c["action_dim"]
        hidden = c["action_hidden_dim"] or 4 * d
        self.action_embedder_B_D = ActionMlp(action_in, hidden, d)
        self.action_embedder_B_3D = ActionMlp(action_in, hidden, 3 * d)

    # --- pieces -----------------------------------------------------------------------------
    def rope_cos_sin(self, frames: int, hp: int, wp: int, offset: int):
        """cos, sin [L, 1, head_dim] of a (frames, hp, wp) token grid from frame `offset`."""
        c, pe = self.c, self.pos_embedder
        fh = rope_freqs(pe.dim_spatial_range, c["rope_h_extrapolation_ratio"])
        fw = rope_freqs(pe.dim_spatial_range, c["rope_w_extrapolation_ratio"])
        ft = rope_freqs(pe.dim_temporal_range, c["rope_t_extrapolation_ratio"])
        t = torch.outer(torch.arange(offset, offset + frames, dtype=torch.float32), ft)
        h = torch.outer(torch.arange(hp, dtype=torch.float32), fh)
        w = torch.outer(torch.arange(wp, dtype=torch.float32), fw)
        t = t.view(frames, 1, 1, -1).expand(frames, hp, wp, -1)
        h = h.view(1, hp, 1, -1).expand(frames, hp, wp, -1)
        w = w.view(1, 1, wp, -1).expand(frames, hp, wp, -1)
        angles = torch.cat([t, h, w, t, h, w], -1).reshape(frames * hp * wp, 1, -1)
        return angles.cos(), angles.sin()

    def temporal_shift(self, frames: int):
        """cos, sin [head_dim] that move a cached key by `frames` in time."""
        cos, sin = self.rope_cos_sin(1, 1, 1, frames)
        return cos.flatten(), sin.flatten()

    def project_context(self, context):
        return self.crossattn_proj(context) if self.c["use_crossattn_projection"] else context

    def embed(self, x, cond_mask):
        """[B, 16, T, H, W] + mask -> patches through x_embedder [B, T, Hp, Wp, D]."""
        b, _, t, h, w = x.shape
        p = self.c["patch_spatial"]
        parts = [x, cond_mask.expand(b, 1, t, h, w)]
        if self.c["concat_padding_mask"]:
            parts.append(torch.zeros(b, 1, t, h, w))
        x_in = torch.cat(parts, 1)
        ch = x_in.shape[1]
        patches = x_in.view(b, ch, t, h // p, p, w // p, p).permute(0, 2, 3, 5, 1, 4, 6) \
            .reshape(b, t, h // p, w // p, ch * p * p)
        return self.x_embedder.proj[1](patches)

    def conditioning(self, timesteps, actions, frames: int, lead: int):
        """SiLU(normalised t_emb) [B, T_t, D] and adaLN-LoRA [B, T_t, 3D]; the first `lead`
        frames get no action term."""
        d = self.c["model_channels"]
        half = d // 2
        freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32) / half)
        args = (timesteps * self.c["timestep_scale"]).unsqueeze(-1) * freqs
        t_emb = torch.cat([torch.cos(args), torch.sin(args)], -1)
        adaln_lora = self.t_embedder[1](t_emb)
        if actions is not None and frames - lead > 0:
            b = actions.shape[0]
            rows = actions.reshape(b, frames - lead, -1)
            emb_d, emb_3d = self.action_embedder_B_D(rows), self.action_embedder_B_3D(rows)
            if lead > 0:
                emb_d = torch.cat([torch.zeros(b, lead, d), emb_d], 1)
                emb_3d = torch.cat([torch.zeros(b, lead, 3 * d), emb_3d], 1)
            t_emb = t_emb + emb_d
            adaln_lora = adaln_lora + emb_3d
        return F.silu(self.t_embedding_norm(t_emb)), adaln_lora

    def head(self, x, silu_emb, adaln_lora, shape):
        b, t, hp, wp = shape
        d, p, co = self.c["model_channels"], self.c["patch_spatial"], self.c["out_channels"]
        fm = (self.final_layer.adaln_modulation[2](self.final_layer.adaln_modulation[1](silu_emb)) +
              adaln_lora[..., :2 * d]).unsqueeze(2).chunk(2, -1)
        out = self.final_layer.linear(modulate(x, fm[0], fm[1]))
        return out.view(b, t, hp, wp, p, p, co).permute(0, 6, 1, 2, 4, 3, 5).reshape(b, co, t, hp * p, wp * p)

    # --- entry points -------------------------------------------------------------------------
    def forward(self, x, timesteps, cond_mask, actions):
        """A whole clip from frame 0 (teacher): velocity [B, 16, T, H, W]; timesteps [B, 1] or
        [B, T] in network units; actions [B, 4 (T - 1), A]; the text context is zeros."""
        b, _, t, h, w = x.shape
        p = self.c["patch_spatial"]
        tokens = self.embed(x, cond_mask)
        cos, sin = self.rope_cos_sin(t, h // p, w // p, 0)
        context = self.project_context(torch.zeros(b, 1, self.c["crossattn_emb_channels"]))
        silu_emb, adaln_lora = self.conditioning(timesteps, actions, t, 1)
        y = tokens.view(b, t, -1, self.c["model_channels"])
        for block in self.blocks:
            y, _, _ = block(y, silu_emb, adaln_lora, cos, sin, context)
        return self.head(y, silu_emb, adaln_lora, (b, t, h // p, w // p))

    def forward_frame(self, x, timesteps, actions, context, cos, sin, k_cache, v_cache):
        """One latent frame of a stream after frame 0 (student): x [B, 16, 1, h, w] attends the
        cached keys/values k_cache, v_cache [blocks, B, heads, Lc, d] before its own. Returns the
        velocity and this frame's keys and values [blocks, B, heads, S, d]."""
        b, _, t, h, w = x.shape
        p = self.c["patch_spatial"]
        tokens = self.embed(x, torch.zeros(b, 1, t, h, w))
        silu_emb, adaln_lora = self.conditioning(timesteps, actions, t, 0)
        y = tokens.view(b, t, -1, self.c["model_channels"])
        keys, values = [], []
        for i, block in enumerate(self.blocks):
            y, k, v = block(y, silu_emb, adaln_lora, cos, sin, context, k_cache[i], v_cache[i])
            keys.append(k)
            values.append(v)
        return self.head(y, silu_emb, adaln_lora, (b, t, h // p, w // p)), torch.stack(keys), torch.stack(values)

    def first_frame_keys(self, x, context):
        """Keys and values [blocks, B, heads, S, d] of the clean start frame at position 0 (no
        action term, time 0)."""
        b, _, t, h, w = x.shape
        p = self.c["patch_spatial"]
        tokens = self.embed(x, torch.zeros(b, 1, t, h, w))
        cos, sin = self.rope_cos_sin(t, h // p, w // p, 0)
        silu_emb, adaln_lora = self.conditioning(torch.zeros(b, 1), None, t, 1)
        y = tokens.view(b, t, -1, self.c["model_channels"])
        keys, values = [], []
        for block in self.blocks:
            y, k, v = block(y, silu_emb, adaln_lora, cos, sin, context)
            keys.append(k)
            values.append(v)
        return torch.stack(keys), torch.stack(values)


def denoise_velocity(net, x_t, x0, noise, mask, timesteps, actions):
    """The teacher's velocity with frame 0 replaced by the clean latent (conditional frames)."""
    v = net(x0 * mask + x_t * (1 - mask), timesteps, mask, actions)
    return (noise - x0) * mask + v * (1 - mask)
