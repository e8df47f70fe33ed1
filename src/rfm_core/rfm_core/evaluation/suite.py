"""`rfm eval`: the paper's localization and mapping tables over generated scenes.

Each scene is rendered once and every setting runs the same back end the nodes run
(detector -> view graph -> mapper, in-process: the nodes are thin wrappers around exactly
this code) on it. Settings follow the paper's rows that apply here:

========================  ==============================  =======  =====
setting                   detector                        poses    BA
========================  ==============================  =======  =====
RGB-D (depth_clusters)    depth_clusters                  un-posed
RGB-D posed               depth_clusters                  posed
GT rgbd                   ground_truth:rgbd               un-posed
GT rgbd posed             ground_truth:rgbd               posed
GT rgbd posed + BA        ground_truth:rgbd               posed    yes
GT rgb                    ground_truth:rgb                un-posed
GT rgb posed              ground_truth:rgb                posed
GT rgb posed + BA         ground_truth:rgb                posed    yes
========================  ==============================  =======  =====

The ``rgb`` preset is a monocular detector (``Detector.monocular``): its relative poses are
verified and refit along the viewing rays (``matching.config.monocular``), as the matcher
node does with ``range_error`` set.

Un-posed results are aligned to the ground truth without scale (yaw + translation: gravity
is shared). Scene seeds start at 5000, disjoint from training (3000+), tuning (0-99), the
detection suite (1000+) and the matching evaluation (2000+).
"""
from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

__all__ = ['SETTINGS', 'Setting', 'eval_configs', 'evaluate_scene', 'summarize', 'format_tables']


@dataclass(frozen=True)
class Setting:
    name: str
    detector: str
    posed: bool = False
    bundle_adjustment: bool = False


SETTINGS = (
    Setting('RGB-D (depth_clusters)', 'depth_clusters'),
    Setting('RGB-D posed (depth_clusters)', 'depth_clusters', posed=True),
    Setting('GT rgbd', 'ground_truth:rgbd'),
    Setting('GT rgbd posed', 'ground_truth:rgbd', posed=True),
    Setting('GT rgbd posed + BA', 'ground_truth:rgbd', posed=True, bundle_adjustment=True),
    Setting('GT rgb', 'ground_truth:rgb'),
    Setting('GT rgb posed', 'ground_truth:rgb', posed=True),
    Setting('GT rgb posed + BA', 'ground_truth:rgb', posed=True, bundle_adjustment=True),
)


def eval_configs(count: int = 20, first_seed: int = 5000, frames: int = 100, fps: float = 10.0):
    """Mixed scenes: plain / textured rooms, handheld / sparse captures."""
    from rfm_core.sim.capture import CaptureConfig  # noqa: PLC0415

    out = []
    for i in range(count):
        style = 'plain' if i % 2 == 0 else 'textured'
        capture = 'sparse' if i % 4 in (1, 2) else 'handheld'
        out.append(CaptureConfig(seed=first_seed + i, room_style=style, capture=capture, frames=frames, fps=fps))
    return out


def evaluate_scene(args) -> dict:
    """All settings on one scene (rendered once). Returns {setting: metrics}."""
    config, settings = args
    import torch  # noqa: PLC0415

    from rfm_core.evaluation.pipeline import run_capture  # noqa: PLC0415
    from rfm_core.matching.learned import make_matcher  # noqa: PLC0415
    from rfm_core.sim.capture import Capture  # noqa: PLC0415

    torch.set_num_threads(1)
    capture = Capture(config)
    frames = list(capture.frames())
    out = {}
    for s in settings:
        r = run_capture(config, s.detector, matcher=make_matcher('learned'), posed=s.posed,
                        bundle_adjustment=s.bundle_adjustment, capture=capture, frames=frames)
        out[s.name] = {**r.localization, **r.mapping,
                       'keyframes': r.keyframes, 'seconds': r.seconds}
    return {'scene': f'{config.seed}_{config.room_style}_{config.capture}', 'results': out}


