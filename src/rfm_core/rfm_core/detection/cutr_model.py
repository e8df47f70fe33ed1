"""Cubify Transformer (CuTR) in PyTorch, checkpoint-compatible with the official release.

A from-scratch implementation of ``../shared/docs/cutr-architecture.md`` (the spec of the
``apple/ml-cubifyanything`` model): module names and shapes give exactly the official
state_dict keys, so ``cutr_rgb.pth`` / ``cutr_rgbd.pth`` load with ``strict=True``, and the
forward pass follows the spec's sections (2.1 preprocessing ... 2.9 post-processing).

Model: a ViTDet-style ViT-B/16 backbone (RGB-D: depth tokens fused in the windowed blocks),
a 1x1 neck, Plain-DETR two-stage proposals over three levels, 300 object queries plus two
metric queries through 6 decoder layers with box-relative cross-attention bias, and per-layer
heads for class, 2D box, 3D box and the metric scale.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

__all__ = ['CubifyTransformer', 'preprocess', 'gravity_tensor', 'PIXEL_MEAN', 'PIXEL_STD']

PIXEL_MEAN = (123.675, 116.28, 103.53)
PIXEL_STD = (58.395, 57.12, 57.375)
EMBED_DIM, DEC_DIM, NUM_QUERIES, TOP_K = 768, 256, 300, 100
WINDOW = 16
WINDOWED_BLOCKS = (0, 1, 3, 4, 6, 7, 9, 10)
DELTA_CLAMP = math.log(1.0 / 0.016)


# ----------------------------------------------------------------------------- backbone

class PatchEmbed(nn.Module):
    def __init__(self, in_chans: int, dim: int = EMBED_DIM):
        super().__init__()
        self.proj = nn.Conv2d(in_chans, dim, kernel_size=16, stride=16)

    def forward(self, x):                       # (B, C, H, W) -> (B, H/16, W/16, D)
        return self.proj(x).permute(0, 2, 3, 1)


class Attention(nn.Module):
    def __init__(self, dim: int = EMBED_DIM, heads: int = 12):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def attend(self, x):                        # (B, N, D) -> (B, N, D), before proj
        b, n, d = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(qkv[0], qkv[1], qkv[2])   # scale (d/h)^-1/2
        return out.transpose(1, 2).reshape(b, n, d)

    def forward(self, x):
        return self.proj(self.attend(x))


class Mlp(nn.Module):
    def __init__(self, dim: int = EMBED_DIM, hidden: int = 4 * EMBED_DIM):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x):
        return self.fc2(F.gelu(self.fc1(x)))


class LayerScale(nn.Module):
    def __init__(self, dim: int = EMBED_DIM):
        super().__init__()
        self.gamma = nn.Parameter(torch.ones(dim))

    def forward(self, x):
        return x * self.gamma


def _windows(x, size):
    """(B, H, W, C) -> (B * nW, size, size, C), zero-padded; and the padded (H, W)."""
    b, h, w, c = x.shape
    ph, pw = (-h) % size, (-w) % size
    if ph or pw:
        x = F.pad(x, (0, 0, 0, pw, 0, ph))
    hp, wp = h + ph, w + pw
    x = x.view(b, hp // size, size, wp // size, size, c).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(-1, size, size, c), (hp, wp)


def _unwindow(x, size, padded, hw):
    hp, wp = padded
    b = x.shape[0] // ((hp // size) * (wp // size))
    x = x.view(b, hp // size, wp // size, size, size, -1).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(b, hp, wp, -1)[:, :hw[0], :hw[1]]


class Block(nn.Module):
    def __init__(self, windowed: bool, layer_scale: bool):
        super().__init__()
        self.windowed = windowed
        self.norm1 = nn.LayerNorm(EMBED_DIM, eps=1e-6)
        self.attn = Attention()
        self.norm2 = nn.LayerNorm(EMBED_DIM, eps=1e-6)
        self.mlp = Mlp()
        if layer_scale:
            self.ls1 = LayerScale()
            self.ls2 = LayerScale()
        self.layer_scale = layer_scale

    def _scale(self, name, x):
        return getattr(self, name)(x) if self.layer_scale else x

    def forward(self, x, depth=None):
        """x: image tokens (B, h, w, D); depth: depth tokens (B, hd, wd, D) or None."""
        b, h, w, d = x.shape
        xn = self.norm1(x)
        if not self.windowed:
            out = self.attn(xn.reshape(b, h * w, d)).reshape(b, h, w, d)
        elif depth is None:
            win, padded = _windows(xn, WINDOW)
            out = self.attn(win.reshape(win.shape[0], -1, d)).reshape(win.shape)
            out = _unwindow(out, WINDOW, padded, (h, w))
        else:
            ratio = h // depth.shape[1] if depth.shape[1] else 1
            dsize = WINDOW // max(ratio, 1)
            if dsize not in (4, 8, 16):
                raise ValueError(f'image/depth token ratio {ratio} unsupported (depth windows '
                                 f'of {dsize}); depth must be 1/1, 1/2 or 1/4 of the image size')
            win, padded = _windows(xn, WINDOW)
            dwin, dpadded = _windows(self.norm1(depth), dsize)
            if dwin.shape[0] != win.shape[0]:
                raise ValueError('image and depth windows do not line up; check the depth size')
            n_img = WINDOW * WINDOW
            tokens = torch.cat([win.reshape(win.shape[0], n_img, d),
                                dwin.reshape(dwin.shape[0], -1, d)], 1)
            fused = self.attn(tokens)
            out = _unwindow(fused[:, :n_img].reshape(win.shape), WINDOW, padded, (h, w))
            dout = _unwindow(fused[:, n_img:].reshape(dwin.shape), dsize, dpadded, depth.shape[1:3])
            depth = depth + dout
            depth = depth + self.mlp(self.norm2(depth))
        x = x + self._scale('ls1', out)
        x = x + self._scale('ls2', self.mlp(self.norm2(x)))
        return x, depth


class ViT(nn.Module):
    def __init__(self, rgbd: bool):
        super().__init__()
        self.rgbd = rgbd
        grid = 14 if rgbd else 32
        # registration order follows the official state_dict
        self.pos_embed = nn.Parameter(torch.zeros(1, grid * grid + 1, EMBED_DIM))
        self.patch_embed = PatchEmbed(3)
        if rgbd:
            self.patch_embed_depth = PatchEmbed(1)
            self.pos_embed_depth = nn.Parameter(torch.zeros(1, grid * grid + 1, EMBED_DIM))
        self.blocks = nn.ModuleList(Block(i in WINDOWED_BLOCKS, layer_scale=not rgbd)
                                    for i in range(12))
        if not rgbd:
            self.encoder_norm = nn.LayerNorm(EMBED_DIM, eps=1e-6)

    @staticmethod
    def _add_pos(tokens, pos):
        g = int(math.isqrt(pos.shape[1] - 1))
        grid = pos[:, 1:].reshape(1, g, g, -1).permute(0, 3, 1, 2)
        grid = F.interpolate(grid, size=tokens.shape[1:3], mode='bicubic', align_corners=False)
        return tokens + grid.permute(0, 2, 3, 1)

    def forward(self, image, depth=None):
        x = self._add_pos(self.patch_embed(image), self.pos_embed)
        d = None
        if self.rgbd and depth is not None:
            d = self._add_pos(self.patch_embed_depth(depth), self.pos_embed_depth)
        for block in self.blocks:
            if block.windowed:
                x, d = block(x, d)
            else:                               # global blocks leave depth tokens unchanged
                x, _ = block(x)
        if not self.rgbd:
            x = self.encoder_norm(x)
        return x.permute(0, 3, 1, 2)            # (B, D, h, w)


class Backbone(nn.Sequential):
    """The official model wraps the ViT in a one-element Sequential: keys 'backbone.0.'."""

    def forward(self, image, depth=None):  # noqa: D102
        return self[0](image, depth)


# ----------------------------------------------------------------------------- heads

class MLP(nn.Module):
    def __init__(self, out: int, dim: int = DEC_DIM):
        super().__init__()
        self.layers = nn.ModuleList([nn.Linear(dim, dim), nn.Linear(dim, dim), nn.Linear(dim, out)])

    def forward(self, x):
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i < len(self.layers) - 1:
                x = F.relu(x)
        return x


class ClassHead(nn.Module):
    def __init__(self):
        super().__init__()
        self.linear = nn.Linear(DEC_DIM, 2)

    def forward(self, x):
        return self.linear(x)


class DeltaBoxHead(nn.Module):
    def __init__(self, out: int = 4):
        super().__init__()
        self.mlp = MLP(out)

    def forward(self, x):
        return self.mlp(x)


class ScaleShiftHead(nn.Module):
    def __init__(self):
        super().__init__()
        self.shift = nn.Linear(DEC_DIM, 1)
        self.scale = nn.Linear(DEC_DIM, 1)


class LayerNorm2D(nn.Module):
    def __init__(self, dim: int = DEC_DIM):
        super().__init__()
        self.ln = nn.LayerNorm(dim, eps=1e-5)

    def forward(self, x):                       # (B, C, H, W)
        return self.ln(x.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)


class BoxEncoder(nn.Module):
    """2D box -> 256-d embedding: integer lookups of cx, cy, w, h (pixels, clamped to 0..1279)."""

    def __init__(self):
        super().__init__()
        self.register_buffer('min_bounds', torch.zeros(4))
        self.register_buffer('max_bounds', torch.full((4,), 1279.0))
        self.x = nn.Embedding(1280, 64)
        self.y = nn.Embedding(1280, 64)
        self.w = nn.Embedding(1280, 64)
        self.h = nn.Embedding(1280, 64)

    def forward(self, boxes):                   # (..., 4) cxcywh
        idx = torch.maximum(torch.minimum(boxes, self.max_bounds), self.min_bounds).long()
        return torch.cat([self.x(idx[..., 0]), self.y(idx[..., 1]), self.w(idx[..., 2]),
                          self.h(idx[..., 3])], -1)


class Encoders(nn.Module):
    def __init__(self):
        super().__init__()
        self.box_2d_encoder = BoxEncoder()


class MetricPrompter(nn.Module):
    def __init__(self):
        super().__init__()
        self.query_embed = nn.Embedding(2, DEC_DIM)


class ProposalPrompter(nn.Module):
    def __init__(self):
        super().__init__()
        self.predictors = nn.ModuleList([ClassHead(), DeltaBoxHead(4)])
        self.query_embed = nn.Embedding(4 * NUM_QUERIES, DEC_DIM)
        self.enc_output_proj = nn.ModuleList([
            nn.Identity(),
            nn.Sequential(nn.Conv2d(DEC_DIM, DEC_DIM, 2, 2)),
            nn.Sequential(nn.Conv2d(DEC_DIM, DEC_DIM, 2, 2), LayerNorm2D(), nn.GELU(),
                          nn.Conv2d(DEC_DIM, DEC_DIM, 2, 2)),
        ])
        self.enc_output = nn.Linear(DEC_DIM, DEC_DIM)
        self.enc_output_norm = nn.LayerNorm(DEC_DIM)


class Prompting(nn.Module):
    def __init__(self):
        super().__init__()
        self.prompters = nn.ModuleList([MetricPrompter(), ProposalPrompter()])
        self.encoders = Encoders()
        for prompter in self.prompters:         # shared: serialised under three prefixes
            prompter.encoders = self.encoders


class RayPositionEmbedding(nn.Module):
    def __init__(self):
        super().__init__()
        self.proj = nn.Linear(255, DEC_DIM)


class CrossAttention(nn.Module):
    def __init__(self, heads: int = 8):
        super().__init__()
        self.heads = heads
        self.cpb_mlp1 = nn.Sequential(nn.Linear(2, 512), nn.ReLU(), nn.Linear(512, heads, bias=False))
        self.cpb_mlp2 = nn.Sequential(nn.Linear(2, 512), nn.ReLU(), nn.Linear(512, heads, bias=False))
        self.q = nn.Linear(DEC_DIM, DEC_DIM)
        self.k = nn.Linear(DEC_DIM, DEC_DIM)
        self.v = nn.Linear(DEC_DIM, DEC_DIM)
        self.proj = nn.Linear(DEC_DIM, DEC_DIM)

    def box_bias(self, boxes, hf, wf):
        """(Q, 4) cxcywh reference boxes -> (heads, Q, hf * wf) attention bias."""
        x1, x2 = boxes[:, 0] - boxes[:, 2] / 2, boxes[:, 0] + boxes[:, 2] / 2
        y1, y2 = boxes[:, 1] - boxes[:, 3] / 2, boxes[:, 1] + boxes[:, 3] / 2
        pb = 16 * (torch.arange(wf, dtype=boxes.dtype) + 0.5)
        pa = 16 * (torch.arange(hf, dtype=boxes.dtype) + 0.5)
        bx = self.cpb_mlp1(torch.stack([x1[:, None] - pb, x2[:, None] - pb], -1))   # (Q, wf, H)
        by = self.cpb_mlp2(torch.stack([y1[:, None] - pa, y2[:, None] - pa], -1))   # (Q, hf, H)
        bias = by[:, :, None, :] + bx[:, None, :, :]                                # (Q, hf, wf, H)
        return bias.reshape(boxes.shape[0], hf * wf, -1).permute(2, 0, 1)

    def forward(self, t, pos, src, src_pos, boxes, num_metric, hf, wf):
        q_len, d = t.shape
        hd = d // self.heads
        q = (self.q(t + pos) * hd ** -0.5).reshape(q_len, self.heads, hd).transpose(0, 1)
        k = self.k(src + src_pos).reshape(-1, self.heads, hd).transpose(0, 1)
        v = self.v(src).reshape(-1, self.heads, hd).transpose(0, 1)
        logits = q @ k.transpose(1, 2)                                              # (H, Q, M)
        bias = torch.zeros_like(logits)
        bias[:, num_metric:] = self.box_bias(boxes, hf, wf)
        out = torch.softmax(logits + bias, -1) @ v
        return self.proj(out.transpose(0, 1).reshape(q_len, d))


class DecoderLayer(nn.Module):
    def __init__(self):
        super().__init__()
        self.xattn = CrossAttention()
        self.norm1 = nn.LayerNorm(DEC_DIM)
        self.norm2 = nn.LayerNorm(DEC_DIM)
        self.norm3 = nn.LayerNorm(DEC_DIM)
        self.self_attn = nn.MultiheadAttention(DEC_DIM, 8)
        self.linear1 = nn.Linear(DEC_DIM, 2048)
        self.linear2 = nn.Linear(2048, DEC_DIM)


class Decoder(nn.Module):
    def __init__(self):
        super().__init__()
        self.layers = nn.ModuleList(DecoderLayer() for _ in range(6))
        self.predictors = nn.ModuleList(
            nn.ModuleList([ScaleShiftHead(), ClassHead(), DeltaBoxHead(4), DeltaBoxHead(7)])
            for _ in range(6))
        self.norm = nn.LayerNorm(DEC_DIM)


# ----------------------------------------------------------------------------- helpers

def _apply_delta(delta, ref, size):
    """Refine cxcywh reference boxes by (dx, dy, dw, dh); clamp corners to the padded image."""
    dw = delta[..., 2].clamp(-DELTA_CLAMP, DELTA_CLAMP)
    dh = delta[..., 3].clamp(-DELTA_CLAMP, DELTA_CLAMP)
    gx = ref[..., 0] + ref[..., 2] * delta[..., 0]
    gy = ref[..., 1] + ref[..., 3] * delta[..., 1]
    gw = ref[..., 2] * torch.exp(dw)
    gh = ref[..., 3] * torch.exp(dh)
    x1, x2 = (gx - gw / 2).clamp(0, size), (gx + gw / 2).clamp(0, size)
    y1, y2 = (gy - gh / 2).clamp(0, size), (gy + gh / 2).clamp(0, size)
    return torch.stack([(x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1], -1)


def gravity_tensor(gravity_down) -> np.ndarray:
    """T_gravity (3x3) of the spec from the unit "down" vector in the camera frame:
    T = Rz(gamma) Rx(beta), beta = asin(g_z), gamma = atan2(-g_x, g_y); T[:, 1] = g."""
    g = np.asarray(gravity_down, dtype=np.float64)
    g = g / np.linalg.norm(g)
    beta, gamma = np.arcsin(np.clip(g[2], -1, 1)), np.arctan2(-g[0], g[1])
    cb, sb, cg, sg = np.cos(beta), np.sin(beta), np.cos(gamma), np.sin(gamma)
    rz = np.array([[cg, -sg, 0.0], [sg, cg, 0.0], [0.0, 0.0, 1.0]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cb, -sb], [0.0, sb, cb]])
    return rz @ rx


def padded_size(height: int, width: int) -> int:
    side = max(height, width)
    if side > 1024:
        raise ValueError(f'CuTR takes images up to 1024 px on the long side, got {side}; '
                         'resize first (and scale the intrinsics)')
    s = max(256, int(math.ceil(side / 128.0)) * 128)
    return int(math.ceil(s / 32.0)) * 32


def preprocess(rgb: np.ndarray, depth: np.ndarray | None = None):
    """Spec 2.1: normalised, zero-padded image (1, 3, S, S); depth (1, 1, S/r, S/r) and its
    (mu, sigma), or None. ``rgb`` is upright uint8 (H, W, 3); depth in metres, 0 / NaN invalid."""
    h, w = rgb.shape[:2]
    s = padded_size(h, w)
    img = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float()
    img = (img - torch.tensor(PIXEL_MEAN)[:, None, None]) / torch.tensor(PIXEL_STD)[:, None, None]
    img = F.pad(img, (0, s - w, 0, s - h))[None]
    if depth is None:
        return img, None, None
    hd, wd = depth.shape
    ratio = int(round(w / wd))
    if ratio not in (1, 2, 4) or (wd * ratio, hd * ratio) != (w, h):
        raise ValueError(f'depth must be exactly 1, 1/2 or 1/4 of the image size (got {wd}x{hd} for {w}x{h}): '
                         'resample it (rfm_core.detection.cutr.block_median)')
    d = np.nan_to_num(np.asarray(depth, dtype=np.float64), nan=0.0)
    valid = np.sort(d[d > 0])
    n = len(valid)
    sl = valid[int(0.1 * n):int(0.9 * n)]
    if len(sl) <= 1:
        mu, sigma = 0.0, 1.0
    else:
        mu, sigma = float(sl.mean()), float(np.sqrt(sl.var(ddof=1) + 0.01))
    d = np.where(d > 0, d, mu)
    dn = torch.from_numpy((d - mu) / sigma).float()
    side = int(math.ceil((s / ratio) / 32.0)) * 32
    dn = F.pad(dn, (0, side - wd, 0, side - hd))[None, None]
    return img, dn, (mu, sigma)


# ----------------------------------------------------------------------------- model

class CubifyTransformer(nn.Module):
    """CuTR. ``rgbd`` selects the RGB-D variant (depth tokens in the backbone)."""

    def __init__(self, rgbd: bool = False):
        super().__init__()
        self.rgbd = rgbd
        # registration order follows the official state_dict: level_embed, backbone, ...
        self.level_embed = nn.Parameter(torch.zeros(1, DEC_DIM))
        self.backbone = Backbone(ViT(rgbd))
        self.input_proj = nn.ModuleList([nn.Sequential(nn.Conv2d(EMBED_DIM, DEC_DIM, 1),
                                                       nn.GroupNorm(32, DEC_DIM))])
        self.pos_embedding = RayPositionEmbedding()
        self.prompting = Prompting()
        self.decoder = Decoder()
        self.register_buffer('pixel_mean', torch.tensor(PIXEL_MEAN).view(3, 1, 1), persistent=False)
        self.register_buffer('pixel_std', torch.tensor(PIXEL_STD).view(3, 1, 1), persistent=False)

    @staticmethod
    def is_rgbd_state_dict(state_dict) -> bool:
        return any(k.startswith('backbone.0.patch_embed_depth.') for k in state_dict)

    def _ray_embedding(self, k, h, w, s, hf, wf):
        """Spec 2.3: camera-ray position embedding of every stride-16 token (hf * wf, 256)."""
        a, b = torch.meshgrid(torch.arange(hf), torch.arange(wf), indexing='ij')
        i, j = (16 * a).double(), (16 * b).double()
        inside = (i < h) & (j < w)
        ray = torch.stack([(j + 0.5 - k[0, 2]) / k[0, 0], (i + 0.5 - k[1, 2]) / k[1, 1],
                           torch.ones_like(i)], -1)
        ray = ray / ray.norm(dim=-1, keepdim=True)
        ray = torch.where(inside[..., None], ray, torch.zeros_like(ray))
        ray = ray.reshape(-1, 3)
        freqs = 2.0 ** (torch.arange(85, dtype=torch.float64) * math.log2(wf / 2) / 84)
        enc = torch.sin(math.pi * freqs[None, None, :] * ray[:, :, None]).reshape(-1, 255)
        return self.pos_embedding.proj(enc.float())

    def forward(self, image, intrinsics, depth=None, depth_stats=None, gravity=None, *, image_size):
        """Spec 2.2-2.9 for one image. ``image`` (1, 3, S, S) from :func:`preprocess`;
        ``intrinsics`` 3x3 pixels; ``image_size`` (h, w) before padding (required: without it
        the padding would be taken for image). Returns a dict of the spec's outputs (top-100)."""
        s = image.shape[-1]
        h, w = image_size
        k = torch.as_tensor(np.asarray(intrinsics), dtype=torch.float64)
        feats = self.backbone(image, depth)                              # (1, 768, hf, wf)
        hf, wf = feats.shape[-2:]
        src_map = self.input_proj[0](feats)                              # (1, 256, hf, wf)
        src = src_map.flatten(2)[0].T                                    # (hf*wf, 256)
        pos_flat = self._ray_embedding(k, h, w, s, hf, wf) + self.level_embed[0]

        # two-stage proposals over three levels
        prompter = self.prompting.prompters[1]
        levels = [proj(src_map) for proj in prompter.enc_output_proj]
        mem, anchors = [], []
        for lvl, feat in enumerate(levels):
            lh, lw = feat.shape[-2:]
            stride = 16 * 2 ** lvl
            a, b = torch.meshgrid(torch.arange(lh), torch.arange(lw), indexing='ij')
            size = 50.0 * 2 ** lvl
            anc = torch.stack([(b.float() + 0.5) * stride, (a.float() + 0.5) * stride,
                               torch.full_like(a, size, dtype=torch.float32),
                               torch.full_like(a, size, dtype=torch.float32)], -1).reshape(-1, 4)
            anchors.append(anc)
            mem.append(feat.flatten(2)[0].T)
        anchors = torch.cat(anchors)
        mem = torch.cat(mem)
        valid = ((anchors > 0.01 * s) & (anchors < 0.99 * s)).all(-1)
        anchors = torch.where(valid[:, None], anchors, torch.full_like(anchors, float(s)))
        mem = torch.where(valid[:, None], mem, torch.zeros_like(mem))
        mem = prompter.enc_output_norm(prompter.enc_output(mem))
        logits0 = prompter.predictors[0](mem)
        refined = _apply_delta(prompter.predictors[1](mem), anchors, s)
        top = torch.topk(logits0[:, 0], NUM_QUERIES).indices
        ref = refined[top]

        # queries: [metric 0, metric 1, objects 0..299]
        encoder = self.prompting.encoders.box_2d_encoder
        metric = self.prompting.prompters[0].query_embed.weight
        t = torch.cat([metric, prompter.query_embed.weight[:NUM_QUERIES]])
        pos = torch.cat([torch.zeros_like(metric), encoder(ref)])
        nm = metric.shape[0]
        n = t.shape[0]
        mask = torch.ones(n, n, dtype=torch.bool)
        mask[:nm, :nm] = False
        mask[nm:, nm:] = False

        kinv = torch.linalg.inv(k)
        tg = None if gravity is None else torch.as_tensor(gravity_tensor(gravity), dtype=torch.float64)
        for layer, heads in zip(self.decoder.layers, self.decoder.predictors):
            tn = layer.norm2(t)
            t = t + layer.self_attn(tn + pos, tn + pos, tn, attn_mask=mask, need_weights=False)[0]
            t = t + layer.xattn(layer.norm1(t), pos, src, pos_flat, ref, nm, hf, wf)
            t = t + layer.linear2(F.relu(layer.linear1(layer.norm3(t))))
            y = self.decoder.norm(t)
            shift = torch.exp(heads[0].shift(y[0]))
            scale = torch.exp(heads[0].scale(y[1]))
            yq = y[nm:]
            logits = heads[1](yq)
            ref = _apply_delta(heads[2](yq), ref, s)
            box3d = heads[3](yq)
        # 3D decoding of the last layer (spec 2.8)
        if depth_stats is not None:
            t_off, s_mul = float(depth_stats[0]), float(depth_stats[1])
        else:
            t_off, s_mul = float(shift[0]), float(scale[0])
        b = box3d.double()
        refd = ref.double()
        u = (refd[:, 0] + b[:, 0] * refd[:, 2]).clamp(0, s)
        v = (refd[:, 1] + b[:, 1] * refd[:, 3]).clamp(0, s)
        z = s_mul * b[:, 2] + t_off
        sizes = s_mul * torch.exp(b[:, 3:6].clamp(max=5.0))
        theta = b[:, 6]
        centre = (kinv @ torch.stack([u * z, v * z, z])).T
        c, sn = torch.cos(theta), torch.sin(theta)
        zero, one = torch.zeros_like(c), torch.ones_like(c)
        r_theta = torch.stack([torch.stack([c, zero, sn], -1), torch.stack([zero, one, zero], -1),
                               torch.stack([-sn, zero, c], -1)], -2)
        rot = tg @ r_theta if tg is not None else r_theta
        boxes3d = torch.cat([centre, sizes.flip(-1)], -1)                # (x, y, z, l, h, w)

        # post-processing (spec 2.9)
        probs = torch.sigmoid(logits).flatten()
        scores, idx = torch.topk(probs, TOP_K)
        q, cls = idx // 2, idx % 2
        xyxy = torch.stack([ref[:, 0] - ref[:, 2] / 2, ref[:, 1] - ref[:, 3] / 2,
                            ref[:, 0] + ref[:, 2] / 2, ref[:, 1] + ref[:, 3] / 2], -1)[q]
        xyxy = torch.stack([xyxy[:, 0].clamp(0, w), xyxy[:, 1].clamp(0, h),
                            xyxy[:, 2].clamp(0, w), xyxy[:, 3].clamp(0, h)], -1)
        return {'scores': scores, 'pred_classes': cls, 'pred_boxes': xyxy,
                'pred_logits': logits[q], 'pred_boxes_3d': boxes3d[q], 'pred_rotation': rot[q],
                'pred_proj_xy': torch.stack([u, v], -1)[q], 'object_desc': yq[q]}
