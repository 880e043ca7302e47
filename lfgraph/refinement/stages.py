"""One stage of the refinement as a GTSAM graph, assembled from `lfgraph.factors.scene_graph` fragments.

- ``points``: cameras constant, only landmarks move (`TriangulationFactorCal3DS2`, one small block per landmark).
- ``intrinsics``: fx, fy, cx, cy free, distortion and poses held (`GeneralSFMFactor2Cal3DS2` + priors).
- ``poses``: poses free except the reference (gauge), intrinsics constant (`GenericProjectionFactorCal3DS2`).
- ``all``: poses and fx, fy, cx, cy free, distortion held.
The gauges are described in `lfgraph.factors.scene_graph`.
"""

from __future__ import annotations

import gtsam
import numpy as np

from lfgraph.calibration import Calibration
from lfgraph.camera import lens_table
from lfgraph.factors import scene_graph
from lfgraph.factors.hooks import GraphContext, GraphHook, run_hooks
from lfgraph.factors.keys import LANDMARK_CHAR, view_pose_key
from lfgraph.factors.noise import Noise, measurement_noise
from lfgraph.factors.values import (
    insert_intrinsics,
    insert_landmarks,
    insert_view_poses,
    read_intrinsics,
    read_landmarks,
    read_view_poses,
)
from lfgraph.optimize import IterationCallback, OptimizerSettings, gtsam_quiet, optimize
from lfgraph.refinement.config import Stage
from lfgraph.refinement.priors import ViewPriors
from lfgraph.refinement.projections import ProjectionProblem
from lfgraph.schur import optimize_problem
from lfgraph.schur_system import NotReducible

STAGE_RELATIVE_TOL = 1e-7  # LM stops when an iteration lowers the cost by less than this fraction. GTSAM's 1e-10
# costs one more iteration per stage whose cost decrease is ~1e-11 relative (measured on paper-5x5: a parameter step
# of ~0.002 posterior sigma); the accuracy in benchmarks/refine.py is the same to the printed digits
# A robust kernel's stage (iteratively reweighted: linear convergence, ~20 iterations of 1e-6..1e-7 of the cost each
# where a Gaussian stage takes 2-3) stops at GTSAM's default relative tolerance. An earlier extra stop, once the
# cameras moved by less than 0.01 of their posterior sigma per step, wrote a worse calibration on a sweep scenario
# (benchmarks/sweep.py seed 57: a 3x4 on repeated texture, 29.9 -> 57.8 px at infinity; kept unchanged without it).
ROBUST_RELATIVE_TOL = 1e-5


def baseline_scale(centre: np.ndarray, new: np.ndarray) -> float:
    """The scale that keeps the calibrated baselines' lengths: least squares over views of s |c_new| = |c_old|.

    Scale is a gauge of a scene refinement (images cannot tell it); matching the lengths, not the projections
    (``sum c_old . c_new / sum |c_new|^2``), keeps a turned baseline as long as it was.
    """
    old_len = np.linalg.norm(centre[:, :3, 3], axis=1)
    new_len = np.linalg.norm(new[:, :3, 3], axis=1)
    denom = float(np.sum(new_len**2))
    return float(np.sum(old_len * new_len)) / denom if denom > 0 else 1.0


def stage_graph(stage: Stage, calib: Calibration, pixels: np.ndarray, valid: np.ndarray, points: np.ndarray,
                model: gtsam.noiseModel.Base, scale_sigma_mm: float | None = None,
                held_views: frozenset[int] = frozenset(),
                priors: ViewPriors | None = None,
                projections: bool = True) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """The graph and initial values of one free-variable stage (``intrinsics``, ``poses`` or ``all``) at ``calib``
    and ``points``: what `run_stage` optimises, and what the posterior marginals are taken from. ``projections``
    False: only the camera variables and their priors and gauges (`stage_problem` evaluates the projections)."""
    stage = Stage(stage)
    n_views = calib.num_views
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    if projections:
        insert_landmarks(values, points)
    poses_free = stage.frees_poses
    intr_free = stage.frees_intrinsics
    insert_view_poses(values, calib.ref_T_view)
    centre = None if priors is None else priors.centre.ref_T_view
    graph.push_back(scene_graph.pose_priors(calib, poses_free, held_views, scale_sigma_mm, centre,
                                            None if priors is None else priors.pose_sigmas, intr_free))
    free_views = [v for v in range(n_views) if v != calib.grid.reference and v not in held_views]
    # a held view fixes scale by itself; otherwise one range does, and the result is rescaled in run_stage
    if poses_free and scale_sigma_mm is None and not held_views and free_views:
        graph.push_back(scene_graph.range_gauge(calib if priors is None else priors.centre))
    if intr_free:
        insert_intrinsics(values, calib.intrinsics)
        graph.push_back(scene_graph.intrinsics_priors(calib, held_views, None if priors is None else priors.centre,
                                                      None if priors is None else priors.intrinsics_sigmas))
        graph.push_back(scene_graph.sfm_factors(pixels, valid, model))
    elif projections:
        graph.push_back(scene_graph.projection_factors(calib, pixels, valid, model))
    return graph, values


