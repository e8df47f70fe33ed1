"""Training the learned box refiner of `depth_clusters`
(:mod:`rfm_core.detection.box_refiner`): ``rfm train-box-refiner``.

Samples: every candidate cluster of `depth_clusters` on frames of simulated scenes
(training seeds), labelled from the renderer's instance image: the object most of the
cluster's points belong to gives the regression target (its full box) and the class; the
cluster is a positive when that object holds at least half of its points, is one the
ground truth lists as visible, and the cluster is that object's largest in the frame.
"""
from __future__ import annotations

import time

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from rfm_core.detection.box_refiner import (CLASSES, GLOBAL_FEATURES, POINT_FEATURES, RefinerNet, candidate_inputs,
                                            encode_target, save_box_refiner)
from rfm_core.detection.depth_clusters import DepthClustersConfig, DepthClustersDetector
from rfm_core.evaluation.detection import express_in
from rfm_core.sim.capture import Capture

__all__ = ['training_configs', 'refiner_samples', 'train_box_refiner', 'BoxRefinerNet', 'save', 'inference_net']

MIN_SHARE = 0.5       #: a positive: its object owns at least this share of the cluster's points
TARGET_SHARE = 0.3    #: a box target (and class) from the object owning at least this share


def training_configs(seeds, frames_per_scene: int = 10, boxes_every: int = 4) -> list:
    """The evaluation suite's scene distribution on training seeds: the realistic world
    (furniture of parts, clutter, both sensor models, handheld / robot / sparse captures,
    5-30 Hz, 320x240 and 640x480); every ``boxes_every``-th scene from the boxes world so
    the refiner keeps working on solid furniture. Returns (config, frame indices) pairs."""
    from rfm_core.evaluation.suite import seed_config  # noqa: PLC0415

    out = []
    for i, seed in enumerate(seeds):
        config = seed_config(seed, 'boxes' if boxes_every and i % boxes_every == boxes_every - 1 else 'realistic')
        n = config.frames
        out.append((config, np.linspace(0, n - 1, min(frames_per_scene, n)).round().astype(int)))
    return out


def refiner_samples(item) -> dict:
    """Inputs and labels of every candidate over the chosen frames of one scene."""
    config, indices = item
    detector = DepthClustersDetector(DepthClustersConfig(box_refiner='', score_model=''))
    capture = Capture(config)
    out = {k: [] for k in ('points', 'globals', 'objectness', 'target', 'has_target', 'label')}
    for frame in capture.frames(indices):
        found = detector.candidates(frame.detector_input())
        if not found.items:
            continue
        truth = frame.ground_truth
        truth_boxes = express_in(truth, found.frame.gravity_cam) if len(truth.boxes) else np.zeros((0, 7))
        row = {int(k): j for j, k in enumerate(truth.object_ids)}
        instance = frame.render.instance
        major, share, count = [], [], []
        for c in found.items:
            ids = instance[c.pixels[:, 0], c.pixels[:, 1]]
            values, counts = np.unique(ids, return_counts=True)
            k = int(np.argmax(counts))
            major.append(int(values[k]))
            share.append(counts[k] / len(ids))
            count.append(counts[k])
        largest = {}
        for i, (k, n) in enumerate(zip(major, count)):
            if k > 0 and (k not in largest or n > count[largest[k]]):
                largest[k] = i
        pts, glob = candidate_inputs(found)
        for i, c in enumerate(found.items):
            k = major[i]
            has = k > 0 and k in row and share[i] >= TARGET_SHARE
            target = encode_target(c.box, truth_boxes[row[k]]) if has else np.zeros(8)
            out['objectness'].append(bool(has and share[i] >= MIN_SHARE and largest[k] == i))
            out['target'].append(target)
            out['has_target'].append(has)
            out['label'].append(CLASSES.index(truth.labels[row[k]]) if has else -1)
        out['points'].append(pts)
        out['globals'].append(glob)
    if not out['points']:
        return {}
    return {'points': np.concatenate(out['points']).astype(np.float16),
            'globals': np.concatenate(out['globals']),
            'objectness': np.array(out['objectness']), 'target': np.array(out['target'], np.float32),
            'has_target': np.array(out['has_target']), 'label': np.array(out['label'], np.int64)}


