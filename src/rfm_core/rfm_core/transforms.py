"""A TF tree without ROS: what ``/tf`` and ``/tf_static`` say, looked up between any two
frames at a moment, and where the map attaches to it (REP 105).

:class:`TransformBuffer` keeps, per child frame, its parent and the transforms received:
static ones (``/tf_static``) hold at all times; dynamic ones are kept for ``cache_s`` and
interpolated between the two around the moment asked (translation linearly, rotation by
slerp), never extrapolated beyond ``tolerance_s``; a link whose time goes back by more than
``cache_s`` starts again. Every frame has one parent: a transform that gives a frame a second
parent is refused and reported (tf2 would keep re-parenting it).

:func:`map_attachment` is where the mapper hangs the map on a robot's tree: the map frame is
the parent of the root of the camera frame's tree, so the tree stays a tree. On a robot with
odometry the root is ``odom`` (``odom -> base_link -> camera_link -> optical frame``): the
mapper publishes ``map -> odom`` as REP 105 asks; a handheld camera with a static mount gets
``map -> camera_link``; a camera frame with no TF at all, ``map -> camera frame``.
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass, field

import numpy as np

__all__ = ['TransformBuffer', 'Attachment', 'map_attachment', 'interpolate']


def interpolate(a: np.ndarray, b: np.ndarray, t: float) -> np.ndarray:
    """The 4x4 transform ``t`` of the way from ``a`` to ``b`` (0: a, 1: b): translation
    linearly, rotation along the shorter arc (slerp)."""
    from scipy.spatial.transform import Rotation, Slerp  # noqa: PLC0415

    out = np.eye(4)
    out[:3, :3] = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]])))([t]).as_matrix()[0]
    out[:3, 3] = (1.0 - t) * a[:3, 3] + t * b[:3, 3]
    return out


@dataclass
class _Link:
    parent: str
    static: bool
    stamps: list = field(default_factory=list)          # ns, ascending (dynamic links)
    matrices: list = field(default_factory=list)        # 4x4 T_parent_child


class TransformBuffer:
    """``/tf`` and ``/tf_static`` (see the module): :meth:`add` what arrives, :meth:`lookup`
    T_target_source at a moment."""

    def __init__(self, cache_s: float = 10.0, tolerance_s: float = 0.05):
        self.cache_ns = int(cache_s * 1e9)
        self.tolerance_ns = int(tolerance_s * 1e9)
        self.links: dict = {}                     # child -> _Link

    def add(self, parent: str, child: str, stamp_ns: int, matrix, static: bool = False) -> str | None:
        """Take a transform (T_parent_child at ``stamp_ns``); returns why it was refused, or
        None: a frame given a second parent, a frame its own ancestor, a non-finite or
        non-rigid transform."""
        m = np.asarray(matrix, float)
        if not parent or not child or parent == child:
            return f'transform {parent!r} -> {child!r}: frames must be named and differ'
        if m.shape != (4, 4) or not np.all(np.isfinite(m)) or not np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3),
                                                                              atol=1e-3):
            return f'transform {parent} -> {child}: not a finite rigid transform'
        link = self.links.get(child)
        if link is not None and link.parent != parent:
            return (f'{child} already has the parent {link.parent}; {parent} -> {child} would give it a second one '
                    '(a TF tree gives every frame one parent)')
        if child in self._ancestors(parent):
            return f'transform {parent} -> {child}: {child} is already an ancestor of {parent} (a loop)'
        if link is None:
            link = self.links[child] = _Link(parent, static)
        if static or link.static:
            link.static, link.stamps, link.matrices = True, [0], [m]
            return None
        if link.stamps and int(stamp_ns) < link.stamps[-1] - self.cache_ns:
            # time went back (a bag loops, a simulator restarts): start the link again, as tf2
            # clears its buffer on a jump back (kept, the new transform would be cut at once)
            link.stamps, link.matrices = [], []
        i = bisect.bisect_right(link.stamps, int(stamp_ns))
        if i and link.stamps[i - 1] == int(stamp_ns):
            link.matrices[i - 1] = m
        else:
            link.stamps.insert(i, int(stamp_ns))
            link.matrices.insert(i, m)
        cut = bisect.bisect_left(link.stamps, link.stamps[-1] - self.cache_ns)
        if cut:
            del link.stamps[:cut], link.matrices[:cut]
        return None

    def parent(self, frame: str) -> str | None:
        link = self.links.get(frame)
        return None if link is None else link.parent

    def _ancestors(self, frame: str) -> list:
        """[frame, its parent, ..., the root]."""
        chain, seen = [frame], {frame}
        while frame in self.links:
            frame = self.links[frame].parent
            if frame in seen:
                break
            chain.append(frame)
            seen.add(frame)
        return chain

    def root(self, frame: str) -> str:
        """The root of ``frame``'s tree (``frame`` itself when it has no parent)."""
        return self._ancestors(frame)[-1]

    def static_between(self, ancestor: str, frame: str) -> bool:
        """Whether every link from ``frame`` up to ``ancestor`` is static."""
        for f in self._ancestors(frame):
            if f == ancestor:
                return True
            if not self.links[f].static:
                return False
        return False

    def _link_at(self, child: str, stamp_ns: int, tolerance_ns: int) -> np.ndarray | None:
        link = self.links[child]
        if link.static:
            return link.matrices[0]
        stamps = link.stamps
        i = bisect.bisect_left(stamps, stamp_ns)
        if i < len(stamps) and stamps[i] == stamp_ns:
            return link.matrices[i]
        if 0 < i < len(stamps):
            a, b = stamps[i - 1], stamps[i]
            return interpolate(link.matrices[i - 1], link.matrices[i], (stamp_ns - a) / (b - a))
        nearest = 0 if i == 0 else len(stamps) - 1
        return link.matrices[nearest] if abs(stamps[nearest] - stamp_ns) <= tolerance_ns else None

    def lookup(self, target: str, source: str, stamp_ns: int, exact: bool = False) -> np.ndarray | None:
        """T_target_source (maps points in ``source`` into ``target``) at ``stamp_ns``; None
        when the frames are not connected or a link has nothing near that moment (``exact``:
        nothing on both sides of it, no tolerance)."""
        tolerance_ns = 0 if exact else self.tolerance_ns
        up_source, up_target = self._ancestors(source), self._ancestors(target)
        common = next((f for f in up_source if f in set(up_target)), None)
        if common is None:
            return None

        def to_common(chain):                       # T_common_frame along one branch
            m = np.eye(4)
            for f in chain[:chain.index(common)]:
                link = self._link_at(f, stamp_ns, tolerance_ns)
                if link is None:
                    return None
                m = link @ m
            return m

        a, b = to_common(up_source), to_common(up_target)
        if a is None or b is None:
            return None
        return np.linalg.inv(b) @ a

    def acceleration(self, target: str, source: str, stamp_ns: int, step_ns: int) -> np.ndarray | None:
        """(3,) acceleration (m/s^2) of ``source``'s origin in ``target`` (a frame at rest, such
        as a robot's odometry frame), in ``source``'s axes at ``stamp_ns``: the second difference
        of its positions at ``stamp_ns`` and one and two ``step_ns`` before (so it is the
        acceleration ``step_ns`` ago). None unless /tf has ``target`` -> ``source`` on both
        sides of all three moments."""
        poses = [self.lookup(target, source, stamp_ns - k * step_ns, exact=True) for k in range(3)]
        if any(p is None for p in poses):
            return None
        a = (poses[0][:3, 3] - 2 * poses[1][:3, 3] + poses[2][:3, 3]) / (step_ns * 1e-9) ** 2
        return poses[0][:3, :3].T @ a

    def newest(self, ancestor: str, frame: str) -> int | None:
        """The newest moment (ns) /tf has every link from ``frame`` up to ``ancestor``; None
        when ``ancestor`` is not above ``frame`` or every link between them is static."""
        chain = self._ancestors(frame)
        if ancestor not in chain:
            return None
        stamps = [self.links[f].stamps[-1] for f in chain[:chain.index(ancestor)] if not self.links[f].static]
        return min(stamps) if stamps else None


