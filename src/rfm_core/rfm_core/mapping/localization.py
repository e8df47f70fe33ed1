"""Localization mode: a stream of frames localized against a frozen map.

Each frame relocalized on its own (:func:`rfm_core.mapping.relocalization.relocalize`) is
right or wrong alone: look-alike furniture (two equal chairs, a shifted row of cabinets)
explains three or four detections as well as the truth does, and a frame that sees two or
three of the map's objects cannot be told from a look-alike by the map alone. A camera moves
continuously, so a stream of frames can do what one frame cannot, as a robot's localization
does with its odometry:

- **A track.** Once a pose is accepted, the next frame's pose is predicted: its yaw from the
  gyroscope's turns from the track's last frames (:func:`rfm_core.observations.imu_relative_yaw`;
  without one, any turn a hand makes in the time), its camera centre within walking reach
  of the last. Only hypotheses consistent with the prediction are kept (the keyframes
  nearest it are tried too), and one is accepted with ``stream_min_explained`` detections
  explained, all of a smaller query: the prediction verifies it as well.
- **Confirmation.** Without a track (the first frame, or after ``stream_max_gap_s`` without
  a pose), a pose found against the whole map is held until a later frame's pose, found
  the same way, agrees with it under the same motion bounds; then both are accepted (the
  held one late). A look-alike that one frame happens to see rarely survives the next.
- **Walking back.** The newest frames nothing placed are kept; when a track goes on after
  them (a new track's first frames, once confirmed), they are placed walking back from its
  first frame, each as the track places a frame (its objects where the pose after it
  predicts it, else its depth points), their poses late, as a confirmed frame's.
- **Kidnapping.** A track that nothing confirms for ``stream_max_gap_s`` is dropped; poses
  against the whole map that contradict a live track are held and confirmed the same way,
  and two that agree replace the track.
- **Depth points.** A frame of a live track that its objects do not place (a frame the
  detector sent with its depth points only, too few detections, or too few of them
  explained) is aligned on its depth points, from the predicted pose, to the map's depth
  points (every registered keyframe's cloud merged:
  :meth:`rfm_core.mapping.map_index.MapIndex.cloud_near`; a view
  sees surfaces several keyframes saw), else to the map keyframes nearest the prediction
  (:func:`rfm_core.matching.relative_pose.track_on_points`),
  and accepted where the points fix every direction and the pose is within the
  prediction's bounds: the map's own surfaces place it, so a run of such frames does not
  drift. An alignment finds the surfaces within a quarter metre of where it starts, and a
  walking camera moves that far in half a second: it starts where the track's velocity
  (its last two frames) puts the camera, and again from the last frame's centre (a velocity
  from one wrong pose predicts wrong); the one that puts more of the frame on the map's
  surfaces wins.
- **The objects have the last word.** Points alone can slide a track along a wall, a frame
  at a time, 0.5 m off in a few seconds while each alignment fits well. A frame the points
  place whose objects, relocalized against the whole map, place it somewhere else is taken
  as contradicting the track (held, and two such frames that agree replace it). Frames the
  points alone place confirm nothing: they carry the track on (and walk it back over the
  frames before them), but the poses held against it stay held, and a later frame that
  agrees with one replaces the track and places the held frame again.

No ROS here: :class:`rfm_core.session.MapSession` calls :meth:`StreamLocalizer.step` for
each frame in localization mode (``rfm/detections``), and ``rfm eval-reloc --offline`` does
the same. The ``rfm/relocalize`` service answers single queries without the stream.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rfm_core.geometry import Pose4, wrap_angle
from rfm_core.mapping.relocalization import (MotionPrior, Relocalization, RelocalizationConfig, same_view,
                                             walking_reach)
from rfm_core.matching.relative_pose import track_on_points
from rfm_core.observations import FrameObservations, imu_relative_yaw

__all__ = ['StreamLocalizer', 'motion_prior', 'on_points']

HELD = 8                        #: unconfirmed poses held at most (the newest)
UNPLACED = 8                    #: frames nothing placed kept for the next track to walk back over (the newest)
TRACK = 10                      #: accepted frames the track predicts yaw from (the newest)
POINT_KEYFRAMES = 2             #: map keyframes (the nearest the prediction) a frame is aligned to on its points


def motion_prior(track: list, obs: FrameObservations, config: RelocalizationConfig) -> MotionPrior:
    """Where ``obs``'s camera can be, given the accepted frames ``track`` ((observations,
    T_view_map) pairs, oldest first): its centre within ``stream_speed_mps`` of the newest's
    (plus ``stream_slack_m``); its yaw, where the gyroscope measured the turns from them, the
    median of each one's yaw turned by its turn to ``obs`` (``stream_slack_deg``: one pose's
    error does not carry over), else the newest's within any turn at ``stream_turn_dps``."""
    last, pose = track[-1]
    dt = abs(obs.stamp_ns - last.stamp_ns) * 1e-9
    t_map_last = pose.inverse()
    yaws = []
    for o, p in track:
        turn = imu_relative_yaw(o, obs)
        if turn is not None:
            yaws.append(p.inverse().yaw + turn)
    if yaws:
        ref = yaws[-1]                          # a median of angles about the newest's
        yaw, tolerance = ref + float(np.median(wrap_angle(np.array(yaws) - ref))), config.stream_slack_deg
    else:
        yaw, tolerance = t_map_last.yaw, config.stream_slack_deg + config.stream_turn_dps * dt
    predicted = None
    if len(track) >= 2:                         # the camera keeps the velocity of its last two frames
        before, pose_before = track[-2]
        gap = (last.stamp_ns - before.stamp_ns) * 1e-9
        if 0 < gap <= config.stream_max_gap_s:
            velocity = (t_map_last.t - pose_before.inverse().t) / gap
            speed = float(np.linalg.norm(velocity))
            if speed > config.stream_speed_mps:
                velocity *= config.stream_speed_mps / speed
            predicted = t_map_last.t + velocity * dt
    return MotionPrior(float(yaw), t_map_last.t.copy(), walking_reach(config, dt),
                       min(math.radians(tolerance), math.pi), predicted)


