"""`rfm record`: subscribe to topics as raw CDR and write a rosbag2 MCAP bag.

Like ``ros2 bag record``: topics are discovered as they appear (all of them, or the ones
asked for), subscribed with a QoS compatible with their publishers (transient-local when
all publishers are, best-effort when any publisher is), and every message is written with
its receive time on the node's clock (bag time when ``use_sim_time`` is set). The bag is
closed cleanly, metadata.yaml included, on Ctrl-C or when :meth:`close` is called.
"""
from __future__ import annotations

import threading

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from rfm_core.io.messages import ros_message_class
from rfm_detector_node.polling import PolledGroup, take_all

__all__ = ['BagRecorder']


class BagRecorder(Node):

    def __init__(self, path, topics=(), node_name: str = 'rfm_recorder',
                 discovery_period: float = 0.5, compression_level: int = 10, max_bytes: dict | None = None,
                 batch_period_s: float = 0.0):
        """``compression_level``: zstd level of the chunks (10: small files; 1-3: cheap on the
        CPU, for recording beside a running graph). ``max_bytes``: {topic: bytes}, a topic
        stops being recorded (logged once) once its messages add up to that many.
        ``batch_period_s``: > 0 queues the messages and writes them in batches this often (their
        receive time is then the batch's, up to that much late) instead of waking the executor
        for each one: cheap beside a graph in the same process."""
        super().__init__(node_name)
        from rfm_core.io.bag import BagWriter  # noqa: PLC0415

        self.path = path
        self.wanted = set(topics)
        self.counts: dict = {}                 #: messages written per topic
        self.received: dict = {}               #: messages received per topic (capped topics too)
        self.bytes: dict = {}
        self.max_bytes = dict(max_bytes or {})
        self._bag = BagWriter(path, compression_level=compression_level).__enter__()
        self._subscriptions_by_topic = {}
        self._closed = False
        self._lock = threading.Lock()          # writes, batches and close() from any thread
        self._polled = None
        if batch_period_s > 0:
            self._polled = PolledGroup()
            self.create_timer(batch_period_s, self.take_queued)
        self.create_timer(discovery_period, self._discover)
        self._discover()
        what = ', '.join(sorted(self.wanted)) if self.wanted else 'all topics'
        self.get_logger().info(f'recording {what} to {path}')

    def _qos_for(self, topic: str) -> tuple:
        infos = self.get_publishers_info_by_topic(topic)
        latched = bool(infos) and all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                                      for i in infos)
        best_effort = any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos)
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100 if not latched else 10,
                         reliability=(ReliabilityPolicy.BEST_EFFORT if best_effort
                                      else ReliabilityPolicy.RELIABLE),
                         durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                     else DurabilityPolicy.VOLATILE))
        return qos, latched, not best_effort

    def _discover(self) -> None:
        if self._closed:
            return
        for topic, types in self.get_topic_names_and_types():
            if topic in self._subscriptions_by_topic or (self.wanted and topic not in self.wanted):
                continue
            if not self.wanted and topic in ('/rosout', '/parameter_events'):
                continue
            if not self.get_publishers_info_by_topic(topic):
                continue
            try:
                msg_type = ros_message_class(types[0])
            except LookupError as exc:
                self.get_logger().warning(f'not recording {topic}: {exc}')
                self._subscriptions_by_topic[topic] = None
                continue
            qos, latched, reliable = self._qos_for(topic)
            try:
                self._bag.add_topic(topic, types[0], latched=latched, reliable=reliable)
            except Exception as exc:  # noqa: BLE001 - unknown to the typestore
                self.get_logger().warning(f'not recording {topic} ({types[0]}): {exc}')
                self._subscriptions_by_topic[topic] = None
                continue
            self.counts[topic] = 0
            self._subscriptions_by_topic[topic] = self.create_subscription(
                msg_type, topic, lambda raw, topic=topic: self._write(topic, raw), qos, raw=True,
                callback_group=self._polled)
            self.get_logger().info(f'subscribed to {topic} [{types[0]}]')

    def take_queued(self) -> None:
        """Write the messages queued on every topic (``batch_period_s`` > 0)."""
        if self._polled is None or self._closed:
            return
        with self._lock:
            for topic, sub in list(self._subscriptions_by_topic.items()):
                if sub is not None and not self._closed:
                    take_all(sub, lambda raw, topic=topic: self._write_locked(topic, raw))

    def _write(self, topic: str, raw: bytes) -> None:
        with self._lock:
            self._write_locked(topic, raw)

    def _write_locked(self, topic: str, raw: bytes) -> None:
        if self._closed:
            return
        self.received[topic] = self.received.get(topic, 0) + 1
        size = self.bytes.get(topic, 0) + len(raw)
        cap = self.max_bytes.get(topic)
        if cap is not None and size > cap:
            if self.bytes.get(topic, 0) <= cap:
                self.get_logger().warning(f'{topic}: {cap / 1e6:.0f} MB recorded, the cap; no more of it is recorded')
                self.bytes[topic] = cap + 1
            return
        self.bytes[topic] = size
        self._bag.write_raw(topic, self.get_clock().now().nanoseconds, raw)
        self.counts[topic] += 1

    def close(self) -> dict:
        """Finish the bag (idempotent); returns messages written per topic."""
        self.take_queued()
        with self._lock:
            if self._closed:
                return dict(self.counts)
            self._closed = True
            self._bag.__exit__(None, None, None)
            self.get_logger().info(f'wrote {sum(self.counts.values())} messages to {self.path}')
        return dict(self.counts)
