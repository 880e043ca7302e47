"""Tracking a rig whose views differ in image size: each view is resampled to the reference view's scale before
the tracker sees it, and the tracks are mapped back to each view's own pixels.

KLT follows a patch between neighbouring views; it fails when the same scene is imaged at different scales (a
1920x1080 view beside a 1280x720 one of a similar field: 1.5x). `ViewCanvas` scales each view about its principal
point by the reference view's focal length over its own (x and y apart) and puts the principal point where the
reference view has it, on a canvas of the reference view's size, so every view shows the scene as the reference
view would from its position. The map is affine and exactly invertible, so the tracks — and everything the tracker
filters by (F-RANSAC: an affine change of pixels keeps a fundamental matrix) — carry over; a track that lands
outside a view's own image is dropped there. Lens distortion is left in the images: the views' lenses differ less
than their scales.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.grid import ViewGrid
from lfgraph.refinement.matching import Tracker, Tracks


class ViewCanvas:
    """The per-view affine maps of a mixed-size rig onto the reference view's scale (module docstring).

    Attributes:
        size_px: the canvas (width, height): the reference view's image size.
        scale: (V, 2) x and y scale of each view's pixels on the canvas.
        offset: (V, 2) canvas position of each view's pixel (0, 0).
    """

    def __init__(self, calib: Calibration):
        ref = calib.intrinsics[calib.grid.reference]
        self.size_px = tuple(calib.image_size(calib.grid.reference))
        self.view_image_sizes_px = list(calib.image_sizes)
        self.scale = np.array([[ref.fx / i.fx, ref.fy / i.fy] for i in calib.intrinsics])
        centres = np.array([[i.cx, i.cy] for i in calib.intrinsics])
        self.offset = np.array([ref.cx, ref.cy]) - self.scale * centres  # canvas = scale * view + offset

    def warp(self, images: Sequence[np.ndarray]) -> np.ndarray:
        """(V, H, W) uint8: each view's image resampled onto the canvas (bilinear; outside a view: black)."""
        w, h = self.size_px
        out = np.empty((len(images), h, w), dtype=np.uint8)
        for v, img in enumerate(images):
            (sx, sy), (ox, oy) = self.scale[v], self.offset[v]
            if sx == 1.0 and sy == 1.0 and ox == 0.0 and oy == 0.0 and img.shape == (h, w):
                out[v] = img
                continue
            m = np.array([[sx, 0.0, ox], [0.0, sy, oy]])
            out[v] = cv2.warpAffine(img, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        return out

    def to_views(self, tracks: Tracks) -> Tracks:
        """The tracks in each view's own pixels; a track outside a view's image is not seen there."""
        pts = (tracks.points_px - self.offset[:, None, :]) / self.scale[:, None, :]
        valid = tracks.valid.copy()
        for v, (w, h) in enumerate(self.view_image_sizes_px):
            x, y = pts[v, :, 0], pts[v, :, 1]
            with np.errstate(invalid="ignore"):
                valid[v] &= (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
        pts[~valid] = np.nan
        return Tracks(pts, valid, dict(tracks.counts))


def canvas_for(calib: Calibration) -> ViewCanvas | None:
    """The `ViewCanvas` of a rig whose views differ in image size; None for a one-size rig (tracked as it is)."""
    return ViewCanvas(calib) if len(set(calib.image_sizes)) > 1 else None


def track_views(tracker: Tracker, images, grid: ViewGrid, canvas: ViewCanvas | None) -> Tracks:
    """One frame's tracks in each view's own pixels: ``images`` (V, H, W) tracked as they are (``canvas`` None), or
    a mixed rig's list of (H, W) views tracked on its ``canvas`` (`canvas_for`)."""
    if canvas is None:
        return tracker.track(images, grid)
    return canvas.to_views(tracker.track(canvas.warp(images), grid))
