"""The pipeline, readable top to bottom, without ROS: what the nodes and ``rfm eval`` run.

Per frame (paper 3.1-3.6)::

    detections --ViewGraphBuilder.add--> keyframe?, its verified edges, the frame's track
               --MapSession-----------> keyframe + edges into pose averaging (incremental),
                                         the frame logged and posed against its keyframe

:class:`Session` runs both stages in one process, one :meth:`Session.step` per frame
(``rfm eval --offline``). The node graph splits them: the matcher node owns the
:class:`~rfm_core.matching.view_graph.ViewGraphBuilder`, the mapper node a
:class:`MapSession`, which takes keyframes, edges, tracked frames and external poses in any
order (an edge waits for its keyframes, a posed keyframe for its pose), solves when asked
(:meth:`MapSession.tick`: incrementally, and all at once when the input has been idle),
relocalizes in localization mode, and saves and loads maps. Nodes only convert messages.
"""
from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, fields, replace
from typing import Callable, NamedTuple

import numpy as np

from rfm_core.geometry import Pose4
from rfm_core.mapping.frame_log import camera_to_map, pose_from_camera
from rfm_core.mapping.localization import StreamLocalizer
from rfm_core.mapping.map_io import load_map, save_map
from rfm_core.mapping.mapper import MODES, Mapper, MapperConfig
from rfm_core.mapping.relocalization import Relocalization
from rfm_core.matching.view_graph import ViewGraphBuilder, ViewGraphConfig
from rfm_core.observations import EdgeRecord, FrameObservations, FrameTrack

__all__ = ['MapSession', 'Session', 'Step', 'CameraPose', 'ExternalPoses', 'SequenceCheck']

PENDING_EDGES = 5000            #: edges (and tracked frames) waiting for their keyframes (oldest dropped first)
PENDING_EDGE_AGE_S = 30.0       #: ... for at most this long
PENDING_KEYFRAMES = 100         #: posed keyframes waiting for their poses
EDGES_WAIT_S = 1.0              #: a keyframe is solved once the edges sent with it are in, or this long after it
MAX_KEYFRAME_ID = 2 ** 40       #: larger incoming ids get the next free map id (track ids stay in 64 bits)
RELOCALIZE_TIMES_KEPT = 1000    #: relocalization queries whose wall time is kept (for the latency reported)


class SequenceCheck:
    """Gaps in a numbered message stream (the matcher's ``session`` / ``sequence`` fields):
    :meth:`add` returns how many messages were skipped before this one (0 in order; a new
    session, a repeat or an unnumbered message: 0)."""

    def __init__(self):
        self.session, self.last, self.lost = 0, 0, 0

    def add(self, session: int, sequence: int) -> int:
        if not session or not sequence:
            return 0
        if session != self.session or sequence <= self.last:
            self.session, self.last = session, sequence - 1     # a matcher (re)started: count from here
        gap = sequence - self.last - 1
        self.last = sequence
        self.lost += gap
        return gap


class CameraPose(NamedTuple):
    """A localized frame's camera optical frame in the map."""

    stamp_ns: int
    frame_id: str
    matrix: np.ndarray              #: 4x4 camera-to-map
    covariance: np.ndarray | None = None   #: (6, 6) x, y, z, rotations about x, y, z (Mapper.frame_covariance)
    #: the frame continues a stream (the matcher's ``continuous``: the camera moved smoothly from the
    #: frame before); False: a separate view, such as a photo (no TF of its own: MapperCore.attach)
    stream: bool = True


class ExternalPoses:
    """Posed mode's pose source from a topic: camera-to-map poses by stamp; a keyframe takes
    the one nearest its stamp within ``tolerance_ns``."""

    def __init__(self, capacity: int = 2000, tolerance_ns: int = 5_000_000):
        self.capacity, self.tolerance_ns = capacity, tolerance_ns
        self.poses: list = []                 # (stamp_ns, 4x4)

    def add(self, stamp_ns: int, matrix: np.ndarray) -> None:
        self.poses.append((int(stamp_ns), np.asarray(matrix, float)))
        del self.poses[:-self.capacity]

    def __call__(self, obs: FrameObservations):
        best = min(self.poses, key=lambda sp: abs(sp[0] - obs.stamp_ns), default=None)
        if best is not None and abs(best[0] - obs.stamp_ns) <= self.tolerance_ns:
            return best[1]
        return None


