"""The joint route: one graph over all views and frames (`lfgraph.factors.board_graph`'s model), started from the
paper route or design values, solved by the engine's bulk board problem (`lfgraph.engine.board_problem`: GTSAM's
residuals and Jacobians evaluated in numpy, its Levenberg–Marquardt) or, with graph hooks, by GTSAM's factors;
1-sigma uncertainties from the marginals at its optimum (`lfgraph.engine.schur.CameraMarginals`, the one posterior
path)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from lfgraph.core.camera import Intrinsics
from lfgraph.core.sigmas import Sigmas
from lfgraph.detect.detections import BoardObservations
from lfgraph.engine.board_problem import BoardProblem
from lfgraph.engine.optimize import IterationCallback, OptimizationResult, OptimizerSettings, gtsam_quiet, optimize
from lfgraph.engine.schur import CameraMarginals, optimize_problem
from lfgraph.engine.schur_system import NotReducible
from lfgraph.factors import board_graph
from lfgraph.factors.hooks import GraphContext, run_hooks
from lfgraph.factors.keys import BOARD_CORNER_CHAR, board_corner_key, calib_key, view_pose_key
from lfgraph.factors.noise import MIN_SIGMA, RobustKernel, measurement_noise
from lfgraph.factors.values import (
    insert_board_corners,
    insert_board_points,
    insert_board_poses,
    insert_intrinsics,
    insert_view_poses,
    read_board_corners,
    read_board_poses,
    read_intrinsics,
    read_view_poses,
)
from lfgraph.pattern.config import CalibrateConfig
from lfgraph.pattern.initial import weak_views
from lfgraph.pattern.scoring import rig_residuals

SIGMA_FLOOR_PX = 1e-3  # pixel sigma of the measurement model never goes below this (noise-free synthetic data)
PAIR_MAX_ITERATIONS = 100  # a pair's relative pose (`pair_pose`): as cv2.stereoCalibrate's criteria


@dataclass(frozen=True)
class JointResult:
    """The joint graph's calibration: every view's intrinsics and ``ref_T_view`` (V, 4, 4, m), every frame's
    ``board_T_ref`` (F, 4, 4), the board's corners (C, 3, m), the optimiser's record, the corner noise the residuals
    support (px), the posterior sigmas per view and every corner's residual (V, F, C, 2) px (`rig_residuals`)."""
    intrinsics: tuple[Intrinsics, ...]
    ref_T_view: np.ndarray
    board_T_ref: np.ndarray
    object_points_m: np.ndarray
    optimization: OptimizationResult
    noise_sigma_px: float
    sigmas: tuple[dict[str, Any], ...] | None
    residuals_px: np.ndarray


def joint_priors(obs: BoardObservations, intrinsics: tuple[Intrinsics, ...], settings: CalibrateConfig,
                 corners: bool = True) -> gtsam.NonlinearFactorGraph:
    """Every factor but the observations: the corners' priors (unless ``corners`` is False: the corners are then
    constants of the bulk problem, `_solve`), the gauge and the intrinsics pins."""
    graph = gtsam.NonlinearFactorGraph()
    board_sigma_m = board_graph.RIGID_BOARD_SIGMA_M if settings.board_sigma_mm is None \
        else settings.board_sigma_mm * 1e-3
    if corners:
        board_graph.add_corner_priors(graph, obs.board.object_points(), board_sigma_m)
    board_graph.add_gauge_prior(graph, obs.grid.reference)
    board_graph.add_intrinsics_pins(graph, intrinsics, settings.tangential, weak_views(obs),
                                   [obs.image_size(v)[0] for v in range(obs.num_views)])
    return graph


def _with_observations(priors: gtsam.NonlinearFactorGraph, values: gtsam.Values, obs: BoardObservations,
                       valid: np.ndarray, noise, lenses: tuple[str, ...]) -> tuple[gtsam.NonlinearFactorGraph,
                                                                                 gtsam.Values]:
    """The whole GTSAM graph (one factor per observation, `lfgraph.factors.board_graph`) and its values (with the
    board points of views whose lens has no board factor)."""
    graph = gtsam.NonlinearFactorGraph(priors)
    board_graph.add_board_observations(graph, obs.corners_px, valid, noise, lenses)
    values = gtsam.Values(values)
    frames = sorted({f for f, _ in board_graph.unified_board_points(valid, lenses)})
    boards = read_board_poses(values, obs.num_frames, frames)
    insert_board_points(values, board_graph.unified_board_points(valid, lenses), boards,
                        read_board_corners(values, obs.board.num_corners))
    return graph, values


