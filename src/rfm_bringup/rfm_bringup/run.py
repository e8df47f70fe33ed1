"""`rfm run`: the detector -> matcher -> mapper graph on a bag or a live camera.

As three node processes talking over DDS (the default) or, with ``--no-processes``, in one
process (each node on its own executor thread). With ``--bag`` the bag is replayed by ``rfm
play`` (with ``/clock``; the nodes use sim time); when it ends, the graph is given time to settle, the
map is saved, and the output folder is written: ``map.rfm``, ``trajectory.tum``,
``keyframes.tum``, ``objects.json``, ``outputs.mcap/`` (the output topics, for Foxglove),
``report.md``, ``summary.json`` (the report's numbers) and ``top_down.png`` (with the ground
truth overlaid when the bag has it). With ``--live`` it
runs until Ctrl-C, then writes the same folder.
"""
from __future__ import annotations

import datetime
import difflib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from rfm_core.detection.frontend import DROP_COUNTERS
from rfm_core.io.ros1 import is_ros1_bag, ros1_to_rosbag2, ros1_topics
from rfm_core.io.topics import CAMERA_TOPICS, GROUND_TRUTH_TOPICS
from rfm_core.processes import die_with_parent

__all__ = ['run_graph', 'BAG_REMAPS', 'OUTPUT_TOPICS']

# The detector's inputs on a RealSense-style driver (and on rfm's sim bags).
BAG_REMAPS = {'rgb/image': CAMERA_TOPICS['color'], 'rgb/camera_info': CAMERA_TOPICS['color_info'],
              'depth/image': CAMERA_TOPICS['depth'], 'imu': CAMERA_TOPICS['imu'],
              'ground_truth/detections': GROUND_TRUTH_TOPICS['gt_detections']}
# What outputs.mcap records (with --live --record-images also the colour images, which a bag already has).
# A live run keeps the first LIVE_DETECTIONS_MB of rfm/detections (each carries the frame's depth
# points, 12-30 kB: half a megabyte a second at 30 Hz); the rest of the outputs are small.
LIVE_DETECTIONS_MB = 1000
#: rfm run --paced: the bag's speed at most (faster, the IMU between photos comes in bursts the transport drops)
PACED_RATE = 8.0
OUTPUT_TOPICS = ['/rfm/detections', '/rfm/keyframes', '/rfm/view_graph/edges', '/rfm/tracked_frames',
                 '/rfm/keyframe_poses', '/rfm/trajectory', '/rfm/camera_pose', '/rfm/object_map',
                 '/rfm/object_markers', '/rfm/status', '/rfm/detection_markers', '/tf', '/tf_static']


def _params(args, output: Path) -> dict:
    """Parameters of each node from the command line (name: {param: value}), each checked
    against the node's configuration (rfm_core.config) and converted to its type."""
    from rfm_core.config import NODES, node_settings  # noqa: PLC0415

    sim_time = bool(args.bag)
    detector = {'backend': args.backend, 'use_sim_time': sim_time}
    if args.backend == 'ground_truth':
        detector['ground_truth.preset'] = args.preset
    if args.cutr_checkpoint:
        detector['cutr.checkpoint'] = args.cutr_checkpoint
    matcher = {'matcher': args.matcher, 'use_sim_time': sim_time}
    mapper = {'map_path': str(output / 'map.rfm'), 'use_sim_time': sim_time, 'matcher': args.matcher}
    if args.posed:
        mapper['pose_source'] = 'topic'
    if args.backend == 'ground_truth' and _ground_truth_monocular(args.preset):
        from rfm_core.matching.config import MONOCULAR_RANGE_ERROR  # noqa: PLC0415

        for node in (matcher, mapper):      # distances misjudged along the viewing rays
            node['matching.range_error'], node['matching.range_error_per_m'] = MONOCULAR_RANGE_ERROR
    nodes = {'detector': detector, 'matcher': matcher, 'mapper': mapper}
    declared = {node: {s.name: s for s in node_settings(node)} for node in NODES}
    for item in args.param or []:
        name, sep, value = item.partition(':=')
        node, _, param = name.partition('.')
        targets = [node] if node in nodes and param else [n for n in NODES if name in declared[n]]
        param = param if node in nodes and param else name
        if not sep or not targets or any(param not in declared[n] for n in targets):
            known = sorted({f'{n}.{p}' for n in NODES for p in declared[n]} | {p for n in NODES for p in declared[n]})
            close = difflib.get_close_matches(name, known, n=3, cutoff=0.6)
            raise SystemExit(f'rfm run: --param {item!r}: expected NODE.NAME:=VALUE or NAME:=VALUE (every node '
                             'with that parameter), NAME a parameter of that node (rfm params lists them)'
                             + (f'; did you mean {", ".join(close)}?' if close else ''))
        for n in targets:
            try:
                setting = declared[n][param]
                nodes[n][param] = setting.check(value if setting.kind == 'str' else _parse_value(value))
            except ValueError as exc:
                raise SystemExit(f'rfm run: --param {item!r}: {n}.{exc}') from None
    # the run's map is saved into the output folder (by rfm/save_map with --processes), also when
    # map_path names a map loaded from elsewhere (localization mode)
    mapper.setdefault('map_dir', str(output.resolve()))
    return nodes


