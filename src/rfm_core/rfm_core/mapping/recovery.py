"""Tracking recovery (not in the paper): a keyframe outside the registered map (tracking
lost, a view that matched no keyframe) is matched against the map's objects, so that a lost
track goes on in the map instead of starting a component that nothing joins.

Each such keyframe with enough detections is matched (:func:`~rfm_core.mapping.
relocalization.match_to_map`: every box correspondence with the map's objects proposes a pose
under the gyroscope's yaw through the nearest registered keyframe of its integration epoch)
once a keyframe or frame newer than it has arrived, and again whenever the registered map
has doubled since; a match it accepts (:meth:`~rfm_core.mapping.relocalization.MapMatch.
accepted`) gives the edge that joins it. Not before something newer: the keyframe's own
edges come just after it on another topic, and matching it first made the map depend on the
messages' timing. A keyframe the gyroscope does not link to the map (another integration
epoch: separate photos, no IMU) is not tried: box pairs alone propose wrong yaws.
"""
from __future__ import annotations

from typing import Callable

from rfm_core.mapping.relocalization import MapIndex, RelocalizationConfig, match_to_map
from rfm_core.matching.config import MatchingConfig
from rfm_core.matching.view_graph import Edge
from rfm_core.observations import EdgeRecord, FrameObservations

__all__ = ['TrackingRecovery']


class TrackingRecovery:
    """Which keyframes recovery has tried, and the edges it finds (see the module)."""

    def __init__(self):
        self.tried: dict = {}                # keyframe id -> registered keyframes when it was last matched

    @staticmethod
    def recoverable(obs: FrameObservations, config: RelocalizationConfig) -> bool:
        """Whether a keyframe has enough detections to be matched to the map."""
        return len(obs) >= max(config.min_explained, 2)

    def awaits(self, keyframe_id: int, obs: FrameObservations, config: RelocalizationConfig) -> bool:
        """Whether an unregistered keyframe has yet to be tried."""
        return self.recoverable(obs, config) and keyframe_id not in self.tried

    def edges(self, keyframes: dict, poses: dict, newest_stamp_ns: int, index: Callable[[], MapIndex],
              gyro_yaw: Callable[[int, dict], float | None], config: RelocalizationConfig,
              matching: MatchingConfig) -> list:
        """The edges that join keyframes outside the registered map to it (see the module):
        ``keyframes`` {id: FrameObservations}, ``poses`` the registered ones' {id: Pose4},
        ``index()`` the map indexed for relocalization, ``gyro_yaw(id, poses)`` the yaw of a
        keyframe's T_map_k as the gyroscope gives it (None without)."""
        due = []
        for k, obs in keyframes.items():
            if (k in poses or not self.recoverable(obs, config) or obs.stamp_ns >= newest_stamp_ns
                    or len(poses) < 2 * self.tried.get(k, len(poses) / 2)):
                continue
            self.tried[k] = len(poses)
            gyro = gyro_yaw(k, poses)
            if gyro is not None:
                due.append((k, gyro))
        found = []
        mapped = index() if due else None
        for k, gyro in due:
            match = match_to_map(keyframes[k], mapped, matching, config, gyro)
            if match is not None and match.accepted(config):
                found.append(EdgeRecord.from_edge(Edge(match.keyframe_id, k, match.relative)))
        return found
