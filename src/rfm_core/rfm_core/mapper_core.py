"""The mapper node without ROS: what ``rfm_mapper_node`` does between decoding a message and
publishing one, as core code with core tests.

:class:`MapperCore` owns the :class:`~rfm_core.session.MapSession` (paper 3.5-3.6 and
appendix) and the node's policy around it:

- delivery checks of the matcher's numbered topics (:class:`~rfm_core.session.SequenceCheck`);
- :meth:`MapperCore.tick`, every 0.1 s: solves what arrived and returns a :class:`Tick`
  (the poses changed, the newest frame's camera pose, keyframes recovered or culled, whether
  the object map is due, the autosave written);
- autosave (:class:`Autosave`: every n keyframes, or once a larger map has grown by a
  fraction, or after a while with frames logged since), and once more when the node stops
  (:meth:`MapperCore.close`);
- the object map rebuilt at most every ``map_publish_period_s`` and at most
  ``map_max_cpu_share`` of the time (:class:`Throttle`);
- the files a service request may name (:class:`MapFiles`: inside ``map_dir``);
- a :class:`MapStatus` snapshot for ``rfm/status``.

Each method takes decoded inputs and returns what to publish; the node translates messages.
"""
from __future__ import annotations

import os
import time
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

from rfm_core.mapping.map_io import MapFileError
from rfm_core.mapping.mapper import MODES
from rfm_core.matching.factory import make_matcher
from rfm_core.observations import FrameObservations, FrameTrack
from rfm_core.session import CameraPose, ExternalPoses, MapSession, SequenceCheck
from rfm_core.transforms import Attachment, TransformBuffer, map_attachment

__all__ = ['MapperCore', 'Tick', 'MapStatus', 'MapFiles', 'Autosave', 'Throttle', 'default_map_path']

MAX_PATH_CHARS = 1024           #: longest path a service request may name


def default_map_path(environ=os.environ) -> str:
    """``$ROS_HOME/rfm/map.rfm`` (``~/.ros/rfm/map.rfm`` without ROS_HOME), as ROS 2 places a
    node's files."""
    return str(Path(environ.get('ROS_HOME', '~/.ros')) / 'rfm' / 'map.rfm')


class MapFiles:
    """The map file (``map_path``; empty: :func:`default_map_path`) and the directory service
    requests may name files in (``map_dir``; empty: the map file's)."""

    def __init__(self, map_path: str = '', map_dir: str = ''):
        self.path = map_path or default_map_path()
        self.dir = Path(map_dir or Path(self.path).expanduser().parent).expanduser().resolve()

    def resolve(self, requested: str) -> str:
        """The file a request names: the map file when empty, else a path inside the directory
        (relative ones are taken there). ValueError saying why for any other."""
        if not requested:
            return self.path
        if len(requested) > MAX_PATH_CHARS or '\x00' in requested:
            raise ValueError(f'the path is longer than {MAX_PATH_CHARS} characters or holds a NUL')
        p = Path(requested).expanduser()
        resolved = (p if p.is_absolute() else self.dir / p).resolve()
        if self.dir not in resolved.parents:
            raise ValueError(f"{requested} is outside map_dir {self.dir} (the mapper's map_dir parameter sets where "
                             'maps may be saved and loaded)')
        return str(resolved)


@dataclass(frozen=True)
class Autosave:
    """Save every ``every_n`` new keyframes (0: never) or, once the map is larger, when it has
    grown by ``growth`` since the last save: a save rewrites the whole map (its frame log is
    appended to), so the total cost of autosaving stays linear in the map's size. A map that
    no longer grows (the room covered) still logs frames: they are saved every ``period_s``
    (0: only with keyframes)."""

    every_n: int
    growth: float
    period_s: float = 0.0

    def due(self, since_save: int, keyframes: int, unsaved_frames: int = 0, waited_s: float = 0.0) -> bool:
        return bool(self.every_n) and (since_save >= max(self.every_n, self.growth * keyframes)
                                       or bool(self.period_s and unsaved_frames and waited_s >= self.period_s))


