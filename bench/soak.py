"""Soak: a long capture walking around one room again and again, replayed through the node
graph; does anything keep growing once the room is seen?

    ros_ws/env.sh python bench/soak.py [--minutes 60] [--fps 5] [--seed 7000] [--work /tmp/soak]
                                       [--param NODE.NAME:=VALUE ...]

Renders a handheld capture (the simulator's walk is a loop around the room at ~0.35 m/s,
so a long capture goes round many times; furniture made of parts, clutter), replays it with
`rfm run --processes` in real time and samples every 10 s: keyframes, registered keyframes,
objects, frames localized and the latest autosave's wall time (rfm/status; the mapper
autosaves every 10 new keyframes, culled ones included), and each node's resident memory
(VmRSS). Writes ``soak.json`` and ``soak.png`` (growth over time, loop boundaries marked)
to the work folder and prints the growth after the first loop of keyframes, objects,
memory and autosave time. `make soak` runs it with the defaults (an hour of camera time).
"""
from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

NODES = ('detector', 'matcher', 'mapper')


def _rss_mb(root: int) -> dict:
    """Resident memory (MB) of the rfm node processes under process ``root`` (the ``rfm run``
    this started: not another run's on the same machine), by node."""
    parents, cmds, rss = {}, {}, {}
    for proc in Path('/proc').iterdir():
        if not proc.name.isdigit():
            continue
        try:
            status = (proc / 'status').read_text()
            cmds[int(proc.name)] = (proc / 'cmdline').read_bytes().decode(errors='replace').split('\0')[:3]
        except OSError:
            continue
        fields = dict(line.split(':', 1) for line in status.splitlines() if ':' in line)
        parents[int(proc.name)] = int(fields.get('PPid', '0').split()[0])
        rss[int(proc.name)] = int(fields.get('VmRSS', '0 kB').split()[0]) / 1024

    def under_root(pid):
        while pid > 1:
            if pid == root:
                return True
            pid = parents.get(pid, 0)
        return False

    out = {}
    for pid, cmd in cmds.items():
        for node in NODES:                     # the executable, or the python running it
            if any(part.endswith(f'/lib/rfm_{node}_node/{node}') for part in cmd) and under_root(pid):
                out[node] = out.get(node, 0.0) + rss[pid]
    return out


