"""Auto-refinement from ordinary scenes (paper Section 4): tracks -> filters -> staged GTSAM bundle adjustment,
frame after frame.

Schedules (`lfgraph.refinement.config`): ``paper`` = points, intrinsics, all (the paper's strategy); ``default`` =
points, poses, clean — chosen by measurement (`benchmarks/refine.py`): holding the intrinsics and cleaning bad
tracks is several times more accurate in view rotation and transfer error at infinity. ``clean`` drops tracks whose
worst residual stands out (the F-matrix test cannot see errors along the baseline), then repeats the previous free
stage (with ``clean_robust`` when set).
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.observer import Observer, resolve, tell
from lfgraph.engine.triangulate import (
    finite_rms,
    reprojection_errors,
    triangulate_dlt,
)
from lfgraph.io.capture import check_frame_array, check_frames_argument
from lfgraph.refinement.assess import assess
from lfgraph.refinement.config import RefineConfig
from lfgraph.refinement.fit import fit_auto, fit_sigma
from lfgraph.refinement.matching import Tracker, Tracks
from lfgraph.refinement.report import RefinementReport
from lfgraph.refinement.resample import ViewCanvas, canvas_for, track_views
from lfgraph.refinement.tracks import (
    COVERAGE_CELLS,
    collect_tracks,
    pooled_filter,
    track_coverage,
)

COVERAGE_WARN = 0.5  # warn when kept tracks fill less than half of the reference image's 8x8 cells
CHAIN_WARN = 0.05  # warn when fewer than 5 % of detected features can be followed through the whole grid
MATCH_WARN = 0.15  # warn when fewer than 15 % of detected features survive tracking and the filters


def with_reference(calib: Calibration, reference: int) -> Calibration:
    """The same array expressed relative to another reference view (`Calibration.with_reference`)."""
    return calib.with_reference(reference)


def _timed_track(images: np.ndarray, grid, tracker: Tracker, canvas: ViewCanvas | None) -> tuple[Tracks, float]:
    """The tracker's tracks and its wall seconds (it runs in `refine`'s worker thread); views of different sizes
    are tracked on the reference view's scale (`track_views`)."""
    t0 = time.perf_counter()
    tracks = track_views(tracker, images, grid, canvas)
    return tracks, time.perf_counter() - t0


FOREIGN_RMS_PX = 1.0  # tracks that fit the input this badly, and refits of the poses that predict them no better:
# a calibration of another camera (a knocked rig's refits predict better, even when the folds disagree)


def refine(calib: Calibration, frames: Iterable[np.ndarray], config: RefineConfig | None = None,
           observer: Observer | None = None) -> tuple[Calibration, RefinementReport]:
    """Refine a calibration from ordinary (textured) captures, frame after frame.

    Each frame's tracks (chain KLT + filters + the triangulation filter, judged with the MAP fit of the frames so
    far) join the pool; every pass starts from, and has its priors centred on, the input calibration, and the
    baselines keep their lengths. It stops after ``max_frames``, when the frames run out, or when a new frame already
    fits at ``target_rms_px``. The pooled tracks then go through `lfgraph.refinement.assess.assess`: the MAP fit,
    its posterior, held-out folds and a per-view verdict; only significant, confirmed changes are applied.

    Args:
        calib: the calibration to refine (e.g. from the pattern).
        frames: (V, H, W) uint8 grayscale images per frame, of the calibration's grid and image size (for a rig
            whose views differ in size, a list of each view's (H, W) image, as `CaptureSet.frames` yields).
        config: options (`RefineConfig()` by default).
        observer: hears log lines, frames, stages, outliers and optimiser iterations (`lfgraph.core.observer`);
            default: log lines go to `logging`.

    Returns:
        the refined calibration (the input where no change was significant and confirmed) and the report (with
        ``verdicts``).

    Raises:
        ValueError: a frame whose shape, dtype or size does not match the calibration (named), no frame, no
            track survives the filters (too little texture).
        TypeError: ``calib``, ``config`` or ``frames`` of the wrong kind (named).
    """
    if not isinstance(calib, Calibration):
        raise TypeError(f"refine: calib must be a lfgraph.Calibration "
                        f"(load a file with lfgraph.Calibration.load), got {type(calib).__name__}")
    if config is not None and not isinstance(config, RefineConfig):
        raise TypeError(f"refine: config must be a lfgraph.RefineConfig, got {type(config).__name__}")
    check_frames_argument(frames, "refine")
    config = config or RefineConfig()
    obs = resolve(observer)
    # A frame's KLT does not depend on the calibration: it runs in a worker thread (OpenCV releases the GIL) while
    # the frames so far are refitted, and only judging its tracks waits for that fit. Results are unchanged.
    klt = ThreadPoolExecutor(max_workers=1, thread_name_prefix="lfgraph-klt")
    tell(obs, "run_start", "refine", calib)  # e.g. a rerun recording shows the input rig and the refine layout
    try:
        out, report = _refine_frames(calib, frames, config, obs, klt)
    finally:
        klt.shutdown(wait=True, cancel_futures=True)
    tell(obs, "run_end", "refine", calib, out, report)  # ... and the refined rig, the change, the summaries
    return out, report


