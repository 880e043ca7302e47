"""Calibration import and export in other tools' formats ("interoperability").

Two entry points: `export_calibration(calib, fmt, path)` and `import_calibration(path, fmt, grid)`. Every file is
written atomically (a temporary sibling renamed onto the final name), so a crash never leaves half a file.

Formats (views are always row-major on the grid; poses are in metres; pixels follow OpenCV's convention, the centre
of the top-left pixel is ``(0, 0)``, except where a format says otherwise):

``opencv-yaml`` (export, import)
    One ``cv2.FileStorage`` YAML file. Top level ``grid_rows``, ``grid_cols``, ``reference``, ``image_width``,
    ``image_height``, ``num_views``; per view ``i``: ``K_i`` (3x3), ``D_i`` (1x5: k1 k2 p1 p2 k3 with k3 = 0),
    ``R_i`` (3x3) and ``T_i`` (3x1, metres) with ``x_view = R_i x_ref + T_i`` (= ``calib.view_T_ref(i)``, the
    convention of ``cv2.stereoCalibrate``). A stored rectification adds ``K_r`` (3x3), ``R_rect_i`` (3x3, rectified
    from view) and ``P_i`` (3x4). Import reads the calibration, not the rectification (recompute that with
    ``lfgraph rectify``): ``K_r``, ``R_rect_i`` and ``P_i`` alone do not make a complete lfgraph rectification.
``kalibr`` (export, import)
    Kalibr's ``camchain.yaml``: ``cam0 .. camN-1`` in row-major view order, each with ``camera_model: pinhole``,
    ``intrinsics: [fu, fv, pu, pv]``, ``distortion_model: radtan``, ``distortion_coeffs: [k1, k2, p1, p2]``,
    ``resolution: [w, h]`` and a ``rostopic``; ``cam1 ..`` also hold ``T_cn_cnm1`` (4x4), which maps points of
    camera n-1 into camera n: ``view_T_ref(n) @ inv(view_T_ref(n-1))``. Kalibr stores neither grid nor reference,
    so import needs ``grid``; the chain is re-expressed relative to the grid's reference view (view 0 when ``grid``
    is a plain ``(rows, cols)``). Written as plain text (PyYAML is not a dependency) with floats that always hold a
    ``.``, so PyYAML's YAML 1.1 resolver, which Kalibr uses, reads them as floats; read back with a small parser
    of exactly this subset (block mappings, flow lists, block lists of flow lists, ``#`` comments).
    ``distortion_model: none`` is read as zero distortion; ``equidistant`` and ``fov`` are refused.
``colmap`` (export, import)
    A COLMAP (>= 3.12) text model folder. ``cameras.txt`` holds one ``OPENCV`` camera per view, camera ID = view
    index + 1: ``CAMERA_ID OPENCV W H fx fy cx cy k1 k2 p1 p2``. COLMAP puts the centre of the top-left pixel at
    ``(0.5, 0.5)`` (COLMAP docs, database format), so ``cx``, ``cy`` are written +0.5 px and read back -0.5 px.
    ``rigs.txt`` is COLMAP's own rig file (doc/format.rst): one rig whose reference sensor is the reference
    view's camera and whose other sensors carry ``sensor_from_rig`` = ``view_T_ref(i)`` as a Hamilton unit
    quaternion ``QW QX QY QZ`` and a translation ``TX TY TZ`` (metres). A comment line ``# lfgraph grid: RxC``
    records the grid, which COLMAP cannot; without it import needs ``grid``. Empty ``frames.txt``, ``images.txt``
    and ``points3D.txt`` make the folder a complete (image-less) model. Import also takes ``PINHOLE``,
    ``SIMPLE_PINHOLE``, ``SIMPLE_RADIAL`` and ``RADIAL`` cameras; camera IDs in increasing order become the
    row-major views. Export replaces an existing folder only when it holds nothing but COLMAP model files.
``json`` (export, import)
    lfgraph's own ``calibration.json`` (`Calibration.save` / `Calibration.load`), the only format that keeps the
    rectification and the metrics.
``middlebury`` (import)
    Middlebury 2014 ``calib.txt`` (or the scene folder holding it): ``cam0=[f 0 cx0; 0 f cy; 0 0 1]``, ``cam1=..``,
    ``baseline=`` (mm), ``width=``, ``height=`` and others (``doffs``, ``ndisp``, ... are not needed). A rectified
    1x2 grid: cam1 sits ``baseline`` to the right of cam0 with the same orientation, ``x_view1 = x_ref - [b, 0, 0]``;
    no distortion. Assumes Middlebury pixels follow OpenCV's convention (its ``doffs = cx1 - cx0`` does not depend
    on it).
``hci`` (import)
    The HCI 4D light-field benchmark's ``parameters.cfg`` (or the scene folder holding it), an INI file.
    ``[intrinsics]``: ``focal_length_mm``, ``sensor_size_mm``, ``image_resolution_x_px``, ``image_resolution_y_px``;
    ``[extrinsics]``: ``num_cams_x`` (columns), ``num_cams_y`` (rows), ``baseline_mm``. Focal length in pixels =
    ``focal_length_mm / sensor_size_mm * max(width, height)`` (Blender's automatic sensor fit); principal point at
    the image centre ``((w - 1) / 2, (h - 1) / 2)``; no distortion; parallel views on a regular grid of pitch
    ``baseline_mm``, row-major, column index along camera +x (right), row index along camera +y (down); reference
    = the top-left view unless ``grid`` names another. Assumptions: the benchmark renders with shifted sensors
    so that disparity is zero at ``focus_distance_m``; that shift is not modelled here (disparities measured with
    this calibration differ from HCI's ground truth by a constant), and ``center_cam_*`` (the rig's place in the
    Blender scene), ``fstop`` and ``[meta]`` are not used.

Grids on import: ``grid`` is a `ViewGrid`, a ``(rows, cols)`` pair or None. Its view count and shape must match
the file's (the error names the file and the key). A `ViewGrid` whose reference differs from the file's re-expresses
all poses relative to that view (refused when the file holds a rectification, which is tied to its reference);
a ``(rows, cols)`` pair keeps the file's reference.
"""

