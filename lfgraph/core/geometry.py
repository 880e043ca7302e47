"""Rigid-transform helpers on (4, 4) numpy matrices; poses are named ``a_T_b`` (maps frame b into frame a)."""

from __future__ import annotations

import gtsam
import numpy as np

ROTATION_ORTHONORMAL_TOLERANCE = 1e-6  # max |R^T R - I| entry accepted as a rotation


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:  # noqa: N802, N803
    """(3, 3) rotation and (3,) translation -> (4, 4) homogeneous transform."""
    T = np.eye(4)  # noqa: N806
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).ravel()
    return T


def invert_T(a_T_b: np.ndarray) -> np.ndarray:  # noqa: N802, N803
    """Inverse of a rigid transform: ``b_T_a`` (of each, for a (..., 4, 4) stack)."""
    a_T_b = np.asarray(a_T_b, dtype=np.float64)  # noqa: N806
    Rt = np.swapaxes(a_T_b[..., :3, :3], -1, -2)  # noqa: N806
    out = np.zeros(a_T_b.shape)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ a_T_b[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def is_rotation(R: np.ndarray, tol: float = ROTATION_ORTHONORMAL_TOLERANCE) -> bool:  # noqa: N803
    """True when R is a finite (3, 3) orthonormal matrix with determinant +1."""
    R = np.asarray(R, dtype=np.float64)  # noqa: N806
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        return False
    return bool(np.max(np.abs(R.T @ R - np.eye(3))) < tol and np.linalg.det(R) > 0)


def rotation_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues vector (3,) in radians -> (3, 3) rotation."""
    return gtsam.Rot3.Expmap(np.asarray(rotvec, dtype=np.float64).ravel()).matrix()


def rotvec_from_rotation(R: np.ndarray) -> np.ndarray:  # noqa: N803
    """(3, 3) rotation -> Rodrigues vector (3,) in radians."""
    return gtsam.Rot3.Logmap(gtsam.Rot3(np.asarray(R, dtype=np.float64)))


def rotation_angle_deg(R: np.ndarray) -> float | np.ndarray:  # noqa: N803
    """Angle of a rotation (or a stack (..., 3, 3) of them) in degrees, computed stably from the trace."""
    R = np.asarray(R, dtype=np.float64)  # noqa: N806
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    # arccos is ill-conditioned near 0: use the skew part for the sine.
    skew = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    sin = np.linalg.norm(skew, axis=-1) / 2.0
    return np.degrees(np.arctan2(sin, cos))


def to_pose3(a_T_b: np.ndarray) -> gtsam.Pose3:  # noqa: N803
    """(4, 4) matrix -> ``gtsam.Pose3``."""
    return gtsam.Pose3(np.asarray(a_T_b, dtype=np.float64))


def from_pose3(pose: gtsam.Pose3) -> np.ndarray:
    """``gtsam.Pose3`` -> (4, 4) matrix."""
    return np.asarray(pose.matrix(), dtype=np.float64)
