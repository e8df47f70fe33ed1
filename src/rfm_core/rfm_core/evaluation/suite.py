"""`rfm eval`: the paper's localization and mapping tables over generated scenes.

By default every scene is measured as a user runs rfm: the scene is written as a bag and
replayed in real time through the node graph (``rfm run``: the IMU's gravity, frames dropped
when the detector is busy, the capture type unknown to the graph), and scored from the run's
outputs against the bag's ground truth, every frame of the input counted. ``--jobs`` runs
scenes in parallel, each graph in its own ROS domain. The in-process path (``offline``:
every frame detected, the simulator's gravity, no ROS) stays for ablations.

Settings follow the paper's rows that apply here:

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

import json
import os
import queue
import random
import shutil
import subprocess
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rfm_core.evaluation.mapping import OBJECT_KINDS
from rfm_core.processes import die_with_parent

__all__ = ['SETTINGS', 'Setting', 'WORLDS', 'scene_kind', 'eval_configs', 'seed_config', 'scene_info', 'select_settings', 'evaluate_scene', 'evaluate_scene_graph', 'run_suite',
           'run_graph_suite', 'summarize', 'format_tables', 'QUERY_CAPTURES', 'RELOC_PROTOCOLS', 'query_capture',
           'query_folders', 'relocalization_scene_graph', 'relocalization_scene', 'relocalization_scores',
           'session_scores']


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


def select_settings(keys=None) -> list:
    """The settings named by ``keys`` (all when empty), in SETTINGS order: a key equal to a
    setting's name (case-insensitive) picks that setting alone, any other key every setting
    whose name contains it ('rgbd': the three ground_truth:rgbd rows)."""
    def chosen(key):
        exact = [s for s in SETTINGS if s.name.lower() == key.lower()]
        return exact or [s for s in SETTINGS if key.lower() in s.name.lower()]
    picked = {s.name for k in keys or () for s in chosen(k)}
    return [s for s in SETTINGS if not keys or s.name in picked]


def scene_kind(i: int) -> tuple[str, str]:
    """(room style, capture) of a suite's i-th scene: plain / textured rooms alternate, and
    every other pair of scenes is a sparse capture, so each style gets both captures."""
    return ('plain' if i % 2 == 0 else 'textured'), ('sparse' if i % 4 in (1, 2) else 'handheld')


WORLDS = ('realistic', 'boxes')


def eval_configs(count: int = 20, first_seed: int = 5000, frames: int = 100, fps: float = 10.0,
                 world: str = 'realistic', capture: str | None = None):
    """Mixed scenes: plain / textured rooms, handheld / sparse captures (:func:`scene_kind`).

    ``world='boxes'``: every object a solid box, mild sensor noise, ``frames`` at ``fps``
    (the suite before the realistic world). ``world='realistic'`` (the default): furniture
    made of parts and clutter; every other pair of scenes seen through the ``realsense``
    sensor model; every fourth handheld slot a robot's low, level camera; per scene (drawn
    from its seed) a frame rate of 5, 15 or 30 Hz for ``frames / fps`` seconds (10 s by
    default), 640x480 one time in four (else 320x240; a robot's camera: 10, 15 or 30 Hz,
    640x480 one time in two), a horizontal field of view of 60-90 deg, a handheld camera
    1.0-1.8 m high; sparse captures are ``frames / 2`` photos
    1.5-5 s apart. ``capture``: every scene captured this way instead (``'handheld'``: the
    relocalization protocol's walk around each room, ``frames / fps`` seconds at the scene's
    rate; the rooms and the scenes' other draws are the suite's).
    """
    from rfm_core.sim.capture import CaptureConfig  # noqa: PLC0415
    from rfm_core.sim.render import NoiseModel  # noqa: PLC0415

    if world not in WORLDS:
        raise ValueError(f'world must be one of {WORLDS}, got {world!r}')
    out = []
    for i, (style, kind) in enumerate(map(scene_kind, range(count))):
        seed = first_seed + i
        if world == 'boxes':
            out.append(CaptureConfig(seed=seed, room_style=style, capture=capture or kind, frames=frames, fps=fps))
            continue
        rng = np.random.default_rng([seed, 99])
        rate = float(rng.choice([5.0, 15.0, 30.0]))
        width, height = (640, 480) if rng.random() < 0.25 else (320, 240)
        hfov = float(rng.uniform(60.0, 90.0))
        eye = float(rng.uniform(1.0, 1.8))
        if kind == 'handheld' and i % 8 == 4:
            kind = 'robot'
        kind = capture or kind
        if kind == 'robot':                  # a robot's camera: 10-30 Hz, 640x480 one time in two
            robot = np.random.default_rng([seed, 98])
            rate = float(robot.choice([10.0, 15.0, 30.0]))
            width, height = (640, 480) if robot.random() < 0.5 else (320, 240)
        options = dict(seed=seed, room_style=style, capture=kind, width=width, height=height, hfov_deg=hfov,
                       furniture='parts', clutter=True,
                       noise=NoiseModel.realsense() if (i // 2) % 2 else NoiseModel())
        if kind == 'sparse':
            options.update(frames=max(frames // 2, 2), sparse_gap_s=(1.5, 5.0))
        else:
            options.update(frames=max(int(round(frames / fps * rate)), 2), fps=rate,
                           camera_height=(eye - 0.05, eye + 0.05) if kind == 'handheld' else ())
        out.append(CaptureConfig(**options))
    return out


def seed_config(seed: int, world: str = 'realistic'):
    """The configuration a seed gets in a suite that starts at a multiple of 8 (every kind of
    scene of :func:`eval_configs` occurs in each block of eight): scenes of the suite's
    distribution for seeds outside it (training)."""
    return eval_configs(seed % 8 + 1, first_seed=seed - seed % 8, world=world)[-1]


def scene_info(config) -> dict:
    """What kind of scene a configuration is, for the evaluation's breakdowns."""
    return {'capture': config.capture, 'sensor': 'realsense' if config.noise.projector_baseline_m > 0 else 'default',
            'furniture': config.furniture, 'fps': config.fps if config.capture != 'sparse' else None,
            'size': f'{config.width}x{config.height}'}


