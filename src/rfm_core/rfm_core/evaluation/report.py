"""The output folder of a run: TUM trajectory, object map JSON, a Markdown report and a
top-down PNG — from a saved map, plus ground truth when the bag has it.

No ROS here; the picture is drawn with matplotlib (imported only when one is drawn).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rfm_core.evaluation.mapping import evaluate_map
from rfm_core.evaluation.trajectory import covariance_coverage, map_to_truth, trajectory_errors
from rfm_core.geometry import Pose4, bev_corners, iou_3d, quaternion_from_matrix
from rfm_core.io.messages import track_colour

__all__ = ['GroundTruth', 'read_ground_truth', 'published_camera_poses', 'tf_camera_poses', 'map_boxes',
           'frames_seeing_mapped', 'evaluate_run', 'write_tum',
           'write_keyframes_tum', 'write_object_json', 'render_top_down', 'write_report']


@dataclass
class GroundTruth:
    camera_poses: dict = field(default_factory=dict)     #: stamp_ns -> 4x4 camera-to-map
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))   #: (M, 7) map frame, z up
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    labels: list = field(default_factory=list)           #: the objects' classes, as ``boxes``
    best_visibility: dict = field(default_factory=dict)  #: object id -> best visible fraction
    frame_visibility: dict = field(default_factory=dict)  #: stamp_ns -> {object id: visible fraction}

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
        if not conns:                    # (an empty list would make rosbags read every topic)
            return gt
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
                gt.labels = [o.label for o in msg.objects]
            else:
                seen = gt.frame_visibility.setdefault(stamp_to_ns(msg.header.stamp), {})
                for d in msg.detections:
                    k = int(d.object_id)
                    seen[k] = float(d.visibility)
                    gt.best_visibility[k] = max(gt.best_visibility.get(k, 0.0), float(d.visibility))
    return gt


def map_boxes(tracks, alignment: Pose4) -> np.ndarray:
    """(N, 7) the boxes of a map's ``tracks`` moved by ``alignment`` (e.g. T_truth_map)."""
    return alignment.transform_boxes(np.array([t.box for t in tracks]).reshape(-1, 7))


def frames_seeing_mapped(truth: GroundTruth, map_boxes: np.ndarray, min_objects: int = 2,
                         min_visibility: float = 0.2, iou: float = 0.25) -> set:
    """The stamps of the frames of ``truth`` that see ``min_objects`` mapped objects: objects
    of the room a box of the map (``map_boxes``, (N, 7) in the truth's frame) overlaps by
    ``iou``, each at least ``min_visibility`` in view (the relocalization score's denominator:
    a frame that sees fewer gives an object-level relative pose nothing to verify)."""
    if not len(map_boxes) or not len(truth.boxes):
        return set()
    mapped = {int(i) for i, hit in zip(truth.ids, iou_3d(truth.boxes, map_boxes).max(1) >= iou) if hit}
    return {stamp for stamp, seen in truth.frame_visibility.items()
            if sum(v >= min_visibility for k, v in seen.items() if k in mapped) >= min_objects}


def published_camera_poses(output) -> tuple[dict, dict]:
    """({stamp_ns: 4x4 camera-to-map}, {stamp_ns: (6, 6) covariance or None}) of every
    ``rfm/camera_pose`` an ``rfm run`` recorded (its ``outputs.mcap`` bag folder), as the
    mapper published them; a recording of PoseStamped messages has no covariances."""
    from rfm_core.io.bag import topic_messages  # noqa: PLC0415
    from rfm_core.io.messages import pose_to_matrix, stamp_to_ns  # noqa: PLC0415

    poses, covariances = {}, {}
    for msg in topic_messages(Path(output) / 'outputs.mcap', '/rfm/camera_pose'):
        stamp, pose = stamp_to_ns(msg.header.stamp), msg.pose
        poses[stamp] = pose_to_matrix(getattr(pose, 'pose', pose))
        cov = np.asarray(getattr(pose, 'covariance', np.zeros(36)), float).reshape(6, 6)
        covariances[stamp] = cov if np.any(cov) else None
    return poses, covariances


