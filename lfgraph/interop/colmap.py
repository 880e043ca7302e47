"""``colmap`` (export, import): a COLMAP (>= 3.12) text model folder.

``cameras.txt`` holds one ``OPENCV`` camera per view, camera ID = view index + 1:
``CAMERA_ID OPENCV W H fx fy cx cy k1 k2 p1 p2``. COLMAP puts the centre of the top-left pixel at ``(0.5, 0.5)``
(COLMAP docs, database format), so ``cx``, ``cy`` are written +0.5 px and read back -0.5 px. ``rigs.txt`` is COLMAP's
own rig file (doc/format.rst): one rig whose reference sensor is the reference view's camera and whose other sensors
carry ``sensor_from_rig`` = ``view_T_ref(i)`` as a Hamilton unit quaternion ``QW QX QY QZ`` and a translation
``TX TY TZ`` (metres). A comment line ``# lfgraph grid: RxC`` records the grid, which COLMAP cannot; without it import
needs ``grid``. Empty ``frames.txt``, ``images.txt`` and ``points3D.txt`` make the folder a complete (image-less)
model. ``rig_config.json`` beside it is the rig for COLMAP's rig workflow (``colmap rig_configurator
--rig_config_path``, doc/rigs.rst; `rig_config`): images in one folder per view named after the view. Import also
takes ``PINHOLE``, ``SIMPLE_PINHOLE``, ``SIMPLE_RADIAL`` and ``RADIAL`` cameras; camera IDs in increasing order
become the row-major views. Export replaces an existing folder only when it holds nothing but
COLMAP model files.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import gtsam
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.camera import Intrinsics
from lfgraph.core.geometry import invert_T, make_T
from lfgraph.core.grid import ViewGrid
from lfgraph.interop.common import (
    GridLike,
    build,
    fail,
    finite,
    fit_grid,
    intrinsics,
    num,
    read_text,
    required_grid,
    whole,
    write_folder,
)

COLMAP_PIXEL_OFFSET_PX = 0.5  # COLMAP's centre of the top-left pixel is (0.5, 0.5), OpenCV's (0, 0)
QUATERNION_NORM_TOLERANCE = 1e-3  # |q| may differ from 1 by this (rounded text) before a quaternion is refused
COLMAP_RIG_CONFIG = "rig_config.json"  # the rig_configurator's input (doc/rigs.rst), written beside the model
COLMAP_MODEL_FILES = frozenset({*(f"{name}.{ext}" for name in ("rigs", "cameras", "frames", "images", "points3D")
                                  for ext in ("txt", "bin")), COLMAP_RIG_CONFIG})
# COLMAP camera model -> names of its parameters, in file order (src/colmap/sensor/models.h)
COLMAP_CAMERA_MODELS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
}
_COLMAP_GRID_COMMENT = re.compile(r"^#\s*lfgraph grid:\s*(\d+)\s*[xX]\s*(\d+)\s*$")


def quaternion_wxyz(R: np.ndarray) -> np.ndarray:  # noqa: N803
    """(3, 3) rotation -> (4,) Hamilton unit quaternion (w, x, y, z) with w >= 0."""
    q = gtsam.Rot3(np.asarray(R, dtype=np.float64)).toQuaternion()
    wxyz = np.array([q.w(), q.x(), q.y(), q.z()])
    return -wxyz if wxyz[0] < 0 else wxyz


def rotation_from_wxyz(wxyz: np.ndarray) -> np.ndarray:
    """(4,) quaternion (w, x, y, z), already normalised -> (3, 3) rotation."""
    return np.asarray(gtsam.Rot3.Quaternion(*(float(c) for c in wxyz)).matrix(), dtype=np.float64)


def rig_config(calib: Calibration) -> str:
    """COLMAP's ``rig_config.json`` for ``colmap rig_configurator`` (doc/rigs.rst): one rig whose cameras are the
    views, images under ``<view name>/`` (e.g. ``r00_c01/000.png``: one folder per view, the same file name for one
    frame in every folder); the reference view is the ``ref_sensor``, every other view carries ``cam_from_rig_rotation``
    (w, x, y, z) and ``cam_from_rig_translation`` (metres) = ``view_T_ref``, and every camera its calibrated
    ``camera_model_name`` and ``camera_params`` (COLMAP's pixel convention, as ``cameras.txt``)."""
    cameras = []
    for v, intr in enumerate(calib.intrinsics):
        entry: dict = {"image_prefix": f"{calib.grid.name(v)}/"}
        if v == calib.grid.reference:
            entry["ref_sensor"] = True
        else:
            cam_from_rig = calib.view_T_ref(v)
            entry["cam_from_rig_rotation"] = [float(x) for x in quaternion_wxyz(cam_from_rig[:3, :3])]
            entry["cam_from_rig_translation"] = [float(x) for x in cam_from_rig[:3, 3]]
        entry["camera_model_name"] = "OPENCV_FISHEYE" if intr.lens == "fisheye" else "OPENCV"
        entry["camera_params"] = [float(p) for p in _params(intr)]
        cameras.append(entry)
    return json.dumps([{"cameras": cameras}], indent=2) + "\n"


def _params(intr: Intrinsics) -> list[float]:
    """The COLMAP parameters of a view (``OPENCV`` / ``OPENCV_FISHEYE`` order, COLMAP's pixel centres)."""
    return [intr.fx, intr.fy, intr.cx + COLMAP_PIXEL_OFFSET_PX, intr.cy + COLMAP_PIXEL_OFFSET_PX,
            *intr.distortion.values()]


def colmap_files(calib: Calibration) -> dict[str, str]:
    """The COLMAP text model of ``calib`` as {file name: text}: ``cameras.txt``, ``rigs.txt``, the empty
    ``frames.txt``, ``images.txt``, ``points3D.txt`` and ``rig_config.json`` (see the module docstring).

    Raises:
        ValueError: a unified lens (COLMAP has no such model)."""
    unified = [calib.grid.name(v) for v, i in enumerate(calib.intrinsics) if i.lens == "unified"]
    if unified:
        raise ValueError(f"COLMAP has no unified (omnidirectional) camera model, which views {', '.join(unified)} "
                         f"use; export them to Kalibr (omni-radtan) instead")
    n = calib.num_views
    cameras = [
        "# Camera list with one line of data per camera:",
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
        f"# Number of cameras: {n}",
        "# lfgraph: camera ID = view index + 1 (row-major); cx, cy in COLMAP's pixels (OpenCV's + 0.5)",
    ]
    for v, intr in enumerate(calib.intrinsics):
        model = "OPENCV_FISHEYE" if intr.lens == "fisheye" else "OPENCV"
        w, h = calib.image_size(v)  # each view's own (a rig of mixed sizes)
        cameras.append(f"{v + 1} {model} {w} {h} " + " ".join(num(p) for p in _params(intr)))
    ref = calib.grid.reference
    sensors = []
    for v in range(n):
        if v == ref:
            continue
        sensor_from_rig = calib.view_T_ref(v)  # the rig frame is the reference view's frame
        pose = [*quaternion_wxyz(sensor_from_rig[:3, :3]), *sensor_from_rig[:3, 3]]
        sensors.append(f"CAMERA {v + 1} 1 " + " ".join(num(x) for x in pose))
    rigs = [
        "# Rig calib list with one line of data per calib:",
        "#   RIG_ID, NUM_SENSORS, REF_SENSOR_TYPE, REF_SENSOR_ID, SENSORS[] as (SENSOR_TYPE, SENSOR_ID, HAS_POSE, "
        "[QW, QX, QY, QZ, TX, TY, TZ])",
        "# Number of rigs: 1",
        f"# lfgraph grid: {calib.grid.rows}x{calib.grid.cols}",
        " ".join([f"1 {n} CAMERA {ref + 1}", *sensors]),
    ]
    return {
        COLMAP_RIG_CONFIG: rig_config(calib),
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


def write(calib: Calibration, path: Path) -> None:
    """Write ``calib`` as a COLMAP text model folder at ``path`` (`lfgraph.interop.common.write_folder`)."""
    write_folder(path, colmap_files(calib), lambda name: name in COLMAP_MODEL_FILES, "a COLMAP model")


def _data_lines(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, tokens) of the data lines of a COLMAP text file."""
    text = read_text(path)
    return [(i, line.split()) for i, line in enumerate(text.splitlines(), 1)
            if line.strip() and not line.lstrip().startswith("#")]


def _read_cameras(cameras_path: Path) -> dict[int, tuple[Intrinsics, tuple[int, int]]]:
    """``cameras.txt``: camera ID -> (intrinsics, image size), OpenCV's pixel centres."""
    cameras: dict[int, tuple[Intrinsics, tuple[int, int]]] = {}
    for lineno, tok in _data_lines(cameras_path):
        where = f"line {lineno}"
        if len(tok) < 4:
            raise fail(cameras_path, where, "must be CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        cam_id = whole(tok[0], cameras_path, f"{where} CAMERA_ID")
        model = tok[1]
        names = COLMAP_CAMERA_MODELS.get(model)
        if names is None:
            raise fail(cameras_path, f"camera {cam_id} MODEL", f"{model!r} is not supported (supported: "
                                                                f"{', '.join(COLMAP_CAMERA_MODELS)})")
        if len(tok) != 4 + len(names):
            raise fail(cameras_path, f"camera {cam_id} PARAMS", f"{model} needs {len(names)} parameters "
                                                                 f"({' '.join(names)}), got {len(tok) - 4}")
        size = (whole(tok[2], cameras_path, f"camera {cam_id} WIDTH"),
                whole(tok[3], cameras_path, f"camera {cam_id} HEIGHT"))
        p = {name: finite(t, cameras_path, f"camera {cam_id} {name}") for name, t in zip(names, tok[4:], strict=True)}
        fx, fy = p.get("fx", p.get("f")), p.get("fy", p.get("f"))
        K = np.array([[fx, 0.0, p["cx"] - COLMAP_PIXEL_OFFSET_PX],  # noqa: N806
                      [0.0, fy, p["cy"] - COLMAP_PIXEL_OFFSET_PX], [0.0, 0.0, 1.0]])
        fisheye = model == "OPENCV_FISHEYE"
        dist = [p.get(k, 0.0) for k in (("k1", "k2", "k3", "k4") if fisheye else ("k1", "k2", "p1", "p2"))]
        if cam_id in cameras:
            raise fail(cameras_path, f"camera {cam_id}", "appears twice")
        cameras[cam_id] = (intrinsics(cameras_path, f"camera {cam_id}", K, dist, "fisheye" if fisheye else "radtan"),
                           size)
    if not cameras:
        raise fail(cameras_path, "cameras", "holds no camera")
    return cameras


def _read_rig(rigs_path: Path, ids: list[int]) -> tuple[int, dict[int, np.ndarray]]:
    """``rigs.txt``: the reference camera's ID and every camera's ``sensor_from_rig`` (4x4)."""
    rigs = _data_lines(rigs_path)
    if len(rigs) != 1:
        raise fail(rigs_path, "rigs", f"must hold exactly one rig with all {len(ids)} cameras, got {len(rigs)} rigs")
    lineno, tok = rigs[0]
    where = f"line {lineno}"
    if len(tok) < 4:
        raise fail(rigs_path, where, "must be RIG_ID NUM_SENSORS REF_SENSOR_TYPE REF_SENSOR_ID SENSORS[]")
    num_sensors = whole(tok[1], rigs_path, f"{where} NUM_SENSORS")
    if tok[2] != "CAMERA":
        raise fail(rigs_path, f"{where} REF_SENSOR_TYPE", f"must be CAMERA, got {tok[2]!r}")
    ref_id = whole(tok[3], rigs_path, f"{where} REF_SENSOR_ID")
    sensor_from_rig = {ref_id: np.eye(4)}
    pos = 4
    while pos < len(tok):
        if pos + 3 > len(tok):
            raise fail(rigs_path, f"{where} SENSORS", "ends inside a sensor (SENSOR_TYPE SENSOR_ID HAS_POSE ...)")
        sensor_type, sensor_id = tok[pos], whole(tok[pos + 1], rigs_path, f"{where} SENSOR_ID")
        has_pose = tok[pos + 2]
        key = f"sensor {sensor_id}"
        if sensor_type != "CAMERA":
            raise fail(rigs_path, f"{key} SENSOR_TYPE", f"must be CAMERA, got {sensor_type!r}")
        if has_pose != "1":
            raise fail(rigs_path, f"{key} HAS_POSE", f"must be 1 (lfgraph needs every camera's pose in the rig), "
                                                      f"got {has_pose!r}")
        if pos + 10 > len(tok):
            raise fail(rigs_path, f"{key} pose", "needs QW QX QY QZ TX TY TZ")
        q = np.array([finite(t, rigs_path, f"{key} Q") for t in tok[pos + 3: pos + 7]])
        t = np.array([finite(x, rigs_path, f"{key} T") for x in tok[pos + 7: pos + 10]])
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise fail(rigs_path, f"{key} QW QX QY QZ", f"must be a unit quaternion, |q| = {norm}")
        if sensor_id in sensor_from_rig:
            raise fail(rigs_path, key, "appears twice in the rig")
        sensor_from_rig[sensor_id] = make_T(rotation_from_wxyz(q / norm), t)
        pos += 10
    if num_sensors != len(sensor_from_rig):
        raise fail(rigs_path, f"{where} NUM_SENSORS", f"is {num_sensors}, but the rig lists {len(sensor_from_rig)}")
    if set(sensor_from_rig) != set(ids):
        raise fail(rigs_path, "SENSORS", f"the rig's cameras {sorted(sensor_from_rig)} must be the cameras of "
                                          f"cameras.txt {ids}")
    return ref_id, sensor_from_rig


def read(path: Path, grid: GridLike) -> Calibration:
    """Read a COLMAP text model folder (``cameras.txt`` and ``rigs.txt``) as a calibration on ``grid`` (the ``# lfgraph
    grid`` comment when None).

    Raises:
        CalibrationFileError: naming the file and the line or field."""
    if not path.is_dir():
        raise fail(path, "folder", "does not exist" if not path.exists() else "is not a folder (a COLMAP text "
                                                                              "model is a folder)")
    cameras_path, rigs_path = path / "cameras.txt", path / "rigs.txt"
    for p in (cameras_path, rigs_path):
        if not p.is_file():
            raise fail(path, p.name, "is missing")

    cameras = _read_cameras(cameras_path)
    ids = sorted(cameras)
    sizes = [cameras[i][1] for i in ids]
    ref_id, sensor_from_rig = _read_rig(rigs_path, ids)
    reference = ids.index(ref_id)

    file_dims = None
    for line in rigs_path.read_text(encoding="utf-8").splitlines():
        m = _COLMAP_GRID_COMMENT.match(line.strip())
        if m:
            file_dims = (int(m.group(1)), int(m.group(2)))
    if file_dims is None:
        view_grid = required_grid(grid, len(ids), path, "cameras.txt", reference)
    else:
        rows, cols = file_dims
        if rows * cols != len(ids):
            raise fail(rigs_path, "# lfgraph grid", f"is {rows}x{cols}, but the model holds {len(ids)} cameras")
        view_grid = ViewGrid(rows, cols, reference)
    views = [cameras[i][0] for i in ids]
    ref_T_view = np.stack([invert_T(sensor_from_rig[i]) for i in ids])  # noqa: N806
    ref_T_view[reference] = np.eye(4)
    calib = build(path, "rigs.txt", view_grid, sizes[reference], views, ref_T_view, sizes)
    return fit_grid(calib, grid, path, "cameras.txt")