from __future__ import annotations

import configparser
import math
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import gtsam
import numpy as np

from lfgraph.calibration import REFERENCE_POSE_TOLERANCE, Calibration, CalibrationFileError
from lfgraph.camera import Intrinsics
from lfgraph.geometry import invert_T, is_rotation, make_T
from lfgraph.grid import ViewGrid
from lfgraph.io_utils import atomic_path, write_text_atomic

EXPORT_FORMATS: tuple[str, ...] = ("opencv-yaml", "kalibr", "colmap", "json")
IMPORT_FORMATS: tuple[str, ...] = (*EXPORT_FORMATS, "middlebury", "hci")

MM_PER_M = 1000.0
COLMAP_PIXEL_OFFSET_PX = 0.5  # COLMAP's centre of the top-left pixel is (0.5, 0.5), OpenCV's (0, 0)
QUATERNION_NORM_TOLERANCE = 1e-3  # |q| may differ from 1 by this (rounded text) before a quaternion is refused
HOMOGENEOUS_ROW_TOLERANCE = 1e-9  # the last row of a 4x4 transform must be [0, 0, 0, 1] to this
COLMAP_MODEL_FILES = frozenset(f"{name}.{ext}" for name in ("rigs", "cameras", "frames", "images", "points3D")
                               for ext in ("txt", "bin"))
KALIBR_DISTORTION_MODELS = ("radtan", "none")
# COLMAP camera model -> names of its parameters, in file order (src/colmap/sensor/models.h)
COLMAP_CAMERA_MODELS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}

GridLike = ViewGrid | Sequence[int] | None
PathLike = str | os.PathLike


# ============================================================================================== entry points
def export_calibration(calib: Calibration, fmt: str, path: PathLike) -> Path:
    """Write a calibration in another tool's format (see the module docstring for each format).

    Args:
        calib: the calibration to write.
        fmt: one of `EXPORT_FORMATS`: ``opencv-yaml``, ``kalibr``, ``colmap``, ``json``.
        path: the output file; for ``colmap`` a folder (created, or replaced if it holds only COLMAP model files).

    Returns:
        The path written.

    Raises:
        ValueError: unknown format, a rectification of the wrong shape, or a ``colmap`` folder that holds other
            files.
        OSError: the output cannot be written.
    """
    writer = _WRITERS.get(fmt)
    if writer is None:
        raise ValueError(f"unknown export format {fmt!r}; valid formats: {', '.join(EXPORT_FORMATS)}")
    out = Path(path)
    writer(calib, out)
    return out


def import_calibration(path: PathLike, fmt: str, grid: GridLike = None) -> Calibration:
    """Read a calibration written by another tool (see the module docstring for each format).

    Args:
        path: the file (for ``colmap`` the model folder; for ``middlebury`` and ``hci`` also the scene folder).
        fmt: one of `IMPORT_FORMATS`: ``opencv-yaml``, ``kalibr``, ``colmap``, ``json``, ``middlebury``, ``hci``.
        grid: the view grid, as a `ViewGrid` (its reference becomes the calibration's reference) or ``(rows, cols)``
            (the file's reference is kept); required for ``kalibr`` and for a ``colmap`` folder without the
            ``# lfgraph grid`` comment, optional (and then checked against the file) otherwise.

    Returns:
        The calibration, row-major views, poses relative to the reference view. Metrics are empty and the
        rectification None for every format but ``json``.

    Raises:
        ValueError: unknown format. `CalibrationFileError` (a ValueError) naming the file and the key: a missing
            file or key, a malformed or non-finite number, a matrix of the wrong shape or not a rotation, a grid
            whose shape or view count does not match the file.
    """
    reader = _READERS.get(fmt)
    if reader is None:
        raise ValueError(f"unknown import format {fmt!r}; valid formats: {', '.join(IMPORT_FORMATS)}")
    return reader(Path(path), grid)


# ============================================================================================== shared helpers
def _fail(path: PathLike | None, key: str, problem: str) -> CalibrationFileError:
    return CalibrationFileError(path, key, problem)


def _read_text(path: Path) -> str:
    if not path.exists():
        raise _fail(path, "file", "does not exist")
    if path.is_dir():
        raise _fail(path, "file", "is a folder, expected a file")
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise _fail(path, "file", f"cannot be read ({exc})") from None


def _in_folder(path: Path, filename: str) -> Path:
    """``path`` itself, or ``path / filename`` when ``path`` is a folder (a Middlebury or HCI scene)."""
    return path / filename if path.is_dir() else path


