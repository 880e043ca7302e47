"""Detections made by other tools (circle grids, AprilGrids, any detector) read as `BoardObservations`.

Two formats (`DETECTION_FORMATS`):

- ``opencv-multiview``: a folder with one ``cam_*.json`` per view (views in natural name order, row-major in the
  grid), each an OpenCV FileStorage JSON file with one node ``frame_N`` per frame that camera saw the target in:
  2C numbers ``x0, y0, x1, y1, ...`` in the order of the object points (a flat sequence, or an ``opencv-matrix``
  of 2C numbers). A missing node means the target was not seen in frame N; a point given as ``(-1, -1)`` or NaN
  was not detected. Other nodes are ignored. The (C, 3) object points come separately (`load_object_points`).
- ``npz``: one numpy archive with ``object_points`` (C, 3) metres, ``image_points`` (V, F, C, 2) pixels and
  ``valid`` (V, F, C) booleans (`write_points_npz` writes it).

Every observed point must lie inside the image (``image_size_px``, with a one-pixel margin). As for detection,
a view-frame with fewer than `MIN_CORNERS_PER_BOARD` points, or points along one line, counts as not seen.
"""

from __future__ import annotations

import logging
import os
import re
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from lfgraph.core.files import atomic_path, input_problem
from lfgraph.core.grid import ViewGrid
from lfgraph.detect.charuco import is_spread
from lfgraph.detect.detections import MIN_CORNERS_PER_BOARD, BoardObservations, PointBoard

DETECTION_FORMATS = ("opencv-multiview", "npz")
MULTIVIEW_GLOB = "cam_*.json"
IMAGE_MARGIN_PX = 1.0  # observed points may lie this far outside the image (sub-pixel corners at the border)
_FRAME_RE = re.compile(r"^frame_(\d+)$")
NPZ_KEYS = ("object_points", "image_points", "valid")
MAX_TARGET_SPAN_M = 20.0  # object points spanning more than this are not a calibration target in metres
SUSPECT_SPACING_M = 1.0  # object points further apart than this are probably in millimetres, not metres
log = logging.getLogger(__name__)


class PointsError(ValueError):
    """Detections that cannot be used; the message names the file and the field."""


def _natural_key(name: str) -> list:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _grid(grid: ViewGrid | tuple[int, int]) -> ViewGrid:
    return grid if isinstance(grid, ViewGrid) else ViewGrid(*grid)


def load_object_points(path: str | os.PathLike) -> PointBoard:
    """The (C, 3) object points in metres of a ``.npy`` file, as a `PointBoard`.

    Raises:
        PointsError: an unreadable file, a wrong shape, non-finite or non-planar points (names the file).
    """
    path = Path(path)
    problem = input_problem(path)
    if problem:
        raise PointsError(f"{path}: {problem}")
    try:
        pts = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise PointsError(f"{path}: cannot read object points as a .npy array ({exc})") from None
    if not isinstance(pts, np.ndarray) or pts.dtype.kind not in "fiu":
        raise PointsError(f"{path}: object points must be a numeric (C, 3) array in metres")
    try:
        board = PointBoard(pts, path.name)
    except ValueError as exc:
        raise PointsError(str(exc)) from None
    return check_metres(board, pts, str(path))


def check_metres(board: PointBoard, pts: np.ndarray, where: str) -> PointBoard:
    """Refuse object points that span more than `MAX_TARGET_SPAN_M` (millimetres taken for metres); warn when
    neighbours are more than `SUSPECT_SPACING_M` apart."""
    span = float(np.max(np.ptp(np.asarray(pts, dtype=float).reshape(-1, 3), axis=0)))
    if span > MAX_TARGET_SPAN_M:
        raise PointsError(f"{where}: the object points span {span:g} m, larger than any calibration target: they "
                          f"look like millimetres; object points must be in metres (divide by 1000)")
    if board.spacing_m > SUSPECT_SPACING_M:
        log.warning("%s: neighbouring object points are %g m apart; object points must be in metres (millimetres "
                    "give a rig %gx too large)", where, board.spacing_m, 1000)
    return board


