"""Depth image to organized cloud, for depth cameras (Azure Kinect, RealSense). Pure.

A depth camera gives a (H, W) image of raw depth units; with its pinhole
intrinsics each pixel unprojects to a point in the camera's optical frame
(OpenCV convention: x right, y down, z along the optical axis). Open3D's
tensor image does it: ``clip_transform`` scales to metres and marks depths
outside the kept range, ``create_vertex_map`` unprojects.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike

from celld.errors import InputError


def intrinsic_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """The (3, 3) pinhole matrix K of focal lengths and principal point, pixels."""
    if not (fx > 0.0 and fy > 0.0) or not np.all(np.isfinite([fx, fy, cx, cy])):
        raise InputError(f"intrinsics: expected positive finite fx, fy and finite cx, cy, got {fx}, {fy}, {cx}, {cy}")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def depth_to_points(depth: ArrayLike, K: ArrayLike, units_per_metre: float, depth_min: float, depth_max: float) -> np.ndarray:
    """Unproject a depth image to an organized cloud.

    Parameters
    ----------
    depth : array_like
        (H, W) uint16 or float32 depth along the optical axis, in the camera's
        raw unit; 0 means no return.
    K : array_like
        (3, 3) intrinsic matrix of the camera that took ``depth``, pixels.
    units_per_metre : float
        Raw depth units per metre (1000 for millimetres).
    depth_min, depth_max : float
        Kept depth range, metres; other pixels become NaN.

    Returns
    -------
    numpy.ndarray
        (H, W, 3) float32 points in the camera frame, metres, NaN where there
        is no return or the depth is out of range.
    """
    d = np.asarray(depth)
    if d.ndim != 2 or d.dtype not in (np.uint16, np.float32):
        raise InputError(f"depth image: expected an (H, W) uint16 or float32 array, got {d.dtype} {d.shape}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0.0 or K[1, 1] <= 0.0:
        raise InputError(f"depth intrinsics: expected a (3, 3) matrix with positive focal lengths, got {K.tolist()}")
    if not (units_per_metre > 0.0 and 0.0 <= depth_min < depth_max):
        raise InputError(
            f"depth scale and range: expected units_per_metre > 0 and 0 <= min < max, got {units_per_metre}, {depth_min}, {depth_max}"
        )
    image = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(d)))
    metres = image.clip_transform(units_per_metre, depth_min, depth_max, float("nan"))
    vertex_map = metres.create_vertex_map(o3d.core.Tensor(K), float("nan"))
    P = vertex_map.as_tensor().numpy().astype(np.float32, copy=False)
    # A zero depth is "no return" even when depth_min is 0.
    P[~(P[..., 2] > 0.0)] = np.nan
    return P
