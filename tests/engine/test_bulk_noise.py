"""Noise models in bulk (lfgraph.engine.bulk_noise) against GTSAM's own: the M-estimators' weight and loss, the
whitening and robust reweighting of residuals, and the refinement's bulk stages with a robust kernel, a user's
Gaussian model or a user's hook against GTSAM's factors and GTSAM's own Levenberg–Marquardt."""

import gtsam
import numpy as np
import pytest

from lfgraph.datasets.rig import ShakeConfig, shake_rig
from lfgraph.engine.bulk_noise import BulkNoise, Kernel, NotBulk, vectorised_estimator
from lfgraph.engine.kernel_table import TABLE_RTOL
from lfgraph.engine.optimize import OptimizerSettings, optimize
from lfgraph.engine.schur import GraphProblem, optimize_problem
from lfgraph.engine.stage_engine import START_WEIGHT_MIN, least_squares_start
from lfgraph.engine.triangulate import reprojection_errors, triangulate_dlt
from lfgraph.factors.keys import view_pose_key
from lfgraph.factors.noise import RobustKernel, measurement_noise, pose_noise
from lfgraph.judge.evaluation import evaluate_calibration
from lfgraph.refinement import Stage, stages
from lfgraph.refinement.config import DriftModel
from lfgraph.refinement.priors import view_priors
from lfgraph.refinement.stages import run_stage, stage_graph, stage_problem
from tests.engine.test_schur import gtsam_route, scene

M = gtsam.noiseModel.mEstimator
BLOCK, SCALAR = M.Base.ReweightScheme.Block, M.Base.ReweightScheme.Scalar
SAME_FORMULA = 1e-12  # relative: numpy's kernel formulas vs GTSAM's C++ ones
SAME_SYSTEM = 1e-9  # relative: the bulk normal equations vs GTSAM's linearised factors, at one state
SAME_MINIMUM = 1e-6  # relative: the final cost of the bulk LM vs GTSAM's own LM, both converged (the goal)
SAME_POSE = 1e-6  # rad and m: the poses at that minimum
SIGMA_PX = 0.05
OUTLIER_PX = 3.0  # 60 sigma: 10 tracks of the scene moved by this in every view


def cauchy_custom():
    """Cauchy (k = 2) written as Python callbacks: a user's own estimator."""
    return M.Custom.Create(lambda d: 4.0 / (4.0 + d * d), lambda d: 2.0 * np.log1p(d * d / 4.0))


ESTIMATORS = {
    "huber": lambda s: M.Huber.Create(1.345, s),
    "cauchy": lambda s: M.Cauchy.Create(2.385, s),
    "tukey": lambda s: M.Tukey.Create(4.685, s),
    "geman-mcclure": lambda s: M.GemanMcClure.Create(1.5, s),
    "dcs": lambda s: M.DCS.Create(1.2, s),
    "welsch": lambda s: M.Welsch.Create(2.985, s),
    "fair": lambda s: M.Fair.Create(1.3998, s),
    "null": lambda s: M.Null.Create(),  # GTSAM gives it no scheme (Block)
}


@pytest.mark.parametrize("name", sorted(ESTIMATORS))
@pytest.mark.parametrize("scheme", [BLOCK, SCALAR])
def test_kernel_formulas_are_gtsams(name, scheme):
    est = ESTIMATORS[name](scheme)
    kernel = Kernel(est)
    assert kernel.vectorised  # the fast formulas, not per-residual calls
    assert kernel.block == (scheme == BLOCK or name == "null")
    d = np.concatenate([[0.0], np.geomspace(1e-3, 100.0, 200)])
    np.testing.assert_allclose(kernel.weights(d), [est.weight(x) for x in d], rtol=SAME_FORMULA, atol=1e-15)
    np.testing.assert_allclose(kernel.losses(d), [est.loss(x) for x in d], rtol=SAME_FORMULA, atol=1e-15)


BOUNDED = {"tukey", "geman-mcclure", "welsch", "dcs"}  # the redescenders whose loss levels off


@pytest.mark.parametrize("name", sorted(ESTIMATORS))
def test_bounded_losses_are_told_apart(name):
    assert Kernel(ESTIMATORS[name](BLOCK)).bounded == (name in BOUNDED)


KNOCK_DEG = 0.5  # test_schur.scene: the truth is this far (and 2 mm) from the rig refined from: ~5 px, 100 sigmas
REPAIRED_DEG = 0.02  # worst view rotation error after one poses stage (the Gaussian fit's is ~0.01 deg)
SAME_ROUTE_RAD = 1e-5  # the bulk and GTSAM routes' rotations under one bounded loss