def evaluate_scene(args) -> dict:
    """All settings on one scene (rendered once). Returns {setting: metrics}."""
    config, settings = args
    import torch  # noqa: PLC0415

    from rfm_core.evaluation.pipeline import run_capture  # noqa: PLC0415
    from rfm_core.matching.factory import make_matcher  # noqa: PLC0415
    from rfm_core.sim.capture import Capture  # noqa: PLC0415

    torch.set_num_threads(1)
    capture = Capture(config)
    frames = list(capture.frames())
    out = {}
    for s in settings:
        r = run_capture(config, s.detector, matcher=make_matcher('learned'), posed=s.posed,
                        bundle_adjustment=s.bundle_adjustment, capture=capture, frames=frames)
        out[s.name] = {**r.localization, **r.mapping, **kind_counts(r.mapping), 'keyframes': r.keyframes,
                       'processed': 1.0, 'seconds': r.seconds}
    return {'scene': scene_name(config), **scene_info(config), 'results': out}


def _slug(text: str) -> str:
    return ''.join(c if c.isalnum() else '_' for c in text.lower()).strip('_')


def run_args(setting: Setting) -> list:
    """``rfm run`` arguments of a setting."""
    backend, _, preset = setting.detector.partition(':')
    args = ['--backend', backend] + (['--preset', preset] if preset else [])
    if setting.posed:
        args.append('--posed')
    if setting.bundle_adjustment:
        args += ['--param', 'mapper.bundle_adjustment:=true']
    return args


def scene_name(config) -> str:
    return f'{config.seed}_{config.room_style}_{config.capture}'


