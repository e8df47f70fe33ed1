"""CuTR: checkpoint-compatible module tree, output contract, strict reload, clear errors.

No official weights exist on these machines: the tests use random weights and the spec's
state_dict tables (docs/cutr/, copied from the spec)."""
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip('torch')

from rfm_core.detection.base import DetectorInput  # noqa: E402
from rfm_core.detection.cutr import CutrConfig, CutrDetector, load_cutr  # noqa: E402
from rfm_core.detection.cutr_model import CubifyTransformer, gravity_tensor, preprocess  # noqa: E402
from rfm_core.observations import CameraIntrinsics  # noqa: E402

SPEC = Path(__file__).resolve().parents[2] / 'docs' / 'cutr'


def spec_table(variant):
    keys = {}
    for line in (SPEC / f'cutr-state-dict-{variant}.tsv').read_text().splitlines():
        if line.startswith('#') or not line.strip():
            continue
        key, shape, _ = line.split('\t')
        keys[key] = tuple(int(v) for v in shape.strip('()').split(',') if v.strip())
    return keys


@pytest.fixture(scope='module')
def models():
    torch.manual_seed(0)
    return {'rgb': CubifyTransformer(rgbd=False).eval(), 'rgbd': CubifyTransformer(rgbd=True).eval()}


@pytest.mark.parametrize('variant,count,params', [('rgb', 498, 99_480_672), ('rgbd', 475, 99_173_472)])
def test_state_dict_keys_and_shapes_match_the_spec(models, variant, count, params):
    mine = {k: tuple(v.shape) for k, v in models[variant].state_dict().items()}
    spec = spec_table(variant)
    assert len(spec) == count
    assert set(mine) == set(spec)
    assert {k: mine[k] for k in spec} == spec
    assert sum(p.numel() for p in models[variant].parameters()) == params
    # the box encoder is one module serialised under three prefixes
    sd = models[variant].state_dict()
    for prefix in ('prompting.prompters.0.encoders.', 'prompting.prompters.1.encoders.'):
        assert torch.equal(sd[prefix + 'box_2d_encoder.x.weight'],
                           sd['prompting.encoders.box_2d_encoder.x.weight'])
    assert sd['prompting.encoders.box_2d_encoder.max_bounds'].tolist() == [1279.0] * 4


@pytest.mark.parametrize('variant', ['rgb', 'rgbd'])
def test_forward_on_a_512_pixel_image_gives_the_output_contract(models, variant):
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (384, 512, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 4.0, (96, 128)).astype(np.float32) if variant == 'rgbd' else None
    image, d, stats = preprocess(rgb, depth)
    assert image.shape == (1, 3, 512, 512)
    k = np.array([[400.0, 0, 256], [0, 400.0, 192], [0, 0, 1]])
    g = np.array([0.0, 0.96, 0.28])
    with torch.no_grad():
        out = models[variant](image, k, d, stats, gravity=g, image_size=(384, 512))
    shapes = {key: tuple(v.shape) for key, v in out.items()}
    assert shapes == {'scores': (100,), 'pred_classes': (100,), 'pred_boxes': (100, 4),
                      'pred_logits': (100, 2), 'pred_boxes_3d': (100, 6),
                      'pred_rotation': (100, 3, 3), 'pred_proj_xy': (100, 2),
                      'object_desc': (100, 256)}
    assert all(torch.isfinite(v.double()).all() for v in out.values())
    assert torch.all(out['scores'][:-1] >= out['scores'][1:])            # sorted
    boxes = out['pred_boxes']
    assert torch.all(boxes[:, [0, 2]] <= 512) and torch.all(boxes[:, [1, 3]] <= 384)
    rot = out['pred_rotation']
    eye = torch.eye(3, dtype=rot.dtype).expand_as(rot)
    assert torch.allclose(rot @ rot.transpose(1, 2), eye, atol=1e-6)
    # local y of every box is the gravity axis: T_gravity[:, 1] = g
    assert torch.allclose(rot[:, :, 1], torch.as_tensor(g / np.linalg.norm(g)).expand(100, 3), atol=1e-6)
    assert np.allclose(gravity_tensor(g)[:, 1], g / np.linalg.norm(g))
    assert np.allclose(gravity_tensor([0, 1, 0]), np.eye(3))
    if variant == 'rgbd':       # metric scale comes from the depth statistics
        assert stats[0] == pytest.approx(np.mean(np.sort(depth.ravel())[1228:11059]), rel=1e-3)


@pytest.mark.slow
def test_saved_state_dict_reloads_strictly_and_runs_as_a_detector(models, tmp_path):
    path = tmp_path / 'cutr_rgbd_random.pth'
    torch.save({'model': models['rgbd'].state_dict()}, path)
    model = load_cutr(path)
    assert model.rgbd
    for key, value in models['rgbd'].state_dict().items():
        assert torch.equal(model.state_dict()[key], value)
    detector = CutrDetector(CutrConfig(checkpoint=str(path), score_threshold=0.0), model=model)
    assert detector.needs_depth
    intr = CameraIntrinsics(250.0, 250.0, 159.5, 119.5, 320, 240)
    rng = np.random.default_rng(1)
    frame = DetectorInput(7, 'cam', intr, [0.0, 1.0, 0.0],
                          rng.integers(0, 256, (240, 320, 3), dtype=np.uint8),
                          rng.uniform(0.5, 4.0, (240, 320)).astype(np.float32))
    obs = detector.detect(frame)
    assert 0 < len(obs) <= 100 and obs.embeddings.shape == (len(obs), 256)
    np.testing.assert_allclose(np.linalg.norm(obs.embeddings, axis=1), 1.0, rtol=1e-5)
    assert obs.backend == 'cutr'