def test_a_bounded_loss_starts_from_the_least_squares_minimum():
    """A bounded loss (Tukey) is started from the minimum under its Gaussian part, by both routes, and reaches the
    truth; an unbounded one (Cauchy) and a Gaussian start where the stage starts. (On the refine benchmark's
    paper-5x5 knock, Tukey started at the input weighted every track of a knocked view zero and kept the input.)"""
    tukey = measurement_noise(RobustKernel.parse("tukey"), SIGMA_PX)
    assert least_squares_start(tukey).equals(tukey.noise(), 1e-12)
    assert least_squares_start(measurement_noise(RobustKernel.parse("cauchy"), SIGMA_PX)) is None
    assert least_squares_start(measurement_noise(RobustKernel.parse("none"), SIGMA_PX)) is None
    rig, pix, valid = scene(seed=5)
    truth = shake_rig(rig, ShakeConfig(rot_deg=KNOCK_DEG, trans_mm=2.0), np.random.default_rng(6))
    points = triangulate_dlt(rig, pix, valid)
    assert np.max(evaluate_calibration(rig, truth).rotation_deg) > KNOCK_DEG / 2
    fits = [run_stage(Stage.POSES, rig, pix, valid, points, RobustKernel.parse("tukey"), SIGMA_PX, hooks=hooks)[0]
            for hooks in ((), (gtsam_route,))]
    for fit in fits:
        assert np.max(evaluate_calibration(fit, truth).rotation_deg) < REPAIRED_DEG
    np.testing.assert_allclose(fits[0].ref_T_view[:, :3, :3], fits[1].ref_T_view[:, :3, :3], atol=SAME_ROUTE_RAD)


def test_a_start_within_a_bounded_kernels_reach_is_told_from_a_knocked_one():
    """`ProjectionProblem.typical_weights`, which lets a bounded kernel's stage start where it is: the kernel's weight
    at each view's median whitened reprojection error (computed here from `reprojection_errors`); above
    `START_WEIGHT_MIN` for every view at the truth, below it for a knocked view."""
    rig, pix, valid = scene(seed=5)
    truth = shake_rig(rig, ShakeConfig(rot_deg=KNOCK_DEG, trans_mm=2.0), np.random.default_rng(6))
    model = measurement_noise(RobustKernel.parse("tukey"), SIGMA_PX)
    kernel = Kernel(model.robust())
    for calib in (truth, rig):
        points = triangulate_dlt(calib, pix, valid)
        problem, state = stage_problem(Stage.POSES, calib, pix, valid, points, model)
        errors = reprojection_errors(calib, points, pix, valid) / SIGMA_PX
        expected = kernel.weights(np.array([np.median(e[np.isfinite(e)]) for e in errors]))
        np.testing.assert_allclose(problem.typical_weights(state), expected, rtol=1e-9)
        assert (np.min(expected) >= START_WEIGHT_MIN) == (calib is truth)


def cauchy_arrays():
    """Cauchy (k = 2) of your own, written for arrays: `vectorised_estimator`."""
    return vectorised_estimator(lambda d: 4.0 / (4.0 + d * d), lambda d: 2.0 * np.log1p(d * d / 4.0))


def test_a_kernel_of_your_own_written_for_arrays_runs_on_arrays():
    est = cauchy_arrays()
    kernel = Kernel(est)
    assert kernel.vectorised and kernel.block
    d = np.geomspace(1e-3, 100.0, 50)
    np.testing.assert_allclose(kernel.weights(d), [est.weight(x) for x in d], rtol=SAME_FORMULA)
    np.testing.assert_allclose(kernel.losses(d), [est.loss(x) for x in d], rtol=SAME_FORMULA)
    assert Kernel(vectorised_estimator(lambda d: 1.0 / (1.0 + d * d), lambda d: 0.5 * np.log1p(d * d),
                                       scheme="scalar")).block is False
    # functions that only take numbers are found out and run from a table of their values (kinked at 1: called
    # there), exactly
    scalar_only = vectorised_estimator(lambda d: 1.0 if d < 1.0 else 1.0 / d,
                                       lambda d: 0.5 * d * d if d < 1.0 else d - 0.5)
    kernel = Kernel(scalar_only)
    assert kernel.tabulated
    np.testing.assert_allclose(kernel.weights(np.array([0.5, 1.0, 4.0])), [1.0, 1.0, 0.25], rtol=TABLE_RTOL)
    constant = Kernel(vectorised_estimator(lambda d: 1.0, lambda d: 0.5 * d * d))  # a constant weight, broadcast
    assert constant.vectorised and constant.weights(np.array([1.0, 2.0])).tolist() == [1.0, 1.0]
    with pytest.raises(ValueError, match="scheme"):
        vectorised_estimator(np.ones_like, np.ones_like, scheme="rows")
    # issue 42: refused at the door, not deep in a solve
    with pytest.raises(TypeError, match="weight must be a function"):
        vectorised_estimator(None, None)
    with pytest.raises(ValueError, match=r"weight\(d\) must be finite and >= 0"):
        vectorised_estimator(lambda d: -np.ones_like(d), lambda d: 0.5 * d * d)


