"""Synthetic checkerboards: OpenCV must find what the renderer drew, where the ground truth says."""

import dataclasses

import cv2
import numpy as np
import pytest

from lfgraph.core.geometry import rotation_angle_deg
from lfgraph.datasets.checkerboard import (
    CheckerboardConfig,
    CheckerboardTruth,
    iter_view_images,
    make_board_poses,
    make_checkerboard_truth,
    make_corner_observations,
    write_checkerboard_dataset,
)
from lfgraph.datasets.rig import RigConfig, make_rig
from lfgraph.detect.board import BoardSpec
from lfgraph.detect.chessboard import detect_board

DETECTION_RMS_LIMIT_PX = 0.05  # detected vs true corners, noise-free render with mild blur
NOISE_STD_TOLERANCE = 0.10  # relative error of the corner-only noise std over ~10^4 samples
MAX_CORNER_ERROR_PX = 0.5  # no single detected corner further than this from its true projection (noise 1 grey level)


@pytest.fixture(scope="module")
def setup():
    # 2x2 rig, 640x480, strong barrel distortion, boards tilted up to 40 degrees
    calib = make_rig(RigConfig(rows=2, cols=2, image_size_px=(640, 480), focal_px=600, k1=-0.12, pitch_m=0.01),
                     np.random.default_rng(0))
    cfg = CheckerboardConfig(board=BoardSpec(7, 5, 0.02), frames=6, distance_m=(0.3, 0.6), noise_sigma=0.0)
    truth = make_checkerboard_truth(calib, cfg, np.random.default_rng(1))
    return calib, cfg, truth


def test_detected_corners_land_on_ground_truth(setup):
    calib, cfg, truth = setup
    sq_err, n_found = [], 0
    for v in range(calib.num_views):
        for f, img in iter_view_images(calib, truth, cfg, seed=0, view=v):
            corners = detect_board(img, cfg.board)
            if truth.board_visible[v, f]:
                assert corners is not None, f"board not found in view {v} frame {f} though fully visible"
            if corners is None:
                continue
            n_found += 1
            sq_err.append(np.sum((corners - truth.corners_px[v, f]) ** 2, axis=1))
    rms = float(np.sqrt(np.mean(np.concatenate(sq_err))))
    assert n_found >= truth.board_visible.sum()
    assert rms <= DETECTION_RMS_LIMIT_PX, f"detection RMS {rms:.4f} px"


def test_board_poses_cover_the_view_and_respect_limits(setup):
    calib, cfg, truth = setup
    cfg9 = dataclasses.replace(cfg, frames=18)
    poses = make_board_poses(calib, cfg9, np.random.default_rng(5))
    ref = calib.grid.reference
    t = make_checkerboard_truth(calib, cfg9, np.random.default_rng(0), ref_T_board=poses)
    assert t.board_visible[ref].all(), "every board must be whole in the reference view"
    tilt = rotation_angle_deg(poses[:, :3, :3])
    assert np.all(tilt <= np.hypot(cfg.max_tilt_deg, cfg.max_roll_deg) + 1e-9)
    centre = poses[:, :3, 3] + poses[:, :3, :3] @ np.array([3 * 0.02, 2 * 0.02, 0])
    dist = np.linalg.norm(centre, axis=1)
    assert np.all(dist >= cfg.distance_m[0] - 1e-9) and np.all(dist <= cfg.distance_m[1] * 1.5)
    # centres spread: boards reach every quadrant of the reference image
    mid = t.corners_px[ref].mean(axis=1)
    w, h = calib.image_size_px
    quadrants = {(bool(x > w / 2), bool(y > h / 2)) for x, y in mid}
    assert len(quadrants) == 4


def test_generation_is_seeded(setup):
    calib, cfg, _ = setup
    a = make_board_poses(calib, cfg, np.random.default_rng(7))
    b = make_board_poses(calib, cfg, np.random.default_rng(7))
    c = make_board_poses(calib, cfg, np.random.default_rng(8))
    assert np.array_equal(a, b) and not np.allclose(a, c)