class MapSession:
    """The mapper's side of the pipeline (paper 3.5-3.6 and appendix): see the module.

    ``pose_lookup`` (posed mode): a keyframe's pose from outside, given its observations: a
    Pose4 ``T_k_map``, a 4x4 camera-to-map matrix, or None while there is none yet.
    ``warn``: where dropped input is reported (the node logs it, throttled).

    Keyframe ids: the view graph numbers its keyframes from 0 again when it restarts, and a
    map loaded from a file already holds ids. Each incoming keyframe gets a map id (its own
    while that is new and larger than every id in the map, else the next free one); edges and
    tracked frames are translated through a table keyed by (view-graph session, its keyframe
    id). The matcher node numbers its sessions (``source``), and the table is kept in map
    files (:attr:`Mapper.origins`), so a keyframe received again (a mapper restarted from its
    autosave that gets the matcher's kept history) is recognised and ignored, and a restarted
    matcher's ids never meet an earlier session's. Without a session number (``source`` 0,
    e.g. in one process) a restart is recognised by an id that does not increase, or one
    reused with another stamp: that table and the edges still waiting for keyframes are
    dropped, so nothing from a restarted view graph attaches to the keyframes of an earlier one.
    """

    def __init__(self, config: MapperConfig | None = None, matcher=None, pose_lookup=None,
                 idle_full_solve_s: float = 0.0, warn: Callable[[str], None] | None = None,
                 clock: Callable[[], float] = time.monotonic):
        config = config or MapperConfig()
        if pose_lookup is not None and not config.posed:
            config = replace(config, posed=True)
        self.mapper = Mapper(config, matcher=matcher)
        self.pose_lookup = pose_lookup
        self.idle_full_solve_s = idle_full_solve_s
        self.warn = warn or (lambda text: None)
        self.clock = clock
        self.counts = dict(keyframes=0, edges=0, frames=0, dropped=0, relocalized=0, relocalize_failed=0)
        self.message = ''                     # the last error, for status
        self.relocalize_seconds = deque(maxlen=RELOCALIZE_TIMES_KEPT)   # wall time of the latest queries
        self._clear()

    def _clear(self) -> None:
        self.pending_edges: list = []         # (arrival time, EdgeRecord) waiting for keyframes
        self.pending_keyframes: list = []     # posed: (id, observations) waiting for a pose
        self.pending_frames: list = []        # (arrival time, FrameTrack) waiting for their keyframe
        self.awaiting: dict = {}              # map id -> [edges sent with the keyframe not yet in, arrival time]
        self._held: list = []                 # tracked frames not given out while their keyframe's edges came
        self.released: list = []              # their CameraPoses, given out by the last tick before its own
        self.dirty = False                    # keyframes or edges not yet solved
        self.since_save = 0                   # keyframes added since the map was last saved
        self._full_solve_due = None           # clock time of the idle full re-solve
        self._latest_track = None             # the newest tracked frame
        self.stream = StreamLocalizer(self.mapper)
        self._last_camera = None              # the last CameraPose handed out
        # (view-graph session, its keyframe id) -> map id; numbered sessions' from the map file
        self._incoming: dict = {origin: k for k, origin in self.mapper.origins.items()}
        self._incoming_last = None            # the newest keyframe id of the unnumbered session
        self._max_id = max(self.mapper.keyframes, default=-1)   # the largest map id given out

    @property
    def mode(self) -> str:
        return self.mapper.mode

    @mode.setter
    def mode(self, mode: str) -> None:
        if mode not in MODES:
            raise ValueError(f'unknown mode {mode!r}: one of {", ".join(MODES)}')
        self.mapper.mode = mode
        self.stream.reset()                   # a track from before means nothing now

    @property
    def full_solve_pending(self) -> bool:
        """Whether an idle full re-solve is scheduled (incremental updates since the last)."""
        return self._full_solve_due is not None

    # ------------------------------------------------------------------ mapping input

    def add_keyframe(self, keyframe_id: int, obs: FrameObservations, source: int = 0, edges: int = 0) -> bool:
        """A keyframe from the view graph session ``source`` (0: unnumbered; posed: it waits
        for its pose). False: ignored (localization mode, or a keyframe already received).
        ``edges``: how many edges the view graph sent with it; :meth:`tick` does not solve
        until they are in (or :data:`EDGES_WAIT_S` has passed): they arrive as separate
        messages, and a keyframe solved on the first of them alone is placed on that edge
        alone, and published there."""
        if self.mode != 'mapping':
            return False
        map_id = self._new_map_id(int(keyframe_id), obs.stamp_ns, int(source))
        if map_id is None:
            return False
        if self.mapper.config.posed:
            self.pending_keyframes.append((map_id, obs))
            self.attach_external_poses()
            return True
        if not self.mapper.add_keyframe(map_id, obs):
            return False
        if edges > 0:
            self.awaiting[map_id] = [int(edges), self.clock()]
        self._keyframe_added()
        return True

    def _new_map_id(self, incoming: int, stamp_ns: int, source: int) -> int | None:
        """The map id of a new keyframe from the view graph; None for one received before."""
        known = self._incoming.get((source, incoming))
        if known is not None:
            obs = self.mapper.keyframes.get(known) or dict(self.pending_keyframes).get(known)
            culled = self.mapper.merged.get(known)
            if (obs is not None and obs.stamp_ns == stamp_ns) or (culled is not None and culled.stamp_ns == stamp_ns):
                return None                                   # the same keyframe again
        if not source and (known is not None or (self._incoming_last is not None and incoming < self._incoming_last)):
            if any(not s for s, _ in self._incoming):
                self.warn(f'keyframe id {incoming} after {self._incoming_last}: the view graph restarted; '
                          f'its keyframes continue as new map ids from {self._max_id + 1}')
            self._incoming = {key: k for key, k in self._incoming.items() if key[0]}
            self.pending_edges = [p for p in self.pending_edges if p[1]]
            self.pending_frames = [p for p in self.pending_frames if p[1]]
        map_id = incoming if self._max_id < incoming < MAX_KEYFRAME_ID else self._max_id + 1
        self._incoming[source, incoming] = map_id
        if source:
            self.mapper.origins[map_id] = (source, incoming)
        else:
            self._incoming_last = incoming
        self._max_id = max(self._max_id, map_id)
        return map_id

    def _translate_edge(self, edge: EdgeRecord, source: int) -> EdgeRecord | None:
        """The edge between map ids; None while one of its keyframes is not in the map."""
        a, b = self._incoming.get((source, edge.source)), self._incoming.get((source, edge.target))
        if a is None or b is None or not self.mapper.knows(a) or not self.mapper.knows(b):
            return None
        return replace(edge, source=a, target=b)

    def _keyframe_added(self) -> None:
        self.counts['keyframes'] += 1
        self.since_save += 1
        self.dirty = True
        self._retry_edges()
        self._retry_frames()

    def add_edge(self, edge: EdgeRecord, source: int = 0) -> None:
        """A verified edge of view-graph session ``source``; it waits (bounded) while one of
        its keyframes has not arrived."""
        if self.mode != 'mapping':
            return
        mapped = self._translate_edge(edge, source)
        if mapped is None:
            self.pending_edges.append((self.clock(), source, edge))
            if len(self.pending_edges) > PENDING_EDGES:
                self.pending_edges.pop(0)
                self.counts['dropped'] += 1
            return
        for k in (mapped.source, mapped.target):
            if k in self.awaiting:
                self.awaiting[k][0] -= 1
                if self.awaiting[k][0] <= 0:
                    del self.awaiting[k]
        try:
            if self.mapper.add_edge(mapped):
                self.counts['edges'] += 1
                self.dirty = True
        except ValueError as exc:
            self.counts['dropped'] += 1
            self.warn(f'edge dropped: {exc}')

    def _retry_edges(self) -> None:
        self.pending_edges = self._retry(self.pending_edges, lambda e, s: self._translate_edge(e, s) is not None,
                                         self.add_edge)

    def _retry_frames(self) -> None:
        self.pending_frames = self._retry(self.pending_frames, lambda t, s: (s, t.keyframe_id) in self._incoming,
                                          self.add_frame)

    def _retry(self, pending: list, ready, add) -> list:
        """Hand on the waiting (arrival time, session, item) whose keyframes have arrived
        (``ready(item, session)``, then ``add(item, session)``); returns those still waiting
        and younger than PENDING_EDGE_AGE_S."""
        now, still = self.clock(), []
        for arrived, source, item in pending:
            if ready(item, source):
                add(item, source)
            elif now - arrived < PENDING_EDGE_AGE_S:
                still.append((arrived, source, item))
        return still

    def attach_external_poses(self) -> None:
        """Posed mode: give waiting keyframes their poses from ``pose_lookup`` (call again
        when a new pose has arrived)."""
        still = []
        for k, obs in self.pending_keyframes:
            found = self.pose_lookup(obs) if self.pose_lookup is not None else None
            if found is None:
                still.append((k, obs))
                continue
            try:
                pose = found if isinstance(found, Pose4) else pose_from_camera(found, obs.gravity_cam)
            except ValueError:
                self.warn('external pose disagrees with gravity by > 3 deg; keyframe dropped')
                continue
            if self.mapper.add_keyframe(k, obs):
                self.mapper.set_keyframe_pose(k, pose)
                self._keyframe_added()
        self.pending_keyframes = still[-PENDING_KEYFRAMES:]
        self._retry_edges()

    def add_frame(self, track: FrameTrack, source: int = 0) -> CameraPose | None:
        """A tracked frame (its pose relative to a keyframe of view-graph session ``source``):
        logged; returns its camera pose when it has one and is newer than the last one handed out."""
        if self.mode != 'mapping':
            return None
        map_id = self._incoming.get((source, track.keyframe_id))
        if map_id is None:                  # its keyframe has not arrived yet (topics are not ordered)
            self.pending_frames.append((self.clock(), source, track))
            if len(self.pending_frames) > PENDING_EDGES:
                self.pending_frames.pop(0)
                self.counts['dropped'] += 1
            return None
        if not self.mapper.add_frame(replace(track, keyframe_id=map_id)):
            self.counts['dropped'] += 1
            self.warn(f'tracked frame dropped: its keyframe {track.keyframe_id} is not in the map with that stamp '
                      '(did the matcher restart?)')
            return None
        self.counts['frames'] += 1
        self._latest_track = track
        if self.mapper.awaits_recovery(map_id):
            self.dirty = True                   # the next update tries to recover its keyframe
        if map_id in self.awaiting or self._held:
            self._held.append(track)            # placed on part of its keyframe's edges (or after one that is):
            return None                         # the solve after them gives them out, in order
        return self._latest_camera()

    def _latest_camera(self) -> CameraPose | None:
        """The newest localized frame's pose if newer than the last handed out (the camera
        pose stream never goes back in time); without tracked frames, the newest keyframe's.
        Not a pose :meth:`Mapper.withheld` holds back: nothing measured enough holds its keyframe."""
        track = self._latest_track
        if track is not None:
            cam = self.mapper.frame_pose(track)
            pose = (CameraPose(track.stamp_ns, track.frame_id, cam, stream=track.continuous) if cam is not None
                    else None)
        else:
            poses = self.mapper.camera_poses()
            last = max(poses, default=None)
            track = None if last is None else self.mapper.keyframe_track(last)
            pose = (CameraPose(self.mapper.keyframes[last].stamp_ns, self.mapper.keyframes[last].frame_id,
                               poses[last]) if last is not None else None)
        if (pose is None or (self._last_camera is not None and pose.stamp_ns <= self._last_camera.stamp_ns)
                or self.mapper.withheld(track)):
            return None
        pose = pose._replace(covariance=self.mapper.frame_covariance(track))
        self._last_camera = pose
        return pose

    def _release_held(self, newest: CameraPose | None, after_ns: int) -> list:
        """The camera poses of the frames held while their keyframe's edges were on their way,
        now solved: those between the last pose handed out before (``after_ns``) and ``newest``,
        in time order (the stream never goes back)."""
        held, self._held = self._held, []
        until = newest.stamp_ns if newest is not None else float('inf')
        out = []
        for track in sorted(held, key=lambda t: t.stamp_ns):
            if not after_ns < track.stamp_ns < until:
                continue
            cam = self.mapper.frame_pose(track)
            if cam is not None and not self.mapper.withheld(track):
                out.append(CameraPose(track.stamp_ns, track.frame_id, cam, self.mapper.frame_covariance(track),
                                      track.continuous))
        if out and newest is None:
            self._last_camera = out[-1]
        return out

    # ------------------------------------------------------------------ solving

    def update(self, force_full: bool = False):
        """Fold what arrived into the poses now (the averaging stats; None without changes)."""
        if not (self.dirty or force_full):
            return None
        self.dirty = False
        self._full_solve_due = None
        return self.mapper.update(force_full=force_full)

    def tick(self) -> CameraPose | bool | None:
        """Solve what arrived since the last tick, or all poses at once when the input has
        been idle for ``idle_full_solve_s`` after incremental updates. False: nothing to do;
        otherwise the poses changed and the result is the newest frame's new camera pose (or
        None). Never raises: a failed solve is kept in :attr:`message`. :attr:`released`: the
        frames held for their keyframe's edges, given out now, before the result."""
        now = self.clock()
        self.released = []
        self.awaiting = {k: w for k, w in self.awaiting.items() if now - w[1] < EDGES_WAIT_S}
        if self.awaiting:
            return False                                    # a keyframe's edges are still on their way
        after = self._last_camera.stamp_ns if self._last_camera is not None else -1
        idle = (not self.dirty and self._full_solve_due is not None and now >= self._full_solve_due)
        newest = False
        if self.dirty or idle:
            try:
                stats = self.update(force_full=idle)
            except Exception as exc:                       # noqa: BLE001 - a solve never kills the node
                self.message = f'update failed: {exc}'
                self.warn(self.message)
            else:
                if stats is not None and stats.kind == 'local' and self.idle_full_solve_s > 0:
                    self._full_solve_due = self.clock() + self.idle_full_solve_s
                newest = self._latest_camera()
        self.released = self._release_held(newest or None, after)
        return newest

    # ------------------------------------------------------------------ localization

    def relocalize(self, obs: FrameObservations) -> tuple[Relocalization | None, str]:
        """The query's pose in the map, or None and why."""
        if len(obs) < 2:
            return None, f'the query has {len(obs)} detections; need >= 2'
        if not self.mapper.poses:
            return None, 'the map is empty: nothing to relocalize against'
        why = []
        start = time.perf_counter()
        reloc = self.mapper.relocalize(obs, why)
        seconds = time.perf_counter() - start
        self.relocalize_seconds.append(seconds)
        took = f' ({1e3 * seconds:.0f} ms)'
        if reloc is None:
            self.counts['relocalize_failed'] += 1
            return None, ('; then '.join(why) if why else 'no pose found') + took
        self.counts['relocalized'] += 1
        reloc.covariance = self.mapper.frame_covariance(self.mapper.relocalized_track(obs, reloc))
        if not reloc.num_inliers:           # no keyframe verified it: the map's objects and depth points did
            return reloc, (f'relocalized on the map\'s depth points from its objects (nearest keyframe '
                           f'{reloc.keyframe_id}): {reloc.explained} detections explained by the map{took}')
        return reloc, (f'relocalized against keyframe {reloc.keyframe_id}: {reloc.num_inliers} inliers, '
                       f'{reloc.agreeing} agreeing keyframes, {reloc.explained} detections explained by the '
                       f'map{took}')

    def relocalize_latency(self) -> dict:
        """Relocalization queries so far and the wall time of the latest
        ``RELOCALIZE_TIMES_KEPT``: {'queries', 'relocalized', 'median_ms', 'p95_ms'} (the
        times 0 before the first query)."""
        times = np.sort(np.asarray(self.relocalize_seconds, float)) * 1e3
        return {'queries': self.counts['relocalized'] + self.counts['relocalize_failed'],
                'relocalized': self.counts['relocalized'],
                'median_ms': float(np.median(times)) if len(times) else 0.0,
                'p95_ms': float(times[int(0.95 * (len(times) - 1))]) if len(times) else 0.0}

    def localize(self, obs: FrameObservations) -> list:
        """Localization mode: localize a frame of the stream against the (frozen) map
        (:class:`~rfm_core.mapping.localization.StreamLocalizer`) and log it. The frames placed
        by it, oldest first, as CameraPoses: this one, and a held frame it confirmed before it;
        [] while its pose waits for confirmation, or when nothing places it."""
        if self.mode != 'localization':
            return []
        why = []
        start = time.perf_counter()
        accepted = self.stream.step(obs, why)
        self.relocalize_seconds.append(time.perf_counter() - start)
        self.counts['relocalized' if accepted and accepted[-1][0] is obs else 'relocalize_failed'] += 1
        self.message = '' if accepted else (why[-1] if why else 'no pose found')
        out = []
        for o, reloc in accepted:
            track = self.mapper.relocalized_track(o, reloc)
            self.mapper.frames.add(track)
            out.append(CameraPose(o.stamp_ns, o.frame_id, camera_to_map(reloc.pose, o.gravity_cam),
                                  self.mapper.frame_covariance(track)))
        if out:
            self._last_camera = out[-1]
        return out

    # ------------------------------------------------------------------ the map

    def save(self, path, frames_beside: bool = False) -> str:
        """Write the map atomically (OSError / ValueError on failure); the path written. With
        ``frames_beside`` the frame log is appended to a file beside it (:func:`save_map`)."""
        written = save_map(self.mapper, path, frames_beside)
        self.since_save = 0
        return str(written)

    def load(self, path) -> tuple[dict, dict]:
        """Replace the map by a map file (MapFileError: the current map is unchanged). The
        mapper takes the configuration the map was built with, except how localization mode
        localizes a stream (``relocalization.stream*``: this session's, as the map was not
        built with them). Returns the file's header and the settings that differ from before
        ({dotted name: (file, before)})."""
        before = self.mapper.config
        header = load_map(self.mapper, path)
        loaded = self.mapper.config.relocalization
        self.mapper.config = replace(self.mapper.config, relocalization=replace(loaded, **{
            f.name: getattr(before.relocalization, f.name) for f in fields(loaded) if f.name.startswith('stream')}))
        mine, theirs = _flat(before.to_dict()), _flat(self.mapper.config.to_dict())
        changed = {k: (theirs[k], mine.get(k)) for k in sorted(theirs) if theirs[k] != mine.get(k)}
        self._clear()
        self.dirty = True
        return header, changed

    def reset(self) -> None:
        """An empty map, in the same mode."""
        mode = self.mode
        self.mapper.reset()
        self.mapper.mode = mode
        self._clear()


