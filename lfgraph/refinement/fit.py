"""One run of the refinement's stage schedule on a set of tracks (`fit_tracks`), with the measurement sigma
estimated or carried (`fit_auto`, `fit_sigma`), and the unassessed `refine_tracks`; `lfgraph.refinement.schedule`
runs them frame after frame and `lfgraph.refinement.assess` judges the result."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import gtsam
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.geometry import rotation_angle_deg
from lfgraph.core.observer import Observer, SilentObserver, resolve, tell
from lfgraph.engine.bulk_noise import BulkNoise, NotBulk
from lfgraph.engine.schedule import StageRecord, Step, TrackState, Triangulator, at_supported_sigma, run_schedule
from lfgraph.engine.triangulate import (
    finite_rms,
    per_coordinate_sigma,
    reprojection_errors,
    robust_per_coordinate_sigma,
    triangulate_dlt,
    worst_error_filter,
)
from lfgraph.factors.noise import Noise, RobustKernel, describe_noise, measurement_noise
from lfgraph.refinement.config import RefineConfig, Stage
from lfgraph.refinement.priors import ViewPriors, view_priors
from lfgraph.refinement.report import StageReport
from lfgraph.refinement.stages import run_stage
from lfgraph.refinement.tracks import in_front

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
    posterior needs to rebuild the graph that was solved — the last free stage, its tracks and landmarks, the
    measurement sigma, the held views, the noise model that stage ran with (what `fit_sigma` and the gates of
    `lfgraph.refinement.assess` judge by) and the priors it ran with (None: a free fit)."""

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
    priors: ViewPriors | None = None