def _ground_truth_monocular(preset: str) -> bool:
    from rfm_core.detection import make_detector  # noqa: PLC0415

    try:
        return make_detector('ground_truth', preset=preset).monocular
    except ValueError as exc:
        raise SystemExit(f'rfm run: --preset: {exc}') from None


def _parse_value(text: str):
    """A command-line value: a number, true/false, a [list] of numbers, or a string."""
    text = text.strip()
    if text.startswith('[') and text.endswith(']'):
        try:
            return [float(v) for v in text[1:-1].split(',') if v.strip()]
        except ValueError:
            return text
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    if text.lower() in ('true', 'false'):
        return text.lower() == 'true'
    return text


#: TUM RGB-D's topics (its ROS 1 bags), taken when a bag has them and not rfm's defaults
TUM_REMAPS = {'rgb/image': '/camera/rgb/image_color', 'rgb/camera_info': '/camera/rgb/camera_info',
              'depth/image': '/camera/depth/image', 'imu': '/imu'}


def _remaps(args) -> dict:
    remaps = dict(BAG_REMAPS)
    for item in args.remap or []:
        if ':=' not in item:
            raise SystemExit(f'rfm run: --remap {item!r}: expected FROM:=TO')
        a, b = item.split(':=', 1)
        remaps[a] = b
    return remaps


def _from_ros1(source: Path, bag: Path, args, remaps: dict) -> Path:
    """A ROS 1 bag converted to the rosbag2 ``bag`` (in the output folder) to replay; TUM
    RGB-D's topics taken where the bag has them and the user remapped nothing."""
    truth = None
    if args.ground_truth_tf:
        world, _, camera = args.ground_truth_tf.partition(':')
        if not world or not camera:
            raise SystemExit(f'rfm run: --ground-truth-tf {args.ground_truth_tf!r}: expected WORLD:CAMERA_FRAME')
        truth = (world, camera)
    print(f'rfm run: {source} is a ROS 1 bag; converting it to rosbag2 in {bag}', flush=True)
    try:
        topics = ros1_topics(source)
        if not args.remap and remaps['rgb/image'] not in topics and TUM_REMAPS['rgb/image'] in topics:
            remaps.update(TUM_REMAPS)
            print("rfm run: TUM RGB-D's topics (" + ', '.join(TUM_REMAPS.values()) + ')', flush=True)
        made = ros1_to_rosbag2(source, bag, truth, colour=remaps['rgb/image'], imu=remaps['imu'])
    except ValueError as exc:
        raise SystemExit(f'rfm run: {exc}') from None
    if made['left_out']:
        print('rfm run: left out (no ROS 2 type): ' + ', '.join(f'{t} ({m})' for t, m in made['left_out'].items()),
              flush=True)
    if truth:
        print(f"rfm run: ground truth {truth[0]} -> {truth[1]} at {made['ground_truth']} colour images, "
              f"levelled by {made['levelled_deg']:.1f} deg", flush=True)
    return bag