def _finite(value: Any, path: PathLike, key: str) -> float:
    """A finite float from a number or numeric text; anything else raises naming the key."""
    if isinstance(value, bool):
        raise _fail(path, key, f"must be a number, got {value!r}")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise _fail(path, key, f"must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise _fail(path, key, f"must be finite, got {value!r}")
    return x


def _whole(value: Any, path: PathLike, key: str, minimum: int = 1) -> int:
    """An integer >= ``minimum`` from an int, an integral float or text."""
    x = _finite(value, path, key)
    if x != int(x) or x < minimum:
        raise _fail(path, key, f"must be a whole number >= {minimum}, got {value!r}")
    return int(x)


def _array(values: Any, shape: tuple[int, ...], path: PathLike, key: str) -> np.ndarray:
    """A finite float64 array of ``shape`` from nested lists or an array; raises naming the key.

    A vector may arrive as a row or a column (``1xN``, ``Nx1``): dimensions of length 1 are not compared.
    """
    want = "x".join(map(str, shape))
    try:
        arr = np.array(values, dtype=object)
    except ValueError:
        raise _fail(path, key, f"must be a {want} array of numbers") from None
    squeeze = tuple(d for d in arr.shape if d != 1)
    if arr.size != math.prod(shape) or squeeze != tuple(d for d in shape if d != 1):
        raise _fail(path, key, f"must have shape {want}, got {'x'.join(map(str, arr.shape)) or 'a scalar'}")
    return np.array([_finite(v, path, key) for v in arr.ravel()]).reshape(shape)


def _intrinsics(path: PathLike, key: str, K: np.ndarray, dist: Sequence[float] | np.ndarray | None) -> Intrinsics:  # noqa: N803
    try:
        return Intrinsics.from_opencv(K, None if dist is None else np.asarray(dist, dtype=np.float64))
    except ValueError as exc:
        raise _fail(path, key, str(exc)) from None


def _rotation(R: np.ndarray, path: PathLike, key: str) -> np.ndarray:  # noqa: N803
    if not is_rotation(R):
        raise _fail(path, key, "is not a rotation matrix (R^T R must be I and det R = +1)")
    return R


def _transform(T: np.ndarray, path: PathLike, key: str) -> np.ndarray:  # noqa: N803
    """Check a (4, 4) rigid transform read from a file."""
    if np.max(np.abs(T[3] - [0.0, 0.0, 0.0, 1.0])) > HOMOGENEOUS_ROW_TOLERANCE:
        raise _fail(path, key, f"last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    _rotation(T[:3, :3], path, key)
    return make_T(T[:3, :3], T[:3, 3])


def _build(path: PathLike, key: str, grid: ViewGrid, image_size_px: tuple[int, int],
           intrinsics: Sequence[Intrinsics], ref_T_view: np.ndarray) -> Calibration:  # noqa: N803
    try:
        return Calibration(grid, image_size_px, tuple(intrinsics), ref_T_view)
    except ValueError as exc:
        raise _fail(path, key, str(exc)) from None


def _grid_dims(grid: GridLike) -> tuple[int, int, int | None] | None:
    """(rows, cols, reference or None) of a grid argument."""
    if grid is None:
        return None
    if isinstance(grid, ViewGrid):
        return grid.rows, grid.cols, grid.reference
    try:
        rows, cols = (int(x) for x in grid)
    except (TypeError, ValueError):
        raise ValueError(f"grid must be a ViewGrid or (rows, cols), got {grid!r}") from None
    ViewGrid(rows, cols)  # validates the dimensions
    return rows, cols, None


def _required_grid(grid: GridLike, num_views: int, path: PathLike, key: str, reference: int) -> ViewGrid:
    """The grid of a file that does not store one: ``grid`` must be given and hold ``num_views`` views.

    The returned grid has the file's natural ``reference``; `_fit_grid` then moves it to the one asked for.
    """
    dims = _grid_dims(grid)
    if dims is None:
        raise _fail(path, "grid", f"this format does not store the grid of its {num_views} views; give the grid "
                                  f"(rows x cols, e.g. --grid RxC)")
    rows, cols, _ = dims
    if rows * cols != num_views:
        raise _fail(path, key, f"holds {num_views} views, but the {rows}x{cols} grid needs {rows * cols}")
    return ViewGrid(rows, cols, reference)


def _fit_grid(calib: Calibration, grid: GridLike, path: PathLike, key: str) -> Calibration:
    """Check ``calib`` (as read) against the grid asked for; re-express it relative to that grid's reference."""
    dims = _grid_dims(grid)
    if dims is None:
        return calib
    rows, cols, reference = dims
    if rows * cols != calib.num_views:
        raise _fail(path, key, f"holds {calib.num_views} views, but the {rows}x{cols} grid needs {rows * cols}")
    if (rows, cols) != (calib.grid.rows, calib.grid.cols):
        raise _fail(path, "grid", f"the file's grid is {calib.grid}, but {rows}x{cols} was asked for")
    if reference is None or reference == calib.grid.reference:
        return calib
    if calib.rectification is not None:
        raise _fail(path, "rectification", f"is tied to reference view {calib.grid.reference} and cannot move to "
                                           f"view {reference}; import with the file's reference and rectify again")
    new_T_ref = invert_T(calib.ref_T_view[reference])  # noqa: N806 - new reference from old reference
    new_T_view = np.einsum("ij,vjk->vik", new_T_ref, calib.ref_T_view)  # noqa: N806
    new_T_view[reference] = np.eye(4)  # exactly, not to rounding
    return calib.replace(grid=ViewGrid(rows, cols, reference), ref_T_view=new_T_view)


def _check_reference_pose(view_T_ref: np.ndarray, path: PathLike, key: str) -> None:  # noqa: N803
    if np.max(np.abs(view_T_ref - np.eye(4))) > REFERENCE_POSE_TOLERANCE:
        raise _fail(path, key, "belongs to the reference view, so it must be the identity")


def _num(x: float) -> str:
    """Shortest text that reads back as exactly ``x``."""
    return repr(float(x))


# ============================================================================================== OpenCV YAML
def _write_opencv_yaml(calib: Calibration, path: Path) -> None:
    rect = calib.rectification if isinstance(calib.rectification, Mapping) else None
    rect_views = []
    if rect is not None:
        views = rect.get("views")
        if "K_r" not in rect or not isinstance(views, Sequence) or len(views) != calib.num_views:
            raise ValueError(f"calibration's rectification must hold K_r and {calib.num_views} views to be exported")
        for i, view in enumerate(views):
            if not isinstance(view, Mapping) or "R_rect_from_view" not in view or "P" not in view:
                raise ValueError(f"rectification.views[{i}] must hold R_rect_from_view and P to be exported")
            R = np.asarray(view["R_rect_from_view"], dtype=np.float64)  # noqa: N806
            P = np.asarray(view["P"], dtype=np.float64)  # noqa: N806
            if R.shape != (3, 3) or P.shape != (3, 4):
                raise ValueError(f"rectification.views[{i}]: R_rect_from_view must be 3x3 and P 3x4, got "
                                 f"{R.shape} and {P.shape}")
            rect_views.append((R, P))
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
                fs.write("K_r", np.asarray(rect["K_r"], dtype=np.float64).reshape(3, 3))
                for i, (R, P) in enumerate(rect_views):  # noqa: N806
                    fs.write(f"R_rect_{i}", R)
                    fs.write(f"P_{i}", P)
        finally:
            fs.release()


def _read_opencv_yaml(path: Path, grid: GridLike) -> Calibration:
    if not path.is_file():
        raise _fail(path, "file", "does not exist" if not path.exists() else "is not a file")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # OpenCV 5 raises SystemError wrapping cv2.error on a parse error
        cause = exc.__cause__ or exc
        raise _fail(path, "file", f"not a readable OpenCV FileStorage file ({str(cause).strip()[:200]})") from None
    if not fs.isOpened():
        raise _fail(path, "file", "cannot be opened by cv2.FileStorage")
    try:
        def node(key: str) -> cv2.FileNode:
            n = fs.getNode(key)
            if n.empty() or n.isNone():
                raise _fail(path, key, "is missing")
            return n

        def integer(key: str, minimum: int) -> int:
            n = node(key)
            if not (n.isInt() or n.isReal()):
                raise _fail(path, key, "must be a number")
            return _whole(n.real(), path, key, minimum)

        def matrix(key: str, shape: tuple[int, ...] | None) -> np.ndarray:
            n = node(key)
            try:
                m = n.mat() if n.isMap() else None
            except cv2.error:
                m = None
            if m is None:
                raise _fail(path, key, "must be an !!opencv-matrix")
            m = np.asarray(m, dtype=np.float64)
            return _array(m, shape or (m.size,), path, key)

        rows, cols = integer("grid_rows", 1), integer("grid_cols", 1)
        reference = integer("reference", 0)
        size = (integer("image_width", 1), integer("image_height", 1))
        num_views = integer("num_views", 1)
        if num_views != rows * cols:
            raise _fail(path, "num_views", f"is {num_views}, but grid_rows x grid_cols = {rows}x{cols} needs "
                                           f"{rows * cols}")
        try:
            file_grid = ViewGrid(rows, cols, reference)
        except ValueError as exc:
            raise _fail(path, "reference", str(exc)) from None
        intrinsics, poses = [], []
        for i in range(num_views):
            K = matrix(f"K_{i}", (3, 3))  # noqa: N806
            dist = matrix(f"D_{i}", None)  # 4, 5 or more coefficients; those past p2 must be 0
            intrinsics.append(_intrinsics(path, f"K_{i}, D_{i}", K, dist))
            R = _rotation(matrix(f"R_{i}", (3, 3)), path, f"R_{i}")  # noqa: N806
            view_T_ref = make_T(R, matrix(f"T_{i}", (3, 1)).ravel())  # noqa: N806
            if i == reference:
                _check_reference_pose(view_T_ref, path, f"R_{i}, T_{i}")
            poses.append(invert_T(view_T_ref))
    finally:
        fs.release()
    calib = _build(path, "num_views", file_grid, size, intrinsics, np.stack(poses))
    return _fit_grid(calib, grid, path, "num_views")


# ============================================================================================== Kalibr
def _yaml_float(x: float) -> str:
    """Shortest exact text of ``x`` that YAML 1.1 (PyYAML, Kalibr) also reads as a float: it needs a ``.``."""
    s = repr(float(x))
    mantissa, e, exponent = s.partition("e")
    if e and "." not in mantissa:
        s = f"{mantissa}.0e{exponent}"
    return s


def _flow(values: Sequence[float]) -> str:
    return "[" + ", ".join(_yaml_float(v) for v in values) + "]"


def _write_kalibr(calib: Calibration, path: Path) -> None:
    w, h = calib.image_size_px
    lines = [f"# Kalibr camera chain written by lfgraph: {calib.grid} grid, views row-major (cam0 = view 0), "
             f"reference view {calib.grid.reference}",
             "# T_cn_cnm1 maps points of camera n-1 into camera n (metres)"]
    for v in range(calib.num_views):
        intr = calib.intrinsics[v]
        lines.append(f"cam{v}:")
        if v > 0:
            # view_T_ref(v) @ inv(view_T_ref(v - 1)), with inv(view_T_ref) = ref_T_view already at hand
            cn_T_cnm1 = calib.view_T_ref(v) @ calib.ref_T_view[v - 1]  # noqa: N806
            cn_T_cnm1[3] = [0.0, 0.0, 0.0, 1.0]
            lines.append("  T_cn_cnm1:")
            lines += [f"  - {_flow(row)}" for row in cn_T_cnm1]
        lines += [
            "  camera_model: pinhole",
            f"  intrinsics: {_flow([intr.fx, intr.fy, intr.cx, intr.cy])}",
            "  distortion_model: radtan",
            f"  distortion_coeffs: {_flow([intr.k1, intr.k2, intr.p1, intr.p2])}",
            f"  resolution: [{w}, {h}]",
            f"  rostopic: /lfgraph/{calib.grid.name(v)}/image_raw",
        ]
    write_text_atomic(path, "\n".join(lines) + "\n")


_YAML_SPECIAL_FLOATS = {".nan": math.nan, ".inf": math.inf, "+.inf": math.inf, "-.inf": -math.inf}
_FLOW_TOKEN = re.compile(r"\s*(\[|\]|,|[^\[\],]+)")


def _yaml_scalar(text: str) -> Any:
    s = text.strip()
    if len(s) >= 2 and s[0] == s[-1] and s[0] in "'\"":
        return s[1:-1]
    if s.lower() in _YAML_SPECIAL_FLOATS:
        return _YAML_SPECIAL_FLOATS[s.lower()]
    if re.fullmatch(r"[-+]?\d+", s):
        return int(s)
    if re.fullmatch(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?", s):
        return float(s)
    return s


def _yaml_value(text: str, where: str) -> Any:
    """A scalar or a (nested) flow list ``[a, [b, c]]``."""
    text = text.strip()
    if not text.startswith("["):
        return _yaml_scalar(text)
    tokens = [m.group(1).strip() for m in _FLOW_TOKEN.finditer(text) if m.group(1).strip()]
    pos = 0

    def parse_list() -> list[Any]:
        nonlocal pos
        pos += 1  # past "["
        items: list[Any] = []
        while pos < len(tokens) and tokens[pos] != "]":
            if tokens[pos] == "[":
                items.append(parse_list())
            elif tokens[pos] == ",":
                raise ValueError(f"{where}: empty item in a flow list")
            else:
                items.append(_yaml_scalar(tokens[pos]))
                pos += 1
            if pos < len(tokens) and tokens[pos] == ",":
                pos += 1
        if pos >= len(tokens):
            raise ValueError(f"{where}: unterminated flow list")
        pos += 1  # past "]"
        return items

    value = parse_list()
    if pos != len(tokens):
        raise ValueError(f"{where}: text after the closing ]")
    return value


def _strip_comment(line: str) -> str:
    if line.lstrip().startswith("#"):
        return ""
    m = re.search(r"\s#", line)
    return line[:m.start()] if m else line


def _parse_simple_yaml(text: str, path: PathLike) -> dict[str, Any]:
    """Parse the YAML subset of a Kalibr camchain: a top-level mapping of mappings whose values are scalars,
    flow lists, or block lists of flow lists (``T_cn_cnm1``). Raises `CalibrationFileError` naming the line."""
    root: dict[str, Any] = {}
    section: dict[str, Any] | None = None
    list_key: str | None = None
    for lineno, raw in enumerate(text.splitlines(), 1):
        where = f"line {lineno}"
        line = _strip_comment(raw).rstrip()
        body = line.strip()
        if not body or body in ("---", "...") or line.startswith("%"):
            continue
        if "\t" in line[: len(line) - len(line.lstrip())]:
            raise _fail(path, where, "indented with a tab, which YAML does not allow")
        indent = len(line) - len(line.lstrip(" "))
        try:
            if indent == 0:
                key, colon, rest = body.partition(":")
                if not colon or not key.strip():
                    raise ValueError("expected 'name:' at the top level")
                if key.strip() in root:
                    raise ValueError(f"{key.strip()!r} appears twice")
                if rest.strip():
                    root[key.strip()] = _yaml_value(rest, where)
                    section = None
                else:
                    section = root[key.strip()] = {}
                list_key = None
            elif section is None:
                raise ValueError("indented line outside a mapping")
            elif body == "-" or body.startswith("- "):
                if list_key is None:
                    raise ValueError("list item without a key above it")
                section[list_key].append(_yaml_value(body[1:], where))
            else:
                key, colon, rest = body.partition(":")
                if not colon or not key.strip():
                    raise ValueError("expected 'key: value'")
                key = key.strip()
                if key in section:
                    raise ValueError(f"{key!r} appears twice")
                if rest.strip():
                    section[key] = _yaml_value(rest, where)
                    list_key = None
                else:
                    section[key] = []
                    list_key = key
        except ValueError as exc:
            if isinstance(exc, CalibrationFileError):
                raise
            raise _fail(path, where, str(exc).removeprefix(f"{where}: ")) from None
    return root


def _read_kalibr(path: Path, grid: GridLike) -> Calibration:
    data = _parse_simple_yaml(_read_text(path), path)
    cams = sorted(int(k[3:]) for k in data if re.fullmatch(r"cam\d+", k))
    if not cams:
        raise _fail(path, "cam0", "is missing (no camN entries)")
    n = len(cams)
    for i in range(n):
        if f"cam{i}" not in data:
            raise _fail(path, f"cam{i}", f"is missing (found {', '.join(f'cam{c}' for c in cams)})")
    ref_grid = _required_grid(grid, n, path, "cam*", reference=0)

    def get(cam: str, key: str) -> Any:
        entry = data[cam]
        if not isinstance(entry, dict):
            raise _fail(path, cam, "must be a mapping")
        if key not in entry:
            raise _fail(path, f"{cam}.{key}", "is missing")
        return entry[key]

    intrinsics, size = [], None
    cn_T_c0 = [np.eye(4)]  # noqa: N806 - camera n from camera 0, chained
    for i in range(n):
        cam = f"cam{i}"
        model = get(cam, "camera_model")
        if model != "pinhole":
            raise _fail(path, f"{cam}.camera_model", f"must be 'pinhole', got {model!r}")
        fu, fv, pu, pv = _array(get(cam, "intrinsics"), (4,), path, f"{cam}.intrinsics")
        dist_model = get(cam, "distortion_model")
        if dist_model not in KALIBR_DISTORTION_MODELS:
            raise _fail(path, f"{cam}.distortion_model", f"must be one of {', '.join(KALIBR_DISTORTION_MODELS)} "
                                                         f"(lfgraph models k1 k2 p1 p2), got {dist_model!r}")
        if dist_model == "radtan":
            dist = _array(get(cam, "distortion_coeffs"), (4,), path, f"{cam}.distortion_coeffs")
        else:
            dist = np.zeros(4)
        K = np.array([[fu, 0.0, pu], [0.0, fv, pv], [0.0, 0.0, 1.0]])  # noqa: N806
        intrinsics.append(_intrinsics(path, f"{cam}.intrinsics", K, dist))
        res = _array(get(cam, "resolution"), (2,), path, f"{cam}.resolution")
        cam_size = (_whole(res[0], path, f"{cam}.resolution"), _whole(res[1], path, f"{cam}.resolution"))
        if size is None:
            size = cam_size
        elif cam_size != size:
            raise _fail(path, f"{cam}.resolution", f"is {list(cam_size)}, but cam0's is {list(size)}; lfgraph needs "
                                                   f"one image size for all views")
        if i > 0:
            T = _transform(_array(get(cam, "T_cn_cnm1"), (4, 4), path, f"{cam}.T_cn_cnm1"), path,  # noqa: N806
                           f"{cam}.T_cn_cnm1")
            cn_T_c0.append(T @ cn_T_c0[-1])
    ref = ref_grid.reference
    c0_T_ref = invert_T(cn_T_c0[ref])  # noqa: N806
    # ref_T_view = inv(view_T_c0 @ c0_T_ref)
    ref_T_view = np.stack([invert_T(cn_T_c0[v] @ c0_T_ref) for v in range(n)])  # noqa: N806
    ref_T_view[ref] = np.eye(4)
    calib = _build(path, "cam*", ref_grid, size, intrinsics, ref_T_view)
    return _fit_grid(calib, grid, path, "cam*")


# ============================================================================================== COLMAP
_COLMAP_GRID_COMMENT = re.compile(r"^#\s*lfgraph grid:\s*(\d+)\s*[xX]\s*(\d+)\s*$")


def _quaternion_wxyz(R: np.ndarray) -> np.ndarray:  # noqa: N803
    """(3, 3) rotation -> (4,) Hamilton unit quaternion (w, x, y, z) with w >= 0."""
    q = gtsam.Rot3(np.asarray(R, dtype=np.float64)).toQuaternion()
    wxyz = np.array([q.w(), q.x(), q.y(), q.z()])
    return -wxyz if wxyz[0] < 0 else wxyz


def _rotation_from_wxyz(wxyz: np.ndarray) -> np.ndarray:
    """(4,) quaternion (w, x, y, z), already normalised -> (3, 3) rotation."""
    return np.asarray(gtsam.Rot3.Quaternion(*(float(c) for c in wxyz)).matrix(), dtype=np.float64)


def _colmap_files(calib: Calibration) -> dict[str, str]:
    n = calib.num_views
    w, h = calib.image_size_px
    cameras = [
        "# Camera list with one line of data per camera:",
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
        f"# Number of cameras: {n}",
        "# lfgraph: camera ID = view index + 1 (row-major); cx, cy in COLMAP's pixels (OpenCV's + 0.5)",
    ]
    for v, intr in enumerate(calib.intrinsics):
        params = [intr.fx, intr.fy, intr.cx + COLMAP_PIXEL_OFFSET_PX, intr.cy + COLMAP_PIXEL_OFFSET_PX,
                  intr.k1, intr.k2, intr.p1, intr.p2]
        cameras.append(f"{v + 1} OPENCV {w} {h} " + " ".join(_num(p) for p in params))
    ref = calib.grid.reference
    sensors = []
    for v in range(n):
        if v == ref:
            continue
        sensor_from_rig = calib.view_T_ref(v)  # the rig frame is the reference view's frame
        pose = [*_quaternion_wxyz(sensor_from_rig[:3, :3]), *sensor_from_rig[:3, 3]]
        sensors.append(f"CAMERA {v + 1} 1 " + " ".join(_num(x) for x in pose))
    rigs = [
        "# Rig calib list with one line of data per calib:",
        "#   RIG_ID, NUM_SENSORS, REF_SENSOR_TYPE, REF_SENSOR_ID, SENSORS[] as (SENSOR_TYPE, SENSOR_ID, HAS_POSE, "
        "[QW, QX, QY, QZ, TX, TY, TZ])",
        "# Number of rigs: 1",
        f"# lfgraph grid: {calib.grid.rows}x{calib.grid.cols}",
        " ".join([f"1 {n} CAMERA {ref + 1}", *sensors]),
    ]
    return {
        "rigs.txt": "\n".join(rigs) + "\n",
        "cameras.txt": "\n".join(cameras) + "\n",
        "frames.txt": "# Frame list with one line of data per frame:\n"
                      "#   FRAME_ID, RIG_ID, RIG_FROM_WORLD[QW, QX, QY, QZ, TX, TY, TZ], NUM_DATA_IDS, DATA_IDS[] as "
                      "(SENSOR_TYPE, SENSOR_ID, DATA_ID)\n# Number of frames: 0\n",
        "images.txt": "# Image list with two lines of data per image:\n"
                      "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
                      "#   POINTS2D[] as (X, Y, POINT3D_ID)\n# Number of images: 0, mean observations per image: 0\n",
        "points3D.txt": "# 3D point list with one line of data per point:\n"
                        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
                        "# Number of points: 0, mean track length: 0\n",
    }


def _write_colmap(calib: Calibration, path: Path) -> None:
    final = path
    if final.exists() and not final.is_dir():
        raise ValueError(f"{final}: a COLMAP model is a folder, but a file of that name exists")
    if final.is_dir():
        others = sorted(p.name for p in final.iterdir() if p.name not in COLMAP_MODEL_FILES)
        if others:
            raise ValueError(f"{final}: the folder holds files that are not part of a COLMAP model "
                             f"({', '.join(others[:5])}{', ...' if len(others) > 5 else ''}); refusing to replace it")
    final.parent.mkdir(parents=True, exist_ok=True)
    # Write a temporary sibling folder, then rename it into place: the model never appears half-written.
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".tmp", dir=final.parent))
    old: Path | None = None
    try:
        for name, text in _colmap_files(calib).items():
            (tmp / name).write_text(text, encoding="utf-8")
        if final.is_dir():
            old = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".old", dir=final.parent))
            os.replace(final, old)  # onto an empty folder: allowed by rename(2)
            try:
                os.replace(tmp, final)
            except OSError:
                os.replace(old, final)
                old = None
                raise
        else:
            os.replace(tmp, final)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
        if old is not None and old.exists():
            shutil.rmtree(old, ignore_errors=True)


