"""The staged MAP graph of self-calibration: landmarks seen through free poses and intrinsics, design priors, the
outlier filter, the measured noise and the marginals."""

from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.camera import Intrinsics
from lfgraph.core.sigmas import Sigmas
from lfgraph.engine.optimize import IterationCallback, OptimizerSettings, gtsam_quiet
from lfgraph.engine.schur import CameraMarginals
from lfgraph.engine.stage_engine import INTERMEDIATE_RELATIVE_TOL, StagePlan, run_plan
from lfgraph.engine.triangulate import drop_mismatches, reprojection_errors, triangulate_dlt
from lfgraph.factors import selfcal_graph
from lfgraph.factors.groups import Group
from lfgraph.factors.keys import LANDMARK_CHAR, calib_key, landmark_key, view_pose_key
from lfgraph.factors.noise import Noise, measurement_noise
from lfgraph.factors.prior_table import PriorTable
from lfgraph.lenses import lens_model

# after every Levenberg–Marquardt step the landmarks are solved again with the cameras held (`lfgraph.engine.schur`'s
# embedded point iterations). The common zoom and the hidden principal-point gauge are long curved valleys that move
# every landmark: plain LM crawled along them (each step ~0.96 of the last's decrease) and stopped at its 150-iteration
# cap (paper-4x4 rig, 10 frames of exact tracks: principal-point slope 0.72 px per grid step and zoom 1.52 px, at the
# minimum -0.05 px/step, posterior sigma 0.17, and 0.03 px); with 2 landmark iterations per step it reached the
# minimum in 4 steps from there, 5 + 3 from the staged start
LANDMARK_ITERATIONS = 2
# landmarks the design geometry puts behind the reference view, when all are, start where the whole array sees this
# disparity (px). Was 1000x the largest view offset: 18 m on paper-4x4, beyond the 10.8 m (1 px across the array) at
# which `lfgraph.selfcal.stages.reachable` drops a landmark, so rig seed 4 at 10 frames lost every track before its
# first stage; 10 px puts them at 1.08 m there (scenes 0.5-2 m)
NO_DEPTH_DISPARITY_PX = 10.0
# ... and so do all when fewer than this share of the DLT landmarks lie in front: those few are noise (rig seed 4 at
# 20 frames: 35 of 5686 in front, at 0-4 mm; their median, 2.6 mm, was every other landmark's start and the first
# stage kept 4 % of them). Rig seeds 0 and 5 have all in front, seed 1 21-22 %: unchanged
MIN_DLT_FRONT_SHARE = 0.05
# Cal3DS2 tangent order -> the parameters lfgraph reports