@dataclass(frozen=True)
class Attachment:
    """Where the map hangs on the TF tree for one camera pose: ``parent`` (the map frame) ->
    ``child`` = ``matrix``; ``held``: the child is a moving frame of the robot's odometry
    (``map -> odom``), so the transform is re-published between frames (future-dated), not
    only at the image's stamp. ``stamp_ns``: when it is broadcast (0: at the image's stamp)."""

    child: str
    matrix: np.ndarray
    held: bool
    stamp_ns: int = 0


def map_attachment(buffer: TransformBuffer, camera_to_map: np.ndarray, camera_frame: str, stamp_ns: int,
                   map_frame: str, odom_frame: str = 'odom') -> Attachment | str:
    """The transform from the map frame to the frame the map attaches to at the image's stamp
    (see the module): ``odom_frame`` where it is above the camera frame, else the root of
    the camera frame's tree; or why there is none (that frame has a parent already, or the
    chain has no transform near that moment). A link from ``map_frame`` is taken as the
    mapper's own broadcast."""
    above = [f for f in buffer._ancestors(camera_frame) if f != map_frame]      # the map's link is the mapper's
    child = odom_frame if odom_frame in above[1:] else above[-1]
    parent = buffer.parent(child)
    if parent is not None and parent != map_frame:
        return (f'{child} already has the parent {parent} on /tf (another node localizes it): the map is not '
                'broadcast')
    if child == camera_frame:
        return Attachment(camera_frame, np.asarray(camera_to_map, float), False)
    t_child_camera = buffer.lookup(child, camera_frame, stamp_ns)
    if t_child_camera is None:
        return (f'no transform {child} -> {camera_frame} at {stamp_ns * 1e-9:.3f} s on /tf yet '
                '(odometry late or stopped?)')
    matrix = np.asarray(camera_to_map, float) @ np.linalg.inv(t_child_camera)       # T_map_child
    return Attachment(child, matrix, not buffer.static_between(child, camera_frame))
