"""The flange detector's parameters (:class:`DetectParams`) and their presets per scanner model.

Apart from :mod:`celld.calib.detect` so that the detector's coarse pass
(:mod:`celld.calib.segment`) and every caller can read them without an
import circle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from celld.errors import InputError


@dataclass(frozen=True)
class DetectParams:
    """Parameters of :func:`detect_flange`; SI units.

    The defaults are the paper's for a structured-light scanner (section
    3.2.2: e_d = 0.3 mm, e_r = 1 mm, k_max = 10 000); see
    :data:`PARAMS_BY_SCANNER` for a time-of-flight camera.

    Attributes
    ----------
    e_d : float
        Inlier distance of a rim point to the circle, m.
    e_r : float
        Tolerance of the fitted radius around the model's ``circle_radius``, m.
    k_max : int
        Most RANSAC triples per circle fit.
    e_plane : float
        Inlier distance to the face plane in the fine pass, m. Above half the
        bore depth the bore cannot be told from the face and the bore check
        is skipped.
    e_plane_coarse : float
        Inlier distance of the coarse plane segmentation, m.
    crop_min, crop_max : tuple of 3 float, or None
        Workspace box in the camera frame, m; None for no box.
    roi_radius : float
        Radius of the sphere kept around ``roi_center``, m.
    coarse_points : int
        Size the coarse pass thins the cloud to.
    max_planes : int
        Most planes segmented in the coarse pass.
    size_tol : float
        A cluster may be at most ``2 R (1 + size_tol)`` wide (the paper's constraint) ...
    min_extent : float
        ... and at least ``2 R min_extent`` (a flange seen in part).
    cluster_eps : float
        DBSCAN radius in units of the point spacing.
    outlier_neighbours, outlier_std : int, float
        Statistical outlier filter: neighbours and the std-dev ratio.
    min_coverage : float
        Fraction of the circumference the rim inliers must cover.
    min_inliers : int
        Fewest rim inliers of an accepted circle.
    hollow_fraction : float
        The bore may hold at most this fraction of the points a solid face would have there.
    max_range_bias : float
        Largest range bias between bare metal and paint the scanner may show,
        m (0 for structured light). When positive the step check compares
        surfaces of one finish only (:func:`celld.calib.segment.hollow`): a
        time-of-flight camera reads the metal face of a UR flange below its
        painted shoulder.
    seed : int
        Seed of every random choice (RANSAC samples, subsets).
    """

    e_d: float = 0.0003
    e_r: float = 0.001
    k_max: int = 10_000
    e_plane: float = 0.0005
    e_plane_coarse: float = 0.002
    crop_min: tuple[float, float, float] | None = None
    crop_max: tuple[float, float, float] | None = None
    roi_radius: float = 0.12
    coarse_points: int = 12_000
    max_planes: int = 12
    size_tol: float = 0.15
    min_extent: float = 0.5
    cluster_eps: float = 2.5
    outlier_neighbours: int = 8
    outlier_std: float = 2.5
    min_coverage: float = 0.5
    min_inliers: int = 30
    hollow_fraction: float = 0.2
    max_range_bias: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        positive = ("e_d", "e_r", "e_plane", "e_plane_coarse", "roi_radius", "size_tol", "cluster_eps", "outlier_std")
        for key in positive:
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"DetectParams.{key}: expected a positive number, got {value!r}")
        for key in ("k_max", "coarse_points", "max_planes", "outlier_neighbours", "min_inliers"):
            if getattr(self, key) < 1:
                raise InputError(f"DetectParams.{key}: expected a positive integer, got {getattr(self, key)!r}")
        if not 0 < self.min_extent <= 1 or not 0 < self.min_coverage <= 1 or not 0 <= self.hollow_fraction <= 1:
            raise InputError("DetectParams: min_extent, min_coverage and hollow_fraction are fractions in (0, 1]")
        if not (math.isfinite(self.max_range_bias) and 0.0 <= self.max_range_bias < 0.1):
            raise InputError(f"DetectParams.max_range_bias: expected 0 <= bias < 0.1 m, got {self.max_range_bias!r}")
        if (self.crop_min is None) != (self.crop_max is None):
            raise InputError("DetectParams: give both crop_min and crop_max, or neither")
        if self.crop_min is not None and not all(a < b for a, b in zip(self.crop_min, self.crop_max)):  # type: ignore[arg-type]
            raise InputError(f"DetectParams: crop_min {self.crop_min} must be below crop_max {self.crop_max}")


# Parameters per scanner model. Time of flight: mm noise, so wide tolerances,
# a plane slab thick enough to take the face and the wrist shoulder as one,
# and a range bias on metal of up to 20 mm (users report 8-15 mm on the
# Azure Kinect, research/handeye_anchors.md section 4).
PARAMS_BY_SCANNER: dict[str, DetectParams] = {
    "phoxi-s": DetectParams(),
    "phoxi-m": DetectParams(),
    "azure-kinect": DetectParams(
        e_d=0.003,
        e_r=0.005,
        e_plane=0.008,
        e_plane_coarse=0.010,
        min_coverage=0.4,
        cluster_eps=3.0,
        coarse_points=40_000,  # a 640 x 576 image: thin it less, the flange is small in it
        max_range_bias=0.020,
    ),
}
