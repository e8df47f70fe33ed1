"""The rfm command line.

    rfm sim OUT [--seed N --style plain|textured --capture handheld|sparse|orbit ...]
    rfm sim-suite DIR [--count 20 --first-seed 1000 --jobs 2 ...]
    rfm play BAG [--rate R --start-offset S --loop --topics T ... --remap FROM:=TO ...]
    rfm record OUT [--topics T ...]
    rfm preview BAG OUT.png [--frames 4]
    rfm eval-detections BAG|SUITE ... [--backend depth_clusters|ground_truth]
    rfm eval-matching [--inputs depth_clusters ground_truth:rgbd ...] [--matchers learned classical]
    rfm train-depth-score [--scenes 32 --first-seed 3000]
    rfm train-matcher [--backend depth_clusters|ground_truth] [--scenes 60 --first-seed 3000]
    rfm run --bag BAG | --live [--backend depth_clusters --no-processes --output DIR ...]
    rfm eval [--scenes 20 --jobs 2]
    rfm eval-reloc [--detector depth_clusters --scenes 10 --jobs 2 --offline]
    rfm replay WORK [--reloc]

`sim` needs no ROS; `play` and `record` start rclpy nodes.
"""
from __future__ import annotations

import argparse
import json
from dataclasses import replace
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from rfm_core.config import MATCHERS, RfmConfig
from rfm_core.detection import BACKENDS
from rfm_core.detection.ground_truth import PRESETS
from rfm_core.io.topics import CAMERA_TOPICS

__all__ = ['main', 'suite_configs']


def _size(text: str) -> tuple:
    try:
        w, h = (int(v) for v in text.lower().split('x'))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 320x240, got '{text}'") from None
    return w, h


def _add_scene_options(p: argparse.ArgumentParser) -> None:
    p.add_argument('--frames', type=int, default=100, help='frames per capture (default 100)')
    p.add_argument('--fps', type=float, default=30.0,
                   help='frame rate of handheld/orbit captures (default 30)')
    p.add_argument('--size', type=_size, default=(320, 240), help='WIDTHxHEIGHT (default 320x240)')
    p.add_argument('--hfov', type=float, default=70.0, help='horizontal field of view, deg')
    p.add_argument('--imu-rate', type=float, default=200.0, help='IMU rate, Hz (default 200)')
    p.add_argument('--depth-encoding', choices=('16UC1', '32FC1'), default='16UC1',
                   help='depth image encoding: 16UC1 in mm (default) or 32FC1 in m')
    p.add_argument('--color-noise', type=float, default=None,
                   help="std of colour noise in 8-bit levels (default: the sensor's, 2 or 4; 0 makes smaller bags)")
    p.add_argument('--sensor', choices=('default', 'realsense'), default='default',
                   help="default: mild structured-light noise; realsense: an active-stereo camera's artefacts "
                        '(range^2 noise, projector shadows, flying pixels, depth lost on dark surfaces, depth a '
                        'pixel off colour and 3-10 ms late, exposure drift, IMU bias and time offset)')
    p.add_argument('--camera-height', type=float, nargs=2, metavar=('MIN', 'MAX'),
                   help="range of the handheld / robot camera's height, m (default 1.45-1.65 / 0.3-0.9)")
    p.add_argument('--sparse-gap', type=float, nargs=2, metavar=('MIN', 'MAX'), default=(1.0, 1.0),
                   help='seconds between sparse views, drawn in this range (default 1 1)')
    p.add_argument('--furniture', choices=('boxes', 'parts'), default='boxes',
                   help='boxes: every object a solid box (default); parts: tables on legs, chairs with '
                        'backs, open shelves with objects on their boards, sofas, beds, lamps, plants')
    p.add_argument('--clutter', action='store_true',
                   help='add rugs, pictures, door frames, radiators and cables (in no ground truth)')
    p.add_argument('--force', action='store_true', help='overwrite existing output')


def _config(args, seed, style, capture):
    from rfm_core.sim.capture import CaptureConfig  # noqa: PLC0415
    from rfm_core.sim.render import NoiseModel  # noqa: PLC0415
    return CaptureConfig(seed=seed, room_style=style, capture=capture, frames=args.frames,
                         fps=args.fps, width=args.size[0], height=args.size[1],
                         hfov_deg=args.hfov, imu_rate_hz=args.imu_rate,
                         depth_encoding=args.depth_encoding, furniture=args.furniture, clutter=args.clutter,
                         camera_height=tuple(args.camera_height or ()), sparse_gap_s=tuple(args.sparse_gap),
                         noise=_noise(NoiseModel, args))


def _noise(model, args):
    """The sensor model of ``rfm sim`` options."""
    noise = model.realsense() if args.sensor == 'realsense' else model()
    if args.color_noise is not None:
        noise = replace(noise, color_sigma=args.color_noise)
    return noise


def _frame_progress(prefix: str):
    """A progress(done, total) that rewrites one line on a terminal (else only the last)."""
    def progress(done, total):
        if sys.stderr.isatty() or done == total:
            sys.stderr.write(f'\r{prefix} {done}/{total} frames')
            sys.stderr.flush()
    return progress


def _prepare(path: Path, force: bool) -> None:
    if path.exists():
        if not force:
            raise SystemExit(f'rfm: {path} exists; pass --force to overwrite it')
        shutil.rmtree(path)
    path.parent.mkdir(parents=True, exist_ok=True)


def _write_scene(config, path: str) -> dict:
    from rfm_core.sim.capture import Capture  # noqa: PLC0415
    start = time.perf_counter()
    summary = Capture(config).write_bag(path)
    summary['seconds'] = round(time.perf_counter() - start, 2)
    return summary


def cmd_sim(args) -> int:
    out = Path(args.output)
    _prepare(out, args.force)
    config = _config(args, args.seed, args.style, args.capture)

    progress = _frame_progress('[rfm sim] rendered')
    from rfm_core.sim.capture import Capture  # noqa: PLC0415
    capture = Capture(config)
    summary = capture.write_bag(out, progress=progress)
    sys.stderr.write('\n')
    size = sum(f.stat().st_size for f in out.iterdir())
    print(f'wrote {out} ({size / 1e6:.1f} MB): {config.frames} frames of a {config.room_style} '
          f'room with {summary["objects"]} objects, {config.capture} capture')
    return 0


def suite_configs(args) -> list:
    """The scenes of a suite: seeds first_seed.., rooms and captures as rfm eval's
    (rfm_core.evaluation.suite.scene_kind)."""
    from rfm_core.evaluation.suite import scene_kind  # noqa: PLC0415

    configs = []
    for i in range(args.count):
        style, capture = scene_kind(i)
        configs.append((f'scene_{i:03d}_{style}_{capture}',
                        _config(args, args.first_seed + i, style, capture)))
    return configs


def cmd_sim_suite(args) -> int:
    out = Path(args.output)
    _prepare(out, args.force)
    out.mkdir(parents=True)
    configs = suite_configs(args)
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futures = [(name, cfg, pool.submit(_write_scene, cfg, str(out / name)))
                   for name, cfg in configs]
        scenes = []
        for name, cfg, future in futures:
            summary = future.result()
            scenes.append({'name': name, 'path': name, 'config': json.loads(cfg.to_json()),
                           'objects': summary['objects']})
            print(f'[rfm sim-suite] {name}: {summary["objects"]} objects, {summary["seconds"]} s')
    (out / 'suite.json').write_text(json.dumps({'scenes': scenes}, indent=1))
    print(f'wrote {len(scenes)} scenes to {out}')
    return 0


