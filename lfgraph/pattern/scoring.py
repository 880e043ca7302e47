"""How a pattern calibration is scored and reported: rig-consistent residuals (board poses re-fitted
through the fixed rig), RMS, coverage maps and warnings, outlier frames, the `CalibrationReport`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from lfgraph.core.camera import Intrinsics
from lfgraph.core.geometry import invert_T
from lfgraph.detect.detections import BoardObservations
from lfgraph.engine.optimize import OptimizationResult, OptimizerSettings, optimize
from lfgraph.factors import board_graph
from lfgraph.factors.noise import pixel_noise
from lfgraph.factors.values import insert_board_corners, insert_board_poses, read_board_poses
from lfgraph.pattern.initial import initial_board_T_ref, pnp_all

COVERAGE_CELLS = 8  # coverage is measured on an 8x8 grid of image cells
COVERAGE_WARN_FRACTION = 0.75  # warn below this share of cells holding corners
OUTLIER_FRAME_FACTOR = 3.0  # a frame is flagged when its RMS is this many times the median frame RMS ...
OUTLIER_FRAME_MIN_PX = 0.25  # ... and above this absolute level (noise-free data would flag noise otherwise)
REGION_NAMES = (("top-left", "top", "top-right"), ("left", "centre", "right"),
                ("bottom-left", "bottom", "bottom-right"))



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
                    start_board_T_ref: np.ndarray | None = None) -> np.ndarray:  # noqa: N803
    """(F, 4, 4) ``board_T_ref`` that best explain the corners with the rig held fixed (a GTSAM graph).

    This is what makes the rig-consistent RMS comparable across routes: every route's rig is scored with board
    poses fitted to all of its views at once.
    """
    if start_board_T_ref is None:  # PnP in every view through the fixed rig
        start_board_T_ref = initial_board_T_ref(pnp_all(obs, intrinsics), ref_T_view, obs.valid.sum(axis=2))
    graph = gtsam.NonlinearFactorGraph()
    frames = [f for f in range(obs.num_frames) if np.all(np.isfinite(start_board_T_ref[f]))]
    valid = obs.valid.copy()
    valid[:, [f for f in range(obs.num_frames) if f not in frames]] = False
    board_graph.add_fixed_rig_observations(graph, obs.corners_px, valid, intrinsics, ref_T_view, pixel_noise(1.0))
    board_graph.add_corner_priors(graph, obs.board.object_points(), board_graph.RIGID_BOARD_SIGMA_M)
    values = gtsam.Values()
    insert_board_poses(values, start_board_T_ref, frames)
    insert_board_corners(values, obs.board.object_points())
    result = optimize(graph, values, OptimizerSettings(max_iterations=50))
    return read_board_poses(result.values, obs.num_frames, frames)


def rms_px(residuals: np.ndarray, axis: tuple[int, ...] | int | None = None) -> np.ndarray | float:
    """RMS of the finite residual vectors (..., 2) (px) over ``axis`` (None: all); NaN where none is finite."""
    sq = np.sum(residuals**2, axis=-1)
    n = np.sum(np.isfinite(sq), axis=axis)
    total = np.nansum(sq, axis=axis)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(total / n)


def coverage_map(obs: BoardObservations, cells: int = COVERAGE_CELLS) -> np.ndarray:
    """(V, cells, cells) bool: which image cells hold at least one observed corner."""
    out = np.zeros((obs.num_views, cells, cells), dtype=bool)
    for v in range(obs.num_views):
        w, h = obs.image_size(v)
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
    """The frames whose RMS (px) exceeds `OUTLIER_FRAME_FACTOR` x the median frame's and `OUTLIER_FRAME_MIN_PX`."""
    finite = frame_rms_px[np.isfinite(frame_rms_px)]
    if finite.size == 0:
        return []
    limit = max(OUTLIER_FRAME_FACTOR * float(np.median(finite)), OUTLIER_FRAME_MIN_PX)
    return [int(f) for f in np.nonzero(np.nan_to_num(frame_rms_px, nan=0.0) > limit)[0]]