def tf_camera_poses(output, bag, stamps, map_frame: str = 'map') -> dict:
    """{stamp_ns: 4x4 camera-to-map} at each of ``stamps`` (every image of the input) as a
    tf2 lookup of ``map_frame`` -> the camera's frame gives it after an ``rfm run``: the
    bag's ``/tf`` and ``/tf_static`` (a robot's odometry and its camera's mount) under the
    transforms from ``map_frame`` the mapper broadcast (``outputs.mcap``: ``map`` -> ``odom``
    on a robot), interpolated, never extrapolated. What a robot stack reads, at every image,
    also those the detector had no time for; empty when the mapper broadcast nothing."""
    from rfm_core.io.bag import topics_messages  # noqa: PLC0415
    from rfm_core.io.messages import transforms_from_msg  # noqa: PLC0415
    from rfm_core.transforms import TransformBuffer  # noqa: PLC0415

    outputs = Path(output) / 'outputs.mcap'
    buffer = TransformBuffer(cache_s=1e9, tolerance_s=0.0)
    camera, broadcast = None, False
    for path in (bag, outputs):
        for topic, msg in topics_messages(path, ('/tf_static', '/tf', '/rfm/tracked_frames')):
            if topic == '/rfm/tracked_frames':
                camera = camera or msg.header.frame_id
                continue
            for parent, child, stamp_ns, matrix in transforms_from_msg(msg):
                if (parent == map_frame) != (path == outputs):     # the bag's own transforms from the bag
                    continue
                refused = buffer.add(parent, child, stamp_ns, matrix, static=topic == '/tf_static')
                broadcast |= path == outputs and refused is None
    if camera is None or not broadcast:
        return {}
    return {s: m for s in stamps if (m := buffer.lookup(map_frame, camera, s)) is not None}


def evaluate_run(mapper, truth: GroundTruth, min_visibility: float = 0.2, posed: bool = False,
                 published: tuple | None = None, through_tf: dict | None = None) -> dict:
    """Localization and mapping accuracy of a mapper against ground truth (``mapping`` None
    where the ground truth has camera poses only, no objects). Localization is
    over every frame of the input (``registered``: the share of the ground truth's frames
    localized, as in the paper), with the keyframes' figures beside it (``keyframe_*``) and,
    given ``published`` (:func:`published_camera_poses`), the camera poses as the mapper
    published them: ``published``, ``published_gross`` (wrong ones) and ``within_2sigma``
    (:func:`~rfm_core.evaluation.trajectory.covariance_coverage`); given ``through_tf``
    (:func:`tf_camera_poses`), the camera poses a tf2 lookup gives at every image:
    ``tf`` (the localization figures of :func:`trajectory_errors`)."""
    align_kind = False if posed else '4dof'
    frames = mapper.frame_poses()
    loc = trajectory_errors(frames, truth.camera_poses, align=align_kind)
    if published is not None and published[0]:
        live, covariances = published
        loc['published'] = len(live)
        loc['published_gross'] = trajectory_errors(live, truth.camera_poses, align=align_kind)['gross']
        loc['within_2sigma'] = covariance_coverage(live, covariances, truth.camera_poses, align=align_kind)[
            'within_2sigma']
    if through_tf:
        loc['tf'] = trajectory_errors(through_tf, truth.camera_poses, align=align_kind)
    est = mapper.camera_poses()
    by_stamp = {mapper.keyframes[k].stamp_ns: m for k, m in est.items()}
    truth_kf = {mapper.keyframes[k].stamp_ns: truth.camera_poses[mapper.keyframes[k].stamp_ns]
                for k in mapper.keyframes if mapper.keyframes[k].stamp_ns in truth.camera_poses}
    kf = trajectory_errors(by_stamp, truth_kf, align=align_kind)
    loc.update({f'keyframe_{k}': v for k, v in kf.items()})
    loc['keyframes'] = len(mapper.keyframes)
    align = Pose4(0.0, (0.0, 0.0, 0.0)) if posed else map_to_truth(frames or by_stamp, truth.camera_poses)
    tracks = mapper.tracks()
    boxes = map_boxes(tracks, align)
    ignore = np.array([truth.best_visibility.get(int(i), 0.0) < min_visibility for i in truth.ids], bool)
    mapping = (evaluate_map(boxes, [tr.score for tr in tracks], truth.boxes, ignore,
                            labels=[tr.label for tr in tracks], gt_labels=truth.labels)
               if len(truth.boxes) else None)
    return {'localization': loc, 'mapping': mapping, 'alignment': align}