def cmd_play(args) -> int:
    import rclpy  # noqa: PLC0415
    from rclpy.executors import ExternalShutdownException  # noqa: PLC0415

    from rfm_bringup.player import BagPlayer, PlayOptions  # noqa: PLC0415
    remaps = {}
    for item in args.remap or []:
        if ':=' not in item:
            raise SystemExit(f"rfm: --remap takes FROM:=TO, got '{item}'")
        old, new = item.split(':=', 1)
        remaps[old] = new
    pace, answer = args.pace or (None, None)
    try:
        options = PlayOptions(rate=args.rate, start_offset=args.start_offset, loop=args.loop,
                              topics=args.topics or [], remaps=remaps, clock=not args.no_clock,
                              clock_hz=args.clock_hz, delay=args.delay, wait_for=args.wait_for or [],
                              progress=None if not args.quiet else False, pace_topic=pace or '',
                              answer_topic=answer or '')
    except ValueError as exc:
        raise SystemExit(f'rfm play: {exc}') from None
    if not Path(args.bag).exists():
        raise SystemExit(f'rfm: no bag at {args.bag}')
    rclpy.init()
    player = None
    try:
        player = BagPlayer(args.bag, options)
        player.play()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if player is not None:
            player.destroy_node()
        rclpy.try_shutdown()
    return 0


def cmd_convert(args) -> int:
    """A TUM RGB-D or generic RGB-D dataset folder as a bag for rfm run --bag."""
    from rfm_core.io.datasets import read_folder, write_bag  # noqa: PLC0415

    out = Path(args.output) if args.output else Path('bags') / Path(args.folder).resolve().name
    try:
        folder = read_folder(args.folder, intrinsics=args.intrinsics, accel_axes=args.accel_axes,
                             max_difference_s=args.max_difference)
    except (FileNotFoundError, ValueError) as exc:
        raise SystemExit(f'rfm convert: {exc}') from None
    _prepare(out, args.force)
    try:
        summary = write_bag(folder, out, progress=None if args.quiet else _frame_progress('[rfm convert]'))
    except (FileNotFoundError, ValueError) as exc:
        raise SystemExit(f'rfm convert: {exc}') from None
    if not args.quiet:
        sys.stderr.write('\n')
    sensors = 'accelerometer and gyroscope' if summary['gyroscope'] else 'accelerometer only'
    imu = (f'{summary["imu"]} IMU samples ({sensors})' if summary['imu']
           else 'no IMU (run with --param detector.gravity_source:=parameter)')
    levelled = f'levelled by {summary["levelled_deg"]:.1f} deg' if summary['imu'] else 'as given: no IMU to level it'
    truth = (f'{summary["ground_truth"]} ground-truth poses ({levelled})' if summary['ground_truth']
             else 'no ground truth')
    print(f'wrote {out}: {summary["frames"]} frames {summary["width"]}x{summary["height"]} ({summary["layout"]} '
          f'layout; {summary["skipped"]} colour images without depth within {args.max_difference} s), {imu}, '
          f'{truth}. Next: rfm run --bag {out}')
    return 0


def cmd_record(args) -> int:
    import rclpy  # noqa: PLC0415
    from rclpy.executors import ExternalShutdownException  # noqa: PLC0415

    from rfm_bringup.recorder import BagRecorder  # noqa: PLC0415
    out = Path(args.output)
    _prepare(out, args.force)
    rclpy.init()
    recorder = None
    try:
        recorder = BagRecorder(out, topics=args.topics or ())
        rclpy.spin(recorder)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if recorder is not None:
            counts = recorder.close()
            print(f'wrote {out}: ' + ', '.join(f'{t} {n}' for t, n in sorted(counts.items())))
            recorder.destroy_node()
        rclpy.try_shutdown()
    return 0


def cmd_preview(args) -> int:
    """A contact sheet (colour | depth) of evenly spaced frames of a bag, as PNG."""
    import numpy as np  # noqa: PLC0415
    from rosbags.highlevel import AnyReader  # noqa: PLC0415

    from rfm_core.io.images import depth_to_meters, image_to_rgb  # noqa: PLC0415
    from rfm_core.io.png import write_png  # noqa: PLC0415
    from rfm_core.sim.capture import TOPICS  # noqa: PLC0415

    color_topic = args.color_topic or TOPICS['color']
    depth_topic = args.depth_topic or TOPICS['depth']
    picked = {color_topic: {}, depth_topic: {}}          # index -> image, only the frames shown
    with AnyReader([Path(args.bag)]) as reader:
        conns = [c for c in reader.connections if c.topic in picked]
        n = sum(c.msgcount for c in conns if c.topic == color_topic)
        if not n:
            raise SystemExit(f'rfm: no {color_topic} in {args.bag} (its topics: '
                             f'{sorted({c.topic for c in reader.connections})}); pass --color-topic')
        picks = np.linspace(0, n - 1, min(args.frames, n)).round().astype(int)
        wanted, seen = set(picks.tolist()), {color_topic: 0, depth_topic: 0}
        for conn, _, raw in reader.messages(connections=conns):   # streamed: a bag of any size
            i = seen[conn.topic]
            seen[conn.topic] += 1
            if i in wanted:
                msg = reader.deserialize(raw, conn.msgtype)
                picked[conn.topic][i] = (image_to_rgb(msg) if conn.topic == color_topic
                                         else np.nan_to_num(depth_to_meters(msg), nan=0.0))
    rows = []
    for i in picks:
        row = [picked[color_topic][i]]
        if i in picked[depth_topic]:
            grey = (np.clip(picked[depth_topic][i] / args.max_depth, 0, 1) * 255).astype(np.uint8)
            row.append(np.repeat(grey[..., None], 3, axis=2))
        rows.append(np.concatenate(row, axis=1))
    write_png(args.output, np.concatenate(rows, axis=0))
    print(f'wrote {args.output}: frames {picks.tolist()} of {n}')
    return 0


def cmd_eval_detections(args) -> int:
    """Per-frame AP/AR of a detector backend on bags with ground truth."""
    from rfm_core.detection import make_detector  # noqa: PLC0415
    from rfm_core.evaluation.detection import DetectionEvaluator  # noqa: PLC0415
    from rfm_core.evaluation.detection_bags import evaluate_bag  # noqa: PLC0415

    bags = []
    for item in args.bags:
        path = Path(item)
        if (path / 'suite.json').exists():
            suite = json.loads((path / 'suite.json').read_text())
            bags += [path / scene['path'] for scene in suite['scenes']]
        elif (path / 'metadata.yaml').exists():
            bags.append(path)
        else:
            raise SystemExit(f'rfm: {path} is neither a bag directory nor a suite')
    options = {}
    if args.backend == 'depth_clusters':
        options['stride'] = args.stride
    elif args.backend == 'ground_truth':
        options['preset'] = args.preset
    rows = []
    for bag in bags:
        detector = make_detector(args.backend, **options)
        result = evaluate_bag(bag, detector, every=args.every, max_frames=args.max_frames,
                              evaluator=DetectionEvaluator(min_visibility=args.min_visibility))
        rows.append((bag.name, result))
        print(f'{bag.name}: AP15 {result["AP15"]:.3f} AR15 {result["AR15"]:.3f} '
              f'AP25 {result["AP25"]:.3f} AR25 {result["AR25"]:.3f} '
              f'({result["frames"]} frames, {result["latency_ms"]:.0f} ms/frame)', flush=True)
    name = args.backend + (f':{args.preset}' if args.backend == 'ground_truth' else '')
    keys = ('AP15', 'AR15', 'AP25', 'AR25')
    mean = {k: float(np.mean([r[k] for _, r in rows])) for k in keys}
    print('\n| backend | scenes | frames | ' + ' | '.join(keys) + ' |')
    print('|---|---|---|' + '---|' * len(keys))
    print(f'| {name} | {len(rows)} | {sum(r["frames"] for _, r in rows)} | '
          + ' | '.join(f'{mean[k]:.3f}' for k in keys) + ' |')
    if args.json:
        Path(args.json).write_text(json.dumps({'backend': name, 'mean': mean,
                                               'scenes': dict(rows)}, indent=1))
    return 0


