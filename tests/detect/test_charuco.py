"""ChArUco boards: the spec and its parse, detection against OpenCV-rendered truth and caliscope's detections of a
real rig, and calibration (both routes) from partly visible boards."""

import csv
import dataclasses
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import pytest

from lfgraph.datasets.checkerboard import make_checkerboard_truth, make_corner_observations
from lfgraph.datasets.rig import make_rig
from lfgraph.datasets.scenes import get_scene
from lfgraph.detect.board import BoardSpec
from lfgraph.detect.charuco import MIN_CHARUCO_CORNERS, detect_charuco
from lfgraph.detect.detections import MIN_CORNERS_PER_BOARD, _cache_key, detect_capture, observations_from_arrays
from lfgraph.io.capture import open_capture
from lfgraph.judge.evaluation import evaluate_calibration
from lfgraph.pattern import CalibrateConfig, calibrate

DATA = Path(__file__).resolve().parents[1] / "data" / "charuco"
CALISCOPE = BoardSpec.parse("charuco:4x5:DICT_4X4_1000:inverted", 54.0, 40.5)  # caliscope's charuco.toml
PX_PER_SQUARE = 80  # rendered board resolution
RENDER_MARGIN_PX = 80
SYNTH_TOL_PX = 0.25  # corners of a warped, slightly blurred rendering to this of the homography's truth
CALISCOPE_MEDIAN_TOL_PX = 1.0  # our corners vs caliscope's on the same real frames (its own refinement differs)
CALISCOPE_P95_TOL_PX = 1.5
CALISCOPE_MAX_TOL_PX = 6.0  # one blurred corner of cam 3's small oblique board differs by 4.6 px; a wrong id by >= 20
MIN_COMMON_CORNERS = 4  # the detectors' corner subsets differ at the edge of visibility and blur
BOARD_PLANE_TOL_SQUARES = 0.4  # our corners to the board plane through caliscope's corners, in local squares
#                                 (distortion and extrapolation reach 0.3; a wrong id is a square or more away)
EXACT_RELATIVE = 1e-6  # noise-free synthetic calibration, relative to the scales below
PAPER_RELATIVE = 1e-4  # ... the paper route stops at OpenCV's convergence criteria
FOCAL_SCALE_PX = 300.0
PITCH_M = 0.010
FLOAT32_M = 1e-7  # OpenCV keeps board points in float32


# ----------------------------------------------------------------------------------------------------- spec
def test_parse_charuco_matches_opencv_board():
    assert (CALISCOPE.cols, CALISCOPE.rows, CALISCOPE.squares) == (3, 4, (4, 5))
    assert CALISCOPE.square_m == pytest.approx(0.054) and CALISCOPE.marker_m == pytest.approx(0.0405)
    assert CALISCOPE.inverted and not CALISCOPE.legacy_pattern and not CALISCOPE.is_symmetric
    cv_board = cv2.aruco.CharucoBoard((4, 5), 0.054, 0.0405, cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_1000))
    # corner j is ChArUco id j, one square in from OpenCV's board origin
    expected = cv_board.getChessboardCorners() - np.array([0.054, 0.054, 0.0])
    np.testing.assert_allclose(CALISCOPE.object_points(), expected, atol=FLOAT32_M)


def test_parse_keeps_chessboards_and_refuses_bad_charuco():
    assert BoardSpec.parse("11x8", 20.0) == BoardSpec(11, 8, 0.020)
    legacy = BoardSpec.parse("charuco:5x6:DICT_5X5_100:legacy", 30.0, 22.0)
    assert legacy.legacy_pattern and not legacy.inverted and legacy.squares == (5, 6)
    assert BoardSpec.parse("charuco:8x6:dict_apriltag_36h11", 30.0, 22.0).dictionary == "DICT_APRILTAG_36h11"
    bad = [("charuco:4x5:DICT_NOPE", 54, 40), ("charuco:4x5:DICT_4X4_50:upside", 54, 40),
           ("charuco:4x5:DICT_4X4_1000", 54, None), ("charuco:4x5:DICT_4X4_1000", 54, 60),
           ("charuco:4x5", 54, 40), ("11x8", 20, 15), ("charuco:20x20:DICT_4X4_50", 20, 15)]
    for text, square, marker in bad:
        with pytest.raises(ValueError):
            BoardSpec.parse(text, square, marker)


def test_cache_key_tells_boards_apart(tmp_path):
    cap_dir = tmp_path / "cap" / "000"
    cap_dir.mkdir(parents=True)
    for v in range(2):
        cv2.imwrite(str(cap_dir / f"r00_c{v:02d}.png"), np.zeros((8, 8), np.uint8))
    capture = open_capture(tmp_path / "cap", (1, 2))
    inverted = dataclasses.replace(CALISCOPE, inverted=False)
    chess = BoardSpec(3, 4, 0.054)
    assert len({_cache_key(capture, b) for b in (CALISCOPE, inverted, chess)}) == 3


