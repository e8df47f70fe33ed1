"""Learned object matcher: LightGlue (Lindenberger et al., 2023) applied to objects (paper 3.2).

Each detection is a token: its embedding projected to ``dim`` plus an MLP positional
encoding of its box (centre in the gravity-aligned camera frame, log of the sorted footprint
sizes and of the height, score). ``layers`` blocks of self-attention (within a frame) and
cross-attention (between the two frames) let a token look at its neighbours, which is what
tells two identical chairs apart. The assignment is LightGlue's: a similarity matrix, a
double softmax (rows and columns), and a matchability per token, giving a
(N+1) x (M+1) log-assignment whose last row/column means "unmatched". Matches are mutual
best entries with probability >= ``match_threshold`` (paper: 0.5).

Weights depend on the embedding a detector produces; one file per detector family ships in
``rfm_core/matching/weights`` (trained by ``rfm train-matcher``, see its README).
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from rfm_core.matching.classical import ObjectMatches
from rfm_core.matching.config import MatchingConfig
from rfm_core.observations import FrameObservations

__all__ = ['MatcherNetConfig', 'ObjectMatcherNet', 'LearnedMatcher', 'box_features',
           'WEIGHTS_DIR', 'default_weights', 'load_matcher_net', 'save_matcher_net']

WEIGHTS_DIR = Path(__file__).resolve().parent / 'weights'
POSITION_FEATURES = 7


@dataclass(frozen=True)
class MatcherNetConfig:
    embedding_dim: int                #: input embedding size (the detector's)
    dim: int = 256                    #: token width
    layers: int = 3                   #: self + cross blocks
    heads: int = 4


def box_features(boxes: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """(N, 7) positional input: centre (m), log sorted footprint sizes, log height, score.
    Sizes are sorted because a box's yaw symmetry may swap its footprint sides."""
    boxes = np.asarray(boxes, dtype=np.float32).reshape(-1, 7)
    foot = np.sort(np.maximum(boxes[:, 3:5], 1e-3), axis=1)
    return np.c_[boxes[:, :3] / 2.0, np.log(foot), np.log(np.maximum(boxes[:, 5:6], 1e-3)),
                 np.asarray(scores, np.float32).reshape(-1, 1)].astype(np.float32)


class _Attention(nn.Module):
    """Multi-head attention over padded token sets (mask: True = a real token)."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads

    def forward(self, q, k, v, key_mask):
        b, n, d = q.shape
        h = self.heads
        q, k, v = (t.reshape(b, -1, h, d // h).transpose(1, 2) for t in (q, k, v))
        mask = key_mask[:, None, None, :]
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
        return out.transpose(1, 2).reshape(b, n, d)


def _ffn(dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(2 * dim, dim), nn.LayerNorm(dim), nn.GELU(), nn.Linear(dim, dim))


class _SelfBlock(nn.Module):
    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.qkv = nn.Linear(dim, 3 * dim)
        self.attention = _Attention(dim, heads)
        self.out = nn.Linear(dim, dim)
        self.ffn = _ffn(dim)

    def forward(self, x, mask):
        q, k, v = self.qkv(x).chunk(3, dim=-1)
        message = self.out(self.attention(q, k, v, mask))
        return x + self.ffn(torch.cat([x, message], -1))


class _CrossBlock(nn.Module):
    """LightGlue's bidirectional cross-attention: shared query/key projection."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.qk = nn.Linear(dim, dim)
        self.v = nn.Linear(dim, dim)
        self.attention = _Attention(dim, heads)
        self.out = nn.Linear(dim, dim)
        self.ffn = _ffn(dim)

    def forward(self, x0, x1, mask0, mask1):
        qk0, qk1 = self.qk(x0), self.qk(x1)
        v0, v1 = self.v(x0), self.v(x1)
        m0 = self.out(self.attention(qk0, qk1, v1, mask1))
        m1 = self.out(self.attention(qk1, qk0, v0, mask0))
        return x0 + self.ffn(torch.cat([x0, m0], -1)), x1 + self.ffn(torch.cat([x1, m1], -1))


