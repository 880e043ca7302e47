"""The one stage runner below both staged-MAP wings: `refine` / `check` (`lfgraph.refinement.stages`) and
`calibrate-scene` (`lfgraph.selfcal.solve`).

A wing describes a stage as a `StagePlan`: which camera variables the graph holds (none: landmarks through constant
cameras; poses; poses and intrinsics), the priors and gauges that pull or pin them (each wing's own prior fragments:
drift priors centred on the input for a refinement, design priors for a self-calibration), and how to solve it.
`run_plan` assembles the graph (`stage_graph`: landmarks seen by `TriangulationFactor`, `GenericProjectionFactor` or
`GeneralSFMFactor2` by what is free, each view through its own lens), runs the user's graph hooks, solves it — the
bulk projections (`lfgraph.engine.projections`, `bulk_problem`) where the plan allows them and they apply, else GTSAM's
Levenberg–Marquardt (landmarks eliminated first, or with embedded landmark iterations) — and reads the result back
exactly relative to the reference view. Adding a stage is a plan; the wings keep only their priors and schedules.

A robust model whose loss is bounded (Tukey, Geman–McClure, Welsch, DCS: a residual far beyond the threshold pulls
nothing) starts each stage from the minimum under its Gaussian part (`least_squares_start`), as a redescending
M-estimator needs a start near its minimum: started from a knocked calibration, Tukey at 4.685 sigmas gave every
track of a knocked view zero weight and kept the input (3.3 px at infinity; 0.064 px from the least-squares start,
`benchmarks/refine.py --kernels-only`). Unbounded ones (Huber, Cauchy, Fair) start where the stage starts, and so
does a bounded one on the bulk path when every view's median residual keeps at least `START_WEIGHT_MIN` of the
weight the kernel gives Gaussian noise (the start is within the kernel's reach: a refinement's clean-up stage, after
its poses stage).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.camera import lens_table
from lfgraph.engine.bulk_noise import Kernel
from lfgraph.engine.optimize import IterationCallback, OptimizerSettings, gtsam_quiet, optimize
from lfgraph.engine.projections import ProjectionProblem
from lfgraph.engine.schur import optimize_problem
from lfgraph.engine.schur_system import NotReducible
from lfgraph.factors import scene_graph
from lfgraph.factors.groups import Group
from lfgraph.factors.hooks import GraphContext, GraphHook, run_hooks
from lfgraph.factors.keys import LANDMARK_CHAR, view_pose_key
from lfgraph.factors.prior_table import PriorTable
from lfgraph.factors.values import (
    insert_intrinsics,
    insert_landmarks,
    insert_view_poses,
    read_intrinsics,
    read_landmarks,
    read_view_poses,
)

# Levenberg–Marquardt's stop — an iteration lowering the cost by less than this fraction — by kind of stage:
REFINE_RELATIVE_TOL = 1e-7  # refine's stages. GTSAM's 1e-10 costs one more iteration per stage whose cost decrease is
# ~1e-11 relative (measured on paper-5x5: a parameter step of ~0.002 posterior sigma); the accuracy in
# benchmarks/refine.py is the same to the printed digits
ROBUST_RELATIVE_TOL = 1e-4  # refine's stages under a robust kernel (iteratively reweighted: linear convergence, each
# iteration lowering the cost by ~0.3-0.8 of the one before, where a Gaussian stage takes 2-3 iterations). On the kernel
# table (benchmarks/refine.py --kernels-only) Tukey, Geman-McClure (3.787 and 1 sigma), Cauchy and Huber land within
# 0.002 px at infinity of their fits converged to 1e-9 (Geman-McClure at 1 sigma: 0.003 px RMS with the start rule of
# `START_WEIGHT_MIN`), in 0.1-0.4x its iterations (0.55-0.8x those of 1e-5). A robust
# bulk stage also stops once the decrease still to come (`schur._left_to_gain`) is below this fraction. On the bulk path
# the fraction is of the cost or of what Gaussian noise would cost (one per observation), whichever is more: a cost
# gap measures the distance to the minimum in the estimator's own posterior sigmas whatever the kernel, and a kernel
# whose cost is far below the Gaussian's (Geman-McClure at 1 sigma: ~0.2 of it) was held ~5x tighter than the others
# (measured: every kernel of the table still lands within 0.002 px RMS at infinity of its converged fit; Geman-McClure
# at 1 sigma 299 -> 228 iterations over the table's refine, 205 with the shorter stretch of `schur._extrapolate`)
# An extra stop once the cameras moved by less than 0.01 of their posterior sigma per step wrote a worse calibration on
# a sweep scenario (benchmarks/sweep.py seed 57: a 3x4 on repeated texture, 29.9 -> 57.8 px at infinity)
INTERMEDIATE_RELATIVE_TOL = 1e-6  # a self-calibration's intermediate stages (the next stage starts from there)
FINAL_RELATIVE_TOL = 1e-9  # a self-calibration's final stage converges fully (the marginals are taken at its optimum)
START_WEIGHT_MIN = 0.5  # a bounded kernel's bulk stage starts where it is when the kernel gives every view's median
# residual at least this fraction of the weight it gives Gaussian noise's median (else from the least-squares minimum:
# a knocked view's tracks would weigh 0). Relative, because a narrow kernel weighs even noise little (Geman-McClure at
# 1 sigma: 0.18 at the median), and its stages started from least squares every time: a refinement's clean-up stage,
# which starts at the robust minimum of the stage before, went there and back (the kernel table's refine: 205 -> 184
# iterations)
NOISE_MEDIAN_DISTANCE = float(np.sqrt(2.0 * np.log(2.0)))  # median length of a 2-D whitened Gaussian residual
NOISE_WEIGHT_MIN = 0.1  # a kernel weighing Gaussian noise's median less than this (e.g. Tukey at 1 px during the
# first pass's 1 px sigma, which weighs it 0) cannot tell a start within its reach: its stages start from least squares


@dataclass(frozen=True)
class StagePlan:
    """One stage of a staged MAP fit.

    Attributes:
        name: the stage's name (graph hooks see it as ``GraphContext.stage``).
        wing: ``refinement`` or ``selfcal`` (``GraphContext.kind``).
        priors: the camera variables' priors and gauges as data (`lfgraph.factors.prior_table.PriorTable`: per view a
            mean and sigmas per parameter, held ones at ``HELD_SIGMA``, and gauge factors such as a range): what pulls
            the free groups and pins the rest; its ``graph`` is what the solvers add.
        frees: what the priors leave free of a free view (`lfgraph.factors.groups.Group`: pan/tilt, roll, position,
            focal, principal, distortion, k1 and their unions); what counts a stage's parameters derives from it.
            Variables the plan holds are still variables (`cameras`, `intrinsics`), pinned by ``priors``.
        settings: the optimiser's iterations, tolerance and embedded landmark iterations.
        eliminate_landmarks: GTSAM's graph is solved with the landmarks eliminated first (`lfgraph.engine.schur`);
            False: GTSAM's own Levenberg–Marquardt and ordering.
        bulk: the bulk projections may solve it (points and poses stages with a 2-D Gaussian or robust noise).
        keep_distortion: intrinsics read back keep the input's distortion (the stage holds it: no round-off).
        tangential: p1, p2 read back (False clears their round-off where priors hold them at 0).
    """

    name: str
    wing: str
    priors: PriorTable
    settings: OptimizerSettings
    frees: frozenset[Group] = frozenset()
    eliminate_landmarks: bool = True
    bulk: bool = False
    keep_distortion: bool = False
    tangential: bool = True

    @property
    def cameras(self) -> bool:
        """The views' poses are variables: the priors have pose rows (none: the points stage, landmarks through
        constant cameras)."""
        return self.priors.pose_sigmas is not None

    @property
    def intrinsics(self) -> bool:
        """The views' intrinsics are variables too (`scene_graph.sfm_factors`): the priors have calibration rows."""
        return self.priors.intrinsics_sigmas is not None


