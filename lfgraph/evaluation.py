"""Judges: a calibration's errors against ground truth (poses relative to the estimate's reference view).
Imports no estimator."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lfgraph.calibration import Calibration
from lfgraph.geometry import invert_T, rotation_angle_deg


@dataclass(frozen=True)
class CalibrationErrors:
    """Estimated minus true, per view; poses compared relative to the estimate's reference view.

    Attributes:
        intrinsics: (V, 6) signed errors of fx, fy, cx, cy (px), k1, k2.
        position_mm: (V, 3) signed position error; rotation_deg: (V,) angle of the rotation error.
    """

    intrinsics: np.ndarray
    position_mm: np.ndarray
    rotation_deg: np.ndarray

    FIELDS = ("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2")

    def summary(self) -> dict[str, float]:
        """RMS over views of each error (and max), JSON-friendly."""
        out = {f"rms_{name}": float(np.sqrt(np.mean(self.intrinsics[:, i] ** 2))) for i, name in enumerate(self.FIELDS)}
        out["rms_position_mm"] = float(np.sqrt(np.mean(np.sum(self.position_mm**2, axis=1))))
        out["max_position_mm"] = float(np.max(np.linalg.norm(self.position_mm, axis=1)))
        out["rms_rotation_deg"] = float(np.sqrt(np.mean(self.rotation_deg**2)))
        out["max_rotation_deg"] = float(np.max(self.rotation_deg))
        return out


def evaluate(estimate: Calibration, truth: Calibration) -> CalibrationErrors:
    """Per-parameter errors of ``estimate`` against ``truth`` (alias of `evaluate_calibration`)."""
    return evaluate_calibration(estimate, truth)


def evaluate_calibration(estimate: Calibration, truth: Calibration) -> CalibrationErrors:
    """Per-parameter errors of ``estimate`` against ``truth``.

    Raises:
        ValueError: different grids or image sizes (the message says which).
        TypeError: an argument that is not a `Calibration` (load files with ``Calibration.load``).
    """
    for name, value in (("estimate", estimate), ("truth", truth)):
        if not isinstance(value, Calibration):
            raise TypeError(f"evaluate: {name} must be a lfgraph.Calibration (load a file with "
                            f"lfgraph.Calibration.load), got {type(value).__name__}")
    if (estimate.grid.rows, estimate.grid.cols) != (truth.grid.rows, truth.grid.cols):
        raise ValueError(f"the calibration is a {estimate.grid} grid but the truth is {truth.grid}")
    if estimate.image_size_px != truth.image_size_px:
        raise ValueError(f"the calibration is for {estimate.image_size_px} px images but the truth for "
                         f"{truth.image_size_px}")
    est_vec = np.array([[i.fx, i.fy, i.cx, i.cy, i.k1, i.k2] for i in estimate.intrinsics])
    true_vec = np.array([[i.fx, i.fy, i.cx, i.cy, i.k1, i.k2] for i in truth.intrinsics])
    ref = estimate.grid.reference
    true_rel = invert_T(truth.ref_T_view[ref])[None] @ truth.ref_T_view
    est_rel = estimate.ref_T_view
    pos = 1e3 * (est_rel[:, :3, 3] - true_rel[:, :3, 3])
    rot = np.asarray(rotation_angle_deg(np.swapaxes(true_rel[:, :3, :3], 1, 2) @ est_rel[:, :3, :3]))
    return CalibrationErrors(est_vec - true_vec, pos, rot)
