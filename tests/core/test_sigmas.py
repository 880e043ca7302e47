"""The one sigma record (issue 39): what calibrate and calibrate-scene store is the same quantity — each view's
uncertainty about and along its own axes — so a rig turned 90° about its optical axis stores the same sigmas with x
and y exchanged; and the record's own arithmetic."""

from __future__ import annotations

import numpy as np
import pytest

import lfgraph as lf
from lfgraph.core.grid import ViewGrid
from lfgraph.core.sigmas import Sigmas
from lfgraph.datasets.board_render import CheckerboardConfig
from lfgraph.datasets.checkerboard import make_checkerboard_truth, make_corner_observations
from lfgraph.datasets.rig import RigConfig, make_rig
from lfgraph.detect.board import BoardSpec
from lfgraph.detect.detections import observations_from_arrays
from lfgraph.selfcal import Design, PooledTracks, calibrate_tracks
from tests.selfcal.test_selfcal import synthetic_tracks

SIZE_PX, FOCAL_PX, PITCH_M = 240, 250.0, 0.02
# the same problem with its axes exchanged: the stored sigmas agree to the solvers' tolerance, not to the bit
SAME_PROBLEM_REL = 1e-3
ANISOTROPY_MIN = 20 * SAME_PROBLEM_REL  # |log(x / y)| of a non-reference view's rotation or position sigmas, at least
RIG = RigConfig(rows=1, cols=3, reference=1, pitch_m=PITCH_M, image_size_px=(SIZE_PX, SIZE_PX), focal_px=FOCAL_PX,
                k1=-0.1, k2=0.0, focal_jitter_px=0.0, principal_jitter_px=0.0, distortion_jitter=0.0,
                rot_jitter_deg=0.5, trans_jitter_mm=0.3)


def _turned(px: np.ndarray) -> np.ndarray:
    """Pixels of a view turned -90° about its optical axis (x' = -y, y' = x), for a square image with the principal
    point at its centre and equal focal lengths: u' = 2 c - v, v' = u."""
    c = (SIZE_PX - 1) / 2.0
    return np.stack([2 * c - px[..., 1], px[..., 0]], axis=-1)


def _assert_turned(flat: Sigmas, turned: Sigmas) -> None:
    """``turned`` is ``flat`` with x and y exchanged: rotations about x and y, positions along them, fx and fy, cx
    and cy (the reference view's pose is the gauge: ~0 either way)."""
    swap = [1, 0, 2]
    other = np.arange(flat.num_views) != RIG.reference
    np.testing.assert_allclose(turned.rotation_deg[other][:, swap], flat.rotation_deg[other], rtol=SAME_PROBLEM_REL)
    np.testing.assert_allclose(turned.position_mm[other][:, swap], flat.position_mm[other], rtol=SAME_PROBLEM_REL)
    np.testing.assert_allclose(turned.intrinsics[:, [1, 0, 3, 2]], flat.intrinsics, rtol=SAME_PROBLEM_REL)
    np.testing.assert_allclose(turned.distortion["k1"], flat.distortion["k1"], rtol=SAME_PROBLEM_REL)
    # and x and y differ by far more than the tolerance (else the swap proves nothing): the rig's axis is one of them
    spread = np.abs(np.log(flat.pose[other][:, [0, 3]] / flat.pose[other][:, [1, 4]]))
    assert np.all(spread.max(axis=1) > ANISOTROPY_MIN), spread


def test_calibrate_and_calibrate_scene_store_each_views_sigmas_about_its_own_axes():
    truth = make_rig(RIG, np.random.default_rng(1))
    # calibrate: board corners, and the same corners in the turned rig (a 3x1 of the same views)
    boards = make_checkerboard_truth(truth, CheckerboardConfig(board=BoardSpec(7, 5, 0.02), frames=12,
                                                               distance_m=(0.25, 0.5)), np.random.default_rng(2))
    c, v = make_corner_observations(boards, 0.2, np.random.default_rng(3))
    grids = (truth.grid, ViewGrid(3, 1, RIG.reference))
    flat, turned = (lf.calibrate(observations_from_arrays(boards.board, g, (SIZE_PX, SIZE_PX), px, v),
                                 lf.CalibrateConfig(lens="radtan", screen=False))[0].sigmas
                    for g, px in zip(grids, (c, _turned(c)), strict=True))
    _assert_turned(flat, turned)
    # calibrate-scene: scene tracks, and the same tracks in the turned rig
    tracks = synthetic_tracks(truth, 5, 80, 0.1, np.random.default_rng(4))
    designs = (Design(1, 3, pitch_mm=1e3 * PITCH_M, focal_px=FOCAL_PX, image_size_px=(SIZE_PX, SIZE_PX), k1=-0.1,
                      reference=RIG.reference),
               Design(3, 1, pitch_mm=1e3 * PITCH_M, focal_px=FOCAL_PX, image_size_px=(SIZE_PX, SIZE_PX), k1=-0.1,
                      reference=RIG.reference))
    pooled = (tracks, PooledTracks(_turned(tracks.pixels), tracks.valid, tracks.frame, tracks.frames_seen,
                                   tracks.frames_used))
    flat, turned = (calibrate_tracks(t, d)[0].sigmas for t, d in zip(pooled, designs, strict=True))
    _assert_turned(flat, turned)


def test_the_record_round_trips_and_combines():
    s = Sigmas.uniform(2, rotation_rad=(0.01, 0.01, 0.02), position_m=0.003, focal_px=2.0, principal_px=3.0,
                       distortion={"k1": 0.05})
    assert Sigmas.from_metrics(s.to_metrics(), 2) == s
    stored = s.to_metrics()[0]
    assert {k: stored[k] for k in ("fx_px", "fy_px", "cx_px", "cy_px", "k1")} == {
        "fx_px": 2.0, "fy_px": 2.0, "cx_px": 3.0, "cy_px": 3.0, "k1": 0.05}
    np.testing.assert_allclose(stored["rotation_deg"], np.degrees([0.01, 0.01, 0.02]), rtol=1e-15)
    np.testing.assert_allclose(stored["position_mm"], [3.0, 3.0, 3.0], rtol=1e-15)
    both = s.combined(Sigmas.uniform(2, 0.01, 0.004, 0.0, 4.0))
    np.testing.assert_allclose(both.pose[1], [np.hypot(0.01, 0.01), np.hypot(0.01, 0.01), np.hypot(0.02, 0.01),
                                              0.005, 0.005, 0.005])
    np.testing.assert_allclose(both.intrinsics[0], [2.0, 2.0, 5.0, 5.0])
    assert both.distortion["k1"][0] == 0.05  # held by one of them only
    with pytest.raises(ValueError, match="pose must be"):
        Sigmas(np.zeros((2, 5)), np.zeros((2, 4)))