def cmd_eval_matching(args) -> int:
    """Object matching and relative-pose accuracy on simulated frame pairs."""
    from rfm_core.evaluation.matching import WIDE_TURN_DEG, evaluate_pairs  # noqa: PLC0415
    from rfm_core.detection import detector_for_spec  # noqa: PLC0415
    from rfm_core.matching.config import MatchingConfig, monocular  # noqa: PLC0415
    from rfm_core.matching.classical import ClassicalMatcher  # noqa: PLC0415
    from rfm_core.matching.learned import LearnedMatcher  # noqa: PLC0415
    from rfm_core.training.matcher import labelled_pairs, scene_configs  # noqa: PLC0415

    seeds = range(args.first_seed, args.first_seed + args.scenes)
    pairs = labelled_pairs(scene_configs(seeds, frames=args.frames, world=args.world), args.inputs,
                           noise_seeds=(args.noise_seed,), gaps=(args.gap,), min_shared=3,
                           visible=True, jobs=args.jobs)
    matchers = {'learned': lambda: LearnedMatcher(weights=args.weights),
                'classical': ClassicalMatcher}
    print('| input | matcher | pairs | match precision | match recall | F1 | verified | '
          f'median yaw (deg) | median translation (cm) | verified turned >= {WIDE_TURN_DEG:.0f} deg | '
          'their median yaw (deg) |')
    print('|---|---|---|---|---|---|---|---|---|---|---|')
    for spec in args.inputs:
        # an RGB-only detector's poses are verified and refit along the viewing rays, as in rfm eval
        config = monocular(MatchingConfig()) if detector_for_spec(spec).monocular else MatchingConfig()
        for name in args.matchers:
            result = evaluate_pairs(pairs[spec], matchers[name](), config)
            print(f'| {spec} | {name} | {result.row()} |', flush=True)
    return 0


def cmd_train_depth_score(args) -> int:
    """Fit depth_clusters' calibrated score on simulated scenes from the training seeds."""
    from rfm_core.detection.score_model import DEFAULT_SCORE_MODEL  # noqa: PLC0415
    from rfm_core.training.depth_score import fit_score_model, score_samples  # noqa: PLC0415
    from rfm_core.training.matcher import scene_configs  # noqa: PLC0415

    configs = scene_configs(range(args.first_seed, args.first_seed + args.scenes), frames=args.frames)
    start = time.perf_counter()
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        samples = list(pool.map(score_samples, configs))
    x = np.concatenate([f for f, _ in samples])
    y = np.concatenate([lab for _, lab in samples])
    if len(y) < 50 or y.all() or not y.any():
        raise SystemExit(f'rfm train-depth-score: {len(y)} boxes, {int(y.sum())} right: too few to fit')
    model = fit_score_model(x, y)
    output = Path(args.output) if args.output else DEFAULT_SCORE_MODEL
    output.parent.mkdir(parents=True, exist_ok=True)
    model.save(output, {'command': 'rfm train-depth-score ' + ' '.join(sys.argv[2:])
                        if sys.argv[1:2] == ['train-depth-score'] else 'rfm train-depth-score (API)',
                        'scenes': args.scenes, 'first_seed': args.first_seed, 'frames': args.frames,
                        'boxes': int(len(y)), 'right': int(y.sum())})
    print(f'{len(y)} boxes ({100 * y.mean():.0f}% right) from {args.scenes} scenes in '
          f'{time.perf_counter() - start:.0f} s -> {output}')
    return 0


def cmd_train_box_refiner(args) -> int:
    """Train depth_clusters' learned box refiner on simulated scenes of the training seeds."""
    import torch  # noqa: PLC0415

    from rfm_core.detection.box_refiner import DEFAULT_BOX_REFINER  # noqa: PLC0415
    from rfm_core.training.box_refiner import (  # noqa: PLC0415
        refiner_samples, save, train_box_refiner, training_configs)

    torch.set_num_threads(max(1, args.threads))
    seeds = range(args.first_seed, args.first_seed + args.scenes)
    start = time.perf_counter()
    if args.samples and Path(args.samples).exists():
        data = dict(np.load(args.samples))
        print(f'{len(data["objectness"])} samples from {args.samples}')
    else:
        items = training_configs(seeds, frames_per_scene=args.frames)
        with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            parts = []
            for i, r in enumerate(pool.map(refiner_samples, items, chunksize=4)):
                if r:
                    parts.append(r)
                print(f'\rscenes {i + 1}/{len(items)}', end='', flush=True)
        print()
        if not parts:
            raise SystemExit('rfm train-box-refiner: no candidates in the training scenes')
        data = {k: np.concatenate([r[k] for r in parts]) for k in parts[0]}
        if args.samples:
            np.savez(args.samples, **data)
    n = len(data['objectness'])
    print(f'{n} candidates ({100 * data["objectness"].mean():.0f}% objects) from {args.scenes} scenes '
          f'in {time.perf_counter() - start:.0f} s', flush=True)
    net, history = train_box_refiner(data, epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                                     width=args.width, seed=args.seed)
    output = Path(args.output) if args.output else DEFAULT_BOX_REFINER
    output.parent.mkdir(parents=True, exist_ok=True)
    command = ('rfm train-box-refiner ' + ' '.join(sys.argv[2:]) if sys.argv[1:2] == ['train-box-refiner']
               else 'rfm train-box-refiner (API)')
    save(net, output, {'command': command, 'scene_seeds': [seeds.start, seeds.stop - 1], 'samples': n,
                       'epochs': args.epochs, 'final_losses': history[-1], 'torch': str(torch.__version__),
                       'seconds': round(time.perf_counter() - start)})
    print(f'wrote {output} ({output.stat().st_size / 1e6:.2f} MB, {time.perf_counter() - start:.0f} s)')
    return 0


def cmd_train_matcher(args) -> int:
    """Train the learned object matcher on sim pairs through a real detector backend."""
    from dataclasses import asdict  # noqa: PLC0415

    import torch  # noqa: PLC0415

    from rfm_core.matching.learned import MatcherNetConfig, WEIGHTS_DIR  # noqa: PLC0415
    from rfm_core.training.matcher import (  # noqa: PLC0415
        TrainConfig, labelled_pairs, save, scene_configs, train_matcher)

    specs = ([f'ground_truth:{p}' for p in args.presets] if args.backend == 'ground_truth'
             else [args.backend])
    seeds = range(args.first_seed, args.first_seed + args.scenes)
    start = time.perf_counter()
    pairs = labelled_pairs(scene_configs(seeds, frames=args.frames, world=args.world), specs,
                           noise_seeds=tuple(range(args.noise_draws)), jobs=args.jobs, structure=args.structure,
                           progress=lambda i, n: print(f'\rscenes {i}/{n}', end='', flush=True))
    print()
    data = [p for spec in specs for p in pairs[spec]]
    if not data:
        raise SystemExit('rfm train-matcher: no training pairs (no shared detections)')
    print(f'{len(data)} pairs from {args.scenes} scenes ({", ".join(specs)}) in '
          f'{time.perf_counter() - start:.0f} s', flush=True)
    dim = data[0][0].observations.embeddings.shape[1]
    config = TrainConfig(epochs=args.epochs, batch_size=args.batch_size, learning_rate=args.lr,
                         seed=args.seed, threads=args.threads)
    net = train_matcher(data, MatcherNetConfig(embedding_dim=dim, layers=args.layers), config)
    output = Path(args.output) if args.output else WEIGHTS_DIR / f'object_matcher_{args.backend}.npz'
    output.parent.mkdir(parents=True, exist_ok=True)
    metadata = {'command': 'rfm train-matcher ' + ' '.join(sys.argv[2:]) if sys.argv[1:2] == ['train-matcher']
                else 'rfm train-matcher (API)', 'backend': args.backend, 'inputs': specs,
                'scene_seeds': [seeds.start, seeds.stop - 1], 'world': args.world, 'pairs': len(data),
                'structure': args.structure,
                'train': asdict(config),
                'torch': torch.__version__,
                'seconds': round(time.perf_counter() - start)}
    save(net, output, metadata)
    print(f'wrote {output} ({output.stat().st_size / 1e6:.1f} MB, {time.perf_counter() - start:.0f} s)')
    return 0


