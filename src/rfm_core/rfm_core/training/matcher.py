"""Training data and training loop of the learned object matcher.

Pairs come from rendered sim captures run through a real detector backend. Supervision is
the ground-truth object id of each detection: the ``ground_truth`` backend keeps the ids
of the objects it perturbs; detections of an image-based backend (``depth_clusters``) get
the id of the visible ground-truth box they overlap best (one-to-one, IoU3D >= 0.25), or
none. Two detections match when they carry the same id.

With ``structure``, detections that are no ground-truth object (a fragment of an object,
two merged objects, a cluster on a wall) but that a detector reports again and again at
the same place also get an id (:func:`label_structure`), so the matcher learns
to match them too: for the relative pose, any structure detected consistently in both
frames is a landmark (an image-based detector's junk is most of what some views show).
"""
from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment
from torch import nn

from rfm_core.detection import detector_for_spec
from rfm_core.geometry import Pose4, iou_3d
from rfm_core.matching.learned import POSITION_FEATURES, MatcherNet, MatcherNetConfig, batch_inputs, save_matcher_net
from rfm_core.observations import FrameObservations
from rfm_core.sim.capture import Capture, CaptureConfig

__all__ = ['LabelledFrame', 'assign_object_ids', 'label_structure', 'STRUCTURE_ID_BASE', 'labelled_capture',
           'frame_pairs', 'scene_configs', 'labelled_pairs', 'TrainConfig', 'train_matcher', 'match_targets',
           'ObjectMatcherNet', 'batch_tensors', 'inference_net', 'save']


@dataclass
class LabelledFrame:
    observations: FrameObservations      #: detections, object_ids = ground-truth ids (-1: none)
    aligned_from_map: Pose4              #: true T_aligned_map of the frame
    visible_ids: np.ndarray              #: ids of the objects visible in the frame


def assign_object_ids(pred: FrameObservations, truth: FrameObservations, min_iou: float = 0.25) -> np.ndarray:
    """Ground-truth object id per detection: one-to-one by IoU3D >= min_iou, else -1."""
    ids = np.full(len(pred), -1, np.int64)
    if len(pred) == 0 or len(truth) == 0:
        return ids
    iou = iou_3d(pred.boxes, truth.boxes)
    rows, cols = linear_sum_assignment(-iou)
    ok = iou[rows, cols] >= min_iou
    ids[rows[ok]] = truth.object_ids[cols[ok]]
    return ids


#: ids given to consistently detected structure that is not a ground-truth object
STRUCTURE_ID_BASE = 1_000_000


def label_structure(frames, min_iou: float = 0.25) -> None:
    """Give the detections without a ground-truth id (``object_ids == -1``) of one capture
    ids of their own, in place: each is placed in the map frame with the frame's true pose
    and joins the earlier such detection it overlaps best (IoU3D >= ``min_iou``, one per
    frame), else starts a new id from :data:`STRUCTURE_ID_BASE`."""
    world: list = []                                 # first map-frame box of each structure
    for frame in frames:
        obs = frame.observations
        todo = np.flatnonzero(obs.object_ids < 0)
        if len(todo) == 0:
            continue
        boxes = frame.aligned_from_map.inverse().transform_boxes(obs.boxes[todo])
        if world:
            iou = iou_3d(boxes, np.array(world))
            rows, cols = linear_sum_assignment(-iou)
            ok = iou[rows, cols] >= min_iou
            obs.object_ids[todo[rows[ok]]] = STRUCTURE_ID_BASE + cols[ok]
        for i, box in zip(todo, boxes):
            if obs.object_ids[i] < 0:
                obs.object_ids[i] = STRUCTURE_ID_BASE + len(world)
                world.append(box)


def labelled_capture(config: CaptureConfig, specs, noise_seeds=(0,), structure: bool = False) -> dict:
    """{(spec, noise_seed): [LabelledFrame, ...]} for one capture (rendered once); with
    ``structure``, image-based detections that are no object are labelled by
    :func:`label_structure`."""
    # ground_truth presets perturb the true boxes (ids known, one run per noise seed); the
    # others detect in the images (ids assigned by overlap, structure labelled on request)
    from_truth = {spec: spec.startswith('ground_truth') for spec in specs}
    detectors = {(spec, s): detector_for_spec(spec, s) for spec in specs
                 for s in (noise_seeds if from_truth[spec] else (0,))}
    out = {key: [] for key in detectors}
    capture = Capture(config)
    for frame in capture.frames():
        truth = frame.ground_truth
        pose = frame.aligned_from_map()
        for key, det in detectors.items():
            if from_truth[key[0]]:
                obs = det.perturb(truth)
            else:
                obs = det.detect(frame.detector_input())
                obs = replace(obs, object_ids=assign_object_ids(obs, truth))
            out[key].append(LabelledFrame(obs, pose, truth.object_ids))
    if structure:
        for (spec, _), frames in out.items():
            if not from_truth[spec]:
                label_structure(frames)
    return out