class ObjectMatcherNet(nn.Module):
    def __init__(self, config: MatcherNetConfig):
        super().__init__()
        self.config = config
        d = config.dim
        self.embed = nn.Linear(config.embedding_dim, d)
        self.position = nn.Sequential(nn.Linear(POSITION_FEATURES, 64), nn.GELU(),
                                      nn.Linear(64, 64), nn.GELU(), nn.Linear(64, d))
        self.self_blocks = nn.ModuleList(_SelfBlock(d, config.heads) for _ in range(config.layers))
        self.cross_blocks = nn.ModuleList(_CrossBlock(d, config.heads) for _ in range(config.layers))
        self.final = nn.Linear(d, d)
        self.matchability = nn.Linear(d, 1)

    def forward(self, emb0, pos0, mask0, emb1, pos1, mask1) -> torch.Tensor:
        """Log-assignment (B, N+1, M+1) of padded token sets (masks: True = real)."""
        x0 = self.embed(emb0) + self.position(pos0)
        x1 = self.embed(emb1) + self.position(pos1)
        for self_block, cross_block in zip(self.self_blocks, self.cross_blocks):
            x0, x1 = self_block(x0, mask0), self_block(x1, mask1)
            x0, x1 = cross_block(x0, x1, mask0, mask1)
        return self._log_assignment(x0, x1, mask0, mask1)

    def _log_assignment(self, x0, x1, mask0, mask1):
        d = x0.shape[-1]
        m0, m1 = self.final(x0) / d ** 0.25, self.final(x1) / d ** 0.25
        sim = m0 @ m1.transpose(1, 2)                                   # (B, N, M)
        pair = mask0[:, :, None] & mask1[:, None, :]
        very_negative = torch.finfo(sim.dtype).min / 4
        sim = sim.masked_fill(~pair, very_negative)
        z0, z1 = self.matchability(x0), self.matchability(x1)          # (B, N, 1), (B, M, 1)
        scores = (F.log_softmax(sim, 2) + F.log_softmax(sim, 1)
                  + F.logsigmoid(z0) + F.logsigmoid(z1).transpose(1, 2))
        b, n, m = sim.shape
        out = sim.new_full((b, n + 1, m + 1), 0.0)
        out[:, :n, :m] = scores
        out[:, :n, m] = F.logsigmoid(-z0[..., 0])
        out[:, n, :m] = F.logsigmoid(-z1[..., 0])
        return out


def _padded(items, width):
    n = max((len(x) for x in items), default=0)
    out = np.zeros((len(items), max(n, 1), width), np.float32)
    mask = np.zeros((len(items), max(n, 1)), bool)
    for i, x in enumerate(items):
        out[i, :len(x)] = x
        mask[i, :len(x)] = True
    return torch.from_numpy(out), torch.from_numpy(mask)


def batch_inputs(frames_a, frames_b):
    """Padded network inputs of lists of FrameObservations (pairs a[i], b[i])."""
    dim = frames_a[0].embeddings.shape[1]
    ea, ma = _padded([f.embeddings for f in frames_a], dim)
    eb, mb = _padded([f.embeddings for f in frames_b], dim)
    pa, _ = _padded([box_features(f.boxes, f.scores) for f in frames_a], POSITION_FEATURES)
    pb, _ = _padded([box_features(f.boxes, f.scores) for f in frames_b], POSITION_FEATURES)
    return ea, pa, ma, eb, pb, mb


def mutual_matches(log_assignment: np.ndarray, threshold: float):
    """(rows, cols, probabilities) of the mutual best entries above ``threshold``."""
    p = np.exp(log_assignment[:-1, :-1])
    if p.size == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    best_col = p.argmax(1)
    best_row = p.argmax(0)
    rows = np.arange(p.shape[0])
    keep = (best_row[best_col] == rows) & (p[rows, best_col] >= threshold)
    return rows[keep], best_col[keep], p[rows[keep], best_col[keep]]


def save_matcher_net(net: ObjectMatcherNet, path, metadata: dict | None = None) -> None:
    """Half-precision state dict plus the config and training metadata (a few MB)."""
    state = {k: v.detach().to(torch.float16) for k, v in net.state_dict().items()}
    path = Path(path)
    tmp = path.with_suffix(path.suffix + '.tmp')
    torch.save({'format': 'rfm-object-matcher', 'version': 1, 'config': asdict(net.config),
                'metadata': json.dumps(metadata or {}), 'state_dict': state}, tmp)
    tmp.replace(path)


