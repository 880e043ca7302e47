"""The Schur-complement Levenberg–Marquardt (lfgraph.engine.schur) against GTSAM's own optimiser and marginals, and the
bulk projections of the points/poses stages against GTSAM's factors."""

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from lfgraph.core.camera import project_world, undistort_views
from lfgraph.core.geometry import make_T, rotation_from_rotvec
from lfgraph.datasets.rig import RigConfig, ShakeConfig, make_rig, shake_rig
from lfgraph.engine.optimize import OptimizerSettings, optimize
from lfgraph.engine.schur import marginal_covariance, problem_covariance
from lfgraph.engine.schur_system import camera_block, chol3_inv
from lfgraph.engine.triangulate import triangulate_dlt
from lfgraph.factors.keys import LANDMARK_CHAR, landmark_key, view_pose_key
from lfgraph.factors.noise import RobustKernel, measurement_noise
from lfgraph.refinement import Stage
from lfgraph.refinement.config import DriftModel
from lfgraph.refinement.priors import view_priors
from lfgraph.refinement.stages import run_stage, stage_graph, stage_problem

SAME_SOLUTION = 1e-9  # rad and m: the same minimum as GTSAM's optimiser (same LM, different linear solver)
SAME_COVARIANCE = 1e-6  # relative: the reduced camera system's inverse vs GTSAM's Marginals
STAGE_TOL_OFFSET = 1e-6  # rad and m: the bulk stage stops at REFINE_RELATIVE_TOL, GTSAM's path at 1e-10
SAME_UNDISTORT = 1e-14  # normalised units: one Newton loop for all views vs one per view
ONE_PLACE_TRACKS = 40
ONE_PLACE_DEPTH_SIGMA_M = 1.0  # GTSAM's reference: this prior on such landmarks (at 3 m it is indeterminate)
ONE_PLACE_COVARIANCE = 1e-7  # relative: the prior's effect falls as 1 / sigma^2 (3.8e-8 at 0.3 m, 3.4e-9 at 1 m)


def scene(seed=0, n=150, reference=0, tangential=0.0, lens="radtan"):
    wide = {"fisheye": dict(lens="fisheye", k1=-0.02, k2=0.005), "unified": dict(lens="unified", xi=0.9, k1=-0.1,
                                                                                k2=0.02)}.get(lens, {})
    rig = make_rig(RigConfig(rows=3, cols=3, reference=reference, pitch_m=0.05, image_size_px=(512, 512),
                             focal_px=600.0, **wide), np.random.default_rng(seed))
    if tangential:  # p1, p2 of every lens: the bulk projections must carry GTSAM's Cal3DS2 terms for them too
        rig = rig.replace(intrinsics=[replace(i, p1=tangential, p2=-0.5 * tangential) for i in rig.intrinsics])
    truth = shake_rig(rig, ShakeConfig(rot_deg=0.5, trans_mm=2.0), np.random.default_rng(seed + 1))
    rng = np.random.default_rng(seed + 2)
    depth = rng.uniform(1.5, 5.0, n)
    pts = np.column_stack([rng.uniform(-0.3, 0.3, (n, 2)) * depth[:, None], depth])
    pix = np.stack([project_world(truth.intrinsics[v], truth.view_T_ref(v), pts) for v in range(9)])
    pix += 0.05 * rng.standard_normal(pix.shape)
    valid = np.ones(pix.shape[:2], dtype=bool)
    valid[rng.integers(0, 9, 40), rng.integers(0, n, 40)] = False  # not every landmark in every view
    valid[rig.grid.reference] = True
    return rig, pix, valid


def gtsam_route(ctx):
    """A hook whose factor sits on a landmark (a prior of 1 km on landmark 0: no information) sends the stage down
    GTSAM's factor route: the reference the bulk route is compared with."""
    key = landmark_key(0)
    if ctx.initial.exists(key):
        ctx.graph.add(gtsam.PriorFactorPoint3(key, ctx.initial.atPoint3(key), gtsam.noiseModel.Isotropic.Sigma(3, 1e3)))
    else:  # the bulk route's camera graph: ask for the landmark, which it cannot give
        ctx.graph.add(gtsam.PriorFactorPoint3(key, np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, 1e3)))


