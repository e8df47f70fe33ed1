"""Every matching threshold, with the paper's defaults, in one place."""
from __future__ import annotations

from dataclasses import dataclass, replace

__all__ = ['MatchingConfig', 'MONOCULAR_RANGE_ERROR', 'monocular']


@dataclass(frozen=True)
class MatchingConfig:
    # object matching (3.2)
    match_threshold: float = 0.5          #: paper: 0.5 on CA-1M (0.4 on ScanNet++)
    size_ratio_gate: float = 0.5          #: classical: min/max size ratio per sorted axis
    # relative pose and verification (3.4)
    inlier_iou: float = 0.25              #: a match is an inlier when IoU3D >= this after transfer
    min_inlier_ratio: float = 0.5         #: a sample needs this share of all matches as inliers
    corner_inlier_m: float = 0.10         #: corner inliers (for bundle adjustment)
    min_matches: int = 2                  #: a minimal sample is two matched objects
    size_consistency: float = 0.35        #: max relative footprint-size difference of a box
                                          #: pair under a yaw hypothesis (yaw symmetry)
    refine: bool = True                   #: refit the winner on all inlier matches (not in the paper)
    refine_sigma_m: float = 0.02          #: refit weights: detection error at the camera ...
    refine_sigma_per_m: float = 0.01      #: ... growing by this per metre of range
    refine_range_error: float = 0.0       #: relative error of a detection's distance along its
                                          #: viewing ray: 0 for depth sensors; > 0 (monocular depth):
                                          #: verification lets a box slide along its ray by that
                                          #: much, and the refit uses every match consistent with
                                          #: the pose, each weighted by its along-ray covariance
    refine_range_error_per_m: float = 0.0  #: ... growing by this per metre of range
    refine_max_error_increase: float = 0.0   #: keep an isotropic refit only if the mean box error
                                          #: (1 - IoU3D) grows by at most this (< 0: always); an
                                          #: along-ray refit is kept whenever it verifies (box IoU
                                          #: penalises the likelier pose when distances are off)

    @property
    def along_rays(self) -> bool:
        """Whether detections err along their viewing rays (a range error is set)."""
        return self.refine_range_error > 0 or self.refine_range_error_per_m > 0


#: An RGB-only detector's distance error along the viewing ray, relative: 3% + 1% per metre
#: (the ``ground_truth:rgb`` preset's, not measured on a real monocular detector).
MONOCULAR_RANGE_ERROR = (0.03, 0.01)


def monocular(config: MatchingConfig) -> MatchingConfig:
    """``config`` for a detector that judges distance from RGB alone (unless already set)."""
    if config.along_rays:
        return config
    return replace(config, refine_range_error=MONOCULAR_RANGE_ERROR[0],
                   refine_range_error_per_m=MONOCULAR_RANGE_ERROR[1])