def counted(f, calls):
    def g(d):
        calls.append(d)
        return f(d)
    return g


def test_a_custom_estimator_of_scalar_callbacks_runs_from_a_table_of_its_values():
    """A ``Custom`` of Python callbacks is tabulated (`lfgraph.engine.kernel_table`): the table matches the callbacks to
    `TABLE_RTOL` everywhere, signed distances and far ones included, with no callback once built; where a cell does
    not match (a kink) the callbacks answer; a function that is not finite somewhere is called per residual."""
    rng = np.random.default_rng(3)
    d = np.concatenate([rng.standard_normal(20000) * 3.0, rng.uniform(-1e5, 1e5, 500), [0.0, 2e6, -3e7]])
    calls = []
    est = M.Custom.Create(counted(lambda x: 4.0 / (4.0 + x * x), calls),
                          counted(lambda x: 2.0 * np.log1p(x * x / 4.0), calls))
    kernel = Kernel(est)
    assert kernel.vectorised and kernel.tabulated and kernel.block
    built = len(calls)
    w, loss = kernel.weights(d), kernel.losses(d)
    assert len(calls) - built == 2 * 2  # the two distances beyond the table's reach, one call each function
    np.testing.assert_allclose(w, 4.0 / (4.0 + d * d), rtol=TABLE_RTOL, atol=TABLE_RTOL)
    np.testing.assert_allclose(loss, 2.0 * np.log1p(d * d / 4.0), rtol=TABLE_RTOL, atol=TABLE_RTOL)
    before = len(calls)
    assert Kernel(est).tabulated and len(calls) - before < 10  # built once per estimator (it takes ~75 000 calls)
    # Huber as callbacks: kinked at 1.345, the cells around it are left to the callbacks, exactly
    huber = M.Huber.Create(1.345)
    kinked = Kernel(M.Custom.Create(huber.weight, huber.loss))
    assert kinked.tabulated and 0.99 < kinked.weight.coverage < 1.0
    near = 1.345 + np.linspace(-0.02, 0.02, 401)
    np.testing.assert_array_equal(kinked.weights(near[np.abs(near - 1.345) < 0.004]),
                                  [huber.weight(x) for x in near[np.abs(near - 1.345) < 0.004]])
    np.testing.assert_allclose(kinked.weights(near), [huber.weight(x) for x in near], rtol=TABLE_RTOL)
    # infinite at 0: no table
    pole = Kernel(M.Custom.Create(lambda x: 1.0 / abs(x) if x else float("inf"), lambda x: abs(x)))
    assert not pole.vectorised and not pole.tabulated
    np.testing.assert_allclose(pole.weights(np.array([0.5, -4.0])), [2.0, 0.25])


MODELS = {
    "isotropic": lambda: gtsam.noiseModel.Isotropic.Sigma(2, 0.4),
    "diagonal": lambda: gtsam.noiseModel.Diagonal.Sigmas(np.array([0.3, 0.7])),
    "full covariance": lambda: gtsam.noiseModel.Gaussian.Covariance(np.array([[0.09, 0.03], [0.03, 0.25]])),
    "huber block": lambda: gtsam.noiseModel.Robust.Create(M.Huber.Create(1.345),
                                                          gtsam.noiseModel.Diagonal.Sigmas(np.array([0.3, 0.7]))),
    "cauchy scalar": lambda: gtsam.noiseModel.Robust.Create(M.Cauchy.Create(1.0, SCALAR),
                                                            gtsam.noiseModel.Isotropic.Sigma(2, 0.5)),
    "custom": lambda: gtsam.noiseModel.Robust.Create(cauchy_custom(), gtsam.noiseModel.Isotropic.Sigma(2, 0.5)),
    "custom per residual": lambda: gtsam.noiseModel.Robust.Create(
        M.Custom.Create(lambda x: 1.0 / abs(x) if x else float("inf"), lambda x: abs(x)),
        gtsam.noiseModel.Isotropic.Sigma(2, 0.5)),
}