@dataclass(frozen=True)
class PlanResult:
    """What `run_plan` returns: the calibration and (N, 3) landmarks exactly relative to the reference view, the
    Levenberg–Marquardt iterations, and the GTSAM graph with its optimum (None when the bulk projections solved it)."""

    calib: Calibration
    points: np.ndarray
    iterations: int
    graph: gtsam.NonlinearFactorGraph | None
    values: gtsam.Values | None


def stage_graph(plan: StagePlan, calib: Calibration, pixels: np.ndarray, valid: np.ndarray, points: np.ndarray,
                model: gtsam.noiseModel.Base, projections: bool = True) -> tuple[gtsam.NonlinearFactorGraph,
                                                                                   gtsam.Values]:
    """The plan's GTSAM graph and initial values at ``calib`` and (N, 3) ``points``; ``projections`` False: only
    the camera variables with their priors and gauges (what `bulk_problem` adds its projections to).

    Args:
        pixels: (V, N, 2) observations; valid: (V, N); model: the measurement noise.
    """
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    if projections:
        insert_landmarks(values, points)
    if not plan.cameras:
        if projections:
            graph.push_back(scene_graph.triangulation_factors(calib, pixels, valid, model))
        return graph, values
    insert_view_poses(values, calib.ref_T_view)
    graph.push_back(plan.priors.graph)
    if plan.intrinsics:
        insert_intrinsics(values, calib.intrinsics)
        if projections:
            graph.push_back(scene_graph.sfm_factors(pixels, valid, model, [i.lens for i in calib.intrinsics]))
    elif projections:
        graph.push_back(scene_graph.projection_factors(calib, pixels, valid, model))
    return graph, values


