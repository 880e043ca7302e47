"""Pattern calibration of the whole array (paper Section 3.2) and a joint GTSAM graph that improves on it.

Two routes over the same `BoardObservations`:

- ``paper``: per view Zhang calibration (``cv2.calibrateCamera``, k1 and k2 only) -> **E_mono**; each view's pose
  relative to the reference from every frame both see (PnP averaged, then Levenberg–Marquardt with intrinsics fixed,
  ``cv2.stereoCalibrate(CALIB_FIX_INTRINSIC)``) -> **E_PnP**.
- ``joint`` (default): one factor graph over all views and frames (`lfgraph.factors.board_graph`), initialised from
  the paper route or from design values; 1-sigma uncertainties from `gtsam.Marginals`.

Every result is scored the same way: the **rig-consistent RMS** reprojects every observation through the one rig
(board poses re-fitted with the rig fixed), so inconsistency between views cannot hide in per-view figures.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import gtsam
import numpy as np

from lfgraph.calibration import Calibration
from lfgraph.camera import Intrinsics
from lfgraph.detections import MIN_CORNERS_PER_BOARD, BoardObservations
from lfgraph.factors import board_graph
from lfgraph.factors.keys import board_corner_key, board_pose_key, calib_key, view_pose_key
from lfgraph.factors.noise import parse_robust, pixel_noise, robust
from lfgraph.geometry import from_pose3, invert_T, make_T, rotation_angle_deg, rotation_from_rotvec
from lfgraph.optimize import IterationCallback, OptimizationResult, OptimizerSettings, optimize

MIN_FRAMES_PER_VIEW = 3  # Zhang's method needs >= 3 board poses for fx, fy, cx, cy, k1, k2
MONO_FLAGS = cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST  # the paper's model: k1, k2, no tangential, no skew
COVERAGE_CELLS = 8  # coverage is measured on an 8x8 grid of image cells
COVERAGE_WARN_FRACTION = 0.75  # warn below this share of cells holding corners
OUTLIER_FRAME_FACTOR = 3.0  # a frame is flagged when its RMS is this many times the median frame RMS ...
OUTLIER_FRAME_MIN_PX = 0.25  # ... and above this absolute level (noise-free data would flag noise otherwise)
SIGMA_FLOOR_PX = 1e-3  # pixel sigma of the measurement model never goes below this (noise-free synthetic data)
METHODS = ("joint", "paper")
INITS = ("paper", "design")
REGION_NAMES = (("top-left", "top", "top-right"), ("left", "centre", "right"),
                ("bottom-left", "bottom", "bottom-right"))


class CalibrationInputError(ValueError):
    """Observations that cannot be calibrated; the message names the view (and file) and what is missing."""


# ------------------------------------------------------------------------------------------------- settings
@dataclass(frozen=True)
class JointSettings:
    """Options of the joint route.

    Attributes:
        robust: kernel spec, ``none`` or ``NAME[:THRESHOLD]`` (threshold in units of ``corner_sigma_px``).
        tangential: estimate p1, p2 (held at 0 otherwise, the paper's model).
        board_sigma_mm: board non-flatness tolerance; None treats the board as rigid and flat.
        corner_sigma_px: the measurement model's corner noise; sets the scale of robust thresholds and of the
            board prior's weight. Reported uncertainties are rescaled by the noise estimated from the residuals.
        max_iterations: Levenberg–Marquardt cap.
        marginals: compute 1-sigma uncertainties (costs ~0.2 s for 4x4x40).
    """

    robust: str = "none"
    tangential: bool = False
    board_sigma_mm: float | None = None
    corner_sigma_px: float = 1.0
    max_iterations: int = 100
    marginals: bool = True

    def __post_init__(self) -> None:
        parse_robust(self.robust)
        if self.board_sigma_mm is not None and not (np.isfinite(self.board_sigma_mm) and self.board_sigma_mm > 0):
            raise ValueError(f"board_sigma_mm must be positive, got {self.board_sigma_mm}")
        if not (np.isfinite(self.corner_sigma_px) and self.corner_sigma_px > 0):
            raise ValueError(f"corner_sigma_px must be positive, got {self.corner_sigma_px}")


# ------------------------------------------------------------------------------------------------- results
@dataclass(frozen=True)
class CalibrationReport:
    """Everything `calibrate` measured.

    Attributes:
        method: ``paper`` or ``joint``; init: how the joint route started (``paper``/``design``; None for paper).
        e_mono_px: per-view Zhang RMS pooled over views (None when the paper route was not run).
        e_pnp_px: relative-pose RMS pooled over non-reference views (None likewise).
        view_e_mono_px, view_e_pnp_px: (V,) the same per view (NaN where not available).
        rig_rms_px: RMS Euclidean reprojection error of every observation through the one rig.
        view_rms_px: (V,) rig-consistent RMS per view; frame_rms_px: (F,) per frame.
        outlier_frames: frame indices whose RMS stands out (`OUTLIER_FRAME_FACTOR`).
        coverage: (V,) share of the 8x8 image cells holding detected corners; coverage_cells: (V, 8, 8) bool.
        frames_per_view: (V,) frames in which each view saw the board.
        noise_sigma_px: corner noise per coordinate estimated from the residuals (joint route).
        sigmas: per view 1-sigma of fx, fy, cx, cy, k1, k2 (px, -), position (mm, xyz) and rotation (deg, xyz).
        optimization: the joint route's optimiser result (None for paper).
        warnings: human-readable warnings (coverage, outlier frames, views without a direct link).
        seconds: wall time per stage.
    """

    method: str
    init: str | None
    e_mono_px: float | None
    e_pnp_px: float | None
    view_e_mono_px: np.ndarray
    view_e_pnp_px: np.ndarray
    rig_rms_px: float
    view_rms_px: np.ndarray
    frame_rms_px: np.ndarray
    outlier_frames: tuple[int, ...]
    coverage: np.ndarray
    coverage_cells: np.ndarray
    frames_per_view: np.ndarray
    noise_sigma_px: float | None
    sigmas: tuple[dict[str, Any], ...] | None
    optimization: OptimizationResult | None
    warnings: tuple[str, ...]
    seconds: dict[str, float] = field(default_factory=dict)
    board_T_ref: np.ndarray | None = None  # (F, 4, 4) board poses used for the rig-consistent figures
    residuals_px: np.ndarray | None = None  # (V, F, C, 2) observed minus reprojected, NaN where not observed

    def metrics(self) -> dict[str, Any]:
        """JSON-serialisable figures for ``calibration.json`` (None for what is not available)."""

        def opt(x: float | None) -> float | None:
            return None if x is None or not np.isfinite(x) else float(x)

        return {
            "method": self.method, "init": self.init,
            "e_mono_px": opt(self.e_mono_px), "e_pnp_px": opt(self.e_pnp_px), "rig_rms_px": opt(self.rig_rms_px),
            "view_e_mono_px": [opt(x) for x in self.view_e_mono_px],
            "view_e_pnp_px": [opt(x) for x in self.view_e_pnp_px],
            "view_rms_px": [opt(x) for x in self.view_rms_px],
            "frame_rms_px": [opt(x) for x in self.frame_rms_px],
            "outlier_frames": list(self.outlier_frames),
            "coverage": [float(x) for x in self.coverage],
            "frames_per_view": [int(x) for x in self.frames_per_view],
            "noise_sigma_px": opt(self.noise_sigma_px),
            "sigmas": None if self.sigmas is None else list(self.sigmas),
            "iterations": None if self.optimization is None else self.optimization.iterations,
            "warnings": list(self.warnings),
        }


# ------------------------------------------------------------------------------------------------- checks
def check_observations(obs: BoardObservations) -> None:
    """Refuse observations that cannot calibrate every view.

    Raises:
        CalibrationInputError: a view that never saw the board, or saw it in fewer than `MIN_FRAMES_PER_VIEW`
            frames — the message names the view and its files.
    """
    seen = obs.seen
    counts = seen.sum(axis=1)
    problems = []
    for v in np.nonzero(counts < MIN_FRAMES_PER_VIEW)[0]:
        files = ""
        if obs.sources:
            first = obs.sources[0]
            files = f" (e.g. {first[v] if len(first) == obs.num_views else first[0]})"
        what = "no board detected in any frame" if counts[v] == 0 else \
            f"the board in only {counts[v]} frame(s), at least {MIN_FRAMES_PER_VIEW} are needed"
        problems.append(f"{obs.describe(int(v))}{files}: {what}")
    if problems:
        raise CalibrationInputError(
            f"cannot calibrate the {obs.grid} array with the {obs.board} board: " + "; ".join(problems)
            + ". Check the board size (--board, inner corners) and that the board is inside these views.")


# ------------------------------------------------------------------------------------------------- helpers
def _object_points(obs: BoardObservations, mask: np.ndarray) -> np.ndarray:
    return obs.board.object_points()[mask].astype(np.float32)


def _mean_rotation(rotations: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of (N, 3, 3) rotations (projection of the sum onto SO(3))."""
    u, _, vt = np.linalg.svd(np.sum(rotations, axis=0))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _mean_pose(poses: np.ndarray) -> np.ndarray:
    return make_T(_mean_rotation(poses[:, :3, :3]), poses[:, :3, 3].mean(axis=0))


def _pnp_all(obs: BoardObservations, intrinsics: tuple[Intrinsics, ...]) -> np.ndarray:
    """(V, F, 4, 4) ``view_T_board`` from PnP in every seen view-frame (NaN elsewhere)."""
    out = np.full((obs.num_views, obs.num_frames, 4, 4), np.nan)
    seen = obs.seen
    for v, f in zip(*np.nonzero(seen), strict=True):
        mask = obs.valid[v, f]
        ok, rvec, tvec = cv2.solvePnP(_object_points(obs, mask), obs.corners_px[v, f][mask].astype(np.float32),
                                      intrinsics[v].K, intrinsics[v].dist_cv, flags=cv2.SOLVEPNP_ITERATIVE)
        if ok:
            out[v, f] = make_T(rotation_from_rotvec(rvec.ravel()), tvec.ravel())
    return out


def _relative_poses(view_T_board: np.ndarray, reference: int) -> tuple[np.ndarray, np.ndarray]:  # noqa: N803
    """``ref_T_view`` of every view from per-frame board poses, through a tree of most-shared frames.

    Views that share frames with the reference get the average over those frames; others are linked through the
    view they share most frames with (a maximum spanning tree grown from the reference).

    Returns:
        (V, 4, 4) ``ref_T_view`` and (V,) the view each was linked through (itself for the reference).
    """
    n_views = view_T_board.shape[0]
    have = np.all(np.isfinite(view_T_board.reshape(n_views, view_T_board.shape[1], -1)), axis=-1)
    shared = (have[:, None, :] & have[None, :, :]).sum(axis=-1)
    ref_T_view = np.full((n_views, 4, 4), np.nan)  # noqa: N806
    ref_T_view[reference] = np.eye(4)
    parent = np.full(n_views, -1)
    parent[reference] = reference
    while np.any(parent < 0):
        linked = parent >= 0
        score = np.where(linked[:, None] & ~linked[None, :], shared, 0)
        a, b = np.unravel_index(np.argmax(score), score.shape)
        if score[a, b] == 0:
            break
        frames = np.nonzero(have[a] & have[b])[0]
        # a_T_b = a_T_board @ board_T_b, averaged over the shared frames
        a_T_b = _mean_pose(np.stack([view_T_board[a, f] @ invert_T(view_T_board[b, f]) for f in frames]))  # noqa: N806
        ref_T_view[b] = ref_T_view[a] @ a_T_b
        parent[b] = a
    return ref_T_view, parent


def _board_T_ref(view_T_board: np.ndarray, ref_T_view: np.ndarray, counts: np.ndarray) -> np.ndarray:  # noqa: N802, N803
    """(F, 4, 4) per frame ``board_T_ref`` from the view that saw the most corners of it."""
    n_frames = view_T_board.shape[1]
    out = np.full((n_frames, 4, 4), np.nan)
    for f in range(n_frames):
        order = np.argsort(-counts[:, f], kind="stable")
        for v in order:
            if counts[v, f] == 0 or not np.all(np.isfinite(view_T_board[v, f])) \
                    or not np.all(np.isfinite(ref_T_view[v])):
                continue
            out[f] = invert_T(view_T_board[v, f]) @ invert_T(ref_T_view[v])
            break
    return out


def rig_residuals(intrinsics: tuple[Intrinsics, ...], ref_T_view: np.ndarray, board_T_ref: np.ndarray,  # noqa: N803
                  obs: BoardObservations, object_points_m: np.ndarray | None = None) -> np.ndarray:
    """(V, F, C, 2) observed minus projected corners through one rig (NaN where not observed). Vectorised per view."""
    obj = obs.board.object_points() if object_points_m is None else object_points_m
    ref_T_board = np.stack([invert_T(T) if np.all(np.isfinite(T)) else np.full((4, 4), np.nan)  # noqa: N806
                            for T in board_T_ref])
    out = np.full(obs.corners_px.shape, np.nan)
    for v in range(obs.num_views):
        view_T_board = invert_T(ref_T_view[v])[None] @ ref_T_board  # noqa: N806  (F, 4, 4)
        cam = np.einsum("fij,cj->fci", view_T_board[:, :3, :3], obj) + view_T_board[:, None, :3, 3]
        proj = intrinsics[v].project(cam.reshape(-1, 3)).reshape(cam.shape[0], cam.shape[1], 2)
        out[v] = obs.corners_px[v] - proj
    out[~obs.valid] = np.nan
    return out


def fit_board_poses(intrinsics: tuple[Intrinsics, ...], ref_T_view: np.ndarray, obs: BoardObservations,  # noqa: N803
                    initial_board_T_ref: np.ndarray | None = None) -> np.ndarray:  # noqa: N803
    """(F, 4, 4) ``board_T_ref`` that best explain the corners with the rig held fixed (a GTSAM graph).

    This is what makes the rig-consistent RMS comparable across routes: every route's rig is scored with board
    poses fitted to all of its views at once.
    """
    if initial_board_T_ref is None:
        initial_board_T_ref = _board_T_ref(_pnp_all(obs, intrinsics), ref_T_view, obs.valid.sum(axis=2))
    graph = gtsam.NonlinearFactorGraph()
    frames = [f for f in range(obs.num_frames) if np.all(np.isfinite(initial_board_T_ref[f]))]
    valid = obs.valid.copy()
    valid[:, [f for f in range(obs.num_frames) if f not in frames]] = False
    board_graph.add_fixed_rig_observations(graph, obs.corners_px, valid, intrinsics, ref_T_view, pixel_noise(1.0))
    board_graph.add_corner_priors(graph, obs.board.object_points(), board_graph.RIGID_BOARD_SIGMA_M)
    values = gtsam.Values()
    board_graph.insert_board_values(values, initial_board_T_ref, obs.board.object_points(), frames)
    result = optimize(graph, values, OptimizerSettings(max_iterations=50))
    out = np.full((obs.num_frames, 4, 4), np.nan)
    for f in frames:
        out[f] = from_pose3(result.values.atPose3(board_pose_key(f)))
    return out


def _rms(residuals: np.ndarray, axis: tuple[int, ...] | int | None = None) -> np.ndarray | float:
    sq = np.sum(residuals**2, axis=-1)
    n = np.sum(np.isfinite(sq), axis=axis)
    total = np.nansum(sq, axis=axis)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(total / n)


def coverage_map(obs: BoardObservations, cells: int = COVERAGE_CELLS) -> np.ndarray:
    """(V, cells, cells) bool: which image cells hold at least one observed corner."""
    w, h = obs.image_size_px
    out = np.zeros((obs.num_views, cells, cells), dtype=bool)
    for v in range(obs.num_views):
        pts = obs.corners_px[v][obs.valid[v]]
        cx = np.clip((pts[:, 0] + 0.5) / w * cells, 0, cells - 1).astype(int)
        cy = np.clip((pts[:, 1] + 0.5) / h * cells, 0, cells - 1).astype(int)
        out[v, cy, cx] = True
    return out


def coverage_warnings(obs: BoardObservations, cells_map: np.ndarray,
                      threshold: float = COVERAGE_WARN_FRACTION) -> list[str]:
    """One warning per view whose coverage is below ``threshold``, naming the empty image regions."""
    warnings = []
    cells = cells_map.shape[1]
    bounds = np.array_split(np.arange(cells), 3)
    for v in range(obs.num_views):
        share = cells_map[v].mean()
        if share >= threshold:
            continue
        empty = [REGION_NAMES[i][j] for i in range(3) for j in range(3)
                 if cells_map[v][np.ix_(bounds[i], bounds[j])].mean() < 0.5]
        warnings.append(f"{obs.describe(v)}: corners cover {100 * share:.0f} % of the image "
                        f"({cells}x{cells} cells); show the board in the {', '.join(empty) or 'outer'} region(s) "
                        f"of this view")
    return warnings


def outlier_frames(frame_rms_px: np.ndarray) -> list[int]:
    finite = frame_rms_px[np.isfinite(frame_rms_px)]
    if finite.size == 0:
        return []
    limit = max(OUTLIER_FRAME_FACTOR * float(np.median(finite)), OUTLIER_FRAME_MIN_PX)
    return [int(f) for f in np.nonzero(np.nan_to_num(frame_rms_px, nan=0.0) > limit)[0]]


# ------------------------------------------------------------------------------------------------- paper route
@dataclass(frozen=True)
class PaperResult:
    """The paper route's rig and figures; ``view_T_board`` (V, F, 4, 4) from Zhang (NaN where unseen)."""

    intrinsics: tuple[Intrinsics, ...]
    ref_T_view: np.ndarray
    view_T_board: np.ndarray
    view_e_mono_px: np.ndarray
    view_e_pnp_px: np.ndarray
    e_mono_px: float
    e_pnp_px: float | None
    warnings: tuple[str, ...]


def calibrate_paper(obs: BoardObservations) -> PaperResult:
    """The paper's Section 3.2: per-view Zhang (k1, k2) then relative poses by PnP + LM with intrinsics fixed."""
    check_observations(obs)
    n_views, n_frames = obs.num_views, obs.num_frames
    ref = obs.grid.reference
    seen = obs.seen
    intrinsics: list[Intrinsics] = []
    view_T_board = np.full((n_views, n_frames, 4, 4), np.nan)  # noqa: N806
    e_mono = np.full(n_views, np.nan)
    n_points = np.zeros(n_views)
    for v in range(n_views):
        frames = np.nonzero(seen[v])[0]
        objs = [_object_points(obs, obs.valid[v, f]) for f in frames]
        imgs = [obs.corners_px[v, f][obs.valid[v, f]].astype(np.float32) for f in frames]
        try:
            rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(objs, imgs, obs.image_size_px, None, None,  # noqa: N806
                                                             flags=MONO_FLAGS)
        except cv2.error as exc:
            raise CalibrationInputError(f"{obs.describe(v)}: OpenCV's calibrateCamera failed ({exc.err})") from None
        intrinsics.append(Intrinsics.from_opencv(K, np.concatenate([dist.ravel()[:4], [0.0]])))
        for f, r, t in zip(frames, rvecs, tvecs, strict=True):
            view_T_board[v, f] = make_T(rotation_from_rotvec(r.ravel()), t.ravel())
        e_mono[v] = rms
        n_points[v] = sum(len(p) for p in imgs)
    ref_T_view, parent = _relative_poses(view_T_board, ref)  # noqa: N806  the PnP average, the LM start
    warnings = []
    unlinked = [obs.describe(v) for v in range(n_views) if parent[v] < 0]
    if unlinked:
        raise CalibrationInputError(f"no chain of shared frames links {', '.join(unlinked)} to the reference view; "
                                    f"show the board to these views together with others")
    e_pnp = np.full(n_views, np.nan)
    pnp_points = np.zeros(n_views)
    ref_K, ref_d = intrinsics[ref].K, intrinsics[ref].dist_cv  # noqa: N806
    for v in range(n_views):
        if v == ref:
            continue
        frames = np.nonzero(seen[v] & seen[ref])[0]
        masks = [obs.valid[v, f] & obs.valid[ref, f] for f in frames]
        keep = [i for i, m in enumerate(masks) if m.sum() >= MIN_CORNERS_PER_BOARD]
        if not keep:
            warnings.append(f"{obs.describe(v)} shares no frame with the reference view; its pose is chained "
                            f"through view {parent[v]} and has no E_PnP")
            continue
        objs = [_object_points(obs, masks[i]) for i in keep]
        ref_pts = [obs.corners_px[ref, frames[i]][masks[i]].astype(np.float32) for i in keep]
        view_pts = [obs.corners_px[v, frames[i]][masks[i]].astype(np.float32) for i in keep]
        view_T_ref = invert_T(ref_T_view[v])  # noqa: N806
        rms, *_, R, T, _, _ = cv2.stereoCalibrate(  # noqa: N806
            objs, ref_pts, view_pts, ref_K, ref_d, intrinsics[v].K, intrinsics[v].dist_cv, obs.image_size_px,
            view_T_ref[:3, :3].copy(), view_T_ref[:3, 3].copy(), flags=cv2.CALIB_FIX_INTRINSIC,
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
        ref_T_view[v] = invert_T(make_T(R, T.ravel()))
        e_pnp[v] = rms
        pnp_points[v] = 2 * sum(len(p) for p in objs)
    pooled_mono = float(np.sqrt(np.sum(e_mono**2 * n_points) / np.sum(n_points)))
    has = np.isfinite(e_pnp)
    pooled_pnp = float(np.sqrt(np.sum(e_pnp[has] ** 2 * pnp_points[has]) / np.sum(pnp_points[has]))) \
        if has.any() else None
    return PaperResult(tuple(intrinsics), ref_T_view, view_T_board, e_mono, e_pnp, pooled_mono, pooled_pnp,
                       tuple(warnings))


# ------------------------------------------------------------------------------------------------- design start
def design_initial(obs: BoardObservations, focal_px: float | None = None,
                   pitch_m: float | None = None) -> tuple[tuple[Intrinsics, ...], np.ndarray, np.ndarray]:
    """Design values: focal length (given, or the larger image side), centred principal point, no distortion;
    poses from the ideal grid (``pitch_m``) or, without it, PnP averages under the design intrinsics.

    Returns:
        intrinsics, ``ref_T_view`` (V, 4, 4) and ``view_T_board`` (V, F, 4, 4) from PnP.
    """
    w, h = obs.image_size_px
    f = float(focal_px) if focal_px is not None else float(max(w, h))
    design = Intrinsics(f, f, (w - 1) / 2.0, (h - 1) / 2.0)
    intrinsics = (design,) * obs.num_views
    view_T_board = _pnp_all(obs, intrinsics)  # noqa: N806
    if pitch_m is not None:
        ref_T_view = np.stack([make_T(np.eye(3), np.array([*obs.grid.offset(v)[::-1], 0.0]) * pitch_m)  # noqa: N806
                               for v in range(obs.num_views)])
    else:
        ref_T_view, parent = _relative_poses(view_T_board, obs.grid.reference)  # noqa: N806
        if np.any(parent < 0):
            bad = [obs.describe(v) for v in np.nonzero(parent < 0)[0]]
            raise CalibrationInputError(f"no chain of shared frames links {', '.join(bad)} to the reference view")
    return intrinsics, ref_T_view, view_T_board


# ------------------------------------------------------------------------------------------------- joint route
@dataclass(frozen=True)
class JointResult:
    intrinsics: tuple[Intrinsics, ...]
    ref_T_view: np.ndarray
    board_T_ref: np.ndarray
    object_points_m: np.ndarray
    optimization: OptimizationResult
    noise_sigma_px: float
    sigmas: tuple[dict[str, Any], ...] | None


def _intrinsics_from_values(values: gtsam.Values, v: int, tangential: bool) -> Intrinsics:
    cal = values.atCal3DS2(calib_key(v))
    k = cal.k()
    # skew and (unless estimated) p1, p2 are pinned at 0 by priors; clear their ~1e-13 round-off
    p1, p2 = (float(k[2]), float(k[3])) if tangential else (0.0, 0.0)
    return Intrinsics(cal.fx(), cal.fy(), cal.px(), cal.py(), float(k[0]), float(k[1]), p1, p2)


def _marginal_sigmas(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, n_views: int, scale: float,
                     ref_T_view: np.ndarray) -> tuple[dict[str, Any], ...]:  # noqa: N803
    marginals = gtsam.Marginals(graph, values)
    keys = gtsam.KeyVector([calib_key(v) for v in range(n_views)] + [view_pose_key(v) for v in range(n_views)])
    joint = marginals.jointMarginalCovariance(keys)
    out = []
    for v in range(n_views):
        kc = np.sqrt(np.maximum(np.diag(joint.at(calib_key(v), calib_key(v))), 0.0)) * scale
        pc = np.asarray(joint.at(view_pose_key(v), view_pose_key(v))) * scale**2
        R = ref_T_view[v][:3, :3]  # noqa: N806  Pose3 covariance is in the body frame, rotation first
        pos_cov = R @ pc[3:, 3:] @ R.T
        rot_cov = R @ pc[:3, :3] @ R.T
        out.append({
            "fx_px": float(kc[0]), "fy_px": float(kc[1]), "cx_px": float(kc[3]), "cy_px": float(kc[4]),
            "k1": float(kc[5]), "k2": float(kc[6]),
            "position_mm": [float(x) for x in 1e3 * np.sqrt(np.maximum(np.diag(pos_cov), 0.0))],
            "rotation_deg": [float(x) for x in np.degrees(np.sqrt(np.maximum(np.diag(rot_cov), 0.0)))],
        })
    return tuple(out)


def calibrate_joint(obs: BoardObservations, intrinsics: tuple[Intrinsics, ...], ref_T_view: np.ndarray,  # noqa: N803
                    board_T_ref: np.ndarray, settings: JointSettings | None = None,  # noqa: N803
                    callback: IterationCallback | None = None) -> JointResult:
    """One GTSAM graph over all views and frames (see `lfgraph.factors.board_graph`).

    Args:
        obs: the corners.
        intrinsics, ref_T_view, board_T_ref: the start (from `calibrate_paper` or `design_initial`).
        settings: options; `JointSettings()` by default.
        callback: optimiser iteration hook.
    """
    settings = settings or JointSettings()
    frames = [f for f in range(obs.num_frames) if np.all(np.isfinite(board_T_ref[f]))]
    valid = obs.valid.copy()
    valid[:, [f for f in range(obs.num_frames) if f not in frames]] = False
    kernel, threshold = parse_robust(settings.robust)
    noise = robust(pixel_noise(settings.corner_sigma_px), kernel, threshold)
    graph = gtsam.NonlinearFactorGraph()
    n_obs = board_graph.add_board_observations(graph, obs.corners_px, valid, noise)
    obj = obs.board.object_points()
    board_sigma_m = board_graph.RIGID_BOARD_SIGMA_M if settings.board_sigma_mm is None \
        else settings.board_sigma_mm * 1e-3
    board_graph.add_corner_priors(graph, obj, board_sigma_m)
    board_graph.add_gauge_prior(graph, obs.grid.reference)
    board_graph.add_intrinsics_pins(graph, intrinsics, settings.tangential)
    values = gtsam.Values()
    board_graph.insert_rig_values(values, intrinsics, ref_T_view)
    board_graph.insert_board_values(values, board_T_ref, obj, frames)
    result = optimize(graph, values, OptimizerSettings(max_iterations=settings.max_iterations), callback)
    est = result.values
    n_views = obs.num_views
    intr = tuple(_intrinsics_from_values(est, v, settings.tangential) for v in range(n_views))
    poses = np.stack([from_pose3(est.atPose3(view_pose_key(v))) for v in range(n_views)])
    poses[obs.grid.reference] = np.eye(4)  # the gauge prior holds it to 1e-8; make it exact for the file
    boards = np.full((obs.num_frames, 4, 4), np.nan)
    for f in frames:
        boards[f] = from_pose3(est.atPose3(board_pose_key(f)))
    corners = np.stack([np.asarray(est.atPoint3(board_corner_key(j))) for j in range(len(obj))])
    res = rig_residuals(intr, poses, boards, obs, corners)
    n_params = n_views * (8 if settings.tangential else 6) + 6 * (n_views - 1) + 6 * len(frames)
    dof = max(2 * n_obs - n_params, 1)
    noise_sigma = float(np.sqrt(np.nansum(res**2) / dof))
    sigmas = None
    if settings.marginals:
        scale = max(noise_sigma, SIGMA_FLOOR_PX) / settings.corner_sigma_px
        sigmas = _marginal_sigmas(graph, est, n_views, scale, poses)
    return JointResult(intr, poses, boards, corners, result, noise_sigma, sigmas)


# ------------------------------------------------------------------------------------------------- top level
def calibrate(obs: BoardObservations, method: str = "joint", init: str = "paper",
              settings: JointSettings | None = None, focal_px: float | None = None, pitch_m: float | None = None,
              callback: IterationCallback | None = None,
              log: Callable[[str], None] | None = None) -> tuple[Calibration, CalibrationReport]:
    """Calibrate the array from board observations.

    Args:
        obs: corners of every view and frame.
        method: ``joint`` (default) or ``paper``.
        init: start of the joint route: ``paper`` (the paper route's result) or ``design`` (focal length
            ``focal_px`` or the image size, centred principal point, zero distortion, ideal grid of ``pitch_m``
            or PnP-averaged poses).
        settings: joint-route options.
        focal_px, pitch_m: design values for ``init="design"``.
        callback: optimiser iteration hook (joint route).
        log: receives one line per stage (the CLI prints them).

    Returns:
        the calibration (its ``metrics`` hold the report's figures) and the report.

    Raises:
        CalibrationInputError: views without enough board detections, views that share no frames with others.
        ValueError: unknown method or init.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    if init not in INITS:
        raise ValueError(f"unknown init {init!r}; choose from {', '.join(INITS)}")
    say = log or (lambda _msg: None)
    check_observations(obs)
    seconds: dict[str, float] = {}
    warnings: list[str] = []
    n_views = obs.num_views
    paper = None
    if method == "paper" or init == "paper":
        t0 = time.perf_counter()
        paper = calibrate_paper(obs)
        seconds["paper"] = time.perf_counter() - t0
        warnings += paper.warnings
        say(f"paper route: E_mono {paper.e_mono_px:.4f} px, E_PnP "
            f"{'-' if paper.e_pnp_px is None else f'{paper.e_pnp_px:.4f}'} px ({seconds['paper']:.1f} s)")
    joint = None
    if method == "paper":
        intrinsics, ref_T_view = paper.intrinsics, paper.ref_T_view  # noqa: N806
        t0 = time.perf_counter()
        board_T_ref = fit_board_poses(intrinsics, ref_T_view, obs,  # noqa: N806
                                      _board_T_ref(paper.view_T_board, ref_T_view, obs.valid.sum(axis=2)))
        seconds["rig_fit"] = time.perf_counter() - t0
        res = rig_residuals(intrinsics, ref_T_view, board_T_ref, obs)
        boards = board_T_ref
    else:
        if paper is not None:
            start_intr, start_poses, view_T_board = paper.intrinsics, paper.ref_T_view, paper.view_T_board  # noqa: N806
        else:
            start_intr, start_poses, view_T_board = design_initial(obs, focal_px, pitch_m)  # noqa: N806
        start_boards = _board_T_ref(view_T_board, start_poses, obs.valid.sum(axis=2))
        t0 = time.perf_counter()
        joint = calibrate_joint(obs, start_intr, start_poses, start_boards, settings, callback)
        seconds["joint"] = time.perf_counter() - t0
        say(f"joint route: {joint.optimization.iterations} LM iterations, error {joint.optimization.initial_error:.4g}"
            f" -> {joint.optimization.final_error:.4g} ({seconds['joint']:.1f} s incl. marginals)")
        intrinsics, ref_T_view = joint.intrinsics, joint.ref_T_view  # noqa: N806
        res = rig_residuals(intrinsics, ref_T_view, joint.board_T_ref, obs, joint.object_points_m)
        boards = joint.board_T_ref
    view_rms = np.asarray(_rms(res, axis=(1, 2)))
    frame_rms = np.asarray(_rms(res, axis=(0, 2)))
    rig_rms = float(_rms(res, axis=None))
    outliers = outlier_frames(frame_rms)
    if outliers:
        warnings.append("frames with outlying reprojection error (check these images for a mis-detected board): "
                        + ", ".join(f"{obs.frame_names[f]} ({frame_rms[f]:.3f} px)" for f in outliers))
    cells = coverage_map(obs)
    warnings += coverage_warnings(obs, cells)
    report = CalibrationReport(
        method=method, init=None if method == "paper" else init,
        e_mono_px=None if paper is None else paper.e_mono_px, e_pnp_px=None if paper is None else paper.e_pnp_px,
        view_e_mono_px=np.full(n_views, np.nan) if paper is None else paper.view_e_mono_px,
        view_e_pnp_px=np.full(n_views, np.nan) if paper is None else paper.view_e_pnp_px,
        rig_rms_px=rig_rms, view_rms_px=view_rms, frame_rms_px=frame_rms, outlier_frames=tuple(outliers),
        coverage=cells.mean(axis=(1, 2)), coverage_cells=cells, frames_per_view=obs.seen.sum(axis=1),
        noise_sigma_px=None if joint is None else joint.noise_sigma_px,
        sigmas=None if joint is None else joint.sigmas,
        optimization=None if joint is None else joint.optimization, warnings=tuple(warnings), seconds=seconds,
        board_T_ref=boards, residuals_px=res)
    calib = Calibration(obs.grid, obs.image_size_px, intrinsics, ref_T_view, None, report.metrics())
    return calib, report


# ------------------------------------------------------------------------------------------------- evaluation
@dataclass(frozen=True)
class CalibrationErrors:
    """Estimated minus true, per view; poses compared relative to the estimate's reference view.

    Attributes:
        intrinsics: (V, 6) signed errors of fx, fy, cx, cy (px), k1, k2.
        position_mm: (V, 3) signed position error; rotation_deg: (V,) angle of the rotation error.
    """

    intrinsics: np.ndarray
    position_mm: np.ndarray
    rotation_deg: np.ndarray

    FIELDS = ("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2")

    def summary(self) -> dict[str, float]:
        """RMS over views of each error (and max), JSON-friendly."""
        out = {f"rms_{name}": float(np.sqrt(np.mean(self.intrinsics[:, i] ** 2))) for i, name in enumerate(self.FIELDS)}
        out["rms_position_mm"] = float(np.sqrt(np.mean(np.sum(self.position_mm**2, axis=1))))
        out["max_position_mm"] = float(np.max(np.linalg.norm(self.position_mm, axis=1)))
        out["rms_rotation_deg"] = float(np.sqrt(np.mean(self.rotation_deg**2)))
        out["max_rotation_deg"] = float(np.max(self.rotation_deg))
        return out


def evaluate_calibration(estimate: Calibration, truth: Calibration) -> CalibrationErrors:
    """Per-parameter errors of ``estimate`` against ``truth``.

    Raises:
        ValueError: different grids or image sizes (the message says which).
    """
    if (estimate.grid.rows, estimate.grid.cols) != (truth.grid.rows, truth.grid.cols):
        raise ValueError(f"the calibration is a {estimate.grid} grid but the truth is {truth.grid}")
    if estimate.image_size_px != truth.image_size_px:
        raise ValueError(f"the calibration is for {estimate.image_size_px} px images but the truth for "
                         f"{truth.image_size_px}")
    est_vec = np.array([[i.fx, i.fy, i.cx, i.cy, i.k1, i.k2] for i in estimate.intrinsics])
    true_vec = np.array([[i.fx, i.fy, i.cx, i.cy, i.k1, i.k2] for i in truth.intrinsics])
    ref = estimate.grid.reference
    true_rel = invert_T(truth.ref_T_view[ref])[None] @ truth.ref_T_view
    est_rel = estimate.ref_T_view
    pos = 1e3 * (est_rel[:, :3, 3] - true_rel[:, :3, 3])
    rot = np.asarray(rotation_angle_deg(np.swapaxes(true_rel[:, :3, :3], 1, 2) @ est_rel[:, :3, :3]))
    return CalibrationErrors(est_vec - true_vec, pos, rot)