def scene_metrics(summary: dict) -> dict:
    """One run's ``summary.json`` -> the metrics :func:`summarize` averages."""
    acc = summary.get('accuracy') or {}
    loc, mapping = acc.get('localization', {}), acc.get('mapping', {})
    tf = loc.get('tf') or {}                   # as a tf2 lookup gives the camera at every image
    nan = float('nan')
    out = {k: loc.get(k, nan) for k in ('ARE_median', 'ARE_rmse', 'ATE_median', 'ATE_rmse',
                                        'keyframe_ARE_median', 'keyframe_ATE_median')}
    out.update(registered=loc.get('registered', 0.0), keyframe_registered=loc.get('keyframe_registered', 0.0),
               frames=loc.get('frames', summary.get('input_frames') or 0), gross=loc.get('gross', 0),
               published=loc.get('published', 0), published_gross=loc.get('published_gross', 0),
               within_2sigma=loc.get('within_2sigma', nan),
               tf_registered=tf.get('registered', nan), tf_gross=tf.get('gross', 0),
               tf_ARE_median=tf.get('ARE_median', nan), tf_ATE_median=tf.get('ATE_median', nan),
               keyframes=summary.get('keyframes', 0),
               processed=summary.get('frames', 0) / max(summary.get('input_frames') or 1, 1),
               realtime=summary.get('realtime', nan),
               objects=mapping.get('objects', summary.get('objects', 0)), ground_truth=mapping.get('ground_truth', 0),
               **{k: mapping.get(k, nan) for k in ('AP15', 'AR15', 'AP25', 'AR25')})
    out.update(kind_counts(mapping))
    return out


def kind_counts(mapping: dict) -> dict:
    """``objects_<kind>``: how many map objects :func:`rfm_core.evaluation.mapping.object_kinds`
    put in each kind (NaN when the mapping was not scored), and the label counts of
    :func:`rfm_core.evaluation.mapping.label_scores` (``labelled``, ``labels_right``,
    ``label_classes``), as :func:`summarize` pools them."""
    kinds = mapping.get('kinds') or {}
    labels = mapping.get('labels') or {}
    return {**{f'objects_{k}': kinds.get(k, float('nan')) for k in OBJECT_KINDS},
            'labelled': labels.get('labelled', 0), 'labels_right': labels.get('right', 0),
            'label_classes': labels.get('classes', {})}


def label_precision(rows) -> dict:
    """{class: (labelled, right)} pooled over scenes' ``label_classes``, most labelled first."""
    pooled = {}
    for row in rows:
        for name, (labelled, right) in (row.get('label_classes') or {}).items():
            a, b = pooled.get(name, (0, 0))
            pooled[name] = (a + labelled, b + right)
    return dict(sorted(pooled.items(), key=lambda kv: (-kv[1][0], kv[0])))


def _written_bag(config, bag: Path) -> Path:
    """``bag``, written from the capture ``config`` unless a complete one is there."""
    from rfm_core.sim.capture import Capture  # noqa: PLC0415

    if not (bag / 'metadata.yaml').is_file():
        shutil.rmtree(bag, ignore_errors=True)
        bag.parent.mkdir(parents=True, exist_ok=True)
        Capture(config).write_bag(bag)
    return bag


def _write_bag(job) -> str:
    config, bag = job
    return str(_written_bag(config, Path(bag)))


def write_bags(jobs, processes: int = 1) -> None:
    """Write every bag of ``jobs`` ((capture config, bag folder) pairs) that is not complete
    yet, ``processes`` at a time, before any of them is replayed: on a small machine a scene
    rendered while another replays in real time takes the CPU that graph needs, and its
    detector drops frames a user's machine would process."""
    jobs = [(c, Path(b)) for c, b in jobs if not (Path(b) / 'metadata.yaml').is_file()]
    if processes > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(min(processes, len(jobs))) as pool:
            list(pool.map(_write_bag, jobs))
    else:
        for job in jobs:
            _write_bag(job)


