"""Benchmark: what each frame costs, stage by stage, on one core.

A handheld capture (320x240 at 10 Hz; plain and textured rooms, tuning seeds) is run through
the core stages the node graph runs, in one process, every frame:

- detection: ``depth_clusters`` on colour + depth (the simulator's gravity);
- tracking: matching the frame against the last keyframe (where the previous frame's pose
  and the gyroscope predict its boxes, else with the object matcher) and verifying the
  relative pose (the matcher does this for every frame);
- keyframe matching: a new keyframe against its candidates (recent + retrieved);
- map update: incremental pose averaging per new keyframe, logging the frame and composing
  its camera pose (the mapper does this for every frame);
- object map: rebuilding the tracks (the mapper does this at most every
  ``map_publish_period_s``, within ``map_max_cpu_share``).

Reported per stage: median per call, and mean per frame (amortised over all frames).

    ros_ws/env.sh python bench/bench_stages.py [--frames 100] [--seeds 40 41]
"""
import os

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import torch  # noqa: E402

from rfm_core.detection import make_detector  # noqa: E402
from rfm_core.mapping.mapper import Mapper  # noqa: E402
from rfm_core.observations import EdgeRecord
from rfm_core.matching.factory import make_matcher  # noqa: E402
from rfm_core.matching.view_graph import ViewGraphBuilder  # noqa: E402
from rfm_core.sim.capture import Capture, CaptureConfig  # noqa: E402


def run(config: CaptureConfig) -> dict:
    detector = make_detector('depth_clusters')
    graph = ViewGraphBuilder(matcher=make_matcher('learned'))
    mapper = Mapper(matcher=graph.matcher)
    calls = {k: [] for k in ('detection', 'tracking', 'keyframe matching', 'map update', 'object map')}
    frames = list(Capture(config).frames())
    for frame in frames:
        t0 = time.perf_counter()
        obs = detector.detect(frame.detector_input())
        calls['detection'].append(time.perf_counter() - t0)
        obs.imu_rotation, obs.imu_epoch = frame.rotation, 1        # the gyroscope's (here the true one)
        track_before, kf_before = graph.stats.tracking_s, graph.stats.keyframe_s
        keyframe, edges, track = graph.add(obs)
        calls['tracking'].append(graph.stats.tracking_s - track_before)
        if keyframe is not None:
            calls['keyframe matching'].append(graph.stats.keyframe_s - kf_before)
        t0 = time.perf_counter()
        if keyframe is not None:
            mapper.add_keyframe(keyframe.keyframe_id, keyframe.observations)
        for e in edges:                                # a keyframe's, or a revisit's
            mapper.add_edge(EdgeRecord.from_edge(e))
        if keyframe is not None or edges:
            mapper.update()
        if track is not None:
            mapper.add_frame(track)
            mapper.frame_pose(track)
        calls['map update'].append(time.perf_counter() - t0)
        if keyframe is not None and len(mapper.keyframes) % 10 == 0:
            t0 = time.perf_counter()
            mapper.tracks()
            calls['object map'].append(time.perf_counter() - t0)
    return {'calls': calls, 'frames': len(frames), 'keyframes': len(graph.keyframes)}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--frames', type=int, default=100)
    parser.add_argument('--seeds', type=int, nargs='+', default=[40, 41], help='tuning seeds (0-99)')
    args = parser.parse_args()
    torch.set_num_threads(1)
    print('# cost per frame by stage (one core; ms)')
    print('| scene | stage | median per call | calls | mean per frame |')
    print('|---|---|---|---|---|')
    for seed in args.seeds:
        style = 'plain' if seed % 2 == 0 else 'textured'
        r = run(CaptureConfig(seed=seed, room_style=style, capture='handheld', frames=args.frames, fps=10))
        name = f'{seed} {style}, {r["keyframes"]} keyframes / {r["frames"]} frames'
        for stage, times in r['calls'].items():
            if times:
                print(f'| {name} | {stage} | {1e3 * statistics.median(times):.1f} | {len(times)} | '
                      f'{1e3 * sum(times) / r["frames"]:.1f} |')


if __name__ == '__main__':
    main()