def _refine_frames(calib: Calibration, frames: Iterable[np.ndarray], config: RefineConfig, obs: Observer,
                   klt: ThreadPoolExecutor) -> tuple[Calibration, RefinementReport]:
    """`refine`'s body: the frame loop (``klt`` runs each frame's chain tracking) and the assessment."""
    t_start = time.perf_counter()
    pool_px, pool_valid, pool_frame = [], [], []  # per frame: kept tracks (V, N, 2), (V, N) and their frame (N,)
    counts: list[dict[str, int]] = []
    frame_rms: list[float] = []
    current = calib
    stop = "frames exhausted"
    used = pool_fitted = heard_iterations = 0
    t_match = t_adjust = 0.0  # wall seconds: matching + filters (its tracking as timed in the worker), adjustment
    c_adjust = 0.0  # CPU seconds of the adjustment (this thread's: the solver runs on one thread)
    c_start = time.process_time()
    sigma_estimate: float | None = None
    canvas, sizes = canvas_for(calib), calib.image_sizes  # the canvas: None unless the views differ in size
    for f, images in enumerate(frames):
        if config.max_frames is not None and f >= config.max_frames:
            stop = f"max frames ({config.max_frames})"
            break
        check_frame_array(images, f, calib.grid, sizes)
        tracking = klt.submit(_timed_track, images, calib.grid, config.tracker, canvas)
        if used > 0 and pool_fitted < used:
            # frame after frame: the frames so far are refitted (MAP, centred on the input, from the input) before
            # this frame's tracks are judged with that fit; the last frame's pass is the assessed one below
            t0, c0 = time.perf_counter(), time.thread_time()
            px_pool, ok_pool = np.concatenate(pool_px, axis=1), np.concatenate(pool_valid, axis=1)
            pick = _subsample(px_pool.shape[1], config.max_landmarks, used)
            px_pool, ok_pool = px_pool[:, pick], ok_pool[:, pick]
            pass_fit = fit_auto(calib, px_pool, ok_pool, config, obs, sigma_estimate=sigma_estimate)
            sigma_estimate = fit_sigma(pass_fit)  # the next pass's sigma: no sigma-estimating pass of its own
            current = pass_fit.calib
            heard_iterations += sum(st.iterations for st in pass_fit.stages)
            pool_fitted = used
            t_adjust += time.perf_counter() - t0
            c_adjust += time.thread_time() - c0
        obs.frame(f, images)
        tracks, t_tracking = tracking.result()  # waits only for the tracking the refit above did not hide
        t0 = time.perf_counter()
        # tracks are judged with the MAP fit of the frames so far, itself centred on the input and started from it:
        # one frame's poor fit never carries into the next
        kept, c = collect_tracks(current, tracks, config.triangulation_filter)
        t_match += t_tracking + time.perf_counter() - t0
        counts.append(c)
        rms_now = _rms_with(current, kept.points_px, kept.valid)
        frame_rms.append(rms_now)
        obs.log(f"frame {f}: tracks " + ", ".join(f"{k} {v}" for k, v in c.items())
            + f"; RMS with the current calibration {rms_now:.4f} px")
        if config.target_rms_px is not None and used > 0 and rms_now <= config.target_rms_px:
            stop = f"frame {f} fits at {rms_now:.4f} px <= target {config.target_rms_px:g} px"
            break
        if kept.num_tracks == 0:
            obs.log(f"frame {f}: no usable tracks, skipped")
            continue
        pool_px.append(kept.points_px)
        pool_valid.append(kept.valid)
        pool_frame.append(np.full(kept.num_tracks, f))
        used += 1
    pixels, valid, frame_of, dropped = _pooled_tracks(calib, pool_px, pool_valid, pool_frame, config, obs, used)
    coverage = track_coverage(calib, pixels, valid)
    t0, c0 = time.perf_counter(), time.thread_time()
    result = assess(calib, pixels, valid, config, obs, coverage, used, frame_of, sigma_estimate)
    t_adjust += time.perf_counter() - t0
    c_adjust += time.thread_time() - c0
    c_match = time.process_time() - c_start - c_adjust  # the rest: tracking (OpenCV's threads too) and filters
    fit = result.fit
    kept_px, kept_valid = pixels[:, fit.keep], valid[:, fit.keep]
    before = _rms_with(calib, kept_px, kept_valid)
    after = _rms_with(result.calib, kept_px, kept_valid)  # of what is written (the input where nothing was applied)
    warnings = refinement_warnings(coverage, counts, dropped, result, before)
    for w in warnings:
        obs.log(f"warning: {w}")
    total_iterations = heard_iterations + sum(st.iterations for st in fit.stages)
    report = RefinementReport(tuple(counts), tuple(frame_rms), tuple(fit.stages), used, stop, before, after,
                              time.perf_counter() - t_start, t_match, t_adjust, result.accepted, coverage,
                              tuple(warnings), total_iterations, result.verdicts, result.heldout_before_px,
                              result.heldout_after_px, result.sigma_px, tuple(dropped), cpu_seconds_matching=c_match,
                              cpu_seconds_adjustment=c_adjust)
    out = result.calib
    metrics = {**dict(out.metrics or {}), **report.metrics()}
    return out.replace(metrics=metrics, rectification=None), report


