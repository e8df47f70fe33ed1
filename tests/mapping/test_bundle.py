"""Partial bundle adjustment of track boxes (paper 3.6) on a case with a known answer."""
import numpy as np

from rfm_core.geometry import Pose4, iou_3d_paired
from rfm_core.mapping.bundle import BundleConfig, refine_tracks
from rfm_core.mapping.tracks import TrackConfig, build_tracks
from rfm_core.observations import CameraIntrinsics, FrameObservations

CABINET = np.array([2.0, 1.0, 0.4, 0.6, 0.4, 0.8, 0.3])          # in the map: centre, size, yaw
INTRINSICS = CameraIntrinsics(300.0, 300.0, 160.0, 120.0, 320, 240)


def _view(centre, scale):
    """A level camera at ``centre`` looking at the cabinet, whose detection is the true box
    scaled about the camera by ``scale``: what a monocular detector that misjudges distance
    reports (the same image, the wrong range)."""
    d = CABINET[:3] - np.asarray(centre, float)
    pose = Pose4.from_centre(np.arctan2(d[1], d[0]), centre)             # T_k_map, x forward
    box = pose.transform_boxes(CABINET[None])[0]
    box[:6] *= scale
    obs = FrameObservations(0, 'cam', INTRINSICS, np.array([0.0, 1.0, 0.0]), boxes=box[None],
                            scores=np.array([0.9], np.float32), labels=['cabinet'],
                            embeddings=np.ones((1, 4), np.float32) / 2)
    return pose, obs


def test_bundle_adjustment_removes_along_ray_range_errors():
    views = [_view((0.0, 0.0, 1.2), 1.15), _view((0.5, 2.8, 1.4), 0.88), _view((3.8, 0.2, 1.0), 1.12)]
    keyframes = {k: obs for k, (_, obs) in enumerate(views)}
    poses = {k: pose for k, (pose, _) in enumerate(views)}
    matches = [(0, 0, 1, 0), (1, 0, 2, 0), (0, 0, 2, 0)]
    [track] = build_tracks(keyframes, poses, matches, TrackConfig())
    [refined] = refine_tracks([track], keyframes, poses, BundleConfig(max_seconds=60.0))
    before = np.linalg.norm(track.box[:3] - CABINET[:3])
    after = np.linalg.norm(refined.box[:3] - CABINET[:3])
    assert before > 0.15, before                      # the lifted boxes disagree along their rays
    assert after < 0.3 * before and after < 0.05, (before, after)
    iou_before, iou_after = (iou_3d_paired(b[None], CABINET[None])[0] for b in (track.box, refined.box))
    assert iou_after > max(0.8, iou_before), (iou_before, iou_after)
    # one view constrains nothing along its ray: a track seen once is left as it is
    [single] = build_tracks({0: keyframes[0]}, {0: poses[0]}, [], TrackConfig())
    assert np.array_equal(refine_tracks([single], keyframes, poses)[0].box, single.box)