def _rfm_in_domain(domain: int) -> tuple[str, dict]:
    """The ``rfm`` executable and an environment that keeps its nodes in ROS domain
    ``domain``, discovering on this machine only."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    return shutil.which('rfm') or 'rfm', env


def evaluate_scene_graph(args) -> dict:
    """Every setting on one scene through the node graph: the scene is written as a bag (once,
    kept in ``work``) and replayed by ``rfm run`` in ROS domain ``domain`` (with the extra
    ``--param`` values ``params``); scored from the run's outputs. A run that fails counts as
    nothing localized and nothing mapped."""
    config, settings, work, domain, params = args
    scene = Path(work) / scene_name(config)
    bag = _written_bag(config, scene / 'bag')
    rfm, env = _rfm_in_domain(domain)
    out = {}
    for s in settings:
        run = scene / _slug(s.name)
        cmd = [rfm, 'run', '--bag', str(bag), '--output', str(run), '--force', '--quiet', *run_args(s)]
        if params:
            cmd += ['--param', *params]
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=3600,
                              preexec_fn=die_with_parent())
        if proc.returncode != 0 or not (run / 'summary.json').is_file():
            tail = (proc.stdout + proc.stderr).strip().splitlines()[-3:]
            out[s.name] = {**scene_metrics({}), 'error': f'rfm run exited {proc.returncode}: {" / ".join(tail)}'}
            continue
        out[s.name] = scene_metrics(json.loads((run / 'summary.json').read_text()))
    return {'scene': scene_name(config), **scene_info(config), 'results': out}


def run_graph_suite(configs, settings=SETTINGS, work=None, jobs: int = 1, progress=None, params=()) -> list:
    """:func:`evaluate_scene_graph` over the scenes, ``jobs`` at a time (each in its own ROS
    domain). Long captures (sparse views: one frame a second) go first, interleaved with
    short ones, so parallel jobs rarely replay two dense streams at once."""
    import tempfile  # noqa: PLC0415

    configs = list(configs)
    longest_first = sorted(range(len(configs)), key=lambda i: -configs[i].frames * (
        np.mean(configs[i].sparse_gap_s) if configs[i].capture == 'sparse' else 1.0 / configs[i].fps))
    order = []
    while longest_first:                 # longest, shortest, next longest, next shortest, ...
        order.append(longest_first.pop(0))
        if longest_first:
            order.append(longest_first.pop())
    base = random.SystemRandom().randint(10, 90)
    domains = queue.Queue()
    for j in range(max(1, jobs)):
        domains.put(base + j)
    temporary = tempfile.TemporaryDirectory(prefix='rfm-eval-') if work is None else None
    work_dir = Path(temporary.name if temporary else work)
    results = [None] * len(configs)
    write_bags([(c, work_dir / scene_name(c) / 'bag') for c in configs], jobs)

    def one(i):
        domain = domains.get()
        try:
            return i, evaluate_scene_graph((configs[i], tuple(settings), work_dir, domain, tuple(params)))
        finally:
            domains.put(domain)
    try:
        with ThreadPoolExecutor(max(1, jobs)) as pool:
            for done, (i, r) in enumerate(pool.map(one, order)):
                results[i] = r
                if progress:
                    progress(done + 1, len(configs), r)
    finally:
        if temporary is not None:
            temporary.cleanup()
    return results


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
    """Per setting: ARE/ATE median (median over scenes of per-scene medians over all localized
    frames) and RMSE (mean over scenes), registered (mean share of all input frames
    localized; keyframes beside it), frames processed by the detector, AP/AR (mean over
    scenes), objects mapped per object in the room (median over scenes)."""
    out = {}
    for s in settings:
        rows = [r['results'][s.name] for r in results if s.name in r['results']]
        if not rows:
            continue

        def col(k, default=float('nan')):
            return np.array([row.get(k, default) for row in rows], float)
        out[s.name] = {
            'scenes': len(rows), 'failed': sum('error' in row for row in rows),
            'ARE_median': float(np.nanmedian(col('ARE_median'))), 'ARE_rmse': float(np.nanmean(col('ARE_rmse'))),
            'ATE_median': float(np.nanmedian(col('ATE_median'))), 'ATE_rmse': float(np.nanmean(col('ATE_rmse'))),
            'registered': float(np.mean(col('registered'))),
            # gross errors pooled over scenes: wrong frames of all localized ones
            'gross': int(np.nansum(col('gross', 0))),
            'localized': int(round(np.nansum(col('registered', 0) * col('frames', 0)))),
            'keyframe_registered': float(np.mean(col('keyframe_registered'))),
            'processed': float(np.mean(col('processed', 1.0))),
            **{k: float(np.nanmean(col(k))) for k in ('AP15', 'AR15', 'AP25', 'AR25')},
            'objects_per_object': float(np.nanmedian(col('objects') / np.maximum(col('ground_truth'), 1))),
            # shares of all map objects (pooled over scenes) by kind: real / duplicate / poor fit / phantom
            **{f'share_{k}': float(np.nansum(col(f'objects_{k}')) / max(np.nansum(col('objects')), 1))
               for k in OBJECT_KINDS},
            'keyframes': float(np.mean(col('keyframes'))),
            # labels of the map objects on a real one, pooled: right of labelled, and per class
            'labelled': int(np.nansum(col('labelled', 0))), 'labels_right': int(np.nansum(col('labels_right', 0))),
            'label_classes': label_precision(rows),
            # the camera poses as the mapper published them (live), pooled over scenes
            'published': int(np.nansum(col('published', 0))),
            'published_gross': int(np.nansum(col('published_gross', 0))),
            'within_2sigma': pooled_share(col('within_2sigma'), col('published', 0)),
            # the camera poses a tf2 lookup gives at every image (a robot's map -> odom and its odometry)
            'tf_registered': _over_finite(np.mean, col('tf_registered')),
            'tf_localized': int(round(np.nansum(col('tf_registered') * col('frames', 0)))),
            'tf_gross': int(np.nansum(col('tf_gross', 0))),
            'tf_ARE_median': _over_finite(np.median, col('tf_ARE_median')),
            'tf_ATE_median': _over_finite(np.median, col('tf_ATE_median')),
        }
    return out


def _over_finite(statistic, values) -> float:
    """``statistic`` of the finite values (NaN when none is: no scene had the figure)."""
    values = np.asarray(values, float)
    values = values[np.isfinite(values)]
    return float(statistic(values)) if len(values) else float('nan')


def pooled_share(share, count) -> float:
    """A share pooled over scenes, each weighing its count (scenes without one left out)."""
    share, count = np.asarray(share, float), np.asarray(count, float)
    ok = np.isfinite(share) & (count > 0)
    return float(np.sum(share[ok] * count[ok]) / np.sum(count[ok])) if np.any(ok) else float('nan')


def _share(part: int, whole: int) -> str:
    return f'{100 * part / whole:.1f}% of {whole}' if whole else '-'


def wrong_share(m: dict) -> str:
    """'3 of 412 (0.7%)': the frames off by more than the gross thresholds, of those localized."""
    return f'{m["gross"]} of {m["localized"]} ({100 * m["gross"] / max(m["localized"], 1):.1f}%)'


def format_tables(summary: dict) -> str:
    lines = ['Localization over every frame of the input (medians over scenes of per-scene medians; RMSE '
             'averaged over scenes)', '',
             '| setting | ARE median (deg) | ATE median (cm) | ARE RMSE (deg) | ATE RMSE (cm) | frames localized '
             '| wrong (> 5 deg or > 25 cm) | keyframes registered | frames processed | as published: wrong, within '
             '2 sigma | through TF: localized, wrong, ARE, ATE |',
             '|---|---|---|---|---|---|---|---|---|---|---|']
    for name, m in summary.items():
        live = (f'{m["published_gross"]} of {m["published"]}, {100 * m["within_2sigma"]:.1f}%'
                if m.get('published') else '-')
        tf = (f'{100 * m["tf_registered"]:.1f}%, {m["tf_gross"]} of {m["tf_localized"]}, {m["tf_ARE_median"]:.2f} deg, '
              f'{100 * m["tf_ATE_median"]:.1f} cm' if np.isfinite(m.get('tf_registered', float('nan'))) else '-')
        lines.append(f'| {name} | {m["ARE_median"]:.2f} | {100 * m["ATE_median"]:.1f} | {m["ARE_rmse"]:.2f} | '
                     f'{100 * m["ATE_rmse"]:.1f} | {100 * m["registered"]:.1f}% | {wrong_share(m)} | '
                     f'{100 * m["keyframe_registered"]:.1f}% | {100 * m["processed"]:.1f}% | {live} | {tf} |')
    lines += ['', 'Mapping (scene-level AP/AR at 3D IoU 0.15 / 0.25, mean over scenes; objects mapped per object '
              'in the room, median over scenes; what the map objects are, pooled over scenes: the first box '
              'of a real object (IoU >= 0.25), a duplicate, a poor fit (IoU 0.1-0.25), nothing real '
              '(IoU < 0.1); labels right: of the map objects on a real one (IoU >= 0.25), those that carry its '
              "class in NYU40's names, pooled)", '',
              '| setting | AP15 | AR15 | AP25 | AR25 | objects / room | real | duplicate | poor fit | nothing real '
              '| labels right |',
              '|---|---|---|---|---|---|---|---|---|---|---|']
    for name, m in summary.items():
        lines.append(f'| {name} | {m["AP15"]:.3f} | {m["AR15"]:.3f} | {m["AP25"]:.3f} | {m["AR25"]:.3f} | '
                     f'{m["objects_per_object"]:.1f} | '
                     + ' | '.join(f'{100 * m.get("share_" + k, float("nan")):.0f}%' for k in OBJECT_KINDS)
                     + f' | {_share(m.get("labels_right", 0), m.get("labelled", 0))} |')
    for name, m in summary.items():
        if m.get('label_classes'):
            lines += ['', f'Labels per class the map gives ({name}): right of the map objects so labelled that lie on '
                      'a real object (precision)', '', '| class | labelled | right | precision |', '|---|---|---|---|']
            lines += [f'| {c} | {n} | {k} | {100 * k / n:.0f}% |' for c, (n, k) in m['label_classes'].items()]
    failed = {name: m['failed'] for name, m in summary.items() if m.get('failed')}
    if failed:
        lines += ['', f'Runs that failed (counted as nothing localized or mapped): {failed}']
    return '\n'.join(lines)


#: the relocalization protocol's query walks: ``handheld`` looks at the room the way the
#: mapping walk did (another walk around it), ``outward`` from near its centre at the walls
#: (the other side of the objects the map saw)
QUERY_CAPTURES = ('handheld', 'outward')
#: ``rfm eval-reloc``'s protocols: each query walk in localization mode, and ``session``: the
#: outward walk mapped as a second session on the loaded map (mapping mode)
RELOC_PROTOCOLS = QUERY_CAPTURES + ('session',)


def query_capture(config, frames: int, kind: str = 'handheld'):
    """The relocalization protocol's second capture of a room: another walk (trajectory seed
    1) at 2 Hz, of ``kind`` (:data:`QUERY_CAPTURES`), an hour after the first."""
    from dataclasses import replace  # noqa: PLC0415
    if kind not in QUERY_CAPTURES:
        raise ValueError(f'query capture must be one of {QUERY_CAPTURES}, got {kind!r}')
    return replace(config, frames=frames, fps=2.0, capture=kind, trajectory_seed=1, start_s=3600.0)


def query_folders(scene: Path, kind: str) -> tuple[Path, Path]:
    """(bag, run output) of a room's ``kind`` protocol (:data:`RELOC_PROTOCOLS`) in an ``rfm
    eval-reloc --work`` folder; the second session replays the outward walk's bag."""
    if kind == 'session':
        return Path(scene) / 'query_outward_bag', Path(scene) / 'session_run'
    return Path(scene) / f'query_{kind}_bag', Path(scene) / f'query_{kind}_run'


