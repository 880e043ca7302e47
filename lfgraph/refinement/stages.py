"""One stage of the refinement: its `StagePlan` (the priors from `lfgraph.factors.scene_graph`) run by the one stage
runner, `lfgraph.engine.stage_engine`.

- ``points``: cameras constant, only landmarks move (`TriangulationFactorCal3DS2`, one small block per landmark).
- ``intrinsics``: fx, fy, cx, cy free, distortion and poses held (`GeneralSFMFactor2Cal3DS2` + priors).
- ``poses``: poses free except the reference (gauge), intrinsics constant (`GenericProjectionFactorCal3DS2`).
- ``all``: poses and fx, fy, cx, cy free, distortion held.
The gauges are described in `lfgraph.factors.scene_graph`.
"""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.engine import stage_engine as engine
from lfgraph.engine.optimize import IterationCallback, OptimizerSettings
from lfgraph.engine.projections import ProjectionProblem
from lfgraph.engine.stage_engine import REFINE_RELATIVE_TOL, ROBUST_RELATIVE_TOL, StagePlan
from lfgraph.factors import scene_graph
from lfgraph.factors.hooks import GraphHook
from lfgraph.factors.noise import Noise, measurement_noise
from lfgraph.factors.prior_table import PriorTable
from lfgraph.refinement.config import Stage
from lfgraph.refinement.priors import ViewPriors


def baseline_scale(centre: np.ndarray, new: np.ndarray) -> float:
    """The scale that keeps the calibrated baselines' lengths: least squares over views of s |c_new| = |c_old|.

    Scale is a gauge of a scene refinement (images cannot tell it); matching the lengths, not the projections
    (``sum c_old . c_new / sum |c_new|^2``), keeps a turned baseline as long as it was.
    """
    old_len = np.linalg.norm(centre[:, :3, 3], axis=1)
    new_len = np.linalg.norm(new[:, :3, 3], axis=1)
    denom = float(np.sum(new_len**2))
    return float(np.sum(old_len * new_len)) / denom if denom > 0 else 1.0


def stage_plan(stage: Stage, calib: Calibration, scale_sigma_mm: float | None = None,
               held_views: frozenset[int] = frozenset(), priors: ViewPriors | None = None, max_iterations: int = 100,
               relative_tol: float = REFINE_RELATIVE_TOL) -> StagePlan:
    """A refinement stage as the engine's `StagePlan`: its priors are the input's pose priors (MAP drift priors
    centred on ``priors.centre``, or weak position priors of ``scale_sigma_mm``), the range gauge when scale is
    otherwise free, and with free intrinsics their priors; held views stay where they are."""
    stage = Stage(stage)
    centre = None if priors is None else priors.centre
    table = PriorTable(calib.grid.reference)
    if stage != Stage.POINTS:
        pose_mean, pose_sigmas = scene_graph.pose_priors(calib, stage.frees_poses, held_views, scale_sigma_mm,
                                                         None if centre is None else centre.ref_T_view,
                                                         None if priors is None else priors.pose_sigmas,
                                                         stage.frees_intrinsics)
        table = dataclasses.replace(table, pose_mean=pose_mean, pose_sigmas=pose_sigmas)
        free_views = [v for v in range(calib.num_views) if v != calib.grid.reference and v not in held_views]
        # a held view fixes scale by itself; otherwise one range does, and the result is rescaled in run_stage
        if stage.frees_poses and scale_sigma_mm is None and not held_views and free_views:
            table = dataclasses.replace(table, gauges=scene_graph.range_gauge(calib if centre is None else centre))
        if stage.frees_intrinsics:
            mean, sigmas = scene_graph.intrinsics_priors(calib, held_views, centre,
                                                         None if priors is None else priors.intrinsics_sigmas)
            table = dataclasses.replace(table, intrinsics_mean=mean, intrinsics_sigmas=sigmas,
                                        lenses=calib.lenses)
    settings = OptimizerSettings(max_iterations=max_iterations, relative_error_tol=relative_tol)
    return StagePlan(str(stage), "refinement", priors=table, settings=settings, frees=stage.groups, bulk=True,
                     keep_distortion=True)


def stage_graph(stage: Stage, calib: Calibration, pixels: np.ndarray, valid: np.ndarray, points: np.ndarray,
                model: gtsam.noiseModel.Base, scale_sigma_mm: float | None = None,
                held_views: frozenset[int] = frozenset(),
                priors: ViewPriors | None = None,
                projections: bool = True) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """The graph and initial values of one stage at ``calib`` and ``points`` (`stage_plan` through
    `lfgraph.engine.stage_engine.stage_graph`): what `run_stage` optimises, and what the posterior marginals are taken
    from. ``projections`` False: only the camera variables and their priors and gauges."""
    plan = stage_plan(stage, calib, scale_sigma_mm, held_views, priors)
    return engine.stage_graph(plan, calib, pixels, valid, points, model, projections)


def stage_problem(stage: Stage, calib: Calibration, pixels: np.ndarray, valid: np.ndarray, points: np.ndarray,
                  model: gtsam.noiseModel.Base, scale_sigma_mm: float | None = None,
                  held_views: frozenset[int] = frozenset(),
                  priors: ViewPriors | None = None,
                  hooks: tuple[GraphHook, ...] = ()) -> tuple[ProjectionProblem, tuple] | None:
    """The ``points`` or ``poses`` stage as a `ProjectionProblem` and its initial state, or None where GTSAM's factors
    are needed (`lfgraph.engine.stage_engine.bulk_problem`)."""
    plan = stage_plan(stage, calib, scale_sigma_mm, held_views, priors)
    return engine.bulk_problem(plan, calib, pixels, valid, points, model, hooks)


def run_stage(stage: Stage, calib: Calibration, pixels: np.ndarray, valid: np.ndarray, points: np.ndarray,
              noise: Noise, sigma_px: float = 1.0, scale_sigma_mm: float | None = None, max_iterations: int = 100,
              callback: IterationCallback | None = None, held_views: frozenset[int] = frozenset(),
              hooks: tuple[GraphHook, ...] = (),
              priors: ViewPriors | None = None) -> tuple[Calibration, np.ndarray, int]:
    """Run one free-variable stage (``points``, ``intrinsics``, ``poses`` or ``all``) on the engine
    (`lfgraph.engine.stage_engine.run_plan`), then restore the calibrated baselines' lengths where scale was free.

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
    relative_tol = ROBUST_RELATIVE_TOL if isinstance(model, gtsam.noiseModel.Robust) else REFINE_RELATIVE_TOL
    plan = stage_plan(stage, calib, scale_sigma_mm, held_views, priors, max_iterations, relative_tol)
    out = engine.run_plan(plan, calib, pixels, valid, points, model, callback, hooks)
    new, new_points = out.calib, out.points
    if stage.frees_poses and scale_sigma_mm is None and not held_views:
        scale = baseline_scale((calib if priors is None else priors.centre).ref_T_view, new.ref_T_view)
        poses = np.array(new.ref_T_view)
        poses[:, :3, 3] *= scale
        new, new_points = new.replace(ref_T_view=poses), new_points * scale
    return new, new_points, out.iterations
