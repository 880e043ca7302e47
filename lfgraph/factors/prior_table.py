"""The one builder of a stage's per-view prior factors, below both staged-MAP wings.

A wing says what its priors are as arrays, one row per view — the refinement's drift priors centred on the input
calibration (`lfgraph.factors.scene_graph.pose_priors`, `intrinsics_priors`), a self-calibration's design priors
(`lfgraph.factors.selfcal_graph.pose_map_priors`, `intrinsics_map_priors`) — and these functions turn the rows into
GTSAM factors: the reference view's pose is the gauge (`gauge_pose_noise`); every other row is a
``PriorFactorPose3`` / a prior on the view's calibration of its own lens (``PriorFactorCal3DS2``, ``…Cal3Fisheye``,
``…Cal3Unified``) with diagonal sigmas (floored at ``MIN_SIGMA``); a row of NaN sigmas adds no factor (a view free
without a pull). A held parameter is a sigma of ``HELD_SIGMA``, a group a stage frees is a row's columns
(`lfgraph.factors.groups`). Intrinsics rows are in GTSAM's tangent order, which the three models share up to their
distortion: fx fy s cx cy, then k1 k2 p1 p2 (radtan), k1 k2 k3 k4 (fisheye) or k1 k2 p1 p2 xi (unified), NaN-padded
to `CAL_TANGENT_MAX` columns.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import gtsam
import numpy as np

from lfgraph.core.camera import Intrinsics
from lfgraph.core.geometry import to_pose3
from lfgraph.factors.keys import calib_key, view_pose_key
from lfgraph.factors.noise import calibration_noise, gauge_pose_noise, pose_noise
from lfgraph.lenses import DEFAULT_LENS, lens_model

POSE_TANGENT = 6  # rotation x y z (rad, body frame), then position x y z (m): GTSAM's Pose3 tangent order
CAL_TANGENT_MAX = 10  # the largest lens model's calibration tangent (Cal3Unified; `LensModel.tangent_size`)


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


def calibration_vectors(intrinsics: list[Intrinsics] | tuple[Intrinsics, ...]) -> np.ndarray:
    """(V, `CAL_TANGENT_MAX`) each view's calibration in its lens's tangent order (skew 0; NaN beyond its size)."""
    out = np.full((len(intrinsics), CAL_TANGENT_MAX), np.nan)
    for v, i in enumerate(intrinsics):
        row = i.model.vector(i)
        out[v, :len(row)] = row
    return out


def intrinsics_prior_factors(mean: np.ndarray, sigmas: np.ndarray,
                             lenses: list[str] | tuple[str, ...] | None = None) -> gtsam.NonlinearFactorGraph:
    """One calibration prior per view, of its lens model: ``mean`` (V, >= the lens's tangent size) calibration
    vectors (`calibration_vectors`) with their ``sigmas`` (same shape; px and
    unitless coefficients; a NaN row: no prior); ``lenses`` each view's model (all radtan when None)."""
    _check(mean.shape, sigmas.shape, "intrinsics")
    lenses = [DEFAULT_LENS] * len(mean) if lenses is None else list(lenses)
    graph = gtsam.NonlinearFactorGraph()
    for v, lens in enumerate(lenses):
        model = lens_model(lens)
        n = model.tangent_size
        if mean.shape[1] < n:
            raise ValueError(f"intrinsics priors: view {v} ({lens}) needs {n} columns, got {mean.shape[1]}")
        if np.any(np.isnan(sigmas[v, :n])):
            continue
        graph.add(model.gtsam("PriorFactor")(calib_key(v), model.gtsam()(*mean[v, :n].tolist()),
                                             calibration_noise(sigmas[v, :n])))
    return graph


@dataclass(frozen=True)
class PriorTable:
    """A stage's priors as data, what a `lfgraph.engine.stage_engine.StagePlan` carries: the reference view (the
    gauge), each view's pose ``pose_mean`` (V, 4, 4) ``ref_T_view`` and ``pose_sigmas`` (V, 6; rad, m, Pose3 tangent
    order), each view's calibration ``intrinsics_mean`` / ``intrinsics_sigmas`` (V, `CAL_TANGENT_MAX`, its lens's
    tangent order, `calibration_vectors`) under ``lenses``, and ``gauges``: factors that are no prior on one view (a
    range fixing scale). Held parameters are sigmas of ``HELD_SIGMA``, a view free without a pull a NaN row; None: no
    such priors (the points stage). `graph` renders it: pose priors, the gauges, calibration priors."""
    reference: int
    pose_mean: np.ndarray | None = field(default=None, repr=False)
    pose_sigmas: np.ndarray | None = None
    intrinsics_mean: np.ndarray | None = field(default=None, repr=False)
    intrinsics_sigmas: np.ndarray | None = None
    lenses: tuple[str, ...] = ()
    gauges: gtsam.NonlinearFactorGraph | None = field(default=None, repr=False)

    @cached_property
    def graph(self) -> gtsam.NonlinearFactorGraph:
        """The GTSAM factors (`pose_prior_factors`, the gauges, `intrinsics_prior_factors`), built once."""
        graph = gtsam.NonlinearFactorGraph()
        if self.pose_sigmas is not None:
            graph.push_back(pose_prior_factors(self.reference, self.pose_mean, self.pose_sigmas))
        if self.gauges is not None:
            graph.push_back(self.gauges)
        if self.intrinsics_sigmas is not None:
            graph.push_back(intrinsics_prior_factors(self.intrinsics_mean, self.intrinsics_sigmas, self.lenses))
        return graph


def _check(shape: tuple, expected: tuple, what: str) -> None:
    if tuple(shape) != tuple(expected):
        raise ValueError(f"{what} priors: shape {tuple(shape)} where {tuple(expected)} was expected")
