"""Drift check of a stored calibration on an ordinary capture (no pattern): track features through the grid,
triangulate them with the calibration, and report reprojection residuals and parallax-compensated misalignment."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from lfgraph.alignment import PointAlignmentReport, align_points
from lfgraph.calibration import Calibration
from lfgraph.rectification import Rectification
from lfgraph.refinement.matching import MatchSettings, Tracks, track_chain
from lfgraph.refinement.triangulate import reprojection_errors, triangulate_dlt, worst_error_filter

TRACK_OUTLIER_FACTOR = 4.0  # a track whose largest residual exceeds 4x the median track's is a mismatch
TRACK_OUTLIER_MIN_PX = 0.5  # ... and exceeds this (so a perfect calibration does not reject its noise)
# (the same rule as the refinement's `worst` triangulation filter)


@dataclass(frozen=True)
class DriftReport:
    """What `check_capture` measured.

    Attributes:
        rms_px: RMS Euclidean reprojection residual of every kept track in every view.
        view_rms_px: (V,) the same per view.
        counts: tracks after each filter, summed over frames (``detected``, ``chain``, ``dedup``, ``ransac``,
            ``triangulation``).
        alignment: parallax-compensated alignment of the kept tracks (before/after/compensated/parallax).
        frames: number of frames used.
    """

    rms_px: float
    view_rms_px: np.ndarray
    counts: dict[str, int]
    alignment: PointAlignmentReport
    frames: int

    def to_dict(self, calib: Calibration) -> dict:
        """JSON-friendly figures, views named as in the grid (``rRR_cCC``)."""
        return {
            "rms_px": _finite_or_none(self.rms_px), "frames": self.frames, "tracks": dict(self.counts),
            "view_rms_px": {calib.grid.name(v): _finite_or_none(x) for v, x in enumerate(self.view_rms_px)},
            "alignment": {name: getattr(self.alignment, name).as_dict()
                          for name in ("before", "after", "compensated", "parallax")},
        }


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def reprojection_residuals(calib: Calibration, tracks: Tracks) -> np.ndarray:
    """(V, N) residual norms (px) of tracks triangulated with ``calib``."""
    points = triangulate_dlt(calib, tracks.points_px, tracks.valid)
    return reprojection_errors(calib, points, tracks.points_px, tracks.valid)


def check(calib: Calibration, frames: Iterable[np.ndarray], settings: MatchSettings | None = None) -> DriftReport:
    """The drift check: does the calibration still fit these ordinary (textured) frames?

    Tracks features through the grid, triangulates them with the calibration, drops mismatches and reports the
    reprojection RMS per view and the alignment figures (with the stored rectification, or one computed here).

    Args:
        calib: the calibration to check.
        frames: (V, H, W) uint8 grayscale images per frame, of the calibration's grid and image size.
    """
    from lfgraph.rectification import compute_rectification, stored_rectification

    rect = stored_rectification(calib) or compute_rectification(calib)
    return check_capture(calib, rect, frames, settings)


def check_capture(calib: Calibration, rect: Rectification, frames: Iterable[np.ndarray],
                  settings: MatchSettings | None = None) -> DriftReport:
    """Run the drift check over (V, H, W) grayscale frames."""
    pixels, valid, counts, n_frames = [], [], {}, 0
    for images in frames:
        tracks = track_chain(images, calib.grid, settings)
        res = reprojection_residuals(calib, tracks)
        keep = worst_error_filter(res, TRACK_OUTLIER_FACTOR, TRACK_OUTLIER_MIN_PX)
        tracks_counts = {**tracks.counts, "triangulation": int(keep.sum())}
        for k, n in tracks_counts.items():
            counts[k] = counts.get(k, 0) + n
        pixels.append(tracks.points_px[:, keep])
        valid.append(tracks.valid[:, keep])
        n_frames += 1
    if not n_frames:
        raise ValueError("the capture has no frames to check")
    px = np.concatenate(pixels, axis=1)
    ok = np.concatenate(valid, axis=1)
    if ok.shape[1] == 0:
        raise ValueError("no feature could be tracked through every view; the scene has too little texture "
                         "(or the views do not overlap)")
    res = reprojection_residuals(calib, Tracks(px, ok))
    rms = float(np.sqrt(np.nanmean(res**2)))
    view_rms = np.sqrt(np.nanmean(res**2, axis=1))
    return DriftReport(rms, view_rms, counts, align_points(calib, rect, px, ok), n_frames)
