"""ChArUco boards: the OpenCV board of a `BoardSpec` and detection of its (often partly visible) corners."""

from __future__ import annotations

import functools

import cv2
import numpy as np

from lfgraph.detect.board import BoardSpec

MIN_CHARUCO_CORNERS = 6  # PnP and Zhang need at least this many corners of a board in one image
MIN_SPREAD_SQUARES = 0.3  # corners within this (RMS, in squares) of one line leave the board's tilt unknown; two rows
#                          of corners have 0.5


@functools.lru_cache(maxsize=8)
def charuco_board(board: BoardSpec) -> cv2.aruco.CharucoBoard:
    """OpenCV's board for a ChArUco `BoardSpec` (cached: detection builds it once per process)."""
    if board.kind != "charuco":
        raise ValueError(f"not a ChArUco board: {board}")
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
    cv_board = cv2.aruco.CharucoBoard(board.squares, board.square_m, board.marker_m, dictionary)
    cv_board.setLegacyPattern(board.legacy_pattern)
    return cv_board


@functools.lru_cache(maxsize=8)
def _detector(board: BoardSpec) -> cv2.aruco.CharucoDetector:
    return cv2.aruco.CharucoDetector(charuco_board(board))


def render_charuco(board: BoardSpec, px_per_square: int = 100) -> np.ndarray:
    """(H, W) uint8 image of the printed board with a one-square white margin (inverted boards as printed)."""
    margin = px_per_square
    size = (board.squares[0] * px_per_square + 2 * margin, board.squares[1] * px_per_square + 2 * margin)
    img = charuco_board(board).generateImage(size, marginSize=margin, borderBits=1)
    return 255 - img if board.inverted else img


def is_spread(points_m: np.ndarray, square_m: float) -> bool:
    """The board points do not all lie near one line (which would leave the board's tilt about it unknown)."""
    centred = points_m[:, :2] - points_m[:, :2].mean(axis=0)
    second = np.linalg.svd(centred, compute_uv=False)[-1] / np.sqrt(len(points_m))
    return bool(second >= MIN_SPREAD_SQUARES * square_m)


def detect_charuco(image: np.ndarray, board: BoardSpec) -> np.ndarray | None:
    """Find a ChArUco board's corners with ``cv2.aruco.CharucoDetector`` (sub-pixel, refined by OpenCV).

    Inverted boards are found by inverting the image: the markers and the squares between them are then the
    colours OpenCV expects (``DetectorParameters.detectInvertedMarker`` would only flip the markers, while the
    corner interpolation still needs the squares right).

    Args:
        image: (H, W) uint8 grayscale (or (H, W, 3) BGR, converted).
        board: a ChArUco board.

    Returns:
        (C, 2) float64 pixel positions in `BoardSpec` order (ChArUco id order), NaN for corners not found; None
        when fewer than `MIN_CHARUCO_CORNERS` corners are found or they lie near one line.
    """
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if board.inverted:
        gray = 255 - gray
    corners, ids, _, _ = _detector(board).detectBoard(gray)
    if ids is None or len(ids) < MIN_CHARUCO_CORNERS:
        return None
    ids = ids.ravel()
    if not is_spread(board.object_points()[ids], board.square_m):
        return None
    out = np.full((board.num_corners, 2), np.nan)
    out[ids] = corners.reshape(-1, 2)
    return out
