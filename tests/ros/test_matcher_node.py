"""The matcher node with real rclpy: detections in, keyframes and verified edges out."""
import threading
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402

from rfm_core.detection import make_detector  # noqa: E402
from rfm_core.geometry import Pose4  # noqa: E402
from rfm_core.io.messages import frame_detections_to_msg  # noqa: E402
from rfm_core.sim.capture import Capture, CaptureConfig  # noqa: E402

pytestmark = pytest.mark.ros



@pytest.mark.slow
def test_keyframes_and_edges_agree_with_ground_truth():
    from rfm_matcher_node.matcher_node import MatcherNode
    from rfm_msgs.msg import FrameDetections, Keyframe, TrackedFrame, ViewGraphEdge

    frames = list(Capture(CaptureConfig(seed=33, frames=24, fps=3)).frames())
    det = make_detector('ground_truth', preset='rgbd', seed=5)
    rclpy.init()
    matcher = MatcherNode()
    test = Node('matcher_test')
    reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    keyframes, edges, tracked = [], [], []
    test.create_subscription(Keyframe, 'rfm/keyframes', keyframes.append, reliable)
    test.create_subscription(ViewGraphEdge, 'rfm/view_graph/edges', edges.append, reliable)
    test.create_subscription(TrackedFrame, 'rfm/tracked_frames', tracked.append, reliable)
    pub = test.create_publisher(FrameDetections, 'rfm/detections', QoSProfile(depth=50))
    executor = MultiThreadedExecutor()
    executor.add_node(matcher)
    executor.add_node(test)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 20
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        bad = frame_detections_to_msg(det.perturb(frames[0].ground_truth))
        bad.fx = 0.0                                      # malformed: dropped, node keeps going
        pub.publish(bad)
        for frame in frames:
            pub.publish(frame_detections_to_msg(det.perturb(frame.ground_truth)))
            time.sleep(0.05)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and matcher.graph.stats.frames < len(frames):
            time.sleep(0.05)
        time.sleep(1.0)
    finally:
        executor.shutdown()
        thread.join(timeout=10)                 # the spin thread is gone before the nodes go
        matcher.destroy_node()
        test.destroy_node()
        rclpy.try_shutdown()
    assert matcher.graph.stats.frames == len(frames)
    # rclpy's message info reached the node: every message counted, none lost, none skipped
    assert matcher.shedder.counts == dict(received=len(frames) + 1, processed=len(frames) + 1, shed=0, lost=0)
    assert 3 <= len(keyframes) < len(frames)
    assert len(edges) >= len(keyframes) - 1
    # numbered per topic within the matcher's session, for the mapper's delivery check
    for stream in (keyframes, edges):
        assert {m.session for m in stream} == {keyframes[0].session} != {0}
        assert [m.sequence for m in stream] == list(range(1, len(stream) + 1))
    by_stamp = {f.stamp_ns: f for f in frames}
    kf_frame = {k.keyframe_id: by_stamp[k.header.stamp.sec * 10**9 + k.header.stamp.nanosec]
                for k in keyframes}
    yaw_err, t_err = [], []
    for e in edges:
        est = Pose4(e.yaw, (e.translation.x, e.translation.y, e.translation.z))
        truth = kf_frame[e.source_id].aligned_from_map() @ kf_frame[e.target_id].aligned_from_map().inverse()
        yaw_err.append(np.degrees(est.angle_to(truth)))
        t_err.append(np.linalg.norm(est.t - truth.t))
        assert len(e.inliers) >= 2 and 0 < e.score <= 1
    assert np.median(yaw_err) < 2.0 and np.median(t_err) < 0.12
    # every tracked frame states how far off its pose may be; the keyframes are exact
    within, frames = 0, 0
    for t in tracked:
        cov = np.asarray(t.covariance).reshape(4, 4)
        if t.is_keyframe:
            assert not np.any(cov)
            continue
        assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
        est = Pose4(t.yaw, (t.translation.x, t.translation.y, t.translation.z))
        truth = (kf_frame[t.keyframe_id].aligned_from_map()
                 @ by_stamp[t.header.stamp.sec * 10**9 + t.header.stamp.nanosec].aligned_from_map().inverse())
        err = np.r_[est.t - truth.t, est.angle_to(truth)]
        within += err @ np.linalg.solve(cov, err) <= 9.49        # chi-square, 4 dof, 95%
        frames += 1
    assert frames >= 5
    assert within >= 0.8 * frames, f'{within} of {frames} tracked frames within their 2-sigma bound'