def _solve(obs: BoardObservations, valid: np.ndarray, frames: list[int], intrinsics: tuple[Intrinsics, ...],
           values: gtsam.Values, settings: CalibrateConfig, lenses: tuple[str, ...], callback):
    """Levenberg–Marquardt on the joint graph: the engine's bulk board problem (`BoardProblem`; a rigid board's
    corners as its constants rather than variables held by 1 um priors: 240 instead of 504 columns on paper-4x4, its
    sigmas 6e-7 apart; a board given in square units, 1 mm a square, was not rigid under 1 um: pycalib's corners moved
    0.04 % of a square and its fx 0.25 px), or GTSAM's factors where it cannot (graph hooks, a noise model it does not
    evaluate in bulk). Returns (the result, the problem or None, a function making the whole GTSAM graph and values
    at a state)."""
    noise = measurement_noise(settings.noise, settings.corner_sigma_px)
    priors = joint_priors(obs, intrinsics, settings)

    def build(state: gtsam.Values):
        if not state.exists(board_corner_key(0)):  # a rigid board's corners, constants of the bulk problem
            state = gtsam.Values(state)
            insert_board_corners(state, obs.board.object_points())
        return _with_observations(priors, state, obs, valid, noise, lenses)

    if not settings.graph_hooks:
        rigid = settings.board_sigma_mm is None
        state = _without_corners(values, obs.board.num_corners) if rigid else values
        try:
            problem = BoardProblem(joint_priors(obs, intrinsics, settings, corners=False) if rigid else priors,
                                   state, obs.corners_px[:, frames], valid[:, frames], frames, noise, lenses,
                                   fixed_corners=obs.board.object_points() if rigid else None)
            return optimize_problem(problem, state, settings.max_iterations, callback=callback), problem, build
        except NotReducible:
            pass
    graph, full = build(values)
    run_hooks(settings.graph_hooks, GraphContext("calibration", None, graph, full, obs.num_views))
    result = optimize(graph, full, OptimizerSettings(max_iterations=settings.max_iterations), callback)
    return result, None, lambda state: (graph, state)


def _without_corners(values: gtsam.Values, n_corners: int) -> gtsam.Values:
    """``values`` without the board's corners (a rigid board's: constants of the bulk problem)."""
    out = gtsam.Values(values)
    for c in range(n_corners):
        out.erase(board_corner_key(c))
    return out