def _labels_line(labels: dict) -> str:
    """The labels of the map objects on a real one, overall and per class (NYU40 names)."""
    per_class = ', '.join(f'{name} {right}/{n}' for name, (n, right) in
                          sorted(labels['classes'].items(), key=lambda kv: -kv[1][0]))
    return (f"Labels: {labels['right']} of the {labels['labelled']} map objects on a real object carry its class "
            f"({100 * labels['right'] / labels['labelled']:.0f}%; NYU40 names; right of labelled, per class: "
            f'{per_class}).')


def _write_tum(path, poses: dict) -> Path:
    """{stamp_ns: 4x4} -> TUM lines: stamp(s) tx ty tz qx qy qz qw, in stamp order."""
    lines = []
    for stamp, m in sorted(poses.items()):
        q = quaternion_from_matrix(m[:3, :3])
        lines.append(f'{stamp / 1e9:.9f} ' + ' '.join(f'{v:.6f}' for v in (*m[:3, 3], *q)))
    path = Path(path)
    path.write_text('\n'.join(lines) + ('\n' if lines else ''))
    return path


def write_tum(path, mapper) -> Path:
    """Every localized frame's camera pose (optical frame in the map) in TUM format: stamp(s)
    tx ty tz qx qy qz qw."""
    return _write_tum(path, mapper.frame_poses())


def write_keyframes_tum(path, mapper) -> Path:
    """The registered keyframes' camera poses in TUM format."""
    return _write_tum(path, {mapper.keyframes[k].stamp_ns: m for k, m in mapper.camera_poses().items()})


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

def render_top_down(path, mapper, truth: GroundTruth | None = None, alignment: Pose4 | None = None,
                    title: str = '') -> Path:
    """The map from above (matplotlib, axes in metres), in the ground truth's frame when
    given (``alignment``: T_truth_map): map boxes coloured by track, the trajectory of every
    localized frame, keyframes, and with ground truth its boxes, its trajectory and the true
    positions of the frames that were not localized."""
    import matplotlib  # noqa: PLC0415
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # noqa: PLC0415
    from matplotlib.patches import Polygon  # noqa: PLC0415

    align = alignment if alignment is not None else Pose4(0.0, (0.0, 0.0, 0.0))
    frames = mapper.frame_poses()
    path_xy = align.transform_points(np.array([m[:3, 3] for _, m in sorted(frames.items())]).reshape(-1, 3))
    keyframes = align.transform_points(
        np.array([m[:3, 3] for m in mapper.camera_poses().values()]).reshape(-1, 3))
    tracks = mapper.tracks()
    boxes = map_boxes(tracks, align)
    fig, ax = plt.subplots(figsize=(8, 8), dpi=100)
    handles = []
    if truth:
        for corners in bev_corners(truth.boxes):
            ax.add_patch(Polygon(corners, closed=True, fill=True, facecolor='0.92', edgecolor='0.55', lw=1.0))
        gt_path = np.array([m[:3, 3] for _, m in sorted(truth.camera_poses.items())]).reshape(-1, 3)
        handles += ax.plot(gt_path[:, 0], gt_path[:, 1], color='0.6', lw=3, alpha=0.7, label='true trajectory')
        handles.append(Polygon(np.zeros((4, 2)), facecolor='0.92', edgecolor='0.55', label='true objects'))
        lost = np.array([m[:3, 3] for s_, m in sorted(truth.camera_poses.items()) if s_ not in frames]).reshape(-1, 3)
        if len(lost):
            handles.append(ax.scatter(lost[:, 0], lost[:, 1], marker='x', s=25, color='tab:orange', zorder=4,
                                      label=f'not localized ({len(lost)} of {len(truth.camera_poses)} frames)'))
    for tr, corners in zip(tracks, bev_corners(boxes)):
        colour = 0.15 + 0.7 * np.array(track_colour(tr.track_id))
        ax.add_patch(Polygon(corners, closed=True, fill=True, facecolor=(*colour, 0.15), edgecolor=colour, lw=1.6))
    if len(boxes):
        handles.append(Polygon(np.zeros((4, 2)), facecolor=(0.5, 0.5, 0.9, 0.15), edgecolor='tab:blue',
                               label=f'mapped objects ({len(boxes)}, coloured by track)'))
    if len(path_xy):
        handles += ax.plot(path_xy[:, 0], path_xy[:, 1], color='navy', lw=1.5,
                           label=f'trajectory ({len(path_xy)} frames)')
    if len(keyframes):
        handles.append(ax.scatter(keyframes[:, 0], keyframes[:, 1], s=14, color='tab:red', zorder=5,
                                  label=f'keyframes ({len(keyframes)} of {len(mapper.keyframes)} registered)'))
    ax.set_aspect('equal')
    ax.autoscale_view()
    ax.margins(0.05)
    ax.grid(True, color='0.9', lw=0.8)
    ax.set_axisbelow(True)
    ax.set_xlabel('x (m)')
    ax.set_ylabel('y (m)')
    ax.set_title(title or ('rfm map, aligned to the ground truth' if truth else 'rfm map'), fontsize=10)
    if handles:
        ax.legend(handles=handles, loc='upper center', bbox_to_anchor=(0.5, -0.08), ncol=2, fontsize=8,
                  frameon=False)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


