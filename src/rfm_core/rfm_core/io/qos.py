"""The graph's QoS, in one place: what each rfm topic promises, for the nodes, ``rfm run`` and
the tests. Each profile is plain data here; :func:`qos` makes the rclpy ``QoSProfile``
(imported lazily, so rfm_core stays importable without ROS).

- ``GRAPH``: rfm/keyframes and rfm/view_graph/edges, reliable and transient local, keeping
  the last ``GRAPH_HISTORY``: a mapper started or restarted after the matcher still gets the
  view graph's recent history.
- ``STREAM``: per-frame results between the nodes (rfm/tracked_frames), reliable with a deep
  queue: a busy mapper falls behind instead of losing frames.
- ``LATCHED``: map-like outputs (rfm/keyframe_poses, rfm/trajectory, rfm/object_map,
  rfm/object_markers), reliable and transient local, so RViz or Foxglove started later get them.
- ``RELIABLE``: other outputs and inputs (depth 10).
- ``SENSOR``: camera and IMU inputs, best effort, so reliable and best-effort publishers
  both connect.
- ``TF``: /tf, as tf2's broadcaster publishes it.
"""
from __future__ import annotations

import importlib
from typing import NamedTuple

__all__ = ['QosSpec', 'GRAPH', 'STREAM', 'LATCHED', 'RELIABLE', 'SENSOR', 'TF', 'GRAPH_HISTORY', 'qos']

#: keyframes and edges the matcher keeps for subscribers that join later
GRAPH_HISTORY = 1000


class QosSpec(NamedTuple):
    depth: int
    reliable: bool = True
    transient_local: bool = False


GRAPH = QosSpec(GRAPH_HISTORY, transient_local=True)
STREAM = QosSpec(1000)
LATCHED = QosSpec(1, transient_local=True)
RELIABLE = QosSpec(10)
SENSOR = QosSpec(5, reliable=False)
TF = QosSpec(100)


def qos(spec: QosSpec, depth: int | None = None):
    """The rclpy QoSProfile of ``spec`` (keep last ``depth``, default the spec's)."""
    q = importlib.import_module('rclpy.qos')
    return q.QoSProfile(
        depth=spec.depth if depth is None else depth, history=q.HistoryPolicy.KEEP_LAST,
        reliability=q.ReliabilityPolicy.RELIABLE if spec.reliable else q.ReliabilityPolicy.BEST_EFFORT,
        durability=q.DurabilityPolicy.TRANSIENT_LOCAL if spec.transient_local else q.DurabilityPolicy.VOLATILE)
