"""The one builder of per-view prior factors (lfgraph.factors.prior_table) under both wings' priors."""

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from lfgraph.core.camera import Intrinsics
from lfgraph.factors.noise import GAUGE_SIGMA, MIN_SIGMA
from lfgraph.factors.prior_table import (
    calibration_vectors,
    intrinsics_prior_factors,
    pose_prior_factors,
)


def poses(n):
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, 0, 3] = 0.05 * np.arange(n)
    return out


def test_the_reference_is_the_gauge_a_nan_row_adds_nothing_and_sigmas_are_floored():
    sigmas = np.array([[0.01] * 6, [np.nan] * 6, [1e-12, 0.01, 0.01, 0.001, 0.001, 0.002]])
    graph = pose_prior_factors(0, poses(3), sigmas)
    assert graph.size() == 2  # view 1 is free without a pull
    gauge, view2 = graph.at(0), graph.at(1)
    np.testing.assert_allclose(gauge.noiseModel().sigmas(), GAUGE_SIGMA)  # not the row's 0.01
    np.testing.assert_allclose(view2.noiseModel().sigmas(), [MIN_SIGMA, 0.01, 0.01, 0.001, 0.001, 0.002])
    np.testing.assert_allclose(view2.prior().translation(), [0.1, 0.0, 0.0])


def test_intrinsics_priors_are_cal3ds2_rows():
    views = [Intrinsics(600.0, 601.0, 320.0, 240.0, -0.1, 0.02, 1e-4, -2e-4), Intrinsics(610.0, 611.0, 330, 250)]
    mean = calibration_vectors(views)  # radtan rows: the Cal3DS2 vector, NaN in the unified-only column
    sigmas = np.full(mean.shape, 1e-6)
    sigmas[1] = np.nan
    graph = intrinsics_prior_factors(mean, sigmas)
    assert graph.size() == 1
    np.testing.assert_allclose(graph.at(0).prior().vector(), [600.0, 601.0, 0.0, 320.0, 240.0, -0.1, 0.02, 1e-4,
                                                              -2e-4])
    assert isinstance(graph.at(0), gtsam.PriorFactorCal3DS2)


def test_shapes_a_lens_cannot_take_are_refused_by_name():
    with pytest.raises(ValueError, match="pose priors"):
        pose_prior_factors(0, poses(3), np.zeros((3, 5)))
    with pytest.raises(ValueError, match="intrinsics priors"):
        intrinsics_prior_factors(np.zeros((2, 9)), np.zeros((3, 9)))
    with pytest.raises(ValueError, match=r"view 0 \(unified\) needs 10 columns"):
        intrinsics_prior_factors(np.zeros((1, 9)), np.ones((1, 9)), ["unified"])


def test_each_view_gets_the_prior_of_its_own_lens_model():
    """A rig of three models: each view's prior is GTSAM's prior on its own calibration type, centred on the view's
    calibration (`Intrinsics.to_gtsam`), with the sigmas of its row in that model's tangent order."""
    views = [Intrinsics(600.0, 601.0, 320.0, 240.0, -0.1, 0.02, 1e-4, -2e-4),
             replace(Intrinsics(300.0, 301.0, 330.0, 250.0, 0.01, -0.002), k3=3e-4, k4=-1e-5, lens="fisheye"),
             replace(Intrinsics(500.0, 502.0, 310.0, 230.0, -0.2, 0.05, 1e-3, 2e-3), xi=0.9, lens="unified")]
    mean = calibration_vectors(views)
    sigmas = np.tile(np.arange(1.0, 11.0), (3, 1))
    graph = intrinsics_prior_factors(mean, sigmas, [v.lens for v in views])
    kinds = (gtsam.PriorFactorCal3DS2, gtsam.PriorFactorCal3Fisheye, gtsam.PriorFactorCal3Unified)
    for k, (view, kind) in enumerate(zip(views, kinds, strict=True)):
        factor = graph.at(k)
        assert isinstance(factor, kind)
        assert factor.prior().equals(view.to_gtsam(), 1e-12)
        n = 10 if view.lens == "unified" else 9
        np.testing.assert_allclose(factor.noiseModel().sigmas(), np.arange(1.0, n + 1.0))


def test_a_stage_plan_says_what_its_priors_are_as_data():
    from lfgraph.datasets.rig import RigConfig, make_rig
    from lfgraph.refinement.config import DriftModel, Stage
    from lfgraph.refinement.priors import view_priors
    from lfgraph.refinement.stages import stage_plan

    rig = make_rig(RigConfig(rows=2, cols=2), np.random.default_rng(0))
    drift = view_priors(rig, DriftModel())
    poses = stage_plan(Stage.POSES, rig, priors=drift)
    table = poses.priors
    free = [v for v in range(rig.num_views) if v != rig.grid.reference]
    np.testing.assert_array_equal(table.pose_sigmas[free], drift.pose_sigmas[free])  # the drift model's sigmas
    np.testing.assert_array_equal(table.pose_mean, drift.centre.ref_T_view)  # centred on the input
    assert table.intrinsics_sigmas is None  # a poses stage holds the intrinsics as constants
    assert table.graph.size() == rig.num_views + 1  # one pose prior per view, and the range gauge
    every = stage_plan(Stage.ALL, rig, priors=drift).priors
    np.testing.assert_array_equal(every.intrinsics_sigmas[free][:, [0, 1, 3, 4]], drift.intrinsics_sigmas[free])
    assert every.graph.size() == 2 * rig.num_views + 1
    assert stage_plan(Stage.POINTS, rig, priors=drift).priors.graph.size() == 0
