"""Auto-refinement from ordinary scenes (paper Section 4): tracks -> filters -> staged GTSAM bundle adjustment.

Stages (each a factor graph; what is not free is held by the factor type or by a tight prior):

- ``points``: cameras constant, only landmarks move (`TriangulationFactorCal3DS2`, one small block per landmark).
- ``intrinsics``: fx, fy, cx, cy free, distortion and poses held (`GeneralSFMFactor2Cal3DS2` + priors).
- ``poses``: poses free except the reference (gauge), intrinsics constant (`GenericProjectionFactorCal3DS2`).
- ``all``: poses and fx, fy, cx, cy free, distortion held.
- ``clean``: drop tracks whose worst residual stands out (the F-matrix test cannot see errors along the baseline),
  then repeat the previous free stage with a Cauchy kernel.

Schedules: ``paper`` = points, intrinsics, all (the paper's strategy); ``default`` = points, poses, clean — chosen by
measurement (`benchmarks/refine.py`): holding the intrinsics and cleaning bad tracks is several times more accurate
in view rotation and transfer error at infinity.

Two gauges are handled explicitly: (1) the array's frame — a prior on the reference view's pose, and scale,
unobservable from a scene alone — one range constraint (reference to the farthest view) during the solve, then the
least-squares rescaling to the calibrated baselines (weak per-position priors, ``scale_sigma_mm``, are an option);
(2) per-view intrinsics have a hidden freedom: shifting each view's principal point in proportion to its baseline
while shifting every landmark's inverse depth leaves all images unchanged (fixing the reference view does not remove
it). Whenever principal points are free, cx of the reference row's neighbour of the reference view (or cy of its
column neighbour in a single-column grid) is held. (3) With nearly parallel views a common zoom and shift of every
view's fx, fy, cx, cy, with the landmarks' depths, is unobservable too: the reference view's intrinsics are held,
as its pose is.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import gtsam
import numpy as np

from lfgraph.calibration import Calibration
from lfgraph.camera import Intrinsics
from lfgraph.factors.keys import calib_key, landmark_key, view_pose_key
from lfgraph.factors.noise import MIN_SIGMA, parse_robust, pixel_noise, pose_noise, robust
from lfgraph.geometry import from_pose3, rotation_angle_deg, to_pose3
from lfgraph.optimize import IterationCallback, OptimizerSettings, optimize
from lfgraph.refinement.matching import MatchSettings, Tracks, track_chain
from lfgraph.refinement.triangulate import median_filter, reprojection_errors, triangulate_dlt, worst_error_filter

STAGES = ("points", "intrinsics", "poses", "all", "clean")
SCHEDULES = {"paper": ("points", "intrinsics", "all"), "default": ("points", "poses", "clean")}
TRIANGULATION_FILTERS = ("median", "worst", "none")
FREE_SIGMA = 1e4  # px: fx, fy, cx, cy when free (no practical pull)
HELD_SIGMA = 1e-6  # tight prior for what a stage holds (px, -, rad, m); >= 1e-8 keeps GTSAM's fast solver
GAUGE_SIGMA = 1e-8
RANGE_GAUGE_SIGMA_M = 1e-3
OUTLIER_FACTOR = 4.0  # between stages: drop a track whose worst residual is > 4x the median track's ...
OUTLIER_FLOOR_PX = 0.5  # ... and > 0.5 px
CLEAN_FACTOR = 3.0  # the clean stage: worst residual > 3x the median track's ...
CLEAN_FLOOR_PX = 0.3  # ... and > 0.3 px (the prototype's threshold)
COVERAGE_CELLS = 8
MIN_BASELINE_M = 1e-6  # a track needs observing centres at least this far apart
COVERAGE_WARN = 0.5  # warn when kept tracks fill less than half of the reference image's 8x8 cells
MATCH_WARN = 0.15  # warn when fewer than 15 % of detected features survive tracking and the filters


def parse_stages(spec: str | Iterable[str]) -> tuple[str, ...]:
    """``"paper"``, ``"default"`` or a comma list such as ``"points,poses"``; raises ValueError naming the bad one."""
    if isinstance(spec, str):
        if spec in SCHEDULES:
            return SCHEDULES[spec]
        names = tuple(s.strip() for s in spec.split(",") if s.strip())
    else:
        names = tuple(spec)
    if not names:
        raise ValueError("the stage schedule is empty")
    for n in names:
        if n not in STAGES:
            raise ValueError(f"unknown stage {n!r}; stages are {', '.join(STAGES)} (or the schedules "
                             f"{', '.join(SCHEDULES)})")
    if names[0] == "clean":
        raise ValueError("'clean' repeats a previous stage, so it cannot come first")
    return names


@dataclass(frozen=True)
class RefineSettings:
    """Options of the refinement.

    Attributes:
        stages: the schedule (see `parse_stages`).
        robust: kernel of the measurement noise, ``none`` or ``NAME[:THRESHOLD_PX]``.
        triangulation_filter: ``median`` (the paper: keep tracks whose reference-view error is <= the median;
            it halves the tracks and favours the image centre), ``worst`` (drop tracks whose worst error is > 4x the
            median track's and > 0.5 px) or ``none``; default: ``median`` with the paper's schedule, else ``worst``.
        max_frames: use at most this many frames (None: all).
        target_rms_px: stop adding frames once a new frame's tracks fit the current calibration at this RMS.
        scale_sigma_mm: None (default): scale is fixed by one range and the result rescaled to the calibrated
            baselines (least squares); a number: weak priors of this sigma on every view's position instead (the
            simpler scheme, which pulls positions back and biases rotations by ~position error / depth).
        max_iterations: LM cap per stage.
        clean_robust: kernel of the ``clean`` stage's repeat (the prototype's ``cauchy:0.1`` measured worse here).
        max_landmarks: cap of the pooled tracks (a seeded random subset is kept when frames bring more): memory and
            time of the adjustment grow with them (~200 MB and ~0.5 s per 1000 landmarks of a 5x5 rig) while the
            accuracy has stopped improving well before (measured in `benchmarks/refine.py`). None: no cap.
        min_view_observations: a view with fewer kept observations is held where it is (its pose alone is too
            weakly determined: on the Middlebury ring, views with 3-9 observations drifted by 10-35 degrees).
        min_improvement: keep the input calibration unless the refined one lowers the RMS of the kept tracks by at
            least this factor — with no real drift, a refit only chases the tracks' own small biases (1 = always
            accept).
        match: feature tracking options.
    """

    stages: tuple[str, ...] = SCHEDULES["default"]
    robust: str = "none"
    triangulation_filter: str | None = None
    max_frames: int | None = None
    target_rms_px: float | None = None
    scale_sigma_mm: float | None = None
    max_iterations: int = 100
    clean_robust: str = "none"
    min_improvement: float = 1.1
    max_landmarks: int | None = 2000
    min_view_observations: int = 30
    match: MatchSettings = field(default_factory=MatchSettings)

    def __post_init__(self) -> None:
        object.__setattr__(self, "stages", parse_stages(self.stages))
        if self.triangulation_filter is None:  # the paper's schedule comes with the paper's filter
            object.__setattr__(self, "triangulation_filter",
                               "median" if self.stages == SCHEDULES["paper"] else "worst")
        parse_robust(self.robust)
        parse_robust(self.clean_robust)
        if self.triangulation_filter not in TRIANGULATION_FILTERS:
            raise ValueError(f"triangulation_filter must be one of {TRIANGULATION_FILTERS}, "
                             f"got {self.triangulation_filter!r}")
        if self.max_frames is not None and self.max_frames < 1:
            raise ValueError(f"max_frames must be >= 1, got {self.max_frames}")
        if self.max_landmarks is not None and self.max_landmarks < 10:
            raise ValueError(f"max_landmarks must be >= 10, got {self.max_landmarks}")
        if self.scale_sigma_mm is not None and self.scale_sigma_mm <= 0:
            raise ValueError(f"scale_sigma_mm must be positive, got {self.scale_sigma_mm}")


@dataclass(frozen=True)
class StageReport:
    """One stage: landmarks used, RMS before/after (px), iterations, and per-view changes it made."""

    name: str
    landmarks: int
    observations: int
    rms_before_px: float
    rms_after_px: float
    iterations: int
    seconds: float
    rotation_change_deg: np.ndarray
    position_change_mm: np.ndarray
    focal_change_px: np.ndarray
    principal_change_px: np.ndarray


@dataclass(frozen=True)
class RefinementReport:
    """Everything `refine` measured: per-frame track counts after each filter, per-stage reports, and the RMS of
    the tracks kept by the last pass with the input and with the refined calibration."""

    frame_counts: tuple[dict[str, int], ...]
    frame_rms_before_px: tuple[float, ...]
    stages: tuple[StageReport, ...]
    frames_used: int
    stop_reason: str
    rms_before_px: float
    rms_after_px: float
    seconds: float
    seconds_matching: float = 0.0
    seconds_adjustment: float = 0.0
    accepted: bool = True
    coverage: float = 1.0
    warnings: tuple[str, ...] = ()
    total_iterations: int = 0  # LM iterations of every stage of every pass (the rerun ``iteration`` timeline)

    def metrics(self) -> dict:
        return {
            "refinement": {
                "frames_used": self.frames_used, "stop_reason": self.stop_reason, "accepted": self.accepted,
                "coverage": self.coverage, "warnings": list(self.warnings),
                "total_iterations": self.total_iterations,
                "rms_before_px": self.rms_before_px, "rms_after_px": self.rms_after_px,
                "frame_counts": list(self.frame_counts),
                "stages": [{"name": s.name, "landmarks": s.landmarks, "rms_before_px": s.rms_before_px,
                            "rms_after_px": s.rms_after_px, "iterations": s.iterations,
                            "max_rotation_change_deg": float(np.max(s.rotation_change_deg)),
                            "max_position_change_mm": float(np.max(s.position_change_mm))}
                           for s in self.stages],
            }
        }


# --------------------------------------------------------------------------------------------- helpers
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


def _gauge_view(calib: Calibration) -> tuple[int, int] | None:
    """(view, Cal3DS2 index) of the principal-point coordinate held to remove the hidden intrinsics gauge."""
    grid = calib.grid
    r0, c0 = grid.position(grid.reference)
    if grid.cols > 1:
        c = c0 + 1 if c0 + 1 < grid.cols else c0 - 1
        return grid.index(r0, c), 3  # cx
    if grid.rows > 1:
        r = r0 + 1 if r0 + 1 < grid.rows else r0 - 1
        return grid.index(r, c0), 4  # cy
    return None


def _intrinsics_prior(intr: Intrinsics, free: bool, hold_index: int | None) -> gtsam.noiseModel.Base:
    # Cal3DS2 order: fx fy s cx cy k1 k2 p1 p2
    sigmas = np.full(9, HELD_SIGMA)
    sigmas[2] = MIN_SIGMA
    if free:
        sigmas[[0, 1, 3, 4]] = FREE_SIGMA
        if hold_index is not None:
            sigmas[hold_index] = HELD_SIGMA
    return gtsam.noiseModel.Diagonal.Sigmas(sigmas)


def in_front(calib: Calibration, points_ref: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(N,) finite points in front of every view that observes them, seen from at least two distinct centres
    (views that share a centre — the Middlebury rings hold such pairs, one turned by 180° — give no depth)."""
    ok = np.all(np.isfinite(points_ref), axis=1)
    centres = calib.ref_T_view[:, :3, 3]
    lo = np.where(valid[..., None], centres[:, None, :], np.inf).min(axis=0)
    hi = np.where(valid[..., None], centres[:, None, :], -np.inf).max(axis=0)
    ok &= np.max(hi - lo, axis=1) > MIN_BASELINE_M
    for v in range(calib.num_views):
        m = valid[v] & ok
        if m.any():
            T = calib.view_T_ref(v)  # noqa: N806
            depth = points_ref[m] @ T[2, :3] + T[2, 3]
            bad = np.nonzero(m)[0][~(depth > 0)]
            ok[bad] = False
    return ok