def bulk_problem(plan: StagePlan, calib: Calibration, pixels: np.ndarray, valid: np.ndarray, points: np.ndarray,
                 model: gtsam.noiseModel.Base, hooks: Sequence[GraphHook] = ()
                 ) -> tuple[ProjectionProblem, tuple] | None:
    """The plan as a `ProjectionProblem` (projections in bulk; priors, gauges and the hooks' factors as GTSAM
    factors) and its initial state, or None where GTSAM's factors are needed: a plan without ``bulk``, free
    intrinsics, a noise model the bulk path cannot apply, a landmark behind a camera, a hook's factor on a variable
    the camera graph does not hold (a landmark; on the points stage, any). The hooks see the camera graph."""
    if not plan.bulk or plan.intrinsics:
        return None
    graph, values = stage_graph(plan, calib, pixels, valid, points, model, projections=False)
    if hooks:
        run_hooks(hooks, GraphContext(plan.wing, plan.name, graph, values, calib.num_views, calib))
        if not set(graph.keyVector()) <= set(values.keys()):
            return None
    vs, js = np.nonzero(valid)
    intr, lenses = lens_table(calib.intrinsics)
    cameras = dict(pose_keys=[view_pose_key(v) for v in range(calib.num_views)]) if plan.cameras else \
        dict(fixed_poses=np.asarray(calib.ref_T_view))
    try:
        problem = ProjectionProblem(graph, values, vs, js, pixels[vs, js], model, intr, lenses, len(points), **cameras)
    except NotReducible:
        return None
    state = (values, np.asarray(points, dtype=np.float64))
    return (problem, state) if np.isfinite(problem.error(state)) else None