def on_points(obs: FrameObservations, prior: MotionPrior, index, matching) -> Relocalization | None:
    """A frame placed on its depth points from where ``prior`` predicts it (see the module):
    aligned to the map's merged depth points near the prediction (``index``: a
    :class:`~rfm_core.mapping.map_index.MapIndex`), else to the map keyframes nearest it;
    accepted where the points fix every direction and the pose is one ``prior`` admits. Each
    is aligned from the centre the camera's velocity predicts and from the last frame's (a
    velocity from a wrong pose predicts wrong), and the alignment that puts more of the
    frame's points on the map's surfaces is kept (as many: the one they lie closer on; the
    share is capped where all that can lie on a surface does). None otherwise."""
    if not len(obs.cloud):
        return None
    starts = [prior.start] + ([prior.centre] if prior.predicted is not None else [])
    best = None
    for start in starts:
        t_map_view = Pose4(prior.yaw, start)
        found = track_on_points(t_map_view, index.cloud_near(start), obs, matching)
        if (found is not None and not found.free and prior.admits(found.pose.inverse())
                and (best is None or _better(found, best[0]))):
            best = (found, found.pose.inverse(), index.nearest_keyframe(found.pose.t), 1)
    if best is None:
        near = index.keyframes_with_points_near(prior.start, POINT_KEYFRAMES)
        for k in near:
            t_k_map = index.poses[k]
            for start in starts:
                found = track_on_points(t_k_map @ Pose4(prior.yaw, start), index.keyframes[k], obs, matching)
                if found is None or found.free:
                    continue
                pose = found.pose.inverse() @ t_k_map                  # T_view_map
                if prior.admits(pose) and (best is None or _better(found, best[0])):
                    best = (found, pose, k, len(near))
            if best is not None:
                break
    if best is None:
        return None
    return Relocalization(best[1], best[2], 0, np.zeros((0, 2), int), candidates=best[3])


def _better(a, b) -> bool:
    """Whether point alignment ``a`` puts the frame on the map's surfaces better than ``b``."""
    return (a.overlap, -a.residual_m) > (b.overlap, -b.residual_m)


@dataclass
class _Held:
    obs: FrameObservations
    reloc: Relocalization