def _check_bag(bag: Path, params: dict, remaps: dict) -> None:
    """Check that the bag has what the detector needs (its topics after the remaps) and adapt
    to what it has: a colour topic published only compressed (``<topic>/compressed``)
    switches the detector to ``image_transport:=compressed``. SystemExit saying what to do
    when something is missing."""
    from rosbags.highlevel import AnyReader  # noqa: PLC0415

    with AnyReader([bag]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}

    def listing(*kinds):
        found = sorted(t for t, m in types.items() if m.split('/')[-1] in kinds)
        return ', '.join(found) or 'none'

    detector = params['detector']
    backend = detector['backend']
    if backend == 'ground_truth':
        if remaps['ground_truth/detections'] not in types:
            raise SystemExit(f'rfm run: backend ground_truth needs {remaps["ground_truth/detections"]} '
                             '(a bag made by rfm sim); this bag has none: use --backend depth_clusters')
        return
    colour = remaps['rgb/image']
    if types.get(colour) == 'sensor_msgs/msg/CompressedImage' or (
            colour not in types and types.get(colour + '/compressed') == 'sensor_msgs/msg/CompressedImage'):
        compressed = colour if colour in types else colour + '/compressed'
        detector.setdefault('image_transport', 'compressed')
        remaps['rgb/image/compressed'] = compressed
    elif colour not in types:
        raise SystemExit(f'rfm run: the bag has no colour image topic {colour} (its image topics: '
                         f'{listing("Image", "CompressedImage")}); pass --remap rgb/image:=TOPIC')
    if remaps['rgb/camera_info'] not in types:
        raise SystemExit(f'rfm run: the bag has no {remaps["rgb/camera_info"]} (its camera_info topics: '
                         f'{listing("CameraInfo")}); pass --remap rgb/camera_info:=TOPIC')
    if backend == 'depth_clusters':
        depth = remaps['depth/image']
        if types.get(depth) == 'sensor_msgs/msg/CompressedImage' or (
                depth not in types and depth + '/compressedDepth' in types):
            raise SystemExit(f'rfm run: {depth} is compressed; depth_clusters needs raw depth (16UC1 mm or '
                             '32FC1 m) registered to colour: record it uncompressed')
        if depth not in types:
            raise SystemExit(f'rfm run: depth_clusters needs depth registered to colour; the bag has no {depth} '
                             f'(its image topics: {listing("Image", "CompressedImage")}); pass '
                             '--remap depth/image:=TOPIC')
    if detector.get('gravity_source', 'imu') == 'imu' and remaps['imu'] not in types:
        raise SystemExit(f'rfm run: the bag has no IMU topic {remaps["imu"]} (its IMU topics: {listing("Imu")}); '
                         'pass --remap imu:=TOPIC, or give gravity yourself: --param '
                         'detector.gravity_source:=parameter detector.gravity:=[gx,gy,gz] ("down" in the camera '
                         'optical frame)')


def _tf_subscribers(params: dict) -> int:
    """How many subscriptions /tf and /tf_static have in the graph: the recorder's, the
    mapper's (where it broadcasts the map or reads posed poses from /tf) and the detector's
    (where it reads a robot's odometry). The player waits for them all: a /tf message sent
    before a node discovered the player is lost to it (a robot's first seconds without
    odometry), a latched /tf_static comes late."""
    from rfm_core.config import DetectorNodeConfig, MapperNodeConfig  # noqa: PLC0415

    mapper, detector = params['mapper'], params['detector']
    reads = (mapper.get('publish_tf', MapperNodeConfig.publish_tf)
             or mapper.get('pose_source', MapperNodeConfig.pose_source) == 'tf')
    return 1 + bool(reads) + bool(detector.get('odom_frame', DetectorNodeConfig.odom_frame))


def _detector_inputs(backend: str, remaps: dict) -> list:
    """The bag topics the detector subscribes to (the player waits for their subscribers)."""
    colour = 'rgb/image/compressed' if 'rgb/image/compressed' in remaps else 'rgb/image'
    names = {'ground_truth': ['ground_truth/detections'], 'cutr': [colour, 'rgb/camera_info']}
    return [remaps[n] for n in names.get(backend, [colour, 'rgb/camera_info', 'depth/image', 'imu'])]


