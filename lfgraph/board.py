"""Checkerboard specification (and, with the calibration pipeline, detection)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache

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
# Locating: findChessboardCorners without FAST_CHECK (the fast check missed 2 of 29 real pycalib boards); when it fails,
# findChessboardCornersSB with EXHAUSTIVE (not ACCURACY: the refinement below replaces it at a fraction of its cost).
LOCATE_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
FALLBACK_SB_FLAGS = cv2.CALIB_CB_EXHAUSTIVE
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
# cornerSubPix half windows tried, px (about x1.4 apart). No single size suits all real boards: ECoCheck marks inside
# the white squares (BoofCV trinocular) need <= 6 px, blurred 55 px squares (pycalib) want 16 px.
SUBPIX_HALF_WINDOWS_PX = (2, 3, 4, 6, 8, 11, 16, 23, 32)
SUBPIX_MAX_HALF_WINDOW_SQUARES = 0.45  # a window wider than ~0.9 squares reaches the neighbouring corners
PRESMOOTH_SIGMAS_PX = (0.0, 1.0)  # Gaussian pre-smoothing tried (0 = none): 1 px tames JPEG noise, moves no corner
MIN_CORNERS_FOR_SELECTION = 9  # below this a homography leaves too few residuals to rank windows; use the default
DEFAULT_HALF_WINDOW_SQUARES = 0.25  # window for boards too small to rank windows: a quarter square


@lru_cache(maxsize=32)
def _smoothness_basis(cols: int, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Board coordinates in [-1, 1] (C, 2) and the polynomial basis (C, T) used by `_grid_roughness_px`."""
    iy, ix = np.mgrid[0:rows, 0:cols]
    uv = np.stack([ix.ravel() / (cols - 1), iy.ravel() / (rows - 1)], axis=1) * 2.0 - 1.0
    n = cols * rows
    degree = 3 if n >= 40 else 2 if n >= 16 else 1  # keeps >= ~2 residuals per coefficient
    terms = [uv[:, 0] ** i * uv[:, 1] ** j for i in range(degree + 1) for j in range(degree + 1 - i)]
    return uv, np.stack(terms, axis=1)


def _grid_roughness_px(corners: np.ndarray, board: BoardSpec) -> float:
    """RMS of the corners about a smooth map of the board grid (homography + polynomial), px.

    Lens distortion and perspective bend the grid smoothly; corner localisation noise does not, so the residual
    ranks refinements of the same detection by their noise without needing a calibration.
    """
    uv, basis = _smoothness_basis(board.cols, board.rows)
    H, _ = cv2.findHomography(uv, corners, 0)  # noqa: N806
    if H is None:
        return float("inf")
    rest = corners - cv2.perspectiveTransform(uv.reshape(-1, 1, 2), H).reshape(-1, 2)
    coef, *_ = np.linalg.lstsq(basis, rest, rcond=None)
    return float(np.sqrt(np.mean((rest - basis @ coef) ** 2)))


def _min_spacing_px(corners: np.ndarray, board: BoardSpec) -> float:
    """Shortest distance between neighbouring corners of the grid, px."""
    grid = corners.reshape(board.rows, board.cols, 2)
    return float(min(np.min(np.linalg.norm(np.diff(grid, axis=0), axis=-1)),
                     np.min(np.linalg.norm(np.diff(grid, axis=1), axis=-1))))


def _locate_board(gray: np.ndarray, board: BoardSpec) -> np.ndarray | None:
    """(C, 2) float32 pixel-accurate corners in OpenCV's order, or None."""
    found, corners = cv2.findChessboardCorners(gray, board.pattern_size, flags=LOCATE_FLAGS)
    if not found:
        found, corners = cv2.findChessboardCornersSB(gray, board.pattern_size, flags=FALLBACK_SB_FLAGS)
        if not found:
            return None
    return corners.reshape(-1, 2).astype(np.float32)


def _refine_corners(gray: np.ndarray, corners: np.ndarray, board: BoardSpec) -> np.ndarray:
    """Sub-pixel corners: cornerSubPix over a set of windows and pre-smoothings, keep the smoothest grid.

    Returns:
        (C, 2) float64 refined corners, same order.
    """
    spacing_px = _min_spacing_px(corners, board)
    if board.num_corners < MIN_CORNERS_FOR_SELECTION:
        half = int(max(2, DEFAULT_HALF_WINDOW_SQUARES * spacing_px))
        out = corners.reshape(-1, 1, 2).astype(np.float32)
        cv2.cornerSubPix(gray, out, (half, half), (-1, -1), SUBPIX_CRITERIA)
        return out.reshape(-1, 2).astype(np.float64)
    halves = [h for h in SUBPIX_HALF_WINDOWS_PX if h <= SUBPIX_MAX_HALF_WINDOW_SQUARES * spacing_px]
    halves = halves or [SUBPIX_HALF_WINDOWS_PX[0]]
    best, best_roughness = corners.astype(np.float64), float("inf")
    for sigma in PRESMOOTH_SIGMAS_PX:
        image = cv2.GaussianBlur(gray, (0, 0), sigma) if sigma > 0 else gray
        for half in halves:
            cand = corners.reshape(-1, 1, 2).astype(np.float32)
            cv2.cornerSubPix(image, cand, (half, half), (-1, -1), SUBPIX_CRITERIA)
            cand = cand.reshape(-1, 2).astype(np.float64)
            roughness = _grid_roughness_px(cand, board)
            if roughness < best_roughness:
                best, best_roughness = cand, roughness
    return best


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

    Method: locate the board to about a pixel with ``cv2.findChessboardCorners`` (adaptive threshold, normalised
    image, no fast check), or, where that fails, ``cv2.findChessboardCornersSB`` with ``CALIB_CB_EXHAUSTIVE``. Then
    refine with ``cv2.cornerSubPix`` for each half window of `SUBPIX_HALF_WINDOWS_PX` up to
    `SUBPIX_MAX_HALF_WINDOW_SQUARES` of the square and each pre-smoothing of `PRESMOOTH_SIGMAS_PX`, and keep the
    candidate whose corners lie closest to a smooth map of the grid (`_grid_roughness_px`): the window that suits
    this image's blur, noise and square size, chosen per image.

    Measured against ``findChessboardCornersSB(EXHAUSTIVE | ACCURACY)`` on real sets (``benchmarks/detection.py``,
    per-camera k1-k2 calibration on the frames both found, leave-one-frame-out PnP error): it finds every board
    SB finds, in 3-10 % of SB's time, with a lower leave-one-out error on the OpenCV stereo, Bumblebee2 and BoofCV
    trinocular sets (e.g. trinocular 0.10 vs 0.28 px) and within 2 % of SB's on pycalib (0.312 vs 0.306 px).

    Args:
        image: (H, W) uint8 grayscale (or (H, W, 3) BGR, converted).
        board: the board to look for.

    Returns:
        (C, 2) float64 pixel positions in `BoardSpec` order, or None when the whole board is not found.
    """
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    corners = _locate_board(gray, board)
    if corners is None:
        return None
    return _canonical_order(gray, _refine_corners(gray, corners, board), board)
