"""Checkerboard specification (and, with the calibration pipeline, detection)."""

from __future__ import annotations

import re
from dataclasses import dataclass

import cv2
import numpy as np

_BOARD_RE = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")


@dataclass(frozen=True)
class BoardSpec:
    """A checkerboard given as OpenCV's ``patternSize``.

    Attributes:
        cols: inner corners per board row (along board x), e.g. 11 for a 12x9-square board.
        rows: inner corners per board column (along board y), e.g. 8.
        square_m: side of one square in metres.
        margin_squares: width of the white quiet zone around the squares, in squares (for rendering).

    Board frame: origin at the first inner corner, x along a row of corners, y along a column, z into the board
    (away from a camera that sees the printed side). Inner corner ``j = iy * cols + ix`` is at
    ``(ix * square_m, iy * square_m, 0)``, the order in which ``cv2.findChessboardCorners`` reports them. The
    square whose lower-right corner is inner corner (0, 0) is black.
    """

    cols: int
    rows: int
    square_m: float
    margin_squares: float = 1.0

    def __post_init__(self) -> None:
        if self.cols < 2 or self.rows < 2:
            raise ValueError(f"a checkerboard needs at least 2x2 inner corners, got {self.cols}x{self.rows}")
        if not (np.isfinite(self.square_m) and self.square_m > 0):
            raise ValueError(f"square size must be a positive length in metres, got {self.square_m}")

    @classmethod
    def parse(cls, pattern: str, square_mm: float) -> BoardSpec:
        """From ``"11x8"`` (inner corners per row x per column) and the square side in millimetres."""
        m = _BOARD_RE.match(pattern)
        if not m:
            raise ValueError(f"board must be COLSxROWS inner corners such as 11x8, got {pattern!r}")
        return cls(int(m.group(1)), int(m.group(2)), float(square_mm) / 1000.0)

    @property
    def pattern_size(self) -> tuple[int, int]:
        """OpenCV ``patternSize`` (cols, rows)."""
        return (self.cols, self.rows)

    @property
    def is_symmetric(self) -> bool:
        """The board looks the same turned by 180° (its corner order is then ambiguous): cols + rows even."""
        return (self.cols + self.rows) % 2 == 0

    @property
    def num_corners(self) -> int:
        return self.cols * self.rows

    def __str__(self) -> str:
        return f"{self.cols}x{self.rows} inner corners, {self.square_m * 1000:g} mm squares"

    def object_points(self) -> np.ndarray:
        """(C, 3) inner-corner positions in the board frame, metres, row-major as OpenCV reports them."""
        iy, ix = np.mgrid[0 : self.rows, 0 : self.cols]
        pts = np.zeros((self.num_corners, 3))
        pts[:, 0] = ix.ravel() * self.square_m
        pts[:, 1] = iy.ravel() * self.square_m
        return pts

    def outline(self) -> np.ndarray:
        """(4, 3) corners of the printed board including its white margin, board frame, metres."""
        s, m = self.square_m, self.margin_squares
        x0, y0 = -s * (1 + m), -s * (1 + m)
        x1, y1 = s * (self.cols + m), s * (self.rows + m)
        return np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])


# ------------------------------------------------------------------------------------------------ detection
FIND_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
SUBPIX_MAX_HALF_WINDOW_PX = 6  # cornerSubPix half window; shrunk for small squares so it never spans two corners


def _canonical_order(gray: np.ndarray, corners: np.ndarray, board: BoardSpec) -> np.ndarray:
    """Put detected corners in `BoardSpec` order: OpenCV may report them reversed (the board turned by 180°).

    The square diagonally before inner corner 0 is black (`BoardSpec`), its neighbour along the first row is white.
    Reversal swaps their colours on every board whose square counts make the 180° turn change colours (e.g. 12x9
    squares). A board that looks the same turned around (both square counts even or both odd, e.g. 8x6 squares =
    7x5 inner corners) cannot tell; there corner 0 is put nearer the image's top-left than the last corner, which
    is consistent across the nearly parallel views of an array as long as the board is rolled by less than 45°.
    """
    if board.is_symmetric:
        return corners[::-1].copy() if corners[0].sum() > corners[-1].sum() else corners
    obj = board.object_points()[:, :2] / board.square_m
    H, _ = cv2.findHomography(obj, corners, 0)  # noqa: N806
    if H is None:
        return corners
    probes = np.array([[-0.5, -0.5], [0.5, -0.5]], dtype=np.float64).reshape(-1, 1, 2)
    pts = cv2.perspectiveTransform(probes, H).reshape(-1, 2)
    h, w = gray.shape
    x = np.clip(np.round(pts[:, 0]).astype(int), 0, w - 1)
    y = np.clip(np.round(pts[:, 1]).astype(int), 0, h - 1)
    dark, light = gray[y[0], x[0]], gray[y[1], x[1]]
    return corners[::-1].copy() if dark > light else corners


def detect_board(image: np.ndarray, board: BoardSpec) -> np.ndarray | None:
    """Find the checkerboard's inner corners with sub-pixel accuracy.

    ``cv2.findChessboardCorners`` (adaptive threshold, normalised image) first, ``cv2.findChessboardCornersSB`` as
    the fallback; then ``cv2.cornerSubPix`` with a window sized to the squares (the paper's Förstner refinement).

    Args:
        image: (H, W) uint8 grayscale (or (H, W, 3) BGR, converted).
        board: the board to look for.

    Returns:
        (C, 2) float64 pixel positions in `BoardSpec` order, or None when the whole board is not found.
    """
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    found, corners = cv2.findChessboardCorners(gray, board.pattern_size, flags=FIND_FLAGS)
    if not found:
        found, corners = cv2.findChessboardCornersSB(gray, board.pattern_size, flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not found:
            return None
    corners = corners.reshape(-1, 2).astype(np.float32)
    grid = corners.reshape(board.rows, board.cols, 2)
    spacing = min(np.min(np.linalg.norm(np.diff(grid, axis=0), axis=-1)),
                  np.min(np.linalg.norm(np.diff(grid, axis=1), axis=-1)))
    half = int(max(2, min(SUBPIX_MAX_HALF_WINDOW_PX, np.floor(0.45 * spacing))))
    cv2.cornerSubPix(gray, corners.reshape(-1, 1, 2), (half, half), (-1, -1), SUBPIX_CRITERIA)
    return _canonical_order(gray, corners.astype(np.float64), board)
