"""Board specification: a plain checkerboard or a ChArUco board (detection: `lfgraph.detect.chessboard`,
`lfgraph.detect.charuco`)."""

from __future__ import annotations

import re
from dataclasses import dataclass

import cv2
import numpy as np

_BOARD_RE = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")
BOARD_KINDS = ("chessboard", "charuco")
CHARUCO_FLAGS = ("legacy", "inverted")
# OpenCV's predefined dictionary names by their upper-case spelling (DICT_APRILTAG_36h11 has a lower-case h)
_DICTIONARIES = {name.upper(): name for name in dir(cv2.aruco) if name.startswith("DICT_")}


MIN_SQUARE_M, MAX_SQUARE_M = 1e-5, 10.0  # 0.01 mm .. 10 m: anything else is a unit mistake


@dataclass(frozen=True)
class BoardSpec:
    """A checkerboard given as OpenCV's ``patternSize``, or a ChArUco board (a checkerboard with ArUco markers).

    Attributes:
        cols: inner corners per board row (along board x), e.g. 11 for a 12x9-square board.
        rows: inner corners per board column (along board y), e.g. 8.
        square_m: side of one square in metres.
        margin_squares: width of the white quiet zone around the squares, in squares (for rendering).
        kind: ``"chessboard"`` (every inner corner or none) or ``"charuco"`` (any subset of corners, each
            identified by the markers around it).
        marker_m: ChArUco only: side of one ArUco marker in metres (smaller than the square).
        dictionary: ChArUco only: OpenCV's predefined dictionary name, e.g. ``"DICT_4X4_1000"``.
        legacy_pattern: ChArUco only: the board was made by OpenCV < 4.6 (different layout when the number of
            square rows is even; ``cv2.aruco.CharucoBoard.setLegacyPattern``).
        inverted: ChArUco only: printed with colours inverted (white squares and markers on black).

    Board frame: origin at the first inner corner, x along a row of corners, y along a column, z into the board
    (away from a camera that sees the printed side). Inner corner ``j = iy * cols + ix`` is at
    ``(ix * square_m, iy * square_m, 0)``, the order in which ``cv2.findChessboardCorners`` reports them. The
    square whose lower-right corner is inner corner (0, 0) is black. A ChArUco board of ``(cols + 1) x (rows + 1)``
    squares uses the same frame: corner ``j`` is ChArUco id ``j``, whose point in OpenCV's board frame
    (``getChessboardCorners``, origin at the outer board corner) is one square further along x and y.
    """

    cols: int
    rows: int
    square_m: float
    margin_squares: float = 1.0
    kind: str = "chessboard"
    marker_m: float | None = None
    dictionary: str | None = None
    legacy_pattern: bool = False
    inverted: bool = False

    def __post_init__(self) -> None:
        for name in ("cols", "rows"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer):
                raise ValueError(f"board {name} must be a whole number of inner corners, got {value!r}")
        least = 3 if self.kind == "chessboard" else 2  # OpenCV's chessboard finder needs more than 2 each way
        if self.cols < least or self.rows < least:
            raise ValueError(f"a {self.kind} board needs at least {least}x{least} inner corners, got "
                             f"{self.cols}x{self.rows}")
        if not (isinstance(self.square_m, int | float | np.floating) and MIN_SQUARE_M <= self.square_m <= MAX_SQUARE_M):
            raise ValueError(f"square size must be between {1e3 * MIN_SQUARE_M:g} mm and {MAX_SQUARE_M:g} m, got "
                             f"{self.square_m!r} m")
        if self.kind not in BOARD_KINDS:
            raise ValueError(f"board kind must be one of {', '.join(BOARD_KINDS)}, got {self.kind!r}")
        if self.kind == "chessboard":
            if self.marker_m is not None or self.dictionary is not None or self.legacy_pattern or self.inverted:
                raise ValueError("marker size, dictionary, legacy and inverted apply to ChArUco boards only")
            return
        if self.marker_m is None or not (np.isfinite(self.marker_m) and 0 < self.marker_m < self.square_m):
            raise ValueError(f"a ChArUco marker must be a positive length smaller than the square "
                             f"({self.square_m * 1000:g} mm), got {self.marker_m}")
        if not self.dictionary or not isinstance(getattr(cv2.aruco, self.dictionary, None), int) \
                or not self.dictionary.startswith("DICT_"):
            raise ValueError(f"unknown ArUco dictionary {self.dictionary!r}; use an OpenCV name such as DICT_4X4_1000")
        needed = (self.cols + 1) * (self.rows + 1) // 2  # markers sit in the white squares
        available = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary)).bytesList.shape[0]
        if needed > available:
            raise ValueError(f"a {self.squares[0]}x{self.squares[1]}-square ChArUco board needs {needed} markers, "
                             f"{self.dictionary} has {available}")

    @classmethod
    def parse(cls, pattern: str, square_mm: float, marker_mm: float | None = None) -> BoardSpec:
        """From a CLI-like board string and the square (and marker) side in millimetres.

        ``"11x8"`` is a checkerboard of 11x8 inner corners (OpenCV ``patternSize``). ``"charuco:4x5:DICT_4X4_1000"``
        is a ChArUco board of 4x5 **squares** (as ``cv2.aruco.CharucoBoard`` and board generators count them, so
        3x4 inner corners), optionally followed by ``:legacy`` and/or ``:inverted``, e.g.
        ``"charuco:4x5:DICT_4X4_1000:inverted"``; it needs ``marker_mm``.

        Raises:
            ValueError: a malformed string, an unknown dictionary or flag, a missing or too large marker.
        """
        if not isinstance(pattern, str):
            raise TypeError(f"board pattern must be a string such as '11x8', got {type(pattern).__name__}")
        parts = [p.strip() for p in pattern.split(":")]
        if parts[0].lower() != "charuco":
            m = _BOARD_RE.match(pattern)
            if not m:
                raise ValueError(f"board must be COLSxROWS inner corners such as 11x8, or "
                                 f"charuco:SQUARESXxSQUARESY:DICT_...[:legacy][:inverted], got {pattern!r}")
            if marker_mm is not None:
                raise ValueError("a marker size applies to ChArUco boards only")
            return cls(int(m.group(1)), int(m.group(2)), float(square_mm) / 1000.0)
        m = _BOARD_RE.match(parts[1]) if len(parts) >= 3 else None
        if not m:
            raise ValueError(f"a ChArUco board must be charuco:SQUARESXxSQUARESY:DICT_...[:legacy][:inverted] "
                             f"such as charuco:4x5:DICT_4X4_1000, got {pattern!r}")
        flags = {f.lower() for f in parts[3:]}
        unknown = flags - set(CHARUCO_FLAGS)
        if unknown:
            raise ValueError(f"unknown ChArUco flag(s) {', '.join(sorted(unknown))}; use {', '.join(CHARUCO_FLAGS)}")
        if marker_mm is None:
            raise ValueError("a ChArUco board needs the marker side (millimetres) as well as the square side")
        return cls(int(m.group(1)) - 1, int(m.group(2)) - 1, float(square_mm) / 1000.0, kind="charuco",
                   marker_m=float(marker_mm) / 1000.0, dictionary=_DICTIONARIES.get(parts[2].upper(), parts[2]),
                   legacy_pattern="legacy" in flags, inverted="inverted" in flags)

    @property
    def squares(self) -> tuple[int, int]:
        """(squares along x, squares along y) of the printed pattern."""
        return (self.cols + 1, self.rows + 1)

    @property
    def pattern_size(self) -> tuple[int, int]:
        """OpenCV ``patternSize`` (cols, rows)."""
        return (self.cols, self.rows)

    @property
    def is_symmetric(self) -> bool:
        """The board looks the same turned by 180° (its corner order is then ambiguous): a checkerboard with
        cols + rows even. ChArUco corners are identified by their markers, never ambiguous."""
        return self.kind == "chessboard" and (self.cols + self.rows) % 2 == 0

    @property
    def num_corners(self) -> int:
        """Number of inner corners, cols x rows (the corners OpenCV detects)."""
        return self.cols * self.rows

    def __str__(self) -> str:
        if self.kind == "charuco":
            on = (self.legacy_pattern, self.inverted)
            flags = "".join(f", {f}" for f, is_on in zip(CHARUCO_FLAGS, on, strict=True) if is_on)
            return (f"ChArUco {self.squares[0]}x{self.squares[1]} squares ({self.cols}x{self.rows} inner corners), "
                    f"{self.square_m * 1000:g} mm squares, {self.marker_m * 1000:g} mm {self.dictionary} markers"
                    f"{flags}")
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