def camera_poses_of_run(output) -> dict:
    """{stamp_ns: 4x4 camera-to-map} of every ``rfm/camera_pose`` an ``rfm run`` recorded (its
    ``outputs.mcap`` bag folder)."""
    from rfm_core.evaluation.report import published_camera_poses  # noqa: PLC0415

    return published_camera_poses(output)[0]


def relocalization_scene_graph(args) -> list:
    """The appendix protocol through the node graph, as a user runs it: ``rfm run`` maps one
    capture of a room; each query walk (:func:`query_capture` of every kind in ``queries``) is
    replayed by ``rfm run`` with that map loaded in localization mode
    (``mapper.load_map_on_start``, ``mapper.mode:=localization``), and every
    ``rfm/camera_pose`` it publishes is scored against the truth in the world frame (the map's
    alignment to the world from the mapping run's keyframes: the query frames are not
    re-aligned). ``wrong``: > 5 deg or > 25 cm. ``params``: extra ``--param`` values for
    every run. One row per query walk."""
    config, detector, query_frames, work, domain, params, queries = args
    from rfm_core.mapping.map_io import load_map  # noqa: PLC0415
    from rfm_core.mapping.mapper import Mapper  # noqa: PLC0415

    scene = Path(work) / scene_name(config)
    map_bag = _written_bag(config, scene / 'map_bag')
    rfm, env = _rfm_in_domain(domain)
    backend, _, preset = detector.partition(':')
    detector_args = ['--backend', backend] + (['--preset', preset] if preset else [])
    mapped = scene / 'map_run'
    nan = float('nan')

    def failed(kind, error):
        return {'scene': scene_name(config), 'query': kind, 'registered': 0.0, 'wrong': nan, 'gross': 0,
                'ARE_median': nan, 'ATE_median': nan, 'frames': query_frames, 'map_registered': 0.0,
                'latency_ms': nan, 'seeing_mapped': 0, 'registered_seeing': nan, 'error': error}

    def run(bag, output, extra):
        cmd = [rfm, 'run', '--bag', str(bag), '--output', str(output), '--force', '--quiet', *detector_args, *extra]
        if params:
            cmd += ['--param', *params]
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=3600,
                              preexec_fn=die_with_parent())
        if proc.returncode != 0 or not (output / 'summary.json').is_file():
            tail = (proc.stdout + proc.stderr).strip().splitlines()[-3:]
            return f'rfm run exited {proc.returncode}: {" / ".join(tail)}'
        return None

    error = run(map_bag, mapped, [])
    if error:
        return [failed(kind, f'mapping: {error}') for kind in queries]
    mapper = Mapper()
    load_map(mapper, mapped / 'map.rfm')
    rows = []
    for kind in queries:
        bag, queried = query_folders(scene, kind)
        bag = _written_bag(query_capture(config, query_frames, 'outward' if kind == 'session' else kind), bag)
        if kind == 'session':                   # mapping on a copy of the map (its autosaves go there)
            loaded = scene / 'session_map.rfm'
            shutil.copyfile(mapped / 'map.rfm', loaded)
            error = run(bag, queried, ['--param', 'mapper.load_map_on_start:=true', f'mapper.map_path:={loaded}'])
        else:
            error = run(bag, queried, ['--param', 'mapper.load_map_on_start:=true',
                                       f'mapper.map_path:={mapped / "map.rfm"}', 'mapper.mode:=localization'])
        if error:
            rows.append(failed(kind, error))
            continue
        if kind == 'session':
            rows.append({'scene': scene_name(config), 'query': kind, 'latency_ms': nan,
                         **session_scores(mapper, queried / 'map.rfm', map_bag, bag)})
            continue
        scores = relocalization_scores(mapper, map_bag, bag, camera_poses_of_run(queried))
        latency = json.loads((queried / 'summary.json').read_text()).get('relocalization') or {}
        rows.append({'scene': scene_name(config), 'query': kind, **scores.row,
                     'latency_ms': latency.get('median_ms', nan) if latency.get('queries') else nan})
    return rows


