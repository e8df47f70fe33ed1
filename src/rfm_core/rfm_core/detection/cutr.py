"""`cutr`: the Cubify Transformer detector (paper section 3.1) behind the Detector interface.

The official checkpoints (``cutr_rgb.pth``, ``cutr_rgbd.pth``) are under Apple's research-only
model licence: rfm does not ship them. Obtain them from the apple/ml-cubifyanything project
and pass their path (``checkpoint``). The variant (RGB or RGB-D) is read from the checkpoint;
the RGB-D model gets the registered depth image, the RGB model never does.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rfm_core.detection.base import Detector, DetectorConfig, DetectorInput, finalize
from rfm_core.geometry import boxes_from_oriented, gravity_aligned_rotation
from rfm_core.observations import FrameObservations
from rfm_core.settings import setting

__all__ = ['CutrConfig', 'CutrDetector', 'load_cutr']

_HOW_TO_GET = ('The CuTR weights (cutr_rgb.pth / cutr_rgbd.pth) are released by the '
               'apple/ml-cubifyanything project under a research-only licence and are not '
               'shipped with rfm: download them there and set the checkpoint parameter to the file.')


@dataclass(frozen=True)
class CutrConfig(DetectorConfig):
    checkpoint: str = setting('', 'Path to cutr_rgb.pth or cutr_rgbd.pth (not shipped: research licence; the '
                              'variant is read from the file)', read_only=True)
    device: str = setting('cpu', 'Torch device: cpu, cuda, cuda:1, ...', read_only=True)
    max_side_px: int = setting(1024, 'Resize so the long image side is at most this (px)', lo=32, hi=1024)


def load_cutr(path, device: str = 'cpu'):
    """A CubifyTransformer with the weights at ``path`` (strict key matching), in eval mode."""
    import torch  # noqa: PLC0415

    from rfm_core.detection.cutr_model import CubifyTransformer  # noqa: PLC0415

    path = Path(path) if path else None
    if path is None or not path.is_file():
        raise FileNotFoundError(f'no CuTR checkpoint at {str(path) if path else "(unset)"}. {_HOW_TO_GET}')
    ckpt = torch.load(path, map_location='cpu', weights_only=True)
    state = ckpt.get('model', ckpt) if isinstance(ckpt, dict) else None
    if not isinstance(state, dict) or not state:
        raise ValueError(f'{path} holds no state_dict (expected a dict with a "model" entry)')
    model = CubifyTransformer(rgbd=CubifyTransformer.is_rgbd_state_dict(state))
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise ValueError(f'{path} is not a CuTR checkpoint this implementation can load '
                         f'strictly: {str(exc)[:500]}') from exc
    return model.to(device).eval()


class CutrDetector(Detector):
    name = 'cutr'

    def __init__(self, config: CutrConfig | None = None, model=None):
        self.config = config or CutrConfig()
        if not 32 <= self.config.max_side_px <= 1024:
            raise ValueError('max_side_px must be within 32..1024')
        self.model = model if model is not None else load_cutr(self.config.checkpoint, self.config.device)
        self.needs_depth = bool(self.model.rgbd)
        self.monocular = not self.needs_depth

    def detect(self, frame: DetectorInput) -> FrameObservations:
        import torch  # noqa: PLC0415

        from rfm_core.detection.cutr_model import preprocess  # noqa: PLC0415

        cfg = self.config
        frame.validate(needs_depth=self.needs_depth)
        if frame.rgb is None:
            raise ValueError('CuTR needs a colour image')
        rgb, k, (sy, sx) = fit_image(frame.rgb, frame.intrinsics.matrix.copy(), cfg.max_side_px,
                                     multiple=DEPTH_RATIO if self.needs_depth else 1)
        h, w = rgb.shape[:2]
        # the released RGB-D weights saw depth at a quarter of the image's resolution (CA-1M)
        depth = block_median(frame.depth, h // DEPTH_RATIO, w // DEPTH_RATIO) if self.needs_depth else None
        device = next(self.model.parameters()).device
        image, d, stats = preprocess(rgb, depth)
        with torch.no_grad():
            out = self.model(image.to(device), k, None if d is None else d.to(device), stats,
                             gravity=frame.gravity_cam, image_size=(h, w))
        out = {key: v.detach().cpu().double().numpy() for key, v in out.items()}
        # Both classes compete in the top 100, as in the official inference (only class 0 is
        # supervised, but its detections are kept on their score alike); a query that made it
        # with both classes is one box: keep its better score.
        order = np.argsort(-out['scores'], kind='stable')
        _, first = np.unique(out['pred_boxes_3d'][order].round(9), axis=0, return_index=True)
        keep = np.sort(order[first])
        boxes3d, rot = out['pred_boxes_3d'][keep], out['pred_rotation'][keep]
        aligned = gravity_aligned_rotation(frame.gravity_cam)
        boxes = boxes_from_oriented(boxes3d[:, :3] @ aligned.T, aligned @ rot, boxes3d[:, 3:6]) \
            if len(boxes3d) else np.zeros((0, 7))
        emb = out['object_desc'][keep]
        emb = emb / np.maximum(np.linalg.norm(emb, axis=1, keepdims=True), 1e-9)
        boxes_2d = out['pred_boxes'][keep] / np.array([sx, sy, sx, sy])
        return finalize(frame, boxes, out['scores'][keep], [''] * len(boxes), emb, boxes_2d,
                        cfg, self.name)


#: image width / depth width the released RGB-D weights were trained with (CA-1M: 1024 / 256)
DEPTH_RATIO = 4


def fit_image(rgb: np.ndarray, k: np.ndarray, max_side: int, multiple: int = 1):
    """The image CuTR takes: at most ``max_side`` px on the long side (bicubic with
    antialiasing, as the official pipeline resizes), both sides a multiple of ``multiple``
    (so that depth at 1/``multiple`` of it aligns exactly). Returns the image, its
    intrinsics and the (y, x) scale factors applied."""
    import torch  # noqa: PLC0415
    import torch.nn.functional as F  # noqa: PLC0415

    h, w = rgb.shape[:2]
    scale = min(1.0, max_side / max(h, w))
    nh = max(multiple, int(round(h * scale / multiple)) * multiple)
    nw = max(multiple, int(round(w * scale / multiple)) * multiple)
    if (nh, nw) == (h, w):
        return rgb, k, (1.0, 1.0)
    t = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None].float()
    t = F.interpolate(t, size=(nh, nw), mode='bicubic', align_corners=False, antialias=True)
    k = k.copy()
    k[0] *= nw / w
    k[1] *= nh / h
    return t[0].clamp(0, 255).round().byte().permute(1, 2, 0).numpy(), k, (nh / h, nw / w)


def block_median(depth: np.ndarray, hd: int, wd: int) -> np.ndarray:
    """``depth`` (H, W, metres; NaN or <= 0 invalid) resampled to (hd, wd): each cell the
    median of the valid pixels it covers (0 where none is valid)."""
    d = np.asarray(depth, dtype=np.float64)
    h, w = d.shape
    rows = np.minimum((np.arange(h) * hd) // h, hd - 1)
    cols = np.minimum((np.arange(w) * wd) // w, wd - 1)
    cell = (rows[:, None] * wd + cols[None, :]).ravel()
    values = d.ravel()
    valid = np.isfinite(values) & (values > 0)
    cell, values = cell[valid], values[valid]
    out = np.zeros(hd * wd)
    if len(values):
        order = np.lexsort((values, cell))
        cell, values = cell[order], values[order]
        counts = np.bincount(cell, minlength=hd * wd)
        start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        has = counts > 0
        lo = start[has] + (counts[has] - 1) // 2
        hi = start[has] + counts[has] // 2
        out[has] = (values[lo] + values[hi]) / 2
    return out.reshape(hd, wd).astype(np.float32)