def _flat(d: dict, prefix: str = '') -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f'{prefix}{k}.'))
        else:
            out[f'{prefix}{k}'] = v
    return out


@dataclass
class Step:
    """What one frame did: the keyframe it made (or None), that keyframe's verified edges,
    the frame's track (None: not localized) and its camera pose in the map."""

    keyframe: object
    edges: list
    track: FrameTrack | None
    camera: CameraPose | None


class Session:
    """Detections in, map out, one :meth:`step` per frame: the matcher's view graph and the
    mapper's :class:`MapSession` in one process."""

    def __init__(self, config: MapperConfig | None = None, graph: ViewGraphConfig | None = None,
                 matcher=None, pose_lookup=None):
        config = config or MapperConfig()
        self.graph = ViewGraphBuilder(config.matching, graph, matcher=matcher)
        self.map = MapSession(config, matcher=self.graph.matcher, pose_lookup=pose_lookup)
        self.seconds = {'match': 0.0, 'map': 0.0}        # time spent per stage

    @property
    def mapper(self) -> Mapper:
        return self.map.mapper

    def step(self, obs: FrameObservations) -> Step:
        start = time.perf_counter()
        keyframe, edges, track = self.graph.add(obs)      # 3.2-3.4: match, verify, keyframe?
        matched = time.perf_counter()
        if keyframe is not None:                          # this frame, or an earlier one bridging lost tracking
            self.map.add_keyframe(keyframe.keyframe_id, keyframe.observations)
        for edge in edges:                                # the keyframe's, or a revisit's
            self.map.add_edge(EdgeRecord.from_edge(edge))
        if keyframe is not None or edges:
            self.map.update()                             # 3.5: incremental pose averaging
        camera = self.map.add_frame(track) if track is not None else None
        if self.map.dirty:                                # a keyframe outside the map awaits recovery
            self.map.update()
        self.seconds['match'] += matched - start
        self.seconds['map'] += time.perf_counter() - matched
        return Step(keyframe, edges, track, camera)

    def finish(self) -> list:
        """All poses re-solved at once (un-posed); the map's object tracks (3.6)."""
        start = time.perf_counter()
        self.map.update(force_full=not self.mapper.config.posed)
        tracks = self.mapper.tracks()
        self.seconds['map'] += time.perf_counter() - start
        return tracks