def session_scores(mapper, session_map, map_bag, session_bag) -> dict:
    """A second session mapped on ``mapper``'s map, scored from the map it saved
    (``session_map``): its frames' poses in the saved map (``trajectory.tum``'s) against the
    truth in the world frame through the first map's alignment (not re-aligned: placed in the
    loaded map's frame or wrong), as :func:`relocalization_scores`; ``moved_cm``: how far the
    loaded map's keyframes moved (median and max of camera centres, cm)."""
    return scored_session(mapper, session_map, map_bag, session_bag)[0]


def scored_session(mapper, session_map, map_bag, session_bag) -> tuple[dict, 'RelocalizationScores']:
    """:func:`session_scores`' row, and the :class:`RelocalizationScores` it comes from."""
    from rfm_core.mapping.map_io import load_map  # noqa: PLC0415
    from rfm_core.mapping.mapper import Mapper  # noqa: PLC0415

    after = Mapper()
    load_map(after, session_map)
    frames = after.frame_poses()
    scores = relocalization_scores(mapper, map_bag, session_bag, frames)
    before, now = mapper.camera_poses(), after.camera_poses()
    moved = [100 * float(np.linalg.norm(now[k][:3, 3] - m[:3, 3])) for k, m in before.items() if k in now]
    return {**scores.row, 'moved_cm_median': float(np.median(moved)) if moved else float('nan'),
            'moved_cm_max': float(np.max(moved)) if moved else float('nan'),
            'loaded_kept': len(moved) / max(len(before), 1)}, scores


