"""``opencv-yaml`` (export, import): one ``cv2.FileStorage`` YAML file.

Top level ``grid_rows``, ``grid_cols``, ``reference``, ``image_width``, ``image_height``, ``num_views``; a rig of
mixed image sizes also ``image_width_i``, ``image_height_i`` per view; per view
``i``: ``K_i`` (3x3), ``D_i`` (1x5: k1 k2 p1 p2 k3 with k3 = 0), ``R_i`` (3x3) and ``T_i`` (3x1, metres) with
``x_view = R_i x_ref + T_i`` (= ``calib.view_T_ref(i)``, the convention of ``cv2.stereoCalibrate``).

A pair (two views) is also written under the names OpenCV's stereo functions use (`stereo_entries`): ``M1 D1 M2
D2 R T`` and ``R1 R2 P1 P2 Q`` (of the stored rectification, else of the one ``lfgraph rectify`` would store,
computed for the export; left out, with a warning, when the pair cannot be rectified).

A stored rectification adds ``rect_image_width``, ``rect_image_height`` (the rectified image size), ``K_r`` (3x3),
and per view ``R_rect_i`` (3x3, rectified from view; the role of ``cv2.stereoRectify``'s R1/R2) and ``P_i`` (3x4) in
``cv2.stereoRectify``'s P1/P2 convention: ``P_i = [K_r | p_i]`` maps points of the *rectified reference frame*
(``x = R_rect_from_ref x_ref``, origin at the reference view's centre, as stereoRectify's frame of rectified
camera 1) to rectified pixels of view i, with ``p_i = -K_r R_rect_from_ref c_i`` and ``c_i`` the view's ideal grid
position (lfgraph's rectified projection, re-expressed). Hence
``cv2.initUndistortRectifyMap(K_i, D_i, R_rect_i, P_i, (rect_image_width, rect_image_height), m1type)`` (which uses
``P_i``'s left 3x3 as the new camera matrix) gives exactly lfgraph's rectified view i (`lfgraph.rectification.rectify
.build_maps`), and ``rect_crop`` (``valid`` or ``full``, lfgraph's crop mode). Import keeps such a rectification
(`lfgraph.rectification.recover` rebuilds the rest of it: the ideal grid from the P_i's last columns, the crop from
K_r's principal point): every one of ``K_r``, ``R_rect_i``, ``P_i`` and the rectified size must be there, each
``P_i``'s left 3x3 must be ``K_r`` (to `P_LEFT_BLOCK_REL`) and each ``R_rect_i`` the view's orientation turned by the
reference's ``R_rect`` (to `RECT_ROTATION_TOLERANCE_RAD`): a rectification of this calibration, or the file is refused
naming the key. The stereo names (``R1 ... Q``) are not read: they repeat what the per-view keys hold.

Import parses the file once with PyYAML's parser (libyaml when available) and walks its node tree:
``cv2.FileStorage`` looks every key up by a linear scan of the top-level map, which made import quadratic in the view
count (a 300x300 grid, 360,000 keys, took minutes). Both OpenCV's ``%YAML:1.0``
and ``%YAML 1.2`` headers are read; FileStorage's XML and JSON flavours are refused (re-save them as YAML). A
header declaring more than `MAX_IMPORT_VIEWS` views is refused before the file is parsed.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from lfgraph.core.calibration import Calibration
from lfgraph.core.files import atomic_path
from lfgraph.core.geometry import invert_T, make_T, rotation_angle_deg
from lfgraph.core.grid import ViewGrid
from lfgraph.interop.common import (
    GridLike,
    array,
    build,
    check_reference_pose,
    check_view_count,
    compose_yaml,
    fail,
    fit_grid,
    intrinsics,
    read_text,
    rotation,
    whole,
)
from lfgraph.rectification.recover import rectification_from_projections
from lfgraph.rectification.rectify import CROPS, attach, rectification_for_export, stored_rectification

_OPENCV_DIRECTIVE = re.compile(r"\A\s*%YAML[: ]\s*\d+\.\d+[^\n]*\n")  # OpenCV 3/4 write %YAML:1.0, OpenCV 5 %YAML 1.2
# cv2.FileStorage writes these for non-finite numbers; YAML 1.1 spells them .nan/.NaN/.inf only
_OPENCV_SPECIAL_FLOATS = {".nan": float("nan"), ".inf": float("inf"), "+.inf": float("inf"), "-.inf": float("-inf")}
_HEADER_COUNT = re.compile(r"^(grid_rows|grid_cols|num_views)[ \t]*:[ \t]*(\d+)[ \t]*(?:#.*)?$", re.MULTILINE)
_MATRIX_TAG = "tag:yaml.org,2002:opencv-matrix"  # what the parser makes of FileStorage's !!opencv-matrix
_RECT_KEYS = ("rect_image_width", "rect_image_height", "K_r", "rect_crop")  # any of them: a rectification
P_LEFT_BLOCK_REL = 1e-6  # P_i's left 3x3 against K_r, relative to K_r's largest entry (six significant digits)
RECT_ROTATION_TOLERANCE_RAD = 1e-4  # R_rect_i against R_rect_ref R_i^T: a file's printed precision, as its rotations


def rectified_projection(K_r: np.ndarray, P_lfgraph: np.ndarray) -> np.ndarray:  # noqa: N803
    """lfgraph's rectified projection (reference-frame points) in OpenCV's P1/P2 convention (rectified-frame points).

    ``P_lfgraph = K_r [R | -R c]`` with ``R = rect_R_ref``; re-expressed for ``x_rect = R x_ref`` it is
    ``P_lfgraph @ diag(R^T, 1) = [K_r | -K_r R c]``: the last column is unchanged and the left block is exactly
    ``K_r``, so it is built from those two pieces rather than by a matrix product that would round.
    """
    return np.column_stack([K_r, P_lfgraph[:, 3]])


_CV_MODELS = {"radtan": "pinhole", "fisheye": "fisheye"}  # lfgraph lens -> the OpenCV module that reads it


def write(calib: Calibration, path: Path) -> None:
    """Write ``calib`` as one ``cv2.FileStorage`` YAML file (see the module docstring; a pair also under OpenCV's
    stereo names), atomically.

    Raises:
        ValueError: a unified lens, or an incomplete stored rectification."""
    unified = [calib.grid.name(v) for v, i in enumerate(calib.intrinsics) if i.lens not in _CV_MODELS]
    if unified:
        raise ValueError(f"{path}: OpenCV's main modules have no unified (omnidirectional) lens model, which views "
                         f"{', '.join(unified)} use; export them to Kalibr (omni-radtan) instead")
    rect = stored_rectification(calib)  # RectificationError (a ValueError) naming the field when incomplete
    w, h = calib.image_size_px
    with atomic_path(path) as tmp:
        # FORMAT_YAML: FileStorage would otherwise choose XML for a name that does not end in .yaml/.yml
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
        if not fs.isOpened():
            raise OSError(f"{path}: cannot be written by cv2.FileStorage")
        try:
            fs.writeComment("lfgraph calibration: views row-major; x_view = R_i x_ref + T_i (metres); "
                            "D_i = k1 k2 p1 p2 k3 (model_i pinhole, for cv2) or k1 k2 k3 k4 (model_i fisheye, for "
                            "cv2.fisheye)")
            for key, value in (("grid_rows", calib.grid.rows), ("grid_cols", calib.grid.cols),
                               ("reference", calib.grid.reference), ("image_width", w), ("image_height", h),
                               ("num_views", calib.num_views)):
                fs.write(key, int(value))
            for i in range(calib.num_views):
                intr = calib.intrinsics[i]
                view_T_ref = calib.view_T_ref(i)  # noqa: N806
                fs.write(f"K_{i}", intr.K)
                fs.write(f"model_{i}", _CV_MODELS[intr.lens])
                fs.write(f"D_{i}", intr.dist_cv.reshape(1, -1))
                fs.write(f"R_{i}", view_T_ref[:3, :3])
                fs.write(f"T_{i}", view_T_ref[:3, 3].reshape(3, 1))
                if calib.view_image_sizes_px is not None:  # a rig of mixed sizes: each view's own
                    fs.write(f"image_width_{i}", int(calib.image_size(i)[0]))
                    fs.write(f"image_height_{i}", int(calib.image_size(i)[1]))
            if rect is not None:
                fs.writeComment("rectification: initUndistortRectifyMap(K_i, D_i, R_rect_i, P_i, (rect_image_width, "
                                "rect_image_height)) gives lfgraph's rectified view i; P_i as stereoRectify's P1/P2")
                fs.write("rect_image_width", int(rect.image_size_px[0]))
                fs.write("rect_image_height", int(rect.image_size_px[1]))
                fs.write("K_r", rect.K_r)
                fs.write("rect_crop", rect.crop)
                for i in range(calib.num_views):
                    fs.write(f"R_rect_{i}", rect.rect_R_view[i])
                    fs.write(f"P_{i}", rectified_projection(rect.K_r, rect.P[i]))
            if calib.num_views == 2:  # without a stored rectification, the one `rectify` would store (R1 R2 P1 P2 Q)
                for key, value in stereo_entries(calib, rect or rectification_for_export(calib, False)).items():
                    fs.write(key, value)
        finally:
            fs.release()


def stereo_entries(calib: Calibration, rect) -> dict[str, np.ndarray]:
    """A pair under the names of ``cv2.stereoCalibrate`` / ``cv2.stereoRectify`` (camera 1 = view 0, camera 2 =
    view 1): ``M1 D1 M2 D2``, ``R T`` (``x2 = R x1 + T``, metres) and, with a rectification, ``R1 R2`` (rectified
    from camera), ``P1 P2`` (3x4, in camera 1's rectified frame: ``P1 = [K_r | 0]``, ``P2 = [K_r | K_r t]`` with
    ``t`` camera 1's centre in camera 2's rectified frame) and ``Q`` (4x4, ``cv2.reprojectImageTo3D``'s: (u, v, d, 1)
    -> camera 1's rectified frame, d = u1 - u2 for a horizontal pair, v1 - v2 for a vertical one)."""
    two_T_one = calib.view_T_ref(1) @ invert_T(calib.view_T_ref(0))  # noqa: N806
    out = {"M1": calib.intrinsics[0].K, "D1": calib.intrinsics[0].dist_cv.reshape(1, -1),
           "M2": calib.intrinsics[1].K, "D2": calib.intrinsics[1].dist_cv.reshape(1, -1),
           "R": two_T_one[:3, :3], "T": two_T_one[:3, 3].reshape(3, 1)}
    if rect is None:
        return out
    k_r = np.asarray(rect.K_r, dtype=np.float64)
    shift = rect.P[1][:, 3] - rect.P[0][:, 3]  # = K_r t: the last columns are -K_r R c_i
    t = np.linalg.solve(k_r, shift)
    axis = 0 if abs(t[0]) >= abs(t[1]) else 1  # horizontal or vertical pair
    # Z = -f t / d with f the focal length along the disparity; the other axis row is scaled by f / its own focal
    # length (OpenCV's stereoRectify makes fx = fy; lfgraph's K_r keeps the mean of each)
    f = k_r[axis, axis]
    q = np.zeros((4, 4))
    for row in (0, 1):
        q[row, row] = f / k_r[row, row]
        q[row, 3] = -k_r[row, 2] * f / k_r[row, row]
    q[2, 3] = f
    q[3, 2] = -1.0 / t[axis]  # views share K_r, so cx1 - cx2 = cy1 - cy2 = 0 (Q[3, 3])
    out.update({"R1": rect.rect_R_view[0], "R2": rect.rect_R_view[1], "P1": np.column_stack([k_r, np.zeros(3)]),
                "P2": np.column_stack([k_r, shift]), "Q": q})
    return out


@dataclass(frozen=True)
class _Matrix:
    """An ``!!opencv-matrix`` as text, validated by `_matrix` once its key is known."""

    rows: Any
    cols: Any
    data: list[Any] | None


def _text(node: yaml.Node | None) -> Any:
    """A scalar node's text; None for no node; any other node as it is (the reader then names the key)."""
    return node.value if isinstance(node, yaml.ScalarNode) else node


def _plain(node: yaml.Node) -> Any:
    """A top-level value as text, a `_Matrix`, or the node itself when it is neither."""
    if isinstance(node, yaml.MappingNode) and node.tag == _MATRIX_TAG:
        fields = {str(k.value): v for k, v in node.value}
        data = fields.get("data")
        items = None if data is None else data.value if isinstance(data, yaml.SequenceNode) else [data]
        return _Matrix(_text(fields.get("rows")), _text(fields.get("cols")),
                       None if items is None else [_text(item) for item in items])
    return _text(node)


def _top_level(root: yaml.Node | None, path: Path) -> dict[str, Any]:
    """The top-level mapping as ``{key: text | _Matrix | node}``; a key given twice is refused (naming its line)."""
    if not isinstance(root, yaml.MappingNode):
        raise fail(path, "file", "must be a YAML mapping of keys (grid_rows, K_0, ...)")
    entries: dict[str, Any] = {}
    for key_node, value_node in root.value:
        key = str(key_node.value)
        if key in entries:
            raise fail(path, f"line {key_node.start_mark.line + 1}", f"{key!r} appears twice")
        entries[key] = _plain(value_node)
    return entries


def _number(value: Any, path: Path, key: str) -> Any:
    if not isinstance(value, str):
        raise fail(path, key, "must be a number")
    return _OPENCV_SPECIAL_FLOATS.get(value.lower(), value)


def _matrix(entries: dict[str, Any], key: str, shape: tuple[int, ...] | None, path: Path) -> np.ndarray:
    """An ``!!opencv-matrix`` (one channel) as a finite float64 array of ``shape`` (any size when None)."""
    if key not in entries:
        raise fail(path, key, "is missing")
    m = entries[key]
    if not isinstance(m, _Matrix):
        raise fail(path, key, "must be an !!opencv-matrix")
    for name in ("rows", "cols", "data"):
        if getattr(m, name) is None:
            raise fail(path, key, f"!!opencv-matrix without {name}")
    rows = whole(_number(m.rows, path, f"{key}.rows"), path, f"{key}.rows")
    cols = whole(_number(m.cols, path, f"{key}.cols"), path, f"{key}.cols")
    values = [_number(v, path, key) for v in m.data]
    if len(values) != rows * cols:
        raise fail(path, key, f"!!opencv-matrix of {rows}x{cols} holds {len(values)} numbers (one channel expected)")
    try:
        m = np.array(values, dtype=np.float64)  # numpy parses the text; `array` re-checks it one by one if this fails
    except ValueError:
        m = np.array(values, dtype=object)
    return array(m.reshape(rows, cols), shape or (rows * cols,), path, key)


def read(path: Path, grid: GridLike) -> Calibration:
    """Read an OpenCV ``FileStorage`` YAML file written in this layout as a calibration (``grid`` checked against it or
    moving its reference)."""
    if not path.is_file():
        raise fail(path, "file", "does not exist" if not path.exists() else "is not a file")
    text = read_text(path)
    if text.lstrip()[:1] in ("<", "{"):
        raise fail(path, "file", "is FileStorage XML or JSON; lfgraph reads the YAML flavour (re-save it with "
                                 "cv2.FileStorage under a .yaml name)")
    # Refuse an absurd grid from the header alone: parsing a file of 100,000 views is already minutes of work.
    header = {m.group(1): int(m.group(2)) for m in _HEADER_COUNT.finditer(text)}
    if "num_views" in header:
        check_view_count(header["num_views"], path, "num_views")
    if "grid_rows" in header and "grid_cols" in header:
        check_view_count(header["grid_rows"] * header["grid_cols"], path, "grid_rows, grid_cols")
    yaml_text = _OPENCV_DIRECTIVE.sub("%YAML 1.1\n", text, count=1)  # PyYAML cannot read OpenCV 3/4's %YAML:1.0
    entries = compose_yaml(yaml_text, path, lambda root: _top_level(root, path))

    def integer(key: str, minimum: int) -> int:
        if key not in entries:
            raise fail(path, key, "is missing")
        return whole(_number(entries[key], path, key), path, key, minimum)

    rows, cols = integer("grid_rows", 1), integer("grid_cols", 1)
    reference = integer("reference", 0)
    size = (integer("image_width", 1), integer("image_height", 1))
    num_views = integer("num_views", 1)
    check_view_count(num_views, path, "num_views")
    if num_views != rows * cols:
        raise fail(path, "num_views", f"is {num_views}, but grid_rows x grid_cols = {rows}x{cols} needs {rows * cols}")
    try:
        file_grid = ViewGrid(rows, cols, reference)
    except ValueError as exc:
        raise fail(path, "reference", str(exc)) from None
    views, poses, sizes = [], [], []
    for i in range(num_views):
        sizes.append((integer(f"image_width_{i}", 1), integer(f"image_height_{i}", 1))
                     if f"image_width_{i}" in entries or f"image_height_{i}" in entries else size)
        K = _matrix(entries, f"K_{i}", (3, 3), path)  # noqa: N806
        dist = _matrix(entries, f"D_{i}", None, path)  # 4, 5 or more coefficients; those past p2 must be 0
        model = entries.get(f"model_{i}", "pinhole")
        lens = {m: lens for lens, m in _CV_MODELS.items()}.get(model) if isinstance(model, str) else None
        if lens is None:
            raise fail(path, f"model_{i}", f"must be {' or '.join(_CV_MODELS.values())}, got {model!r}")
        views.append(intrinsics(path, f"K_{i}, D_{i}", K, dist, lens))
        R = rotation(_matrix(entries, f"R_{i}", (3, 3), path), path, f"R_{i}")  # noqa: N806
        view_T_ref = make_T(R, _matrix(entries, f"T_{i}", (3, 1), path).ravel())  # noqa: N806
        if i == reference:
            check_reference_pose(view_T_ref, path, f"R_{i}, T_{i}")
        poses.append(invert_T(view_T_ref))
    calib = build(path, "num_views", file_grid, size, views, np.stack(poses), sizes)
    if any(key in entries for key in _RECT_KEYS) or any(f"R_rect_{i}" in entries for i in range(num_views)):
        calib = _with_rectification(calib, entries, path, integer)
    return fit_grid(calib, grid, path, "num_views")


def _with_rectification(calib: Calibration, entries: dict[str, Any], path: Path, integer) -> Calibration:
    """The calibration with the file's rectification stored (module docstring: what must hold, what is rebuilt)."""
    size = (integer("rect_image_width", 1), integer("rect_image_height", 1))
    K_r = _matrix(entries, "K_r", (3, 3), path)  # noqa: N806
    intrinsics(path, "K_r", K_r, None)  # the form [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
    crop = entries.get("rect_crop")
    if crop is not None and crop not in CROPS:
        raise fail(path, "rect_crop", f"must be {' or '.join(CROPS)}, got {crop!r}")
    rect_R_view = np.stack([rotation(_matrix(entries, f"R_rect_{i}", (3, 3), path), path, f"R_rect_{i}")  # noqa: N806
                            for i in range(calib.num_views)])
    rect_R_ref = rect_R_view[calib.grid.reference]  # noqa: N806
    p_last = []
    for i in range(calib.num_views):
        P = _matrix(entries, f"P_{i}", (3, 4), path)  # noqa: N806
        if np.max(np.abs(P[:, :3] - K_r)) > P_LEFT_BLOCK_REL * np.max(np.abs(K_r)):
            raise fail(path, f"P_{i}", f"must be [K_r | p] (stereoRectify's P1/P2: every rectified view has K_r), but "
                                       f"its left 3x3 is {P[:, :3].tolist()} and K_r {K_r.tolist()}")
        turn = rect_R_view[i] @ calib.ref_T_view[i][:3, :3].T @ rect_R_ref.T  # the identity for this calibration
        if np.degrees(RECT_ROTATION_TOLERANCE_RAD) < rotation_angle_deg(turn):
            raise fail(path, f"R_rect_{i}", f"does not rectify this calibration's view {i}: it is "
                                            f"{rotation_angle_deg(turn):.4g} deg off the reference's R_rect "
                                            f"R_{i}^T (a rectification of other extrinsics?)")
        p_last.append(P[:, 3])
    return attach(calib, rectification_from_projections(calib, size, K_r, rect_R_view, np.stack(p_last), crop))