def _first_outside(points: np.ndarray, valid: np.ndarray, image_size_px: tuple[int, int]) -> tuple[int, ...] | None:
    """Index of the first valid point outside the image (with `IMAGE_MARGIN_PX`), None when all are inside."""
    w, h = image_size_px
    m = IMAGE_MARGIN_PX
    x, y = points[..., 0], points[..., 1]
    outside = valid & ((x < -0.5 - m) | (y < -0.5 - m) | (x > w - 0.5 + m) | (y > h - 0.5 + m))
    return tuple(int(i[0]) for i in np.nonzero(outside)) if outside.any() else None


def _outside_message(where: str, p: np.ndarray, image_size_px: tuple[int, int]) -> str:
    return (f"{where} at ({p[0]:.1f}, {p[1]:.1f}) px lies outside the {image_size_px[0]}x{image_size_px[1]} image; "
            f"check --image-size")


def _drop_unusable(board: PointBoard, valid: np.ndarray) -> tuple[np.ndarray, int]:
    """(V, F, C) valid with view-frames of too few or collinear points cleared; and how many were cleared."""
    valid = valid.copy()
    obj = board.object_points()
    spacing = board.spacing_m
    dropped = 0
    for v, f in zip(*np.nonzero(valid.any(axis=2)), strict=True):
        mask = valid[v, f]
        if mask.sum() < MIN_CORNERS_PER_BOARD or not is_spread(obj[mask], spacing):
            valid[v, f] = False
            dropped += 1
    return valid, dropped


ImageSizes = tuple[int, int] | tuple[tuple[int, int], Mapping[str | int, tuple[int, int]]]


def view_sizes(image_size_px: ImageSizes, grid: ViewGrid) -> tuple[tuple[int, int], list[tuple[int, int]]]:
    """The rig's (width, height) and each view's, from one size or ``(default, {view name or index: size})``.

    Raises:
        PointsError: a per-view size for a view the grid does not have.
    """
    if len(image_size_px) == 2 and isinstance(image_size_px[1], Mapping):
        default, per_view = image_size_px
    else:
        default, per_view = image_size_px, {}
    default = (int(default[0]), int(default[1]))
    sizes = [default] * grid.num_views
    for key, size in per_view.items():
        v = grid.find(key, "image size", PointsError)
        sizes[v] = (int(size[0]), int(size[1]))
    return default, sizes


def _observations(board: PointBoard, grid: ViewGrid, image_size_px: ImageSizes, points: np.ndarray,
                  valid: np.ndarray, frame_names: tuple[str, ...], sources: tuple[str, ...]) -> BoardObservations:
    valid, _ = _drop_unusable(board, valid)
    per_frame = tuple(tuple(sources) for _ in frame_names)
    default, sizes = view_sizes(image_size_px, grid)
    return BoardObservations(board, grid, default, np.where(valid[..., None], points, np.nan), valid, frame_names,
                             per_frame, tuple(sizes))


def _read_node(node, path: Path, name: str, n_points: int) -> np.ndarray:
    """(C, 2) points of one ``frame_N`` node (a flat sequence or an opencv-matrix of 2C numbers)."""
    if node.isMap():
        mat = node.mat()
        if mat is None:
            raise PointsError(f"{path}: node {name} is a map but not an opencv-matrix of {2 * n_points} numbers")
        values = np.asarray(mat, dtype=np.float64).ravel()
    elif node.isSeq():
        values = np.empty(node.size())
        for i in range(node.size()):
            item = node.at(i)
            if not (item.isReal() or item.isInt()):
                raise PointsError(f"{path}: node {name}, element {i} is not a number")
            values[i] = item.real()
    else:
        raise PointsError(f"{path}: node {name} must be a sequence of {2 * n_points} numbers (x, y per object "
                          f"point), not a single value or string")
    if values.size != 2 * n_points:
        raise PointsError(f"{path}: node {name} holds {values.size} numbers, expected {2 * n_points} "
                          f"(x, y for each of the {n_points} object points)")
    return values.reshape(n_points, 2)