@dataclass
class RelocalizationScores:
    """A query walk's camera poses scored against a map (:func:`relocalization_scores`)."""

    row: dict                #: trajectory errors, frames, seeing_mapped, registered_seeing, map_registered
    estimated: dict          #: {stamp: 4x4 camera-to-world} of the query's frames with a pose
    truth: dict              #: {stamp: 4x4 camera-to-world} of every query frame
    seeing: set              #: the denominator: stamps of the query frames that see two mapped objects


def relocalization_scores(mapper, map_bag, query_bag, camera_poses: dict) -> RelocalizationScores:
    """The scoring of a query walk's camera poses ({stamp: 4x4 camera-to-map}) against
    ``mapper``'s map: the map aligned to the world by its keyframes (the mapping walk's
    truth), the poses not re-aligned; wrong: > 5 deg or > 25 cm; the denominator: the query
    frames that see two objects the map holds."""
    from rfm_core.evaluation.report import frames_seeing_mapped, map_boxes, read_ground_truth  # noqa: PLC0415
    from rfm_core.evaluation.trajectory import map_to_truth, trajectory_errors  # noqa: PLC0415

    keyframes = {mapper.keyframes[k].stamp_ns: m for k, m in mapper.camera_poses().items()}
    alignment = map_to_truth(keyframes, read_ground_truth(map_bag).camera_poses)
    world = alignment.matrix()
    query = read_ground_truth(query_bag)
    truth = query.camera_poses
    estimated = {stamp: world @ pose for stamp, pose in camera_poses.items() if stamp in truth}
    errors = trajectory_errors(estimated, truth, align=False)
    seeing = frames_seeing_mapped(query, map_boxes(mapper.tracks(), alignment)) & set(truth)
    row = {**errors, 'frames': len(truth), 'seeing_mapped': len(seeing),
           'registered_seeing': len(seeing & set(estimated)) / len(seeing) if seeing else float('nan'),
           'map_registered': len(mapper.poses) / max(len(mapper.keyframes), 1)}
    return RelocalizationScores(row, estimated, truth, seeing)


