"""Detections of a simulated capture as the detector node hands them on (shared by tests)."""
from rfm_core.evaluation.pipeline import detections_for
from rfm_core.sim.capture import Capture, CaptureConfig


def detected_frames(seed: int = 40, frames: int = 50, fps: float = 5, noise_seed: int = 3, **config) -> list:
    """FrameObservations of every frame: noisy ground-truth boxes (``ground_truth:rgbd``) with
    the gyroscope's orientation attached, as the detector node attaches it (and on a robot
    capture the camera's pose in its wheel odometry's frame, as the detector attaches it from
    /tf). ``config``: more CaptureConfig fields."""
    detect = detections_for('ground_truth:rgbd', noise_seed)
    capture = Capture(CaptureConfig(seed=seed, frames=frames, fps=fps, **config))
    odometry = capture.camera_odometry() if capture.trajectory.path is not None else {}
    out = []
    for frame in capture.frames():
        obs = detect(frame)
        obs.imu_rotation, obs.imu_epoch = frame.rotation, 1
        if frame.stamp_ns in odometry:
            obs.odometry, obs.odometry_epoch = odometry[frame.stamp_ns], 1
        out.append(obs)
    return out