def _mirror(points, globals_, target):
    """The same sample seen in a mirror (y -> -y in the fitted box's frame)."""
    points = points.clone()
    points[:, :, 1] *= -1
    points[:, :, 4] *= -1
    target = target.clone()
    target[:, 1] *= -1
    target[:, 6] *= -1
    return points, globals_, target


class BoxRefinerNet(nn.Module):
    """The refiner (:class:`~rfm_core.detection.box_refiner.RefinerNet`) as a torch module to train."""

    def __init__(self, width: int = 128, classes: int = len(CLASSES)):
        super().__init__()
        self.width, self.classes = width, classes
        self.point_mlp = nn.Sequential(
            nn.Conv1d(POINT_FEATURES, 64, 1), nn.ReLU(), nn.Conv1d(64, width, 1), nn.ReLU(),
            nn.Conv1d(width, 2 * width, 1))
        self.head = nn.Sequential(
            nn.Linear(2 * width + GLOBAL_FEATURES, 2 * width), nn.ReLU(),
            nn.Linear(2 * width, width), nn.ReLU(), nn.Linear(width, 1 + 8 + classes))

    def forward(self, points: torch.Tensor, globals_: torch.Tensor):
        """points (N, P, POINT_FEATURES), globals (N, GLOBAL_FEATURES) -> objectness logit (N,),
        box deltas (N, 8), class logits (N, classes)."""
        feat = self.point_mlp(points.transpose(1, 2)).amax(dim=2)
        out = self.head(torch.cat([feat, globals_], 1))
        return out[:, 0], out[:, 1:9], out[:, 9:]


def train_box_refiner(data: dict, epochs: int = 30, batch_size: int = 256, lr: float = 2e-3,
                      width: int = 128, seed: int = 0, log=print) -> tuple:
    """Train on ``data`` (concatenated :func:`refiner_samples`); returns (net, history)."""
    torch.manual_seed(seed)
    points = torch.from_numpy(data['points'].astype(np.float32))
    globals_ = torch.from_numpy(data['globals'].astype(np.float32))
    obj = torch.from_numpy(data['objectness'].astype(np.float32))
    target = torch.from_numpy(data['target'])
    has = torch.from_numpy(data['has_target'])
    label = torch.from_numpy(data['label'])
    n = len(obj)
    net = BoxRefinerNet(width=width)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    steps = epochs * ((n + batch_size - 1) // batch_size)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps)
    history = []
    for epoch in range(epochs):
        net.train()
        perm = torch.randperm(n)
        totals = np.zeros(3)
        start = time.perf_counter()
        for b in range(0, n, batch_size):
            idx = perm[b:b + batch_size]
            p, g, t = points[idx], globals_[idx], target[idx]
            if torch.rand(()) < 0.5:
                p, g, t = _mirror(p, g, t)
            logit, deltas, cls = net(p, g)
            l_obj = F.binary_cross_entropy_with_logits(logit, obj[idx])
            m = has[idx]
            l_box = F.smooth_l1_loss(deltas[m], t[m], beta=0.1) if m.any() else logit.sum() * 0
            l_cls = F.cross_entropy(cls[m], label[idx][m]) if m.any() else logit.sum() * 0
            loss = l_obj + 2.0 * l_box + 0.3 * l_cls
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            totals += [l_obj.item() * len(idx), l_box.item() * len(idx), l_cls.item() * len(idx)]
        totals /= n
        history.append(totals.tolist())
        log(f'epoch {epoch + 1}/{epochs}: objectness {totals[0]:.4f} box {totals[1]:.4f} '
            f'class {totals[2]:.4f} ({time.perf_counter() - start:.0f} s)')
    return net.eval(), history


def _parameters(net: BoxRefinerNet) -> dict:
    return {k: v.detach().cpu().numpy().astype(np.float32) for k, v in net.state_dict().items()}


def save(net: BoxRefinerNet, path, metadata: dict) -> None:
    """Write ``net``'s weights for the detector to load (:meth:`BoxRefiner.load`)."""
    save_box_refiner(net.width, _parameters(net), path, metadata)


def inference_net(net: BoxRefinerNet) -> RefinerNet:
    """The numpy network with ``net``'s parameters (what the detector runs)."""
    return RefinerNet(net.width, _parameters(net))
