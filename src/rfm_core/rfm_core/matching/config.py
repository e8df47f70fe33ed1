"""Every threshold of object matching and relative poses (paper 3.2-3.4), with the paper's
defaults, in one place."""
from __future__ import annotations

from dataclasses import dataclass, replace

from rfm_core.settings import constant, setting

__all__ = ['MatchingConfig', 'MONOCULAR_RANGE_ERROR', 'monocular']


@dataclass(frozen=True)
class MatchingConfig:
    # object matching (3.2)
    match_threshold: float = setting(0.5, 'Keep object matches scoring at least this', lo=0.0, hi=1.0,
                                     paper='0.5 on CA-1M (0.4 on ScanNet++)')
    size_ratio_gate: float = constant(0.5, 'Classical matcher: least size similarity of a match (min/max per '
                                      'sorted axis)', lo=0.0, hi=1.0)
    # relative pose and verification (3.4)
    inlier_iou: float = setting(0.25, 'A match is an inlier when its transferred box overlaps its match with '
                                'IoU3D >= this', lo=0.0, hi=1.0, paper=0.25)
    min_inlier_ratio: float = setting(0.5, 'A relative pose needs this share of all matches as inliers',
                                      lo=0.0, hi=1.0, paper=0.5)
    corner_inlier_m: float = setting(0.10, 'Corner matches within this distance are kept for bundle adjustment '
                                     '(m)', lo=0.0, hi=1.0, paper=0.10)
    min_matches: int = setting(2, 'Matched objects in a minimal sample', lo=2, hi=10, paper=2)
    size_consistency: float = constant(0.35, 'Largest relative footprint-size difference of a box pair under a '
                                       'yaw hypothesis (rejects quarter-turn aliases of non-square boxes)',
                                       lo=0.0, hi=10.0)
    refine_sigma_m: float = constant(0.02, "Refit weights: a detection's error at the camera (m) ...",
                                     lo=0.001, hi=1.0)
    refine_sigma_per_m: float = constant(0.01, '... growing by this per metre of range', lo=0.0, hi=1.0)
    range_error: float = setting(0.0, "Relative error of the detector's distances along the viewing ray: 0 for "
                                 'a depth camera, about 0.03 for an RGB-only detector (cutr RGB); verification '
                                 'then lets a box slide along its ray by that much and the refit weighs each '
                                 'match by its along-ray covariance', lo=0.0, hi=1.0)
    range_error_per_m: float = setting(0.0, '... plus this per metre of range (about 0.01 for an RGB-only '
                                       'detector)', lo=0.0, hi=1.0)
    refine_max_error_increase: float = constant(0.0, 'Keep a refit only if the mean box error (1 - IoU3D) grows by '
                                                'at most this (< 0: always); an along-ray refit is kept whenever '
                                                'it verifies', lo=-1.0, hi=1.0)
    # the floor and the walls (not in the paper): matching.relative_pose.with_surfaces
    height_tolerance_m: float = constant(0.2, "A relative pose's height is the difference of the two frames' "
                                         'camera heights above the floor (FrameDetections.camera_height) where '
                                         "that is within this of the boxes' (m; 0: boxes only)", lo=0.0, hi=10.0)
    wall_tolerance_m: float = constant(0.3, "A relative pose's horizontal translation is corrected along the "
                                       'normals of walls both frames measured (FrameDetections.walls) where the '
                                       'boxes put the two planes within this of each other (m; 0: boxes only) ...',
                                       lo=0.0, hi=10.0)
    wall_tolerance_deg: float = constant(10.0, '... and their normals within this (deg)', lo=0.0, hi=90.0)
    wall_yaw_sigma_deg: float = constant(0.2, "Error of the yaw one wall's normals give between two frames (deg)",
                                         lo=1e-3, hi=90.0)
    box_yaw_sigma_deg: float = constant(1.0, "Error of a relative pose's yaw from its boxes (deg), as it is "
                                        'weighed against walls', lo=1e-3, hi=90.0)
    full_box_yaw_tolerance_deg: float = constant(3.0, "A separate view's pose from the objects' full boxes is kept "
                                                 'where two of its verified objects turn their fitted boxes (the '
                                                 'visible surfaces) by its yaw within this, up to a quarter turn, '
                                                 'and turned by their mean disagreement (deg; 0: never)',
                                                 lo=0.0, hi=45.0)
    wall_sigma_m: float = constant(0.02, "Error of a wall plane's offset (m)", lo=1e-4, hi=10.0)
    box_translation_sigma_m: float = constant(0.1, "Error of the boxes' horizontal translation per axis (m), as it "
                                              'is weighed against walls', lo=1e-4, hi=10.0)
    # depth points (not in the paper): matching.points
    point_search_m: float = constant(0.25, 'Point alignment: first correspondence distance (m), halved down to '
                                     'point_match_m', lo=0.01, hi=2.0)
    point_match_m: float = constant(0.05, "... final correspondence distance (m): a point this close to the other "
                                    "frame's surface overlaps it", lo=0.005, hi=1.0)
    point_min_overlap: float = constant(0.15, 'A relative pose refined on depth points is kept when at least this '
                                        'share of the points overlaps ...', lo=0.0, hi=1.0)
    point_max_correction_m: float = constant(1.0, "... and it moves the boxes' pose by at most this (m) ...",
                                             lo=0.0, hi=10.0)
    point_max_correction_deg: float = constant(20.0, '... and turns it by at most this (deg)', lo=0.0, hi=180.0)
    point_track_min_overlap: float = constant(0.25, 'A frame tracked on its depth points needs this share of them '
                                              "on the keyframe's surfaces (a share of what those surfaces can "
                                              "hold: lower for noisy depth)", lo=0.0, hi=1.0)
    point_track_max_free: int = constant(2, '... and may leave at most this many directions free (a wall alone: '
                                         'along it and up); they keep the motion prediction, and only within '
                                         'keyframes.max_motion_edge_s of the last frame placed in full', lo=0, hi=6)

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
