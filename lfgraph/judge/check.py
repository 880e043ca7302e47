"""Drift check of a stored calibration on an ordinary capture (no pattern): track features through the views,
triangulate them with the calibration, report reprojection residuals and parallax-compensated misalignment, and a
per-view verdict from the refinement's own test (`lfgraph.refinement.assess`): a MAP refit with the drift priors,
a significance test of each view's change against its posterior sigma (widened to the scatter of refits on
separate frames), and held-out frames. The residual RMS alone cannot judge drift: mismatched tracks on a repeated
pattern raise it without any camera having moved."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.observer import SilentObserver
from lfgraph.core.verdict import Verdict
from lfgraph.engine.triangulate import drop_mismatches, reprojection_errors, triangulate_dlt
from lfgraph.io.capture import check_frame_array, check_frames_argument
from lfgraph.judge.alignment import PointAlignmentReport, align_points
from lfgraph.rectification.rectify import Rectification
from lfgraph.refinement.matching import MatchSettings, Tracks
from lfgraph.refinement.trackers import AutoTracker

if TYPE_CHECKING:
    from lfgraph.refinement.config import RefineConfig

# (the same rule as the refinement's `worst` triangulation filter)


@dataclass(frozen=True)
class DriftReport:
    """What `check_capture` measured.

    Attributes:
        rms_px: RMS Euclidean reprojection residual of every kept track in every view.
        view_rms_px: (V,) the same per view.
        counts: tracks after each filter, summed over frames (``detected``, ``chain``, ``dedup``, ``ransac``,
            ``triangulation``).
        alignment: parallax-compensated alignment of the kept tracks (before/after/compensated/parallax); None for a
            free arrangement (a ring: no rows and columns to align).
        frames: number of frames used.
        verdicts: per view `lfgraph.refinement.assess.ViewVerdict` (OK, DRIFTED, UNCERTAIN, REFERENCE).
        sigma_px: the measurement sigma of the test (px per coordinate).
        frames_dropped: frames whose tracks were mostly mismatches.
        input_sigma_inf_px: (V,) 1-sigma transfer error at infinity of the calibration itself (from the marginals
            ``calibrate`` stored), or None when it stored none.
        intrinsics_mismatch_px: (RMS with the poses alone, with the intrinsics free too) px when other intrinsics
            explain the tracks far better than any poses: the calibration does not fit this camera.
    """

    rms_px: float
    view_rms_px: np.ndarray
    counts: dict[str, int]
    alignment: PointAlignmentReport | None
    frames: int
    verdicts: tuple = ()
    sigma_px: float = float("nan")
    frames_dropped: tuple[int, ...] = ()
    input_sigma_inf_px: np.ndarray | None = None
    heldout_px: tuple[float, float] = (float("nan"), float("nan"))
    notes: tuple[str, ...] = field(default=())
    intrinsics_mismatch_px: tuple[float, float] | None = None

    def drifted(self) -> list:
        """The views judged DRIFTED: a significant change, confirmed by held-out tracks, that moves the transfer at
        infinity by more than the config's ``tolerance_px`` (applied once, by the test that gave the verdicts)."""
        return [v for v in self.verdicts if v.verdict == Verdict.DRIFTED]

    @property
    def verdict(self) -> Verdict:
        """The capture's verdict: MISMATCH (the calibration does not fit this camera), DRIFTED (a view drifted),
        UNCERTAIN (no view could be confirmed OK: the frames cannot tell) or OK."""
        if self.intrinsics_mismatch_px is not None:
            return Verdict.MISMATCH
        if self.drifted():
            return Verdict.DRIFTED
        judged = [v for v in self.verdicts if v.verdict != Verdict.REFERENCE]
        if all(v.verdict == Verdict.UNCERTAIN for v in judged):  # also: no view judged at all
            return Verdict.UNCERTAIN
        return Verdict.OK

    def depth_errors(self, calib: Calibration, depths_m: Iterable[float]) -> dict[str, list[float | None]]:
        """Per view, the predicted depth error (m) at each range against the reference view: the paper's formula
        (`lfgraph.judge.depth.depth_error_m`) with the 1-sigma transfer at infinity as the disparity error — the
        calibration's own (stored marginals) when present, else the check's posterior."""
        from lfgraph.judge.depth import depth_error_m

        depths = np.asarray(list(depths_m), dtype=float)
        out = {}
        ref = calib.grid.reference
        for v in range(calib.num_views):
            if v == ref:
                continue
            e = self.sigma_inf_px(v)
            b = float(np.linalg.norm(calib.ref_T_view[v][:3, 3] - calib.ref_T_view[ref][:3, 3]))
            if not (np.isfinite(e) and b > 0):
                out[calib.grid.name(v)] = [None] * len(depths)
                continue
            out[calib.grid.name(v)] = [_finite_or_none(x) for x in depth_error_m(calib.intrinsics[v].fx, b, e,
                                                                                     depths)]
        return out

    def sigma_inf_px(self, v: int) -> float:
        """The 1-sigma transfer error at infinity of view v used for depth errors (see `depth_errors`)."""
        if self.input_sigma_inf_px is not None:
            return float(self.input_sigma_inf_px[v])
        for verdict in self.verdicts:
            if verdict.view == v:
                return float(verdict.predicted_transfer_px)
        return float("nan")

    def to_dict(self, calib: Calibration) -> dict:
        """JSON-friendly figures, views named as in the grid (``rRR_cCC``)."""
        return {
            "verdict": self.verdict, "rms_px": _finite_or_none(self.rms_px), "frames": self.frames,
            "tracks": dict(self.counts),
            "view_rms_px": {calib.grid.name(v): _finite_or_none(x) for v, x in enumerate(self.view_rms_px)},
            "alignment": None if self.alignment is None else {name: getattr(self.alignment, name).as_dict() for name
                                                              in ("before", "after", "compensated", "parallax")},
            "sigma_px": _finite_or_none(self.sigma_px), "frames_dropped": list(self.frames_dropped),
            "heldout_px": {"input": _finite_or_none(self.heldout_px[0]),
                           "refits": _finite_or_none(self.heldout_px[1])},
            "input_sigma_inf_px": None if self.input_sigma_inf_px is None else
            {calib.grid.name(v): _finite_or_none(x) for v, x in enumerate(self.input_sigma_inf_px)},
            "views": [v.as_dict() for v in self.verdicts],
            "intrinsics_mismatch_rms_px": None if self.intrinsics_mismatch_px is None else
            dict(zip(("poses_alone", "intrinsics_free"), self.intrinsics_mismatch_px, strict=True)),
        }


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def reprojection_residuals(calib: Calibration, tracks: Tracks) -> np.ndarray:
    """(V, N) residual norms (px) of tracks triangulated with ``calib``."""
    points = triangulate_dlt(calib, tracks.points_px, tracks.valid)
    return reprojection_errors(calib, points, tracks.points_px, tracks.valid)