def test_schur_lm_reaches_gtsams_minimum_and_marginals():
    rig, pix, valid = scene()
    points = triangulate_dlt(rig, pix, valid)
    model = measurement_noise(RobustKernel("none"), 0.05)
    priors = view_priors(rig, DriftModel())
    graph, values = stage_graph(Stage.POSES, rig, pix, valid, points, model, priors=priors)
    ours = optimize(graph, values, OptimizerSettings(), eliminate=LANDMARK_CHAR)
    theirs = optimize(graph, values, OptimizerSettings())
    assert abs(ours.final_error - theirs.final_error) <= 1e-9 * theirs.final_error
    for v in range(rig.num_views):
        d = ours.values.atPose3(view_pose_key(v)).localCoordinates(theirs.values.atPose3(view_pose_key(v)))
        assert np.max(np.abs(d)) < SAME_SOLUTION
    cov, layout = marginal_covariance(graph, theirs.values, LANDMARK_CHAR)
    marginals = gtsam.Marginals(graph, theirs.values)
    for v in (1, 5, 8):
        block = camera_block(layout, view_pose_key(v))
        expected = marginals.marginalCovariance(view_pose_key(v))
        assert np.max(np.abs(cov[block, block] - expected)) < SAME_COVARIANCE * np.max(np.abs(expected))


@pytest.mark.parametrize("lens", ["radtan", "fisheye", "unified"])
def test_bulk_projections_match_gtsam_factors(lens):
    """The points and poses stages on the bulk path reach the minimum of GTSAM's own factors for each lens model
    (Cal3DS2; Cal3Fisheye and Cal3Unified: issue 25), with GTSAM's marginals."""
    rig, pix, valid = scene(seed=5, lens=lens)
    assert {i.lens for i in rig.intrinsics} == {lens}
    points = triangulate_dlt(rig, pix, valid)
    noise = RobustKernel("none")
    priors = view_priors(rig, DriftModel())

    for stage in (Stage.POINTS, Stage.POSES):
        bulk_calib, bulk_pts, _ = run_stage(stage, rig, pix, valid, points, noise, 0.05, priors=priors)
        graph_calib, graph_pts, _ = run_stage(stage, rig, pix, valid, points, noise, 0.05, priors=priors,
                                              hooks=(gtsam_route,))
        np.testing.assert_allclose(bulk_calib.ref_T_view, graph_calib.ref_T_view, atol=STAGE_TOL_OFFSET)
        np.testing.assert_allclose(bulk_pts, graph_pts, atol=STAGE_TOL_OFFSET * 10)
    # and its posterior is GTSAM's
    model = measurement_noise(noise, 0.05)
    problem, state = stage_problem(Stage.POSES, rig, pix, valid, points, model, priors=priors)
    assert (problem.obs_lens is None) == (lens == "radtan")  # wide lenses: the general projections, not the shortcut
    cov = problem_covariance(problem, state)
    graph, values = stage_graph(Stage.POSES, rig, pix, valid, points, model, priors=priors)
    marginals = gtsam.Marginals(graph, values)
    block = camera_block(problem.layout, view_pose_key(4))
    expected = marginals.marginalCovariance(view_pose_key(4))
    assert np.max(np.abs(cov[block, block] - expected)) < SAME_COVARIANCE * np.max(np.abs(expected))


def test_schur_solver_on_gtsams_robust_factors_reaches_gtsams_minimum():
    rig, pix, valid = scene(seed=7)
    points = triangulate_dlt(rig, pix, valid)
    model = measurement_noise(RobustKernel.parse("huber:1.345sigma"), 0.05)
    graph, values = stage_graph(Stage.POSES, rig, pix, valid, points, model, priors=view_priors(rig, DriftModel()))
    ours = optimize(graph, values, OptimizerSettings(), eliminate=LANDMARK_CHAR)
    theirs = optimize(graph, values, OptimizerSettings())
    for v in range(rig.num_views):
        d = ours.values.atPose3(view_pose_key(v)).localCoordinates(theirs.values.atPose3(view_pose_key(v)))
        assert np.max(np.abs(d)) < SAME_SOLUTION


