"""Self-calibration's schedule: its MAP stages as steps of the one schedule (`lfgraph.engine.schedule`) — each freeing
the groups of `SelfCalConfig.stages` that the tracks' coverage can determine, with the kernel's scale from the last
stage's residuals, landmarks without depth dropped after it, the one mismatch rule, and the frames' coverage refused
after the poses (all but the depth span) — and the final least-squares stage repeated at the noise its own residuals
support (`lfgraph.engine.schedule.at_supported_sigma`), after which the depth span is refused (`depths_suffice`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.observer import Observer
from lfgraph.core.sigmas import Sigmas
from lfgraph.engine.schedule import StageRecord, Step, TrackState, at_supported_sigma, run_schedule
from lfgraph.engine.stage_engine import FINAL_RELATIVE_TOL, INTERMEDIATE_RELATIVE_TOL
from lfgraph.engine.triangulate import finite_rms, per_coordinate_sigma, reprojection_errors
from lfgraph.factors.groups import parameters_per_view
from lfgraph.factors.noise import RobustKernel
from lfgraph.refinement.tracks import in_front
from lfgraph.selfcal.config import Design, SelfCalConfig
from lfgraph.selfcal.report import StageResult
from lfgraph.selfcal.solve import LANDMARK_ITERATIONS, graph_landmarks, measurement, robust_sigma, run_map_stage
from lfgraph.selfcal.tracks import MIN_TRACKS, Coverage, PooledTracks, measure_coverage

NOISE_FLOOR_PX = 0.01  # the measured tracking noise is never taken below this (sub-1/100 px is not KLT)
FINAL_ITERATIONS_FACTOR = 3  # the final stage walks the near-gauge valleys to the MAP: give it more iterations
FINAL_PASSES = 3  # the final stage re-runs at the noise its own residuals show until they agree ...
NOISE_AGREEMENT = 0.2  # ... to 20 %
MIN_ARRAY_DISPARITY_PX = 1.0  # a landmark whose disparity across the whole array is below this has (almost) no depth
# a stage that leaves fewer of its landmarks than this share with depth in front of their views is run again with
# damped steps: GTSAM's projection factors have zero error behind a camera, and an undamped step from a poor start can
# throw every landmark there (paper-4x4 rig seed 4, 10 frames: the poses stage from landmarks at 1.08 m kept 0 of 3000
# plain, 3000 damped). The damped run is kept only when it keeps more: rig seeds 0 and 1 at 20 frames and seed 0 at
# 10 keep 99-100 % plain; seed 1 at 10 keeps 46 % plain and no more damped, so its figures are unchanged
MIN_FRONT_SHARE = 0.5


class SelfCalibrationError(ValueError):
    """The frames cannot determine the parameters; the message says what is missing."""


def measured_noise(errors: np.ndarray, landmarks: int, views: int, free: frozenset) -> float:
    """`per_coordinate_sigma` (each view's parameters in the groups ``free`` frees, `parameters_per_view`: 12 with
    every group), never below `NOISE_FLOOR_PX`; no degrees of freedom left is a clear error (a NaN here used to reach
    the noise model as "sigmas must be positive and finite, got [nan]").

    Raises:
        SelfCalibrationError: too few tracks survive to measure the noise.
    """
    measured = per_coordinate_sigma(errors, landmarks, parameters_per_view(free) * views)
    if not np.isfinite(measured):
        raise SelfCalibrationError(
            f"self-calibration: only {landmarks} tracks ({int(np.isfinite(errors).sum())} observations) survive, too "
            f"few to measure the track noise for {views} views; add frames of a textured scene at several depths")
    return max(measured, NOISE_FLOOR_PX)


def reachable(calib: Calibration, points: np.ndarray, valid: np.ndarray, focal_px: float) -> np.ndarray:
    """(N,) landmarks in front of every view that sees them, seen from two centres, and nearer than the depth at
    which their disparity across the whole array falls below `MIN_ARRAY_DISPARITY_PX` (no depth; XYZ at kilometres
    makes the marginals indeterminate)."""
    centres = calib.ref_T_view[:, :3, 3]
    span = float(np.max(np.linalg.norm(centres[:, None] - centres[None], axis=-1)))
    return in_front(calib, points, valid) & (points[:, 2] < focal_px * span / MIN_ARRAY_DISPARITY_PX)


def with_depth(state: TrackState, design: Design) -> TrackState:
    """``state`` without the landmarks `reachable` drops."""
    return state.subset(reachable(state.calib, state.points, state.valid, design.focal_px))


def enough_tracks(tracks: PooledTracks, stage: str) -> None:
    """Raises SelfCalibrationError when a stage left fewer than `MIN_TRACKS` usable tracks."""
    if tracks.num_tracks < MIN_TRACKS:
        raise SelfCalibrationError(f"{stage} left {tracks.num_tracks} usable tracks (at least {MIN_TRACKS} are "
                                   f"needed): the frames do not hold the landmarks' depths; add frames at other "
                                   f"depths or tighten the design tolerances")


def covered_distortion(free: frozenset, coverage: Coverage, design: Design) -> tuple[frozenset, str | None]:
    """The groups a stage frees given how far the tracks reach: short of the corners, the stages estimate k1 alone
    when they reach half way out, else neither (the final stage frees both, pulled to the design with its
    tolerances); with the warning that says so (None when the tracks cover the corners)."""
    if coverage.distortion_covered:
        return free, None
    held = "k2" if coverage.k1_covered else "k1 and k2"
    return (free - {"distortion"} | ({"k1"} if coverage.k1_covered else set()),
            f"tracks reach only {coverage.max_radius:.0%} of the half diagonal: {held} set largely by the design "
            f"values (k1 {design.k1:g}, k2 {design.k2:g}) and their tolerances (see the sigmas); add frames with "
            "texture in the image corners")


def frames_suffice(state: TrackState, design: Design, config: SelfCalConfig) -> Coverage:
    """The tracks' coverage (`measure_coverage`), refusing frames that cannot determine the calibration; all but the
    depth span, which `depths_suffice` refuses after the final fit: the staged fits hold the focal lengths (or their
    common zoom) and their depths absorb the focal errors (paper-4x4 rig seed 5, 20 frames, true depths 0.52-1.86 m:
    0.12-0.16 m after the poses, 0.04-0.05 m after the focal lengths, 0.06 m after the principal points; the final
    fit then within 0.2-0.6x of the checkerboard's errors but for the common zoom).

    Raises:
        SelfCalibrationError: the coverage's problems (too few frames or tracks, image regions)."""
    coverage = measure_coverage(state.calib, state.tracks, state.points, design.focal_px, design.pitch_mm / 1000.0)
    problems = coverage.problems(config.min_frames, depths=False)
    if problems:
        raise SelfCalibrationError("these frames cannot determine the calibration: " + "; ".join(problems))
    return coverage


def depths_suffice(coverage: Coverage) -> None:
    """Refuses a final fit whose landmark depths span too little to tell rotations from positions.

    Raises:
        SelfCalibrationError: far/near depth below `lfgraph.selfcal.tracks.MIN_DEPTH_RATIO` (the message says what to
            add)."""
    problems = [p for p in coverage.problems(0) if p not in coverage.problems(0, depths=False)]
    if problems:
        raise SelfCalibrationError("these frames cannot determine the calibration: " + "; ".join(problems))


@dataclass
class Staged:
    """What the staged steps learn as they run: one `StageResult` per stage run, the warnings, whether the stages
    estimated the distortion, the coverage so far and the last stage's residuals (the next kernel's scale)."""
    errors: np.ndarray
    stages: list[StageResult] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    distortion: bool = True  # tracks reach the corners: the stages estimate k1 and k2
    coverage: Coverage | None = None


def _step(k: int, groups, nominal: Calibration, sigmas: Sigmas, design: Design, config: SelfCalConfig,
          staged: Staged, say: Observer) -> Step:
    """Stage ``k`` of `SelfCalConfig.stages` (freeing ``groups``) as a step of the one schedule."""
    chosen: list[frozenset] = []

    def prepare(state: TrackState) -> TrackState | None:
        free = frozenset(groups)
        if "distortion" in free:
            if staged.coverage is None:
                staged.coverage = measure_coverage(state.calib, state.tracks, state.points, design.focal_px,
                                                   design.pitch_mm / 1000.0)
            free, message = covered_distortion(free, staged.coverage, design)
            if message is not None:
                staged.warnings += [] if not staged.distortion else [message]
                staged.distortion = False
        chosen.append(free)
        return state if free else None

    def solve(state: TrackState) -> tuple[TrackState, int]:
        # the kernel's scale follows the stage's own residuals: early stages see pixels of model error
        stage_sigma = max(config.track_sigma_px, robust_sigma(staged.errors))

        def run(damped: bool) -> tuple[Calibration, np.ndarray, float, int]:
            calib, points, _, _, iters = run_map_stage(state.calib, nominal, state.pixels, state.valid, state.points,
                                                       chosen[-1], sigmas, measurement(config.noise, stage_sigma),
                                                       config.max_iterations, INTERMEDIATE_RELATIVE_TOL, say.iteration,
                                                       config.graph_hooks, damped=damped)
            return calib, points, float(np.mean(reachable(calib, points, state.valid, design.focal_px))), iters

        calib, points, front, iters = run(False)
        if front < MIN_FRONT_SHARE:
            say.log(f"self-calibration stage {k + 1}: only {front:.0%} of the landmarks left in front of their views "
                    "with depth; again with damped steps")
            again = run(True)
            iters += again[3]
            say.log(f"self-calibration stage {k + 1}: damped, {again[2]:.0%} left; "
                    + ("kept" if again[2] > front else "the plain run kept"))
            if again[2] > front:
                calib, points, front = again[:3]
        return TrackState(calib, state.pixels, state.valid, points, state.index, state.tracks), iters

    def check(state: TrackState, record: StageRecord) -> None:
        name = "+".join(sorted(chosen[-1]))
        staged.errors = record.errors
        staged.stages.append(StageResult(tuple(sorted(chosen[-1])), record.landmarks, record.iterations,
                                         record.rms_after_px))
        enough_tracks(state.tracks, f"stage {k + 1} ({name})")
        if k == 0:  # after the poses the landmarks' depths are right: refuse now if the frames cannot do it
            staged.coverage = frames_suffice(state, design, config)

    def describe(r: StageRecord) -> str:
        return (f"self-calibration stage {k + 1} ({'+'.join(sorted(chosen[-1]))}): {r.landmarks} tracks, "
                f"{r.iterations} iterations, rms {r.rms_after_px:.3f} px")

    return Step("+".join(sorted(groups)), solve, prepare, lambda s: with_depth(s, design), check, describe=describe)


def run_stages(state: TrackState, nominal: Calibration, sigmas: Sigmas, design: Design, config: SelfCalConfig,
               say: Observer) -> tuple[TrackState, Staged]:
    """`SelfCalConfig.stages` on the one schedule from ``state`` (landmarks with depth): the last state and what the
    stages learnt.

    Raises:
        SelfCalibrationError: no stage frees anything, too few tracks after one, or frames that cannot determine it.
    """
    staged = Staged(reprojection_errors(state.calib, state.points, state.pixels, state.valid))
    steps = [_step(k, groups, nominal, sigmas, design, config, staged, say) for k, groups in enumerate(config.stages)]
    state, _ = run_schedule(steps, state, say)
    if not staged.stages:
        raise SelfCalibrationError("no stage frees any parameter")
    return state, staged


def final_free(stages: list[StageResult], config: SelfCalConfig) -> frozenset:
    """What the final stage frees: the last stage's groups, and the distortion the stages held (tracks short of the
    corners) free here, pulled to the design values with their tolerances: its uncertainty then enters every posterior
    sigma instead of a pin's 1e-6."""
    free = frozenset(stages[-1].free)
    return free - {"k1"} | {"distortion"} if any("distortion" in st for st in config.stages) else free


def final_fit(state: TrackState, nominal: Calibration, free: frozenset, sigmas: Sigmas, noise: float,
              design: Design, config: SelfCalConfig, say: Observer):
    """The final stage: plain least squares at the measured noise, with embedded landmark iterations, repeated (up to
    `FINAL_PASSES`, `at_supported_sigma`) until the fit's own residuals support the noise it assumed and no landmark
    left. Returns (the state, the graph and its optimum, the noise of the graph — which the marginals scale with —
    and one `StageResult` per pass)."""
    passes: list[StageResult] = []

    def fit(noise_px: float, _: int):
        nonlocal state
        calib, points, graph, values, iters = run_map_stage(
            state.calib, nominal, state.pixels, state.valid, state.points, free, sigmas,
            measurement(RobustKernel("none"), noise_px), FINAL_ITERATIONS_FACTOR * config.max_iterations,
            FINAL_RELATIVE_TOL, say.iteration, config.graph_hooks, hold_gauges=False,
            landmark_iterations=LANDMARK_ITERATIONS)
        state = with_depth(TrackState(calib, state.pixels, state.valid, points, state.index, state.tracks), design)
        errors = state.errors()
        passes.append(StageResult(tuple(sorted(free)), state.tracks.num_tracks, iters, finite_rms(errors)))
        return state, graph, values, errors

    def supported(result) -> float:
        return measured_noise(result[3], result[0].tracks.num_tracks, result[0].calib.num_views, free)

    def agree(measured: float, assumed: float, result) -> bool:
        # the fit's own residuals disagree with the noise it assumed (or landmarks left): again
        return abs(measured / assumed - 1.0) < NOISE_AGREEMENT and len(result[0].points) == graph_landmarks(result[2])

    (state, graph, values, _), used = at_supported_sigma(fit, noise, supported, agree, FINAL_PASSES)
    return state, graph, values, used, passes