def relocalization_scene(args) -> list:
    """Paper appendix, in-process: map one capture of a room, save the map, load it into a
    fresh mapper, and relocalize every frame of each query walk (:func:`query_capture` of
    every kind in ``queries``) of the same room. One row per query walk: relocalized share and
    median errors."""
    config, detector, query_frames, queries = args
    import tempfile  # noqa: PLC0415

    import torch  # noqa: PLC0415

    from rfm_core.evaluation.pipeline import relocalize_capture, run_capture  # noqa: PLC0415
    from rfm_core.evaluation.trajectory import map_to_truth  # noqa: PLC0415
    from rfm_core.mapping.map_io import load_map, save_map  # noqa: PLC0415
    from rfm_core.mapping.mapper import Mapper  # noqa: PLC0415
    from rfm_core.matching.factory import make_matcher  # noqa: PLC0415
    from rfm_core.sim.capture import Capture  # noqa: PLC0415

    torch.set_num_threads(1)
    mapped = run_capture(config, detector, matcher=make_matcher('learned'), noise_seed=3)
    rows = []
    for kind in queries:
        mapper = Mapper(matcher=make_matcher('learned'))
        with tempfile.TemporaryDirectory() as tmp:
            load_map(mapper, save_map(mapped.mapper, Path(tmp) / 'map.rfm'))
        mapper.mode = 'localization'
        world = map_to_truth(mapper.camera_poses(), mapped.truth)
        err = relocalize_capture(mapper, world, Capture(query_capture(config, query_frames, kind)), detector,
                                 noise_seed=11)
        rows.append({'scene': scene_name(config), 'query': kind, **err,
                     'map_registered': mapped.localization['registered']})
    return rows
