"""Refusing a ``--board`` that does not match the images, in seconds, before a detection: a quick OpenCV probe
(`findChessboardCorners`) of the first frames' views for a board larger than asked or, where the asked one is not
there, the size that is."""

from __future__ import annotations

import cv2
import numpy as np

from lfgraph.detect.board import BoardSpec
from lfgraph.io.capture import CaptureError, CaptureSet

BOARD_PROBE_FRAMES = 3  # frames whose views are probed for a board of another size before the detection
BOARD_PROBE_IMAGES = 4  # at most this many images probed for a larger board around the asked one ...
BOARD_SCAN_IMAGES = 2  # ... and this many without the asked board scanned for the size that is there
_PROBE_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
PROBE_MARGIN_SQUARES = 2.5  # a board one corner larger lies within its squares of the asked board's corners


def _around_board(gray: np.ndarray, corners: np.ndarray, asked: tuple[int, int]) -> np.ndarray:
    """The part of ``gray`` within `PROBE_MARGIN_SQUARES` squares of a found board's (N, 2) corners: where a board
    one corner larger than ``asked`` would show (a search of the whole 960x960 image for a board that is not there
    took ~1.4 s, of the crop ~0.1 s)."""
    grid = corners.reshape(asked[1], asked[0], 2)
    square = max(float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2))),
                 float(np.median(np.linalg.norm(np.diff(grid, axis=0), axis=2))))
    margin = PROBE_MARGIN_SQUARES * square
    (x0, y0), (x1, y1) = corners.min(axis=0) - margin, corners.max(axis=0) + margin
    h, w = gray.shape[:2]
    return gray[max(int(y0), 0):min(int(np.ceil(y1)) + 1, h), max(int(x0), 0):min(int(np.ceil(x1)) + 1, w)]


def _refuse_larger(found_other: tuple[tuple[int, int], str] | None, asked: tuple[int, int]) -> None:
    """Raise when a probe found a board with more inner corners than asked (the asked one would be found inside it)."""
    if found_other is not None and found_other[0][0] * found_other[0][1] > asked[0] * asked[1]:
        (c, r), name = found_other
        raise CaptureError(f"{name} shows a {c}x{r} board, larger than --board {asked[0]}x{asked[1]} (found "
                           f"inside it, the asked board would sit at another offset in every frame): give the "
                           f"board's full inner-corner count (squares minus one per side)")


def check_board_size(capture: CaptureSet, board: BoardSpec) -> None:
    """Refuse, in seconds, a ``--board`` that does not match the images: a checkerboard with more inner corners
    than asked (the detector would "find" the asked board inside it, every frame at another offset), or one that is
    not in the first frames while a board of another size is (a search for a board that is not there is ~100x
    slower than one that is). A quick OpenCV probe (`findChessboardCorners`) on the views of the first
    `BOARD_PROBE_FRAMES` frames.

    Raises:
        CaptureError: the images show a board of another size (names the image and the size found).
    """
    if board.kind != "chessboard" or len(capture) == 0:
        return
    asked = (board.cols, board.rows)
    around = [(board.cols + 1, board.rows), (board.cols, board.rows + 1)]
    # sizes to scan where the asked board is not found: larger first, the asked orientation first, nearest first
    scan = sorted(((c, r) for c in range(max(3, board.cols - 2), board.cols + 4)
                   for r in range(max(3, board.rows - 2), board.rows + 4) if (c, r) != asked),
                  key=lambda cr: (-cr[0] * cr[1], (cr[0] >= cr[1]) != (asked[0] >= asked[1]),
                                  abs(cr[0] - asked[0]) + abs(cr[1] - asked[1])))
    found_asked, found_other = False, None
    probed, unscanned = 0, []
    for f in range(min(BOARD_PROBE_FRAMES, len(capture))):
        try:
            images = capture.load_frame(f)
        except Exception:  # noqa: BLE001  the detection itself reports unreadable images with their names
            return
        for v, gray in enumerate(images):
            files = capture.files[f] if capture.files else ()
            name = str(files[v] if len(files) == len(images) else files[0]) if files and files[0] is not None \
                else f"frame {f}, view {v}"
            ok, corners = cv2.findChessboardCorners(gray, asked, flags=_PROBE_FLAGS)
            if ok:
                found_asked = True
                if probed < BOARD_PROBE_IMAGES:
                    probed += 1
                    near = _around_board(gray, corners.reshape(-1, 2), asked)
                    for size in around:
                        if cv2.findChessboardCorners(near, size, flags=_PROBE_FLAGS)[0]:
                            found_other = (size, name)
                            break
            elif len(unscanned) < BOARD_SCAN_IMAGES:
                unscanned.append((gray, name))
            _refuse_larger(found_other, asked)
    # images without the asked board are scanned for the size that is there only when no probed image shows it
    # (a wide lens or a board half out of view hides it in some images: ~35 slow searches each, for nothing)
    for gray, name in unscanned if not found_asked and found_other is None else ():
        found_other = next(((size, name) for size in scan
                            if cv2.findChessboardCorners(gray, size, flags=_PROBE_FLAGS)[0]), None)
        _refuse_larger(found_other, asked)
        if found_other is not None:
            break
    if not found_asked and found_other is not None:
        (c, r), name = found_other
        raise CaptureError(f"no {asked[0]}x{asked[1]} board in the first {min(BOARD_PROBE_FRAMES, len(capture))} "
                           f"frames, but {name} shows a {c}x{r} board: check --board (inner corners, squares minus "
                           f"one per side)")