def run_suite(configs, settings=SETTINGS, jobs: int = 1, progress=None) -> list:
    work = [(c, tuple(settings)) for c in configs]
    results = []
    if jobs > 1:
        with ProcessPoolExecutor(jobs) as pool:
            for i, r in enumerate(pool.map(evaluate_scene, work)):
                results.append(r)
                if progress:
                    progress(i + 1, len(work), r)
    else:
        for i, w in enumerate(work):
            results.append(evaluate_scene(w))
            if progress:
                progress(i + 1, len(work), results[-1])
    return results


def summarize(results, settings=SETTINGS) -> dict:
    """Per setting: ARE/ATE median (median over scenes of per-scene medians) and RMSE (over
    scenes), registered (mean), AP/AR (mean over scenes)."""
    out = {}
    for s in settings:
        rows = [r['results'][s.name] for r in results if s.name in r['results']]
        if not rows:
            continue
        def col(k):
            return np.array([row[k] for row in rows], float)
        out[s.name] = {
            'scenes': len(rows),
            'ARE_median': float(np.nanmedian(col('ARE_median'))), 'ARE_rmse': float(np.nanmean(col('ARE_rmse'))),
            'ATE_median': float(np.nanmedian(col('ATE_median'))), 'ATE_rmse': float(np.nanmean(col('ATE_rmse'))),
            'registered': float(np.mean(col('registered'))),
            **{k: float(np.nanmean(col(k))) for k in ('AP15', 'AR15', 'AP25', 'AR25')},
            'keyframes': float(np.mean(col('keyframes'))),
        }
    return out


def format_tables(summary: dict) -> str:
    lines = ['Localization (keyframes; medians over scenes of per-scene medians, RMSE averaged over scenes)', '',
             '| setting | ARE median (deg) | ATE median (cm) | ARE RMSE (deg) | ATE RMSE (cm) | registered |',
             '|---|---|---|---|---|---|']
    for name, m in summary.items():
        lines.append(f'| {name} | {m["ARE_median"]:.2f} | {100 * m["ATE_median"]:.1f} | {m["ARE_rmse"]:.2f} | '
                     f'{100 * m["ATE_rmse"]:.1f} | {100 * m["registered"]:.1f}% |')
    lines += ['', 'Mapping (scene-level AP/AR at 3D IoU 0.15 / 0.25, mean over scenes)', '',
              '| setting | AP15 | AR15 | AP25 | AR25 |', '|---|---|---|---|---|']
    for name, m in summary.items():
        lines.append(f'| {name} | {m["AP15"]:.3f} | {m["AR15"]:.3f} | {m["AP25"]:.3f} | {m["AR25"]:.3f} |')
    return '\n'.join(lines)


def relocalization_scene(args) -> dict:
    """Paper appendix: map one capture of a room, save the map, load it into a fresh
    mapper, and relocalize every frame of a second capture (another trajectory) of the
    same room. Returns per-scene relocalized share and median errors."""
    config, detector, query_frames = args
    import tempfile  # noqa: PLC0415
    from dataclasses import replace  # noqa: PLC0415
    from pathlib import Path  # noqa: PLC0415

    import torch  # noqa: PLC0415

    from rfm_core.evaluation.pipeline import relocalize_capture, run_capture  # noqa: PLC0415
    from rfm_core.evaluation.trajectory import map_to_truth  # noqa: PLC0415
    from rfm_core.mapping.map_io import load_map, save_map  # noqa: PLC0415
    from rfm_core.mapping.mapper import Mapper  # noqa: PLC0415
    from rfm_core.matching.learned import make_matcher  # noqa: PLC0415
    from rfm_core.sim.capture import Capture  # noqa: PLC0415

    torch.set_num_threads(1)
    mapped = run_capture(config, detector, matcher=make_matcher('learned'), noise_seed=3)
    mapper = Mapper(matcher=make_matcher('learned'))
    with tempfile.TemporaryDirectory() as tmp:
        load_map(mapper, save_map(mapped.mapper, Path(tmp) / 'map.rfm'))
    mapper.mode = 'localization'
    world = map_to_truth(mapper.camera_poses(), mapped.truth)
    second = Capture(replace(config, frames=query_frames, fps=2.0, capture='handheld', trajectory_seed=1))
    err = relocalize_capture(mapper, world, second, detector, noise_seed=11)
    return {'scene': f'{config.seed}_{config.room_style}_{config.capture}', **err,
            'map_registered': mapped.localization['registered']}