@pytest.mark.parametrize("reference", [0, 4])
def test_bulk_stage_without_priors_matches_gtsam(reference):
    """No drift priors: the priors/gauges graph touches only some views (the reference's pose, the range gauge), so
    its Jacobian has fewer columns than the values; they must land on the right views. Tangential distortion on."""
    rig, pix, valid = scene(seed=11, reference=reference, tangential=2e-3)
    points = triangulate_dlt(rig, pix, valid)
    noise = RobustKernel("none")

    bulk_calib, _, _ = run_stage(Stage.POSES, rig, pix, valid, points, noise, 0.05)
    graph_calib, _, _ = run_stage(Stage.POSES, rig, pix, valid, points, noise, 0.05, hooks=(gtsam_route,))
    np.testing.assert_allclose(bulk_calib.ref_T_view, graph_calib.ref_T_view, atol=STAGE_TOL_OFFSET)
    model = measurement_noise(noise, 0.05)
    problem, state = stage_problem(Stage.POSES, rig, pix, valid, points, model)
    cov = problem_covariance(problem, state)
    graph, values = stage_graph(Stage.POSES, rig, pix, valid, points, model)
    marginals = gtsam.Marginals(graph, values)
    for v in range(rig.num_views):
        if v == reference:
            continue
        block = camera_block(problem.layout, view_pose_key(v))
        expected = marginals.marginalCovariance(view_pose_key(v))
        assert np.max(np.abs(cov[block, block] - expected)) < SAME_COVARIANCE * np.max(np.abs(expected))


def test_bulk_stage_with_no_landmarks_keeps_the_poses():
    rig, pix, valid = scene(seed=3)
    calib, points, _ = run_stage(Stage.POSES, rig, pix[:, :0], valid[:, :0], np.zeros((0, 3)), RobustKernel("none"),
                                 0.05, priors=view_priors(rig, DriftModel()))
    np.testing.assert_allclose(calib.ref_T_view, rig.ref_T_view, atol=SAME_SOLUTION)
    assert points.shape == (0, 3)


def test_undistort_views_matches_the_method():
    rig, pix, valid = scene(seed=9)
    pix = np.where(valid[..., None], pix, np.nan)
    out = undistort_views(rig.intrinsics, pix)
    for v in range(rig.num_views):
        m = valid[v]
        np.testing.assert_allclose(out[v, m], rig.intrinsics[v].undistort(pix[v, m]), atol=SAME_UNDISTORT)
        assert np.all(np.isnan(out[v, ~m]))



@pytest.mark.slow
def test_embedded_point_iterations_reach_the_same_minimum_from_a_landmark_far_off():
    rig, pix, valid = scene()
    points = triangulate_dlt(rig, pix, valid)
    points[0] *= 20.0  # 20x its depth: the first Gauss–Newton re-solve of it overshoots and must be undone
    model = measurement_noise(RobustKernel("none"), 0.05)
    graph, values = stage_graph(Stage.POSES, rig, pix, valid, points, model, priors=view_priors(rig, DriftModel()))
    # plain LM walks the far landmark back in ~108 iterations since the neighbour's pan is free (issue 24: not a
    # gauge with the intrinsics held); the embedded iterations in ~80
    plain = optimize(graph, values, OptimizerSettings(max_iterations=300), eliminate=LANDMARK_CHAR)
    embedded = optimize(graph, values, OptimizerSettings(landmark_iterations=2), eliminate=LANDMARK_CHAR)
    assert abs(embedded.final_error - plain.final_error) <= 1e-9 * plain.final_error
    for v in range(rig.num_views):
        d = embedded.values.atPose3(view_pose_key(v)).localCoordinates(plain.values.atPose3(view_pose_key(v)))
        assert np.max(np.abs(d)) < SAME_SOLUTION


