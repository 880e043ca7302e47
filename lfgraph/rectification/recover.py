"""A stored rectification rebuilt from the matrices a file in ``cv2.stereoRectify``'s convention carries: what an
import keeps of one (`lfgraph.interop.opencv_yaml`).

Such a file holds the rectified size, ``K_r``, and per view ``R_rect_i`` (rectified from view, stereoRectify's R1/R2
role) and the last column ``p_i = -K_r rect_R_ref c_i`` of ``P_i = [K_r | p_i]`` (its P1/P2). The rest of lfgraph's
`Rectification` follows from those and the calibration, by the formulas of `compute_rectification`:
- ``rect_R_ref`` is the reference view's ``R_rect`` (the reference's own rotation is the identity);
- view i's ideal position is ``c_i = -rect_R_ref^T K_r^-1 p_i``; the ideal grid (origin, row and column steps, pitch)
  is the rectangular fit through those positions (`rectangular_grid`), which they lie on exactly;
- each view's deviation is its centre minus its ideal position, in the rectified frame, in mm;
- the crop rectangle is where ``K_r``'s principal point puts the output inside the full-size rectified frame, whose
  principal point is the source image's centre ``((w - 1) / 2, (h - 1) / 2)``.
"""

from __future__ import annotations

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.geometry import rotation_angle_deg
from lfgraph.rectification.rectify import CROPS, Rectification, rectangular_grid


def rectification_from_projections(calib: Calibration, image_size_px: tuple[int, int], K_r: np.ndarray,  # noqa: N803
                                   rect_R_view: np.ndarray, p_last_px: np.ndarray,  # noqa: N803
                                   crop: str | None = None) -> Rectification:
    """lfgraph's rectification of ``calib`` from stereoRectify-convention matrices (module docstring).

    Args:
        calib: the calibration the matrices belong to (the caller has checked that ``rect_R_view`` is its views'
            orientations turned by one common rotation).
        image_size_px: (w, h) of the rectified images.
        K_r: (3, 3) the rectified views' common intrinsics.
        rect_R_view: (V, 3, 3) per view, rectified from view.
        p_last_px: (V, 3) per view the last column of ``P_i = [K_r | p_i]``.
        crop: ``valid`` or ``full`` when the file says so; otherwise ``full`` when the output is the whole
            full-size rectified frame, else ``valid``.

    Returns:
        The `Rectification` (store it with `lfgraph.rectification.rectify.attach`).

    Raises:
        ValueError: ``crop`` is not one of `CROPS`.
    """
    if crop is not None and crop not in CROPS:
        raise ValueError(f"crop must be one of {', '.join(CROPS)}, got {crop!r}")
    K_r = np.asarray(K_r, dtype=np.float64)  # noqa: N806
    rect_R_view = np.asarray(rect_R_view, dtype=np.float64)  # noqa: N806
    rect_R_ref = rect_R_view[calib.grid.reference]  # noqa: N806
    ideal = -np.linalg.solve(K_r, np.asarray(p_last_px, dtype=np.float64).T).T @ rect_R_ref  # (V, 3), reference frame
    origin, u, v = rectangular_grid(calib.grid, ideal, rect_R_ref)
    w, h = calib.image_size_px
    x0, y0 = round((w - 1) / 2.0 - K_r[0, 2]), round((h - 1) / 2.0 - K_r[1, 2])
    crop_rect = (int(x0), int(y0), int(image_size_px[0]), int(image_size_px[1]))
    if crop is None:
        crop = "full" if crop_rect == (0, 0, w, h) else "valid"
    P = np.stack([np.column_stack([K_r @ rect_R_ref, p]) for p in p_last_px])  # noqa: N806  lfgraph's P_i
    deviation_mm = 1e3 * (calib.ref_T_view[:, :3, 3] - ideal) @ rect_R_ref.T
    return Rectification((w, h), (int(image_size_px[0]), int(image_size_px[1])), crop, crop_rect, K_r, rect_R_ref,
                         rect_R_view, P, np.array([np.linalg.norm(u), np.linalg.norm(v)]), origin, u, v, deviation_mm,
                         np.asarray(rotation_angle_deg(rect_R_view)))