def _read_multiview_file(path: Path, n_points: int) -> dict[int, np.ndarray]:
    import json

    import cv2

    problem = input_problem(path)
    if problem:
        raise PointsError(f"{path}: {problem}")
    try:  # OpenCV's JSON reader crashes the process on deeply nested input: Python's parser vets it first
        json.loads(path.read_text(encoding="utf-8"))
    except RecursionError:
        raise PointsError(f"{path}: nested too deeply to be OpenCV FileStorage JSON") from None
    except (ValueError, OSError, UnicodeDecodeError):
        pass  # OpenCV's own reader gives the message (its JSON dialect is not always strict JSON)

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_FORMAT_JSON)
    except (cv2.error, SystemError) as exc:  # cv2 may wrap its parse error in a SystemError
        text = str(exc.__cause__ or exc.__context__ or exc).strip()
        msg = text.splitlines()[-1] if text else "parse error"
        raise PointsError(f"{path}: not a readable OpenCV FileStorage JSON file ({msg})") from None
    if not fs.isOpened():
        raise PointsError(f"{path}: cannot open this file")
    try:
        root = fs.root()
        if not root.isMap():
            raise PointsError(f"{path}: the top level must be a JSON object of frame_N nodes")
        frames = {}
        for name in root.keys():
            m = _FRAME_RE.match(name)
            if m:
                frames[int(m.group(1))] = _read_node(root.getNode(name), path, name, n_points)
        return frames
    finally:
        fs.release()


def read_opencv_multiview(folder: str | os.PathLike, board: PointBoard, grid: ViewGrid | tuple[int, int],
                          image_size_px: ImageSizes) -> BoardObservations:
    """Read OpenCV's multi-view calibration points: one ``cam_*.json`` per view (see the module docstring).

    Frames are ``0 .. max N`` over all files; a frame no camera saw stays in the observations, unseen.

    Raises:
        PointsError: no ``cam_*.json`` files, a count that does not match the grid, an unreadable file, a
            malformed node, a node with the wrong number of numbers, a point outside the image.
    """
    folder = Path(folder)
    grid = _grid(grid)
    if not folder.is_dir():
        raise PointsError(f"{folder}: the opencv-multiview detections must be a folder of {MULTIVIEW_GLOB} files")
    files = sorted(folder.glob(MULTIVIEW_GLOB), key=lambda p: _natural_key(p.name))
    if not files:
        raise PointsError(f"{folder}: no {MULTIVIEW_GLOB} files (one per view, OpenCV FileStorage JSON)")
    if len(files) != grid.num_views:
        raise PointsError(f"{folder}: {len(files)} {MULTIVIEW_GLOB} files ({', '.join(p.name for p in files)}) but "
                          f"the {grid} grid has {grid.num_views} views")
    c = board.num_corners
    per_view = [_read_multiview_file(p, c) for p in files]
    indices = [i for frames in per_view for i in frames]
    if not indices:
        raise PointsError(f"{folder}: no frame_N nodes in any {MULTIVIEW_GLOB} file")
    n_frames = max(indices) + 1
    points = np.full((grid.num_views, n_frames, c, 2), np.nan)
    for v, frames in enumerate(per_view):
        for f, pts in frames.items():
            points[v, f] = pts
    missing = np.all(points == -1.0, axis=-1)  # OpenCV's marker for a point not detected
    valid = np.all(np.isfinite(points), axis=-1) & ~missing
    _, sizes = view_sizes(image_size_px, grid)
    for v, p in enumerate(files):
        bad = _first_outside(points[v], valid[v], sizes[v])
        if bad is not None:
            raise PointsError(_outside_message(f"{p}: node frame_{bad[0]}, point {bad[1]}", points[v][bad],
                                               sizes[v]))
    names = tuple(f"frame_{f}" for f in range(n_frames))
    return _observations(board, grid, image_size_px, points, valid, names, tuple(str(p) for p in files))


