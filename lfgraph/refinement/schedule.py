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
from dataclasses import dataclass

import numpy as np

from lfgraph.calibration import Calibration
from lfgraph.factors.noise import describe_noise
from lfgraph.geometry import rotation_angle_deg
from lfgraph.observer import Observer, StageEnd, resolve
from lfgraph.refinement.assess import assess
from lfgraph.refinement.config import RefineConfig, Stage
from lfgraph.refinement.matching import Tracks, track_chain
from lfgraph.refinement.priors import ViewPriors, view_priors
from lfgraph.refinement.report import RefinementReport, StageReport
from lfgraph.refinement.stages import run_stage
from lfgraph.refinement.tracks import (
    COVERAGE_CELLS,
    OUTLIER_FACTOR,
    OUTLIER_FLOOR_PX,
    collect_tracks,
    in_front,
    pooled_filter,
    track_coverage,
)
from lfgraph.refinement.triangulate import (
    normalized_coordinates,
    reprojection_errors,
    triangulate_dlt,
    worst_error_filter,
)

FIRST_PASS_SIGMA_PX = 1.0  # the measurement sigma of the pass that estimates it
SIGMA_CARRY_RATIO = 1.15  # a sigma carried from the previous frames is kept while the fit's own residuals support
# one within this factor of it (measured frame to frame on paper-5x5: within 1.08); otherwise the pass is refitted
MIN_MEASUREMENT_SIGMA_PX = 0.05  # floor of the estimated sigma: KLT errors are not independent below this
CLEAN_FACTOR = 3.0  # the clean stage: worst residual > 3x the median track's ...
CLEAN_FLOOR_PX = 0.3  # ... and > 0.3 px (the prototype's threshold)
COVERAGE_WARN = 0.5  # warn when kept tracks fill less than half of the reference image's 8x8 cells
CHAIN_WARN = 0.05  # warn when fewer than 5 % of detected features can be followed through the whole grid
MATCH_WARN = 0.15  # warn when fewer than 15 % of detected features survive tracking and the filters


def with_reference(calib: Calibration, reference: int) -> Calibration:
    """The same array expressed relative to another reference view."""
    from lfgraph.grid import ViewGrid

    poses = np.linalg.inv(calib.ref_T_view[reference])[None] @ calib.ref_T_view
    poses[reference] = np.eye(4)
    return calib.replace(grid=ViewGrid(calib.grid.rows, calib.grid.cols, reference), ref_T_view=poses,
                         rectification=None)


def _rms(errors: np.ndarray) -> float:
    e = errors[np.isfinite(errors)]
    return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")


def _changes(before: Calibration, after: Calibration) -> tuple[np.ndarray, ...]:
    rot = np.asarray(rotation_angle_deg(np.swapaxes(before.ref_T_view[:, :3, :3], 1, 2)
                                        @ after.ref_T_view[:, :3, :3]))
    pos = 1e3 * np.linalg.norm(after.ref_T_view[:, :3, 3] - before.ref_T_view[:, :3, 3], axis=1)
    foc = np.array([np.hypot(a.fx - b.fx, a.fy - b.fy) for a, b in zip(after.intrinsics, before.intrinsics,
                                                                        strict=True)])
    pp = np.array([np.hypot(a.cx - b.cx, a.cy - b.cy) for a, b in zip(after.intrinsics, before.intrinsics,
                                                                       strict=True)])
    return rot, pos, foc, pp


@dataclass(frozen=True)
class FitResult:
    """One run of the stage schedule (`fit_tracks`): the calibration, stage reports, kept-track mask, and what the
    posterior needs — the last free stage, its tracks and landmarks, the measurement sigma and the held views."""

    calib: Calibration
    stages: list[StageReport]
    keep: np.ndarray
    last_stage: Stage | None
    pixels: np.ndarray
    valid: np.ndarray
    points: np.ndarray
    sigma_px: float
    held: frozenset[int]