def test_corner_only_noise_and_masks(setup):
    calib, cfg, truth = setup
    sigma = 0.3
    noisy, valid = make_corner_observations(truth, sigma, np.random.default_rng(0), full_boards_only=True)
    assert np.all(np.isnan(noisy[~valid]))
    assert not valid[~truth.board_visible].any()
    big = dataclasses.replace(truth, corners_px=np.repeat(truth.corners_px, 20, axis=1),
                              ref_T_board=np.repeat(truth.ref_T_board, 20, axis=0),
                              corner_valid=np.repeat(truth.corner_valid, 20, axis=1),
                              board_visible=np.repeat(truth.board_visible, 20, axis=1))
    noisy, valid = make_corner_observations(big, sigma, np.random.default_rng(1))
    std = np.std((noisy - big.corners_px)[valid])
    assert abs(std / sigma - 1) < NOISE_STD_TOLERANCE


def test_npz_round_trip_and_errors(tmp_path, setup):
    _, _, truth = setup
    path = tmp_path / "truth_corners.npz"
    truth.save_npz(path)
    back = CheckerboardTruth.load_npz(path)
    assert back.board == truth.board
    assert np.array_equal(back.corners_px, truth.corners_px, equal_nan=True)
    np.savez(tmp_path / "missing.npz", board=np.array([7, 5, 0.02, 1.0]))
    with pytest.raises(ValueError, match="missing.npz: missing arrays"):
        CheckerboardTruth.load_npz(tmp_path / "missing.npz")
    with np.load(path) as data:
        arrays = dict(data)
    arrays["corners_px"] = arrays["corners_px"][:, :, :3]
    np.savez(tmp_path / "shape.npz", **arrays)
    with pytest.raises(ValueError, match="shape.npz: corners_px must be"):
        CheckerboardTruth.load_npz(tmp_path / "shape.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="junk.npz"):
        CheckerboardTruth.load_npz(tmp_path / "junk.npz")


def test_dataset_writer_layouts_and_job_independence(tmp_path):
    calib = make_rig(RigConfig(rows=2, cols=2, image_size_px=(160, 120), focal_px=150, pitch_m=0.01),
                     np.random.default_rng(0))
    cfg = CheckerboardConfig(board=BoardSpec(5, 4, 0.02), frames=2, distance_m=(0.35, 0.5))
    truth = make_checkerboard_truth(calib, cfg, np.random.default_rng(0))
    write_checkerboard_dataset(tmp_path / "a", calib, truth, cfg, seed=3, jobs=1, progress=False)
    write_checkerboard_dataset(tmp_path / "b", calib, truth, cfg, seed=3, jobs=2, progress=False)
    write_checkerboard_dataset(tmp_path / "m", calib, truth, cfg, seed=3, layout="mosaic", jobs=2, progress=False)
    names = sorted(p.relative_to(tmp_path / "a").as_posix() for p in (tmp_path / "a").rglob("*.png"))
    assert names == [f"{f:03d}/r{r:02d}_c{c:02d}.png" for f in range(2) for r in range(2) for c in range(2)]
    for name in names:
        a = cv2.imread(str(tmp_path / "a" / name), cv2.IMREAD_GRAYSCALE)
        b = cv2.imread(str(tmp_path / "b" / name), cv2.IMREAD_GRAYSCALE)
        assert a.shape == (120, 160) and np.array_equal(a, b)
    mosaic = cv2.imread(str(tmp_path / "m" / "001.png"), cv2.IMREAD_GRAYSCALE)
    assert mosaic.shape == (240, 320)
    assert np.array_equal(mosaic[120:, 160:], cv2.imread(str(tmp_path / "a" / "001" / "r01_c01.png"), 0))
    assert sorted(p.name for p in (tmp_path / "m").iterdir()) == ["000.png", "001.png", "truth.json",
                                                                 "truth_corners.npz"]
    with pytest.raises(ValueError, match="layout"):
        write_checkerboard_dataset(tmp_path / "x", calib, truth, cfg, seed=3, layout="tiles", progress=False)


def test_symmetric_board_order_does_not_depend_on_what_opencv_reports(setup):
    from lfgraph.detect.chessboard import _canonical_order

    calib, cfg, truth = setup
    assert cfg.board.is_symmetric  # 7x5 inner corners = 8x6 squares: the same after a 180° turn
    _, img = next(iter_view_images(calib, truth, cfg, seed=0, view=1, frames=range(1)))
    corners = detect_board(img, cfg.board)
    np.testing.assert_allclose(_canonical_order(img, corners[::-1].copy(), cfg.board), corners)
    assert np.max(np.abs(corners - truth.corners_px[1, 0])) < 0.2


EDGE_COVERAGE_TOLERANCE_GREY = 0.5 + 1e-6  # the rendered image is rounded to whole grey levels


def test_edge_pixels_take_the_exact_covered_area():
    """A fronto-parallel board, no lens distortion, no blur: a pixel cut by a vertical square edge at 80 % of its
    width must hold the area-weighted mean of the two squares (8x8 point samples would give 75 % or 87.5 %)."""
    from lfgraph.core.camera import Intrinsics
    from lfgraph.core.geometry import make_T
    from lfgraph.datasets.board_render import BLACK_LEVEL, WHITE_LEVEL, render_checkerboard_view

    f_px, square_m, z_m = 500.0, 0.02, 1.0  # 10 px per square
    intr = Intrinsics(f_px, f_px, 100.0, 80.0)
    board = BoardSpec(7, 5, square_m)
    edge_px = 120.3  # board corner (0, 0), i.e. the edge between square columns -1 and 0, at this image x
    top_px = 60.0
    view_T_board = make_T(np.eye(3), [(edge_px - 100.0) / f_px * z_m, (top_px - 80.0) / f_px * z_m, z_m])  # noqa: N806
    cfg = CheckerboardConfig(board=board, blur_sigma_px=0.0, noise_sigma=0.0)
    img = render_checkerboard_view(intr, (200, 160), view_T_board, board, cfg).astype(float)
    rows = slice(int(top_px) + 2, int(top_px) + 8)  # inside square row 0, away from horizontal edges
    col = int(round(edge_px))  # the pixel [119.5, 120.5] is 80 % left of the edge: square (-1, 0) white, (0, 0) black
    left = (edge_px - (col - 0.5))
    expected = left * WHITE_LEVEL + (1 - left) * BLACK_LEVEL
    assert np.all(np.abs(img[rows, col] - expected) <= EDGE_COVERAGE_TOLERANCE_GREY), img[rows, col]
    assert np.all(img[rows, col - 1] == WHITE_LEVEL) and np.all(img[rows, col + 1] == BLACK_LEVEL)


def test_no_detected_corner_is_far_off_on_small_squares(tmp_path):
    """Rendered small-2x2 boards (squares of 6-8 px): findChessboardCorners placed single corners 3.6 and 12.6 px
    off the grid on frames 7 and 10 of this capture; every corner must now sit on its true projection."""
    from lfgraph.cli import main

    assert main(["synth", "checkerboard", str(tmp_path), "--scene", "small-2x2", "--frames", "12", "--jobs", "2",
                 "--quiet", "--seed", "8"]) == 0
    truth = np.load(tmp_path / "truth_corners.npz")["corners_px"]
    board = BoardSpec(7, 5, 0.015)
    worst = 0.0
    for f in range(12):
        for v, name in enumerate(("r00_c00", "r00_c01", "r01_c00", "r01_c01")):
            found = detect_board(cv2.imread(str(tmp_path / f"{f:03d}" / f"{name}.png"), cv2.IMREAD_GRAYSCALE), board)
            if found is not None:  # a symmetric board: either order
                worst = max(worst, min(np.max(np.linalg.norm(found - truth[v, f], axis=1)),
                                       np.max(np.linalg.norm(found[::-1] - truth[v, f], axis=1))))
    assert worst < MAX_CORNER_ERROR_PX
