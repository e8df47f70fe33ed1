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

from rfm_core.inference import attention, gelu, layer_norm, linear, load_weights, log_sigmoid, log_softmax, save_weights
from rfm_core.matching.classical import ObjectMatches
from rfm_core.matching.config import MatchingConfig
from rfm_core.observations import FrameObservations

__all__ = ['MatcherNetConfig', 'MatcherNet', 'LearnedMatcher', 'box_features', 'batch_inputs', 'parameter_shapes',
           'WEIGHTS_DIR', 'WEIGHTS_FORMAT', 'default_weights', 'load_matcher_net', 'save_matcher_net']

WEIGHTS_DIR = Path(__file__).resolve().parent / 'weights'
WEIGHTS_FORMAT = 'rfm-object-matcher'
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


def parameter_shapes(config: MatcherNetConfig) -> dict:
    """{parameter name: shape} of the network (the names of the training module's state_dict)."""
    d = config.dim
    shapes = {'embed.weight': (d, config.embedding_dim), 'embed.bias': (d,),
              'position.0.weight': (64, POSITION_FEATURES), 'position.0.bias': (64,),
              'position.2.weight': (64, 64), 'position.2.bias': (64,),
              'position.4.weight': (d, 64), 'position.4.bias': (d,),
              'final.weight': (d, d), 'final.bias': (d,), 'matchability.weight': (1, d), 'matchability.bias': (1,)}
    for i in range(config.layers):
        for block, projections in ((f'self_blocks.{i}', {'qkv': 3 * d, 'out': d}),
                                   (f'cross_blocks.{i}', {'qk': d, 'v': d, 'out': d})):
            for name, rows in projections.items():
                shapes |= {f'{block}.{name}.weight': (rows, d), f'{block}.{name}.bias': (rows,)}
            shapes |= {f'{block}.ffn.0.weight': (d, 2 * d), f'{block}.ffn.0.bias': (d,),
                       f'{block}.ffn.1.weight': (d,), f'{block}.ffn.1.bias': (d,),
                       f'{block}.ffn.3.weight': (d, d), f'{block}.ffn.3.bias': (d,)}
    return shapes


class MatcherNet:
    """The network's forward pass in numpy (float32), from its parameters.

    Each block: self-attention within a frame, then LightGlue's bidirectional
    cross-attention (a shared query/key projection) between the frames; each message is
    merged by a feed-forward net of [token, message] (Linear, LayerNorm, GELU, Linear).
    """

    def __init__(self, config: MatcherNetConfig, params: dict):
        self.config = config
        self.params = params

    def _ffn(self, block: str, x, message):
        p = self.params
        h = gelu(layer_norm(linear(np.concatenate([x, message], -1), p, f'{block}.ffn.0'), p, f'{block}.ffn.1'))
        return x + linear(h, p, f'{block}.ffn.3')

    def _tokens(self, emb, pos):
        p = self.params
        position = linear(gelu(linear(gelu(linear(pos, p, 'position.0')), p, 'position.2')), p, 'position.4')
        return linear(emb, p, 'embed') + position

    def __call__(self, emb0, pos0, mask0, emb1, pos1, mask1) -> np.ndarray:
        """Log-assignment (B, N+1, M+1) of padded token sets (masks: True = real)."""
        p, heads = self.params, self.config.heads
        x0, x1 = self._tokens(emb0, pos0), self._tokens(emb1, pos1)
        for i in range(self.config.layers):
            block = f'self_blocks.{i}'
            updated = []
            for x, mask in ((x0, mask0), (x1, mask1)):
                q, k, v = np.split(linear(x, p, f'{block}.qkv'), 3, axis=-1)
                updated.append(self._ffn(block, x, linear(attention(q, k, v, mask, heads), p, f'{block}.out')))
            x0, x1 = updated
            block = f'cross_blocks.{i}'
            qk0, qk1 = linear(x0, p, f'{block}.qk'), linear(x1, p, f'{block}.qk')
            v0, v1 = linear(x0, p, f'{block}.v'), linear(x1, p, f'{block}.v')
            m0 = linear(attention(qk0, qk1, v1, mask1, heads), p, f'{block}.out')
            m1 = linear(attention(qk1, qk0, v0, mask0, heads), p, f'{block}.out')
            x0, x1 = self._ffn(block, x0, m0), self._ffn(block, x1, m1)
        return self._log_assignment(x0, x1, mask0, mask1)

    def _log_assignment(self, x0, x1, mask0, mask1):
        p, d = self.params, x0.shape[-1]
        m0, m1 = linear(x0, p, 'final') / d ** 0.25, linear(x1, p, 'final') / d ** 0.25
        sim = m0 @ m1.transpose(0, 2, 1)                                 # (B, N, M)
        pair = mask0[:, :, None] & mask1[:, None, :]
        sim = np.where(pair, sim, np.finfo(np.float32).min / 4)
        z0, z1 = linear(x0, p, 'matchability'), linear(x1, p, 'matchability')     # (B, N, 1), (B, M, 1)
        scores = log_softmax(sim, 2) + log_softmax(sim, 1) + log_sigmoid(z0) + log_sigmoid(z1).transpose(0, 2, 1)
        b, n, m = sim.shape
        out = np.zeros((b, n + 1, m + 1), np.float32)
        out[:, :n, :m] = scores
        out[:, :n, m] = log_sigmoid(-z0[..., 0])
        out[:, n, :m] = log_sigmoid(-z1[..., 0])
        return out


