"""`rfm replay`: the detections a graph run recorded, through the in-process back end again.

A graph run is not repeatable: which frames the detector finishes, and which go out with
depth points only, changes from run to run, and single scenes swing by tens of points.
Replaying one run's recorded ``rfm/detections`` (``outputs.mcap``) through
:class:`rfm_core.session.Session` (the matcher's and the mapper's code, default settings, no
timing) is: two versions of the back end compared on the same detections differ only by
their code.

- :func:`replay_mapping`: a scene of ``rfm eval --work WORK``, or the mapping walk of a room
  of ``rfm eval-reloc --work WORK`` (its bag's ground truth scores the frames localized, as
  ``rfm eval`` does, with the share off by > 5 deg or > 25 cm), and how many of its frames
  any back end could relate by three objects (:func:`shared_detections`).
- :func:`replay_localization`: a room of ``rfm eval-reloc --work WORK``: its saved map
  loaded in localization mode, the query walk's recorded detections localized as a stream
  and scored as ``rfm eval-reloc`` scores the graph. Localization against a frozen map is
  deterministic: the same detections give the graph's result.
- :func:`replay_session`: a room of ``rfm eval-reloc --work WORK``: its saved map loaded in
  mapping mode, the second session's recorded detections mapped on it, and the map it ends
  with scored as ``rfm eval-reloc`` scores the graph's saved map.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ['recorded_detections', 'shared_detections', 'replay_mapping', 'replay_localization', 'replay_session']

#: two detections of one object from two frames: full-box centres this close in the world (m)
SAME_OBJECT_M = 0.3


def recorded_detections(run: Path) -> list:
    """The FrameObservations of every ``rfm/detections`` message a run recorded, by stamp."""
    from rfm_core.io.bag import topic_messages  # noqa: PLC0415
    from rfm_core.io.messages import frame_detections_from_msg  # noqa: PLC0415

    out = [frame_detections_from_msg(msg) for msg in topic_messages(Path(run) / 'outputs.mcap', '/rfm/detections')]
    return sorted(out, key=lambda o: o.stamp_ns)


def shared_detections(observations: list, truth: dict, radius_m: float = SAME_OBJECT_M) -> dict:
    """{stamp_ns: how many of a frame's detections some other frame also detected} (full-box
    centres within ``radius_m`` in the world, placed by the true camera poses ``truth``
    {stamp_ns: 4x4 camera-to-world}; frames without a true pose are left out). Clutter the
    ground truth does not list counts: a detector's box on it is a landmark too. A frame
    whose count is under ``keyframes.min_retrieved_inliers`` (3) cannot be related to any
    other by that many objects, whatever the matching and the back end: what the detector
    leaves a photo collection."""
    centres = {}
    for obs in observations:
        pose = truth.get(obs.stamp_ns)
        if pose is None:
            continue
        pose = np.asarray(pose, float)
        c = np.asarray(obs.map_boxes, float).reshape(-1, 7)[:, :3] @ obs.rotation_aligned_from_camera  # R^T c
        centres[obs.stamp_ns] = c @ pose[:3, :3].T + pose[:3, 3]
    out = {}
    for stamp, own in centres.items():
        others = [c for s, c in centres.items() if s != stamp and len(c)]
        if not len(own) or not others:
            out[stamp] = 0
            continue
        others = np.concatenate(others)
        near = np.linalg.norm(own[:, None] - others[None], axis=-1).min(axis=1) < radius_m
        out[stamp] = int(near.sum())
    return out


def replay_mapping(scene: Path, run: str = 'rgb_d__depth_clusters', bag: str = 'bag',
                   matcher: str = 'learned') -> dict:
    """One scene's recorded detections through a Session; the frames it localizes scored
    against the bag's ground truth (4-DoF aligned)."""
    from rfm_core.evaluation.report import read_ground_truth  # noqa: PLC0415
    from rfm_core.evaluation.trajectory import covariance_coverage, trajectory_errors  # noqa: PLC0415
    from rfm_core.mapping.mapper import MapperConfig  # noqa: PLC0415
    from rfm_core.matching.factory import make_matcher  # noqa: PLC0415
    from rfm_core.session import Session  # noqa: PLC0415

    scene = Path(scene)
    observations = recorded_detections(scene / run)
    truth = read_ground_truth(scene / bag).camera_poses
    session = Session(MapperConfig(), matcher=make_matcher(matcher))
    live, covariances = {}, {}                  # the camera poses as published, with their covariances
    for obs in observations:
        camera = session.step(obs).camera
        if camera is not None:
            live[camera.stamp_ns], covariances[camera.stamp_ns] = camera.matrix, camera.covariance
    session.finish()
    errors = trajectory_errors(session.mapper.frame_poses(), truth)
    published = trajectory_errors(live, truth)
    coverage = covariance_coverage(live, covariances, truth)
    shared = shared_detections(observations, truth)
    return {'scene': scene.name, 'frames': len(truth), 'detections': len(observations),
            'registered': errors['registered'], 'ARE_median': errors['ARE_median'],
            'ATE_median': errors['ATE_median'], 'wrong': errors['wrong'], 'gross': errors['gross'],
            'published': len(live), 'published_gross': published['gross'],
            'within_2sigma': coverage['within_2sigma'], 'sigma_m': coverage['sigma_m'],
            'sigma_deg': coverage['sigma_deg'],
            'point_tracked': session.graph.stats.point_tracked, 'keyframes': len(session.mapper.keyframes),
            'relatable': sum(n >= session.graph.config.keyframes.min_retrieved_inliers for n in shared.values())}