class _InProcessGraph:
    """The three nodes in this process, each spun by its own single-threaded executor in its
    own thread (rclpy's multi-threaded executor keeps the GIL so busy that the detector's
    worker thread starves)."""

    def __init__(self, params: dict, remaps: dict):
        from rclpy.parameter import Parameter  # noqa: PLC0415
        from rfm_detector_node.detector_node import DetectorNode  # noqa: PLC0415
        from rfm_mapper_node.mapper_node import MapperNode  # noqa: PLC0415
        from rfm_matcher_node.matcher_node import MatcherNode  # noqa: PLC0415

        def overrides(p):
            return [Parameter(k, value=v) for k, v in p.items()]

        rules = [f'{a}:={b}' for a, b in remaps.items()]
        self.detector = DetectorNode(parameter_overrides=overrides(params['detector']),
                                     cli_args=['--ros-args'] + [x for r in rules for x in ('-r', r)])
        self.matcher = MatcherNode(parameter_overrides=overrides(params['matcher']))
        self.mapper = MapperNode(parameter_overrides=overrides(params['mapper']))
        self.nodes = [self.detector, self.matcher, self.mapper]
        self.executors, self.threads = [], []

    def add(self, node):
        self.nodes.append(node)

    def start(self):
        from rclpy.executors import SingleThreadedExecutor  # noqa: PLC0415
        for node in self.nodes:
            executor = SingleThreadedExecutor()
            executor.add_node(node)
            thread = threading.Thread(target=executor.spin, daemon=True, name=f'spin_{node.get_name()}')
            thread.start()
            self.executors.append(executor)
            self.threads.append(thread)

    def progress(self) -> dict:
        core = self.mapper.core
        dropped = self.detector.frontend.dropped()
        return {'received': self.detector.counts['received'], 'frames': self.detector.counts['processed'],
                'points_only': self.detector.counts['points_only'],
                'dropped': sum(dropped.values()), 'dropped_by_reason': dropped,
                'detections': self.detector.counts['published'], 'matcher_frames': dict(self.matcher.shedder.counts),
                'keyframes': self.matcher.graph.stats.keyframes,
                'registered': len(core.mapper.poses), 'objects': core.num_objects, 'lost': core.num_lost,
                'relocalization': core.session.relocalize_latency(),
                'busy': core.session.dirty or not self.detector.worker.idle}

    def cpu_seconds(self) -> dict:
        """CPU seconds spent so far by each thread of this process, by thread name (the
        detector's worker, each node's executor, ...; Linux only, else empty). In one process
        the nodes share one interpreter lock: these say which node the frames wait for."""
        seconds = {t.name: _cpu_seconds(f'/proc/self/task/{t.native_id}/stat') for t in threading.enumerate()}
        return {k: v for k, v in seconds.items() if v is not None}

    def peak_memory_mb(self) -> dict:
        """Peak resident memory of this process, which runs all three nodes (Linux only)."""
        mb = _peak_memory_mb('/proc/self/status')
        return {'graph': mb} if mb is not None else {}

    def save(self, path) -> bool:
        """Save the map once the nodes have stopped spinning: no callback changes the map
        while it is written (with --live input still arrives)."""
        self._halt()
        return self.mapper.core.save(str(Path(path).resolve()))['success']

    def _halt(self):
        for executor in self.executors:
            executor.shutdown()
        for thread in self.threads:
            thread.join(timeout=10)
        self.executors, self.threads = [], []

    def stop(self):
        self._halt()
        for node in (self.detector, self.matcher, self.mapper):
            node.destroy_node()


def _peak_memory_mb(status_path: str) -> float | None:
    """Peak resident memory (VmHWM, MB) of a process from its /proc status file (None where
    there is none)."""
    try:
        with open(status_path) as f:
            line = next(line for line in f if line.startswith('VmHWM:'))
        return round(int(line.split()[1]) / 1024, 1)
    except (OSError, StopIteration, IndexError, ValueError):
        return None