# -------------------------------------------------------------------------------------------- detection
def _rendered(board: BoardSpec) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's own image of the board and the pixel positions of its inner corners in that image."""
    size = (board.squares[0] * PX_PER_SQUARE + 2 * RENDER_MARGIN_PX,
            board.squares[1] * PX_PER_SQUARE + 2 * RENDER_MARGIN_PX)
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
    cv_board = cv2.aruco.CharucoBoard(board.squares, board.square_m, board.marker_m, dictionary)
    cv_board.setLegacyPattern(board.legacy_pattern)
    img = cv_board.generateImage(size, marginSize=RENDER_MARGIN_PX, borderBits=1)
    corners = RENDER_MARGIN_PX + (board.object_points()[:, :2] / board.square_m + 1.0) * PX_PER_SQUARE
    return img, corners


def _warp(img: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A perspective view of the rendering (sub-pixel corner positions by the same homography)."""
    h, w = img.shape
    src = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
    dst = np.float32([[60, 40], [w + 20, 90], [w - 30, h + 50], [30, h + 10]])
    H = cv2.getPerspectiveTransform(src, dst)  # noqa: N806
    # corner positions are pixel-centre based: warp with the same convention OpenCV uses for the image
    warped = cv2.warpPerspective(img, H, (w + 100, h + 100), flags=cv2.INTER_LINEAR, borderValue=255)
    truth = cv2.perspectiveTransform(corners.reshape(-1, 1, 2), H).reshape(-1, 2)
    return cv2.GaussianBlur(warped, (3, 3), 0.6), truth


@pytest.mark.parametrize("squares,legacy", [((5, 7), False), ((6, 6), True)])
def test_detects_rendered_board_at_true_corners(squares, legacy):
    board = BoardSpec(squares[0] - 1, squares[1] - 1, 0.03, kind="charuco", marker_m=0.022,
                      dictionary="DICT_5X5_100", legacy_pattern=legacy)
    img, corners = _rendered(board)
    warped, truth = _warp(img, corners - 0.5)  # OpenCV corners are pixel-centre based, square edges on borders
    found = detect_charuco(warped, board)
    assert found is not None and np.all(np.isfinite(found))
    np.testing.assert_allclose(found, truth, atol=SYNTH_TOL_PX)


def test_partly_covered_and_inverted_boards():
    board = BoardSpec(6, 6, 0.03, kind="charuco", marker_m=0.022, dictionary="DICT_5X5_100")
    img, corners = _rendered(board)
    covered = img.copy()
    covered[:, : RENDER_MARGIN_PX + int(2.5 * PX_PER_SQUARE)] = 255  # hide the left two and a half columns
    found = detect_charuco(covered, board)
    visible = corners[:, 0] > RENDER_MARGIN_PX + 2.5 * PX_PER_SQUARE + PX_PER_SQUARE  # a whole square in view
    assert found is not None
    got = np.isfinite(found[:, 0])
    assert np.all(got[visible]) and not np.any(got[corners[:, 0] < RENDER_MARGIN_PX + 2.5 * PX_PER_SQUARE])
    np.testing.assert_allclose(found[got], corners[got] - 0.5, atol=SYNTH_TOL_PX)
    # an inverted print is found with the flag, and not without it
    inverted = dataclasses.replace(board, inverted=True)
    assert detect_charuco(255 - img, board) is None
    np.testing.assert_allclose(detect_charuco(255 - img, inverted), corners - 0.5, atol=SYNTH_TOL_PX)


def test_too_few_or_collinear_corners_are_dropped():
    board = BoardSpec(9, 3, 0.03, kind="charuco", marker_m=0.022, dictionary="DICT_5X5_100")
    img, corners = _rendered(board)
    strip = np.full_like(img, 255)
    # keep one row of squares around the first row of corners and a sliver of the next: corners on one line
    y0, y1 = RENDER_MARGIN_PX, RENDER_MARGIN_PX + 2 * PX_PER_SQUARE
    strip[y0:y1] = img[y0:y1]
    found_ids = cv2.aruco.CharucoDetector(cv2.aruco.CharucoBoard(
        board.squares, board.square_m, board.marker_m,
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_5X5_100))).detectBoard(strip)[1]
    assert found_ids is not None and len(found_ids) >= MIN_CHARUCO_CORNERS  # OpenCV does find a line of corners
    cv_board = cv2.aruco.CharucoBoard(board.squares, board.square_m, board.marker_m,
                                      cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_5X5_100))
    assert cv_board.checkCharucoCornersCollinear(found_ids)  # ... and calls them collinear itself
    assert detect_charuco(strip, board) is None


def _caliscope_reference() -> dict[tuple[str, int], dict[int, tuple[float, float]]]:
    ref: dict = defaultdict(dict)
    with open(DATA / "caliscope_xy_CHARUCO.csv") as fh:
        for r in csv.DictReader(fh):
            ref[(r["sync_index"], int(r["cam_id"]))][int(r["keypoint_id"])] = (float(r["img_loc_x"]),
                                                                                  float(r["img_loc_y"]))
    return ref


def test_real_frames_through_detect_capture_match_caliscope():
    capture = open_capture(DATA, (1, 4))
    obs, from_cache = detect_capture(capture, CALISCOPE, jobs=1, progress=False, cache=False)
    assert not from_cache and obs.board.kind == "charuco"
    ref = _caliscope_reference()
    obj = CALISCOPE.object_points()[:, :2]
    distances, off_plane = [], []
    for f, name in enumerate(obs.frame_names):
        for v in range(obs.num_views):
            theirs = ref.get((name, v), {})
            ours = np.nonzero(obs.valid[v, f])[0]
            if len(theirs) < MIN_CORNERS_PER_BOARD:
                assert not len(ours), obs.describe(v, f)  # too few corners are dropped, not half-used
                continue
            common = sorted(set(ours.tolist()) & set(theirs))
            assert len(common) >= MIN_COMMON_CORNERS, f"{obs.describe(v, f)}: {ours} vs {sorted(theirs)}"
            distances += [np.hypot(*(obs.corners_px[v, f, i] - theirs[i])) for i in common]
            # corners only we found must sit where caliscope's corners put the board plane (a wrong id would be a
            # square or more away)
            ids = sorted(theirs)
            H, _ = cv2.findHomography(obj[ids], np.array([theirs[i] for i in ids]))  # noqa: N806
            predicted = cv2.perspectiveTransform(obj[ours].reshape(-1, 1, 2), H).reshape(-1, 2)
            step = obj[ours] + [CALISCOPE.square_m, 0.0]
            square_px = np.linalg.norm(cv2.perspectiveTransform(step.reshape(-1, 1, 2), H).reshape(-1, 2) - predicted,
                                       axis=1)
            off_plane += (np.linalg.norm(obs.corners_px[v, f, ours] - predicted, axis=1) / square_px).tolist()
    assert obs.valid.sum(axis=2).min() == 0 and (obs.valid.sum(axis=2) < obs.board.num_corners).sum() >= 3
    assert np.median(distances) < CALISCOPE_MEDIAN_TOL_PX and np.percentile(distances, 95) < CALISCOPE_P95_TOL_PX
    assert np.max(distances) < CALISCOPE_MAX_TOL_PX
    assert np.max(off_plane) < BOARD_PLANE_TOL_SQUARES


# ------------------------------------------------------------------------------------------- calibration
@pytest.mark.slow
@pytest.mark.parametrize("method", ["paper", "joint"])
def test_calibrates_from_partial_charuco_boards(method):
    """Synthetic ChArUco corners, partly outside the images as a moving board usually is; noise-free: exact."""
    scene = get_scene("small-2x2")
    rng = np.random.default_rng(3)
    calib = make_rig(scene.rig, rng)
    board = BoardSpec(11, 8, 0.020, kind="charuco", marker_m=0.015, dictionary="DICT_5X5_100")
    truth = make_checkerboard_truth(calib, dataclasses.replace(scene.checkerboard, frames=14, board=board), rng)
    corners, valid = make_corner_observations(truth, 0.0, rng, full_boards_only=False)
    # hide part of the board in half of the view-frames (occluded, or out of the image)
    ix = np.arange(board.num_corners) % board.cols
    iy = np.arange(board.num_corners) // board.cols
    for v, f in zip(*np.nonzero(rng.random(valid.shape[:2]) < 0.5), strict=True):
        cut = rng.integers(2, 6)
        valid[v, f] &= (ix >= cut) if rng.random() < 0.5 else (iy < board.rows - cut)
    valid &= valid.sum(axis=2, keepdims=True) >= MIN_CHARUCO_CORNERS  # as detect_charuco drops them
    obs = observations_from_arrays(board, calib.grid, calib.image_size_px, corners, valid)
    partial = obs.seen & (obs.valid.sum(axis=2) < board.num_corners)
    assert partial.sum() >= 5, "the scene should have partly visible boards"
    est, report = calibrate(obs, CalibrateConfig(method=method))
    err = evaluate_calibration(est, calib)
    tol = EXACT_RELATIVE if method == "joint" else PAPER_RELATIVE
    assert np.max(np.abs(err.intrinsics[:, :4])) / FOCAL_SCALE_PX < tol
    assert np.max(np.abs(err.position_mm)) / 1e3 / PITCH_M < tol
    assert report.rig_rms_px < 1e-4