def calibrate_joint(obs: BoardObservations, intrinsics: tuple[Intrinsics, ...], ref_T_view: np.ndarray,  # noqa: N803
                    board_T_ref: np.ndarray, config: CalibrateConfig | None = None,  # noqa: N803
                    callback: IterationCallback | None = None) -> JointResult:
    """One graph over all views and frames (see `lfgraph.factors.board_graph`), solved by the engine.

    Args:
        obs: the corners.
        intrinsics, ref_T_view, board_T_ref: the start (from `calibrate_paper` or `design_initial`).
        config: options; `CalibrateConfig()` by default.
        callback: optimiser iteration hook.
    """
    settings = config or CalibrateConfig()
    frames = [f for f in range(obs.num_frames) if np.all(np.isfinite(board_T_ref[f]))]
    valid = obs.valid.copy()
    valid[:, [f for f in range(obs.num_frames) if f not in frames]] = False
    lenses = tuple(i.lens for i in intrinsics)
    obj = obs.board.object_points()
    values = gtsam.Values()
    insert_intrinsics(values, intrinsics)
    insert_view_poses(values, ref_T_view)
    insert_board_poses(values, board_T_ref, frames)
    insert_board_corners(values, obj)
    result, problem, build = _solve(obs, valid, frames, intrinsics, values, settings, lenses, callback)
    fit = est = result.values
    if not est.exists(board_corner_key(0)):  # a rigid board's corners were constants
        est = gtsam.Values(est)
        insert_board_corners(est, obj)
    n_views = obs.num_views
    # skew and (unless estimated) p1, p2 are pinned at 0 by priors: read_intrinsics clears their round-off
    intr = read_intrinsics(est, n_views, tangential=settings.tangential, lenses=lenses)
    poses = read_view_poses(est, n_views)
    poses[obs.grid.reference] = np.eye(4)  # the gauge prior holds it to 1e-8; make it exact for the file
    boards = read_board_poses(est, obs.num_frames, frames)
    corners = read_board_corners(est, len(obj))
    res = rig_residuals(intr, poses, boards, obs, corners)
    n_params = sum(i.model.free_size(settings.tangential) for i in intr) + 6 * (n_views - 1) + 6 * len(frames)
    dof = max(2 * int(valid.sum()) - n_params, 1)
    noise_sigma = float(np.sqrt(np.nansum(res**2) / dof))
    sigmas = None
    if settings.marginals:
        scale = max(noise_sigma, SIGMA_FLOOR_PX) / settings.corner_sigma_px
        try:
            with gtsam_quiet():
                marginals = CameraMarginals(problem=problem, state=fit, build=lambda: build(est)) \
                    if problem is not None else CameraMarginals(*build(est), BOARD_CORNER_CHAR)
            # Pose3's covariance is in the body frame: about / along each view's own axes, as `Sigmas` keeps them
            sigmas = tuple(Sigmas.from_marginals(marginals, [calib_key(v) for v in range(n_views)],
                                                 [view_pose_key(v) for v in range(n_views)], lenses, scale,
                                                 settings.tangential).to_metrics())
        except RuntimeError:  # GTSAM: an indeterminate system (e.g. a unified lens whose xi the board cannot fix)
            logging.getLogger("lfgraph").warning(
                "the calibration's uncertainties cannot be computed: some parameters are not determined by these "
                "boards (GTSAM found the system indeterminate); the file has no 1-sigma figures")
    return JointResult(intr, poses, boards, corners, result, noise_sigma, sigmas, res)


def pair_pose(obs: BoardObservations, ref: int, v: int, pair: tuple[Intrinsics, Intrinsics], frames: list[int],
              masks: list[np.ndarray], start_ref_T_view: np.ndarray,  # noqa: N803
              ref_T_board: np.ndarray) -> tuple[np.ndarray, float, float]:  # noqa: N803
    """View ``v``'s pose relative to the reference with both views' intrinsics held, by Levenberg–Marquardt over the
    shared ``frames`` (corner ``masks`` seen by both; each frame's board pose free, started at ``ref_T_board``
    (F', 4, 4), the reference's PnP; the board's corners as printed): ``cv2.stereoCalibrate(CALIB_FIX_INTRINSIC)``'s
    problem on the engine's bulk board problem, without its per-call setup. Returns (ref_T_view, RMS px of both
    views' corners, number of residual coordinates)."""
    corners = np.stack([obs.corners_px[u][frames] for u in (ref, v)])
    valid = np.stack([np.asarray(masks, dtype=bool)] * 2)
    local = list(range(len(frames)))
    values = gtsam.Values()
    insert_intrinsics(values, pair)
    insert_view_poses(values, np.stack([np.eye(4), start_ref_T_view]))
    insert_board_poses(values, np.linalg.inv(np.asarray(ref_T_board)), local)
    priors = gtsam.NonlinearFactorGraph()
    board_graph.add_gauge_prior(priors, 0)
    for u, intr in enumerate(pair):  # both views' intrinsics held, as CALIB_FIX_INTRINSIC holds them
        priors.add(intr.model.gtsam("PriorFactor")(calib_key(u), intr.to_gtsam(),
                                                   gtsam.noiseModel.Isotropic.Sigma(intr.model.tangent_size,
                                                                                    MIN_SIGMA)))
    problem = BoardProblem(priors, values, corners, valid, local, measurement_noise(RobustKernel("none"), 1.0),
                           tuple(i.lens for i in pair), fixed_corners=obs.board.object_points())
    est = optimize_problem(problem, values, PAIR_MAX_ITERATIONS).values
    return read_view_poses(est, 2)[1], problem.rms_px(est), float(valid.sum())