def load_matcher_net(path) -> tuple[ObjectMatcherNet, dict]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f'object matcher weights not found: {path} '
                                f'(train them with `rfm train-matcher`)')
    try:
        blob = torch.load(path, map_location='cpu', weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises several kinds for a damaged file
        raise ValueError(f'{path} cannot be read as an rfm object-matcher checkpoint ({exc.__class__.__name__}); '
                         'retrain it with `rfm train-matcher` or pass another file') from exc
    if not isinstance(blob, dict) or blob.get('format') != 'rfm-object-matcher':
        raise ValueError(f'{path} is not an rfm object-matcher checkpoint')
    if blob.get('version') != 1:
        raise ValueError(f'{path}: unsupported object-matcher checkpoint version {blob.get("version")}')
    net = ObjectMatcherNet(MatcherNetConfig(**blob['config']))
    net.load_state_dict({k: v.float() for k, v in blob['state_dict'].items()}, strict=True)
    net.eval()
    return net, json.loads(blob.get('metadata') or '{}')


def default_weights(backend: str) -> Path | None:
    """The shipped weights for a detector backend ('depth_clusters', 'ground_truth:rgb', ...);
    None for none, and for a name that is no backend's (a message's, so a file name of the
    weights directory: lower-case letters, digits and underscores)."""
    family = backend.split(':', 1)[0]
    if not (0 < len(family) <= 64 and family.replace('_', '').isalnum() and family.isascii() and family.islower()):
        return None
    path = WEIGHTS_DIR / f'object_matcher_{family}.pt'
    return path if path.is_file() else None


class LearnedMatcher:
    """The learned matcher behind the same interface as the classical one.

    ``weights`` is a checkpoint path; without one the shipped weights for each frame's
    detector backend are loaded on first use. Frames the network cannot take (no shipped
    weights for their detector, or embeddings of another size) go to ``fallback`` (e.g. the
    classical matcher) after one call of ``on_fallback(reason)``; without a fallback they
    raise ValueError saying what to do.
    """

    def __init__(self, config: MatchingConfig | None = None, weights=None, threads: int | None = None,
                 fallback=None, on_fallback=None):
        self.config = config or MatchingConfig()
        self._fixed = load_matcher_net(weights)[0] if weights else None
        self._by_backend: dict = {}
        self.threads = threads
        self.fallback = fallback
        self.on_fallback = on_fallback
        self._reported: set = set()

    def network(self, backend: str) -> ObjectMatcherNet:
        if self._fixed is not None:
            return self._fixed
        family = backend.split(':', 1)[0]
        if family not in self._by_backend:
            path = default_weights(family)
            if path is None:
                raise ValueError(f'no shipped object-matcher weights for detector {family!r}: '
                                 f'train some with `rfm train-matcher --backend {family}` and pass '
                                 f'them as matcher_weights, or use the classical matcher')
            self._by_backend[family] = load_matcher_net(path)[0]
        return self._by_backend[family]

    def log_assignment(self, a: FrameObservations, b: FrameObservations) -> np.ndarray:
        return self.log_assignments(a, [b])[0]

    def log_assignments(self, a: FrameObservations, others) -> list:
        """Log-assignment matrices of ``a`` against each of ``others``, in one batched pass."""
        net = self.network(a.backend or others[0].backend)
        dim = net.config.embedding_dim
        for b in others:
            if a.embeddings.shape[1] != dim or b.embeddings.shape[1] != dim:
                raise ValueError(f'object matcher expects {dim}-d embeddings, got {a.embeddings.shape[1]} '
                                 f'and {b.embeddings.shape[1]} (detector {a.backend!r}); pass weights '
                                 f'trained for this detector as matcher_weights')
        previous = torch.get_num_threads()
        if self.threads:
            torch.set_num_threads(self.threads)
        try:
            with torch.inference_mode():
                out = net(*batch_inputs([a] * len(others), list(others))).numpy()
        finally:
            if self.threads:
                torch.set_num_threads(previous)
        # crop each pair's padding: rows 0..len(a)-1 plus the dustbin, same for columns
        rows = np.r_[np.arange(len(a)), out.shape[1] - 1]
        return [o[rows][:, np.r_[np.arange(len(b)), out.shape[2] - 1]] for o, b in zip(out, others)]

    def match_many(self, a: FrameObservations, others) -> list:
        """``[match(a, b) for b in others]`` with one batched network pass (a new keyframe
        against all its candidates costs little more than against one)."""
        empty = ObjectMatches(np.zeros(0, int), np.zeros(0, int), np.zeros(0))
        out = [empty] * len(others)
        todo = [i for i, b in enumerate(others) if len(a) and len(b)]
        if not todo:
            return out
        try:
            assignments = self.log_assignments(a, [others[i] for i in todo])
        except ValueError:
            return [self.match(a, b) for b in others]        # the fallback path, reported once
        for i, la in zip(todo, assignments):
            rows, cols, p = mutual_matches(la, self.config.match_threshold)
            out[i] = ObjectMatches(rows, cols, p)
        return out

    def match(self, a: FrameObservations, b: FrameObservations) -> ObjectMatches:
        if len(a) == 0 or len(b) == 0:
            return ObjectMatches(np.zeros(0, int), np.zeros(0, int), np.zeros(0))
        try:
            log_assignment = self.log_assignment(a, b)
        except ValueError as exc:
            if self.fallback is None:
                raise
            key = (a.backend, a.embeddings.shape[1], b.embeddings.shape[1])
            if key not in self._reported and self.on_fallback is not None:
                self.on_fallback(f'learned matcher unavailable, using the fallback: {exc}')
            self._reported.add(key)
            return self.fallback.match(a, b)
        rows, cols, p = mutual_matches(log_assignment, self.config.match_threshold)
        return ObjectMatches(rows, cols, p)
