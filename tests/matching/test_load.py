"""The matcher under load: it thins a stream it cannot keep up with evenly, never skips a
frame with detections, and counts what the transport lost."""
import numpy as np

from rfm_core.matching.load import UNKNOWN_SEQUENCE, FrameShedder


def _simulate(shedder, cost_s: float, fps: float = 30.0, seconds: float = 20.0, detections_every: int = 10):
    """A stream at ``fps`` into a matcher that takes ``cost_s`` per frame it processes (and
    nothing for one it skips): the stamps processed and each frame's wait in the queue."""
    clock, processed, waits = 0.0, [], []
    for i in range(int(fps * seconds)):
        arrival = i / fps
        clock = max(clock, arrival)               # the matcher is idle until the frame arrives
        waited = clock - arrival
        waits.append(waited)
        detections = 3 if i % detections_every == 0 else 0
        if shedder.admit(int(arrival * 1e9), waited, detections, sequence=i + 1):
            processed.append((arrival, detections))
            clock += cost_s
    return processed, np.array(waits)


def test_a_matcher_that_keeps_up_skips_nothing():
    shedder = FrameShedder(shed_after_s=0.5, max_gap_s=0.2)
    processed, waits = _simulate(shedder, cost_s=0.02)
    assert len(processed) == 600 and shedder.counts == dict(received=600, processed=600, shed=0, lost=0)
    assert waits.max() == 0.0


def test_an_overloaded_matcher_thins_the_stream_evenly_and_stays_close_behind():
    shedder = FrameShedder(shed_after_s=0.5, max_gap_s=0.2)
    processed, waits = _simulate(shedder, cost_s=0.06)            # half the rate it is sent
    stamps = np.array([t for t, _ in processed])
    assert 0.3 < shedder.counts['shed'] / shedder.counts['received'] < 0.7
    assert np.diff(stamps).max() <= 0.2 + 1 / 30 + 1e-9         # the stream never breaks
    assert waits.max() < 1.2                                      # it settles behind by at most ~2 x 0.5 s
    # every frame with detections is processed
    assert sum(d > 0 for _, d in processed) == 60
    # without shedding the wait grows without bound (the transport would drop bursts)
    _, unbounded = _simulate(FrameShedder(shed_after_s=0.0, max_gap_s=0.2), cost_s=0.06)
    assert unbounded.max() > 9.0


def test_lost_messages_are_counted_from_sequence_numbers():
    shedder = FrameShedder(shed_after_s=0.5, max_gap_s=0.2)
    for i, seq in enumerate([1, 2, 5, 6, UNKNOWN_SEQUENCE, 7, None, 10]):
        assert shedder.admit(i * 33_000_000, 0.0, 2, seq)
    assert shedder.counts['lost'] == 2 + 2 and shedder.counts['processed'] == 8
