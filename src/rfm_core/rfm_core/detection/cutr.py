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
        import torch.nn.functional as F  # noqa: PLC0415

        from rfm_core.detection.cutr_model import preprocess  # noqa: PLC0415

        cfg = self.config
        frame.validate(needs_depth=self.needs_depth)
        if frame.rgb is None:
            raise ValueError('CuTR needs a colour image')
        rgb = frame.rgb
        h, w = rgb.shape[:2]
        intr = frame.intrinsics
        k = intr.matrix.copy()
        scale = min(1.0, cfg.max_side_px / max(h, w))
        if scale < 1.0:
            nh, nw = int(round(h * scale)), int(round(w * scale))
            t = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None].float()
            rgb = F.interpolate(t, size=(nh, nw), mode='bilinear', align_corners=False)[0]
            rgb = rgb.clamp(0, 255).round().byte().permute(1, 2, 0).numpy()
            k[:2] *= np.array([[nw / w], [nh / h]])
            h, w = nh, nw
        depth = frame.depth if self.needs_depth else None
        if depth is not None and depth.shape[1] > w:          # keep depth <= image size
            step = int(np.ceil(depth.shape[1] / w))
            depth = depth[::step, ::step]
        device = next(self.model.parameters()).device
        image, d, stats = preprocess(rgb, depth)
        with torch.no_grad():
            out = self.model(image.to(device), k, None if d is None else d.to(device), stats,
                             gravity=frame.gravity_cam, image_size=(h, w))
        out = {key: v.detach().cpu().double().numpy() for key, v in out.items()}
        keep = out['pred_classes'] == 0                     # class 0 = object (supervised)
        boxes3d, rot = out['pred_boxes_3d'][keep], out['pred_rotation'][keep]
        aligned = gravity_aligned_rotation(frame.gravity_cam)
        boxes = boxes_from_oriented(boxes3d[:, :3] @ aligned.T, aligned @ rot, boxes3d[:, 3:6]) \
            if len(boxes3d) else np.zeros((0, 7))
        emb = out['object_desc'][keep]
        emb = emb / np.maximum(np.linalg.norm(emb, axis=1, keepdims=True), 1e-9)
        boxes_2d = out['pred_boxes'][keep] / scale
        return finalize(frame, boxes, out['scores'][keep], [''] * len(boxes), emb, boxes_2d,
                        cfg, self.name)