def stage_problem(stage: Stage, calib: Calibration, pixels: np.ndarray, valid: np.ndarray, points: np.ndarray,
                  model: gtsam.noiseModel.Base, scale_sigma_mm: float | None = None,
                  held_views: frozenset[int] = frozenset(),
                  priors: ViewPriors | None = None,
                  hooks: tuple[GraphHook, ...] = ()) -> tuple[ProjectionProblem, tuple] | None:
    """The ``points`` or ``poses`` stage as a `ProjectionProblem` (`refinement.projections`: projections in bulk, the
    priors, gauges and the ``hooks``' factors as GTSAM factors) and its initial state, or None where GTSAM's factors
    are needed: a noise model the bulk path cannot apply (not a 2-D Gaussian, robust or not), free intrinsics, a
    landmark behind a camera, a hook's factor on a variable the camera graph does not hold (a landmark; on the
    ``points`` stage, any). The hooks see the camera graph (``ctx.graph`` without the projection factors)."""
    stage = Stage(stage)
    if stage not in (Stage.POINTS, Stage.POSES):
        return None
    vs, js = np.nonzero(valid)
    intr, lenses = lens_table(calib.intrinsics)
    if stage == Stage.POINTS:
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    else:
        graph, values = stage_graph(stage, calib, pixels, valid, points, model, scale_sigma_mm, held_views, priors,
                                    projections=False)
    if hooks:
        run_hooks(hooks, GraphContext("refinement", str(stage), graph, values, calib.num_views, calib))
        if not set(graph.keyVector()) <= set(values.keys()):
            return None
    try:
        if stage == Stage.POINTS:
            problem = ProjectionProblem(graph, values, vs, js, pixels[vs, js], model, intr, lenses,
                                        len(points), fixed_poses=np.asarray(calib.ref_T_view))
        else:
            problem = ProjectionProblem(graph, values, vs, js, pixels[vs, js], model, intr, lenses,
                                        len(points), pose_keys=[view_pose_key(v) for v in range(calib.num_views)])
    except NotReducible:
        return None
    state = (values, np.asarray(points, dtype=np.float64))
    return (problem, state) if np.isfinite(problem.error(state)) else None


def run_stage(stage: Stage, calib: Calibration, pixels: np.ndarray, valid: np.ndarray, points: np.ndarray,
              noise: Noise, sigma_px: float = 1.0, scale_sigma_mm: float | None = None, max_iterations: int = 100,
              callback: IterationCallback | None = None, held_views: frozenset[int] = frozenset(),
              hooks: tuple[GraphHook, ...] = (),
              priors: ViewPriors | None = None) -> tuple[Calibration, np.ndarray, int]:
    """Run one free-variable stage (``points``, ``intrinsics``, ``poses`` or ``all``).

    Args:
        pixels: (V, N, 2) observations; valid: (V, N); points: (N, 3) initial landmarks (reference frame, m).
        noise: the measurement noise (a normalised `lfgraph.factors.noise.NoiseSpec`); sigma_px its sigma.
        scale_sigma_mm: None: scale by one range and a rescale to the calibrated baselines' lengths; else weak
            position priors of this sigma.
        held_views: views whose pose and intrinsics stay where they are (at the prior centre with ``priors``).
        hooks: user graph hooks (`lfgraph.factors.hooks`).
        priors: MAP priors centred on the input calibration (`lfgraph.refinement.priors`); None: a free fit.

    Returns:
        the updated calibration, (N, 3) landmarks, LM iterations.
    """
    stage = Stage(stage)
    model = measurement_noise(noise, sigma_px)
    n_views = calib.num_views
    poses_free = stage.frees_poses
    intr_free = stage.frees_intrinsics
    relative_tol = ROBUST_RELATIVE_TOL if isinstance(model, gtsam.noiseModel.Robust) else STAGE_RELATIVE_TOL
    bulk = stage_problem(stage, calib, pixels, valid, points, model, scale_sigma_mm, held_views, priors, hooks)
    if bulk is not None:  # the projections in bulk
        with gtsam_quiet():
            res = optimize_problem(*bulk, max_iterations=max_iterations, callback=callback,
                                   relative_error_tol=relative_tol)
        result_values, new_points = res.values
        iterations = res.iterations
    else:
        if stage == Stage.POINTS:
            graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
            insert_landmarks(values, points)
            graph.push_back(scene_graph.triangulation_factors(calib, pixels, valid, model))
        else:
            graph, values = stage_graph(stage, calib, pixels, valid, points, model, scale_sigma_mm, held_views,
                                        priors)
        run_hooks(hooks, GraphContext("refinement", str(stage), graph, values, n_views, calib))
        result = optimize(graph, values, OptimizerSettings(max_iterations=max_iterations,
                                                           relative_error_tol=relative_tol), callback,
                          eliminate=LANDMARK_CHAR)
        result_values, iterations = result.values, result.iterations
        new_points = read_landmarks(result_values, len(points)) if len(points) else points
    if stage == Stage.POINTS:
        return calib, new_points, iterations
    poses = read_view_poses(result_values, n_views)
    ref = calib.grid.reference
    poses = np.linalg.inv(poses[ref])[None] @ poses  # exactly relative to the reference again
    poses[ref] = np.eye(4)
    if poses_free and scale_sigma_mm is None and not held_views:
        scale = baseline_scale((calib if priors is None else priors.centre).ref_T_view, poses)
        poses[:, :3, 3] *= scale
        new_points = new_points * scale
    intr = read_intrinsics(result_values, n_views, keep=calib.intrinsics) if intr_free else calib.intrinsics
    return calib.replace(intrinsics=intr, ref_T_view=poses), new_points, iterations
