"""SE(3) helpers on :class:`scipy.spatial.transform.Rotation`.

``T_a_b`` is the pose of frame b in frame a, a (4, 4) homogeneous matrix, so
``p_a = T_a_b @ p_b``. Points are ``(n, 3)`` arrays. UR poses are
``[x, y, z, rx, ry, rz]`` in metres with a rotation vector in radians.
Functions never modify their inputs. ``check_*`` functions validate data where
it enters and raise :class:`~celld.errors.InputError` that says what shape was
expected and what came.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from celld.errors import InputError

# scipy's Rotation is imported where it is used: loading a config (celld status,
# celld config check) checks transforms and reads UR poses, and importing
# scipy.spatial would more than double its time and memory.

# Tolerance on R^T R - I and det(R) - 1 for a matrix to count as a rotation.
_ROTATION_TOL = 1e-6

Array = NDArray[np.float64]


def check_transform(T: ArrayLike, name: str = "T") -> Array:
    """Return ``T`` as a float64 (4, 4) rigid transform, or raise InputError."""
    arr = np.asarray(T, dtype=np.float64)
    if arr.shape != (4, 4):
        raise InputError(f"{name}: expected a (4, 4) homogeneous matrix, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: contains NaN or infinite values")
    if not np.allclose(arr[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise InputError(f"{name}: last row must be [0, 0, 0, 1], got {arr[3].tolist()}")
    R = arr[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=_ROTATION_TOL) or abs(np.linalg.det(R) - 1.0) > _ROTATION_TOL:
        raise InputError(f"{name}: upper-left (3, 3) block is not a rotation matrix")
    return arr


def check_points(P: ArrayLike, name: str = "P", min_points: int = 0) -> Array:
    """Return ``P`` as a finite float64 (n, 3) array, or raise InputError."""
    arr = np.asarray(P, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name}: expected an (n, 3) array of points, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(arr), axis=1)))
        raise InputError(f"{name}: {bad} of {len(arr)} points contain NaN or infinite values")
    if len(arr) < min_points:
        raise InputError(f"{name}: expected at least {min_points} points, got {len(arr)}")
    return arr


def transform_from(R: ArrayLike, t: ArrayLike) -> Array:
    """Return the (4, 4) transform with rotation ``R`` (3, 3) and translation ``t`` (3,)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


def invert(T: ArrayLike) -> Array:
    """Return the inverse of a rigid transform: ``T_b_a`` from ``T_a_b``."""
    T = np.asarray(T, dtype=np.float64)
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def apply(T: ArrayLike, P: ArrayLike) -> Array:
    """Map points ``P_b`` (n, 3) to ``P_a`` with ``T_a_b``."""
    T = np.asarray(T, dtype=np.float64)
    P = np.asarray(P, dtype=np.float64)
    return P @ T[:3, :3].T + T[:3, 3]


def rotate(T: ArrayLike, v: ArrayLike) -> Array:
    """Rotate direction vectors ``v`` (n, 3) or (3,) by the rotation of ``T``."""
    T = np.asarray(T, dtype=np.float64)
    return np.asarray(v, dtype=np.float64) @ T[:3, :3].T


def from_ur_pose(pose: ArrayLike) -> Array:
    """Return ``T_base_tcp`` from a UR pose ``[x, y, z, rx, ry, rz]`` (m, rad)."""
    from scipy.spatial.transform import Rotation

    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (6,):
        raise InputError(f"UR pose: expected 6 values [x, y, z, rx, ry, rz], got shape {pose.shape}")
    return transform_from(Rotation.from_rotvec(pose[3:]).as_matrix(), pose[:3])


def from_ur_poses(poses: ArrayLike) -> Array:
    """Return the ``T_base_tcp`` (n, 4, 4) of n UR poses (n, 6) ``[x, y, z, rx, ry, rz]`` (m, rad), in one go."""
    from scipy.spatial.transform import Rotation

    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 6:
        raise InputError(f"UR poses: expected (n, 6) values [x, y, z, rx, ry, rz], got shape {poses.shape}")
    T = np.tile(np.eye(4), (len(poses), 1, 1))
    if len(poses):
        T[:, :3, :3] = Rotation.from_rotvec(poses[:, 3:]).as_matrix()
        T[:, :3, 3] = poses[:, :3]
    return T


def to_ur_pose(T: ArrayLike) -> Array:
    """Return the UR pose ``[x, y, z, rx, ry, rz]`` (m, rad) of ``T_base_tcp``."""
    from scipy.spatial.transform import Rotation

    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()])


def from_xyz_rpy(xyz: ArrayLike, rpy: ArrayLike) -> Array:
    """Return a transform from a translation and extrinsic roll-pitch-yaw (x, y, z), rad."""
    from scipy.spatial.transform import Rotation

    return transform_from(Rotation.from_euler("xyz", rpy).as_matrix(), xyz)


def from_xyz_quat_wxyz(xyz: ArrayLike, q_wxyz: ArrayLike) -> Array:
    """Return a transform from a translation and a quaternion in (w, x, y, z) order."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(q_wxyz, dtype=np.float64)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-9:
        raise InputError(f"quaternion: expected 4 finite values (w, x, y, z), got {q.tolist()}")
    return transform_from(Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix(), xyz)


def error(T_est: ArrayLike, T_true: ArrayLike) -> tuple[float, float]:
    """Return the translation error (m) and rotation angle error (rad) of ``T_est``.

    The rotation error is the angle of ``R_true^T R_est``; the translation error
    is the norm of the difference of the translations.
    """
    from scipy.spatial.transform import Rotation

    T_est = np.asarray(T_est, dtype=np.float64)
    T_true = np.asarray(T_true, dtype=np.float64)
    dt = float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
    dR = T_true[:3, :3].T @ T_est[:3, :3]
    return dt, float(Rotation.from_matrix(dR).magnitude())


def delta(T_est: ArrayLike, T_true: ArrayLike) -> tuple[Array, Array]:
    """Return the signed translation (m, (3,)) and rotation-vector (rad, (3,)) error."""
    from scipy.spatial.transform import Rotation

    T_est = np.asarray(T_est, dtype=np.float64)
    T_true = np.asarray(T_true, dtype=np.float64)
    dt = T_est[:3, 3] - T_true[:3, 3]
    drot = Rotation.from_matrix(T_true[:3, :3].T @ T_est[:3, :3]).as_rotvec()
    return dt, drot


def frame_from_z(origin: ArrayLike, z_axis: ArrayLike, x_hint: ArrayLike | None = None) -> Array:
    """Return a right-handed frame at ``origin`` whose z axis is ``z_axis``.

    The x axis is ``x_hint`` projected onto the plane normal to z (or an
    arbitrary perpendicular when no hint is given or the hint is parallel to z).
    """
    z = np.asarray(z_axis, dtype=np.float64)
    z = z / np.linalg.norm(z)
    hint = np.asarray(x_hint if x_hint is not None else [1.0, 0.0, 0.0], dtype=np.float64)
    x = hint - np.dot(hint, z) * z
    if np.linalg.norm(x) < 1e-9:
        hint = np.array([0.0, 1.0, 0.0]) if abs(z[0]) > 0.9 else np.array([1.0, 0.0, 0.0])
        x = hint - np.dot(hint, z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return transform_from(np.column_stack([x, y, z]), origin)