def _colmap_lines(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, tokens) of the data lines of a COLMAP text file."""
    text = _read_text(path)
    return [(i, line.split()) for i, line in enumerate(text.splitlines(), 1)
            if line.strip() and not line.lstrip().startswith("#")]


def _read_colmap(path: Path, grid: GridLike) -> Calibration:
    if not path.is_dir():
        raise _fail(path, "folder", "does not exist" if not path.exists() else "is not a folder (a COLMAP text "
                                                                              "model is a folder)")
    cameras_path, rigs_path = path / "cameras.txt", path / "rigs.txt"
    for p in (cameras_path, rigs_path):
        if not p.is_file():
            raise _fail(path, p.name, "is missing")

    cameras: dict[int, tuple[Intrinsics, tuple[int, int]]] = {}
    for lineno, tok in _colmap_lines(cameras_path):
        where = f"line {lineno}"
        if len(tok) < 4:
            raise _fail(cameras_path, where, "must be CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        cam_id = _whole(tok[0], cameras_path, f"{where} CAMERA_ID")
        model = tok[1]
        names = COLMAP_CAMERA_MODELS.get(model)
        if names is None:
            raise _fail(cameras_path, f"camera {cam_id} MODEL", f"{model!r} is not supported (supported: "
                                                                f"{', '.join(COLMAP_CAMERA_MODELS)})")
        if len(tok) != 4 + len(names):
            raise _fail(cameras_path, f"camera {cam_id} PARAMS", f"{model} needs {len(names)} parameters "
                                                                 f"({' '.join(names)}), got {len(tok) - 4}")
        size = (_whole(tok[2], cameras_path, f"camera {cam_id} WIDTH"),
                _whole(tok[3], cameras_path, f"camera {cam_id} HEIGHT"))
        p = {name: _finite(t, cameras_path, f"camera {cam_id} {name}") for name, t in zip(names, tok[4:], strict=True)}
        fx, fy = p.get("fx", p.get("f")), p.get("fy", p.get("f"))
        K = np.array([[fx, 0.0, p["cx"] - COLMAP_PIXEL_OFFSET_PX],  # noqa: N806
                      [0.0, fy, p["cy"] - COLMAP_PIXEL_OFFSET_PX], [0.0, 0.0, 1.0]])
        dist = [p.get(k, 0.0) for k in ("k1", "k2", "p1", "p2")]
        if cam_id in cameras:
            raise _fail(cameras_path, f"camera {cam_id}", "appears twice")
        cameras[cam_id] = (_intrinsics(cameras_path, f"camera {cam_id}", K, dist), size)
    if not cameras:
        raise _fail(cameras_path, "cameras", "holds no camera")
    ids = sorted(cameras)
    sizes = {cameras[i][1] for i in ids}
    if len(sizes) > 1:
        raise _fail(cameras_path, "WIDTH, HEIGHT", f"cameras have different image sizes {sorted(sizes)}; lfgraph "
                                                   f"needs one size for all views")

    rigs = _colmap_lines(rigs_path)
    if len(rigs) != 1:
        raise _fail(rigs_path, "rigs", f"must hold exactly one rig with all {len(ids)} cameras, got {len(rigs)} rigs")
    lineno, tok = rigs[0]
    where = f"line {lineno}"
    if len(tok) < 4:
        raise _fail(rigs_path, where, "must be RIG_ID NUM_SENSORS REF_SENSOR_TYPE REF_SENSOR_ID SENSORS[]")
    num_sensors = _whole(tok[1], rigs_path, f"{where} NUM_SENSORS")
    if tok[2] != "CAMERA":
        raise _fail(rigs_path, f"{where} REF_SENSOR_TYPE", f"must be CAMERA, got {tok[2]!r}")
    ref_id = _whole(tok[3], rigs_path, f"{where} REF_SENSOR_ID")
    sensor_from_rig = {ref_id: np.eye(4)}
    pos = 4
    while pos < len(tok):
        if pos + 3 > len(tok):
            raise _fail(rigs_path, f"{where} SENSORS", "ends inside a sensor (SENSOR_TYPE SENSOR_ID HAS_POSE ...)")
        sensor_type, sensor_id = tok[pos], _whole(tok[pos + 1], rigs_path, f"{where} SENSOR_ID")
        has_pose = tok[pos + 2]
        key = f"sensor {sensor_id}"
        if sensor_type != "CAMERA":
            raise _fail(rigs_path, f"{key} SENSOR_TYPE", f"must be CAMERA, got {sensor_type!r}")
        if has_pose != "1":
            raise _fail(rigs_path, f"{key} HAS_POSE", f"must be 1 (lfgraph needs every camera's pose in the rig), "
                                                      f"got {has_pose!r}")
        if pos + 10 > len(tok):
            raise _fail(rigs_path, f"{key} pose", "needs QW QX QY QZ TX TY TZ")
        q = np.array([_finite(t, rigs_path, f"{key} Q") for t in tok[pos + 3: pos + 7]])
        t = np.array([_finite(x, rigs_path, f"{key} T") for x in tok[pos + 7: pos + 10]])
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise _fail(rigs_path, f"{key} QW QX QY QZ", f"must be a unit quaternion, |q| = {norm}")
        if sensor_id in sensor_from_rig:
            raise _fail(rigs_path, key, "appears twice in the rig")
        sensor_from_rig[sensor_id] = make_T(_rotation_from_wxyz(q / norm), t)
        pos += 10
    if num_sensors != len(sensor_from_rig):
        raise _fail(rigs_path, f"{where} NUM_SENSORS", f"is {num_sensors}, but the rig lists {len(sensor_from_rig)}")
    if set(sensor_from_rig) != set(ids):
        raise _fail(rigs_path, "SENSORS", f"the rig's cameras {sorted(sensor_from_rig)} must be the cameras of "
                                          f"cameras.txt {ids}")
    reference = ids.index(ref_id)

    file_dims = None
    for line in rigs_path.read_text(encoding="utf-8").splitlines():
        m = _COLMAP_GRID_COMMENT.match(line.strip())
        if m:
            file_dims = (int(m.group(1)), int(m.group(2)))
    if file_dims is None:
        view_grid = _required_grid(grid, len(ids), path, "cameras.txt", reference)
    else:
        rows, cols = file_dims
        if rows * cols != len(ids):
            raise _fail(rigs_path, "# lfgraph grid", f"is {rows}x{cols}, but the model holds {len(ids)} cameras")
        view_grid = ViewGrid(rows, cols, reference)
    intrinsics = [cameras[i][0] for i in ids]
    ref_T_view = np.stack([invert_T(sensor_from_rig[i]) for i in ids])  # noqa: N806
    ref_T_view[reference] = np.eye(4)
    calib = _build(path, "rigs.txt", view_grid, sizes.pop(), intrinsics, ref_T_view)
    return _fit_grid(calib, grid, path, "cameras.txt")


# ============================================================================================== lfgraph JSON
def _write_json(calib: Calibration, path: Path) -> None:
    calib.save(path)


def _read_json(path: Path, grid: GridLike) -> Calibration:
    return _fit_grid(Calibration.load(path), grid, path, "views")


# ============================================================================================== Middlebury
def _middlebury_matrix(text: str, path: PathLike, key: str) -> np.ndarray:
    """``[a b c; d e f; g h i]`` (spaces or commas between numbers) -> (3, 3)."""
    body = text.strip()
    if not (body.startswith("[") and body.endswith("]")):
        raise _fail(path, key, f"must be a matrix [a b c; d e f; g h i], got {text.strip()!r}")
    rows = [r.replace(",", " ").split() for r in body[1:-1].split(";")]
    return _array(rows, (3, 3), path, key)


def _read_middlebury(path: Path, grid: GridLike) -> Calibration:
    path = _in_folder(path, "calib.txt")
    entries: dict[str, str] = {}
    for lineno, line in enumerate(_read_text(path).splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        key, eq, value = line.partition("=")
        if not eq:
            raise _fail(path, f"line {lineno}", f"must be KEY=VALUE, got {line!r}")
        entries[key.strip()] = value.strip()
    for key in ("cam0", "cam1", "baseline", "width", "height"):
        if key not in entries:
            raise _fail(path, key, "is missing")
    intrinsics = [_intrinsics(path, key, _middlebury_matrix(entries[key], path, key), None)
                  for key in ("cam0", "cam1")]
    size = (_whole(entries["width"], path, "width"), _whole(entries["height"], path, "height"))
    baseline_m = _finite(entries["baseline"], path, "baseline") / MM_PER_M
    if baseline_m <= 0:
        raise _fail(path, "baseline", f"must be positive (mm), got {entries['baseline']!r}")
    ref_T_view = np.stack([np.eye(4), make_T(np.eye(3), [baseline_m, 0.0, 0.0])])  # noqa: N806 - cam1 to the right
    calib = _build(path, "cam0, cam1", ViewGrid(1, 2, 0), size, intrinsics, ref_T_view)
    return _fit_grid(calib, grid, path, "cam0, cam1")


# ============================================================================================== HCI
def _read_hci(path: Path, grid: GridLike) -> Calibration:
    path = _in_folder(path, "parameters.cfg")
    parser = configparser.ConfigParser()
    try:
        parser.read_string(_read_text(path), source=str(path))
    except configparser.Error as exc:
        raise _fail(path, "file", f"not a valid INI file ({' '.join(str(exc).split())})") from None

    def get(section: str, key: str) -> str:
        if not parser.has_section(section):
            raise _fail(path, f"[{section}]", "section is missing")
        if not parser.has_option(section, key):
            raise _fail(path, f"[{section}] {key}", "is missing")
        return parser.get(section, key)

    def positive(section: str, key: str) -> float:
        x = _finite(get(section, key), path, f"[{section}] {key}")
        if x <= 0:
            raise _fail(path, f"[{section}] {key}", f"must be positive, got {x}")
        return x

    focal_mm = positive("intrinsics", "focal_length_mm")
    sensor_mm = positive("intrinsics", "sensor_size_mm")
    w = _whole(get("intrinsics", "image_resolution_x_px"), path, "[intrinsics] image_resolution_x_px")
    h = _whole(get("intrinsics", "image_resolution_y_px"), path, "[intrinsics] image_resolution_y_px")
    cols = _whole(get("extrinsics", "num_cams_x"), path, "[extrinsics] num_cams_x")
    rows = _whole(get("extrinsics", "num_cams_y"), path, "[extrinsics] num_cams_y")
    pitch_m = positive("extrinsics", "baseline_mm") / MM_PER_M
    focal_px = focal_mm / sensor_mm * max(w, h)  # the sensor size spans the longer image side
    intr = Intrinsics(focal_px, focal_px, (w - 1) / 2.0, (h - 1) / 2.0)
    view_grid = ViewGrid(rows, cols, 0)
    ref_T_view = np.tile(np.eye(4), (view_grid.num_views, 1, 1))  # noqa: N806
    for v in range(view_grid.num_views):
        r, c = view_grid.position(v)
        ref_T_view[v, :3, 3] = [c * pitch_m, r * pitch_m, 0.0]  # +x right along a row, +y down the columns
    calib = _build(path, "[extrinsics]", view_grid, (w, h), [intr] * view_grid.num_views, ref_T_view)
    return _fit_grid(calib, grid, path, "[extrinsics] num_cams_x, num_cams_y")


_WRITERS: dict[str, Callable[[Calibration, Path], None]] = {
    "opencv-yaml": _write_opencv_yaml,
    "kalibr": _write_kalibr,
    "colmap": _write_colmap,
    "json": _write_json,
}
_READERS: dict[str, Callable[[Path, GridLike], Calibration]] = {
    "opencv-yaml": _read_opencv_yaml,
    "kalibr": _read_kalibr,
    "colmap": _read_colmap,
    "json": _read_json,
    "middlebury": _read_middlebury,
    "hci": _read_hci,
}
assert tuple(_WRITERS) == EXPORT_FORMATS and tuple(_READERS) == IMPORT_FORMATS
