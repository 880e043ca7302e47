"""One run of the refinement's stage schedule on a set of tracks (`fit_tracks`), with the measurement sigma
estimated or carried (`fit_auto`, `fit_sigma`), and the unassessed `refine_tracks`; `lfgraph.refinement.schedule`
runs them frame after frame and `lfgraph.refinement.assess` judges the result."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.geometry import rotation_angle_deg
from lfgraph.core.observer import Observer, SilentObserver, StageEnd, resolve, tell
from lfgraph.factors.noise import describe_noise
from lfgraph.refinement.config import RefineConfig, Stage
from lfgraph.refinement.priors import ViewPriors, view_priors
from lfgraph.refinement.report import StageReport
from lfgraph.refinement.stages import run_stage
from lfgraph.refinement.tracks import in_front
from lfgraph.refinement.triangulate import (
    drop_mismatches,
    finite_rms,
    normalized_coordinates,
    per_coordinate_sigma,
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
        rms_before = finite_rms(errors)
        before = calib
        tell(obs, "measurement_sigma", float(sigma_px))  # the stage's graph errors are in units of this sigma
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
        rms_after = finite_rms(errors)
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
            good = drop_mismatches(errors)
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

    # the sigma-estimating pass is not heard: the observer hears the pass that counts, once
    fit = fit_tracks(calib, pixels, valid, config, SilentObserver(), priors=priors, held_views=held_views,
                     sigma_px=FIRST_PASS_SIGMA_PX)
    sigma = fit_sigma(fit)
    if not np.isfinite(sigma):
        return fit
    resolve(observer).log(f"measurement sigma estimated from the first pass: {sigma:.4f} px per coordinate")
    return fit_tracks(calib, pixels, valid, config, observer, priors=priors, held_views=held_views, sigma_px=sigma)


def fit_sigma(fit: FitResult) -> float:
    """The measurement sigma the fit's residuals support (px per coordinate, floored)."""
    if fit.last_stage is None or fit.valid.shape[1] == 0:
        return float("nan")
    errors = reprojection_errors(fit.calib, fit.points, fit.pixels, fit.valid)
    free = fit.calib.num_views - 1 - len(fit.held)
    sigma = per_coordinate_sigma(errors, fit.points.shape[0], fit.last_stage.free_per_view * max(free, 0))
    return max(sigma, MIN_MEASUREMENT_SIGMA_PX) if np.isfinite(sigma) else sigma