def _loops(truth_poses: dict) -> tuple[float, list]:
    """Number of loops around the room and the times (s from the start) each one ends."""
    stamps = np.array(sorted(truth_poses))
    xy = np.array([truth_poses[s][:2, 3] for s in stamps])
    angle = np.unwrap(np.arctan2(*(xy - xy.mean(0)).T[::-1]))
    turned = np.abs(angle - angle[0]) / (2 * np.pi)
    ends = [float((stamps[np.argmax(turned >= k)] - stamps[0]) / 1e9) for k in range(1, int(turned.max()) + 1)]
    return float(turned.max()), ends


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--minutes', type=float, default=60.0, help='camera time (real-time replay)')
    parser.add_argument('--fps', type=float, default=5.0)
    parser.add_argument('--seed', type=int, default=7000)
    parser.add_argument('--work', type=Path, default=Path('/tmp/rfm_soak'))
    parser.add_argument('--param', nargs='+', default=[], help='passed to rfm run')
    args = parser.parse_args()
    import rclpy  # noqa: PLC0415
    from rfm_msgs.msg import MapperStatus  # noqa: PLC0415

    from rfm_core.evaluation.report import read_ground_truth  # noqa: PLC0415

    rfm = shutil.which('rfm')
    if rfm is None:
        raise SystemExit('soak: rfm is not on PATH: run through ros_ws/env.sh')
    args.work.mkdir(parents=True, exist_ok=True)
    bag = args.work / 'bag'
    frames = int(round(args.minutes * 60 * args.fps))
    if not (bag / 'metadata.yaml').is_file():
        subprocess.run([rfm, 'sim', str(bag), '--seed', str(args.seed), '--capture', 'handheld', '--frames',
                        str(frames), '--fps', str(args.fps), '--furniture', 'parts', '--clutter', '--force'],
                       check=True)
    loops, loop_ends = _loops(read_ground_truth(bag).camera_poses)
    os.environ['ROS_DOMAIN_ID'] = str(random.SystemRandom().randint(1, 101))
    run = subprocess.Popen([rfm, 'run', '--bag', str(bag), '--output', str(args.work / 'out'), '--force', '--quiet',
                            '--processes', *(['--param', *args.param] if args.param else [])])
    rclpy.init()
    node = rclpy.create_node('rfm_soak')
    latest = {}
    node.create_subscription(MapperStatus, 'rfm/status', lambda m: latest.update(status=m), 10)
    samples, start, last = [], None, 0.0
    try:
        while run.poll() is None:
            rclpy.spin_once(node, timeout_sec=0.2)
            s = latest.get('status')
            if s is None:
                continue
            now = time.monotonic()
            if start is None and s.num_frames > 0:
                start = now
            if start is not None and now - last >= 10.0:
                last = now
                samples.append({'t': now - start, 'keyframes': s.num_keyframes, 'registered': s.num_registered,
                                'objects': s.num_objects, 'frames': s.num_frames, 'saves': s.num_saves,
                                'save_s': s.save_seconds, 'rss_mb': _rss_mb(run.pid)})
                print(f"[soak] {samples[-1]['t']:6.0f} s  keyframes {s.num_keyframes:4d}  registered "
                      f"{s.num_registered:4d}  objects {s.num_objects:4d}  frames {s.num_frames:5d}  saves "
                      f"{s.num_saves:4d} (latest {1e3 * s.save_seconds:.0f} ms)  RSS "
                      + ' '.join(f'{k} {v:.0f} MB' for k, v in sorted(samples[-1]['rss_mb'].items())), flush=True)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        if run.poll() is None:
            run.terminate()
    summary = json.loads((args.work / 'out' / 'summary.json').read_text())
    after = [s for s in samples if loop_ends and s['t'] >= loop_ends[0]]
    growth = {}
    if after:
        # counts: the first sample after the first loop against the last; memory and autosave
        # time: the median of the first and of the last 10% of the samples after it
        first, end = after[0], samples[-1]
        growth = {k: (end[k] - first[k]) / max(first[k], 1) for k in ('keyframes', 'objects')}
        tenth = max(1, len(after) // 10)
        for key, value in (('rss_mb', lambda x: sum(x['rss_mb'].values())), ('save_s', lambda x: x['save_s'])):
            early, late = (float(np.median([value(x) for x in part])) for part in (after[:tenth], after[-tenth:]))
            growth[key] = (late - early) / max(early, 1e-9)
            growth[key + '_first_last'] = (early, late)
    result = {'minutes': args.minutes, 'fps': args.fps, 'seed': args.seed, 'loops': loops, 'loop_ends_s': loop_ends,
              'samples': samples, 'growth_after_first_loop': growth, 'summary': summary, 'params': args.param}
    (args.work / 'soak.json').write_text(json.dumps(result, indent=1, default=float))
    _plot(args.work / 'soak.png', samples, loop_ends, summary)
    acc = summary.get('accuracy') or {}
    loc = acc.get('localization', {})
    print(f"[soak] {loops:.1f} loops; after the first: keyframes {100 * growth.get('keyframes', 0):+.0f}%, objects "
          f"{100 * growth.get('objects', 0):+.0f}%, memory of the three nodes "
          f"{100 * growth.get('rss_mb', 0):+.0f}% ({'%.0f -> %.0f MB' % growth.get('rss_mb_first_last', (0, 0))}), "
          f"autosave time {100 * growth.get('save_s', 0):+.0f}% "
          f"({'%.3f -> %.3f s' % growth.get('save_s_first_last', (0, 0))}); "
          f"final {summary['keyframes']} keyframes ({summary['registered']} "
          f"registered), {summary['objects']} objects; ARE {loc.get('ARE_median', float('nan')):.2f} deg, ATE "
          f"{100 * loc.get('ATE_median', float('nan')):.1f} cm, {100 * loc.get('registered', 0):.0f}% localized; "
          f"{args.work / 'soak.png'}")
    return 0


def _plot(path: Path, samples: list, loop_ends: list, summary: dict) -> None:
    import matplotlib  # noqa: PLC0415
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # noqa: PLC0415
    t = [s['t'] for s in samples]
    fig, (ax, mem, save) = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
    for key in ('keyframes', 'registered', 'objects'):
        ax.plot(t, [s[key] for s in samples], label=key)
    ax.set_ylabel('count')
    ax.legend()
    for node in NODES:
        mem.plot(t, [s['rss_mb'].get(node, np.nan) for s in samples], label=node)
    mem.set_ylabel('resident memory (MB)')
    mem.legend()
    save.plot(t, [1e3 * s['save_s'] for s in samples], label='latest autosave')
    save.set_ylabel('autosave wall time (ms)')
    save.set_xlabel('time since the first frame (s)')
    save.legend()
    marked = loop_ends if len(loop_ends) <= 30 else loop_ends[:1]       # many loops: the first one's end
    for a in (ax, mem, save):
        for end in marked:
            a.axvline(end, color='grey', lw=0.5)
    ax.set_title(f"soak: {len(loop_ends)} loops ({'grey' if len(marked) > 1 else 'grey: the first one ends'}), "
                 f"{summary.get('frames', 0)} frames")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


if __name__ == '__main__':
    sys.exit(main())
