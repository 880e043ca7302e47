"""The MAP priors of the refinement: per view, centred on the input calibration, with sigmas from the drift model
combined with the input's own uncertainty (``metrics["sigmas"]`` of ``calibrate``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.refinement.config import DriftModel


@dataclass(frozen=True)
class ViewPriors:
    """Priors centred on ``centre`` (the input calibration, same reference view).

    Attributes:
        centre: the calibration every prior is centred on.
        pose_sigmas: (V, 6) in GTSAM's Pose3 tangent order, body frame: rotation x, y (pan/tilt), z (roll about
            the optical axis) in radians, then position x, y, z in metres.
        intrinsics_sigmas: (V, 4) fx, fy, cx, cy in pixels.
    """

    centre: Calibration
    pose_sigmas: np.ndarray
    intrinsics_sigmas: np.ndarray


def input_sigmas(calib: Calibration) -> tuple[np.ndarray, np.ndarray] | None:
    """(V, 6) pose and (V, 4) intrinsics sigmas stored by ``calibrate`` (rad, m, px), or None when absent/unusable."""
    stored = calib.sigmas
    return None if stored is None else (stored.pose, stored.intrinsics)


def view_priors(calib: Calibration, drift: DriftModel) -> ViewPriors:
    """Priors for every view of ``calib``: drift (root sum of squares) the input's own sigmas."""
    n = calib.num_views
    pt, roll = np.radians(drift.pan_tilt_deg), np.radians(drift.roll_deg)
    pose = np.tile([pt, pt, roll, *(3 * [1e-3 * drift.position_mm])], (n, 1))
    intr = np.tile([drift.focal_px, drift.focal_px, drift.principal_px, drift.principal_px], (n, 1))
    own = input_sigmas(calib)
    if own is not None:
        pose = np.sqrt(pose**2 + own[0] ** 2)
        intr = np.sqrt(intr**2 + own[1] ** 2)
    return ViewPriors(calib, pose, intr)