NO_TRACKS = ("no usable feature tracks in the capture: the scene needs texture visible in every view (see the "
             "per-frame track counts)")


def _rms_with(calib: Calibration, pixels: np.ndarray, valid: np.ndarray) -> float:
    """RMS reprojection error (px) of tracks triangulated (DLT) and reprojected with ``calib``."""
    return finite_rms(reprojection_errors(calib, triangulate_dlt(calib, pixels, valid), pixels, valid))


def _subsample(n: int, limit: int | None, seed: int) -> np.ndarray:
    """Indices of at most ``limit`` of ``n`` tracks (all of them, in order, when there are not more)."""
    if limit is None or n <= limit:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, limit, replace=False))


def _pooled_tracks(calib: Calibration, pool_px: list[np.ndarray], pool_valid: list[np.ndarray],
                   pool_frame: list[np.ndarray], config: RefineConfig, obs: Observer,
                   used: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
    """Every frame's kept tracks pooled, mismatches against the pool dropped (`pooled_filter`: whole frames too),
    at most ``config.max_landmarks`` kept: (pixels (V, N, 2), valid (V, N), frame of each (N,), dropped frames).

    Raises:
        ValueError: no usable track (none kept, or none left by the pooled filter).
    """
    if not pool_px:
        raise ValueError(NO_TRACKS)
    pixels, valid, frame_of = (np.concatenate(pool_px, axis=1), np.concatenate(pool_valid, axis=1),
                               np.concatenate(pool_frame))
    good, dropped = pooled_filter(calib, pixels, valid, frame_of)
    if dropped:
        obs.log(f"frames {', '.join(map(str, dropped))}: most tracks stand out against the other frames' "
                f"(mismatches on a repetitive pattern?): dropped")
    pixels, valid, frame_of = pixels[:, good], valid[:, good], frame_of[good]
    if pixels.shape[1] == 0:
        raise ValueError(NO_TRACKS)
    pick = _subsample(pixels.shape[1], config.max_landmarks, used)
    return pixels[:, pick], valid[:, pick], frame_of[pick], dropped


def refinement_warnings(coverage: float, counts: list[dict[str, int]], dropped: list[int], result,
                        rms_before_px: float) -> list[str]:
    """What a user must hear about a refinement: poor coverage, few matches or chains, dropped frames, nothing
    changed (and why), a calibration that does not belong to the capture (``result``: the `assess` result;
    ``rms_before_px``: the kept tracks' RMS with the input)."""
    warnings: list[str] = []
    before = rms_before_px
    if coverage < COVERAGE_WARN:
        warnings.append(f"tracks cover only {100 * coverage:.0f} % of the reference image ({COVERAGE_CELLS}x"
                        f"{COVERAGE_CELLS} cells): rotations about the optical axis are weakly constrained; use "
                        f"scenes with texture across the whole field of view")
    detected = sum(c.get("detected", 0) for c in counts)
    survived = sum(c.get("triangulation", 0) for c in counts)
    if detected and survived / detected < MATCH_WARN:
        warnings.append(f"only {survived} of {detected} features ({100 * survived / max(detected, 1):.0f} %) survived "
                        f"tracking and the filters: matches are poor (repetitive or weak texture, occlusions)")
    chained = sum(c.get("chain", 0) for c in counts)
    if detected and chained / detected < CHAIN_WARN:
        warnings.append(f"only {chained} of {detected} features ({100 * chained / detected:.0f} %) could be followed "
                        f"through every view: neighbouring views' images differ by more than the tracker follows, even "
                        f"with a deeper pyramid (a knock of several degrees, a near scene, a narrow field of view or a "
                        f"wide pitch); refine with --tracker sift (tracker=lf.tracker_by_name('sift')), which does "
                        f"not care how far the image moved, or use a farther scene")
    if dropped:
        warnings.append(f"frames {', '.join(map(str, dropped))} dropped: most of their tracks disagree with the other "
                        f"frames' (mismatches)")
    if not result.accepted:
        b, a = result.heldout_before_px, result.heldout_after_px
        foreign, outliers = result.intrinsics_mismatch, result.outliers
        why = (f"other intrinsics explain the tracks far better than any poses ({foreign[0]:.4f} px RMS with the poses "
               f"alone, {foreign[1]:.4f} px with the intrinsics free)" if foreign is not None else
               outliers.text() if outliers is not None and result.blocked else
               "no change was significant against its posterior sigma" if np.isnan(b) else
               f"refits did not predict held-out tracks better ({b:.4f} px input vs {a:.4f} px refined)"
               if not a < b else
               f"refits predict held-out tracks better than the input ({b:.4f} -> {a:.4f} px) but far worse than "
               f"they fit their own ({result.fit.sigma_px:.4f} px per coordinate): the frames disagree")
        if outliers is not None and outliers.text() not in why:
            why += f"; and {outliers.text()}"
        warnings.append(f"no view changed: {why}; the input calibration is kept")
        if before > FOREIGN_RMS_PX and outliers is None:  # wrong matches were named: no other camera is implied
            warnings.append(f"the tracks fit the input calibration at {before:.2f} px RMS and no refit of the views' "
                            f"poses explains them consistently: is this calibration for this camera (focal length, "
                            f"principal point, lens, image size, view order)? Re-calibrate rather than refine (or, "
                            f"if it is, the tracks are mismatched: a repeated texture)")
    return warnings