def _changes(before: Calibration, after: Calibration) -> tuple[np.ndarray, ...]:
    rot = np.asarray(rotation_angle_deg(np.swapaxes(before.ref_T_view[:, :3, :3], 1, 2)
                                        @ after.ref_T_view[:, :3, :3]))
    pos = 1e3 * np.linalg.norm(after.ref_T_view[:, :3, 3] - before.ref_T_view[:, :3, 3], axis=1)
    foc = np.array([np.hypot(a.fx - b.fx, a.fy - b.fy) for a, b in zip(after.intrinsics, before.intrinsics,
                                                                        strict=True)])
    pp = np.array([np.hypot(a.cx - b.cx, a.cy - b.cy) for a, b in zip(after.intrinsics, before.intrinsics,
                                                                       strict=True)])
    return rot, pos, foc, pp


# --------------------------------------------------------------------------------------------- one stage
def run_stage(name: str, calib: Calibration, pixels: np.ndarray, valid: np.ndarray, points: np.ndarray,
              robust_spec: str, scale_sigma_mm: float | None, max_iterations: int,
              callback: IterationCallback | None = None,
              held_views: frozenset[int] = frozenset()) -> tuple[Calibration, np.ndarray, int]:
    """Run one free-variable stage (``points``, ``intrinsics``, ``poses`` or ``all``) as a GTSAM graph.

    Args:
        pixels: (V, N, 2) observations; valid: (V, N); points: (N, 3) initial landmarks (reference frame).
        held_views: views whose pose and intrinsics stay where they are (too few observations to refine them).

    Returns:
        the updated calibration, (N, 3) landmarks, LM iterations.
    """
    kernel, threshold = parse_robust(robust_spec)
    noise = robust(pixel_noise(1.0), kernel, threshold)  # one pixel: thresholds read in pixels
    n_views, n = valid.shape
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for j in range(n):
        values.insert(landmark_key(j), points[j])
    vs, js = np.nonzero(valid)
    meas = pixels[vs, js]
    if name == "points":
        cams = [gtsam.PinholeCameraCal3DS2(to_pose3(calib.ref_T_view[v]), calib.intrinsics[v].to_gtsam())
                for v in range(n_views)]
        for v, j, uv in zip(vs.tolist(), js.tolist(), meas, strict=True):
            graph.add(gtsam.TriangulationFactorCal3DS2(cams[v], uv, noise, landmark_key(j)))
    else:
        poses_free = name in ("poses", "all")
        intr_free = name in ("intrinsics", "all")
        for v in range(n_views):
            values.insert(view_pose_key(v), to_pose3(calib.ref_T_view[v]))
            if v == calib.grid.reference:
                graph.add(gtsam.PriorFactorPose3(view_pose_key(v), to_pose3(calib.ref_T_view[v]),
                                                 gtsam.noiseModel.Isotropic.Sigma(6, GAUGE_SIGMA)))  # the gauge
            elif poses_free and v not in held_views:
                if scale_sigma_mm is not None:  # optional weak priors on every position (they bias rotations)
                    graph.add(gtsam.PriorFactorPose3(view_pose_key(v), to_pose3(calib.ref_T_view[v]),
                                                     pose_noise(1.0, scale_sigma_mm * 1e-3)))
            else:
                graph.add(gtsam.PriorFactorPose3(view_pose_key(v), to_pose3(calib.ref_T_view[v]),
                                                 pose_noise(HELD_SIGMA, HELD_SIGMA)))
        free_views = [v for v in range(n_views) if v != calib.grid.reference and v not in held_views]
        if poses_free and scale_sigma_mm is None and free_views and len(held_views) == 0:
            # scale is unobservable from a scene: one range (reference to the farthest view) fixes it without
            # pulling any direction; the solution is rescaled to the calibrated baselines afterwards (a held view
            # fixes scale by itself)
            far = int(np.argmax(np.linalg.norm(calib.ref_T_view[:, :3, 3], axis=1)))
            # a pure gauge: nothing else observes scale, so any sigma keeps the range exactly at its value; a
            # loose one keeps the system well conditioned (1e-6 m made every LM step fail on a 14 mm baseline)
            graph.add(gtsam.RangeFactorPose3(view_pose_key(calib.grid.reference), view_pose_key(far),
                                             float(np.linalg.norm(calib.ref_T_view[far, :3, 3])),
                                             gtsam.noiseModel.Isotropic.Sigma(1, RANGE_GAUGE_SIGMA_M)))
        if intr_free:
            gauge = _gauge_view(calib)
            for v in range(n_views):
                values.insert(calib_key(v), calib.intrinsics[v].to_gtsam())
                hold = gauge[1] if gauge is not None and gauge[0] == v else None
                # the reference view's intrinsics are held: with nearly parallel views a common zoom and shift of
                # every view's fx, fy, cx, cy (with the landmarks' depths) is as unobservable as the pose gauge
                free = v != calib.grid.reference and v not in held_views
                graph.add(gtsam.PriorFactorCal3DS2(calib_key(v), calib.intrinsics[v].to_gtsam(),
                                                   _intrinsics_prior(calib.intrinsics[v], free, hold)))
            for v, j, uv in zip(vs.tolist(), js.tolist(), meas, strict=True):
                graph.add(gtsam.GeneralSFMFactor2Cal3DS2(uv, noise, view_pose_key(v), landmark_key(j), calib_key(v)))
        else:
            cals = [calib.intrinsics[v].to_gtsam() for v in range(n_views)]
            for v, j, uv in zip(vs.tolist(), js.tolist(), meas, strict=True):
                graph.add(gtsam.GenericProjectionFactorCal3DS2(uv, noise, view_pose_key(v), landmark_key(j),
                                                               cals[v]))
    result = optimize(graph, values, OptimizerSettings(max_iterations=max_iterations), callback)
    est = result.values
    new_points = np.stack([np.asarray(est.atPoint3(landmark_key(j))) for j in range(n)]) if n else points
    if name == "points":
        return calib, new_points, result.iterations
    poses = np.stack([from_pose3(est.atPose3(view_pose_key(v))) for v in range(n_views)])
    ref = calib.grid.reference
    poses = np.linalg.inv(poses[ref])[None] @ poses  # exactly relative to the reference again
    poses[ref] = np.eye(4)
    if name in ("poses", "all") and scale_sigma_mm is None and len(held_views) == 0:
        # the similarity that best keeps the calibrated baselines: s = argmin sum |s c_new - c_old|^2
        c_old, c_new = calib.ref_T_view[:, :3, 3], poses[:, :3, 3]
        denom = float(np.sum(c_new * c_new))
        scale = float(np.sum(c_old * c_new)) / denom if denom > 0 else 1.0
        poses[:, :3, 3] *= scale
        new_points = new_points * scale
    intr = calib.intrinsics
    if name in ("intrinsics", "all"):
        new = []
        for v in range(n_views):
            cal = est.atCal3DS2(calib_key(v))
            old = calib.intrinsics[v]
            new.append(Intrinsics(cal.fx(), cal.fy(), cal.px(), cal.py(), old.k1, old.k2, old.p1, old.p2))
        intr = tuple(new)
    return calib.replace(intrinsics=intr, ref_T_view=poses), new_points, result.iterations