class Throttle:
    """Rebuilding the object map (tracks, merging) at most every ``period_s`` and at most
    ``cpu_share`` of the time: a map that takes 0.3 s to build is published at most every
    1.5 s at 0.2. :meth:`due` once something changed and the wait is over; :meth:`done` with
    what the rebuild cost."""

    def __init__(self, period_s: float, cpu_share: float, clock: Callable[[], float] = time.monotonic):
        self.period_s, self.cpu_share, self.clock = period_s, cpu_share, clock
        self.pending = False                  # changed since the last rebuild
        self.last = -float('inf')             # clock time of the last rebuild's end
        self.seconds = 0.0                    # its cost

    def due(self) -> bool:
        wait = max(self.period_s, self.seconds / self.cpu_share)
        return self.pending and self.clock() - self.last >= wait

    def done(self, seconds: float) -> None:
        self.pending, self.last, self.seconds = False, self.clock(), seconds


@dataclass
class Tick:
    """What one :meth:`MapperCore.tick` did, and what to publish."""

    keyframe_poses: tuple | None = None       #: the poses changed: :meth:`MapperCore.keyframe_poses`
    camera: CameraPose | None = None          #: the newest frame's new camera pose
    earlier: list = field(default_factory=list)   #: frames held for their keyframe's edges, to publish first
    object_map: tuple | None = None           #: the object map was due: :meth:`MapperCore.object_map`
    saved: str | None = None                  #: the autosave written
    log: list = field(default_factory=list)   #: lines for the node's log (recovery, culling)


@dataclass
class MapStatus:
    """A snapshot for ``rfm/status`` (rfm_msgs/MapperStatus: the same field names)."""

    mode: str
    num_keyframes: int
    num_culled: int
    num_registered: int
    num_edges: int
    num_edges_rejected: int
    num_objects: int
    num_components: int
    num_frame_changes: int
    num_frames: int
    num_lost: int
    last_update_seconds: float
    num_relocalize_queries: int
    num_relocalized: int
    relocalize_seconds_median: float
    relocalize_seconds_p95: float
    num_saves: int
    save_seconds: float
    message: str


