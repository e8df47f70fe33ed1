"""Every matching threshold, with the paper's defaults, in one place."""
from __future__ import annotations

from dataclasses import dataclass, replace

from rfm_core.settings import setting

__all__ = ['MatchingConfig', 'MONOCULAR_RANGE_ERROR', 'monocular']


@dataclass(frozen=True)
class MatchingConfig:
    # object matching (3.2)
    match_threshold: float = setting(0.5, 'Keep object matches scoring at least this', lo=0.0, hi=1.0,
                                     paper='0.5 on CA-1M (0.4 on ScanNet++)')
    size_ratio_gate: float = setting(0.5, 'Classical matcher: minimum size similarity (min/max per sorted '
                                     'axis) of a match', lo=0.0, hi=1.0)
    # relative pose and verification (3.4)
    inlier_iou: float = setting(0.25, 'A match is an inlier when its transferred box overlaps its match with '
                                'IoU3D >= this', lo=0.0, hi=1.0, paper=0.25)
    min_inlier_ratio: float = setting(0.5, 'A relative pose needs this share of all matches as inliers',
                                      lo=0.0, hi=1.0, paper=0.5)
    corner_inlier_m: float = setting(0.10, 'Corner inlier distance kept for bundle adjustment (m)',
                                     lo=0.0, hi=1.0, paper=0.10)
    min_matches: int = setting(2, 'Matched objects of a minimal sample', lo=2, hi=10, paper=2)
    size_consistency: float = setting(0.35, 'Max relative footprint-size difference of a box pair under a yaw '
                                      'hypothesis (rejects quarter-turn aliases of non-square boxes)',
                                      lo=0.0, hi=10.0)
    refine: bool = setting(True, 'Refit the winning pose on all inlier matches; kept if it explains them as '
                           'well (not in the paper)')
    refine_sigma_m: float = setting(0.02, "Refit weights: a detection's error at the camera (m) ...",
                                    lo=0.001, hi=1.0)
    refine_sigma_per_m: float = setting(0.01, '... growing by this per metre of range', lo=0.0, hi=1.0)
    face_sigma_deg: float = setting(2.0, "A box's yaw error (deg), where the boxes' orientations give a relative "
                                    "pose's yaw: its prior in an edge's uncertainty (mapper "
                                    'averaging.edge_weights: uncertainty)', lo=0.01, hi=45.0)
    refine_yaw: str = setting('faces', "The refit's yaw: 'centres' (from the spread of the inlier boxes' "
                              "centres) or 'faces' (the boxes' own orientations, robustly averaged: partial "
                              'boxes, whose centres shift towards the camera that saw them, cannot turn it)',
                              choices=('centres', 'faces'))
    range_error: float = setting(0.0, "Relative error of the detector's distances along the viewing ray: 0 "
                                 'for a depth sensor; an RGB-only detector (cutr RGB, ground_truth rgb) '
                                 'misjudges distance, ~0.03: verification then lets a box slide along its '
                                 'ray by that much and the refit weights each match by its along-ray '
                                 'covariance', lo=0.0, hi=1.0)
    range_error_per_m: float = setting(0.0, '... growing by this per metre of range (~0.01 for an RGB-only '
                                       'detector)', lo=0.0, hi=1.0)
    refine_max_error_increase: float = setting(0.0, 'Keep an isotropic refit only if the mean box error (1 - '
                                               'IoU3D) grows by at most this (< 0: always); an along-ray refit '
                                               'is kept whenever it verifies', lo=-1.0, hi=1.0)
    height_tolerance_m: float = setting(0.2, "A relative pose's vertical translation is the difference of the two "
                                        "frames' camera heights above the floor where both measured it "
                                        '(FrameDetections.camera_height: the floor plane fixes a height to about '
                                        "a centimetre, box centres to several) and it is within this of the boxes' "
                                        '(m): a larger disagreement means a frame took another surface for the '
                                        'floor (0: boxes only)', lo=0.0, hi=10.0)
    wall_tolerance_m: float = setting(0.3, "A relative pose's horizontal translation is corrected along the "
                                      'normals of walls both frames measured (FrameDetections.walls: a wall plane '
                                      'fixes the distance to it to about a centimetre, boxes the border cuts or '
                                      'partly hidden to several) where the boxes put the two planes within this '
                                      'of each other (m) and their normals within wall_tolerance_deg (0: boxes '
                                      'only)', lo=0.0, hi=10.0)
    wall_tolerance_deg: float = setting(10.0, '... and their normals within this (deg)', lo=0.0, hi=90.0)
    wall_yaw_sigma_deg: float = setting(0.2, "Error of the yaw between two frames one wall's normals give (deg): "
                                        "against box_yaw_sigma_deg, how far walls turn a relative pose's yaw",
                                        lo=1e-3, hi=90.0)
    box_yaw_sigma_deg: float = setting(1.0, "Error of a relative pose's yaw from its boxes (deg), as it is weighed "
                                       'against walls', lo=1e-3, hi=90.0)
    wall_sigma_m: float = setting(0.02, "A wall plane's offset error (m): against box_translation_sigma_m, how "
                                  "far a wall moves the boxes' translation along its normal", lo=1e-4, hi=10.0)
    box_translation_sigma_m: float = setting(0.1, "Error of the boxes' horizontal translation (m), per axis, as "
                                             'it is weighed against walls', lo=1e-4, hi=10.0)
    # depth points (not in the paper): matching.points
    point_refine: bool = setting(True, "Refine each relative pose on the two frames' depth points "
                                 '(FrameDetections.cloud): 4-DoF point-to-plane ICP from the pose the boxes, floor '
                                 'and walls give. Boxes the image border cuts move from view to view; the '
                                 "surfaces do not. Frames without clouds keep the boxes' pose")
    point_search_m: float = setting(0.25, '... first correspondence distance (m), halved down to point_match_m',
                                    lo=0.01, hi=2.0)
    point_match_m: float = setting(0.05, '... final correspondence distance (m): a point within it of the other '
                                   "frame's surface overlaps", lo=0.005, hi=1.0)
    point_min_overlap: float = setting(0.15, '... kept when at least this share of the points overlaps (however '
                                       "that compares with the boxes' pose: BENCHMARKS.md, session 32)",
                                       lo=0.0, hi=1.0)
    point_max_correction_m: float = setting(1.0, "... and it moves the boxes' pose by at most this (m)",
                                            lo=0.0, hi=10.0)
    point_max_correction_deg: float = setting(20.0, '... and turns it by at most this (deg)', lo=0.0, hi=180.0)
    point_tracking: bool = setting(True, 'Within a stream, a frame that objects do not localize (too few '
                                   'detections, tracking failed, or a frame the detector sent with its depth points '
                                   'only) is tracked on its depth points: aligned from the pose the gyroscope and the '
                                   "recent motion predict to the reference keyframe's (matcher) or the map's, then "
                                   "the nearest map keyframes' (localization mode), in 4-DoF and in 6-DoF (the two "
                                   "frames' gravity may differ by a degree or two), the alignment with more points on "
                                   'surfaces kept (of those that fix every direction, if one does); it becomes no '
                                   'keyframe (not in the paper)')
    point_track_min_overlap: float = setting(0.25, '... kept when at least this share of its points lie on the '
                                             "keyframe's surfaces (within point_match_m; a share of what those "
                                             "surfaces can hold: divided by the share of the keyframe's own points "
                                             'on a surface, lower for noisy depth), the motion is plausible, and '
                                             'the points fix every direction (the matcher: all but one, which keeps '
                                             'the prediction within keyframes.max_motion_edge_s of the last frame '
                                             'placed in full). On '
                                             'tuning scenes poses the points fix in full were within 2 deg / 5 cm of '
                                             'the truth at every overlap from 0.2 (BENCHMARKS.md, session 30)',
                                             lo=0.0, hi=1.0)

    @property
    def along_rays(self) -> bool:
        """Whether detections err along their viewing rays (a range error is set)."""
        return self.range_error > 0 or self.range_error_per_m > 0


#: An RGB-only detector's distance error along the viewing ray, relative: 3% + 1% per metre
#: (the ``ground_truth:rgb`` preset's, not measured on a real monocular detector).
MONOCULAR_RANGE_ERROR = (0.03, 0.01)


def monocular(config: MatchingConfig) -> MatchingConfig:
    """``config`` for a detector that judges distance from RGB alone (unless already set)."""
    if config.along_rays:
        return config
    return replace(config, range_error=MONOCULAR_RANGE_ERROR[0], range_error_per_m=MONOCULAR_RANGE_ERROR[1])
