"""Checkerboard specification (and, with the calibration pipeline, detection)."""

from __future__ import annotations

import re
from dataclasses import dataclass

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