def test_the_decrease_still_to_come_of_a_geometric_sequence_is_its_tail():
    """A robust stage's second stop (`schur._left_to_gain`): decreases 8, 4, 2 of a cost whose decreases halve leave
    2 more (1 + 0.5 + ...); decreases that do not shrink leave an unknown amount (no stop)."""
    from lfgraph.engine.schur import _left_to_gain

    assert _left_to_gain([20.0, 12.0, 8.0, 6.0]) == pytest.approx(2.0)
    assert _left_to_gain([20.0, 12.0, 8.0, 4.0]) == float("inf")  # 4 then 4: not shrinking
    assert _left_to_gain([20.0, 12.0]) == float("inf")  # one decrease says nothing of the next


CHOLESKY_ATOL = 1e-8  # |L^-1 V L^-T - I| of the closed-form factors, for blocks of condition up to ~1e6 (a landmark
# seen over a narrow baseline: its depth ~1000x less certain than its direction)


def test_closed_form_landmark_cholesky_factors_the_blocks_and_refuses_indefinite_ones():
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.normal(size=(50, 3, 3)))
    scales = 10.0 ** rng.uniform(-1.0, 5.0, size=(50, 3))  # eigenvalues 0.1 .. 1e5: condition up to 1e6
    blocks = q @ (scales[:, :, None] * np.swapaxes(q, 1, 2))
    inverse = chol3_inv(blocks)
    assert np.allclose(np.triu(inverse, 1), 0.0)  # lower triangular
    whitened = inverse @ blocks @ np.swapaxes(inverse, 1, 2)
    assert np.max(np.abs(whitened - np.eye(3))) < CHOLESKY_ATOL
    indefinite = blocks.copy()
    indefinite[7] = np.diag([1.0, -1.0, 1.0])
    with pytest.raises(np.linalg.LinAlgError):
        chol3_inv(indefinite)


def test_marginals_of_tracks_seen_from_one_place_match_gtsams_with_a_weak_depth_prior():
    """A track of two views at one place (templeSparseRing captured view 0 twice, as views 0 and 10) has no depth:
    its landmark block is singular, and rounding leaves its determinant a hair above or below zero. Those blocks are
    marginalised by their pseudo-inverse: the cameras' covariance is the limit of GTSAM's with a weak prior on such
    landmarks' positions, where GTSAM's Marginals without it finds the system indeterminate."""
    rig, pix, valid = scene(seed=3)
    poses = rig.ref_T_view.copy()
    poses[2] = make_T(rotation_from_rotvec([0.0, 0.01, 0.02]), poses[0][:3, 3])  # view 2 stands where view 0 does
    rig = rig.replace(ref_T_view=poses)
    rng = np.random.default_rng(4)
    depth = rng.uniform(1.5, 5.0, ONE_PLACE_TRACKS)
    pts = np.column_stack([rng.uniform(-0.2, 0.2, (ONE_PLACE_TRACKS, 2)) * depth[:, None], depth])
    pts = np.concatenate([triangulate_dlt(rig, pix, valid), pts])
    pix = np.stack([project_world(rig.intrinsics[v], rig.view_T_ref(v), pts) for v in range(9)])
    one_place = np.zeros(len(pts), dtype=bool)
    one_place[-ONE_PLACE_TRACKS:] = True
    valid = np.concatenate([valid, np.zeros((9, ONE_PLACE_TRACKS), dtype=bool)], axis=1)
    valid[np.ix_([0, 2], np.flatnonzero(one_place))] = True
    model = measurement_noise(RobustKernel("none"), 0.05)
    priors = view_priors(rig, DriftModel())
    problem, state = stage_problem(Stage.POSES, rig, pix, valid, pts, model, priors=priors)
    cov = problem_covariance(problem, state)
    graph, values = stage_graph(Stage.POSES, rig, pix, valid, pts, model, priors=priors)
    weak = gtsam.noiseModel.Isotropic.Sigma(3, ONE_PLACE_DEPTH_SIGMA_M)
    for i in np.flatnonzero(one_place):
        graph.add(gtsam.PriorFactorPoint3(landmark_key(int(i)), pts[i], weak))
    marginals = gtsam.Marginals(graph, values)
    for v in (1, 2, 5):
        block = camera_block(problem.layout, view_pose_key(v))
        expected = marginals.marginalCovariance(view_pose_key(v))
        assert np.max(np.abs(cov[block, block] - expected)) < ONE_PLACE_COVARIANCE * np.max(np.abs(expected))
