"""The depth error a reprojection error causes (paper Section 5.1, eq. "depth_error" and Fig. "depth_error_2d").

For two views a baseline ``b`` apart with focal length ``f`` (pixels), a point at depth ``Z`` has disparity
``d = f b / Z``. A disparity error of ``E`` pixels moves the depth to ``f b / (d - E)`` or ``f b / (d + E)``; the
depth error is half their difference:

    ΔZ = (f b / (d - E) - f b / (d + E)) / 2.

The paper prints ``ΔZ = f b / (d - E) + f b / (d + E)`` — a typo (that is twice the depth, not an error); its stated
numbers, 0.004 m at 0.5 m and 0.065 m at 2.0 m for f = 850 px, b = 0.018 m, E = 0.246 px, are the half difference
above (0.00402 m and 0.0644 m).
"""

from __future__ import annotations

import numpy as np


def depth_error_m(focal_px: float, baseline_m: float, error_px: float, depth_m: np.ndarray | float) -> np.ndarray:
    """Half the spread of the depths at disparity ``d - E`` and ``d + E`` (see the module docstring).

    Args:
        focal_px: focal length in pixels.
        baseline_m: distance between the two views in metres.
        error_px: disparity (reprojection) error in pixels.
        depth_m: depth(s) in metres.

    Returns:
        the depth error in metres, same shape as ``depth_m``; ``inf`` where ``E >= d`` (the error swallows the
        disparity).

    Raises:
        ValueError: a non-positive focal length, baseline or depth, or a negative error.
    """
    z = np.asarray(depth_m, dtype=np.float64)
    if not (focal_px > 0 and baseline_m > 0):
        raise ValueError(f"focal length and baseline must be positive, got f = {focal_px} px, b = {baseline_m} m")
    if not error_px >= 0:
        raise ValueError(f"the reprojection error must be >= 0, got {error_px} px")
    if np.any(~(z > 0)):
        raise ValueError("depths must be positive")
    fb = focal_px * baseline_m
    d = fb / z
    with np.errstate(divide="ignore"):
        far = np.where(d > error_px, fb / (d - error_px), np.inf)
    return (far - fb / (d + error_px)) / 2.0
