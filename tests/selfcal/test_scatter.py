"""The weak modes' track-clustered sandwich (`lfgraph.selfcal.scatter`): each observation's pull on a mode against
a refit, the sandwich against the known scatter of the errors, and the widened covariance's algebra."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lfgraph.core.grid import ViewGrid
from lfgraph.core.sigmas import Sigmas
from lfgraph.datasets.rig import make_rig
from lfgraph.engine.triangulate import project_views
from lfgraph.factors.noise import RobustKernel
from lfgraph.selfcal import calibrate_tracks
from lfgraph.selfcal.pinned import mode_rows, weak_modes
from lfgraph.selfcal.scatter import mode_pulls, robust_joint, track_sandwich
from lfgraph.selfcal.solve import LANDMARK_ITERATIONS, measurement, posterior, run_map_stage
from tests.selfcal.test_selfcal import DESIGN, RIG, synthetic_tracks

NOISE_PX = 0.05
PULL_TOL_SIGMAS = 0.15  # the pulls' prediction of a refit's mode change, in the mode's sigmas: the near-gauge valleys
# bend within a shift of ~0.7 sigma (the prediction lies between the refits of 0.1x and 1x the shift); a sandwich
# needs its pulls to ~10-20 % of a sigma
REFIT_RELATIVE_TOL = 1e-12  # the refits run to convergence: the gauge valleys are nearly flat
SANDWICH_REL_TOL = 0.15  # G against its expectation: ~4 relative sds of a sum over ~2000 tracks' squared pulls


def _refit(scene, pixels):
    calib, points, graph, values, _ = run_map_stage(
        scene.calib, scene.nominal, pixels, scene.tracks.valid, scene.points, scene.free, scene.sigmas,
        measurement(RobustKernel("none"), scene.noise_px), 300, REFIT_RELATIVE_TOL, None, (), hold_gauges=False,
        landmark_iterations=LANDMARK_ITERATIONS)
    return calib, points, graph, values


@pytest.fixture(scope="module")
def fitted():
    truth = make_rig(RIG, np.random.default_rng(5))
    tracks = synthetic_tracks(truth, 6, 60, NOISE_PX, np.random.default_rng(6))
    scene = calibrate_tracks(tracks, DESIGN)[1].scene
    calib, points, graph, values = _refit(scene, scene.tracks.pixels)
    return dataclasses.replace(scene, calib=calib, points=points), graph, values


def test_each_observations_pull_predicts_a_refit(fitted):
    scene, graph, values = fitted
    cameras = posterior(graph, values, scene.calib.lenses, poses=True)[1]
    n_cal = len(cameras) - 6 * scene.calib.num_views
    rows = mode_rows(scene.calib.grid, scene.calib.num_views, n_cal // scene.calib.num_views)
    pulls = mode_pulls(scene.calib, values, scene.points, scene.tracks.valid, cameras, rows)
    rng = np.random.default_rng(7)
    shift = np.where(scene.tracks.valid[..., None], NOISE_PX * rng.standard_normal(scene.tracks.pixels.shape), 0.0)
    calib, *_ = _refit(scene, scene.tracks.pixels + shift)
    unused = np.zeros((n_cal, n_cal))
    moved = weak_modes(calib, unused)[0] - weak_modes(scene.calib, unused)[0]
    predicted = np.einsum("mvni,vni->m", pulls, shift) / scene.noise_px**2
    sigma = np.sqrt(np.diag(rows @ cameras[:n_cal, :n_cal] @ rows.T))
    assert np.all(np.abs(moved) > 0.1 * sigma)  # the shift moved every mode measurably
    assert np.all(np.abs(predicted - moved) <= PULL_TOL_SIGMAS * sigma)


def test_the_sandwich_sees_tracks_that_err_more_than_the_graph_assumes():
    rng = np.random.default_rng(3)
    pulls = rng.standard_normal((1, 8, 2000, 2))
    noise = 0.1
    white = noise * rng.standard_normal(pulls.shape[1:])
    assumed, seen = track_sandwich(pulls, white, noise)
    assert abs(seen[0, 0] / assumed[0, 0] - 1.0) < SANDWICH_REL_TOL  # errors as the graph assumes: G ~ B
    # a third of the tracks err 4x more, and alike in every view (a depth edge): G follows the true scatter
    track_sigma = np.where(np.arange(2000) % 3 == 0, 4 * noise, noise)
    shared = track_sigma[None, :, None] * rng.standard_normal((1, 2000, 2))
    _, seen = track_sandwich(pulls, np.broadcast_to(shared, white.shape), noise)
    pull_per_track = pulls[0].sum(axis=0) / noise**2  # (N, 2): the same error in every view adds the pulls
    expected = float(np.sum(track_sigma[:, None] ** 2 * pull_per_track**2))
    assert abs(seen[0, 0] / expected - 1.0) < SANDWICH_REL_TOL
    assert seen[0, 0] > 5 * assumed[0, 0]


def test_the_widened_joint_adds_only_the_modes_excess_and_never_narrows():
    rng = np.random.default_rng(4)
    a = rng.standard_normal((12, 12))
    joint = a @ a.T
    rows = rng.standard_normal((3, 12))
    assumed = np.diag([1.0, 2.0, 3.0])
    seen = np.diag([4.0, 1.0, 3.0])  # wider in the first mode, narrower in the second: kept
    out = robust_joint(joint, rows, assumed, seen)
    assert np.allclose(rows @ out @ rows.T, rows @ joint @ rows.T + np.diag([3.0, 0.0, 0.0]))
    other = np.linalg.svd(rows)[2][3:]  # combinations orthogonal to the rows
    assert np.allclose(other @ out @ other.T, other @ joint @ other.T)
    assert np.all(np.linalg.eigvalsh(out - joint) > -1e-9)


def test_project_views_is_every_views_projection(fitted):
    scene, _, _ = fitted
    px = project_views(scene.calib, scene.points)
    assert px.shape == (scene.calib.num_views, len(scene.points), 2)
    seen = scene.tracks.valid
    assert np.sqrt(np.mean((px[seen] - scene.tracks.pixels[seen]) ** 2)) < 2 * NOISE_PX  # the fit's residuals


def test_a_widened_zoom_widens_every_views_focal_length_by_as_much():
    """The report's per-view sigmas are read from the widened covariance: the zoom (the mean of every fx and fy)
    widened by e px^2 with nothing else moved can only be every view's fx and fy moved together, so each view's fx and
    fy variance grows by e and its principal point's stays."""
    grid = ViewGrid(RIG.rows, RIG.cols, RIG.reference)
    n, lenses = grid.num_views, ("radtan",) * grid.num_views
    dim = 9  # Cal3DS2's tangent: fx, fy, s, cx, cy, k1, k2, p1, p2
    rng = np.random.default_rng(5)
    base = rng.uniform(0.2, 1.0, dim * n) ** 2
    rows = mode_rows(grid, n, dim)
    extra_px2 = 4.0
    seen = np.zeros((len(rows), len(rows)))
    seen[0, 0] = extra_px2
    out = robust_joint(np.diag(base), rows, np.zeros_like(seen), seen)
    pose = rng.uniform(1e-4, 1e-3, (n, 6))
    sig = Sigmas(pose, np.zeros((n, 4))).with_calibration_cov(out, lenses)
    b = base.reshape(n, dim)
    assert np.allclose(sig.intrinsics[:, 0] ** 2, b[:, 0] + extra_px2)
    assert np.allclose(sig.intrinsics[:, 1] ** 2, b[:, 1] + extra_px2)
    assert np.allclose(sig.intrinsics[:, 2:] ** 2, b[:, 3:5])
    assert np.allclose(sig.distortion["k1"] ** 2, b[:, 5])
    assert np.array_equal(sig.pose, pose)
    with pytest.raises(ValueError, match="covariance"):
        Sigmas(pose, np.zeros((n, 4))).with_calibration_cov(out[1:, 1:], lenses)