def frame_pairs(frames, gaps=(1, 2, 3, 4), min_shared: int = 2, visible: bool = False):
    """(a, b) pairs ``gap`` frames apart whose detections (or, with ``visible``, whose
    visible objects) share >= min_shared objects."""
    pairs = []
    for gap in gaps:
        for fa, fb in zip(frames[:-gap], frames[gap:]):
            if visible:
                ia, ib = fa.visible_ids, fb.visible_ids
            else:
                ia, ib = fa.observations.object_ids, fb.observations.object_ids
            if len(set(ia[ia > 0]) & set(ib[ib > 0])) >= min_shared:
                pairs.append((fa, fb))
    return pairs


def _capture_job(args):
    config, specs, noise_seeds, structure = args
    return labelled_capture(config, specs, noise_seeds, structure)


def scene_configs(seeds, frames: int = 24, fps: float = 2.0, world: str = 'boxes'):
    """Mixed styles and captures, as the evaluation suites. ``world='realistic'``: the
    realistic suite's scenes for these seeds (furniture of parts, clutter, both sensor
    models, robot cameras; :func:`~rfm_core.evaluation.suite.seed_config`), ``frames`` of
    each at ``fps`` (sparse captures keep their 1.5-5 s between photos)."""
    if world == 'realistic':
        from rfm_core.evaluation.suite import seed_config  # noqa: PLC0415

        configs = [seed_config(s, 'realistic') for s in seeds]
        return [replace(c, frames=frames) if c.capture == 'sparse' else replace(c, frames=frames, fps=fps)
                for c in configs]
    styles = (('plain', 'handheld'), ('textured', 'sparse'), ('plain', 'sparse'), ('textured', 'handheld'))
    return [CaptureConfig(seed=s, room_style=styles[i % 4][0], capture=styles[i % 4][1],
                          frames=frames, fps=fps) for i, s in enumerate(seeds)]


def labelled_pairs(configs, specs, noise_seeds=(0,), gaps=(1, 2, 3, 4), min_shared: int = 2,
                   visible: bool = False, jobs: int = 1, progress=None, structure: bool = False) -> dict:
    """{spec: [(LabelledFrame a, LabelledFrame b), ...]} over captures, in parallel
    (``structure``: see :func:`labelled_capture`)."""
    pairs = {spec: [] for spec in specs}
    work = [(c, tuple(specs), tuple(noise_seeds), structure) for c in configs]
    if jobs > 1:
        with ProcessPoolExecutor(jobs) as pool:
            results = pool.map(_capture_job, work)
            for i, result in enumerate(results):
                _collect(pairs, result, gaps, min_shared, visible)
                if progress:
                    progress(i + 1, len(work))
    else:
        for i, w in enumerate(work):
            _collect(pairs, _capture_job(w), gaps, min_shared, visible)
            if progress:
                progress(i + 1, len(work))
    return pairs


def _collect(pairs, result, gaps, min_shared, visible):
    for (spec, _), frames in result.items():
        pairs[spec].extend(frame_pairs(frames, gaps, min_shared, visible))


def match_targets(ids_a: np.ndarray, ids_b: np.ndarray):
    """(matches (K, 2), unmatched a, unmatched b) from ground-truth ids."""
    index_b = {int(v): j for j, v in enumerate(ids_b) if v > 0}
    matches = [(i, index_b[int(v)]) for i, v in enumerate(ids_a) if v > 0 and int(v) in index_b]
    ma = {i for i, _ in matches}
    mb = {j for _, j in matches}
    return (np.array(matches, dtype=np.int64).reshape(-1, 2),
            np.array([i for i in range(len(ids_a)) if i not in ma], np.int64),
            np.array([j for j in range(len(ids_b)) if j not in mb], np.int64))


