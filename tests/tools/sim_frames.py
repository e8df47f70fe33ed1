"""Detections of a simulated capture as the detector node hands them on (shared by tests)."""
from rfm_core.evaluation.pipeline import detections_for
from rfm_core.sim.capture import Capture, CaptureConfig


def detected_frames(seed: int = 40, frames: int = 50, fps: float = 5, noise_seed: int = 3, **config) -> list:
    """FrameObservations of every frame: noisy ground-truth boxes (``ground_truth:rgbd``) with
    the gyroscope's orientation attached, as the detector node attaches it (and on a robot
    capture the camera's pose in its wheel odometry's frame, as the detector attaches it from
    /tf). ``config``: more CaptureConfig fields."""
    capture = Capture(CaptureConfig(seed=seed, frames=frames, fps=fps, **config))
    odometry = capture.camera_odometry() if capture.trajectory.path is not None else {}
    out, _ = observed(capture, detections_for('ground_truth:rgbd', noise_seed))
    for obs in out:
        if obs.stamp_ns in odometry:
            obs.odometry, obs.odometry_epoch = odometry[obs.stamp_ns], 1
    return out


def observed(capture: Capture, detect, epoch=lambda i: 1) -> tuple:
    """(detections of every frame, {stamp: true camera pose}): each frame given the true
    rotation as its gyroscope's orientation, in integration epoch ``epoch(i)`` (the i-th frame)."""
    observations, truth = [], {}
    for i, frame in enumerate(capture.frames()):
        obs = detect(frame)
        obs.imu_rotation, obs.imu_epoch = frame.rotation, epoch(i)
        observations.append(obs)
        truth[obs.stamp_ns] = frame.pose_matrix
    return observations, truth