def estimate_sigma_px(errors: np.ndarray, n_points: int, n_params: int) -> float:
    """Per-coordinate measurement sigma from Euclidean residuals: sqrt(sum r^2 / (2 n_obs - 3 n_points - params))."""
    e = errors[np.isfinite(errors)]
    dof = 2 * e.size - 3 * n_points - n_params
    if dof <= 0:
        return float("nan")
    return float(np.sqrt(np.sum(e**2) / dof))


def fit_tracks(calib: Calibration, pixels: np.ndarray, valid: np.ndarray, config: RefineConfig | None = None,
               observer: Observer | None = None, *, priors: ViewPriors | None = None,
               held_views: frozenset[int] = frozenset(), sigma_px: float | None = None) -> FitResult:
    """Run the stage schedule once with a given measurement sigma (None: the config's, or 1 px)."""
    config = config or RefineConfig()
    obs = resolve(observer)
    if sigma_px is None:
        sigma_px = config.measurement_sigma_px or FIRST_PASS_SIGMA_PX
    keep = np.ones(valid.shape[1], dtype=bool)
    reports = []
    last_free = None
    last: tuple = (None, pixels[:, :0], valid[:, :0], np.zeros((0, 3)), frozenset(held_views))
    norm, norm_intrinsics = None, None  # undistorted observations, recomputed only when a stage moves intrinsics
    for name in config.stages:
        t0 = time.perf_counter()
        if norm_intrinsics != calib.intrinsics:
            norm, norm_intrinsics = normalized_coordinates(calib, pixels, valid), calib.intrinsics
        # GTSAM pitfall: a landmark behind a camera gives a constant residual with zero Jacobians, which makes the
        # linear system singular and LM give up at once — guard cheirality before building the graph
        points = triangulate_dlt(calib, pixels[:, keep], valid[:, keep], norm[:, keep])
        front = in_front(calib, points, valid[:, keep])
        idx = np.nonzero(keep)[0]
        keep[idx[~front]] = False
        px, ok, points = pixels[:, keep], valid[:, keep], points[front]
        errors = reprojection_errors(calib, points, px, ok)
        if name == Stage.CLEAN:
            if last_free is None:
                raise ValueError("'clean' needs a free stage before it")
            good = worst_error_filter(errors, CLEAN_FACTOR, CLEAN_FLOOR_PX)
            idx = np.nonzero(keep)[0]
            keep[idx[~good]] = False
            px, ok, points = px[:, good], ok[:, good], points[good]
            errors = errors[:, good]
            stage, noise = last_free, config.clean_noise
        else:
            stage, noise = name, config.noise
        rms_before = _rms(errors)
        before = calib
        obs.stage_start(str(name), int(ok.sum()))
        per_view = ok.sum(axis=1)
        thin = frozenset(int(v) for v in np.nonzero(per_view < config.min_view_observations)[0])
        held = thin | frozenset(held_views)
        if thin and stage != Stage.POINTS:
            obs.log(f"stage {name}: views {', '.join(calib.grid.name(v) for v in sorted(thin))} have fewer than "
                f"{config.min_view_observations} observations and are held")
        calib, points, iterations = run_stage(stage, calib, px, ok, points, noise, sigma_px,
                                              config.scale_sigma_mm, config.max_iterations, obs.iteration, held,
                                              config.graph_hooks, priors)
        if stage != Stage.POINTS:
            last = (stage, px, ok, points, held)
        errors = reprojection_errors(calib, points, px, ok)
        rms_after = _rms(errors)
        obs.stage_end(StageEnd(str(name), calib, points, px, ok, errors))
        rot, pos, foc, pp = _changes(before, calib)
        reports.append(StageReport(name, int(ok.shape[1]), int(ok.sum()), rms_before, rms_after, iterations,
                                   time.perf_counter() - t0, rot, pos, foc, pp))
        obs.log(f"stage {name} ({stage}, {describe_noise(noise)}): {ok.shape[1]} landmarks, RMS "
            f"{rms_before:.4f} -> {rms_after:.4f} px, {iterations} iterations, max change {np.max(rot):.4f} deg "
            f"{np.max(pos):.3f} mm {np.max(foc):.3f} px (focal) {np.max(pp):.3f} px (principal point)")
        if name not in (Stage.POINTS, Stage.CLEAN):
            last_free = name
        if name != Stage.CLEAN:
            # re-run the outlier rejection between stages
            good = worst_error_filter(errors, OUTLIER_FACTOR, OUTLIER_FLOOR_PX)
            idx = np.nonzero(keep)[0]
            keep[idx[~good]] = False
        else:
            good = np.ones(px.shape[1], dtype=bool)
        obs.outliers(str(name), px[:, ~good], ok[:, ~good])
    return FitResult(calib, reports, keep, last[0], last[1], last[2], last[3], float(sigma_px), last[4])


