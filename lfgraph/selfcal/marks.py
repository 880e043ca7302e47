"""Marked scene points (a distance pin's) followed from the view they were marked in into every view of their frame."""

from __future__ import annotations

import cv2
import numpy as np

from lfgraph.core.grid import ViewGrid
from lfgraph.engine.triangulate import reprojection_errors, triangulate_dlt

# a marked point is followed from its view through the grid by pyramidal KLT (as the chain tracker does, with the
# self-calibration's deeper pyramid) and then re-tracked from the reference view like every track
MARK_KLT_WINDOW_PX = 21
MARK_KLT_LEVELS = 5
MARK_FORWARD_BACKWARD_PX = 0.5

# a mark's observation whose reprojection error through the scene's calibration exceeds this many times the mark's
# median and `MARK_OUTLIER_FLOOR_PX` is dropped, worst first (as the one mismatch rule drops tracks): a mark on an edge
# can be followed along it (measured: paper-4x4 rig seed 1, a mark 62 px from the top border slid 5-6 px in two views;
# kept, it moved the triangulated mark 7 % deeper and a right wall pin was refused at 13.5 sigma)
MARK_OUTLIER_FACTOR = 4.0
MARK_OUTLIER_FLOOR_PX = 0.5


def follow_marks(images: np.ndarray, grid: ViewGrid, view: int, marked_px: np.ndarray) -> tuple[np.ndarray,
                                                                                                  np.ndarray]:
    """(K, 2) points of one view followed into every view of a frame's (V, H, W) images by pyramidal KLT along the
    grid's chain from that view, each step started at the step before, with a forward-backward check.

    Returns:
        (V, K, 2) pixels (NaN where lost) and (V, K) valid.
    """
    images = np.asarray(images)
    n_views, k = grid.num_views, len(marked_px)
    pixels = np.full((n_views, k, 2), np.nan)
    pixels[view] = marked_px
    win, criteria = (MARK_KLT_WINDOW_PX,) * 2, (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3)
    chain = ViewGrid(grid.rows, grid.cols, view).chain()
    for a, b in chain:
        ok = np.all(np.isfinite(pixels[a]), axis=1)
        if not ok.any():
            continue
        p0 = pixels[a, ok].astype(np.float32).reshape(-1, 1, 2)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(images[a], images[b], p0, p0.copy(), winSize=win,
                                             maxLevel=MARK_KLT_LEVELS, criteria=criteria,
                                             flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        back, st_b, _ = cv2.calcOpticalFlowPyrLK(images[b], images[a], p1, p0.copy(), winSize=win,
                                                 maxLevel=MARK_KLT_LEVELS, criteria=criteria,
                                                 flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        good = (st.ravel() == 1) & (st_b.ravel() == 1) & \
            (np.linalg.norm((back - p0).reshape(-1, 2), axis=1) <= MARK_FORWARD_BACKWARD_PX)
        out = np.full((int(ok.sum()), 2), np.nan)
        out[good] = p1.reshape(-1, 2)[good]
        pixels[b, ok] = out
    valid = np.all(np.isfinite(pixels), axis=2)
    return pixels, valid


def consistent_marks(calib, pixels: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, ...]:
    """A distance pin's marks (V, 2, 2) px with what ``calib``'s geometry explains kept: each mark triangulated and its
    worst observation dropped while its reprojection error exceeds `MARK_OUTLIER_FACTOR` times the mark's median and
    `MARK_OUTLIER_FLOOR_PX`. Returns (pixels, valid, the marks' points, their reprojection errors)."""
    pixels, valid = np.array(pixels), np.array(valid)
    while True:
        points = triangulate_dlt(calib, pixels, valid)
        errors = reprojection_errors(calib, points, pixels, valid)
        dropped = False
        for k in range(2):
            e = np.where(valid[:, k], errors[:, k], np.nan)
            if np.sum(np.isfinite(e)) <= 2:
                continue
            worst = int(np.nanargmax(e))
            if e[worst] > max(MARK_OUTLIER_FACTOR * float(np.nanmedian(e)), MARK_OUTLIER_FLOOR_PX):
                valid[worst, k], dropped = False, True
        if not dropped:
            break
    return pixels, valid, points, errors
