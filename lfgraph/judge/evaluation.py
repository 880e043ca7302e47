"""Judges: a calibration's errors against ground truth (poses relative to the estimate's reference view).
Imports no estimator."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.geometry import invert_T, rotation_angle_deg

INFINITY_SAMPLES = 24  # directions per image side for the misalignment and transfer-error-at-infinity metrics


@dataclass(frozen=True)
class CalibrationErrors:
    """Estimated minus true, per view; poses compared relative to the estimate's reference view.

    Attributes:
        intrinsics: (V, 6) signed errors of fx, fy, cx, cy (px), k1, k2.
        position_mm: (V, 3) signed position error; rotation_deg: (V,) angle of the rotation error.
        transfer_px: (V,) transfer error at infinity (`transfer_error_at_infinity`: a reference pixel sent to
            infinite depth and projected with the estimated and the true cameras; RMS over the reference image, px;
            0 for the reference view) — the figure disparity and refocusing see, the headline of the README tables.
    """

    intrinsics: np.ndarray
    position_mm: np.ndarray
    rotation_deg: np.ndarray
    transfer_px: np.ndarray | None = None

    FIELDS = ("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2")

    def summary(self) -> dict[str, float]:
        """RMS over views (and max) of each error, JSON-friendly, always these keys in this order:

        ``rms_fx_px``, ``rms_fy_px``, ``rms_cx_px``, ``rms_cy_px``, ``rms_k1``, ``rms_k2`` (intrinsics);
        ``rms_position_mm``, ``max_position_mm`` (length of the position error); ``rms_rotation_deg``,
        ``max_rotation_deg`` (angle of the rotation error); ``rms_transfer_px``, ``max_transfer_px`` (transfer error
        at infinity; NaN when not computed). Poses are relative to the estimate's reference view.
        """
        out = {f"rms_{name}": float(np.sqrt(np.mean(self.intrinsics[:, i] ** 2))) for i, name in enumerate(self.FIELDS)}
        out["rms_position_mm"] = float(np.sqrt(np.mean(np.sum(self.position_mm**2, axis=1))))
        out["max_position_mm"] = float(np.max(np.linalg.norm(self.position_mm, axis=1)))
        out["rms_rotation_deg"] = float(np.sqrt(np.mean(self.rotation_deg**2)))
        out["max_rotation_deg"] = float(np.max(self.rotation_deg))
        t = np.full(1, np.nan) if self.transfer_px is None else np.asarray(self.transfer_px, dtype=float)
        out["rms_transfer_px"] = float(np.sqrt(np.mean(t**2)))
        out["max_transfer_px"] = float(np.max(t))
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
    transfer = transfer_error_at_infinity(estimate, truth.with_reference(ref))
    return CalibrationErrors(est_vec - true_vec, pos, rot, transfer)


def reference_pixels(image_size_px: tuple[int, int], samples: int) -> np.ndarray:
    """(samples², 2) pixels on a ``samples`` x ``samples`` grid over 5-95 % of the image, row by row: where the
    transfer at infinity is measured."""
    w, h = image_size_px
    gx, gy = np.meshgrid(np.linspace(0.05 * (w - 1), 0.95 * (w - 1), samples),
                         np.linspace(0.05 * (h - 1), 0.95 * (h - 1), samples))
    return np.column_stack([gx.ravel(), gy.ravel()])


def transfer_error_at_infinity(estimate: Calibration, truth: Calibration,
                               samples: int = INFINITY_SAMPLES) -> np.ndarray:
    """(V,) RMS over reference pixels of |q_est - q_true|: a reference-view pixel sent to infinite depth and projected
    into view i with the estimated and with the true cameras — the error that disparity and refocusing see.

    Both calibrations are taken relative to their own reference view (which must be the same view). In a free
    arrangement (a ring, whose views do not see the reference's directions) each view's own pixels are sent to
    infinity with the true camera and projected with the estimated one: the same figure in the view's own image.
    """
    if (estimate.grid.rows, estimate.grid.cols, estimate.grid.reference) != \
            (truth.grid.rows, truth.grid.cols, truth.grid.reference):
        raise ValueError(f"grids differ: {estimate.grid} (reference {estimate.grid.reference}) vs {truth.grid} "
                         f"(reference {truth.grid.reference})")
    ref = truth.grid.reference
    px = reference_pixels(truth.image_size(ref), samples)
    out = np.zeros(truth.num_views)

    def project_all(calib: Calibration) -> np.ndarray:
        rel = np.linalg.inv(calib.ref_T_view[ref])[None] @ calib.ref_T_view
        xy = calib.intrinsics[ref].undistort(px)
        rays = np.column_stack([xy, np.ones(len(xy))])
        return np.stack([calib.intrinsics[i].project(rays @ rel[i][:3, :3]) for i in range(calib.num_views)])

    if truth.grid.is_free or estimate.grid.is_free:
        d = _own_transfer(estimate, truth, samples)
    else:
        d = np.linalg.norm(project_all(estimate) - project_all(truth), axis=-1)
    for i in range(truth.num_views):
        di = d[i][np.isfinite(d[i])]
        out[i] = np.sqrt(np.mean(di**2)) if di.size else np.nan
    return out


def _own_transfer(estimate: Calibration, truth: Calibration, samples: int) -> list[np.ndarray]:
    """Per view, (N,) |q_est - q_true| of its own pixels sent to infinity by the true view and projected by the
    estimated one (both relative to the reference)."""
    ref = truth.grid.reference
    out = []
    for i in range(truth.num_views):
        px = reference_pixels(truth.image_size(i), samples)
        xy = truth.intrinsics[i].undistort(px)
        rays = np.column_stack([xy, np.ones(len(xy))])
        in_ref = rays @ (np.linalg.inv(truth.ref_T_view[ref]) @ truth.ref_T_view[i])[:3, :3].T
        est_R = (np.linalg.inv(estimate.ref_T_view[ref]) @ estimate.ref_T_view[i])[:3, :3]  # noqa: N806
        out.append(np.linalg.norm(estimate.intrinsics[i].project(in_ref @ est_R) - truth.intrinsics[i].project(rays),
                                  axis=-1))
    return out