# --------------------------------------------------------------------------------------------- the schedule
def collect_tracks(calib: Calibration, tracks: Tracks, triangulation_filter: str) -> tuple[Tracks, dict[str, int]]:
    """Apply the triangulation filter to one frame's tracks; returns the kept tracks and the counts."""
    points = triangulate_dlt(calib, tracks.points_px, tracks.valid)
    errors = reprojection_errors(calib, points, tracks.points_px, tracks.valid)
    if triangulation_filter == "median":
        keep = median_filter(errors, calib.grid.reference)
    elif triangulation_filter == "worst":
        keep = worst_error_filter(errors, OUTLIER_FACTOR, OUTLIER_FLOOR_PX)
    else:
        keep = np.all(np.isfinite(points), axis=1)
    return tracks.subset(keep), {**tracks.counts, "triangulation": int(keep.sum())}


EventHook = Callable[[str, dict], None]  # (kind, data): "frame", "stage", "stage_done", "outliers" — for lfgraph.viz


def refine_tracks(calib: Calibration, pixels: np.ndarray, valid: np.ndarray, settings: RefineSettings,
                  callback: IterationCallback | None = None, log: Callable[[str], None] | None = None,
                  events: EventHook | None = None) -> tuple[Calibration, list[StageReport], np.ndarray]:
    """Run the stage schedule over pooled tracks. Returns the calibration, stage reports and the kept-track mask.

    ``events`` receives ``("stage", {name, measurements})`` before and ``("stage_done", {name, calib, points,
    pixels, valid, errors})`` and ``("outliers", {name, pixels, valid})`` (the tracks the stage's outlier rejection
    dropped) after every stage.
    """
    say = log or (lambda _m: None)
    emit = events or (lambda _k, _d: None)
    keep = np.ones(valid.shape[1], dtype=bool)
    reports = []
    last_free = None
    for name in settings.stages:
        t0 = time.perf_counter()
        # GTSAM pitfall: a landmark behind a camera gives a constant residual with zero Jacobians, which makes the
        # linear system singular and LM give up at once — guard cheirality before building the graph
        points = triangulate_dlt(calib, pixels[:, keep], valid[:, keep])
        front = in_front(calib, points, valid[:, keep])
        idx = np.nonzero(keep)[0]
        keep[idx[~front]] = False
        px, ok, points = pixels[:, keep], valid[:, keep], points[front]
        errors = reprojection_errors(calib, points, px, ok)
        if name == "clean":
            if last_free is None:
                raise ValueError("'clean' needs a free stage before it")
            good = worst_error_filter(errors, CLEAN_FACTOR, CLEAN_FLOOR_PX)
            idx = np.nonzero(keep)[0]
            keep[idx[~good]] = False
            px, ok, points = px[:, good], ok[:, good], points[good]
            errors = errors[:, good]
            stage, spec = last_free, settings.clean_robust
        else:
            stage, spec = name, settings.robust
        rms_before = _rms(errors)
        before = calib
        emit("stage", {"name": name, "measurements": int(ok.sum())})
        per_view = ok.sum(axis=1)
        held = frozenset(int(v) for v in np.nonzero(per_view < settings.min_view_observations)[0])
        if held and stage != "points":
            say(f"stage {name}: views {', '.join(calib.grid.name(v) for v in sorted(held))} have fewer than "
                f"{settings.min_view_observations} observations and are held")
        calib, points, iterations = run_stage(stage, calib, px, ok, points, spec, settings.scale_sigma_mm,
                                              settings.max_iterations, callback, held)
        errors = reprojection_errors(calib, points, px, ok)
        rms_after = _rms(errors)
        emit("stage_done", {"name": name, "calib": calib, "points": points, "pixels": px, "valid": ok,
                            "errors": errors})
        rot, pos, foc, pp = _changes(before, calib)
        reports.append(StageReport(name, int(ok.shape[1]), int(ok.sum()), rms_before, rms_after, iterations,
                                   time.perf_counter() - t0, rot, pos, foc, pp))
        say(f"stage {name}{f' ({stage}, {spec})' if name == 'clean' else ''}: {ok.shape[1]} landmarks, RMS "
            f"{rms_before:.4f} -> {rms_after:.4f} px, {iterations} iterations, max change {np.max(rot):.4f} deg "
            f"{np.max(pos):.3f} mm {np.max(foc):.3f} px (focal) {np.max(pp):.3f} px (principal point)")
        if name != "points" and name != "clean":
            last_free = name
        if name != "clean":
            # re-run the outlier rejection between stages
            good = worst_error_filter(errors, OUTLIER_FACTOR, OUTLIER_FLOOR_PX)
            idx = np.nonzero(keep)[0]
            keep[idx[~good]] = False
        else:
            good = np.ones(px.shape[1], dtype=bool)
        emit("outliers", {"name": name, "pixels": px[:, ~good], "valid": ok[:, ~good]})
    return calib, reports, keep