def refine_tracks(calib: Calibration, pixels: np.ndarray, valid: np.ndarray, config: RefineConfig | None = None,
                  observer: Observer | None = None) -> tuple[Calibration, list[StageReport], np.ndarray]:
    """Run the stage schedule over pooled tracks: (V, N, 2) pixels with a (V, N) mask, any views (grid or not).

    With ``config.priors`` every freed parameter has a prior centred on ``calib`` (`lfgraph.refinement.priors`);
    with ``measurement_sigma_px=None`` the sigma is estimated from a first pass and the schedule re-run with it.
    This is the fit alone: `refine` adds the acceptance (significance, held-out tracks) and the verdicts.

    The observer hears ``stage_start`` before and ``stage_end`` and ``outliers`` (the tracks the stage's outlier
    rejection dropped) after every stage, and every optimiser iteration.

    Returns:
        the calibration, stage reports and the (N,) kept-track mask.
    """
    fit = fit_auto(calib, pixels, valid, config, observer)
    return fit.calib, fit.stages, fit.keep


def fit_auto(calib: Calibration, pixels: np.ndarray, valid: np.ndarray, config: RefineConfig | None = None,
             observer: Observer | None = None, held_views: frozenset[int] = frozenset(),
             sigma_px: float | None = None, priors: ViewPriors | None = None,
             sigma_estimate: float | None = None) -> FitResult:
    """`fit_tracks` with the config's priors centred on ``calib`` and, when neither ``sigma_px`` nor the config
    gives a measurement sigma, one estimated from the residuals of a first pass (floored) — or, when given,
    ``sigma_estimate``: the sigma the residuals of an earlier fit of the frames so far supported (`fit_sigma`), which
    spares that first pass frame after frame. ``priors`` replaces the config's (e.g. with some groups held)."""
    config = config or RefineConfig()
    if priors is None and config.priors:
        priors = view_priors(calib, config.drift)
    sigma_px = sigma_px or config.measurement_sigma_px
    if sigma_px is None and sigma_estimate is not None and np.isfinite(sigma_estimate):
        fit = fit_tracks(calib, pixels, valid, config, observer, priors=priors, held_views=held_views,
                         sigma_px=sigma_estimate)
        measured = fit_sigma(fit)
        # the sigma must be the one these tracks support: refit when they disagree with the earlier frames'
        if not np.isfinite(measured) or abs(np.log(measured / sigma_estimate)) <= np.log(SIGMA_CARRY_RATIO):
            resolve(observer).log(f"measurement sigma {sigma_estimate:.4f} px per coordinate (from the previous "
                                  f"frames; these tracks support {measured:.4f})")
            return fit
        resolve(observer).log(f"measurement sigma {measured:.4f} px per coordinate (these tracks; the previous "
                              f"frames supported {sigma_estimate:.4f}): refitted")
        sigma_px = measured
    if sigma_px is not None:
        return fit_tracks(calib, pixels, valid, config, observer, priors=priors, held_views=held_views,
                          sigma_px=sigma_px)
    from lfgraph.refinement.assess import _Silent  # the observer hears the pass that counts, once

    fit = fit_tracks(calib, pixels, valid, config, _Silent(), priors=priors, held_views=held_views,
                     sigma_px=FIRST_PASS_SIGMA_PX)
    sigma = fit_sigma(fit)
    if not np.isfinite(sigma):
        return fit
    resolve(observer).log(f"measurement sigma estimated from the first pass: {sigma:.4f} px per coordinate")
    return fit_tracks(calib, pixels, valid, config, observer, priors=priors, held_views=held_views, sigma_px=sigma)