def _cpu_seconds(stat_path: str) -> float | None:
    """User + system CPU seconds of a process or thread from its /proc stat file (None where
    there is none)."""
    try:
        with open(stat_path) as f:
            fields = f.read().rsplit(')', 1)[1].split()
        return round((int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK'), 2)
    except (OSError, IndexError, ValueError):
        return None


class _ProcessGraph:
    """The three nodes as separate processes talking over DDS (the default: each node has its
    own interpreter, so none waits for another's lock). What they count comes from the
    detector's and the matcher's /diagnostics and the mapper's rfm/status."""

    def __init__(self, params: dict, remaps: dict, log_dir: Path, detections):
        """``detections``: a callable giving the number of rfm/detections messages seen so far
        (the detector runs elsewhere; the recorder counts them)."""
        from diagnostic_msgs.msg import DiagnosticArray  # noqa: PLC0415
        from rclpy.node import Node  # noqa: PLC0415
        from rfm_msgs.msg import MapperStatus  # noqa: PLC0415
        from rfm_msgs.srv import SaveMap  # noqa: PLC0415

        self.procs = []
        self.logs = []
        try:
            self._start_nodes(params, remaps, log_dir)
        except BaseException:                      # none left running when a later one cannot start
            self._stop_nodes()
            raise
        self.node = Node('rfm_run')
        self.status = None
        self.detections = detections
        self.diagnostics = {}                      # status name -> {key: value} (the latest)
        self.node.create_subscription(MapperStatus, 'rfm/status', self._on_status, 10)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)
        # made now, so that discovery has matched the service's both ways long before the map is
        # saved (a request sent by a client made a moment earlier can lose its response)
        self.save_client = self.node.create_client(SaveMap, 'rfm/save_map')
        from rclpy.executors import SingleThreadedExecutor  # noqa: PLC0415
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)

    def _start_nodes(self, params: dict, remaps: dict, log_dir: Path) -> None:
        from ament_index_python.packages import get_package_prefix  # noqa: PLC0415

        for package, exe in (('rfm_detector_node', 'detector'), ('rfm_matcher_node', 'matcher'),
                             ('rfm_mapper_node', 'mapper')):
            cmd = [os.path.join(get_package_prefix(package), 'lib', package, exe), '--ros-args']
            for k, v in params[exe].items():
                cmd += ['-p', f'{k}:={json.dumps(v) if isinstance(v, str) else str(v).lower() if isinstance(v, bool) else v}']
            if exe == 'detector':
                for a, b in remaps.items():
                    cmd += ['-r', f'{a}:={b}']
            log = open(log_dir / f'{exe}.log', 'w')
            self.logs.append(log)
            # a session of its own: a terminal's Ctrl-C reaches rfm run alone, which saves the map, then stops
            # them; and they die with rfm run however it dies (SIGKILL too)
            self.procs.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                                               preexec_fn=die_with_parent()))

    def _stop_nodes(self, grace_s: float = 15.0) -> None:
        """SIGINT (each node saves what it must), then SIGKILL to those still running after
        ``grace_s`` (one deadline for all of them)."""
        for p in self.procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        deadline = time.monotonic() + grace_s
        for p in self.procs:
            try:
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for log in self.logs:
            log.close()

    def _on_status(self, msg):
        self.status = msg

    def _on_diagnostics(self, msg):
        for status in msg.status:
            if status.name in ('rfm detector', 'rfm matcher'):
                values = {}
                for kv in status.values:
                    try:
                        values[kv.key] = int(kv.value)
                    except ValueError:
                        pass
                self.diagnostics[status.name] = values

    def add(self, node):
        self.executor.add_node(node)

    def start(self):
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            names = set(self.node.get_node_names())
            if {'detector', 'matcher', 'mapper'} <= names and self.status is not None \
                    and self.save_client.service_is_ready():
                return
            for p in self.procs:
                if p.poll() is not None:
                    raise SystemExit(f'rfm run: a node exited at start-up (see {self.logs[self.procs.index(p)].name})')
            time.sleep(0.2)
        raise SystemExit('rfm run: the nodes did not come up within 60 s')

    def progress(self) -> dict:
        s = self.status
        n = self.detections()
        detector, matcher = self.diagnostics.get('rfm detector'), self.diagnostics.get('rfm matcher')
        counts = {'dropped': 0}
        if detector:          # the detector's counters, as the one-process graph reads them (to the last second)
            dropped = {reason: detector.get(key, 0) for reason, key in DROP_COUNTERS.items()}
            dropped['unsynchronised'] = detector.get('dropped_unsynchronised', 0)
            counts = {'received': detector.get('received'), 'points_only': detector.get('points_only'),
                      'dropped': sum(dropped.values()), 'dropped_by_reason': dropped}
        if matcher:
            counts['matcher_frames'] = {k: matcher.get(k, 0) for k in ('received', 'processed', 'shed', 'lost')}
        return {'frames': max(n, detector.get('processed', 0) if detector else 0), 'detections': n,
                **counts, 'keyframes': s.num_keyframes if s else 0, 'registered': s.num_registered if s else 0,
                'objects': s.num_objects if s else 0, 'lost': s.num_lost if s else 0, 'busy': False,
                'relocalization': {'queries': s.num_relocalize_queries, 'relocalized': s.num_relocalized,
                                   'median_ms': 1e3 * s.relocalize_seconds_median,
                                   'p95_ms': 1e3 * s.relocalize_seconds_p95} if s else {}}

    def cpu_seconds(self) -> dict:
        """CPU seconds spent so far by each node's process (Linux only, else empty)."""
        seconds = {name: _cpu_seconds(f'/proc/{p.pid}/stat') for name, p in zip(('detector', 'matcher', 'mapper'),
                                                                                 self.procs)}
        return {k: v for k, v in seconds.items() if v is not None}

    def peak_memory_mb(self) -> dict:
        """Peak resident memory of each node's process so far (Linux only, else empty)."""
        mb = {name: _peak_memory_mb(f'/proc/{p.pid}/status') for name, p in zip(('detector', 'matcher', 'mapper'),
                                                                                self.procs)}
        return {k: v for k, v in mb.items() if v is not None}

    def save(self, path, timeout_s: float = 60.0, resend_s: float = 20.0) -> bool:
        """The mapper saves its map to ``path``. Saving is idempotent (the file is replaced
        atomically), so a request unanswered after ``resend_s`` is sent again (DDS can lose a
        response); the first success counts."""
        from rfm_msgs.srv import SaveMap  # noqa: PLC0415
        if not self.save_client.wait_for_service(timeout_sec=20):
            return False
        # absolute: the mapper takes a relative path inside its map_dir
        request = SaveMap.Request(path=str(Path(path).resolve()))
        start = time.monotonic()
        futures, sent = [], -resend_s
        while time.monotonic() - start < timeout_s:
            if any(f.done() and f.result() is not None and f.result().success for f in futures):
                return True
            if futures and all(f.done() for f in futures):
                return False                           # answered, and not saved
            if time.monotonic() - sent >= resend_s:
                futures.append(self.save_client.call_async(request))
                sent = time.monotonic()
            time.sleep(0.05)
        return False

    def stop(self):
        self._stop_nodes()
        self.executor.shutdown()
        self.thread.join(timeout=10)
        self.node.destroy_node()


