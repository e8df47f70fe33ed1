"""Benchmark: how many of a bag's frames the node graph keeps up with, where the CPU goes, and
the memory each node needs.

Replays one bag through `rfm run` several times for each variant (``NAME=--param settings``,
runs alternating so machine load falls on all alike) and reports medians: frames processed
and localized (of all the bag's colour frames), ARE/ATE when the bag has ground truth, and
the CPU seconds of each node's process (with --no-processes: of each thread, the detector's
worker and each node's executor; in one process the nodes share one interpreter lock, so
these say what the frames wait for), and each node's peak resident memory (VmHWM).

    ros_ws/env.sh python bench/bench_graph.py --bag bags/demo --runs 5 \\
        --variant "default=" --variant "IMU per sample=detector.imu_poll_period_s:=0" [--no-processes]
"""
import argparse
import json
import os
import random
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path


def run_once(bag: str, params: list, processes: bool, work: Path) -> dict:
    out = work / 'out'
    cmd = ['rfm', 'run', '--bag', bag, '--output', str(out), '--force', '--quiet']
    cmd += ['--processes' if processes else '--no-processes']
    cmd += ['--param', *params] if params else []
    env = dict(os.environ, ROS_DOMAIN_ID=str(random.randint(100, 200)))
    subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return json.loads((out / 'summary.json').read_text())


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--bag', default='bags/demo')
    parser.add_argument('--runs', type=int, default=3, help='runs per variant')
    parser.add_argument('--variant', action='append', metavar='NAME=PARAMS',
                        help="a name and the --param settings of rfm run (space separated; none: '')")
    parser.add_argument('--processes', action=argparse.BooleanOptionalAction, default=True,
                        help="rfm run's nodes as processes (its default) or, --no-processes, in one process")
    args = parser.parse_args()
    variants = [v.partition('=') for v in args.variant or ['default=']]
    variants = [(name, params.split()) for name, _, params in variants]
    results = {name: [] for name, _ in variants}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.runs):
            for name, params in variants:
                summary = run_once(args.bag, params, args.processes, Path(tmp))
                results[name].append(summary)
                loc = (summary.get('accuracy') or {}).get('localization', {})
                print(f'# run {i + 1} {name}: {summary["frames"]} processed, {summary["localized"]} localized, '
                      f'ATE {100 * loc.get("ATE_median", float("nan")):.1f} cm', file=sys.stderr)
    frames = results[variants[0][0]][0]['input_frames'] or 1
    mode = '--processes' if args.processes else 'one process'
    print(f'# {args.bag}, {frames} colour frames, {mode}, {args.runs} runs per variant (median [min-max])')
    print('| variant | frames processed | frames localized | ARE (deg) | ATE (cm) '
          '| CPU s per process or thread (median) | peak memory MB (median) |')
    print('|---|---|---|---|---|---|---|')

    def spread(values, fmt='{:.0f}'):
        values = [v for v in values if v == v]
        if not values:
            return '-'
        return f'{fmt.format(statistics.median(values))} [{fmt.format(min(values))}-{fmt.format(max(values))}]'

    for name, _ in variants:
        runs = results[name]
        loc = [(s.get('accuracy') or {}).get('localization', {}) for s in runs]
        threads = sorted({t for s in runs for t in s.get('cpu_s_by_thread', {})})
        cpu = ', '.join(f'{t} {statistics.median(s["cpu_s_by_thread"].get(t, 0.0) for s in runs):.2f}'
                        for t in threads) or '-'
        nodes = sorted({n for s in runs for n in s.get('peak_memory_mb', {})})
        memory = {n: statistics.median(s['peak_memory_mb'].get(n, 0.0) for s in runs) for n in nodes}
        memory = ', '.join([f'{n} {v:.0f}' for n, v in memory.items()]
                           + ([f'all {sum(memory.values()):.0f}'] if len(memory) > 1 else [])) or '-'
        print(f'| {name} | {spread([100 * s["frames"] / frames for s in runs])}% '
              f'| {spread([100 * s["localized"] / frames for s in runs])}% '
              f'| {spread([lc.get("ARE_median", float("nan")) for lc in loc], "{:.2f}")} '
              f'| {spread([100 * lc.get("ATE_median", float("nan")) for lc in loc], "{:.1f}")} | {cpu} | {memory} |')


if __name__ == '__main__':
    main()