def initial_landmarks(calib: Calibration, pixels: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """DLT landmarks; a landmark behind the reference view or not finite goes on its reference ray at the median
    depth of the others (GTSAM gives landmarks behind a camera zero Jacobians). When fewer than
    `MIN_DLT_FRONT_SHARE` are in front (the design geometry's rotation errors swamp the disparities), every landmark
    goes on its ray where the whole array would see `NO_DEPTH_DISPARITY_PX` of disparity: well inside what
    `lfgraph.selfcal.stages.reachable` keeps."""
    pts = triangulate_dlt(calib, pixels, valid)
    ref = calib.grid.reference
    bad = ~(np.all(np.isfinite(pts), axis=1) & (pts[:, 2] > 0))
    if np.mean(~bad) >= MIN_DLT_FRONT_SHARE:
        depth = float(np.median(pts[~bad, 2]))
    else:
        centres = calib.ref_T_view[:, :3, 3]
        span = float(np.max(np.linalg.norm(centres[:, None] - centres[None], axis=-1)))
        depth = calib.intrinsics[ref].fx * span / NO_DEPTH_DISPARITY_PX
        bad[:] = True
    if bad.any():
        xy = calib.intrinsics[ref].undistort(pixels[ref, bad])
        xy = np.where(np.isfinite(xy), xy, 0.0)
        pts[bad] = np.column_stack([xy, np.ones(len(xy))]) * depth
    return pts


def run_map_stage(calib: Calibration, design: Calibration, pixels: np.ndarray, valid: np.ndarray, points: np.ndarray,
                  free: frozenset[str], sigmas: Sigmas, model: gtsam.noiseModel.Base, max_iterations: int,
                  relative_tol: float = INTERMEDIATE_RELATIVE_TOL, callback: IterationCallback | None = None,
                  hooks: tuple[Callable, ...] = (), hold_gauges: bool = True, landmark_iterations: int | None = None,
                  damped: bool = False,
                  ) -> tuple[Calibration, np.ndarray, gtsam.NonlinearFactorGraph, gtsam.Values, int]:
    """One stage on the one stage runner (`lfgraph.engine.stage_engine.run_plan`): poses and intrinsics are variables;
    the groups in ``free`` are pulled to the design, the rest pinned at ``calib``; ``hold_gauges`` pins
    `selfcal_graph.intrinsics_gauges` too (intermediate stages: measured on paper-4x4 with 20 frames, releasing the
    common zoom before distortion was free let it absorb the unmodelled distortion and drift 25 % away, 110 px,
    beyond what 50 iterations walk back). Returns the calibration, landmarks, the graph, its optimum and the LM
    iterations. ``landmark_iterations``: None runs GTSAM's Levenberg–Marquardt; a number runs `lfgraph.engine.schur`'s
    with that many embedded point iterations per step (the final stage: from the staged start it walks the near-gauge
    valleys; from the design values, where landmarks start far off, GTSAM's loop is kept: on the 2x2 test rig the
    first stage in `lfgraph.engine.schur`'s loop, with or without embedded iterations, lost 95 % of its tracks behind
    the views). ``damped``: GTSAM's loop with Marquardt's diagonal damping (`OptimizerSettings.diagonal_damping`)."""
    pose_mean, pose_sigmas = selfcal_graph.pose_map_priors(calib.ref_T_view, design.ref_T_view, calib.grid.reference,
                                                           sigmas, free)
    pinned = selfcal_graph.intrinsics_gauges(calib.grid) if hold_gauges else None
    mean, sig = selfcal_graph.intrinsics_map_priors(calib.intrinsics, design.intrinsics[0], sigmas, free, pinned)
    priors = PriorTable(calib.grid.reference, pose_mean, pose_sigmas, mean, sig, calib.lenses)
    settings = OptimizerSettings(max_iterations=max_iterations, relative_error_tol=relative_tol,
                                 landmark_iterations=landmark_iterations or 0, diagonal_damping=damped)
    plan = StagePlan("+".join(sorted(free)), "selfcal", priors=priors,
                     settings=settings, frees=frozenset(map(Group, free)),
                     eliminate_landmarks=landmark_iterations is not None, tangential=False)
    out = run_plan(plan, calib, pixels, valid, points, model, callback, hooks)
    return out.calib, out.points, out.graph, out.values, out.iterations


def graph_landmarks(values: gtsam.Values) -> int:
    """Landmarks in a stage's values."""
    n = 0
    while values.exists(landmark_key(n)):
        n += 1
    return n


def zoom_to_prior(calib: Calibration, points: np.ndarray, design: Intrinsics) -> tuple[Calibration, np.ndarray]:
    """Move along the common-zoom gauge to where the focal-length priors are least strained.

    For parallel views the images do not change when every fx, fy is scaled by s, k1 by s^2, k2 by s^4, every
    landmark's depth and every view's z position by s. Levenberg–Marquardt walks this near-flat valley very slowly
    (measured: 150 iterations left paper-4x4's mean focal length 10 px from its optimum), so the final stage starts
    at the valley's MAP point s = sum(f_design f_v) / sum(f_v^2) over every fx and fy; it then refines the rest.
    Through a wide lens (fisheye, unified) there is no such valley (its angles pin the focal length): returned
    unchanged.
    """
    if lens_model(design.lens).wide:  # its angles pin the focal length
        return calib, points
    f = np.array([[i.fx, i.fy] for i in calib.intrinsics])
    scale = float(np.sum(design.fx * f[:, 0] + design.fy * f[:, 1]) / np.sum(f**2))
    intr = tuple(Intrinsics(i.fx * scale, i.fy * scale, i.cx, i.cy, i.k1 * scale**2, i.k2 * scale**4, i.p1, i.p2)
                 for i in calib.intrinsics)
    poses = np.array(calib.ref_T_view)
    poses[:, 2, 3] *= scale
    pts = np.array(points, dtype=float)
    pts[:, 2] *= scale
    return calib.replace(intrinsics=intr, ref_T_view=poses), pts


def robust_sigma(errors: np.ndarray) -> float:
    """Per-coordinate noise from (V, N) Euclidean reprojection errors: 1.4826 x MAD of a 2-D Rayleigh norm is
    converted through its median (sigma x sqrt(2 ln 2))."""
    e = errors[np.isfinite(errors)]
    if not len(e):
        return float("nan")
    return float(np.median(e) / np.sqrt(2.0 * np.log(2.0)))


def drop_outliers(calib: Calibration, pixels: np.ndarray, valid: np.ndarray,
                  points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The one mismatch rule (`lfgraph.engine.triangulate.drop_mismatches`); returns (keep, errors)."""
    errors = reprojection_errors(calib, points, pixels, valid)
    keep = drop_mismatches(errors)
    return keep, errors


def posterior(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, lenses: tuple[str, ...],
              points: tuple[int, ...] = (), poses: bool = False) -> tuple[Sigmas, np.ndarray]:
    """Marginal sigmas of every view's calibration and pose at the optimum (`Sigmas`, rescaled by nothing: the
    final stage uses the measured noise; each view's ``lenses`` model says its coefficients), and the (DV, DV) joint
    covariance of every view's calibration (views in order, each in its model's tangent order: D = 9, or 10 for
    Cal3Unified), followed by every view's pose (6 each, rotation first) when ``poses``, then by that of the Point3
    keys ``points`` (3 each: a pin's points) when given.

    The covariances are `lfgraph.engine.schur.CameraMarginals` (the one posterior path): the inverse of the reduced
    camera system (the same numbers as GTSAM's `Marginals`, computed once for both where `Marginals` eliminated every
    landmark twice; paper-4x4 with 20 frames: the whole graph 176 -> 134 s); a graph the Schur complement cannot
    reduce goes through `Marginals`.

    Raises:
        RuntimeError: the system is indeterminate (a parameter without information).
    """
    cal_keys = [calib_key(v) for v in range(len(lenses))]
    try:
        with gtsam_quiet():
            marginals = CameraMarginals(graph, values, LANDMARK_CHAR)
            pose_keys = [view_pose_key(v) for v in range(len(lenses))]
            joint = marginals.joint(cal_keys + (pose_keys if poses else []) + list(points))
            sigmas = Sigmas.from_marginals(marginals, cal_keys, pose_keys, lenses)
    except RuntimeError as exc:
        raise RuntimeError(f"the marginals failed (an undetermined parameter): {exc}") from exc
    return sigmas, np.asarray(joint)


def measurement(noise: Noise, sigma_px: float) -> gtsam.noiseModel.Base:
    """The measurement model of a stage (the kernel wrapped around ``sigma_px``)."""
    return measurement_noise(noise, sigma_px)