def _padded(items, width):
    n = max((len(x) for x in items), default=0)
    out = np.zeros((len(items), max(n, 1), width), np.float32)
    mask = np.zeros((len(items), max(n, 1)), bool)
    for i, x in enumerate(items):
        out[i, :len(x)] = x
        mask[i, :len(x)] = True
    return out, mask


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


def save_matcher_net(config: MatcherNetConfig, params: dict, path, metadata: dict | None = None) -> None:
    """Half-precision parameters ({name: array}) plus the config and training metadata (a few MB)."""
    save_weights(path, {k: np.asarray(v, np.float16) for k, v in params.items()},
                 {'format': WEIGHTS_FORMAT, 'version': 2, 'config': asdict(config), 'metadata': metadata or {}})


def load_matcher_net(path) -> tuple[MatcherNet, dict]:
    """(network, training metadata) of a weights file written by :func:`save_matcher_net`."""
    def shapes(meta):
        return parameter_shapes(MatcherNetConfig(**meta['config']))
    params, meta = load_weights(path, WEIGHTS_FORMAT, 2, shapes, 'rfm train-matcher')
    config = MatcherNetConfig(**meta['config'])
    if config.dim % config.heads:
        raise ValueError(f'{path}: {config.dim}-wide tokens do not split into {config.heads} heads')
    return MatcherNet(config, params), meta.get('metadata') or {}


def default_weights(backend: str) -> Path | None:
    """The shipped weights for a detector backend ('depth_clusters', 'ground_truth:rgb', ...);
    None for none, and for a name that is no backend's (a message's, so a file name of the
    weights directory: lower-case letters, digits and underscores)."""
    family = backend.split(':', 1)[0]
    if not (0 < len(family) <= 64 and family.replace('_', '').isalnum() and family.isascii() and family.islower()):
        return None
    path = WEIGHTS_DIR / f'object_matcher_{family}.npz'
    return path if path.is_file() else None


class LearnedMatcher:
    """The learned matcher behind the same interface as the classical one.

    ``weights`` is a checkpoint path; without one the shipped weights for each frame's
    detector backend are loaded on first use. Frames the network cannot take (no shipped
    weights for their detector, or embeddings of another size) go to ``fallback`` (e.g. the
    classical matcher) after one call of ``on_fallback(reason)``; without a fallback they
    raise ValueError saying what to do.
    """

    def __init__(self, config: MatchingConfig | None = None, weights=None, fallback=None, on_fallback=None):
        self.config = config or MatchingConfig()
        self._fixed = load_matcher_net(weights)[0] if weights else None
        self._by_backend: dict = {}
        self.fallback = fallback
        self.on_fallback = on_fallback
        self._reported: set = set()

    def network(self, backend: str) -> MatcherNet:
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
        out = net(*batch_inputs([a] * len(others), list(others)))
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
