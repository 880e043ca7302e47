"""`detect_board` on real images (tests/data), against OpenCV's most accurate detector and the boards' own colours."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from lfgraph.detect.board import BoardSpec
from lfgraph.detect.chessboard import detect_board

DATA = Path(__file__).resolve().parents[1] / "data"
SB_ACCURATE_FLAGS = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
# Agreement with findChessboardCornersSB(EXHAUSTIVE | ACCURACY), px. Measured: median 0.06-0.16 px, RMS 0.07-0.37 px;
# the RMS comes from the outermost row or column of the 640x480 frames (up to 1.2 px there, where cornerSubPix with
# any window from 2 to 8 px and the saddle fit agree with one another): OpenCV is a reference, not the truth.
SB_AGREEMENT_MEDIAN_PX = 0.2
SB_AGREEMENT_RMS_PX = 0.5
TURN_AGREEMENT_PX = 0.05  # the same image turned by 180° must give the same physical corners
# Left-right corner offsets of a near-parallel pair vary with depth over a tilted board, by about a square on these
# close-up pairs; listing one view's corners reversed moves them by up to the whole board (8-10 squares).
STEREO_DISPARITY_SPREAD_SQUARES = 2.0
COLOUR_CONTRAST_GREY = 40  # grey-level gap between the dark and the light square at corner 0
PROBE_SQUARES = 0.25  # how far from corner 0 the square colours are read, in squares along the grid

CASES = [
    ("opencv_stereo/left01.jpg", BoardSpec(9, 6, 1.0)),
    ("opencv_stereo/right01.jpg", BoardSpec(9, 6, 1.0)),
    ("opencv_stereo/left12.jpg", BoardSpec(9, 6, 1.0)),
    ("opencv_stereo/right12.jpg", BoardSpec(9, 6, 1.0)),
    ("pycalib/00000002.jpg", BoardSpec(10, 7, 1.0)),
    ("pycalib/00000012.jpg", BoardSpec(10, 7, 1.0)),
    ("boofcv_bumblebee2/left01.jpg", BoardSpec(4, 6, 0.03)),
    ("trinocular_extra/right10.jpg", BoardSpec(13, 9, 1.0)),
]


def _load(name: str) -> np.ndarray:
    img = cv2.imread(str(DATA / name), cv2.IMREAD_GRAYSCALE)
    assert img is not None, f"missing test image {DATA / name}"
    return img


def _sb_accurate(gray: np.ndarray, board: BoardSpec) -> np.ndarray | None:
    found, corners = cv2.findChessboardCornersSB(gray, board.pattern_size, flags=SB_ACCURATE_FLAGS)
    return corners.reshape(-1, 2).astype(np.float64) if found else None


def _match_reversal(ref: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """OpenCV may list the corners from either end: turn ``ref`` to the order nearer ``corners``."""
    same = np.linalg.norm(ref - corners, axis=1).mean()
    flipped = np.linalg.norm(ref[::-1] - corners, axis=1).mean()
    return ref if same <= flipped else ref[::-1]


@pytest.mark.slow
@pytest.mark.parametrize(("name", "board"), CASES, ids=[c[0] for c in CASES])
def test_finds_the_board_where_sb_accurate_does_and_agrees_with_it(name, board):
    gray = _load(name)
    ref = _sb_accurate(gray, board)
    assert ref is not None, "premise: OpenCV's SB detector finds this board"
    corners = detect_board(gray, board)
    assert corners is not None, f"{name}: board missed"
    assert corners.shape == (board.num_corners, 2)
    dist = np.linalg.norm(corners - _match_reversal(ref, corners), axis=1)
    assert np.median(dist) <= SB_AGREEMENT_MEDIAN_PX, f"median {np.median(dist):.3f} px"
    assert np.sqrt(np.mean(dist**2)) <= SB_AGREEMENT_RMS_PX, f"RMS {np.sqrt(np.mean(dist**2)):.3f} px"


def test_finds_a_board_the_fast_check_misses():
    gray = _load("pycalib/00000012.jpg")
    board = BoardSpec(10, 7, 1.0)
    fast = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    assert not cv2.findChessboardCorners(gray, board.pattern_size, flags=fast)[0], "premise: the fast check misses it"
    assert detect_board(gray, board) is not None


def test_finds_a_board_only_the_sb_detector_sees():
    gray = _load("trinocular_extra/right10.jpg")
    board = BoardSpec(13, 9, 1.0)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    assert not cv2.findChessboardCorners(gray, board.pattern_size, flags=flags)[0], "premise: needs the fallback"
    assert detect_board(gray, board) is not None


@pytest.mark.parametrize(("name", "board"), [c for c in CASES if not c[1].is_symmetric],
                         ids=[c[0] for c in CASES if not c[1].is_symmetric])
def test_corner_zero_follows_the_board_colours(name, board):
    """`BoardSpec`: the square diagonally before corner 0 is black, its neighbour along the first row is white."""
    gray = _load(name)
    corners = detect_board(gray, board)
    grid = corners.reshape(board.rows, board.cols, 2)
    along_row, along_col = grid[0, 1] - grid[0, 0], grid[1, 0] - grid[0, 0]
    # a quarter square in: the outer squares of a printed board may be cut short (OpenCV's own sample board is)
    dark_at = grid[0, 0] - PROBE_SQUARES * (along_row + along_col)
    light_at = grid[0, 0] + PROBE_SQUARES * (along_row - along_col)

    def grey(p):
        x, y = np.round(p).astype(int)
        return float(np.median(gray[y - 1 : y + 2, x - 1 : x + 2]))

    assert grey(light_at) - grey(dark_at) >= COLOUR_CONTRAST_GREY


@pytest.mark.parametrize(("name", "board"), [c for c in CASES if not c[1].is_symmetric],
                         ids=[c[0] for c in CASES if not c[1].is_symmetric])
def test_order_does_not_depend_on_image_orientation(name, board):
    gray = _load(name)
    corners = detect_board(gray, board)
    h, w = gray.shape
    turned = detect_board(np.ascontiguousarray(gray[::-1, ::-1]), board)
    assert turned is not None
    back = np.column_stack([w - 1 - turned[:, 0], h - 1 - turned[:, 1]])
    assert np.max(np.linalg.norm(back - corners, axis=1)) <= TURN_AGREEMENT_PX


@pytest.mark.parametrize("pair", ["01", "12"])
def test_stereo_views_list_the_same_physical_corners(pair):
    board = BoardSpec(9, 6, 1.0)
    left = detect_board(_load(f"opencv_stereo/left{pair}.jpg"), board)
    right = detect_board(_load(f"opencv_stereo/right{pair}.jpg"), board)
    spacing = np.median(np.linalg.norm(np.diff(left.reshape(board.rows, board.cols, 2), axis=1), axis=-1))
    offsets = right - left  # a near-parallel pair: about one disparity for every corner, unless the order flipped
    spread = np.max(np.linalg.norm(offsets - np.median(offsets, axis=0), axis=1))
    assert spread <= STEREO_DISPARITY_SPREAD_SQUARES * spacing, f"spread {spread / spacing:.2f} squares"


# Rendered boards, where the true corners are known: blurred and noisy like a real capture.
RENDERED_RMS_LIMIT_PX = 0.05  # tests/detect/test_checkerboard.py's limit, here on a blurrier, noisier render


def test_rendered_blurred_boards_are_at_least_as_accurate_as_sb_accurate():
    from lfgraph.datasets.checkerboard import CheckerboardConfig, iter_view_images, make_checkerboard_truth
    from lfgraph.datasets.rig import RigConfig, make_rig

    calib = make_rig(RigConfig(rows=1, cols=2, image_size_px=(640, 480), focal_px=600, k1=-0.12, pitch_m=0.01),
                     np.random.default_rng(0))
    cfg = CheckerboardConfig(board=BoardSpec(9, 6, 0.02), frames=4, distance_m=(0.35, 0.6), blur_sigma_px=1.5,
                             noise_sigma=2.0)
    truth = make_checkerboard_truth(calib, cfg, np.random.default_rng(1))
    ours, sb = [], []
    for v in range(calib.num_views):
        for f, img in iter_view_images(calib, truth, cfg, seed=0, view=v):
            if not truth.board_visible[v, f]:
                continue
            true_px = truth.corners_px[v, f]
            corners = detect_board(img, cfg.board)
            ref = _sb_accurate(img, cfg.board)
            assert corners is not None and ref is not None
            ours.append(np.sum((corners - true_px) ** 2, axis=1))
            sb.append(np.sum((_match_reversal(ref, true_px) - true_px) ** 2, axis=1))
    assert len(ours) >= 4, "premise: enough visible boards"
    rms_ours, rms_sb = (float(np.sqrt(np.mean(np.concatenate(e)))) for e in (ours, sb))
    assert rms_ours <= RENDERED_RMS_LIMIT_PX, f"{rms_ours:.4f} px"
    assert rms_ours <= rms_sb, f"ours {rms_ours:.4f} px, SB {rms_sb:.4f} px"