def cmd_eval(args) -> int:
    """The paper's localization and mapping tables over generated scenes: through the node
    graph (bags replayed by rfm run) by default, in-process with --offline."""
    from rfm_core.evaluation.suite import (  # noqa: PLC0415
        SETTINGS, eval_configs, format_tables, run_graph_suite, run_suite, select_settings, summarize)

    settings = select_settings(args.settings)
    if not settings:
        raise SystemExit(f'rfm eval: no setting matches {args.settings}; settings: {[s.name for s in SETTINGS]}')
    configs = eval_configs(args.scenes, args.first_seed, args.frames, args.fps, world=args.world,
                           capture=args.capture)
    start = time.perf_counter()

    def progress(i, n, r):
        first = r['results'].get(settings[0].name, {})
        print(f'[rfm eval] {i}/{n} {r["scene"]}: {settings[0].name}: ARE {first.get("ARE_median", float("nan")):.2f} '
              f'ATE {100 * first.get("ATE_median", float("nan")):.1f} cm, {100 * first.get("registered", 0):.0f}% '
              f'of frames localized ({first.get("gross", 0)} wrong)'
              + (f', through TF {100 * first["tf_registered"]:.0f}% ({first.get("tf_gross", 0)} wrong)'
                 if first.get('tf_registered', 0) > 0 else '')
              + f', AP25 {first.get("AP25", float("nan")):.3f}'
              f'{" (" + first["error"] + ")" if "error" in first else ""} ({time.perf_counter() - start:.0f} s)',
              flush=True)

    if args.offline:
        if args.param:
            raise SystemExit('rfm eval: --param applies to the node graph, not to --offline')
        results = run_suite(configs, settings, jobs=args.jobs, progress=progress)
    else:
        results = run_graph_suite(configs, settings, work=args.work, jobs=args.jobs, progress=progress,
                                  params=args.param)
    print(f'\n{"In-process (offline: every frame detected, true gravity)" if args.offline else "Through the node graph (rfm run, real-time replay)"}, '
          f'{len(configs)} scenes of the {args.world} world from seed {args.first_seed}, {time.perf_counter() - start:.0f} s')
    summaries = {'all': summarize(results, settings)}
    for key in ('capture', 'sensor'):                # breakdowns by capture style and sensor model
        for kind in sorted({r[key] for r in results}):
            subset = [r for r in results if r[key] == kind]
            if len(subset) < len(results):
                summaries[f'{kind} ({key})'] = summarize(subset, settings)
    for name, summary in summaries.items():
        print(f'\n### {name} scenes\n')
        print(format_tables(summary))
    if args.json:
        Path(args.json).write_text(json.dumps({'path': 'offline' if args.offline else 'graph',
                                               'summary': summaries, 'scenes': results}, indent=1, default=float))
    return 0


def cmd_eval_reloc(args) -> int:
    """Relocalization against a saved map (paper appendix) over generated rooms: through the
    node graph by default (rfm run maps one walk, rfm run in localization mode replays each
    query walk), in-process with --offline. One table row per query walk."""
    import random  # noqa: PLC0415
    import tempfile  # noqa: PLC0415

    from rfm_core.evaluation.suite import (  # noqa: PLC0415
        eval_configs, query_capture, query_folders, relocalization_scene, relocalization_scene_graph, scene_name,
        write_bags)

    # every room mapped from a walk around it (--frames / --fps seconds at the scene's rate)
    configs = eval_configs(args.scenes, args.first_seed, args.frames, args.fps, world=args.world, capture='handheld')
    queries = tuple(dict.fromkeys(args.queries))
    temporary = None
    if args.offline:                            # the second session is a graph protocol (rfm run on a loaded map)
        queries = tuple(k for k in queries if k != 'session')
        if not queries:
            raise SystemExit('rfm eval-reloc: --offline runs the query walks only (handheld, outward)')
        scene_fn, work = relocalization_scene, [(c, args.detector, args.query_frames, queries) for c in configs]
    else:
        temporary = tempfile.TemporaryDirectory(prefix='rfm-eval-reloc-') if args.work is None else None
        folder = temporary.name if temporary else args.work
        base = random.SystemRandom().randint(10, 80)
        # one ROS domain per scene: parallel scenes never see each other's nodes
        scene_fn = relocalization_scene_graph
        work = [(c, args.detector, args.query_frames, folder, base + i, args.param or (), queries)
                for i, c in enumerate(configs)]
        scenes = [Path(folder) / scene_name(c) for c in configs]
        walks = {'outward' if kind == 'session' else kind for kind in queries}
        write_bags([(c, d / 'map_bag') for c, d in zip(configs, scenes)]
                   + [(query_capture(c, args.query_frames, kind), query_folders(d, kind)[0])
                      for c, d in zip(configs, scenes) for kind in sorted(walks)], args.jobs)
    rows = []
    try:
        with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            for scene_rows in pool.map(scene_fn, work):
                for r in scene_rows:
                    rows.append(r)
                    seeing = (f' ({100 * r["registered_seeing"]:.0f}% of the {r["seeing_mapped"]} frames that see '
                              f'two mapped objects)' if r.get('seeing_mapped') else '')
                    moved = (f', the loaded keyframes moved {r["moved_cm_median"]:.1f} cm (max '
                             f'{r["moved_cm_max"]:.1f})' if 'moved_cm_max' in r else '')
                    print(f'[rfm eval-reloc] {r["scene"]} {r["query"]}: placed {100 * r["registered"]:.0f}%'
                          f'{seeing}, {r["ARE_median"]:.2f} deg, {100 * r["ATE_median"]:.1f} cm, wrong '
                          f'{r.get("gross", 0)}, {r.get("latency_ms", float("nan")):.0f} ms per query{moved} '
                          f'(map: {100 * r["map_registered"]:.0f}% of keyframes registered)'
                          + (f' [{r["error"]}]' if r.get('error') else ''), flush=True)
    finally:
        if temporary is not None:
            temporary.cleanup()
    path = 'in-process' if args.offline else 'through the node graph'
    print(f'\n{path}, {args.world} world, {args.detector}; the map from a walk around each room; an hour later '
          'in localization mode: handheld (another walk around it), outward (from near its centre, looking out); '
          'session: the outward walk mapped on the loaded map (mapping mode), its frames placed in the loaded '
          "map's frame\n"
          '| protocol | rooms | placed | of frames that see >= 2 mapped objects | ARE median (deg) '
          '| ATE median (cm) | wrong (> 5 deg or > 25 cm) | ms per query (median) |\n'
          '|---|---|---|---|---|---|---|---|')
    for kind in queries:
        print(reloc_table_row(kind, [r for r in rows if r['query'] == kind]))
    sessions = [r for r in rows if r['query'] == 'session' and np.isfinite(r.get('moved_cm_max', np.nan))]
    if sessions:
        moved = np.median([r['moved_cm_median'] for r in sessions])
        print(f"\nsecond session: the loaded map's keyframes moved {moved:.1f} cm (median of rooms' medians), "
              f"at most {max(r['moved_cm_max'] for r in sessions):.1f} cm; "
              f"{100 * np.mean([r['loaded_kept'] for r in sessions]):.0f}% of them kept in the saved map")
    return 0


