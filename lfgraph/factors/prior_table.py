"""The one builder of a stage's per-view prior factors, below both staged-MAP wings.

A wing says what its priors are as arrays, one row per view — the refinement's drift priors centred on the input
calibration (`lfgraph.factors.scene_graph.pose_priors`, `intrinsics_priors`), a self-calibration's design priors
(`lfgraph.factors.selfcal_graph.pose_map_priors`, `intrinsics_map_priors`) — and these functions turn the rows into
GTSAM factors: the reference view's pose is the gauge (`gauge_pose_noise`); every other row is a
``PriorFactorPose3`` / ``PriorFactorCal3DS2`` with diagonal sigmas (`pose_noise`, `cal3ds2_noise`: floored at
``MIN_SIGMA``); a row of NaN sigmas adds no factor (a view free without a pull). A held parameter is a sigma of
``HELD_SIGMA``, a group a stage frees is a row's columns (`lfgraph.factors.groups`).
"""

from __future__ import annotations

import gtsam
import numpy as np

from lfgraph.camera import RADTAN, Intrinsics
from lfgraph.factors.keys import calib_key, view_pose_key
from lfgraph.factors.noise import cal3ds2_noise, gauge_pose_noise, pose_noise
from lfgraph.geometry import to_pose3

POSE_TANGENT = 6  # rotation x y z (rad, body frame), then position x y z (m): GTSAM's Pose3 tangent order
CAL3DS2_TANGENT = 9  # fx fy s cx cy k1 k2 p1 p2


def cal3ds2_vectors(intrinsics: list[Intrinsics] | tuple[Intrinsics, ...]) -> np.ndarray:
    """(V, 9) Cal3DS2 vectors (fx fy s cx cy k1 k2 p1 p2; skew 0) of radtan views.

    Raises:
        ValueError: a view of another lens model (its intrinsics are not a Cal3DS2).
    """
    other = [v for v, i in enumerate(intrinsics) if i.lens != RADTAN]
    if other:
        raise ValueError(f"Cal3DS2 priors need radtan views; views {other} are "
                         f"{', '.join(sorted({intrinsics[v].lens for v in other}))}")
    return np.array([[i.fx, i.fy, 0.0, i.cx, i.cy, i.k1, i.k2, i.p1, i.p2] for i in intrinsics], dtype=np.float64)


def pose_prior_factors(reference: int, mean: np.ndarray, sigmas: np.ndarray) -> gtsam.NonlinearFactorGraph:
    """One pose prior per view: the reference view's the gauge, every other view's ``mean`` (V, 4, 4)
    ``ref_T_view`` with its row of ``sigmas`` (V, 6; rad, m; a NaN row: no prior)."""
    _check(sigmas.shape, (len(mean), POSE_TANGENT), "pose")
    graph = gtsam.NonlinearFactorGraph()
    for v in range(len(mean)):
        if v == reference:
            graph.add(gtsam.PriorFactorPose3(view_pose_key(v), to_pose3(mean[v]), gauge_pose_noise()))
        elif not np.any(np.isnan(sigmas[v])):
            graph.add(gtsam.PriorFactorPose3(view_pose_key(v), to_pose3(mean[v]),
                                             pose_noise(sigmas[v, :3], sigmas[v, 3:])))
    return graph


def intrinsics_prior_factors(mean: np.ndarray, sigmas: np.ndarray) -> gtsam.NonlinearFactorGraph:
    """One Cal3DS2 prior per view: ``mean`` (V, 9) Cal3DS2 vectors with their ``sigmas`` (V, 9; px and unitless
    coefficients; a NaN row: no prior)."""
    _check(mean.shape, sigmas.shape, "intrinsics")
    _check(mean.shape[1:], (CAL3DS2_TANGENT,), "intrinsics")
    graph = gtsam.NonlinearFactorGraph()
    for v in range(len(mean)):
        if not np.any(np.isnan(sigmas[v])):
            graph.add(gtsam.PriorFactorCal3DS2(calib_key(v), gtsam.Cal3DS2(*mean[v].tolist()),
                                               cal3ds2_noise(sigmas[v])))
    return graph


def _check(shape: tuple, expected: tuple, what: str) -> None:
    if tuple(shape) != tuple(expected):
        raise ValueError(f"{what} priors: shape {tuple(shape)} where {tuple(expected)} was expected")