def _timed_track_chain(images: np.ndarray, grid, settings) -> tuple[Tracks, float]:
    """`track_chain` and its wall seconds (it runs in `refine`'s worker thread)."""
    t0 = time.perf_counter()
    tracks = track_chain(images, grid, settings)
    return tracks, time.perf_counter() - t0


def fit_sigma(fit: FitResult) -> float:
    """The measurement sigma the fit's residuals support (px per coordinate, floored)."""
    if fit.last_stage is None or fit.valid.shape[1] == 0:
        return float("nan")
    errors = reprojection_errors(fit.calib, fit.points, fit.pixels, fit.valid)
    free = fit.calib.num_views - 1 - len(fit.held)
    n_free = (10 if fit.last_stage == Stage.ALL else 4 if fit.last_stage == Stage.INTRINSICS else 6) * max(free, 0)
    sigma = estimate_sigma_px(errors, fit.points.shape[0], n_free)
    return max(sigma, MIN_MEASUREMENT_SIGMA_PX) if np.isfinite(sigma) else sigma


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
        frames: (V, H, W) uint8 grayscale images per frame, of the calibration's grid and image size.
        config: options (`RefineConfig()` by default).
        observer: hears log lines, frames, stages, outliers and optimiser iterations (`lfgraph.observer`);
            default: log lines go to `logging`.

    Returns:
        the refined calibration (the input where no change was significant and confirmed) and the report (with
        ``verdicts``).

    Raises:
        ValueError: a frame whose shape does not match the calibration (named), no frame, or no track survives the
            filters (too little texture).
    """
    config = config or RefineConfig()
    obs = resolve(observer)
    # A frame's KLT does not depend on the calibration: it runs in a worker thread (OpenCV releases the GIL) while
    # the frames so far are refitted, and only judging its tracks waits for that fit. Results are unchanged.
    klt = ThreadPoolExecutor(max_workers=1, thread_name_prefix="lfgraph-klt")
    try:
        return _refine_frames(calib, frames, config, obs, klt)
    finally:
        klt.shutdown(wait=True, cancel_futures=True)


def _refine_frames(calib: Calibration, frames: Iterable[np.ndarray], config: RefineConfig, obs: Observer,
                   klt: ThreadPoolExecutor) -> tuple[Calibration, RefinementReport]:
    """`refine`'s body: the frame loop (``klt`` runs each frame's chain tracking) and the assessment."""
    w, h = calib.image_size_px
    t_start = time.perf_counter()
    pool_px: list[np.ndarray] = []
    pool_valid: list[np.ndarray] = []
    pool_frame: list[np.ndarray] = []
    counts: list[dict[str, int]] = []
    frame_rms: list[float] = []
    current = calib
    stop = "frames exhausted"
    used = pool_fitted = heard_iterations = 0
    t_match = t_adjust = 0.0  # wall seconds: matching + filters (its tracking as timed in the worker), adjustment
    c_adjust = 0.0  # CPU seconds of the adjustment (this thread's: the solver runs on one thread)
    c_start = time.process_time()
    sigma_estimate: float | None = None
    for f, images in enumerate(frames):
        if config.max_frames is not None and f >= config.max_frames:
            stop = f"max frames ({config.max_frames})"
            break
        if images.shape[0] != calib.num_views or images.shape[1:3] != (h, w):
            raise ValueError(f"frame {f} has {images.shape[0]} views of {images.shape[2]}x{images.shape[1]} px but the "
                             f"calibration is a {calib.grid} grid of {w}x{h} px views")
        tracking = klt.submit(_timed_track_chain, images, calib.grid, config.match)
        if used > 0 and pool_fitted < used:
            # frame after frame: the frames so far are refitted (MAP, centred on the input, from the input) before
            # this frame's tracks are judged with that fit; the last frame's pass is the assessed one below
            t0, c0 = time.perf_counter(), time.thread_time()
            px_pool, ok_pool = np.concatenate(pool_px, axis=1), np.concatenate(pool_valid, axis=1)
            if config.max_landmarks is not None and px_pool.shape[1] > config.max_landmarks:
                pick = np.sort(np.random.default_rng(used).choice(px_pool.shape[1], config.max_landmarks,
                                                                   replace=False))
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
        pts = triangulate_dlt(current, kept.points_px, kept.valid)
        rms_now = _rms(reprojection_errors(current, pts, kept.points_px, kept.valid))
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
    if used == 0:
        raise ValueError("no usable feature tracks in the capture: the scene needs texture visible in every view "
                         "(see the per-frame track counts)")
    pixels = np.concatenate(pool_px, axis=1)
    valid = np.concatenate(pool_valid, axis=1)
    frame_of = np.concatenate(pool_frame)
    good, dropped = pooled_filter(calib, pixels, valid, frame_of)
    if dropped:
        obs.log(f"frames {', '.join(map(str, dropped))}: most tracks stand out against the other frames' "
                f"(mismatches on a repetitive pattern?): dropped")
    pixels, valid, frame_of = pixels[:, good], valid[:, good], frame_of[good]
    if pixels.shape[1] == 0:
        raise ValueError("no usable feature tracks in the capture: the scene needs texture visible in every view "
                         "(see the per-frame track counts)")
    if config.max_landmarks is not None and pixels.shape[1] > config.max_landmarks:
        pick = np.sort(np.random.default_rng(used).choice(pixels.shape[1], config.max_landmarks, replace=False))
        pixels, valid, frame_of = pixels[:, pick], valid[:, pick], frame_of[pick]
    warnings = []
    coverage = track_coverage(calib, pixels, valid)
    t0, c0 = time.perf_counter(), time.thread_time()
    result = assess(calib, pixels, valid, config, obs, coverage, used, frame_of, sigma_estimate)
    t_adjust += time.perf_counter() - t0
    c_adjust += time.thread_time() - c0
    c_match = time.process_time() - c_start - c_adjust  # the rest: tracking (OpenCV's threads too) and filters
    fit = result.fit
    kept_px, kept_valid = pixels[:, fit.keep], valid[:, fit.keep]
    before = _rms(reprojection_errors(calib, triangulate_dlt(calib, kept_px, kept_valid), kept_px, kept_valid))
    after = _rms(reprojection_errors(fit.calib, triangulate_dlt(fit.calib, kept_px, kept_valid), kept_px,
                                     kept_valid))
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
                        f"through every view: the disparity between neighbouring views is too large for the tracker "
                        f"(a near scene, a narrow field of view or a wide pitch); use a farther scene")
    if dropped:
        warnings.append(f"frames {', '.join(map(str, dropped))} dropped: most of their tracks disagree with the other "
                        f"frames' (mismatches)")
    if not result.accepted:
        warnings.append("no view changed: " + ("no change was significant against its posterior sigma"
                                               if np.isnan(result.heldout_before_px) else
                                               f"refits did not predict held-out tracks better "
                                               f"({result.heldout_before_px:.4f} px input vs "
                                               f"{result.heldout_after_px:.4f} px refined)")
                        + "; the input calibration is kept")
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