@pytest.mark.parametrize("name", sorted(MODELS))
def test_residuals_are_whitened_reweighted_and_costed_as_gtsam_does(name):
    model = MODELS[name]()
    bulk = BulkNoise(model)
    r = np.random.default_rng(3).standard_normal((40, 2)) * np.geomspace(0.01, 20.0, 40)[:, None]
    e = bulk.whiten(r)
    sw = bulk.sqrt_weights(e)
    ours = e if sw is None else e * sw
    theirs = np.array([model.whiten(x) for x in r])  # GTSAM: whitened, then reweighted
    tol = TABLE_RTOL if bulk.kernel is not None and bulk.kernel.tabulated else SAME_FORMULA
    np.testing.assert_allclose(ours, theirs, rtol=tol, atol=1e-12)
    # GTSAM's error of a factor whose residual is r (a prior at 0 on a Point2 at r)
    values = gtsam.Values()
    values.insert(0, np.zeros(2))
    cost = 0.0
    for x in r:
        values.update(0, x)
        cost += gtsam.PriorFactorPoint2(0, np.zeros(2), model).error(values)
    assert bulk.cost(e) == pytest.approx(cost, rel=tol)


def test_models_the_bulk_path_cannot_apply_are_refused():
    with pytest.raises(NotBulk):
        BulkNoise(gtsam.noiseModel.Isotropic.Sigma(3, 1.0))
    with pytest.raises(NotBulk):
        BulkNoise(gtsam.noiseModel.Constrained.All(2))


def outlier_scene(seed=7):
    rig, pix, valid = scene(seed=seed)
    pix = pix.copy()
    pix[:, :10] += OUTLIER_PX
    return rig, pix, valid, triangulate_dlt(rig, pix, valid)


NOISES = {
    "huber": RobustKernel.parse("huber:1.345sigma"),
    "cauchy": RobustKernel.parse("cauchy:2.385sigma"),
    # every residual inside the kernel (beyond it Tukey's weight is 0 and an outlier's landmark is left with no
    # information: where it goes is the solver's choice)
    "tukey scalar": M.Tukey.Create(100.0, SCALAR),
    "custom": cauchy_custom(),
    "custom for arrays": cauchy_arrays(),
    "diagonal gaussian": gtsam.noiseModel.Diagonal.Sigmas(np.array([0.04, 0.06])),
}


@pytest.mark.parametrize("name", sorted(NOISES))
def test_a_robust_or_user_model_stays_on_the_bulk_path_and_reaches_gtsams_minimum(name):
    rig, pix, valid, points = outlier_scene()
    model = measurement_noise(NOISES[name], SIGMA_PX)
    priors = view_priors(rig, DriftModel())
    bulk = stage_problem(Stage.POSES, rig, pix, valid, points, model, priors=priors)
    assert bulk is not None  # no fall back to a GTSAM factor per observation
    problem, state = bulk
    graph, values = stage_graph(Stage.POSES, rig, pix, valid, points, model, priors=priors)
    assert problem.error(state) == pytest.approx(graph.error(values), rel=SAME_SYSTEM)
    ours_sys, theirs_sys = problem.system(state), GraphProblem(graph, values, "l").system(values)
    for a, b in ((ours_sys.H, theirs_sys.H), (ours_sys.V, theirs_sys.V), (ours_sys.g_c, theirs_sys.g_c),
                 (ours_sys.g_l, theirs_sys.g_l), (ours_sys.W, theirs_sys.W)):
        assert np.max(np.abs(a - b)) <= SAME_SYSTEM * np.max(np.abs(b))
    tight = {"max_iterations": 1000, "relative_error_tol": 1e-14, "absolute_error_tol": 0.0}
    ours = optimize_problem(problem, state, **tight)
    theirs = optimize(graph, values, OptimizerSettings(**tight))  # GTSAM's own LevenbergMarquardtOptimizer
    assert ours.final_error == pytest.approx(theirs.final_error, rel=SAME_MINIMUM)
    for v in range(rig.num_views):
        d = ours.values[0].atPose3(view_pose_key(v)).localCoordinates(theirs.values.atPose3(view_pose_key(v)))
        assert np.max(np.abs(d)) < SAME_POSE