@dataclass(frozen=True)
class TrainConfig:
    epochs: int = 12
    batch_size: int = 32
    learning_rate: float = 3e-4
    weight_decay: float = 1e-4
    drop_detections: float = 0.15        #: augmentation: drop each detection with this probability
    balance: float = 0.5                 #: weight of the match term vs the unmatched term
    seed: int = 0
    threads: int = 2


def _loss(log_assignment: torch.Tensor, targets, balance: float) -> torch.Tensor:
    """LightGlue's negative log-likelihood: matched entries and the unmatched row/column."""
    pos, neg = [], []
    for k, (matches, un_a, un_b) in enumerate(targets):
        la = log_assignment[k]
        if len(matches):
            pos.append(la[matches[:, 0], matches[:, 1]])
        neg.append(la[un_a, -1])
        neg.append(la[-1, un_b])
    pos_t = torch.cat(pos) if pos else log_assignment.new_zeros(0)
    neg_t = torch.cat(neg) if neg else log_assignment.new_zeros(0)
    loss = log_assignment.new_zeros(())
    if pos_t.numel():
        loss = loss - balance * pos_t.mean()
    if neg_t.numel():
        loss = loss - (1 - balance) * neg_t.mean()
    return loss


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
    """The learned matcher (:class:`~rfm_core.matching.learned.MatcherNet`) as a torch module
    to train; :func:`inference_net` hands its parameters to the numpy network the nodes run."""

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


def batch_tensors(frames_a, frames_b):
    """:func:`~rfm_core.matching.learned.batch_inputs` as tensors."""
    return tuple(torch.from_numpy(x) for x in batch_inputs(frames_a, frames_b))


def _parameters(net: ObjectMatcherNet) -> dict:
    return {k: v.detach().cpu().numpy().astype(np.float32) for k, v in net.state_dict().items()}


def inference_net(net: ObjectMatcherNet) -> MatcherNet:
    """The numpy network with ``net``'s parameters (what the nodes run)."""
    return MatcherNet(net.config, _parameters(net))


def save(net: ObjectMatcherNet, path, metadata: dict) -> None:
    """Write ``net``'s weights for the matcher to load (:func:`~rfm_core.matching.learned.load_matcher_net`)."""
    save_matcher_net(net.config, _parameters(net), path, metadata)


def train_matcher(pairs, net_config: MatcherNetConfig, config: TrainConfig = TrainConfig(),
                  log=print) -> ObjectMatcherNet:
    """Train on [(LabelledFrame, LabelledFrame), ...]; both orders of each pair are used."""
    torch.manual_seed(config.seed)
    torch.set_num_threads(config.threads)
    rng = np.random.default_rng(config.seed)
    net = ObjectMatcherNet(net_config)
    net.train()
    examples = [(a.observations, b.observations) for a, b in pairs]
    examples += [(b, a) for a, b in examples]
    steps = config.epochs * ((len(examples) + config.batch_size - 1) // config.batch_size)
    opt = torch.optim.AdamW(net.parameters(), lr=config.learning_rate, weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=config.learning_rate, total_steps=steps,
                                                pct_start=0.1)
    start = time.perf_counter()
    for epoch in range(config.epochs):
        order = rng.permutation(len(examples))
        total, count = 0.0, 0
        for s in range(0, len(order), config.batch_size):
            batch_a, batch_b, targets = [], [], []
            for i in order[s:s + config.batch_size]:
                a, b = examples[i]
                if config.drop_detections > 0:
                    ka = rng.random(len(a)) >= config.drop_detections
                    kb = rng.random(len(b)) >= config.drop_detections
                    if ka.sum() >= 1 and kb.sum() >= 1:
                        a, b = a.subset(ka), b.subset(kb)
                if len(a) == 0 or len(b) == 0:
                    continue
                batch_a.append(a)
                batch_b.append(b)
                targets.append(match_targets(a.object_ids, b.object_ids))
            if not batch_a:
                continue
            la = net(*batch_tensors(batch_a, batch_b))
            loss = _loss(la, targets, config.balance)
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
            opt.step()
            sched.step()
            total += float(loss.detach()) * len(batch_a)
            count += len(batch_a)
        log(f'epoch {epoch + 1}/{config.epochs}: loss {total / max(count, 1):.4f} '
            f'({time.perf_counter() - start:.0f} s)')
    net.eval()
    return net