def refine(calib: Calibration, frames: Iterable[np.ndarray], settings: RefineSettings | None = None,
           callback: IterationCallback | None = None, log: Callable[[str], None] | None = None,
           events: EventHook | None = None) -> tuple[Calibration, RefinementReport]:
    """Refine a calibration from ordinary (textured) captures, frame after frame.

    Each frame's tracks (chain KLT + filters + the triangulation filter) join the pool; the schedule then runs over
    the whole pool starting from the current calibration (the previous result). It stops after ``max_frames``, when
    the frames run out, or when a new frame already fits at ``target_rms_px``.

    Args:
        calib: the calibration to refine (e.g. from the pattern).
        frames: (V, H, W) uint8 grayscale images per frame.
        settings: options.

    Raises:
        ValueError: no frame, or no track survives the filters (too little texture).
    """
    settings = settings or RefineSettings()
    say = log or (lambda _m: None)
    t_start = time.perf_counter()
    pool_px: list[np.ndarray] = []
    pool_valid: list[np.ndarray] = []
    counts: list[dict[str, int]] = []
    frame_rms: list[float] = []
    stages: list[StageReport] = []
    current = calib
    stop = "frames exhausted"
    used = 0
    t_match = t_adjust = 0.0
    total_iterations = 0
    for f, images in enumerate(frames):
        if settings.max_frames is not None and f >= settings.max_frames:
            stop = f"max frames ({settings.max_frames})"
            break
        if events is not None:
            events("frame", {"index": f, "images": images})
        t0 = time.perf_counter()
        tracks = track_chain(images, calib.grid, settings.match)
        kept, c = collect_tracks(current, tracks, settings.triangulation_filter)
        t_match += time.perf_counter() - t0
        counts.append(c)
        pts = triangulate_dlt(current, kept.points_px, kept.valid)
        rms_now = _rms(reprojection_errors(current, pts, kept.points_px, kept.valid))
        frame_rms.append(rms_now)
        say(f"frame {f}: tracks " + ", ".join(f"{k} {v}" for k, v in c.items())
            + f"; RMS with the current calibration {rms_now:.4f} px")
        if settings.target_rms_px is not None and used > 0 and rms_now <= settings.target_rms_px:
            stop = f"frame {f} fits at {rms_now:.4f} px <= target {settings.target_rms_px:g} px"
            break
        if kept.num_tracks == 0:
            say(f"frame {f}: no usable tracks, skipped")
            continue
        pool_px.append(kept.points_px)
        pool_valid.append(kept.valid)
        used += 1
        pixels = np.concatenate(pool_px, axis=1)
        valid = np.concatenate(pool_valid, axis=1)
        if settings.max_landmarks is not None and pixels.shape[1] > settings.max_landmarks:
            pick = np.sort(np.random.default_rng(used).choice(pixels.shape[1], settings.max_landmarks, replace=False))
            pixels, valid = pixels[:, pick], valid[:, pick]
            pool_px, pool_valid = [pixels], [valid]
        t0 = time.perf_counter()
        current, frame_stages, kept_mask = refine_tracks(current, pixels, valid, settings, callback, say, events)
        t_adjust += time.perf_counter() - t0
        total_iterations += sum(st.iterations for st in frame_stages)
        stages = frame_stages  # the last pass over the whole pool is the result
    if used == 0:
        raise ValueError("no usable feature tracks in the capture: the scene needs texture visible in every view "
                         "(see the per-frame track counts)")
    pixels = np.concatenate(pool_px, axis=1)[:, kept_mask]
    valid = np.concatenate(pool_valid, axis=1)[:, kept_mask]
    before = _rms(reprojection_errors(calib, triangulate_dlt(calib, pixels, valid), pixels, valid))
    after = _rms(reprojection_errors(current, triangulate_dlt(current, pixels, valid), pixels, valid))
    warnings = []
    coverage = track_coverage(calib, pixels, valid)
    if coverage < COVERAGE_WARN:
        warnings.append(f"tracks cover only {100 * coverage:.0f} % of the reference image ({COVERAGE_CELLS}x"
                        f"{COVERAGE_CELLS} cells): rotations about the optical axis are weakly constrained; use "
                        f"scenes with texture across the whole field of view")
    detected = sum(c.get("detected", 0) for c in counts)
    survived = sum(c.get("triangulation", 0) for c in counts)
    if detected and survived / detected < MATCH_WARN:
        warnings.append(f"only {survived} of {detected} features ({100 * survived / max(detected, 1):.0f} %) survived "
                        f"tracking and the filters: matches are poor (repetitive or weak texture, occlusions)")
    accepted = bool(after > 0 and before / after >= settings.min_improvement)
    if not accepted:
        warnings.append(f"the input calibration already fits ({before:.4f} px vs {after:.4f} px refined, less than "
                        f"{settings.min_improvement:g}x better): kept unchanged")
        current = calib
    for w in warnings:
        say(f"warning: {w}")
    report = RefinementReport(tuple(counts), tuple(frame_rms), tuple(stages), used, stop, before, after,
                              time.perf_counter() - t_start, t_match, t_adjust, accepted, coverage, tuple(warnings),
                              total_iterations)
    metrics = {**dict(current.metrics or {}), **report.metrics()}
    return current.replace(metrics=metrics, rectification=None), report


def track_coverage(calib: Calibration, pixels: np.ndarray, valid: np.ndarray, cells: int = 8) -> float:
    """Share of an 8x8 grid of reference-image cells holding at least one kept track."""
    ref = calib.grid.reference
    w, h = calib.image_size_px
    pts = pixels[ref][valid[ref]]
    if not len(pts):
        return 0.0
    cx = np.clip((pts[:, 0] / w * cells).astype(int), 0, cells - 1)
    cy = np.clip((pts[:, 1] / h * cells).astype(int), 0, cells - 1)
    grid = np.zeros((cells, cells), dtype=bool)
    grid[cy, cx] = True
    return float(grid.mean())