def _bag_extent(bag, remaps: dict) -> tuple:
    """(duration in s, colour frames) of a bag."""
    from rosbags.highlevel import AnyReader  # noqa: PLC0415
    with AnyReader([Path(bag)]) as reader:
        colour = remaps.get('rgb/image')
        frames = sum(c.msgcount for c in reader.connections if c.topic == colour)
        return (reader.end_time - reader.start_time) / 1e9, frames


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def run_graph(args) -> int:
    import rclpy  # noqa: PLC0415
    from rclpy.signals import SignalHandlerOptions  # noqa: PLC0415

    from rfm_bringup.recorder import BagRecorder  # noqa: PLC0415

    if bool(args.bag) == bool(args.live):
        raise SystemExit('rfm run: give either --bag PATH or --live')
    bag = Path(args.bag).expanduser() if args.bag else None
    ros1 = bag is not None and is_ros1_bag(bag)
    if bag is not None and not ros1 and not (bag / 'metadata.yaml').is_file():
        raise SystemExit(f'rfm run: {bag} is neither a rosbag2 directory (no metadata.yaml) nor a ROS 1 bag')
    if args.ground_truth_tf and not ros1:
        raise SystemExit('rfm run: --ground-truth-tf reads a ROS 1 bag\'s /tf (a rosbag2 bag brings its ground '
                         'truth on /ground_truth/camera_pose: rfm convert writes it)')
    name = bag.stem if ros1 else bag.name if bag else 'live'
    output = Path(args.output or (Path('rfm_output') / name)).expanduser()
    if output.exists() and not args.force:
        raise SystemExit(f'rfm run: {output} exists; pass --force to replace it')
    params = _params(args, output)
    remaps = _remaps(args)
    if bag is not None and not ros1:
        _check_bag(bag, params, remaps)
    if output.exists():
        shutil.rmtree(output)
    output.mkdir(parents=True)
    source = bag
    if ros1:
        bag = _from_ros1(bag, output / 'input', args, remaps)
        _check_bag(bag, params, remaps)
    # Ctrl-C, and kill / docker stop / systemd's SIGTERM, end the loop below; the context stays valid
    # until the map is saved (rclpy's own handlers would shut it down first) and then the nodes are stopped
    signal.signal(signal.SIGTERM, _interrupt)
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    graph = recorder = player = done_at = None
    interrupted = False
    start = time.monotonic()
    play_start = None                              # the first frame detected
    try:
        images = remaps['rgb/image'] if bag is None and args.record_images else None
        caps = {'/rfm/detections': LIVE_DETECTIONS_MB * 1e6} if bag is None else {}
        if images:
            caps[images] = args.record_images * 1e6
        recorder = BagRecorder(str(output / 'outputs.mcap'), topics=OUTPUT_TOPICS + ([images] if images else []),
                               node_name='rfm_run_recorder', compression_level=1,   # beside the graph: cheap
                               batch_period_s=0.1, max_bytes=caps)
        graph = (_ProcessGraph(params, remaps, output, lambda: recorder.received.get('/rfm/detections', 0))
                 if args.processes else _InProcessGraph(params, remaps))
        graph.add(recorder)
        graph.start()
        if bag is not None:
            rfm = shutil.which('rfm') or sys.argv[0]
            # /clock only stamps status and diagnostics here (the nodes' timers that pace work run on
            # a steady clock): 10 Hz instead of 40 spares each node 30 wake-ups a second
            rate = args.rate if args.rate is not None else (PACED_RATE if args.paced else 1.0)
            tf_subscribers, inputs = _tf_subscribers(params), _detector_inputs(args.backend, remaps)
            cmd = [rfm, 'play', str(bag), '--delay', '0.5', '--quiet', '--rate', str(rate), '--clock-hz', '10',
                   '--wait-for', *inputs,
                   *(f'{topic}={tf_subscribers}' for topic in ('/tf', '/tf_static'))]
            if args.paced:                      # each colour image once the detector answered the one before
                cmd += ['--pace', inputs[0], '/rfm/detections']
            if args.posed:
                cmd += ['--remap', '/ground_truth/camera_pose:=/rfm/external_pose']
            player = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                      preexec_fn=die_with_parent())
        last_line = 0.0
        settle_since, last_state = None, None
        while True:
            time.sleep(0.2)
            now = time.monotonic()
            state = graph.progress()
            if now - last_line >= 1.0 and not args.quiet:
                last_line = now
                elapsed = now - start
                sys.stderr.write(f'\r[rfm run] {elapsed:6.1f} s  frames {state["frames"]:5d}  keyframes '
                                 f'{state["keyframes"]:4d}  registered {state["registered"]:4d}  objects '
                                 f'{state["objects"]:4d}  {state["frames"] / max(elapsed, 1e-9):5.1f} frames/s ')
                sys.stderr.flush()
            if bag is None:
                continue
            # processing time: from the first frame detected to the graph's last change (the
            # player's own start-up and shut-down are not processing)
            if play_start is None and state['frames'] > 0:
                play_start = now
            # (with --processes the matcher's count says it still works through a queue)
            key = (state['frames'], state['keyframes'], state['registered'],
                   (state.get('matcher_frames') or {}).get('received'))
            if key != last_state or state['busy']:
                last_state, settle_since = key, now
            if player is not None and player.poll() is None:
                continue
            if now - settle_since >= args.settle:
                done_at = settle_since
                break
    except KeyboardInterrupt:
        interrupted = True
    finally:
        wall = (done_at or time.monotonic()) - (play_start or start)
        if not args.quiet:
            sys.stderr.write('\n')
        cpu = graph.cpu_seconds() if graph is not None else {}     # while the threads run
        ok = graph.save(output / 'map.rfm') if graph is not None else False
        final = dict(graph.progress(), cpu_s=cpu, peak_memory_mb=graph.peak_memory_mb()) if graph is not None else {}
        if recorder is not None:
            recorder.close()
        if graph is not None:
            graph.stop()
        if recorder is not None:
            recorder.destroy_node()
        rclpy.try_shutdown()
        if player is not None and player.poll() is None:
            player.kill()
    if not ok:
        print(f'rfm run: the map could not be saved to {output / "map.rfm"}', file=sys.stderr)
        return 1
    summary = write_outputs(output, bag, params, final, max(wall, 1e-3), posed=args.posed, remaps=remaps,
                            source=source)
    print(f'\nrfm run: results in {output}/')
    acc = summary.get('accuracy')
    frames_in = f' of {summary["input_frames"]}' if summary.get('input_frames') else ''
    print(f'  {summary["frames"]}{frames_in} frames processed, {summary["localized"]} localized; '
          f'{summary["keyframes"]} keyframes ({summary["registered"]} registered), {summary["objects"]} objects; '
          f'{summary["realtime"]:.2f}x real time')
    if acc:
        loc, m = acc['localization'], acc['mapping']
        print(f'  vs ground truth: ARE {loc["ARE_median"]:.2f} deg, ATE {100 * loc["ATE_median"]:.1f} cm, '
              f'{100 * loc["registered"]:.0f}% of frames localized ({loc.get("gross", 0)} wrong: > 5 deg or > 25 cm)'
              + (f'; through TF {100 * loc["tf"]["registered"]:.0f}% ({loc["tf"]["gross"]} wrong)'
                 if loc.get('tf') else '')
              + (f', AP25 {m["AP25"]:.3f}, AR25 {m["AR25"]:.3f}, {m["objects"]} objects for {m["ground_truth"]}'
                 if m else ''))
    print(f'  report: {output / "report.md"}, picture: {output / "top_down.png"}')
    return 130 if interrupted and bag is not None else 0


