"""One board's pose under any lens model (used by the per-view lens choice and the paper route's start)."""

from __future__ import annotations

import cv2
import numpy as np

from lfgraph.core.camera import Intrinsics
from lfgraph.core.geometry import make_T, rotation_from_rotvec

POSE_ITERATIONS = 8  # Gauss-Newton steps of a held-out board pose in distorted pixels


def board_pose(intr: Intrinsics, obj: np.ndarray, px: np.ndarray) -> np.ndarray | None:
    """``view_T_board`` (4, 4) of one board under any lens model: PnP on the undistorted corners, then Gauss-Newton
    on the distorted pixel error. None when the corners cannot be undistorted or PnP fails."""
    xy = intr.undistort(px)
    ok = np.all(np.isfinite(xy), axis=1)
    if ok.sum() < 4:
        return None
    try:
        found, rvec, tvec = cv2.solvePnP(obj[ok].astype(np.float64), xy[ok], np.eye(3), None,
                                         flags=cv2.SOLVEPNP_ITERATIVE)
    except cv2.error:
        return None
    if not found:
        return None
    x = np.concatenate([np.ravel(rvec), np.ravel(tvec)])

    def residual(p: np.ndarray) -> np.ndarray:
        R = rotation_from_rotvec(p[:3])  # noqa: N806
        return (intr.project(obj @ R.T + p[3:]) - px).ravel()

    for _ in range(POSE_ITERATIONS):
        r = residual(x)
        if not np.all(np.isfinite(r)):
            break
        eps = 1e-7 * np.maximum(1.0, np.abs(x))
        J = np.stack([(residual(x + e) - r) / h for e, h in zip(np.diag(eps), eps, strict=True)], axis=1)  # noqa: N806
        if not np.all(np.isfinite(J)):
            break
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        if np.sum(residual(x + step) ** 2) >= np.sum(r**2):
            break
        x = x + step
    return make_T(rotation_from_rotvec(x[:3]), x[3:])