def reloc_table_row(kind: str, rows: list) -> str:
    """One query walk's row of ``rfm eval-reloc``'s table, pooled over its rooms."""
    from rfm_core.evaluation.suite import wrong_share  # noqa: PLC0415
    def median(key):                            # NaN (no warning) where no room placed a frame
        values = np.array([r[key] for r in rows], float)
        return float(np.median(values[np.isfinite(values)])) if np.isfinite(values).any() else float('nan')
    reg = float(np.mean([r['registered'] for r in rows]))
    are, ate = median('ARE_median'), median('ATE_median')
    relocalized = int(round(sum(r['registered'] * r['frames'] for r in rows)))
    gross = int(sum(r.get('gross', 0) for r in rows))
    seeing = np.array([r.get('seeing_mapped', 0) for r in rows], float)
    found = np.nan_to_num(np.array([r.get('registered_seeing', np.nan) for r in rows], float)) * seeing
    seeing_share = f'{100 * found.sum() / seeing.sum():.1f}%' if seeing.sum() else '-'
    latency = np.array([r.get('latency_ms', np.nan) for r in rows], float)
    latency = float(np.median(latency[np.isfinite(latency)])) if np.isfinite(latency).any() else float('nan')
    return (f'| {kind} | {len(rows)} | {100 * reg:.1f}% | {seeing_share} ({int(seeing.sum())} frames) | {are:.2f} '
            f'| {100 * ate:.1f} | {wrong_share({"gross": gross, "localized": relocalized})} | {latency:.0f} |')


def _pooled(rows: list, key: str, count: str) -> float:
    """The share ``key`` over all rows' ``count`` items (rows without any skipped)."""
    from rfm_core.evaluation.suite import pooled_share  # noqa: PLC0415

    return pooled_share([r[key] for r in rows], [r[count] for r in rows])


def cmd_eval_trajectory(args) -> int:
    """ATE and RPE of a TUM trajectory against a TUM ground truth, as evo defines them."""
    from rfm_core.evaluation.tum import evaluate_tum  # noqa: PLC0415

    try:
        r = evaluate_tum(args.trajectory, args.ground_truth, args.align, args.delta, args.max_diff)
    except (OSError, ValueError) as exc:
        raise SystemExit(f'rfm eval-trajectory: {exc}') from None
    print(f"{r['associated']} of {r['poses']} poses associated with the ground truth ({r['ground_truth_poses']} "
          f"poses, within {r['max_diff_s']} s); alignment {r['alignment']}"
          + (f", scale {r['scale']:.4f}" if r['alignment'] == 'sim3' else ''))
    print('| error | rmse | mean | median | std | min | max |')
    print('|---|---|---|---|---|---|---|')
    for key, name in (('ape_translation_m', 'APE translation (m): ATE'), ('ape_rotation_deg', 'APE rotation (deg)'),
                      ('rpe_translation_m', f"RPE translation (m, {r['delta_frames']} frame)"),
                      ('rpe_rotation_deg', f"RPE rotation (deg, {r['delta_frames']} frame)")):
        st = r[key]
        print(f'| {name} | ' + ' | '.join(f'{st[k]:.6f}' for k in ('rmse', 'mean', 'median', 'std', 'min', 'max'))
              + ' |')
    if args.json:
        Path(args.json).write_text(json.dumps(r, indent=1))
    return 0


def cmd_replay(args) -> int:
    """A graph run's recorded detections through the in-process back end again
    (rfm_core.evaluation.replay): two versions of the code compared on the same detections."""
    from rfm_core.evaluation.replay import replay_localization, replay_mapping, replay_session  # noqa: PLC0415

    work = Path(args.work)
    if not work.is_dir():
        raise SystemExit(f'rfm replay: {work} is not a directory (an rfm eval or rfm eval-reloc --work folder)')
    rows = []
    if args.reloc:
        from rfm_core.evaluation.suite import QUERY_CAPTURES, query_folders  # noqa: PLC0415
        rooms = [work / s for s in args.scenes] if args.scenes else sorted(p for p in work.iterdir() if p.is_dir())
        for kind in QUERY_CAPTURES:
            done = [room for room in rooms if query_folders(room, kind)[1].is_dir()]
            for room in done:
                r = replay_localization(room, kind, args.verbose)
                rows.append(r)
                print(f"{r['scene']:26s} {kind:8s} map {100 * r['map_registered']:3.0f}% registered  {r['found']:2d} "
                      f"of the {r['seeing']:2d} frames that see two mapped objects  relocalized {r['relocalized']:2d}"
                      f"  wrong {r['wrong']}  ARE {r['ARE_median']:5.2f} deg  ATE {100 * r['ATE_median']:5.1f} cm"
                      f"  within 2 sigma {100 * r['within_2sigma']:3.0f}%", flush=True)
            sel = [r for r in rows if r['query'] == kind]
            if sel:
                seeing, found = sum(r['seeing'] for r in sel), sum(r['found'] for r in sel)
                relocalized, wrong = sum(r['relocalized'] for r in sel), sum(r['wrong'] for r in sel)
                print(f'{kind} walks, {len(sel)} rooms: {100 * found / max(seeing, 1):.1f}% of the {seeing} frames '
                      f'that see two mapped objects; wrong {wrong} of {relocalized} '
                      f'({100 * wrong / max(relocalized, 1):.1f}%); within their 2-sigma bound '
                      f'{100 * _pooled(sel, "within_2sigma", "covered"):.1f}%')
        sessions = [room for room in rooms if (query_folders(room, 'session')[1] / 'outputs.mcap').exists()]
        for room in sessions:
            r = replay_session(room, args.verbose)
            rows.append(r)
            print(f"{r['scene']:26s} session  {r['registered_seeing'] * r['seeing_mapped']:2.0f} of the "
                  f"{r['seeing_mapped']:2d} frames that see two mapped objects  wrong {r['gross']}  ARE "
                  f"{r['ARE_median']:5.2f} deg  ATE {100 * r['ATE_median']:5.1f} cm  loaded keyframes moved "
                  f"{r['moved_cm_max']:.1f} cm at most", flush=True)
        sel = [r for r in rows if r['query'] == 'session']
        if sel:
            seeing = sum(r['seeing_mapped'] for r in sel)
            found = sum(r['registered_seeing'] * r['seeing_mapped'] for r in sel if r['seeing_mapped'])
            print(f"second sessions, {len(sel)} rooms: {100 * found / max(seeing, 1):.1f}% of the {seeing} frames "
                  f"that see two mapped objects; wrong {sum(r['gross'] for r in sel)}")
    else:
        def recorded(scene):          # an rfm eval scene's run, or an rfm eval-reloc room's mapping walk
            return next(((run, bag) for run, bag in ((args.run, 'bag'), ('map_run', 'map_bag'))
                         if (scene / run / 'outputs.mcap').exists() and (scene / bag).exists()), None)
        scenes = [work / s for s in args.scenes] if args.scenes else sorted(
            p for p in work.iterdir() if p.is_dir() and recorded(p))
        for scene in scenes:
            folders = recorded(scene)
            if folders is None:
                raise SystemExit(f'rfm replay: {scene} holds no recorded run ({args.run}/outputs.mcap and bag/, '
                                 'or map_run/ and map_bag/)')
            r = replay_mapping(scene, *folders)
            rows.append(r)
            print(f"{r['scene']:26s} localized {100 * r['registered']:5.1f}%  ARE {r['ARE_median']:5.2f} deg  "
                  f"ATE {100 * r['ATE_median']:5.1f} cm  wrong {r['gross']} ({100 * r['wrong']:.1f}%)  on points "
                  f"{r['point_tracked']:4d}  keyframes {r['keyframes']}  published {r['published']} (wrong "
                  f"{r['published_gross']}, within 2 sigma {100 * r['within_2sigma']:3.0f}%, sigma "
                  f"{100 * r['sigma_m']:.1f} cm {r['sigma_deg']:.2f} deg)  three detections shared "
                  f"{100 * r['relatable'] / max(r['frames'], 1):.0f}%", flush=True)
        for capture in sorted({r['scene'].rsplit('_', 1)[-1] for r in rows}):
            sel = [r for r in rows if r['scene'].endswith('_' + capture)]
            print(f"{capture} ({len(sel)}): localized {100 * np.mean([r['registered'] for r in sel]):.1f}% (mean); "
                  f"ARE {np.nanmedian([r['ARE_median'] for r in sel]):.2f} deg, ATE "
                  f"{100 * np.nanmedian([r['ATE_median'] for r in sel]):.2f} cm, wrong "
                  f"{100 * np.mean([r['wrong'] for r in sel]):.1f}% (medians, mean; {sum(r['gross'] for r in sel)} "
                  f"frames); as published: {sum(r['published_gross'] for r in sel)} of "
                  f"{sum(r['published'] for r in sel)} wrong, "
                  f"{100 * _pooled(sel, 'within_2sigma', 'published'):.1f}% within their 2-sigma bound; "
                  f"{100 * sum(r['relatable'] for r in sel) / max(sum(r['frames'] for r in sel), 1):.1f}% of the "
                  'frames share three detections with another frame (the most a three-object edge can place)')
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=float))
    return 0