def replay_localization(room: Path, kind: str = 'handheld', verbose: bool = False) -> dict:
    """One room of an ``rfm eval-reloc`` run: its ``kind`` query walk's recorded detections
    localized against its saved map (see the module). ``verbose`` prints each missed frame of
    the denominator (the query frames that see two mapped objects) with the reason, and each
    wrong pose."""
    from rfm_core.evaluation.suite import query_folders, relocalization_scores  # noqa: PLC0415
    from rfm_core.evaluation.trajectory import covariance_coverage  # noqa: PLC0415
    from rfm_core.mapping.mapper import MapperConfig  # noqa: PLC0415
    from rfm_core.matching.factory import make_matcher  # noqa: PLC0415
    from rfm_core.session import MapSession  # noqa: PLC0415

    room = Path(room)
    session = MapSession(MapperConfig(), matcher=make_matcher('learned'))
    session.load(room / 'map_run' / 'map.rfm')
    session.mode = 'localization'
    poses, covariances, why = {}, {}, {}
    bag, run = query_folders(room, kind)
    for obs in recorded_detections(run):
        for camera in session.localize(obs):
            poses[camera.stamp_ns], covariances[camera.stamp_ns] = camera.matrix, camera.covariance
        why[obs.stamp_ns] = f'{len(obs)} detections: {session.message}'
    scores = relocalization_scores(session.mapper, room / 'map_bag', bag, poses)
    estimated, truth, seeing, row = scores.estimated, scores.truth, scores.seeing, scores.row
    if verbose:
        start = min(truth)
        for stamp in sorted(seeing - set(estimated)):
            print(f'    missed {(stamp - start) * 1e-9:5.1f} s: {why.get(stamp, "no detections recorded")}')
        _print_wrong(estimated, truth)
    coverage = covariance_coverage(poses, covariances, truth)          # poses in the map frame: aligned
    return {'scene': room.name, 'query': kind, 'seeing': len(seeing), 'found': len(seeing & set(estimated)),
            'relocalized': len(estimated), 'wrong': row['gross'], 'within_2sigma': coverage['within_2sigma'],
            'covered': coverage['frames'],
            'ARE_median': row['ARE_median'], 'ATE_median': row['ATE_median'], 'map_registered': row['map_registered']}


def replay_session(room: Path, verbose: bool = False) -> dict:
    """One room of an ``rfm eval-reloc`` run: its second session's recorded detections mapped
    on its saved map (mapping mode), scored from the map that ends with, as the graph's
    ``session`` row is. ``verbose`` prints each wrong frame."""
    import tempfile  # noqa: PLC0415

    from rfm_core.evaluation.suite import query_folders, scored_session  # noqa: PLC0415
    from rfm_core.mapping.map_io import load_map  # noqa: PLC0415
    from rfm_core.mapping.mapper import Mapper, MapperConfig  # noqa: PLC0415
    from rfm_core.matching.factory import make_matcher  # noqa: PLC0415
    from rfm_core.session import Session  # noqa: PLC0415

    room = Path(room)
    loaded = room / 'map_run' / 'map.rfm'
    session = Session(MapperConfig(), matcher=make_matcher('learned'))
    session.map.load(loaded)
    bag, run = query_folders(room, 'session')
    for obs in recorded_detections(run):
        session.step(obs)
    session.finish()
    before = Mapper()
    load_map(before, loaded)
    with tempfile.TemporaryDirectory() as tmp:
        row, scores = scored_session(before, session.map.save(Path(tmp) / 'map.rfm'), room / 'map_bag', bag)
    if verbose:
        _print_wrong(scores.estimated, scores.truth)
    return {'scene': room.name, 'query': 'session', **row}


def _print_wrong(estimated: dict, truth: dict) -> None:
    """Each frame of ``estimated`` more than 5 deg or 25 cm off its ``truth`` (seconds from the first)."""
    from rfm_core.evaluation.trajectory import GROSS, frame_errors  # noqa: PLC0415

    start = min(truth)
    for stamp, (metres, deg) in sorted(frame_errors(estimated, truth).items()):
        if deg > GROSS[0] or metres > GROSS[1]:
            print(f'    wrong  {(stamp - start) * 1e-9:5.1f} s: {deg:.1f} deg, {metres:.2f} m')