def check(calib: Calibration, frames: Iterable[np.ndarray], settings: MatchSettings | None = None,
          config: RefineConfig | None = None) -> DriftReport:
    """The drift check: does the calibration still fit these ordinary (textured) frames?

    Tracks features through the grid, triangulates them with the calibration, drops mismatches (per frame, then
    frames whose tracks mostly disagree with the others'), reports the reprojection RMS per view and the alignment
    figures (with the stored rectification, or one computed here), and judges each view as `lfgraph.refine` would
    (without changing anything).

    Args:
        calib: the calibration to check.
        frames: (V, H, W) uint8 grayscale images per frame, of the calibration's grid and image size.
        settings: options of the default tracker's chain KLT; None: the tracker of ``config`` (`AutoTracker` by
            default: the chain KLT on a grid, KLT or SIFT by the links' angles on a free arrangement).
        config: the refinement options of the test (drift priors, significance, folds, ``tracker``); default
            `RefineConfig()`.
    """
    from lfgraph.rectification.rectify import compute_rectification, stored_rectification

    if settings is not None and not isinstance(settings, MatchSettings):
        raise TypeError(f"check: settings must be a lfgraph MatchSettings, got {type(settings).__name__}")

    if not isinstance(calib, Calibration):
        raise TypeError(f"check: calib must be a lfgraph.Calibration "
                        f"(load a file with lfgraph.Calibration.load), got {type(calib).__name__}")
    check_frames_argument(frames, "check")
    rect = None if calib.grid.is_free else stored_rectification(calib) or compute_rectification(calib)
    return check_capture(calib, rect, frames, settings, config)