def write_outputs(output: Path, bag, params: dict, progress: dict, wall_s: float, posed: bool = False,
                  remaps: dict | None = None, source=None) -> dict:
    """Everything but the recording, from the saved map (which this also validates), with
    the configuration the mapper ran with (stored in the map file). ``source``: the input as
    the user named it (a ROS 1 bag; ``bag`` is then its conversion)."""
    from rfm_core.evaluation.report import (  # noqa: PLC0415
        GroundTruth, evaluate_run, published_camera_poses, read_ground_truth, render_top_down, tf_camera_poses,
        write_keyframes_tum, write_object_json, write_report, write_tum)
    from rfm_core.mapping.map_io import load_map  # noqa: PLC0415
    from rfm_core.mapping.mapper import Mapper, MapperConfig  # noqa: PLC0415

    mapper = Mapper(MapperConfig(posed=posed))
    load_map(mapper, output / 'map.rfm')
    truth = read_ground_truth(bag) if bag is not None else GroundTruth()
    published = published_camera_poses(output) if (output / 'outputs.mcap').exists() else None
    through_tf = (tf_camera_poses(output, bag, truth.camera_poses, params['mapper'].get('map_frame', 'map'))
                  if truth and published is not None else None)
    accuracy = evaluate_run(mapper, truth, posed=posed, published=published, through_tf=through_tf) if truth else None
    write_tum(output / 'trajectory.tum', mapper)
    write_keyframes_tum(output / 'keyframes.tum', mapper)
    write_object_json(output / 'objects.json', mapper)
    bag_s, input_frames = _bag_extent(bag, remaps or BAG_REMAPS) if bag is not None else (wall_s, None)
    title = (f'{bag.name if bag is not None else "live"}: ARE {accuracy["localization"]["ARE_median"]:.1f} deg, '
             f'ATE {100 * accuracy["localization"]["ATE_median"]:.1f} cm, '
             f'{100 * accuracy["localization"]["registered"]:.0f}% of frames localized'
             + (f', AP25 {accuracy["mapping"]["AP25"]:.2f}' if accuracy["mapping"] else '') if accuracy else '')
    render_top_down(output / 'top_down.png', mapper, truth if truth else None,
                    accuracy['alignment'] if accuracy else None, title=title)
    summary = {'input': str(source or bag) if bag else 'live camera',
               'date': datetime.datetime.now().isoformat(timespec='seconds'),
               'backend': params['detector']['backend'], 'matcher': params['matcher']['matcher'], 'posed': posed,
               'input_frames': input_frames, 'received': progress.get('received'), 'frames': progress.get('frames', 0),
               'points_only': progress.get('points_only'),
               'detections': progress.get('detections', 0), 'dropped': progress.get('dropped', 0),
               'dropped_by_reason': progress.get('dropped_by_reason', {}),
               'matcher_frames': progress.get('matcher_frames') or {},
               'lost_between_nodes': progress.get('lost', 0), 'cpu_s_by_thread': progress.get('cpu_s', {}),
               'peak_memory_mb': progress.get('peak_memory_mb', {}),
               'relocalization': progress.get('relocalization') or {},
               'localized': len(mapper.frame_poses()), 'keyframes': len(mapper.keyframes),
               'registered': len(mapper.poses), 'edges': len(mapper.active_edges()),
               'edges_rejected': len(mapper.measurements()) - len(mapper.active_edges()), 'objects': len(mapper.tracks()),
               'wall_s': wall_s, 'bag_s': bag_s, 'realtime': bag_s / max(wall_s, 1e-9), 'accuracy': accuracy}
    write_report(output / 'report.md', summary)
    machine = dict(summary, accuracy={k: v for k, v in accuracy.items() if k != 'alignment'} if accuracy else None)
    (output / 'summary.json').write_text(json.dumps(machine, indent=1, default=float))
    return summary