def test_a_hooks_camera_factors_join_the_bulk_system(monkeypatch):
    # the two routes converged (refine's robust stop, 1e-4, leaves them ~2e-5 apart here: each its own path there)
    monkeypatch.setattr(stages, "ROBUST_RELATIVE_TOL", 1e-12)
    rig, pix, valid, points = outlier_scene(seed=9)
    noise = RobustKernel.parse("huber:1.345sigma")
    calls = []

    def pin_view_2(ctx):  # the README's kind of hook: hold one view where it starts
        calls.append(ctx.stage)
        key = view_pose_key(2)
        if ctx.initial.exists(key):
            ctx.graph.add(gtsam.PriorFactorPose3(key, ctx.initial.atPose3(key), pose_noise(1e-6, 1e-7)))

    model = measurement_noise(noise, SIGMA_PX)
    assert stage_problem(Stage.POSES, rig, pix, valid, points, model, hooks=(pin_view_2,)) is not None
    assert calls == ["poses"]
    bulk, _, _ = run_stage(Stage.POSES, rig, pix, valid, points, noise, SIGMA_PX, hooks=(pin_view_2,))
    graph, _, _ = run_stage(Stage.POSES, rig, pix, valid, points, noise, SIGMA_PX, hooks=(pin_view_2, gtsam_route))
    np.testing.assert_allclose(bulk.ref_T_view, graph.ref_T_view, atol=1e-5)
    # the hook's prior held view 2's rotation (its position is rescaled to the calibrated baselines afterwards)
    np.testing.assert_allclose(bulk.ref_T_view[2][:3, :3], rig.ref_T_view[2][:3, :3], atol=1e-5)
    free, _, _ = run_stage(Stage.POSES, rig, pix, valid, points, noise, SIGMA_PX)
    assert np.max(np.abs(free.ref_T_view[2][:3, :3] - rig.ref_T_view[2][:3, :3])) > 1e-4  # it would have moved


EFFICIENCY = 0.95  # the usual constants' asymptotic efficiency on Gaussian noise
EFFICIENCY_TOL = 0.002  # the numerical integral's error and the constants' rounding (4 digits)


@pytest.mark.parametrize("name", ["huber", "cauchy", "tukey", "welsch", "fair", "gm", "dcs"])
def test_a_bare_kernel_name_has_95_percent_efficiency(name):
    """(E psi')^2 / E psi^2 under N(0, 1), psi(d) = w(d) d from GTSAM's own weight of the kernel a bare name builds."""
    est = RobustKernel(name).estimator(1.0)
    x = np.linspace(-40.0, 40.0, 80001)
    psi = np.array([est.weight(float(v)) for v in x]) * x
    density = np.exp(-0.5 * x * x) / np.sqrt(2.0 * np.pi)
    dx = x[1] - x[0]
    efficiency = (np.sum(np.gradient(psi, dx) * density) * dx) ** 2 / (np.sum(psi * psi * density) * dx)
    assert efficiency == pytest.approx(EFFICIENCY, abs=EFFICIENCY_TOL)


def test_a_dcs_threshold_is_a_distance():
    est = RobustKernel.parse("dcs:0.5").estimator(0.05)  # 0.5 px = 10 sigmas
    assert est.weight(9.99) == 1.0
    assert est.weight(10.01) < 1.0


def test_kernel_thresholds_are_in_pixels_unless_written_in_sigmas():
    sigma_px = 0.05
    px = measurement_noise(RobustKernel.parse("huber:0.5"), sigma_px)  # 0.5 px = 10 sigmas
    sig = measurement_noise(RobustKernel.parse("huber:2sigma"), sigma_px)  # 2 sigmas = 0.1 px
    d = 20.0  # whitened distance (1 px): beyond both thresholds, where Huber's weight is k / d
    assert px.robust().weight(d) == pytest.approx(10.0 / d)
    assert sig.robust().weight(d) == pytest.approx(2.0 / d)
    usual = RobustKernel("cauchy")  # no number: the usual 95 %-efficiency constant, in sigmas (GTSAM's is 0.1)
    assert (usual.threshold, usual.unit) == (2.385, "sigma")
    for spec in ("huber:0.5", "huber:2sigma", "cauchy", "tukey:3px", "none"):
        k = RobustKernel.parse(spec)
        assert RobustKernel.parse(str(k)) == k  # what a study's CSV records reads back as the same kernel
    with pytest.raises(ValueError, match="unit"):
        RobustKernel("huber", 1.0, unit="mm")
