"""`rfm play`: publish a rosbag2 bag's raw CDR messages at their recorded timing.

Like ``ros2 bag play`` (which the PyPI wheels lack): messages are published as the bytes
stored in the bag, with the QoS they were recorded with (latched topics stay
transient-local), optionally faster or slower, from an offset, looped, filtered and
remapped, while ``/clock`` carries the bag time so nodes can run with ``use_sim_time``.

Paced (``pace_topic`` and ``answer_topic``): a message of ``pace_topic`` (a camera's colour
images) is published only once the one before it is answered on ``answer_topic`` (a
``header`` with its stamp or a later one: the detector's ``rfm/detections``), or
``pace_timeout`` has passed; the bag's timeline waits with it. A photo collection then goes
through as fast as the graph takes it (``rate`` the upper bound), none lost to a busy detector.
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from rfm_core.io.messages import ros_message_class

__all__ = ['PlayOptions', 'BagPlayer', 'recorded_qos']


def recorded_qos(connection) -> QoSProfile:
    """The QoS to publish a bag connection with: as offered when it was recorded."""
    profiles = list(getattr(connection.ext, 'offered_qos_profiles', []) or [])
    latched = any(getattr(q.durability, 'name', '') == 'TRANSIENT_LOCAL' for q in profiles)
    best_effort = profiles and all(getattr(q.reliability, 'name', '') == 'BEST_EFFORT'
                                   for q in profiles)
    if latched:
        return QoSProfile(history=HistoryPolicy.KEEP_LAST,
                          depth=max(1, min(int(connection.msgcount or 1), 100)),
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                      reliability=(ReliabilityPolicy.BEST_EFFORT if best_effort
                                   else ReliabilityPolicy.RELIABLE),
                      durability=DurabilityPolicy.VOLATILE)


@dataclass
class PlayOptions:
    rate: float = 1.0                 #: playback speed factor
    start_offset: float = 0.0         #: seconds into the bag to start from
    loop: bool = False                #: play again from the start when the bag ends
    topics: list = field(default_factory=list)   #: play only these topics (empty: all)
    remaps: dict = field(default_factory=dict)   #: bag topic -> published topic
    clock: bool = True                #: publish /clock with the bag time
    clock_hz: float = 40.0            #: /clock rate (as ros2 bag play's --clock): every node
                                      #: with use_sim_time wakes up for each /clock message
    delay: float = 0.0                #: seconds to wait (for subscribers) before playing
    wait_for: list = field(default_factory=list)  #: bag topics that need a subscriber first (TOPIC=N: N)
    wait_timeout: float = 30.0        #: ... waited for at most this long (s)
    progress: bool | None = None      #: status line on stderr (default: if a terminal)
    pace_topic: str = ''              #: bag topic whose messages wait for the previous one's answer
    answer_topic: str = ''            #: ... answered here (a message type in rfm_msgs with a header) ...
    answer_type: str = 'rfm_msgs/msg/FrameDetections'
    pace_timeout: float = 3.0         #: ... or after this long (s: a frame the detector refused)

    def __post_init__(self):
        if self.rate <= 0:
            raise ValueError('rate must be > 0')
        if self.start_offset < 0 or self.delay < 0:
            raise ValueError('start offset and delay must be >= 0')
        if bool(self.pace_topic) != bool(self.answer_topic):
            raise ValueError('pacing needs both a topic to pace and a topic that answers it')
        self.subscribers_wanted()                 # refuses a malformed entry

    def subscribers_wanted(self) -> dict:
        """{topic: how many subscribers to wait for} from ``wait_for`` (TOPIC: 1, TOPIC=N: N)."""
        wanted = {}
        for entry in self.wait_for:
            topic, _, count = entry.partition('=')
            if count and not (count.isdigit() and int(count) >= 1):
                raise ValueError(f'--wait-for {entry}: expected TOPIC or TOPIC=N, N a number of subscribers >= 1')
            wanted[topic] = int(count or 1)
        return wanted


class BagPlayer(Node):
    """Plays one bag; call :meth:`play` (blocks until the bag ends, or forever with loop)."""

    def __init__(self, path, options: PlayOptions | None = None, node_name: str = 'rfm_player'):
        super().__init__(node_name)
        from rosbags.highlevel import AnyReader  # noqa: PLC0415

        self.options = options or PlayOptions()
        self.path = path = Path(path)
        self._reader_type = AnyReader
        self.published: dict = {}
        with AnyReader([path]) as reader:
            connections = [c for c in reader.connections
                           if not self.options.topics or c.topic in self.options.topics]
            missing = set(self.options.topics) - {c.topic for c in reader.connections}
            if missing:
                self.get_logger().warning(f'topics not in the bag: {sorted(missing)}')
            self.start_ns, self.end_ns = reader.start_time, reader.end_time
        self._bag_publishers = {}
        for c in connections:
            if c.topic in self._bag_publishers:
                continue
            topic = self.options.remaps.get(c.topic, c.topic)
            try:
                msg_type = ros_message_class(c.msgtype)
            except LookupError as exc:
                self.get_logger().error(f'skipping {c.topic}: {exc}')
                continue
            self._bag_publishers[c.topic] = self.create_publisher(msg_type, topic, recorded_qos(c))
            self.published[topic] = 0
        self._topics = set(self._bag_publishers)
        self._clock_pub = None
        if self.options.clock:
            from rosgraph_msgs.msg import Clock  # noqa: PLC0415
            self._clock_type = Clock
            self._clock_pub = self.create_publisher(
                Clock, '/clock', QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
        self._answered = -1                     # the newest stamp answered on answer_topic (ns)
        if self.options.answer_topic:
            self.create_subscription(ros_message_class(self.options.answer_type), self.options.answer_topic,
                                     self._on_answer, QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
        self.get_logger().info(
            f'playing {path}: {len(self._topics)} topics, '
            f'{(self.end_ns - self.start_ns) / 1e9:.1f} s at {self.options.rate}x'
            + (f', each {self.options.pace_topic} message after the last one\'s answer on '
               f'{self.options.answer_topic}' if self.options.pace_topic else ''))

    def _on_answer(self, msg) -> None:
        stamp = msg.header.stamp
        self._answered = max(self._answered, stamp.sec * 1_000_000_000 + stamp.nanosec)

    def _await_answer(self, stamp_ns: int) -> float:
        """Until the message stamped ``stamp_ns`` is answered, at most ``pace_timeout``; the
        seconds waited."""
        import rclpy  # noqa: PLC0415
        start = time.monotonic()
        while self._answered < stamp_ns and time.monotonic() - start < self.options.pace_timeout:
            rclpy.spin_once(self, timeout_sec=0.005)
        return time.monotonic() - start

    def _publish_clock(self, bag_ns: int) -> None:
        if self._clock_pub is not None:
            msg = self._clock_type()
            msg.clock.sec, msg.clock.nanosec = divmod(int(bag_ns), 1_000_000_000)
            self._clock_pub.publish(msg)

    def _wait_for_subscribers(self) -> None:
        """Until every ``wait_for`` topic in the bag has a subscriber, or ``TOPIC=N`` N of
        them (discovery takes a moment; a message published before it completes is lost),
        at most ``wait_timeout``."""
        wanted = self.options.subscribers_wanted()
        topics = [t for t in wanted if t in self._bag_publishers]
        deadline = time.monotonic() + self.options.wait_timeout
        while topics and time.monotonic() < deadline:
            topics = [t for t in topics if self._bag_publishers[t].get_subscription_count() < wanted[t]]
            if topics:
                time.sleep(0.05)
        if topics:
            self.get_logger().warning(f'no subscriber on {topics} after {self.options.wait_timeout:.0f} s; playing anyway')

    def play(self) -> dict:
        """Publish the bag; returns the number of messages published per topic."""
        opts = self.options
        show = sys.stderr.isatty() if opts.progress is None else opts.progress
        first = self.start_ns + int(opts.start_offset * 1e9)
        duration = max(self.end_ns - first, 1)
        self._wait_for_subscribers()
        if opts.delay:
            time.sleep(opts.delay)
        while True:
            wall0 = time.monotonic()
            last_clock = 0.0
            last_progress = 0.0
            last_stamp = None
            outstanding = None                  # the paced message waiting for its answer (its stamp)
            with self._reader_type([self.path]) as reader:
                conns = [c for c in reader.connections if c.topic in self._topics]
                if not conns:                  # nothing playable (an empty list reads every topic)
                    self.get_logger().warning(f'{self.path}: no topic to play')
                    break
                for conn, stamp, raw in reader.messages(connections=conns, start=first):
                    paced = conn.topic == opts.pace_topic
                    if paced and outstanding is not None:
                        wall0 += self._await_answer(outstanding)     # the bag's timeline waits too
                    target = wall0 + (stamp - first) / 1e9 / opts.rate
                    while True:
                        now = time.monotonic()
                        if now >= target:
                            break
                        if now - last_clock >= 1.0 / opts.clock_hz:
                            self._publish_clock(first + (now - wall0) * opts.rate * 1e9)
                            last_clock = now
                        time.sleep(min(target - now, 1.0 / opts.clock_hz))
                    now = time.monotonic()
                    if now - last_clock >= 1.0 / opts.clock_hz:
                        self._publish_clock(stamp)
                        last_clock = now
                    last_stamp = stamp
                    self._bag_publishers[conn.topic].publish(bytes(raw))
                    self.published[opts.remaps.get(conn.topic, conn.topic)] += 1
                    if paced:
                        outstanding = _header_stamp(raw, conn.msgtype, reader) or stamp
                    if show and now - last_progress > 0.5:
                        last_progress = now
                        done = (stamp - first) / duration
                        sys.stderr.write(f'\r[rfm play] {(stamp - first) / 1e9:7.2f} / '
                                         f'{duration / 1e9:.2f} s ({100 * done:3.0f}%) '
                                         f'{sum(self.published.values())} msgs')
                        sys.stderr.flush()
            if last_stamp is not None:
                self._publish_clock(last_stamp)          # the clock ends at the last message
            if show:
                sys.stderr.write('\n')
            if not opts.loop:
                break
        self._wait_for_delivery()
        self.get_logger().info(f'done: {sum(self.published.values())} messages')
        return dict(self.published)

    def _wait_for_delivery(self, timeout_s: float = 2.0) -> None:
        """Before the player exits: until reliable subscribers have acknowledged everything
        (a message still being re-sent would be lost with the process), at most ``timeout_s``."""
        from rclpy.duration import Duration  # noqa: PLC0415
        deadline = time.monotonic() + timeout_s
        for publisher in self._bag_publishers.values():
            left = deadline - time.monotonic()
            if left <= 0:
                break
            try:
                publisher.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9)))
            except Exception:  # noqa: BLE001 - best effort (e.g. a best-effort publisher)
                pass


def _header_stamp(raw, msgtype: str, reader) -> int | None:
    """The header stamp (ns) of a bag message (what an answer carries), None without one."""
    try:
        msg = reader.deserialize(raw, msgtype)
        return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
    except (AttributeError, ValueError, TypeError, KeyError):
        return None