def test_missing_or_wrong_checkpoints_fail_with_instructions(tmp_path):
    with pytest.raises(FileNotFoundError, match='apple/ml-cubifyanything'):
        load_cutr(tmp_path / 'nope.pth')
    with pytest.raises(FileNotFoundError, match='not shipped'):
        CutrDetector(CutrConfig(checkpoint=''))
    broken = tmp_path / 'broken.pth'
    torch.save({'model': {'level_embed': torch.zeros(1, 256)}}, broken)
    with pytest.raises(ValueError, match='strictly'):
        load_cutr(broken)


# ---------------------------------------------------------------- the wrapper (#18 item 4)

def test_depth_reaches_the_rgbd_model_at_a_quarter_of_the_image_resolution(models):
    """(a) the released RGB-D weights saw depth at 1/4 of the image: registered full-resolution
    depth is resampled by the median of each 4x4 block's valid pixels before preprocessing."""
    from rfm_core.detection.cutr import block_median
    depth = np.full((8, 12), 2.0, np.float32)
    depth[:4, :4] = [[1, 1, 9, np.nan], [1, 1, 1, 0], [1, 1, 1, 1], [1, 1, 1, 1]]   # outliers, holes
    depth[4:, 8:] = np.nan                                                           # nothing valid
    small = block_median(depth, 2, 3)
    np.testing.assert_array_equal(small, [[1.0, 2.0, 2.0], [2.0, 2.0, 0.0]])
    seen = []
    model = models['rgbd']
    forward = model.forward
    model.forward = lambda *args, **kwargs: (seen.append((args, kwargs)), forward(*args, **kwargs))[1]
    try:
        detector = CutrDetector(CutrConfig(score_threshold=0.0), model=model)
        intr = CameraIntrinsics(250.0, 250.0, 159.5, 119.5, 320, 240)
        rng = np.random.default_rng(2)
        full = rng.uniform(0.5, 4.0, (240, 320)).astype(np.float32)
        detector.detect(DetectorInput(7, 'cam', intr, [0.0, 1.0, 0.0],
                                      rng.integers(0, 256, (240, 320, 3), dtype=np.uint8), full))
    finally:
        del model.forward
    (image, k, d, stats), kwargs = seen[0][0][:4], seen[0][1]
    assert image.shape[-1] == 384 and d.shape[-1] == 96            # S / 4 (padded to 32s), not S
    assert kwargs['image_size'] == (240, 320)
    expected = block_median(full, 60, 80)
    assert stats[0] == pytest.approx(np.sort(expected.ravel())[480:4320].mean(), rel=1e-6)


def test_depth_must_align_exactly_and_resizes_keep_it_aligned():
    """(b) a depth whose size is not exactly 1, 1/2 or 1/4 of the image's is refused; the
    wrapper resizes images to sides that are multiples of 4, so a quarter is exact."""
    from rfm_core.detection.cutr import fit_image
    rgb = np.zeros((240, 322, 3), np.uint8)
    with pytest.raises(ValueError, match='exactly 1, 1/2 or 1/4'):
        preprocess(rgb, np.ones((60, 80), np.float32))
    preprocess(rgb[:, :320], np.ones((60, 80), np.float32))
    k = np.array([[1000.0, 0, 640], [0, 1000.0, 480], [0, 0, 1]])
    small, k2, (sy, sx) = fit_image(np.zeros((962, 1283, 3), np.uint8), k, 1024, multiple=4)
    assert small.shape[0] % 4 == 0 and small.shape[1] % 4 == 0 and max(small.shape[:2]) <= 1024
    assert k2[0, 0] == pytest.approx(1000 * sx) and k2[1, 2] == pytest.approx(480 * sy)


def test_downscaling_antialiases():
    """(d) above 1024 px the image is resized with bicubic antialiasing, as the official
    pipeline does: a one-pixel checkerboard becomes grey, not a moire."""
    from rfm_core.detection.cutr import fit_image
    board = ((np.indices((1536, 2048)).sum(0) % 2) * 255).astype(np.uint8)
    small, _, _ = fit_image(np.repeat(board[..., None], 3, -1), np.eye(3), 1024)
    assert small.shape[:2] == (768, 1024)
    assert abs(small.mean() - 127.5) < 3 and small.std() < 3


def test_both_classes_are_kept_once_per_query_and_image_size_is_required(models):
    """(c) detections come from both classes' top 100, one box per query; (e) forward without
    image_size is an error, not padding taken for image."""
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    image, _, _ = preprocess(rgb)
    k = np.array([[250.0, 0, 159.5], [0, 250.0, 119.5], [0, 0, 1]])
    with pytest.raises(TypeError, match='image_size'):
        models['rgb'](image, k, gravity=[0.0, 1.0, 0.0])
    with torch.no_grad():
        out = models['rgb'](image, k, gravity=[0.0, 1.0, 0.0], image_size=(240, 320))
    classes = out['pred_classes'].numpy()
    assert set(classes) == {0, 1}                     # random weights: both classes compete
    detector = CutrDetector(CutrConfig(score_threshold=0.0), model=models['rgb'])
    obs = detector.detect(DetectorInput(1, 'cam', CameraIntrinsics(250.0, 250.0, 159.5, 119.5, 320, 240),
                                        [0.0, 1.0, 0.0], rgb))
    queries = len(np.unique(out['pred_boxes_3d'].numpy().round(9), axis=0))
    assert len(obs) == queries and len(obs) > int(np.sum(classes == 0))
    assert len(np.unique(obs.boxes.round(9), axis=0)) == len(obs)