def _reasons(counts: dict | None) -> str:
    """' (busy 3, no_gravity 1)' for the non-zero drop reasons."""
    parts = [f'{k.replace("_", " ")} {v}' for k, v in (counts or {}).items() if v]
    return f' ({", ".join(parts)})' if parts else ''


def _percent(share) -> str:
    return 'none' if share is None or not np.isfinite(share) else f'{100 * share:.0f}%'


def write_report(path, summary: dict) -> Path:
    """Markdown report of a run: what went in, what came out, timings, accuracy, picture."""
    s = summary
    frames_in = s.get('input_frames')
    processed = s.get('frames', 0)
    share = f' of {frames_in} in the input ({100 * processed / max(frames_in, 1):.0f}%)' if frames_in else ''
    lines = [f'# rfm run: {s.get("input", "")}', '',
             f'- date: {s.get("date", "")}', f'- detector: `{s.get("backend", "")}`, matcher: `{s.get("matcher", "")}`, '
             f'mode: {"posed" if s.get("posed") else "un-posed"}',
             f'- frames processed by the detector: {processed}{share}'
             + (f' ({s["points_only"]} of them sent with their depth points only: the detector was behind)'
                if s.get('points_only') else '')
             + f'; frames dropped: {s.get("dropped", 0)}'
             + _reasons(s.get('dropped_by_reason'))
             + (f'; colour images received: {s["received"]}' if s.get('received') is not None else '')
             + (f'; keyframes, edges and tracked frames lost between matcher and mapper: {s["lost_between_nodes"]}'
                if s.get('lost_between_nodes') else ''),
             *([f'- frames the matcher skipped to keep up (depth points only; matcher.shed_after_s): {m["shed"]} of '
                f'{m["received"]}' + (f'; lost before it: {m["lost"]}' if m.get('lost') else '')]
               if (m := s.get('matcher_frames') or {}).get('shed') or m.get('lost') else []),
             f'- frames localized: {s.get("localized", 0)} (written to `trajectory.tum`)',
             f'- keyframes: {s.get("keyframes", 0)}, registered: {s.get("registered", 0)}, '
             f'edges kept / rejected: {s.get("edges", 0)} / {s.get("edges_rejected", 0)}',
             f'- objects in the map: {s.get("objects", 0)}',
             *([f'- relocalization queries (localization mode, rfm/relocalize): {r["queries"]}, '
                f'{r["relocalized"]} placed in the map; wall time per query: median {r["median_ms"]:.0f} ms, '
                f'95th percentile {r["p95_ms"]:.0f} ms'] if (r := s.get('relocalization') or {}).get('queries') else []),
             f'- processing time: {s.get("wall_s", 0):.1f} s for {s.get("bag_s", 0):.1f} s of data '
             f'({s.get("realtime", 0):.2f}x real time; from the first frame detected until the last change '
             f'of the graph; 0.2 s polling)',
             *([f'- peak resident memory: ' + ', '.join(f'{k} {v:.0f} MB' for k, v in mem.items())
                + (f' ({sum(mem.values()):.0f} MB in all)' if len(mem) > 1 else '')]
               if (mem := s.get('peak_memory_mb')) else []), '']
    if s.get('latency_ms'):
        lines += ['## Per-stage latency (median, ms)', '', '| stage | ms |', '|---|---|']
        lines += [f'| {k} | {v:.1f} |' for k, v in s['latency_ms'].items()] + ['']
    acc = s.get('accuracy')
    if acc:
        loc, m = acc['localization'], acc['mapping']
        lines += ['## Accuracy against the bag\'s ground truth', '',
                  '| frames | ARE median (deg) | ATE median (cm) | ARE RMSE (deg) | ATE RMSE (cm) | localized '
                  '| wrong (> 5 deg or > 25 cm) |',
                  '|---|---|---|---|---|---|---|',
                  f'| all {loc["frames"]} of the input | {loc["ARE_median"]:.2f} | {100 * loc["ATE_median"]:.1f} | '
                  f'{loc["ARE_rmse"]:.2f} | {100 * loc["ATE_rmse"]:.1f} | {100 * loc["registered"]:.0f}% | '
                  f'{loc.get("gross", 0)} |',
                  f'| {loc.get("keyframes", 0)} keyframes | {loc["keyframe_ARE_median"]:.2f} | '
                  f'{100 * loc["keyframe_ATE_median"]:.1f} | {loc["keyframe_ARE_rmse"]:.2f} | '
                  f'{100 * loc["keyframe_ATE_rmse"]:.1f} | {100 * loc["keyframe_registered"]:.0f}% | '
                  f'{loc.get("keyframe_gross", 0)} |',
                  *([f'| {loc["published"]} as published on `rfm/camera_pose` (live) | | | | | | '
                     f'{loc["published_gross"]} |'] if loc.get('published') else []),
                  *([f'| {round(loc["tf"]["registered"] * loc["frames"])} through TF (`map` -> camera at each image) '
                     f'| {loc["tf"]["ARE_median"]:.2f} | {100 * loc["tf"]["ATE_median"]:.1f} | '
                     f'{loc["tf"]["ARE_rmse"]:.2f} | {100 * loc["tf"]["ATE_rmse"]:.1f} | '
                     f'{100 * loc["tf"]["registered"]:.0f}% | {loc["tf"]["gross"]} |']
                    if loc.get('tf') else []),
                  *(['', f'{_percent(loc.get("within_2sigma"))} of the poses as published lie within the 2-sigma '
                     'bound of their covariance (4-DoF; a calibrated covariance: about 95%).']
                    if loc.get('published') else []), '',
                  *(['| AP15 | AR15 | AP25 | AR25 | map objects | ground-truth objects |', '|---|---|---|---|---|---|',
                     f'| {m["AP15"]:.3f} | {m["AR15"]:.3f} | {m["AP25"]:.3f} | {m["AR25"]:.3f} | {m["objects"]} | '
                     f'{m["ground_truth"]} |', ''] if m else
                    ['The ground truth has no objects: the map is not scored.', '']),
                  *([('Map objects: {real} first boxes of real objects, {duplicate} duplicates, {poor_fit} poor '
                      'fits (IoU 0.1-0.25), {phantom} overlapping nothing real (IoU < 0.1).').format(**m['kinds']), '']
                    if m and m.get('kinds') else []),
                  *([_labels_line(m['labels']), ''] if m and (m.get('labels') or {}).get('labelled') else []),
                  'Localization aligned by yaw + translation (gravity is shared), fitted on the frames most of '
                  'the trajectory agrees with; a frame counts as localized when it has a pose in `trajectory.tum`, '
                  'as wrong when it is off by more than 5 deg or 25 cm. Mapping: scene-level AP/AR at 3D IoU 0.15 / 0.25, objects '
                  'never seen >= 20% ignored.', '']
    lines += ['## Map from above', '', '![top-down view](top_down.png)', '',
              '## Files', '', '- `map.rfm`: the map (load it with `rfm/load_map`)',
              '- `trajectory.tum`: camera pose of every localized frame (TUM: stamp tx ty tz qx qy qz qw)',
              '- `keyframes.tum`: the registered keyframes\' camera poses', '- `objects.json`: the object map',
              '- `outputs.mcap/`: the output topics (open in Foxglove)',
              '- `top_down.png`: map and trajectory from above' + (' (ground truth in grey)' if acc else ''), '']
    path = Path(path)
    path.write_text('\n'.join(lines))
    return path