def input_transfer_sigma_px(calib: Calibration) -> np.ndarray | None:
    """(V,) 1-sigma transfer error at infinity that the calibration's stored marginals predict (rotation and fx,
    fy, cx, cy, as independent), or None when ``calibrate`` stored none."""
    from lfgraph.refinement.posterior import Posterior, infinity_rays, predicted_transfer_px

    own = calib.sigmas
    if own is None:
        return None
    n = calib.num_views
    post = Posterior(np.stack([np.diag(s**2) for s in own.pose]), np.stack([np.diag(s**2) for s in own.intrinsics]),
                     np.zeros((n, 6, 4)), True, float("nan"))
    rays = infinity_rays(calib)
    return np.array([0.0 if v == calib.grid.reference else predicted_transfer_px(calib, post, v, rays)
                     for v in range(n)])


def check_capture(calib: Calibration, rect: Rectification | None, frames: Iterable[np.ndarray],
                  settings: MatchSettings | None = None, config: RefineConfig | None = None) -> DriftReport:
    """Run the drift check over (V, H, W) grayscale frames (lists of (H, W) for views of different sizes); the
    alignment figures need ``rect`` (None: not measured, as for a free arrangement)."""
    from lfgraph.refinement.assess import assess
    from lfgraph.refinement.config import RefineConfig
    from lfgraph.refinement.resample import canvas_for, track_views
    from lfgraph.refinement.tracks import pooled_filter, track_coverage

    config = config or RefineConfig()
    tracker = config.tracker if settings is None else AutoTracker(settings)
    pixels, valid, frame_ids, counts, n_frames = [], [], [], {}, 0
    canvas = canvas_for(calib)  # None unless the views differ in size
    sizes = calib.image_sizes
    for f, images in enumerate(frames):
        check_frame_array(images, f, calib.grid, sizes)
        tracks = track_views(tracker, images, calib.grid, canvas)
        res = reprojection_residuals(calib, tracks)
        keep = drop_mismatches(res)
        tracks_counts = {**tracks.counts, "triangulation": int(keep.sum())}
        for k, n in tracks_counts.items():
            counts[k] = counts.get(k, 0) + n
        pixels.append(tracks.points_px[:, keep])
        valid.append(tracks.valid[:, keep])
        frame_ids.append(np.full(int(keep.sum()), f))
        n_frames += 1
    if not n_frames:
        raise ValueError("the capture has no frames to check")
    px = np.concatenate(pixels, axis=1)
    ok = np.concatenate(valid, axis=1)
    frame_of = np.concatenate(frame_ids)
    good, dropped = pooled_filter(calib, px, ok, frame_of) if ok.shape[1] else (np.zeros(0, bool), [])
    px, ok, frame_of = px[:, good], ok[:, good], frame_of[good]
    counts["pooled"] = int(good.sum())
    if ok.shape[1] == 0:
        raise ValueError("no feature could be tracked through every view; the scene has too little texture "
                         "(or the views do not overlap)")
    res = reprojection_residuals(calib, Tracks(px, ok))
    rms = float(np.sqrt(np.nanmean(res**2)))
    view_rms = np.sqrt(np.nanmean(res**2, axis=1))
    verdicts: tuple = ()
    sigma = float("nan")
    heldout = (float("nan"), float("nan"))
    notes: list[str] = []
    mismatch = None
    try:
        result = assess(calib, px, ok, config, SilentObserver(), track_coverage(calib, px, ok), n_frames, frame_of)
        verdicts, sigma = result.verdicts, result.sigma_px
        heldout = (result.heldout_before_px, result.heldout_after_px)
        mismatch = result.intrinsics_mismatch
    except (RuntimeError, ValueError) as exc:  # too few tracks for a graph: no verdict rather than a wrong one
        notes.append(f"no per-view verdict: {exc}")
    alignment = None if rect is None else align_points(calib, rect, px, ok)
    return DriftReport(rms, view_rms, counts, alignment, n_frames, verdicts, sigma,
                       tuple(dropped), input_transfer_sigma_px(calib), heldout, tuple(notes), mismatch)
