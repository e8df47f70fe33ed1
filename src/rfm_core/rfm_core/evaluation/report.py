"""The output folder of a run: TUM trajectory, object map JSON, a Markdown report and a
top-down PNG — from a saved map, plus ground truth when the bag has it.

No ROS and no plotting library: the picture is rasterised with numpy and written by
:mod:`rfm_core.io.png`.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rfm_core.evaluation.mapping import evaluate_map
from rfm_core.evaluation.trajectory import map_to_truth, trajectory_errors
from rfm_core.geometry import Pose4, bev_corners, quaternion_from_matrix
from rfm_core.io.png import write_png
from rfm_core.mapping.tracks import track_colour

__all__ = ['GroundTruth', 'read_ground_truth', 'evaluate_run', 'write_tum', 'write_object_json',
           'render_top_down', 'write_report']


@dataclass
class GroundTruth:
    camera_poses: dict = field(default_factory=dict)     #: stamp_ns -> 4x4 camera-to-map
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))   #: (M, 7) map frame, z up
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    best_visibility: dict = field(default_factory=dict)  #: object id -> best visible fraction

    def __bool__(self) -> bool:
        return bool(self.camera_poses)


def read_ground_truth(bag) -> GroundTruth:
    """``/ground_truth/*`` topics of a bag (empty GroundTruth when it has none)."""
    from rosbags.highlevel import AnyReader  # noqa: PLC0415

    from rfm_core.io.messages import pose_to_matrix, stamp_to_ns  # noqa: PLC0415
    from rfm_core.io.bag import rfm_typestore  # noqa: PLC0415
    from rfm_core.geometry import boxes_from_oriented  # noqa: PLC0415

    gt = GroundTruth()
    wanted = {'/ground_truth/camera_pose', '/ground_truth/objects', '/ground_truth/detections'}
    with AnyReader([Path(bag)], default_typestore=rfm_typestore()) as reader:
        conns = [c for c in reader.connections if c.topic in wanted]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == '/ground_truth/camera_pose':
                gt.camera_poses[stamp_to_ns(msg.header.stamp)] = pose_to_matrix(msg.pose)
            elif conn.topic == '/ground_truth/objects':
                mats = [pose_to_matrix(o.pose) for o in msg.objects]
                sizes = np.array([[o.size.x, o.size.y, o.size.z] for o in msg.objects]).reshape(-1, 3)
                centres = np.array([m[:3, 3] for m in mats]).reshape(-1, 3)
                rots = np.array([m[:3, :3] for m in mats]).reshape(-1, 3, 3)
                gt.boxes = boxes_from_oriented(centres, rots, sizes)
                gt.ids = np.array([o.id for o in msg.objects], np.int64)
            else:
                for d in msg.detections:
                    k = int(d.object_id)
                    gt.best_visibility[k] = max(gt.best_visibility.get(k, 0.0), float(d.visibility))
    return gt


def evaluate_run(mapper, truth: GroundTruth, min_visibility: float = 0.2, posed: bool = False) -> dict:
    """Localization (keyframes) and mapping accuracy of a mapper against ground truth."""
    est = mapper.camera_poses()
    by_stamp = {mapper.keyframes[k].stamp_ns: m for k, m in est.items()}
    truth_kf = {mapper.keyframes[k].stamp_ns: truth.camera_poses[mapper.keyframes[k].stamp_ns]
                for k in mapper.keyframes if mapper.keyframes[k].stamp_ns in truth.camera_poses}
    loc = trajectory_errors(by_stamp, truth_kf, align=False if posed else '4dof')
    align = Pose4(0.0, (0.0, 0.0, 0.0)) if posed else map_to_truth(by_stamp, truth_kf)
    tracks = mapper.tracks()
    boxes = align.transform_boxes(np.array([tr.box for tr in tracks]).reshape(-1, 7))
    ignore = np.array([truth.best_visibility.get(int(i), 0.0) < min_visibility for i in truth.ids], bool)
    mapping = evaluate_map(boxes, [tr.score for tr in tracks], truth.boxes, ignore)
    return {'localization': loc, 'mapping': mapping, 'alignment': align}


def write_tum(path, mapper) -> Path:
    """Keyframe trajectory in TUM format: stamp(s) tx ty tz qx qy qz qw (camera optical frame)."""
    lines = []
    for k, m in sorted(mapper.camera_poses().items(), key=lambda kv: mapper.keyframes[kv[0]].stamp_ns):
        q = quaternion_from_matrix(m[:3, :3])
        stamp = mapper.keyframes[k].stamp_ns / 1e9
        lines.append(f'{stamp:.9f} ' + ' '.join(f'{v:.6f}' for v in (*m[:3, 3], *q)))
    path = Path(path)
    path.write_text('\n'.join(lines) + ('\n' if lines else ''))
    return path


def write_object_json(path, mapper, frame_id: str = 'map') -> Path:
    tracks = mapper.tracks()
    objects = [{'id': int(t.track_id), 'center': [float(v) for v in t.box[:3]],
                'size': [float(v) for v in t.box[3:6]], 'yaw': float(t.box[6]), 'score': float(t.score),
                'label': t.label, 'classes': t.class_distribution,
                'observations': [[int(k), int(i)] for k, i in t.observations]} for t in tracks]
    path = Path(path)
    path.write_text(json.dumps({'frame_id': frame_id, 'box_convention':
                                'center (m), size (m) along the box x/y/z, yaw (rad) about z (up)',
                                'objects': objects}, indent=1))
    return path


# ---------------------------------------------------------------------- picture

def _line(img, p0, p1, colour, width=1):
    n = int(max(abs(p1[0] - p0[0]), abs(p1[1] - p0[1]), 1)) + 1
    xs = np.linspace(p0[0], p1[0], n)
    ys = np.linspace(p0[1], p1[1], n)
    for dx in range(-(width // 2), width - width // 2):
        for dy in range(-(width // 2), width - width // 2):
            x = np.clip(np.round(xs + dx).astype(int), 0, img.shape[1] - 1)
            y = np.clip(np.round(ys + dy).astype(int), 0, img.shape[0] - 1)
            img[y, x] = colour


def render_top_down(path, mapper, truth: GroundTruth | None = None, alignment: Pose4 | None = None,
                    size: int = 800) -> Path:
    """Top-down PNG in the ground truth's frame when given (map aligned onto it by
    ``alignment``, T_truth_map):
    ground-truth boxes grey, map boxes coloured by track, trajectory dark blue, keyframes
    as dots, true trajectory light grey."""
    align = alignment if alignment is not None else Pose4(0.0, (0.0, 0.0, 0.0))
    est = mapper.camera_poses()
    centres = align.transform_points(np.array([m[:3, 3] for _, m in sorted(est.items())]).reshape(-1, 3))
    tracks = mapper.tracks()
    boxes = align.transform_boxes(np.array([tr.box for tr in tracks]).reshape(-1, 7))
    gt_boxes = truth.boxes if truth is not None else np.zeros((0, 7))
    gt_path = (np.array([m[:3, 3] for _, m in sorted(truth.camera_poses.items())]).reshape(-1, 3)
               if truth else np.zeros((0, 3)))
    pts = np.concatenate([centres[:, :2], bev_corners(boxes).reshape(-1, 2),
                          bev_corners(gt_boxes).reshape(-1, 2), gt_path[:, :2]]) if (
        len(centres) or len(boxes) or len(gt_boxes)) else np.zeros((1, 2))
    lo, hi = pts.min(0) - 0.3, pts.max(0) + 0.3
    scale = (size - 20) / max(hi - lo)
    h = int((hi[1] - lo[1]) * scale) + 20
    w = int((hi[0] - lo[0]) * scale) + 20
    img = np.full((h, w, 3), 255, np.uint8)

    def px(p):          # map x right, y up
        return ((p[0] - lo[0]) * scale + 10, h - ((p[1] - lo[1]) * scale + 10))

    for gx in np.arange(np.floor(lo[0]), hi[0] + 1):   # 1 m grid
        _line(img, px((gx, lo[1])), px((gx, hi[1])), np.array([235, 235, 235], np.uint8))
    for gy in np.arange(np.floor(lo[1]), hi[1] + 1):
        _line(img, px((lo[0], gy)), px((hi[0], gy)), np.array([235, 235, 235], np.uint8))
    for a, b in zip(gt_path[:-1], gt_path[1:]):
        _line(img, px(a), px(b), np.array([190, 190, 190], np.uint8), 2)
    for corners in bev_corners(gt_boxes):
        for i in range(4):
            _line(img, px(corners[i]), px(corners[(i + 1) % 4]), np.array([150, 150, 150], np.uint8), 1)
    for tr, corners in zip(tracks, bev_corners(boxes)):
        for i in range(4):
            _line(img, px(corners[i]), px(corners[(i + 1) % 4]), (40 + 180 * np.array(track_colour(tr.track_id))).astype(np.uint8), 2)
    for a, b in zip(centres[:-1], centres[1:]):
        _line(img, px(a), px(b), np.array([20, 40, 140], np.uint8), 2)
    for c in centres:
        x, y = px(c)
        img[max(int(y) - 2, 0):int(y) + 3, max(int(x) - 2, 0):int(x) + 3] = (200, 30, 30)
    return write_png(path, img)


def write_report(path, summary: dict) -> Path:
    """Markdown report of a run: what went in, what came out, timings, accuracy."""
    s = summary
    lines = [f'# rfm run: {s.get("input", "")}', '',
             f'- date: {s.get("date", "")}', f'- detector: `{s.get("backend", "")}`, matcher: `{s.get("matcher", "")}`, '
             f'mode: {"posed" if s.get("posed") else "un-posed"}',
             f'- frames detected: {s.get("frames", 0)}, detections published: {s.get("detections", 0)}, '
             f'frames dropped while the detector was busy (newest wins): {s.get("dropped", 0)}',
             f'- keyframes: {s.get("keyframes", 0)}, registered: {s.get("registered", 0)}, '
             f'edges kept / rejected: {s.get("edges", 0)} / {s.get("edges_rejected", 0)}',
             f'- objects in the map: {s.get("objects", 0)}',
             f'- processing time: {s.get("wall_s", 0):.1f} s for {s.get("bag_s", 0):.1f} s of data '
             f'({s.get("realtime", 0):.2f}x real time; from the first frame detected until the last change '
             f'of the graph; 0.2 s polling)', '']
    if s.get('latency_ms'):
        lines += ['## Per-stage latency (median, ms)', '', '| stage | ms |', '|---|---|']
        lines += [f'| {k} | {v:.1f} |' for k, v in s['latency_ms'].items()] + ['']
    acc = s.get('accuracy')
    if acc:
        loc, m = acc['localization'], acc['mapping']
        lines += ['## Accuracy against the bag\'s ground truth', '',
                  '| ARE median (deg) | ATE median (cm) | ARE RMSE (deg) | ATE RMSE (cm) | registered |',
                  '|---|---|---|---|---|',
                  f'| {loc["ARE_median"]:.2f} | {100 * loc["ATE_median"]:.1f} | {loc["ARE_rmse"]:.2f} | '
                  f'{100 * loc["ATE_rmse"]:.1f} | {100 * loc["registered"]:.0f}% |', '',
                  '| AP15 | AR15 | AP25 | AR25 | map objects | ground-truth objects |', '|---|---|---|---|---|---|',
                  f'| {m["AP15"]:.3f} | {m["AR15"]:.3f} | {m["AP25"]:.3f} | {m["AR25"]:.3f} | {m["objects"]} | '
                  f'{m["ground_truth"]} |', '',
                  'Localization over keyframes, aligned by yaw + translation (gravity is shared); mapping: '
                  'scene-level AP/AR at 3D IoU 0.15 / 0.25, objects never seen >= 20% ignored.', '']
    lines += ['## Files', '', '- `map.rfm`: the map (load it with `rfm/load_map`)',
              '- `trajectory.tum`: keyframe camera poses (TUM: stamp tx ty tz qx qy qz qw)',
              '- `objects.json`: the object map', '- `outputs.mcap/`: the output topics (open in Foxglove)',
              '- `top_down.png`: map and trajectory from above' + (' (ground truth in grey)' if acc else ''), '']
    path = Path(path)
    path.write_text('\n'.join(lines))
    return path
