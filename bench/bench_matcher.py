"""Benchmark: matcher cost per keyframe as the view graph grows, and per-pair latency.

A simulated detection stream (ground_truth:rgbd detections of one room) is replayed into a
ViewGraphBuilder that already holds 10, 100 or 1000 keyframes (copies of the room's
keyframes, so retrieval has real candidates). Reported: median time to process one new
keyframe (matching against the last keyframe, retrieval, matching and verifying the
candidates; classical matcher), the median time of one pair (match + relative pose)
for the classical and the learned matcher, and the learned matcher's time per pair when a
frame is matched against 7 candidates in one batch (``match_many``, what a new keyframe
does) against one pair at a time, in the same run.

    ros_ws/env.sh python bench/bench_matcher.py
"""
import os

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'

import statistics  # noqa: E402
import time  # noqa: E402

from rfm_core.detection import make_detector  # noqa: E402
from rfm_core.matching.classical import ClassicalMatcher  # noqa: E402
from rfm_core.matching.learned import LearnedMatcher  # noqa: E402
from rfm_core.matching.relative_pose import estimate_relative_pose  # noqa: E402
from rfm_core.matching.view_graph import Keyframe, ViewGraphBuilder, bag_of_objects  # noqa: E402
from rfm_core.sim.capture import Capture, CaptureConfig  # noqa: E402


def main():
    frames = list(Capture(CaptureConfig(seed=300, frames=60, fps=4)).frames())
    det = make_detector('ground_truth', preset='rgbd', seed=0)
    stream = [det.perturb(f.ground_truth) for f in frames]
    print('# matcher cost per new keyframe vs keyframes already in the graph (one core)')
    print('| keyframes in graph | per keyframe (ms) | pairs tested per keyframe |')
    print('|---|---|---|')
    for size in (10, 100, 1000):
        graph = ViewGraphBuilder()
        for i in range(size):                       # pre-fill with keyframes of the room
            obs = stream[i % len(stream)]
            graph.add_keyframe(Keyframe(graph.next_id, obs, bag_of_objects(obs)), [])
            graph.next_id += 1
        times, pairs = [], []
        for obs in stream:
            before = graph.stats.pairs_tested
            start = time.perf_counter()
            kf, _, _ = graph.add(obs)
            if kf is not None:
                times.append(time.perf_counter() - start)
                pairs.append(graph.stats.pairs_tested - before)
        print(f'| {size} | {1e3 * statistics.median(times):.1f} | {statistics.median(pairs):.0f} |')
    print(f'\nper pair ({statistics.median(len(s) for s in stream):.0f} detections per frame, one thread):')
    print('| matcher | match (ms) | match + relative pose (ms) |')
    print('|---|---|---|')
    for name, matcher in (('classical', ClassicalMatcher()), ('learned', LearnedMatcher())):
        matcher.match(stream[1], stream[0])                      # load weights, warm up
        match_times, pair_times = [], []
        for a, b in zip(stream[:-1], stream[1:]):
            start = time.perf_counter()
            m = matcher.match(b, a)
            mid = time.perf_counter()
            estimate_relative_pose(b.boxes, a.boxes, m)
            match_times.append(mid - start)
            pair_times.append(time.perf_counter() - start)
        print(f'| {name} | {1e3 * statistics.median(match_times):.1f} | {1e3 * statistics.median(pair_times):.1f} |')
    learned = LearnedMatcher()
    single, batched = [], []
    for i in range(8, len(stream)):
        query, candidates = stream[i], stream[i - 8:i - 1]
        start = time.perf_counter()
        for c in candidates:
            learned.match(query, c)
        mid = time.perf_counter()
        learned.match_many(query, candidates)
        single.append((mid - start) / len(candidates))
        batched.append((time.perf_counter() - mid) / len(candidates))
    print(f'\nlearned match per pair, a frame against 7 candidates: one at a time '
          f'{1e3 * statistics.median(single):.1f} ms, batched {1e3 * statistics.median(batched):.1f} ms '
          f'({statistics.median(single) / statistics.median(batched):.1f}x)')


if __name__ == '__main__':
    main()
