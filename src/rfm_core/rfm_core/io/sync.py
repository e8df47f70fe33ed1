"""Approximate-time synchronisation of 2-4 message streams, without message_filters.

Each input keeps a bounded queue of (stamp, message). When a message arrives, the
synchroniser looks for one message per other input within ``slop`` of it and emits the
combination with the smallest spread (max stamp - min stamp). Emitted messages and every
older message in each queue are dropped: a later set can only be newer. Messages that fall
out of a full queue, or are passed over, are counted as dropped.
"""
from __future__ import annotations

import itertools
import threading
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

__all__ = ['ApproximateTimeSynchronizer', 'SyncStats']


@dataclass
class SyncStats:
    received: int = 0   #: messages added
    emitted: int = 0    #: synchronised sets emitted
    dropped: int = 0    #: messages discarded without being part of a set
    out_of_order: int = 0  #: messages older than the last emitted set (discarded)


class ApproximateTimeSynchronizer:
    """Match messages of ``num_inputs`` streams whose stamps (ns) are within ``slop_ns``.

    ``callback(*messages)`` is called with one message per input, in input order, from the
    thread that called :meth:`add`. Thread-safe.
    """

    #: Candidates per input tried when searching the best set (keeps the search bounded).
    MAX_CANDIDATES = 8

    def __init__(self, num_inputs: int, slop_ns: int, queue_size: int = 10,
                 callback: Callable[..., Any] | None = None):
        if not 2 <= num_inputs <= 4:
            raise ValueError(f'num_inputs must be 2..4, got {num_inputs}')
        if slop_ns < 0:
            raise ValueError(f'slop must be >= 0, got {slop_ns} ns')
        if queue_size < 1:
            raise ValueError(f'queue_size must be >= 1, got {queue_size}')
        self.num_inputs = num_inputs
        self.slop_ns = int(slop_ns)
        self.queue_size = int(queue_size)
        self.callback = callback
        self.stats = SyncStats()
        self._queues = [deque() for _ in range(num_inputs)]
        self._last_emitted = [None] * num_inputs
        self._lock = threading.Lock()

    def add(self, index: int, stamp_ns: int, msg) -> tuple | None:
        """Add ``msg`` with stamp ``stamp_ns`` to input ``index``; return the set emitted, if any."""
        if not 0 <= index < self.num_inputs:
            raise IndexError(f'input index {index} out of range 0..{self.num_inputs - 1}')
        stamp_ns = int(stamp_ns)
        with self._lock:
            self.stats.received += 1
            last = self._last_emitted[index]
            if last is not None and stamp_ns <= last:
                self.stats.out_of_order += 1
                self.stats.dropped += 1
                return None
            queue = self._queues[index]
            queue.append((stamp_ns, msg))
            if len(queue) > 1 and queue[-2][0] > stamp_ns:
                items = sorted(queue, key=lambda item: item[0])
                queue.clear()
                queue.extend(items)
            while len(queue) > self.queue_size:
                queue.popleft()
                self.stats.dropped += 1
            matched = self._match(index, stamp_ns)
            if matched is None:
                return None
            msgs = tuple(self._pop_until(i, s) for i, s in enumerate(matched))
            self.stats.emitted += 1
        if self.callback is not None:
            self.callback(*msgs)
        return msgs

    def _match(self, index: int, stamp_ns: int):
        candidates = []
        for i, queue in enumerate(self._queues):
            if i == index:
                candidates.append([stamp_ns])
                continue
            near = [s for s, _ in queue if abs(s - stamp_ns) <= self.slop_ns]
            if not near:
                return None
            near.sort(key=lambda s: abs(s - stamp_ns))
            candidates.append(near[:self.MAX_CANDIDATES])
        best, best_spread = None, None
        for combo in itertools.product(*candidates):
            spread = max(combo) - min(combo)
            if spread <= self.slop_ns and (best_spread is None or spread < best_spread):
                best, best_spread = combo, spread
        return best

    def _pop_until(self, index: int, stamp_ns: int):
        """Remove and return the matched message of input ``index``, dropping older ones."""
        queue = self._queues[index]
        while queue[0][0] < stamp_ns:
            queue.popleft()
            self.stats.dropped += 1
        self._last_emitted[index] = stamp_ns
        return queue.popleft()[1]

    def reset(self) -> None:
        """Forget all queued messages (e.g. after a time jump when a bag loops)."""
        with self._lock:
            for queue in self._queues:
                queue.clear()
            self._last_emitted = [None] * self.num_inputs
