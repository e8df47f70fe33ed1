"""rfm_core.io.sync: approximate-time synchronisation of 2-4 streams."""
import threading

import pytest

from rfm_core.io.sync import ApproximateTimeSynchronizer

MS = 1_000_000


def test_pairs_nearest_messages_within_slop():
    got = []
    sync = ApproximateTimeSynchronizer(2, slop_ns=10 * MS, callback=lambda a, b: got.append((a, b)))
    # camera at 30 Hz, depth offset by 4 ms
    for k in range(10):
        sync.add(0, k * 33 * MS, f'rgb{k}')
        sync.add(1, k * 33 * MS + 4 * MS, f'depth{k}')
    assert got == [(f'rgb{k}', f'depth{k}') for k in range(10)]
    assert sync.stats.emitted == 10 and sync.stats.dropped == 0


def test_three_streams_and_unmatched_messages_are_dropped():
    sync = ApproximateTimeSynchronizer(3, slop_ns=5 * MS, queue_size=5)
    out = []
    for k in range(6):
        t = k * 100 * MS
        out.append(sync.add(0, t, ('a', k)))
        if k != 2:                                  # stream b misses frame 2
            out.append(sync.add(1, t + 2 * MS, ('b', k)))
        out.append(sync.add(2, t - 1 * MS, ('c', k)))
    sets = [s for s in out if s is not None]
    assert [s[0][1] for s in sets] == [0, 1, 3, 4, 5]
    assert all(s[0][1] == s[1][1] == s[2][1] for s in sets)
    assert sync.stats.dropped == 2                  # a2 and c2 are passed over


def test_messages_beyond_slop_do_not_match():
    sync = ApproximateTimeSynchronizer(2, slop_ns=5 * MS)
    assert sync.add(0, 0, 'a') is None
    assert sync.add(1, 20 * MS, 'b') is None
    assert sync.stats.emitted == 0


def test_picks_the_tightest_set():
    sync = ApproximateTimeSynchronizer(2, slop_ns=50 * MS)
    sync.add(1, 0, 'b0')
    sync.add(1, 30 * MS, 'b1')
    assert sync.add(0, 28 * MS, 'a') == ('a', 'b1')
    assert sync.stats.dropped == 1                  # b0 is older than the emitted set


def test_out_of_order_and_queue_overflow():
    sync = ApproximateTimeSynchronizer(2, slop_ns=1 * MS, queue_size=3)
    for k in range(5):
        sync.add(0, k * 100 * MS, k)                 # only stream 0: queue keeps the newest 3
    assert sync.stats.dropped == 2
    assert sync.add(1, 400 * MS, 'x') == (4, 'x')
    assert sync.add(0, 300 * MS, 'late') is None     # older than the emitted set
    assert sync.stats.out_of_order == 1
    sync.reset()
    assert sync.add(0, 0, 'again') is None           # accepted again after a reset
    assert sync.stats.out_of_order == 1


def test_bad_arguments():
    with pytest.raises(ValueError):
        ApproximateTimeSynchronizer(5, slop_ns=1)
    with pytest.raises(ValueError):
        ApproximateTimeSynchronizer(2, slop_ns=-1)
    with pytest.raises(IndexError):
        ApproximateTimeSynchronizer(2, slop_ns=1).add(2, 0, None)


def test_thread_safe_under_concurrent_producers():
    got = []
    sync = ApproximateTimeSynchronizer(2, slop_ns=2 * MS, queue_size=1000,
                                       callback=lambda a, b: got.append((a, b)))

    def produce(index):
        for k in range(500):
            sync.add(index, k * 10 * MS + index * MS, k)

    threads = [threading.Thread(target=produce, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(a == b for a, b in got)
    assert len(got) >= 250                          # interleaving may skip some, never mismatch
