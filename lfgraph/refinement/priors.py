"""The MAP priors of the refinement: per view, centred on the input calibration, with sigmas from the drift model
combined with the input's own uncertainty (``metrics["sigmas"]`` of ``calibrate``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.sigmas import Sigmas
from lfgraph.refinement.config import DriftModel


@dataclass(frozen=True)
class ViewPriors:
    """Priors centred on ``centre`` (the input calibration, same reference view) with 1-sigma ``sigmas``
    (`lfgraph.core.sigmas.Sigmas`: per view, in its own frame)."""

    centre: Calibration
    sigmas: Sigmas

    @property
    def pose_sigmas(self) -> np.ndarray:
        """(V, 6) in GTSAM's Pose3 tangent order, body frame: rotation x, y (pan/tilt), z (roll about the optical
        axis) in radians, then position x, y, z in metres."""
        return self.sigmas.pose

    @property
    def intrinsics_sigmas(self) -> np.ndarray:
        """(V, 4) fx, fy, cx, cy in pixels."""
        return self.sigmas.intrinsics


def view_priors(calib: Calibration, drift: DriftModel) -> ViewPriors:
    """Priors for every view of ``calib``: the drift (root sum of squares) the input's own stored sigmas."""
    sigmas = drift.sigmas(calib.num_views)
    own = calib.sigmas
    return ViewPriors(calib, sigmas if own is None else sigmas.combined(own))