def read_points_npz(path: str | os.PathLike, grid: ViewGrid | tuple[int, int],
                    image_size_px: ImageSizes) -> BoardObservations:
    """Read the ``.npz`` of `NPZ_KEYS` (see the module docstring).

    Raises:
        PointsError: an unreadable file, a missing key, wrong shapes or types, a view count that does not match
            the grid, NaN at a valid point, a point outside the image.
    """
    path = Path(path)
    grid = _grid(grid)
    problem = input_problem(path)
    if problem:
        raise PointsError(f"{path}: {problem}")
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in NPZ_KEYS if k not in data.files]
            if missing:
                raise PointsError(f"{path}: missing {', '.join(missing)} (an lfgraph points .npz holds "
                                  f"{', '.join(NPZ_KEYS)})")
            arrays = {k: np.asarray(data[k]) for k in NPZ_KEYS}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        if isinstance(exc, PointsError):
            raise
        raise PointsError(f"{path}: cannot read as a numpy .npz archive ({exc})") from None
    try:
        board = PointBoard(arrays["object_points"], f"{path.name}: object_points")
    except ValueError as exc:
        raise PointsError(f"{path}: {exc}") from None
    check_metres(board, arrays["object_points"], f"{path}: object_points")
    pts, valid = arrays["image_points"], arrays["valid"]
    c = board.num_corners
    if pts.dtype.kind not in "fiu" or pts.ndim != 4 or pts.shape[2:] != (c, 2):
        raise PointsError(f"{path}: image_points must be numeric (V, F, C={c}, 2), got {pts.dtype} {pts.shape}")
    if pts.shape[0] != grid.num_views:
        raise PointsError(f"{path}: image_points has {pts.shape[0]} views but the {grid} grid has {grid.num_views}")
    if valid.dtype.kind not in "biu" or valid.shape != pts.shape[:3]:
        raise PointsError(f"{path}: valid must be booleans of shape {pts.shape[:3]}, got {valid.dtype} {valid.shape}")
    if valid.dtype.kind != "b" and not np.isin(valid, (0, 1)).all():
        raise PointsError(f"{path}: valid must hold only 0/1 (or booleans)")
    valid = valid.astype(bool)
    pts = pts.astype(np.float64)
    bad = valid & ~np.all(np.isfinite(pts), axis=-1)
    if bad.any():
        v, f, j = (int(i[0]) for i in np.nonzero(bad))
        raise PointsError(f"{path}: image_points[{v}, {f}, {j}] is not finite but valid says it was observed")
    _, sizes = view_sizes(image_size_px, grid)
    for v in range(grid.num_views):
        bad = _first_outside(pts[v], valid[v], sizes[v])
        if bad is not None:
            raise PointsError(_outside_message(f"{path}: image_points[{v}, {bad[0]}, {bad[1]}]", pts[v][bad],
                                               sizes[v]))
    names = tuple(f"{f:03d}" for f in range(pts.shape[1]))
    return _observations(board, grid, image_size_px, pts, valid, names, (str(path),))


def load_detections(path: str | os.PathLike, fmt: str, grid: ViewGrid | tuple[int, int],
                    image_size_px: ImageSizes, object_points: str | os.PathLike | None = None
                    ) -> BoardObservations:
    """Detections in one of `DETECTION_FORMATS`; ``object_points`` (a ``.npy``) is needed by, and only by,
    ``opencv-multiview``."""
    if fmt not in DETECTION_FORMATS:
        raise PointsError(f"unknown detections format {fmt!r}; choose from {', '.join(DETECTION_FORMATS)}")
    if fmt == "npz":
        if object_points is not None:
            raise PointsError(f"{path}: a points .npz carries its own object_points; drop --object-points")
        return read_points_npz(path, grid, image_size_px)
    if object_points is None:
        raise PointsError("opencv-multiview detections need the object points (--object-points OBJ.npy, (C, 3) m)")
    return read_opencv_multiview(path, load_object_points(object_points), grid, image_size_px)


def write_points_npz(path: str | os.PathLike, obs: BoardObservations) -> Path:
    """Write observations as the ``.npz`` `read_points_npz` reads (atomically). Returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, object_points=obs.board.object_points(),
                            image_points=np.where(obs.valid[..., None], obs.corners_px, np.nan),
                            valid=obs.valid)
    return path