def cmd_params(args) -> int:
    """The nodes' parameters (rfm_core.config) as tables; --readme rewrites a README's."""
    from rfm_core.config import NODES, node_settings, update_parameter_tables  # noqa: PLC0415
    from rfm_core.settings import markdown_table  # noqa: PLC0415

    if args.readme:
        path = Path(args.readme)
        text = path.read_text()
        new = update_parameter_tables(text)
        if args.check:
            if new != text:
                print(f'rfm params: the parameter tables of {path} are out of date: rfm params --readme {path}')
                return 1
            return 0
        path.write_text(new)
        print(f'rfm params: {path}: parameter tables {"updated" if new != text else "already up to date"}')
        return 0
    for node in args.nodes or NODES:
        try:
            table = markdown_table(node_settings(node))
        except ValueError as exc:
            raise SystemExit(f'rfm params: {exc}') from None
        print(f'## {node}\n\n{table}')
    return 0


def cmd_run(args) -> int:
    """The detector -> matcher -> mapper graph on a bag or a live camera."""
    from rfm_bringup.run import run_graph  # noqa: PLC0415
    return run_graph(args)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog='rfm', description='rfm: Rooms from Motion for ROS 2')
    sub = parser.add_subparsers(dest='command', required=True)

    p = sub.add_parser('sim', help='render a synthetic RGB-D capture of a room into a bag')
    p.add_argument('output', help='bag directory to create')
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--style', choices=('plain', 'textured'), default='plain',
                   help='plain-painted (default) or textured room')
    p.add_argument('--capture', choices=('handheld', 'sparse', 'orbit', 'robot', 'outward'), default='handheld',
                   help='handheld walk, sparse photos, orbit, robot (a low, level camera on a base), or outward '
                        '(a walk near the centre looking out)')
    _add_scene_options(p)
    p.set_defaults(func=cmd_sim)

    p = sub.add_parser('sim-suite', help='render a suite of scenes (mixed styles and captures)')
    p.add_argument('output', help='directory to create, one bag per scene plus suite.json')
    p.add_argument('--count', type=int, default=20)
    p.add_argument('--first-seed', type=int, default=1000,
                   help='seed of the first scene (default 1000: disjoint from training seeds)')
    p.add_argument('--jobs', type=int, default=1, help='scenes rendered in parallel')
    _add_scene_options(p)
    p.set_defaults(func=cmd_sim_suite)

    p = sub.add_parser('play', help='play a bag with rclpy (raw CDR, recorded QoS, /clock)')
    p.add_argument('bag')
    p.add_argument('--rate', type=float, default=1.0, help='playback speed factor')
    p.add_argument('--start-offset', type=float, default=0.0, help='start this many s into the bag')
    p.add_argument('--loop', action='store_true', help='play again when the bag ends')
    p.add_argument('--topics', nargs='+', help='play only these topics')
    p.add_argument('--remap', nargs='+', metavar='FROM:=TO', help='publish FROM as TO')
    p.add_argument('--no-clock', action='store_true', help='do not publish /clock')
    p.add_argument('--clock-hz', type=float, default=40.0,
                   help='/clock rate (every node with use_sim_time wakes up for each /clock message)')
    p.add_argument('--wait-for', nargs='+', metavar='TOPIC[=N]',
                   help='before playing, wait (up to 30 s) until each of these bag topics has a subscriber '
                        '(TOPIC=N: N subscribers)')
    p.add_argument('--delay', type=float, default=0.0,
                   help='seconds to wait before playing (lets subscribers connect)')
    p.add_argument('--pace', nargs=2, metavar=('TOPIC', 'ANSWER'),
                   help='publish each TOPIC message (bag topic) only once the one before it is answered on ANSWER '
                        '(an rfm_msgs/FrameDetections stamped as it, e.g. /rfm/detections), at most 3 s later; '
                        '--rate is then an upper bound')
    p.add_argument('--quiet', action='store_true', help='no progress line')
    p.set_defaults(func=cmd_play)

    p = sub.add_parser('preview', help='write a PNG contact sheet (colour | depth) of a bag')
    p.add_argument('bag')
    p.add_argument('output', help='PNG file to write')
    p.add_argument('--frames', type=int, default=4, help='frames to show (default 4)')
    p.add_argument('--color-topic', help=f"default {CAMERA_TOPICS['color']}")
    p.add_argument('--depth-topic', help=f"default {CAMERA_TOPICS['depth']}")
    p.add_argument('--max-depth', type=float, default=6.0, help='depth shown as white (m)')
    p.set_defaults(func=cmd_preview)

    p = sub.add_parser('eval-detections',
                       help='per-frame AP/AR at 3D IoU 0.15/0.25 of a detector on bags with ground truth')
    p.add_argument('bags', nargs='+', help='bag directories or suite directories (suite.json)')
    p.add_argument('--backend', default='depth_clusters', choices=('depth_clusters', 'ground_truth'))
    p.add_argument('--preset', default='rgbd', help='ground_truth noise preset (perfect, rgbd, rgb)')
    p.add_argument('--stride', type=int, default=2, help='depth_clusters: use every n-th pixel')
    p.add_argument('--every', type=int, default=1, help='evaluate every n-th frame')
    p.add_argument('--max-frames', type=int, help='at most this many frames per bag')
    p.add_argument('--min-visibility', type=float, default=0.2,
                   help='ground truth seen less than this is ignored (default 0.2)')
    p.add_argument('--json', help='also write the results to this JSON file')
    p.set_defaults(func=cmd_eval_detections)

    p = sub.add_parser('eval-matching',
                       help='object matching and relative-pose accuracy on simulated frame pairs')
    p.add_argument('--inputs', nargs='+', default=['depth_clusters', 'ground_truth:perfect',
                                                   'ground_truth:rgbd', 'ground_truth:rgb'],
                   help='detector inputs: depth_clusters (depth_clusters:heuristic without the box refiner) '
                        'and/or ground_truth:PRESET')
    p.add_argument('--matchers', nargs='+', default=['learned', 'classical'],
                   choices=('learned', 'classical'))
    p.add_argument('--weights', help='learned matcher checkpoint (default: the shipped one per detector)')
    p.add_argument('--scenes', type=int, default=8)
    p.add_argument('--first-seed', type=int, default=2000,
                   help='first scene seed (default 2000: disjoint from training, tuning and the suite)')
    p.add_argument('--frames', type=int, default=12, help='frames per scene (at 2 Hz)')
    p.add_argument('--gap', type=int, default=2, help='frames between the two of a pair (at 2 Hz)')
    p.add_argument('--world', choices=('boxes', 'realistic'), default='boxes', help='scenes (see rfm eval)')
    p.add_argument('--noise-seed', type=int, default=2)
    p.add_argument('--jobs', type=int, default=1, help='scenes rendered in parallel')
    p.set_defaults(func=cmd_eval_matching)

    p = sub.add_parser('train-depth-score', help="fit depth_clusters' calibrated detection score")
    p.add_argument('--scenes', type=int, default=32)
    p.add_argument('--first-seed', type=int, default=3000, help='training seeds start here (3000+)')
    p.add_argument('--frames', type=int, default=12, help='frames per scene (2 fps)')
    p.add_argument('--jobs', type=int, default=1)
    p.add_argument('--output', help='default: the shipped model in rfm_core/detection/weights')
    p.set_defaults(func=cmd_train_depth_score)

    p = sub.add_parser('train-box-refiner', help="train depth_clusters' learned box refiner on simulated scenes")
    p.add_argument('--scenes', type=int, default=600)
    p.add_argument('--first-seed', type=int, default=3000, help='training seeds start here (3000+)')
    p.add_argument('--frames', type=int, default=12, help='frames per scene, spread over the capture')
    p.add_argument('--epochs', type=int, default=20)
    p.add_argument('--batch-size', type=int, default=256)
    p.add_argument('--lr', type=float, default=2e-3)
    p.add_argument('--width', type=int, default=128, help='network width')
    p.add_argument('--seed', type=int, default=0, help='initialisation and shuffling')
    p.add_argument('--threads', type=int, default=2, help='torch CPU threads')
    p.add_argument('--jobs', type=int, default=2, help='scenes rendered in parallel')
    p.add_argument('--samples', help='cache of the rendered samples (.npz): read when it exists, else written')
    p.add_argument('--output', help='checkpoint to write (default: the shipped weights)')
    p.set_defaults(func=cmd_train_box_refiner)

    p = sub.add_parser('train-matcher',
                       help='train the learned object matcher on sim pairs through a detector backend')
    p.add_argument('--backend', choices=('depth_clusters', 'ground_truth'), default='depth_clusters')
    p.add_argument('--presets', nargs='+', default=['perfect', 'rgbd', 'rgb'],
                   help='ground_truth noise presets to mix')
    p.add_argument('--noise-draws', type=int, default=2,
                   help='ground_truth: noise draws per frame (different detector seeds)')
    p.add_argument('--scenes', type=int, default=60)
    p.add_argument('--first-seed', type=int, default=3000,
                   help='first scene seed (default 3000: disjoint from every evaluation)')
    p.add_argument('--frames', type=int, default=24, help='frames per scene (at 2 Hz)')
    p.add_argument('--world', choices=('boxes', 'realistic'), default='boxes',
                   help="scenes to train on: boxes (solid furniture) or realistic (rfm eval's default world)")
    p.add_argument('--epochs', type=int, default=12)
    p.add_argument('--batch-size', type=int, default=32)
    p.add_argument('--lr', type=float, default=3e-4)
    p.add_argument('--layers', type=int, default=3, help='self + cross attention blocks')
    p.add_argument('--seed', type=int, default=0, help='initialisation and shuffling')
    p.add_argument('--threads', type=int, default=2, help='torch CPU threads')
    p.add_argument('--jobs', type=int, default=2, help='scenes rendered in parallel')
    p.add_argument('--structure', action=argparse.BooleanOptionalAction, default=True,
                   help='depth_clusters: also teach matching detections that are no object but are '
                        'detected again at the same place (fragments, merged objects); see label_structure')
    p.add_argument('--output', help='checkpoint to write (default: the shipped weights of the backend)')
    p.set_defaults(func=cmd_train_matcher)

    p = sub.add_parser('eval', help="the paper's localization and mapping tables over generated scenes")
    p.add_argument('--scenes', type=int, default=20)
    p.add_argument('--first-seed', type=int, default=5000,
                   help='first scene seed (default 5000: disjoint from training, tuning and other suites)')
    p.add_argument('--frames', type=int, default=100,
                   help='frames per capture (realistic world: frames / fps seconds at the scene\'s rate; '
                        'sparse captures frames / 2 photos)')
    p.add_argument('--fps', type=float, default=10.0)
    p.add_argument('--capture', choices=('handheld', 'sparse', 'robot'),
                   help="every scene captured this way (default: the suite's mix)")
    p.add_argument('--world', choices=('realistic', 'boxes'), default='realistic',
                   help='realistic (default): furniture made of parts, clutter, the realsense sensor model on '
                        'half the scenes, robot cameras, 5-30 Hz, 320x240 and 640x480, 60-90 deg; boxes: the '
                        'solid-box world of earlier measurements')
    p.add_argument('--settings', nargs='+', help='only these settings: an exact name, or a part of names (e.g. rgbd)')
    p.add_argument('--jobs', type=int, default=1,
                   help='scenes evaluated in parallel (each graph in its own ROS domain)')
    p.add_argument('--offline', action='store_true',
                   help='in-process instead of through the node graph: every frame detected, the simulated '
                        'true gravity (for ablations; not what a user gets)')
    p.add_argument('--param', nargs='+', metavar='NODE.NAME:=VALUE', default=[],
                   help="passed to every rfm run (e.g. depth_clusters.box_refiner:='' for the heuristic "
                        'boxes); not with --offline')
    p.add_argument('--work', help='keep the scene bags and the rfm run outputs here (default: a temporary folder)')
    p.add_argument('--json', help='also write all results to this JSON file')
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser('eval-reloc', help='relocalization against a saved map over generated rooms')
    p.add_argument('--detector', default='depth_clusters', help='depth_clusters or ground_truth:PRESET')
    p.add_argument('--scenes', type=int, default=10)
    p.add_argument('--world', choices=('realistic', 'boxes'), default='realistic',
                   help="the rooms (as rfm eval's); boxes: the solid-box world of earlier measurements")
    p.add_argument('--offline', action='store_true',
                   help='in-process (every frame detected, true gravity) instead of through the node graph')
    p.add_argument('--work', help='keep the bags and rfm run outputs here (graph path; default: a temporary folder)')
    p.add_argument('--param', nargs='+', metavar='NODE.NAME:=VALUE',
                   help='passed to both rfm runs of each room (graph path), e.g. '
                        'mapper.relocalization.min_explained:=3')
    p.add_argument('--first-seed', type=int, default=5000)
    p.add_argument('--frames', type=int, default=150, help='frames of the mapping capture (a walk around the room)')
    p.add_argument('--fps', type=float, default=5.0, help='frame rate of the mapping capture (150 at 5 fps: 30 s)')
    p.add_argument('--query-frames', type=int, default=20, help='frames of each query walk (at 2 Hz)')
    p.add_argument('--queries', nargs='+', choices=('handheld', 'outward', 'session'),
                   default=['handheld', 'outward', 'session'],
                   help='protocols: query walks in localization mode, handheld (another walk around the room, as '
                        'the map was captured) and outward (from near its centre, looking out: the other side of '
                        'the objects); session: the outward walk mapped as a second session on the loaded map')
    p.add_argument('--jobs', type=int, default=1)
    p.set_defaults(func=cmd_eval_reloc)

    p = sub.add_parser('eval-trajectory', help="ATE and RPE of a TUM trajectory against a TUM ground truth (evo's "
                                               'definitions)')
    p.add_argument('trajectory', help="the estimate, TUM format (timestamp tx ty tz qx qy qz qw; rfm run's "
                                      'trajectory.tum)')
    p.add_argument('ground_truth', help="the ground truth, TUM format (TUM RGB-D's groundtruth.txt)")
    p.add_argument('--align', choices=('se3', 'sim3', 'yaw', 'none'), default='se3',
                   help='alignment of the estimate: se3 (Umeyama), sim3 (and scale), yaw (about z, and a '
                        'translation: a gravity-aligned map) or none')
    p.add_argument('--delta', type=int, default=1, help='RPE over this many frames')
    p.add_argument('--max-diff', type=float, default=0.01, help='association: largest stamp difference (s)')
    p.add_argument('--json', help='also write the results to this JSON file')
    p.set_defaults(func=cmd_eval_trajectory)

    p = sub.add_parser('replay', help="a graph run's recorded detections through the in-process back end again")
    p.add_argument('work', help="an rfm eval --work folder, or an rfm eval-reloc --work folder (its rooms' mapping "
                                'walks; with --reloc their query walks and second sessions)')
    p.add_argument('--reloc', action='store_true',
                   help="rfm eval-reloc's rooms: their query walks against their maps, their second sessions on them")
    p.add_argument('--scenes', nargs='*', help='scene folders of WORK (default: all with a recorded run)')
    p.add_argument('--run', default='rgb_d__depth_clusters', help="the run's folder in each scene")
    p.add_argument('--verbose', action='store_true',
                   help='--reloc: each missed and wrong frame (second sessions: each wrong one)')
    p.add_argument('--json', help='also write the per-scene results to this JSON file')
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser('params', help="the nodes' parameters with defaults and descriptions (markdown)")
    p.add_argument('nodes', nargs='*', metavar='NODE',
                   help='detector, matcher and/or mapper (default: all)')
    p.add_argument('--readme', metavar='FILE', help='rewrite the generated parameter tables of this README')
    p.add_argument('--check', action='store_true', help='with --readme: only check them (exit 1 if stale)')
    p.set_defaults(func=cmd_params)

    p = sub.add_parser('run', help='run detector -> matcher -> mapper on a bag (--bag) or live camera (--live)')
    p.add_argument('--bag', help='rosbag2 directory or ROS 1 .bag file to replay (uses /clock and sim time)')
    p.add_argument('--ground-truth-tf', metavar='WORLD:CAMERA_FRAME',
                   help="a ROS 1 bag's ground truth in its /tf: the camera frame's pose in the world frame at each "
                        'colour image (TUM RGB-D: world:openni_rgb_optical_frame); the report scores against it')
    p.add_argument('--live', action='store_true', help='subscribe to live camera topics until Ctrl-C')
    p.add_argument('--record-images', type=float, nargs='?', const=500.0, default=None, metavar='MB',
                   help='with --live: also record the colour images into outputs.mcap, at most MB megabytes '
                        '(default 500); off by default')
    p.add_argument('--output', help='output folder (default rfm_output/<bag name>)')
    p.add_argument('--force', action='store_true', help='replace an existing output folder')
    defaults = RfmConfig()
    p.add_argument('--backend', default=defaults.detector.backend, choices=BACKENDS)
    p.add_argument('--preset', default=defaults.detector.ground_truth.preset, choices=PRESETS,
                   help='ground_truth noise preset')
    p.add_argument('--cutr-checkpoint', help='cutr: path to cutr_rgb.pth / cutr_rgbd.pth')
    p.add_argument('--matcher', default=defaults.matcher.matcher, choices=MATCHERS)
    p.add_argument('--posed', action='store_true',
                   help="posed mapping: poses from the bag's /ground_truth/camera_pose (as rfm/external_pose)")
    p.add_argument('--processes', action=argparse.BooleanOptionalAction, default=True,
                   help='the nodes as three processes over DDS (the default: no node waits for another\'s '
                        'interpreter lock); --no-processes: all in this process (one interpreter, less memory)')
    p.add_argument('--rate', type=float, help='bag playback speed (default 1; with --paced, 8: an upper bound)')
    p.add_argument('--paced', action='store_true',
                   help='as fast as the graph takes it: each colour image played once the detector answered the '
                        'one before (a photo collection, or a bag on a slow machine: no view lost to a busy '
                        'detector); --rate bounds it')
    p.add_argument('--remap', nargs='+', metavar='FROM:=TO',
                   help='detector input remaps (defaults: RealSense-style /camera/... and /imu/data)')
    p.add_argument('--param', nargs='+', metavar='NODE.NAME:=VALUE',
                   help='node parameters, e.g. matcher.keyframes.max_translation_m:=0.3 (NODE.NAME), or matching.inlier_iou:=0.3 for every node that has it; rfm params lists them')
    p.add_argument('--settle', type=float, default=3.0,
                   help='after the bag ends, stop once nothing changed for this long (s)')
    p.add_argument('--quiet', action='store_true', help='no progress line')
    p.set_defaults(func=cmd_run)

    p = sub.add_parser('convert', help='an RGB-D dataset folder (TUM RGB-D, or the generic layout) as a bag '
                                       'for rfm run --bag')
    p.add_argument('folder', help='a TUM RGB-D sequence folder (rgb.txt, depth.txt, ...) or a generic one '
                                  '(the same files and camera.yaml; README, "Running on your own data")')
    p.add_argument('--output', help='bag directory to create (default bags/<folder name>)')
    p.add_argument('--force', action='store_true', help='replace an existing output')
    p.add_argument('--intrinsics', type=float, nargs=4, metavar=('FX', 'FY', 'CX', 'CY'),
                   help="the colour camera's intrinsics (default: camera.yaml's, or TUM's for its camera)")
    p.add_argument('--accel-axes', help="per optical axis (x right, y down, z forward), the IMU file's axis that "
                                        "measures it, e.g. 'x,y,z' (the default) or '-y,x,z'")
    p.add_argument('--max-difference', type=float, default=0.02,
                   help='pair a colour image with the depth image nearest in time within this (s)')
    p.add_argument('--quiet', action='store_true', help='no progress line')
    p.set_defaults(func=cmd_convert)

    p = sub.add_parser('record', help='record topics to an MCAP bag until Ctrl-C')
    p.add_argument('output', help='bag directory to create')
    p.add_argument('--topics', nargs='+', help='topics to record (default: all)')
    p.add_argument('--force', action='store_true', help='overwrite existing output')
    p.set_defaults(func=cmd_record)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == '__main__':
    sys.exit(main())