def least_squares_start(model: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base | None:
    """The Gaussian part of a robust model whose loss is bounded (`lfgraph.engine.bulk_noise.Kernel.bounded`): a stage
    under it first solves under this, from whose minimum the robust fit starts; None for any other model."""
    if not isinstance(model, gtsam.noiseModel.Robust):
        return None
    return model.noise() if Kernel(model.robust()).bounded else None


def _solve_bulk(plan: StagePlan, problem: ProjectionProblem, state, callback) -> tuple[tuple, int]:
    """The bulk problem solved ((values, points), iterations), from the least-squares minimum for a bounded loss
    unless the start is within the kernel's reach (`START_WEIGHT_MIN`)."""
    limits = dict(max_iterations=plan.settings.max_iterations, relative_error_tol=plan.settings.relative_error_tol)
    iterations = 0
    kernel = problem.noise.kernel
    noise = float(kernel.weights(np.array([NOISE_MEDIAN_DISTANCE]))[0]) if kernel is not None else 1.0
    if kernel is not None and kernel.bounded and (noise < NOISE_WEIGHT_MIN or np.min(problem.typical_weights(state))
                                                  < START_WEIGHT_MIN * noise):
        warm = optimize_problem(problem.gaussian(), state, callback=callback, **limits)
        state, iterations = warm.values, warm.iterations
    res = optimize_problem(problem, state, callback=callback, **limits)
    return res.values, iterations + res.iterations


def _solve_graph(plan: StagePlan, calib: Calibration, pixels: np.ndarray, valid: np.ndarray, points: np.ndarray,
                 model: gtsam.noiseModel.Base, callback, hooks: Sequence[GraphHook]):
    """The stage as GTSAM factors solved by GTSAM's optimiser (graph, values, iterations), from the least-squares
    minimum for a bounded loss."""
    eliminate = LANDMARK_CHAR if plan.eliminate_landmarks else None
    iterations = 0
    start = None
    plain = least_squares_start(model)
    if plain is not None:
        graph, values = stage_graph(plan, calib, pixels, valid, points, plain)
        run_hooks(hooks, GraphContext(plan.wing, plan.name, graph, values, calib.num_views, calib))
        warm = optimize(graph, values, plan.settings, callback, eliminate=eliminate)
        start, iterations = warm.values, warm.iterations
    graph, values = stage_graph(plan, calib, pixels, valid, points, model)
    run_hooks(hooks, GraphContext(plan.wing, plan.name, graph, values, calib.num_views, calib))
    result = optimize(graph, start if start is not None else values, plan.settings, callback, eliminate=eliminate)
    return graph, result.values, iterations + result.iterations


def run_plan(plan: StagePlan, calib: Calibration, pixels: np.ndarray, valid: np.ndarray, points: np.ndarray,
             model: gtsam.noiseModel.Base, callback: IterationCallback | None = None,
             hooks: Sequence[GraphHook] = ()) -> PlanResult:
    """Assemble, solve and read back one stage (module docstring).

    Args:
        pixels: (V, N, 2) observations; valid: (V, N); points: (N, 3) initial landmarks (reference frame, m).
        model: the measurement noise (any GTSAM noise model, robust or not).
        callback: the optimiser's iteration hook; hooks: user graph hooks (`lfgraph.factors.hooks`).
    """
    bulk = bulk_problem(plan, calib, pixels, valid, points, model, hooks)
    graph = None
    with gtsam_quiet():
        if bulk is not None:
            (values, new_points), iterations = _solve_bulk(plan, *bulk, callback)
        else:
            graph, values, iterations = _solve_graph(plan, calib, pixels, valid, points, model, callback, hooks)
            new_points = read_landmarks(values, len(points)) if len(points) else np.asarray(points, dtype=np.float64)
    if not plan.cameras:
        return PlanResult(calib, new_points, iterations, graph, values if graph is not None else None)
    poses = read_view_poses(values, calib.num_views)
    ref = calib.grid.reference
    back = np.linalg.inv(poses[ref])  # the gauge holds the reference to ~1e-8: make it exact, landmarks alike
    poses = back[None] @ poses
    poses[ref] = np.eye(4)
    new_points = new_points @ back[:3, :3].T + back[:3, 3]
    intr = calib.intrinsics
    if plan.intrinsics:
        intr = read_intrinsics(values, calib.num_views, keep=calib.intrinsics if plan.keep_distortion else None,
                               tangential=plan.tangential, lenses=[i.lens for i in calib.intrinsics])
    return PlanResult(calib.replace(intrinsics=intr, ref_T_view=poses), new_points, iterations, graph,
                      values if graph is not None else None)
