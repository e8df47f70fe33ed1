"""The matcher under load: which frames it skips when it falls behind, and what it lost.

A frame waits in the matcher's queue while the matcher works on earlier ones. When the
matcher is slower than the camera (a 30 Hz stream on a busy machine), the queue fills and
the transport drops the oldest frames, a burst at a time: a gap longer than
``motion.max_frame_gap_s`` breaks the stream (no motion prior across it; tracking starts
again from a new keyframe that nothing may link to the map). :class:`FrameShedder` thins
the stream itself before that happens, evenly: once a frame has waited more than
``shed_after_s``, frames with depth points only (no detections: they only track the camera
between frames that have them) are skipped when they follow the last frame processed by
less than an interval that grows with the wait, from 0 at ``shed_after_s`` to
``max_gap_s`` at twice that. The matcher then settles at the rate it can keep up with, a
wait between the two, and the frames it processes are never further apart than
``max_gap_s`` for it. Frames with detections are never skipped. It also counts the frames
the transport lost before they reached the matcher, from the publisher's sequence numbers.
No ROS here.
"""
from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ['FrameShedder']

UNKNOWN_SEQUENCE = 2 ** 64 - 1          #: rmw's "sequence numbers unsupported"


@dataclass
class FrameShedder:
    shed_after_s: float                 #: frames may be skipped once one has waited longer than this (0: never)
    max_gap_s: float                    #: ... at most this long after the last frame processed
    counts: dict = field(default_factory=lambda: dict(received=0, processed=0, shed=0, lost=0))
    _last_processed_ns: int | None = None
    _last_sequence: int | None = None

    def admit(self, stamp_ns: int, waited_s: float, detections: int, sequence: int | None = None) -> bool:
        """Whether to process a frame stamped ``stamp_ns`` that waited ``waited_s`` in the
        queue and holds ``detections`` detections; ``sequence``: its publisher's sequence
        number (gaps count as lost frames; None or unsupported: not counted)."""
        self.counts['received'] += 1
        if sequence is not None and sequence != UNKNOWN_SEQUENCE:
            if self._last_sequence is not None and sequence > self._last_sequence + 1:
                self.counts['lost'] += sequence - self._last_sequence - 1
            self._last_sequence = sequence
        last = self._last_processed_ns
        behind = (waited_s - self.shed_after_s) / self.shed_after_s if self.shed_after_s > 0 else 0.0
        interval = self.max_gap_s * min(behind, 1.0)
        if detections == 0 and behind > 0 and last is not None and 0 <= stamp_ns - last < interval * 1e9:
            self.counts['shed'] += 1
            return False
        self.counts['processed'] += 1
        self._last_processed_ns = stamp_ns if last is None else max(last, stamp_ns)
        return True