class StreamLocalizer:
    """Localization mode's frames as a stream (see the module) against ``mapper``'s map:
    its :meth:`~rfm_core.mapping.mapper.Mapper.relocalize` (with a :class:`MotionPrior`, only
    poses consistent with it) and its ``config.relocalization``, read at each frame, so the
    stream and the relocalization it calls never disagree on a setting."""

    def __init__(self, mapper):
        self.mapper = mapper
        self.reset()

    @property
    def config(self) -> RelocalizationConfig:
        return self.mapper.config.relocalization

    def reset(self) -> None:
        self.track: list = []                     # the newest accepted frames: (observations, T_view_map)
        self.held: list[_Held] = []               # poses waiting for a frame that agrees
        self.unplaced: list = []                  # the newest frames nothing placed (observations)
        # frames, by what became of them
        self.counts = dict(tracked=0, points=0, confirmed=0, held=0, walked_back=0)

    def _live(self, obs: FrameObservations) -> bool:
        return (bool(self.track)
                and abs(obs.stamp_ns - self.track[-1][0].stamp_ns) * 1e-9 <= self.config.stream_max_gap_s)

    def _accept(self, *frames, by_objects: bool = True) -> list:
        """The track goes on with ``frames`` ((observations, Relocalization), oldest first),
        after the unplaced frames between its last one and them, walked back over
        (:meth:`_walk_back`); all of those, oldest first. Frames the objects placed
        (``by_objects``) end the poses held against the track; a frame its depth points alone
        placed confirms nothing, and they stay held."""
        after = self.track[-1][0].stamp_ns if self.track else None
        frames = self._walk_back(*frames[0], after) + list(frames)
        self.track = (self.track + [(o, r.pose) for o, r in frames])[-TRACK:]
        if by_objects:
            self.held = []
        placed = {id(o) for o, _ in frames}
        self.unplaced = [o for o in self.unplaced if id(o) not in placed]
        return frames

    def _walk_back(self, first: FrameObservations, reloc: Relocalization, after: int | None) -> list:
        """The frames nothing placed before ``first`` (and after the stamp ``after``, the
        track's last frame), placed walking back from ``first``'s pose: each as a track places
        a frame (its objects where the pose after it predicts it, else its depth points),
        while they are within ``stream_max_gap_s`` of each other; oldest first. A new track
        (or one that went on after frames it could not place) gets the frames before it that
        only it can place; their poses come late, as a confirmed frame's do."""
        cfg, out = self.config, []
        anchor = (first, reloc.pose)
        for obs in sorted((o for o in self.unplaced if o.stamp_ns < first.stamp_ns
                           and (after is None or o.stamp_ns > after)), key=lambda o: -o.stamp_ns):
            if abs(anchor[0].stamp_ns - obs.stamp_ns) * 1e-9 > cfg.stream_max_gap_s:
                break
            prior = motion_prior([anchor], obs, cfg)
            placed = (self.mapper.relocalize(obs, [], prior) if len(obs) >= 2 else None) or self._on_points(obs, prior)
            if placed is None:
                break
            out.append((obs, placed))
            anchor = (obs, placed.pose)
        self.counts['walked_back'] += len(out)
        return out[::-1]

    def _on_points(self, obs: FrameObservations, prior: MotionPrior) -> Relocalization | None:
        """A frame of the live track placed on its depth points (:func:`on_points`), or None."""
        return on_points(obs, prior, self.mapper.map_index(), self.mapper.config.matching)

    def step(self, obs: FrameObservations, why: list | None = None) -> list:
        """Localize one frame: the frames accepted by it, oldest first, as (observations,
        :class:`Relocalization`) — this one when the track or a confirmation places it, with a
        held frame it confirms before it; [] while its pose waits to be confirmed, or when
        nothing places it (the reason appended to ``why``)."""
        why = why if why is not None else []
        cfg = self.config
        relocalize = self.mapper.relocalize
        reloc = None
        if self._live(obs):
            prior = motion_prior(self.track, obs, cfg)
            reloc = relocalize(obs, why, prior) if len(obs) >= 2 else None
            if reloc is not None:
                self.counts['tracked'] += 1
                return self._accept((obs, reloc))
            by_points = self._on_points(obs, prior)
            if by_points is not None:
                # the objects have the last word: a frame they place elsewhere (the track
                # slid on the points) goes on as one the track cannot place
                alone = relocalize(obs, []) if len(obs) >= 2 else None
                if alone is None or same_view(alone.pose.inverse(), by_points.pose.inverse(), cfg):
                    self.counts['points'] += 1
                    return self._accept((obs, by_points), by_objects=False)
                reloc = alone
        self.unplaced = (self.unplaced + [obs])[-UNPLACED:]        # until something places it
        if reloc is None:
            reloc = relocalize(obs, why)
        if reloc is None:
            return []
        # keep only held poses still within reach in time; the newest that agrees confirms
        self.held = [h for h in self.held if abs(obs.stamp_ns - h.obs.stamp_ns) * 1e-9 <= cfg.stream_max_gap_s]
        for h in reversed(self.held):
            if motion_prior([(h.obs, h.reloc.pose)], obs, cfg).admits(reloc.pose):
                self.counts['confirmed'] += 1
                self.track = []                     # a new track (or the old one replaced)
                return self._accept((h.obs, h.reloc), (obs, reloc))
        self.counts['held'] += 1
        self.held = (self.held + [_Held(obs, reloc)])[-HELD:]
        why.append('the pose waits for a later frame to agree with it' if not self._live(obs)
                   else 'the pose contradicts the track; held until a later frame agrees with it')
        return []
