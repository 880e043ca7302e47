"""One run of the refinement's stage schedule on a set of tracks (`fit_tracks`), with the measurement sigma
estimated or carried (`fit_auto`, `fit_sigma`), and the unassessed `refine_tracks`; `lfgraph.refinement.schedule`
runs them frame after frame and `lfgraph.refinement.assess` judges the result."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import gtsam
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.geometry import rotation_angle_deg
from lfgraph.core.observer import Observer, SilentObserver, StageEnd, resolve, tell
from lfgraph.engine.bulk_noise import BulkNoise, NotBulk
from lfgraph.factors.noise import Noise, RobustKernel, describe_noise, measurement_noise
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
    robust_per_coordinate_sigma,
    triangulate_dlt,
    worst_error_filter,
)

FIRST_PASS_SIGMA_PX = 1.0  # the measurement sigma of the pass that estimates it
SIGMA_CARRY_RATIO = 1.15  # a sigma carried from the previous frames is kept while the fit's own residuals support
# one within this factor of it (measured frame to frame on paper-5x5: within 1.08); otherwise the pass is refitted
MIN_MEASUREMENT_SIGMA_PX = 0.05  # floor of the estimated sigma: KLT errors are not independent below this
MIN_WEIGHT = 1e-9  # a kernel weight below this gives an observation no say (Tukey's is 0 beyond its threshold)
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
    posterior needs — the last free stage, its tracks and landmarks, the measurement sigma and the held views — and
    the noise model that stage ran with (what `fit_sigma` and the gates of `lfgraph.refinement.assess` judge by)."""

    calib: Calibration
    stages: list[StageReport]
    keep: np.ndarray
    last_stage: Stage | None
    pixels: np.ndarray
    valid: np.ndarray
    points: np.ndarray
    sigma_px: float
    held: frozenset[int]
    noise: Noise | None = None


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
    last: tuple = (None, pixels[:, :0], valid[:, :0], np.zeros((0, 3)), frozenset(held_views), None)
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
            last = (stage, px, ok, points, held, noise)
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
    return FitResult(calib, reports, keep, last[0], last[1], last[2], last[3], float(sigma_px), last[4], last[5])


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
    """The measurement sigma the fit's residuals support (px per coordinate, floored): from their mean square under a
    Gaussian noise model, from their median (`robust_per_coordinate_sigma`) under a robust kernel, which a share of
    wrong matches must not inflate (5 % of 2-8 px: 0.64-0.96 px per coordinate from the mean square, ~0.06 from the
    median, on tracks of ~0.05 px)."""
    if fit.last_stage is None or fit.valid.shape[1] == 0:
        return float("nan")
    errors = reprojection_errors(fit.calib, fit.points, fit.pixels, fit.valid)
    free = fit.calib.num_views - 1 - len(fit.held)
    estimate = robust_per_coordinate_sigma if has_kernel(fit.noise) else per_coordinate_sigma
    sigma = estimate(errors, fit.points.shape[0], fit.last_stage.free_per_view * max(free, 0))
    return max(sigma, MIN_MEASUREMENT_SIGMA_PX) if np.isfinite(sigma) else sigma


def has_kernel(noise: Noise | None) -> bool:
    """Whether a noise model weighs large residuals down: a kernel by name (not ``none``), a GTSAM M-estimator or a
    ``noiseModel.Robust`` (not GTSAM's ``Null``, which is least squares)."""
    if isinstance(noise, RobustKernel):
        return noise.name != "none"
    if isinstance(noise, gtsam.noiseModel.Robust):
        noise = noise.robust()
    return isinstance(noise, gtsam.noiseModel.mEstimator.Base) and \
        not isinstance(noise, gtsam.noiseModel.mEstimator.Null)


def gate_rms(errors: np.ndarray, noise: Noise | None, sigma_px: float) -> float:
    """The gates' summary of (V, N) Euclidean residuals (px) under the chosen noise model: their RMS under a Gaussian
    one (exactly `finite_rms`); under a kernel, the RMS that Gaussian residuals of the same mean cost would have,
    s sqrt(2 mean rho(e / s)) with s the model's pixels per whitened unit (``sigma_px``, or a full model's own): a
    wrong match counts at most as much as the kernel lets it count in the fit. (With GTSAM's Scalar reweighting each
    coordinate is taken as e / sqrt(2).) NaN without residuals."""
    if not has_kernel(noise):
        return finite_rms(errors)
    e = errors[np.isfinite(errors)]
    if not e.size:
        return float("nan")
    try:
        bulk = BulkNoise(measurement_noise(noise, sigma_px))
    except NotBulk:  # a model the bulk solver does not take (it ran on GTSAM's factors): judged as least squares
        return finite_rms(errors)
    s = bulk.isotropic_sigma or float(1.0 / np.sqrt(abs(np.linalg.det(bulk.sqrt_information))))
    kernel = bulk.kernel
    loss = kernel.losses(e / s) if kernel.block else 2.0 * kernel.losses(e / s / np.sqrt(2.0))
    return float(s * np.sqrt(2.0 * np.mean(loss)))


def same_track_costs(calibs: list[Calibration], pixels: np.ndarray, valid: np.ndarray, noise: Noise | None,
                     sigma_px: float, max_iterations: int = 100) -> list[float]:
    """How well each calibration explains the same tracks under the same noise model: the tracks in front of every
    view of every calibration, their landmarks refitted at each (a ``points`` stage from DLT, under ``noise``), the
    residuals summarised by `gate_rms` (px)."""
    points = [triangulate_dlt(c, pixels, valid) for c in calibs]
    front = np.logical_and.reduce([in_front(c, p, valid) for c, p in zip(calibs, points, strict=True)])
    px, ok = pixels[:, front], valid[:, front]
    costs = []
    for c, p in zip(calibs, points, strict=True):
        _, refit, _ = run_stage(Stage.POINTS, c, px, ok, p[front], noise or RobustKernel(), sigma_px,
                                max_iterations=max_iterations)
        costs.append(gate_rms(reprojection_errors(c, refit, px, ok), noise, sigma_px))
    return costs


def informative(fit: FitResult) -> FitResult:
    """The fit with only the tracks its noise model lets speak: under a kernel that gives far residuals no weight
    (Tukey, ...), a track with fewer than two observations of weight leaves its landmark undetermined and the
    marginals indeterminate, while it says nothing about the cameras (issue 40: Tukey on 5 % wrong matches of 2-8 px,
    186 of 851 tracks, and no posterior at all). Unchanged under the Gaussian model and other kernels."""
    if not has_kernel(fit.noise) or fit.valid.shape[1] == 0:
        return fit
    try:
        bulk = BulkNoise(measurement_noise(fit.noise, fit.sigma_px))
    except NotBulk:
        return fit
    s = bulk.isotropic_sigma or float(1.0 / np.sqrt(abs(np.linalg.det(bulk.sqrt_information))))
    e = reprojection_errors(fit.calib, fit.points, fit.pixels, fit.valid)
    weighted = fit.valid & (np.nan_to_num(bulk.kernel.weights(np.nan_to_num(e / s, nan=0.0)), nan=0.0) > MIN_WEIGHT)
    keep = weighted.sum(axis=0) >= 2
    if keep.all():
        return fit
    return dataclasses.replace(fit, pixels=fit.pixels[:, keep], valid=fit.valid[:, keep], points=fit.points[keep])