class MapperCore:
    """The mapper node's work (see the module), configured by a
    :class:`~rfm_core.config.MapperNodeConfig`; /tf and /tf_static come in through
    :meth:`transform` (posed mode's pose source 'tf', and where the map attaches to the TF
    tree). ``warn``: where dropped input is reported (the node logs it, throttled);
    ``matcher``: relocalization's object matcher (default: the configured one).
    With ``load_map_on_start`` the map file is loaded. ValueError for a matcher checkpoint or
    a map file that cannot be loaded."""

    def __init__(self, config, warn: Callable[[str], None] | None = None,
                 clock: Callable[[], float] = time.monotonic, matcher=None):
        self.config = config
        self.warn = warn or (lambda text: None)
        if matcher is None:
            try:
                matcher = make_matcher(config.matcher, config.mapper.matching, config.matcher_weights or None,
                                       on_fallback=self.warn)
            except FileNotFoundError as exc:
                raise ValueError(str(exc)) from exc
        self.files = MapFiles(config.map_path, config.map_dir)
        self.autosave = Autosave(config.autosave_every_n_keyframes, config.autosave_growth, config.autosave_period_s)
        self.clock = clock
        self.throttle = Throttle(config.map_publish_period_s, config.map_max_cpu_share, clock)
        self.external_poses = ExternalPoses()
        # /tf and /tf_static as heard; no extrapolation at all (as tf2): the map's attachment
        # holds the camera where the mapper put it only with the odometry at the image's stamp
        self.tf = TransformBuffer(tolerance_s=0.0)
        self.held: Attachment | None = None   # map -> odom, re-published between frames
        self.held_stamp_ns = 0                # the image stamp it was computed at
        self._tf_stamps = deque(maxlen=64)    # the stamps the map's attachment went out with lately
        self._attached_to = None              # the frame the map last attached to (logged when it changes)
        self._said_separate = False           # said once: separate views get no TF
        self._bare_since = None               # clock time of the first camera pose whose frame had no /tf
        lookup = {'topic': self.external_poses, 'tf': self._lookup_tf}.get(config.pose_source)
        mapper = replace(config.mapper, posed=bool(config.pose_source))
        self.session = MapSession(mapper, matcher=matcher, pose_lookup=lookup,
                                  idle_full_solve_s=config.idle_full_solve_s, warn=self.warn, clock=clock)
        self.session.mode = config.mode
        self.num_objects = 0                  # objects in the last object map built
        self.num_saves, self.save_seconds = 0, 0.0      # map saves written, the latest one's wall time
        self._saved = (clock(), 0)                      # when the map file was last written, its frames
        self._republish = False               # a map loaded or cleared: publish it all at the next tick
        self._log: list = []                  # lines for the next tick's log
        self._sequences: dict = {}            # delivery checks of the matcher's numbered topics
        if config.load_map_on_start:
            answer = self.load()
            if not answer['success']:
                raise ValueError(f"load_map_on_start: {answer['message']}")
            self._log.append(answer['message'])

    @property
    def mapper(self):
        return self.session.mapper

    @property
    def num_lost(self) -> int:
        """Messages the matcher numbered that never arrived."""
        return sum(c.lost for c in self._sequences.values())

    # ------------------------------------------------------------------ input

    # Inputs: None stands for a message that could not be decoded (the node reported it with
    # :meth:`dropped`); ``session`` and ``sequence`` number the matcher's messages.

    def dropped(self, what: str, why) -> None:
        """A message that could not be used: counted and reported."""
        self.session.counts['dropped'] += 1
        self.warn(f'{what} dropped: {why}')

    def failed(self, what: str, exc: Exception) -> None:
        """An unexpected error in a callback: counted, reported and kept for rfm/status."""
        self.session.message = f'{what}: unexpected error {exc!r}'
        self.dropped(what, f'unexpected error {exc!r}')

    def delivered(self, what: str, session: int, sequence: int) -> None:
        """Check a numbered message of the matcher's for a gap before it."""
        check = self._sequences.setdefault(what, SequenceCheck())
        lost = check.add(int(session), int(sequence))
        if lost:
            self.session.message = (f'{lost} {what} from the matcher never arrived ({check.lost} in all): a full '
                                    'queue or a dropped connection; the map has a gap there')
            self.warn(self.session.message)

    def keyframe(self, keyframe_id: int, obs: FrameObservations | None, session: int = 0, sequence: int = 0,
                 edges: int = 0) -> None:
        """A keyframe; ``edges``: how many edges the matcher publishes with it (solved with them)."""
        self.delivered('keyframes', session, sequence)
        if obs is not None:
            self.session.add_keyframe(keyframe_id, obs, int(session), edges=edges)

    def edge(self, edge, session: int = 0, sequence: int = 0) -> None:
        self.delivered('edges', session, sequence)
        if edge is not None:
            self.session.add_edge(edge, int(session))

    def tracked_frame(self, track: FrameTrack | None, session: int = 0, sequence: int = 0) -> CameraPose | None:
        """Mapping mode: the frame logged; its camera pose once its keyframe has one."""
        self.delivered('tracked frames', session, sequence)
        if track is None or self.session.mode != 'mapping':
            return None
        return self.session.add_frame(track, int(session))

    def external_pose(self, stamp_ns: int, matrix) -> None:
        """Posed mode (pose_source 'topic'): a camera-to-map pose."""
        if matrix is not None:
            self.external_poses.add(stamp_ns, matrix)
            self.session.attach_external_poses()

    def transform(self, parent: str, child: str, stamp_ns: int, matrix, static: bool) -> None:
        """A transform heard on /tf or /tf_static (one that breaks the tree is reported and
        dropped). Links from the map frame are the map's own broadcast: kept only in posed
        mode (``pose_source`` tf, which reads them); otherwise the first frames' broadcast,
        heard before a latched /tf_static, would take the camera frame's place in the tree
        and keep the map attached to it for good."""
        if parent == self.config.map_frame and self.config.pose_source != 'tf':
            return
        problem = self.tf.add(parent, child, stamp_ns, matrix, static)
        if problem is not None:
            self.warn(f'/tf: {problem}')
        elif self.config.pose_source == 'tf' and self.session.pending_keyframes:
            self.session.attach_external_poses()           # posed mode: a keyframe's pose may be there now

    def _lookup_tf(self, obs: FrameObservations):
        """Posed mode (tf): the camera's pose in the map frame at the keyframe's stamp, from
        /tf (None: not there yet)."""
        return self.tf.lookup(self.config.map_frame, obs.frame_id, obs.stamp_ns)

    def attach(self, camera: CameraPose | None) -> Attachment | None:
        """Where the map attaches to the TF tree for this camera pose
        (:func:`rfm_core.transforms.map_attachment`); None: nothing to broadcast (said once
        per change). A moving attachment (map -> odom) is held for re-publishing. A separate
        view (``camera.stream`` false: a photo) gets no broadcast of its own unless a robot's
        odometry carries the camera to it: a tf2 lookup between two broadcasts interpolates,
        and between two photos it would give the camera a pose no measurement supports, at
        every photo the map did not place (docs/design-notes.md)."""
        if camera is None or not self.config.publish_tf or self.config.pose_source:
            return None
        found = map_attachment(self.tf, camera.matrix, camera.frame_id, camera.stamp_ns, self.config.map_frame,
                               self.config.odom_frame)
        if not isinstance(found, str) and found.child == camera.frame_id:      # no /tf for the camera frame: yet?
            if self._bare_since is None:
                self._bare_since = self.clock()
            if self.clock() - self._bare_since < self.config.camera_tf_wait_s:
                if self._attached_to != '':                # '': waiting (said once)
                    self._attached_to = ''
                    self._log.append(f'TF: no /tf for {camera.frame_id} yet; waiting up to '
                                     f'{self.config.camera_tf_wait_s:g} s for its mount before broadcasting the map '
                                     'as its parent')
                return None
        if isinstance(found, str):
            if self._attached_to != found.split(' at ')[0]:
                self._attached_to = found.split(' at ')[0]
                self.warn(f'TF: {found}')
            return None
        if not (found.held or camera.stream):          # a separate view, no odometry between it and the last
            if not self._said_separate:
                self._said_separate = True
                self._log.append(f'TF: {camera.frame_id} comes in separate views (photos: frames further apart '
                                 "than the matcher's motion.max_frame_gap_s, no odometry between them); map -> "
                                 f'{found.child} goes out for frames of a stream only, as tf2 would interpolate the '
                                 'camera between two views it was carried between. rfm/camera_pose has every pose')
            return None
        if found.child != self._attached_to:
            self._attached_to = found.child
            kind = ('REP 105: the odometry frame' if found.child == self.config.odom_frame else
                    'the camera frame, which has no TF' if found.child == camera.frame_id else
                    f"the root of {camera.frame_id}'s tree on /tf")
            self._log.append(f'TF: broadcasting {self.config.map_frame} -> {found.child} ({kind})')
        self.held = found if found.held else None
        self.held_stamp_ns = camera.stamp_ns
        return replace(found, stamp_ns=self._unique_stamp(camera.stamp_ns))

    def held_transform(self, now_ns: int):
        """(the held map -> odom, its stamp) to re-publish between frames, or None: stamped
        ``transform_tolerance_s`` ahead of the clock or of the image it came from, whichever
        is later (a clock behind the images must not date it onto an earlier image's stamp,
        which carries another value)."""
        if self.held is None:
            return None
        # a nanosecond short: at 10 Hz with a 0.1 s tolerance the held map -> odom would be dated
        # exactly on the next image's stamp, where that image's own must be the one tf2 keeps
        ahead = int(self.config.transform_tolerance_s * 1e9) - 1
        return self.held, self._unique_stamp(max(now_ns, self.held_stamp_ns) + ahead)

    def _unique_stamp(self, stamp_ns: int) -> int:
        """``stamp_ns``, or a nanosecond later where the attachment already went out at it:
        tf2 keeps the first transform of a stamp and drops the others (TF_REPEATED_DATA)."""
        while stamp_ns in self._tf_stamps:
            stamp_ns += 1
        self._tf_stamps.append(stamp_ns)
        return stamp_ns

    def detections(self, obs: FrameObservations | None) -> list:
        """Localization mode: the frame localized as part of a stream; the camera poses found."""
        if obs is None or self.session.mode != 'localization':
            return []
        return self.session.localize(obs)

    # ------------------------------------------------------------------ output

    def tick(self) -> Tick:
        """Solve what arrived (see :meth:`MapSession.tick`), autosave when due; the poses to
        publish when they changed, the object map when it is due."""
        mapper = self.mapper
        recovered, culled = len(mapper.recovered), len(mapper.merged)
        frame_changes = mapper.averager.frame_changes
        changed = self.session.tick()
        out = Tick(log=self._log)
        self._log = []
        if mapper.averager.frame_changes > frame_changes:
            self.warn(f'the map frame changed: a part of the view graph that nothing joins to the part registered '
                      f'so far outgrew it; the map is now its {len(mapper.poses)} keyframes, and camera poses '
                      'published before are in the old frame')
        for edge in mapper.recovered[recovered:]:
            out.log.append(f'tracking recovered: keyframe {edge.target} matched the map through keyframe '
                           f'{edge.source} ({len(edge.inliers)} objects verified)')
        if len(mapper.merged) > culled:                     # (culled keyframes are added at the end)
            merged = {k: m.into for k, m in list(mapper.merged.items())[culled:]}
            out.log.append(f'culled {len(merged)} redundant keyframe(s) ('
                           + ', '.join(f'{k} into {a}' for k, a in sorted(merged.items()))
                           + f'); the map holds {len(mapper.keyframes)}, {len(mapper.merged)} culled')
        out.earlier = self.session.released
        if changed is not False:
            out.camera = changed
            self.throttle.pending = True
        if self._autosave_due():
            out.saved = self.save(frames_beside=True)['path'] or None
        if changed is not False or self._republish:
            out.keyframe_poses = self.keyframe_poses()
        if self.throttle.due() or self._republish:
            out.object_map = self.object_map()
        self._republish = False
        return out

    def object_map(self) -> tuple:
        """The object map now: (tracks, stamp_ns of the newest keyframe, revision); its cost
        goes into the throttle."""
        start = time.monotonic()
        tracks = self.mapper.tracks()
        self.throttle.done(time.monotonic() - start)
        self.num_objects = len(tracks)
        stamp_ns = max((f.stamp_ns for f in self.mapper.keyframes.values()), default=0)
        return tracks, stamp_ns, self.mapper.revision

    def keyframe_poses(self) -> tuple:
        """([keyframe id], {id: 4x4 camera-to-map}, {id: stamp_ns}) of the registered keyframes."""
        poses = self.mapper.camera_poses()
        return sorted(poses), poses, {k: self.mapper.keyframes[k].stamp_ns for k in poses}

    def status(self) -> MapStatus:
        mp, latency = self.mapper, self.session.relocalize_latency()
        active = len(mp.active_edges())
        return MapStatus(mp.mode, len(mp.keyframes), len(mp.merged), len(mp.poses), active,
                         len(mp.measurements()) - active, self.num_objects, mp.num_components(),
                         mp.averager.frame_changes, len(mp.frames),
                         self.num_lost, float(mp.last_update_seconds), latency['queries'], latency['relocalized'],
                         latency['median_ms'] / 1e3, latency['p95_ms'] / 1e3, self.num_saves, self.save_seconds,
                         self.session.message)

    # ------------------------------------------------------------------ services
    # Each answers with the service response's fields (success, message, ...).

    def relocalize(self, obs: FrameObservations):
        """The query's pose in the map: (Relocalization or None, what happened)."""
        return self.session.relocalize(obs)

    def save(self, requested: str = '', frames_beside: bool = False) -> dict:
        """Save the map to the file a request names (empty: the map file): success, message,
        path. An autosave (``frames_beside``) keeps the frame log beside the map file and
        appends to it, so that autosaving costs the same all day; any other save writes one
        self-contained file."""
        try:
            path = self.files.resolve(requested)
        except ValueError as exc:
            return dict(success=False, message=f'not saved: {exc}', path='')
        start = time.perf_counter()
        try:
            written = self.session.save(path, frames_beside=frames_beside)
        except (OSError, ValueError) as exc:
            self.session.message = f'saving the map to {path} failed: {exc}'
            self.warn(self.session.message)
            return dict(success=False, message=self.session.message, path='')
        self.num_saves, self.save_seconds = self.num_saves + 1, time.perf_counter() - start
        if Path(path).expanduser().resolve() == Path(self.files.path).expanduser().resolve():
            self._saved = (self.clock(), len(self.mapper.frames))
        return dict(success=True, message=f'saved {len(self.mapper.keyframes)} keyframes to {written}', path=written)

    def load(self, requested: str = '') -> dict:
        """Replace the map by the file a request names (empty: the map file): success, message,
        num_keyframes, num_objects. On failure the current map is unchanged. The mapper takes
        the configuration the map was built with; settings that differ from this node's are said."""
        try:
            path = self.files.resolve(requested)
            header, changed = self.session.load(path)
        except (MapFileError, ValueError) as exc:
            return dict(success=False, message=f'{exc} (the current map is unchanged)')
        self._republish = True
        self.num_objects = len(self.mapper.tracks())
        text = f'loaded {path}: {header["keyframes"]} keyframes, {self.num_objects} objects'
        if changed:
            text += ("; built with other mapper settings, using the map's: "
                     + ', '.join(f'{k}={file} (parameter: {mine})' for k, (file, mine) in changed.items()))
        return dict(success=True, message=text, num_keyframes=len(self.mapper.keyframes),
                    num_objects=self.num_objects)

    def reset(self) -> dict:
        self.session.reset()
        self._republish = True
        self.num_objects = 0
        return dict(success=True, message='map cleared')

    def set_mode(self, mode: int) -> dict:
        """Switch to SetMode's mode (0 mapping, 1 localization)."""
        if mode not in (0, 1):
            return dict(success=False, message=f'unknown mode {mode}: 0 mapping, 1 localization')
        self.session.mode = MODES[mode]
        return dict(success=True, message=f'mode: {self.session.mode}')

    def _autosave_due(self) -> bool:
        unsaved = len(self.mapper.frames) - self._saved[1] if self.mapper.mode == 'mapping' else 0
        return bool(self.mapper.keyframes) and self.autosave.due(self.session.since_save, len(self.mapper.keyframes),
                                                                 unsaved, self.clock() - self._saved[0])

    def close(self) -> str | None:
        """The node stops: the map file written once more, self-contained (its frame log inside),
        when something is unsaved (the path written)."""
        unsaved = self.mapper.mode == 'mapping' and len(self.mapper.frames) > self._saved[1]
        if self.autosave.every_n and self.mapper.keyframes and (self.session.since_save or unsaved):
            return self.save()['path'] or None
        return None
