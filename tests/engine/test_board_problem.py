"""The engine's bulk board problem against GTSAM's own factors: the same cost and normal equations as the joint
graph of `lfgraph.factors.board_graph` (radtan and fisheye, Gaussian and robust); the unified lens, whose GTSAM
graph observes per-frame board points instead, against GTSAM's projection by finite differences."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from lfgraph.core.camera import Intrinsics
from lfgraph.core.geometry import make_T, rotation_from_rotvec
from lfgraph.core.grid import ViewGrid
from lfgraph.detect.board import BoardSpec
from lfgraph.detect.detections import BoardObservations
from lfgraph.engine.board_problem import BoardProblem
from lfgraph.engine.schur import GraphProblem
from lfgraph.factors import board_graph
from lfgraph.factors.keys import calib_key
from lfgraph.factors.noise import RobustKernel, measurement_noise
from lfgraph.factors.values import insert_board_corners, insert_board_poses, insert_intrinsics, insert_view_poses

COST_REL_TOL = 1e-12  # the two costs are the same sums in another order
SYSTEM_REL_TOL = 1e-9  # each normal-equation entry relative to its row's and column's diagonal scale
GRADIENT_REL_TOL = 1e-5  # central differences of the unified cost against the assembled gradient

LENSES = {"radtan": dict(k1=-0.12, k2=0.03, p1=1e-3, p2=-5e-4), "fisheye": dict(k1=0.05, k2=-0.01, k3=2e-3, k4=-1e-4),
          "unified": dict(xi=0.7, k1=-0.05, k2=0.01, p1=2e-4, p2=1e-4)}


def _rig(lens: str, rng: np.random.Generator):
    """A 1x3 rig (one lens per view cycling the models when ``lens`` is "mixed"), 4 board frames, perturbed start."""
    board = BoardSpec(6, 5, 0.04)
    obj = board.object_points()
    names = ["radtan", "fisheye", "radtan"] if lens == "mixed" else [lens] * 3
    intr = tuple(Intrinsics(600.0 + 10 * v, 605.0, 320.0 + v, 240.0 - v, lens=name, **LENSES[name])
                 for v, name in enumerate(names))
    poses = np.stack([make_T(rotation_from_rotvec([0.0, 0.02 * v, 0.01]), [0.1 * v, 0.0, 0.0]) for v in range(3)])
    poses[0] = np.eye(4)
    boards = np.stack([np.linalg.inv(make_T(rotation_from_rotvec(rng.normal(scale=0.2, size=3)),
                                            [-0.1 + 0.05 * f, -0.1, 0.8 + 0.1 * f])) for f in range(4)])
    values = gtsam.Values()
    insert_intrinsics(values, intr)
    insert_view_poses(values, poses)
    insert_board_poses(values, boards, range(4))
    insert_board_corners(values, obj)
    delta = gtsam.VectorValues()
    for k in values.keys():
        delta.insert(k, rng.normal(scale=1e-4, size=values.zeroVectors().at(k).shape[0]))
    values = values.retract(delta)
    corners = np.zeros((3, 4, len(obj), 2))
    for v in range(3):
        for f in range(4):
            cam = np.linalg.inv(boards[f] @ poses[v])
            pc = obj @ cam[:3, :3].T + cam[:3, 3]
            corners[v, f] = intr[v].project(pc) + rng.normal(scale=0.2, size=(len(obj), 2))
    valid = np.ones(corners.shape[:3], dtype=bool)
    valid[2, 3, :5] = False  # a partly seen board
    obs = BoardObservations(board, ViewGrid(1, 3, 0), (640, 480), corners, valid, tuple(f"f{f}" for f in range(4)))
    priors = gtsam.NonlinearFactorGraph()
    board_graph.add_corner_priors(priors, obj, 1e-6)
    board_graph.add_gauge_prior(priors, 0)
    board_graph.add_intrinsics_pins(priors, intr, False, None, 640.0)
    return obs, priors, values, tuple(names)


@pytest.mark.parametrize("lens", ["radtan", "fisheye", "mixed"])
@pytest.mark.parametrize("kernel", ["none", "cauchy"])
def test_cost_and_system_are_gtsams(lens, kernel):
    obs, priors, values, lenses = _rig(lens, np.random.default_rng(3))
    noise = measurement_noise(RobustKernel(kernel, 1.0), 0.5)
    problem = BoardProblem(priors, values, obs.corners_px, obs.valid, range(4), noise, lenses)
    graph = gtsam.NonlinearFactorGraph(priors)
    board_graph.add_board_observations(graph, obs.corners_px, obs.valid, noise, lenses)
    assert problem.error(values) == pytest.approx(graph.error(values), rel=COST_REL_TOL)
    (H, g), theirs = _whole(problem, values), GraphProblem(graph, values, "\0").system(values)  # noqa: N806
    scale = np.sqrt(np.outer(np.abs(np.diag(theirs.H)), np.abs(np.diag(theirs.H))))
    assert np.max(np.abs(H - theirs.H) / scale) < SYSTEM_REL_TOL
    assert np.max(np.abs(g - theirs.g_c) / np.sqrt(np.abs(np.diag(theirs.H)))) < SYSTEM_REL_TOL


def _whole(problem: BoardProblem, values: gtsam.Values) -> tuple[np.ndarray, np.ndarray]:
    """The problem's Schur-form system (board-pose blocks V, coupling W, the rest H) as one matrix and gradient in
    the values' column order (what GTSAM's linearisation gives)."""
    sys_, lay = problem.system(values), problem.layout
    cam, lm = np.nonzero(lay.col_cam >= 0)[0], np.nonzero(lay.col_lm >= 0)[0]
    lm = lm[np.lexsort((lay.col_comp[lm], lay.col_lm[lm]))]  # board by board, component by component
    H, g = np.zeros((lay.n, lay.n)), np.zeros(lay.n)  # noqa: N806
    H[np.ix_(cam, cam)], g[cam] = sys_.H, sys_.g_c
    n_b, d = sys_.V.shape[:2]
    blocks = np.zeros((n_b * d, n_b * d))
    for b in range(n_b):
        blocks[b * d:(b + 1) * d, b * d:(b + 1) * d] = sys_.V[b]
    H[np.ix_(lm, lm)], g[lm] = blocks, sys_.g_l.ravel()
    H[np.ix_(lm, cam)] = sys_.W.reshape(n_b * d, -1)
    H[np.ix_(cam, lm)] = sys_.W.reshape(n_b * d, -1).T
    return H, g


def test_unified_cost_and_gradient():
    obs, priors, values, lenses = _rig("unified", np.random.default_rng(4))
    noise = measurement_noise(RobustKernel("none", 1.0), 0.5)
    problem = BoardProblem(gtsam.NonlinearFactorGraph(), values, obs.corners_px, obs.valid, range(4), noise, lenses)
    # the cost against GTSAM's own unified camera
    expected = 0.0
    for v in range(3):
        cal = values.atCal3Unified(calib_key(v))
        for f in range(4):
            pose = values.atPose3(gtsam.symbol("b", f)).compose(values.atPose3(gtsam.symbol("x", v)))
            camera = gtsam.PinholeCameraCal3Unified(pose, cal)
            for c in np.nonzero(obs.valid[v, f])[0]:
                point = np.asarray(values.atPoint3(gtsam.symbol("c", int(c))))
                expected += 0.5 * np.sum(((camera.project(point) - obs.corners_px[v, f, c]) / 0.5) ** 2)
    assert problem.error(values) == pytest.approx(expected, rel=COST_REL_TOL)
    g = _whole(problem, values)[1]  # -J^T e: minus the cost's gradient, in the values' column order
    lay = problem.layout
    rng = np.random.default_rng(5)
    for _ in range(5):
        d = rng.normal(size=lay.n) * 1e-7
        dl = np.zeros((lay.n_landmarks, 6))
        lm = lay.col_lm >= 0
        dl[lay.col_lm[lm], lay.col_comp[lm]] = d[lm]
        dc = d[~lm][np.argsort(lay.col_cam[~lm])]
        plus, minus = problem.retract(values, dl, dc), problem.retract(values, -dl, -dc)
        numeric = (problem.error(plus) - problem.error(minus)) / 2
        assert numeric == pytest.approx(-float(g @ d), rel=GRADIENT_REL_TOL)
