"""A robot's wheel odometry as the motion prior: relative poses from it, and a robot that
turns in place and faces bare walls tracked through them."""
import dataclasses

import numpy as np
import pytest
from sim_frames import detected_frames

from rfm_core.evaluation.trajectory import trajectory_errors
from rfm_core.geometry import Pose4, yaw_matrix
from rfm_core.mapping.mapper import MapperConfig
from rfm_core.matching.motion import StreamMotion
from rfm_core.matching.view_graph import ViewGraphConfig
from rfm_core.session import Session
from rfm_core.sim.capture import Capture, CaptureConfig
from rfm_core.sim.render import NoiseModel


def test_odometry_gives_the_relative_pose_between_gravity_aligned_frames():
    """Without odometry errors the relative pose is the truth's, in the matcher's frames."""
    config = CaptureConfig(seed=12, capture='robot', frames=40, fps=5, noise=NoiseModel.none())
    capture = Capture(config)
    frames = detected_frames(seed=12, frames=40, fps=5, capture='robot', noise=NoiseModel.none())
    poses = {f.stamp_ns: f for f in capture.frames()}
    a, b = frames[3], frames[30]
    measured = StreamMotion.odometry(a, b)
    truth = poses[a.stamp_ns].aligned_from_map() @ poses[b.stamp_ns].aligned_from_map().inverse()
    assert abs(measured.yaw - truth.yaw) < 1e-6 and np.allclose(measured.t, truth.t, atol=1e-6)
    assert StreamMotion.odometry(a, dataclasses.replace(b, odometry_epoch=2)) is None      # another epoch
    assert StreamMotion.odometry(a, dataclasses.replace(b, odometry=None, odometry_epoch=0)) is None


ROBOT = dict(seed=12, frames=300, fps=10, capture='robot', furniture='parts', clutter=True)


@pytest.fixture(scope='module')
def robot_frames():
    # a tuning seed whose robot spins and drives past bare walls for long stretches
    return detected_frames(**ROBOT, noise=NoiseModel.realsense())


@pytest.fixture(scope='module')
def robot_truth():
    """The same capture's true camera poses by stamp: camera-to-map, and the gravity-aligned
    frame's (no images kept)."""
    frames = Capture(CaptureConfig(**ROBOT, noise=NoiseModel.realsense())).frames()
    return {f.stamp_ns: (f.pose_matrix, f.aligned_from_map()) for f in frames}


def mapped(frames, odometry: bool = True, **session_args) -> Session:
    """A session that has mapped ``frames`` (``odometry`` False: without their odometry)."""
    session = Session(**session_args)
    for obs in frames:
        session.step(obs if odometry else dataclasses.replace(obs, odometry=None, odometry_epoch=0))
    session.finish()
    return session


def test_the_odometry_carries_a_robot_where_objects_and_points_do_not(robot_frames, robot_truth):
    """A robot that spins and drives past bare walls: tracked through them by its odometry,
    and not without; objects seen again keep its drift from making poses wrong."""
    truth = {stamp: pose for stamp, (pose, _) in robot_truth.items()}
    results = {}
    for use in (True, False):
        session = mapped(robot_frames, odometry=use)
        results[use] = trajectory_errors(session.mapper.frame_poses(), truth), session.graph.stats.odometry_tracked
    (with_odometry, carried), (without, _) = results[True], results[False]
    # more frames, none wrong
    assert with_odometry['registered'] >= without['registered'] + 0.25 and carried > 20, (with_odometry, without)
    assert with_odometry['gross'] == 0 and with_odometry['ARE_median'] < 1.5, with_odometry


def test_a_robots_map_starts_on_its_first_frame_whatever_it_sees(robot_frames, robot_truth):
    """A robot whose camera sees one object or none for its first 6 s (facing a wall, a
    lone chair): nothing can match, but its odometry links every frame to the first, so
    the map starts there and those frames are placed; without odometry they cannot be."""
    truth = {stamp: pose for stamp, (pose, _) in robot_truth.items()}
    frames = [o.subset(np.arange(min(len(o), i % 2))) if i < 60 else o for i, o in enumerate(robot_frames)]
    first = {o.stamp_ns: truth[o.stamp_ns] for o in frames[:60]}
    results = {}
    for use in (True, False):
        poses = mapped(frames, odometry=use).mapper.frame_poses()
        results[use] = trajectory_errors(poses, truth), trajectory_errors(poses, first)
    (everything, start), (_, start_without) = results[True], results[False]
    assert start['registered'] >= 0.95 and start_without['registered'] == 0, (start, start_without)
    assert everything['gross'] == 0 and everything['ARE_median'] < 1.5, everything


