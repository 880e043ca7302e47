"""Board detections of a whole capture as dense ``(view, frame, corner, 2)`` tables, with a cache next to the input."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import stat
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lfgraph.core.files import OutputError, atomic_path
from lfgraph.core.grid import ViewGrid
from lfgraph.core.parallel import run_tasks
from lfgraph.detect.board import BoardSpec
from lfgraph.detect.board_probe import check_board_size
from lfgraph.detect.charuco import detect_charuco
from lfgraph.detect.chessboard import detect_board
from lfgraph.detect.wide_boards import frame_pass, pass_report, wide_models
from lfgraph.io.capture import CaptureSet

MIN_CORNERS_PER_BOARD = 6  # fewer corners of a board in a view-frame are ignored (PnP and Zhang need a spread)
CACHE_NAME = ".lfgraph-detections.npz"
CACHE_VERSION = 7  # bump when detection changes (3: ChArUco; 4: window + saddle fit; 5: video; 6: off-grid check;
#                   7: the wide-view second pass)
PLANAR_TOLERANCE_M = 1e-6  # object points with |z| above this are not a planar target in its own z = 0 plane


@dataclass(frozen=True, eq=False)
class PointBoard:
    """A planar target described only by its points, e.g. a circle grid or an AprilGrid detected by another tool.

    It answers what the calibration routes ask of a board (`object_points`, `num_corners`, `is_symmetric`), so
    detections from any detector go through both routes, the joint graph and the reports unchanged. Its point
    order is whatever the detector reports (never reordered: `is_symmetric` is False).

    Attributes:
        points_m: (C, 3) point positions in the target's frame, metres; the target must be planar with z = 0
            (OpenCV's Zhang initialisation, used by both routes, needs z = 0).
        name: a label for messages, e.g. the file the points came from.
    """

    points_m: np.ndarray
    name: str = "object points"

    kind = "points"
    is_symmetric = False

    def __post_init__(self) -> None:
        pts = np.array(self.points_m, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"{self.name}: object points must be a (C, 3) array in metres, got shape {pts.shape}")
        if pts.shape[0] < MIN_CORNERS_PER_BOARD:
            raise ValueError(f"{self.name}: a target needs at least {MIN_CORNERS_PER_BOARD} points, got {pts.shape[0]}")
        if not np.all(np.isfinite(pts)):
            raise ValueError(f"{self.name}: object points hold NaN or infinity")
        z = np.abs(pts[:, 2]).max()
        if z > PLANAR_TOLERANCE_M:
            raise ValueError(f"{self.name}: object points must lie in the target's z = 0 plane (a planar target), "
                             f"but |z| reaches {z:g} m")
        extent = np.ptp(pts[:, :2], axis=0)
        if np.linalg.matrix_rank(pts[:, :2] - pts[:, :2].mean(axis=0), tol=1e-9 * max(extent.max(), 1e-12)) < 2:
            raise ValueError(f"{self.name}: object points lie on one line; a planar target needs a 2-D spread")
        if len(np.unique(np.round(pts[:, :2], 9), axis=0)) != pts.shape[0]:
            raise ValueError(f"{self.name}: object points hold duplicates (two points at one position)")
        pts[:, 2] = 0.0
        pts.setflags(write=False)
        object.__setattr__(self, "points_m", pts)

    @property
    def num_corners(self) -> int:
        """Number of the board's points."""
        return int(self.points_m.shape[0])

    @property
    def spacing_m(self) -> float:
        """Median distance from a point to its nearest neighbour (the pitch of a grid target), metres."""
        xy = self.points_m[:, :2]
        d = np.linalg.norm(xy[:, None] - xy[None], axis=-1)
        np.fill_diagonal(d, np.inf)
        return float(np.median(d.min(axis=1)))

    def object_points(self) -> np.ndarray:
        """(C, 3) point positions in the target frame, metres (a copy)."""
        return self.points_m.copy()

    def __str__(self) -> str:
        w, h = np.ptp(self.points_m[:, :2], axis=0) * 1000
        return f"{self.num_corners} points spanning {w:g} x {h:g} mm ({self.name})"


@dataclass(frozen=True)
class BoardObservations:
    """Board corners seen by every view in every frame.

    A checkerboard is seen whole or not at all; a ChArUco board is usually seen in part, and ``valid`` says which
    of its corners were found (detection leaves a view-frame with fewer than `MIN_CORNERS_PER_BOARD` corners, or
    with corners along one line, all invalid).

    Attributes:
        board: the board (checkerboard or ChArUco), or a `PointBoard` for points detected by another tool.
        grid: the view grid.
        image_size_px: (width, height) of the views (of every view unless ``view_image_sizes_px`` says otherwise).
        corners_px: (V, F, C, 2) corner positions in pixels, NaN where not observed.
        valid: (V, F, C) which corners were observed.
        frame_names: (F,) one name per frame (for messages).
        sources: (F,) per frame the files it came from (for messages); may be empty for synthetic corners.
        view_image_sizes_px: (V,) (width, height) per view for rigs of mixed image sizes; None: all ``image_size_px``.
    """

    board: BoardSpec | PointBoard
    grid: ViewGrid
    image_size_px: tuple[int, int]
    corners_px: np.ndarray
    valid: np.ndarray
    frame_names: tuple[str, ...]
    sources: tuple[tuple[str, ...], ...] = ()
    view_image_sizes_px: tuple[tuple[int, int], ...] | None = None

    def image_size(self, view: int) -> tuple[int, int]:
        """(width, height) of one view's images."""
        return self.image_size_px if self.view_image_sizes_px is None else self.view_image_sizes_px[view]

    @property
    def image_sizes(self) -> tuple[tuple[int, int], ...]:
        """(V,) (width, height) of every view's images."""
        return tuple(self.image_size(v) for v in range(self.grid.num_views))

    def __post_init__(self) -> None:
        v, c = self.grid.num_views, self.board.num_corners
        if self.view_image_sizes_px is not None:
            sizes = tuple((int(w), int(h)) for w, h in self.view_image_sizes_px)
            if len(sizes) != v or any(w <= 0 or h <= 0 for w, h in sizes):
                raise ValueError(f"view_image_sizes_px must hold {v} positive (width, height), got "
                                 f"{self.view_image_sizes_px}")
            object.__setattr__(self, "view_image_sizes_px", None if len(set(sizes)) == 1 and sizes[0] == tuple(
                self.image_size_px) else sizes)
        corners = np.asarray(self.corners_px, dtype=np.float64)
        if corners.ndim != 4 or corners.shape[0] != v or corners.shape[2:] != (c, 2):
            raise ValueError(f"corners_px must be (V={v}, F, C={c}, 2) for a {self.grid} grid and a {self.board} "
                             f"board, got {corners.shape}")
        f = corners.shape[1]
        valid = np.asarray(self.valid, dtype=bool)
        if valid.shape != (v, f, c):
            raise ValueError(f"valid must be ({v}, {f}, {c}), got {valid.shape}")
        if not np.all(np.isfinite(corners[valid])):
            raise ValueError("corners_px holds NaN or infinity at observations marked valid")
        if len(self.frame_names) != f:
            raise ValueError(f"frame_names must have {f} entries, got {len(self.frame_names)}")
        if self.sources and len(self.sources) != f:
            raise ValueError(f"sources must have {f} entries, got {len(self.sources)}")
        corners = np.where(valid[..., None], corners, np.nan)
        corners.setflags(write=False)
        valid = valid.copy()
        valid.setflags(write=False)
        object.__setattr__(self, "corners_px", corners)
        object.__setattr__(self, "valid", valid)
        object.__setattr__(self, "frame_names", tuple(str(n) for n in self.frame_names))

    @property
    def num_views(self) -> int:
        """Number of views."""
        return self.grid.num_views

    @property
    def num_frames(self) -> int:
        """Number of frames."""
        return self.corners_px.shape[1]

    @property
    def seen(self) -> np.ndarray:
        """(V, F) the board is usable in this view-frame (at least `MIN_CORNERS_PER_BOARD` corners)."""
        return self.valid.sum(axis=2) >= MIN_CORNERS_PER_BOARD

    @property
    def num_observations(self) -> int:
        """Number of detected corners over all views and frames."""
        return int(self.valid.sum())

    def describe(self, view: int, frame: int | None = None) -> str:
        """``view r01_c02 (frame 003: path/to/file.png)`` for messages."""
        name = f"view {view} ({self.grid.name(view)})"
        if frame is None:
            return name
        where = f"frame {self.frame_names[frame]}"
        if self.sources:
            files = self.sources[frame]
            where += f", {files[view] if len(files) == self.num_views else files[0]}"
        return f"{name}, {where}"

    def subset_frames(self, frames: np.ndarray | list[int]) -> BoardObservations:
        """The observations of the given frames only (indices into the frames, in that order)."""
        idx = np.asarray(frames, dtype=int)
        return BoardObservations(self.board, self.grid, self.image_size_px, self.corners_px[:, idx],
                                 self.valid[:, idx], tuple(self.frame_names[i] for i in idx),
                                 tuple(self.sources[i] for i in idx) if self.sources else (), self.view_image_sizes_px)


def observations_from_arrays(board: BoardSpec | PointBoard, grid: ViewGrid, image_size_px: tuple[int, int],
                             corners_px: np.ndarray, valid: np.ndarray) -> BoardObservations:
    """Wrap synthetic (V, F, C, 2) corners, e.g. from `make_corner_observations`."""
    names = tuple(f"{f:03d}" for f in range(np.asarray(corners_px).shape[1]))
    return BoardObservations(board, grid, tuple(image_size_px), corners_px, valid, names)


# ------------------------------------------------------------------------------------------------- detection
def _detect_frame(task: tuple[CaptureSet, int, BoardSpec]) -> np.ndarray:
    """Worker: (V, C, 2) corners of one frame, NaN where a corner was not found. Loads one frame at a time."""
    capture, frame, board = task
    out = np.full((capture.grid.num_views, board.num_corners, 2), np.nan)
    if capture.layout == "mosaic":
        views = capture.load_frame(frame)
        images = (views[v] for v in range(capture.grid.num_views))
    else:
        images = (capture.load_view(frame, v) for v in range(capture.grid.num_views))
    detect = detect_charuco if board.kind == "charuco" else detect_board
    for v, img in enumerate(images):
        if capture.is_missing(frame, v):
            continue  # no image of this view in this frame (missing="unseen"): the board was not seen
        corners = detect(img, board)
        if corners is not None:
            out[v] = corners
    return out


def _wide_frame(task: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Worker: `lfgraph.detect.wide_boards.frame_pass` on one frame's wide views, loaded here."""
    capture, frame, board, wide, first = task
    images = capture.load_frame(frame) if capture.layout == "mosaic" else None
    return frame_pass({v: images[v] if images is not None else capture.load_view(frame, v) for v in wide.wide_views},
                      board, wide, first, frame)


def _wide_pass(capture: CaptureSet, board: BoardSpec, corners: np.ndarray, jobs: int | None,
               progress: bool) -> np.ndarray:
    """The second pass of wide views (`lfgraph.detect.wide_boards`) on the process pool, one frame per task; says what
    it found."""
    wide = wide_models(corners, board, capture.image_sizes)
    if not wide.wide_views:
        return corners
    tasks = [(capture, f, board, wide, corners[:, f]) for f in range(len(capture))]
    per_frame = run_tasks(_wide_frame, tasks, jobs, desc="wide views", unit="frame", progress=progress)
    out = np.stack([c for c, _ in per_frame], axis=1)
    report = pass_report(wide, np.sum([n for _, n in per_frame], axis=0))
    if report.wide_views:
        names = ", ".join(capture.grid.name(v) for v in report.wide_views)
        logging.getLogger("lfgraph").info(
            f"wide views ({names}): {report.recovered} boards found in a turned virtual pinhole, {report.dropped} "
            f"dropped (a corner off the view's rough fisheye model), {report.rerefined} refined again")
    return out


def _cache_key(capture: CaptureSet, board: BoardSpec) -> str:
    files = []
    # a video layout lists the same view videos for every frame: each file once, with the number of frames used
    paths = dict.fromkeys(capture.files[0]) if capture.layout == "video" else \
        (p for frame_files in capture.files for p in frame_files)
    for p in paths:
        if p is None:
            files.append(None)  # a missing view image (missing="unseen")
            continue
        st = p.stat()
        files.append([os.path.relpath(p, capture.root), st.st_size, st.st_mtime_ns])
    spec = {"version": CACHE_VERSION, "layout": capture.layout, "grid": [capture.grid.rows, capture.grid.cols],
            "board": [board.kind, board.cols, board.rows, board.square_m, board.marker_m, board.dictionary,
                      board.legacy_pattern, board.inverted], "files": files}
    if capture.layout == "video":
        spec["frames"] = len(capture)
    return hashlib.sha256(json.dumps(spec).encode()).hexdigest()


def _open_cache(path: Path) -> int | None:
    """A read-only descriptor of the cache ``path`` when it is a regular file (or a link to one), else None with a
    warning. Anything else is never opened (a FIFO put in its place blocked ``calibrate`` forever, a device would be
    read without end); the check is made again on the open file, which is opened without blocking."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK) if stat.S_ISREG(os.stat(path).st_mode) else None
    except OSError as exc:
        logging.getLogger("lfgraph").warning(f"{path}: unreadable detection cache ({exc.strerror}); detecting again")
        return None
    if fd is not None and stat.S_ISREG(os.fstat(fd).st_mode):
        return fd
    if fd is not None:
        os.close(fd)
    logging.getLogger("lfgraph").warning(f"{path}: the detection cache is not a regular file (a FIFO, device or "
                                         f"socket); ignored: detecting again, without replacing it")
    return None


def _read_cache(path: Path, key: str, shape: tuple[int, ...]) -> np.ndarray | None:
    fd = _open_cache(path)
    if fd is None:
        return None
    try:
        with os.fdopen(fd, "rb") as fh, np.load(fh) as data:
            if str(data["key"]) != key or data["corners_px"].shape != shape:
                return None
            return np.array(data["corners_px"])
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        # a damaged or foreign cache is simply recomputed (and rewritten)
        logging.getLogger("lfgraph").warning(f"{path}: unreadable detection cache ({type(exc).__name__}: {exc}); "
                                             f"detecting again")
        return None


def _write_cache(path: Path, key: str, corners: np.ndarray) -> None:
    """Write the cache atomically; never over anything but a regular file (`atomic_path`), and a folder that cannot
    be written only costs the next run a re-detection."""
    try:
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(fh, key=np.array(key), corners_px=corners)
    except (OSError, OutputError):
        pass


def detect_capture(capture: CaptureSet, board: BoardSpec, jobs: int | None = None, progress: bool = True,
                   cache: bool = True) -> tuple[BoardObservations, bool]:
    """Detect the board in every image of a capture, one frame per task on a process pool.

    The result is cached in ``INPUT/.lfgraph-detections.npz``, keyed by the board, the layout, the number of
    frames and every file's (image's or video's) name, size and modification time, so a second run does not
    re-detect and a changed image or video invalidates it. A missing view image (``missing="unseen"``) is not
    searched: the board counts as not seen there.

    Returns:
        the observations and whether they came from the cache.

    Raises:
        CaptureError: an unreadable image or one of a different size (names the file).
        TypeError: ``capture`` or ``board`` of the wrong kind (named).
    """
    if not isinstance(capture, CaptureSet):
        raise TypeError(f"detect_capture: capture must be a lfgraph capture (lfgraph.open_capture), got "
                        f"{type(capture).__name__}")
    if not isinstance(board, BoardSpec):
        raise TypeError(f"detect_capture: board must be a lfgraph.BoardSpec (e.g. BoardSpec.parse('11x8', 20)), got "
                        f"{type(board).__name__}")
    shape = (capture.grid.num_views, len(capture), board.num_corners, 2)
    cache_path = capture.root / CACHE_NAME
    key = _cache_key(capture, board) if cache else ""
    corners = _read_cache(cache_path, key, shape) if cache and os.path.lexists(cache_path) else None
    from_cache = corners is not None
    if corners is None:
        check_board_size(capture, board)
        tasks = [(capture, f, board) for f in range(len(capture))]
        per_frame = run_tasks(_detect_frame, tasks, jobs, desc="detecting", unit="frame", progress=progress)
        corners = np.stack(per_frame, axis=1)
        if board.kind != "charuco":  # wide (fisheye) views: boards the first pass missed, looked for again
            corners = _wide_pass(capture, board, corners, jobs, progress)
        if cache:
            _write_cache(cache_path, key, corners)
    valid = np.all(np.isfinite(corners), axis=-1)
    sources = tuple(tuple("(missing)" if p is None else str(p) for p in files) for files in capture.files)
    obs = BoardObservations(board, capture.grid, capture.image_size_px, corners, valid, capture.frame_names, sources,
                            capture.view_image_sizes_px)
    return obs, from_cache