def fit_tracks(calib: Calibration, pixels: np.ndarray, valid: np.ndarray, config: RefineConfig | None = None,
               observer: Observer | None = None, *, priors: ViewPriors | None = None,
               held_views: frozenset[int] = frozenset(), sigma_px: float | None = None) -> FitResult:
    """Run the stage schedule once with a given measurement sigma (None: the config's, or 1 px): each stage a `Step`
    of the one schedule (`lfgraph.engine.schedule.run_schedule`), its landmarks triangulated from the calibration so
    far and those behind a view dropped, the clean stage's worst-error filter before it."""
    config = config or RefineConfig()
    obs = resolve(observer)
    if sigma_px is None:
        sigma_px = config.measurement_sigma_px or FIRST_PASS_SIGMA_PX
    triangulated = Triangulator(pixels, valid)
    ran: list[tuple] = []  # per stage run: the stage it ran (clean re-runs the last free one), held views, noise
    free_before: list[Stage] = []  # the free stages so far: what a clean stage re-runs

    def step(name: Stage) -> Step:
        stage, noise = (None, config.clean_noise) if name == Stage.CLEAN else (name, config.noise)

        def prepare(state: TrackState) -> TrackState:
            # GTSAM pitfall: a landmark behind a camera gives a constant residual with zero Jacobians, which makes
            # the linear system singular and LM give up at once — guard cheirality before building the graph
            state = triangulated(state)
            state = state.subset(in_front(state.calib, state.points, state.valid))
            if name == Stage.CLEAN:
                if not free_before:
                    raise ValueError("'clean' needs a free stage before it")
                state = state.subset(worst_error_filter(state.errors(), CLEAN_FACTOR, CLEAN_FLOOR_PX))
            tell(obs, "measurement_sigma", float(sigma_px))  # the stage's graph errors are in units of this sigma
            return state

        def solve(state: TrackState) -> tuple[TrackState, int]:
            run = free_before[-1] if stage is None else stage
            thin = frozenset(int(v) for v in np.nonzero(state.valid.sum(axis=1) < config.min_view_observations)[0])
            held = thin | frozenset(held_views)
            if thin and run != Stage.POINTS:
                obs.log(f"stage {name}: views {', '.join(state.calib.grid.name(v) for v in sorted(thin))} have fewer "
                        f"than {config.min_view_observations} observations and are held")
            new, points, iterations = run_stage(run, state.calib, state.pixels, state.valid, state.points, noise,
                                                sigma_px, config.scale_sigma_mm, config.max_iterations,
                                                obs.iteration, held, config.graph_hooks, priors)
            ran.append((run, held, noise))
            if name not in (Stage.POINTS, Stage.CLEAN):
                free_before.append(name)
            return dataclasses.replace(state, calib=new, points=points), iterations

        def describe(r: StageRecord) -> str:
            rot, pos, foc, pp = _changes(r.before, r.state.calib)
            return (f"stage {name} ({ran[-1][0]}, {describe_noise(noise)}): {r.landmarks} landmarks, RMS "
                    f"{r.rms_before_px:.4f} -> {r.rms_after_px:.4f} px, {r.iterations} iterations, max change "
                    f"{np.max(rot):.4f} deg {np.max(pos):.3f} mm {np.max(foc):.3f} px (focal) {np.max(pp):.3f} px "
                    "(principal point)")

        return Step(str(name), solve, prepare, outliers=name != Stage.CLEAN, describe=describe)

    state, records = run_schedule([step(name) for name in config.stages], TrackState.start(calib, pixels, valid), obs)
    reports = [StageReport(name, r.landmarks, r.observations, r.rms_before_px, r.rms_after_px, r.iterations,
                           r.seconds, *_changes(r.before, r.state.calib))
               for name, r in zip(config.stages, records, strict=True)]
    last = next(((run, r.state) for run, r in zip(reversed(ran), reversed(records), strict=True)
                 if run[0] != Stage.POINTS), None)
    if last is None:
        return FitResult(state.calib, reports, state.kept(valid.shape[1]), None, pixels[:, :0], valid[:, :0],
                         np.zeros((0, 3)), float(sigma_px), frozenset(held_views), None, priors)
    (stage, held, noise), ran_state = last
    return FitResult(state.calib, reports, state.kept(valid.shape[1]), stage, ran_state.pixels, ran_state.valid,
                     ran_state.points, float(sigma_px), held, noise, priors)


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
    spares that first pass frame after frame while these tracks support it (`SIGMA_CARRY_RATIO`). Both are the one
    refit loop (`lfgraph.engine.schedule.at_supported_sigma`). ``priors`` replaces the config's (e.g. with some groups
    held)."""
    config = config or RefineConfig()
    say = resolve(observer)
    if priors is None and config.priors:
        priors = view_priors(calib, config.drift)
    sigma_px = sigma_px or config.measurement_sigma_px
    carried = sigma_px is None and sigma_estimate is not None and np.isfinite(sigma_estimate)
    if sigma_px is not None:
        return fit_tracks(calib, pixels, valid, config, observer, priors=priors, held_views=held_views,
                          sigma_px=sigma_px)

    def fit(sigma: float, k: int) -> FitResult:
        # without a carried sigma the first pass only estimates it: the observer hears the pass that counts, once
        heard = observer if carried or k > 0 else SilentObserver()
        return fit_tracks(calib, pixels, valid, config, heard, priors=priors, held_views=held_views, sigma_px=sigma)

    def agree(measured: float, assumed: float, _: FitResult) -> bool:
        if not np.isfinite(measured):
            if carried:
                say.log(f"measurement sigma {assumed:.4f} px per coordinate (from the previous frames; these tracks "
                        f"support {measured:.4f})")
            return True
        if not carried:
            say.log(f"measurement sigma estimated from the first pass: {measured:.4f} px per coordinate")
            return False
        if abs(np.log(measured / assumed)) <= np.log(SIGMA_CARRY_RATIO):
            say.log(f"measurement sigma {assumed:.4f} px per coordinate (from the previous frames; these tracks "
                    f"support {measured:.4f})")
            return True
        say.log(f"measurement sigma {measured:.4f} px per coordinate (these tracks; the previous frames supported "
                f"{assumed:.4f}): refitted")
        return False

    return at_supported_sigma(fit, sigma_estimate if carried else FIRST_PASS_SIGMA_PX, fit_sigma, agree, 2)[0]


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