def test_a_frame_tracked_on_two_objects_is_averaged_with_the_odometry(robot_frames, robot_truth):
    """Two boxes fix a pose only as well as their noise; mid-turn a frame tracked on two of
    them can sit 10 cm off (a held-out robot room), and frames and keyframe links after it
    carry that on. Averaged with the pose the odometry carries it to, the map is closer to
    the truth than with the objects' pose alone."""
    truth = {stamp: pose for stamp, (pose, _) in robot_truth.items()}
    results = {}
    for weight in (2.0, 0.0):                   # the default, and the objects' pose alone
        graph = ViewGraphConfig()
        graph = dataclasses.replace(graph, motion=dataclasses.replace(graph.motion, odometry_weight=weight))
        results[weight] = trajectory_errors(mapped(robot_frames, graph=graph).mapper.frame_poses(), truth)
    averaged, alone = results[2.0], results[0.0]
    assert averaged['gross'] == 0 and averaged['registered'] == alone['registered'], (averaged, alone)
    assert averaged['ATE_rmse'] < 0.9 * alone['ATE_rmse'] and averaged['ARE_median'] < alone['ARE_median'], \
        (averaged, alone)


def test_every_keyframe_of_a_robot_is_linked_to_the_one_it_was_tracked_on(robot_frames, robot_truth):
    """A keyframe whose objects did not verify against the keyframe the stream was tracked
    on, but did against older ones, still gets the link its odometry measures from that one
    (beside the older ones): without it two look-alike objects of an older keyframe could
    place it alone (a held-out robot capture: 75 frames 30 cm off)."""
    aligned = {stamp: aligned for stamp, (_, aligned) in robot_truth.items()}
    session = Session()
    beside = []                                  # (error m, error deg) of odometry links beside object edges
    for obs in robot_frames:
        reference = session.graph.reference if session.graph.keyframes else None
        step = session.step(obs)
        if step.keyframe is None or step.keyframe.observations is not obs or reference is None:
            continue
        links = [e.relative for e in step.edges if e.source_id == reference.keyframe_id]
        assert links, f'keyframe {step.keyframe.keyframe_id} has no edge from {reference.keyframe_id}'
        if len(step.edges) > 1 and not len(links[0].inliers):
            truth = aligned[reference.observations.stamp_ns] @ aligned[obs.stamp_ns].inverse()
            beside.append((np.linalg.norm(np.asarray(links[0].pose.t) - np.asarray(truth.t)),
                           np.degrees(abs(links[0].pose.yaw - truth.yaw))))
    errors = np.array(beside)
    assert len(errors) >= 4 and np.all(errors < (0.05, 1.0)), errors      # and those links are right


def test_the_gyroscopes_drift_is_measured_and_taken_out(robot_frames, robot_truth):
    """A gyroscope that drifts 0.3 deg/s about the vertical (a MEMS zero-rate offset): its
    yaw edges would turn the robot's map against its objects by 9 deg over the capture. The
    mapper measures the drift from the objects' edges and takes it out of them."""
    truth = {stamp: pose for stamp, (pose, _) in robot_truth.items()}
    drift, start = np.radians(0.3), robot_frames[0].stamp_ns
    frames = [dataclasses.replace(o, imu_rotation=yaw_matrix(drift * (o.stamp_ns - start) * 1e-9) @ o.imu_rotation)
              for o in robot_frames]
    results = {}
    for prior_dps in (0.5, 1e-3):               # the default prior, and one that pins the drift at zero
        config = MapperConfig()
        config = dataclasses.replace(config, averaging=dataclasses.replace(config.averaging,
                                                                           gyro_bias_sigma_dps=prior_dps))
        session = mapped(frames, config=config)
        results[prior_dps] = session.mapper.gyro_drift, trajectory_errors(session.mapper.frame_poses(), truth)
    (measured, corrected), (_, uncorrected) = results[0.5], results[1e-3]
    assert abs(measured + drift) < np.radians(0.05), np.degrees(measured)      # the correction undoes it
    assert corrected['gross'] == 0 and corrected['ARE_median'] < 1.2, corrected
    assert uncorrected['gross'] > 20 and uncorrected['ARE_median'] > 1.5, uncorrected
