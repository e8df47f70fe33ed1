"""Detections of a simulated capture as the detector node hands them on (shared by tests)."""
from rfm_core.evaluation.pipeline import detections_for
from rfm_core.sim.capture import Capture, CaptureConfig


def detected_frames(seed: int = 40, frames: int = 50, fps: float = 5, noise_seed: int = 3) -> list:
    """FrameObservations of every frame: noisy ground-truth boxes (``ground_truth:rgbd``) with
    the gyroscope's orientation attached, as the detector node attaches it."""
    detect = detections_for('ground_truth:rgbd', noise_seed)
    out = []
    for frame in Capture(CaptureConfig(seed=seed, frames=frames, fps=fps)).frames():
        obs = detect(frame)
        obs.imu_rotation, obs.imu_epoch = frame.rotation, 1
        out.append(obs)
    return out
