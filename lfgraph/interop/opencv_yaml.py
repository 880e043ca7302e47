"""``opencv-yaml`` (export, import): one ``cv2.FileStorage`` YAML file.

Top level ``grid_rows``, ``grid_cols``, ``reference``, ``image_width``, ``image_height``, ``num_views``; per view
``i``: ``K_i`` (3x3), ``D_i`` (1x5: k1 k2 p1 p2 k3 with k3 = 0), ``R_i`` (3x3) and ``T_i`` (3x1, metres) with
``x_view = R_i x_ref + T_i`` (= ``calib.view_T_ref(i)``, the convention of ``cv2.stereoCalibrate``).

A stored rectification adds ``rect_image_width``, ``rect_image_height`` (the rectified image size), ``K_r`` (3x3),
and per view ``R_rect_i`` (3x3, rectified from view; the role of ``cv2.stereoRectify``'s R1/R2) and ``P_i`` (3x4) in
``cv2.stereoRectify``'s P1/P2 convention: ``P_i = [K_r | p_i]`` maps points of the *rectified reference frame*
(``x = R_rect_from_ref x_ref``, origin at the reference view's centre, as stereoRectify's frame of rectified
camera 1) to rectified pixels of view i, with ``p_i = -K_r R_rect_from_ref c_i`` and ``c_i`` the view's ideal grid
position (lfgraph's rectified projection, re-expressed). Hence
``cv2.initUndistortRectifyMap(K_i, D_i, R_rect_i, P_i, (rect_image_width, rect_image_height), m1type)`` (which uses
``P_i``'s left 3x3 as the new camera matrix) gives exactly lfgraph's rectified view i (`lfgraph.rectification
.build_maps`). Import reads the calibration, not the rectification (recompute that with ``lfgraph rectify``):
``K_r``, ``R_rect_i`` and ``P_i`` alone do not make a complete lfgraph rectification.

"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from lfgraph.calibration import Calibration
from lfgraph.geometry import invert_T, make_T
from lfgraph.grid import ViewGrid
from lfgraph.interop.common import (
    GridLike,
    array,
    build,
    check_reference_pose,
    fail,
    fit_grid,
    intrinsics,
    rotation,
    whole,
)
from lfgraph.io_utils import atomic_path
from lfgraph.rectification import stored_rectification


def rectified_projection(K_r: np.ndarray, P_lfgraph: np.ndarray) -> np.ndarray:  # noqa: N803
    """lfgraph's rectified projection (reference-frame points) in OpenCV's P1/P2 convention (rectified-frame points).

    ``P_lfgraph = K_r [R | -R c]`` with ``R = rect_R_ref``; re-expressed for ``x_rect = R x_ref`` it is
    ``P_lfgraph @ diag(R^T, 1) = [K_r | -K_r R c]``: the last column is unchanged and the left block is exactly
    ``K_r``, so it is built from those two pieces rather than by a matrix product that would round.
    """
    return np.column_stack([K_r, P_lfgraph[:, 3]])


def write(calib: Calibration, path: Path) -> None:
    rect = stored_rectification(calib)  # RectificationError (a ValueError) naming the field when incomplete
    w, h = calib.image_size_px
    with atomic_path(path) as tmp:
        # FORMAT_YAML: FileStorage would otherwise choose XML for a name that does not end in .yaml/.yml
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
        if not fs.isOpened():
            raise OSError(f"{path}: cannot be written by cv2.FileStorage")
        try:
            fs.writeComment("lfgraph calibration: views row-major; x_view = R_i x_ref + T_i (metres); "
                            "D_i = k1 k2 p1 p2 k3")
            for key, value in (("grid_rows", calib.grid.rows), ("grid_cols", calib.grid.cols),
                               ("reference", calib.grid.reference), ("image_width", w), ("image_height", h),
                               ("num_views", calib.num_views)):
                fs.write(key, int(value))
            for i in range(calib.num_views):
                intr = calib.intrinsics[i]
                view_T_ref = calib.view_T_ref(i)  # noqa: N806
                fs.write(f"K_{i}", intr.K)
                fs.write(f"D_{i}", intr.dist_cv.reshape(1, 5))
                fs.write(f"R_{i}", view_T_ref[:3, :3])
                fs.write(f"T_{i}", view_T_ref[:3, 3].reshape(3, 1))
            if rect is not None:
                fs.writeComment("rectification: initUndistortRectifyMap(K_i, D_i, R_rect_i, P_i, (rect_image_width, "
                                "rect_image_height)) gives lfgraph's rectified view i; P_i as stereoRectify's P1/P2")
                fs.write("rect_image_width", int(rect.image_size_px[0]))
                fs.write("rect_image_height", int(rect.image_size_px[1]))
                fs.write("K_r", rect.K_r)
                for i in range(calib.num_views):
                    fs.write(f"R_rect_{i}", rect.rect_R_view[i])
                    fs.write(f"P_{i}", rectified_projection(rect.K_r, rect.P[i]))
        finally:
            fs.release()


def read(path: Path, grid: GridLike) -> Calibration:
    if not path.is_file():
        raise fail(path, "file", "does not exist" if not path.exists() else "is not a file")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # OpenCV 5 raises SystemError wrapping cv2.error on a parse error
        cause = exc.__cause__ or exc
        raise fail(path, "file", f"not a readable OpenCV FileStorage file ({str(cause).strip()[:200]})") from None
    if not fs.isOpened():
        raise fail(path, "file", "cannot be opened by cv2.FileStorage")
    try:
        def node(key: str) -> cv2.FileNode:
            n = fs.getNode(key)
            if n.empty() or n.isNone():
                raise fail(path, key, "is missing")
            return n

        def integer(key: str, minimum: int) -> int:
            n = node(key)
            if not (n.isInt() or n.isReal()):
                raise fail(path, key, "must be a number")
            return whole(n.real(), path, key, minimum)

        def matrix(key: str, shape: tuple[int, ...] | None) -> np.ndarray:
            n = node(key)
            try:
                m = n.mat() if n.isMap() else None
            except cv2.error:
                m = None
            if m is None:
                raise fail(path, key, "must be an !!opencv-matrix")
            m = np.asarray(m, dtype=np.float64)
            return array(m, shape or (m.size,), path, key)

        rows, cols = integer("grid_rows", 1), integer("grid_cols", 1)
        reference = integer("reference", 0)
        size = (integer("image_width", 1), integer("image_height", 1))
        num_views = integer("num_views", 1)
        if num_views != rows * cols:
            raise fail(path, "num_views", f"is {num_views}, but grid_rows x grid_cols = {rows}x{cols} needs "
                                           f"{rows * cols}")
        try:
            file_grid = ViewGrid(rows, cols, reference)
        except ValueError as exc:
            raise fail(path, "reference", str(exc)) from None
        views, poses = [], []
        for i in range(num_views):
            K = matrix(f"K_{i}", (3, 3))  # noqa: N806
            dist = matrix(f"D_{i}", None)  # 4, 5 or more coefficients; those past p2 must be 0
            views.append(intrinsics(path, f"K_{i}, D_{i}", K, dist))
            R = rotation(matrix(f"R_{i}", (3, 3)), path, f"R_{i}")  # noqa: N806
            view_T_ref = make_T(R, matrix(f"T_{i}", (3, 1)).ravel())  # noqa: N806
            if i == reference:
                check_reference_pose(view_T_ref, path, f"R_{i}, T_{i}")
            poses.append(invert_T(view_T_ref))
    finally:
        fs.release()
    calib = build(path, "num_views", file_grid, size, views, np.stack(poses))
    return fit_grid(calib, grid, path, "num_views")
