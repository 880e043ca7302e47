"""``ros`` (export): a folder of ROS ``camera_info`` YAML files, one per view (``<view name>.yaml``, e.g.
``r00_c01.yaml``), in the format of ``camera_calibration_parsers`` (what ``camera_info_manager`` loads and the ROS
``cameracalibrator`` writes): ``image_width``, ``image_height``, ``camera_name``, ``camera_matrix`` (3x3 K),
``distortion_model`` (``plumb_bob``: k1 k2 p1 p2 k3 with k3 = 0; ``equidistant``: k1 k2 k3 k4, for fisheye views),
``distortion_coefficients``, ``rectification_matrix`` (3x3) and ``projection_matrix`` (3x4), each matrix as
``{rows, cols, data}`` row-major.

With a stored rectification, R is the view's rectifying rotation (rectified from view) and P = ``[K_r | -K_r c_i]``
with ``c_i`` the view's ideal position relative to the reference in the rectified frame: ROS's stereo convention
(the reference view has a zero last column, a view at baseline b along x has ``P[0, 3] = -fx b``), so
``cv2.initUndistortRectifyMap(K, D, R, P[:, :3], size, ...)`` gives lfgraph's rectified view. Without a stored one
the rectification `lfgraph.rectification.rectify.rectify` would store is computed (never ``[K | 0]`` for every view:
a zero baseline); a calibration that cannot be rectified is refused, a single view gets R = I, P = ``[K | 0]`` (a
monocular camera_info). Views with a unified lens are refused (ROS's image_geometry has no such model).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import yaml

from lfgraph.core.calibration import Calibration
from lfgraph.interop.common import write_folder
from lfgraph.interop.opencv_yaml import rectified_projection
from lfgraph.rectification.rectify import rectification_for_export

VIEW_FILE = re.compile(r"^r\d+_c\d+\.yaml$")  # what an export writes (and may replace)
ROS_DISTORTION_MODELS = {"radtan": "plumb_bob", "fisheye": "equidistant"}  # lfgraph lens -> ROS distortion_model


def _matrix(m: np.ndarray) -> dict:
    m = np.atleast_2d(np.asarray(m, dtype=np.float64))
    return {"rows": int(m.shape[0]), "cols": int(m.shape[1]), "data": [float(x) for x in m.ravel()]}


def camera_infos(calib: Calibration) -> dict[str, str]:
    """``<view name>.yaml`` -> the view's camera_info YAML text."""
    unified = [calib.grid.name(v) for v, i in enumerate(calib.intrinsics) if i.lens not in ROS_DISTORTION_MODELS]
    if unified:
        raise ValueError(f"ROS camera_info has no unified (omnidirectional) distortion model, which views "
                         f"{', '.join(unified)} use; export them to Kalibr (omni-radtan) instead")
    rect = rectification_for_export(calib, required=True)
    out = {}
    for v, intr in enumerate(calib.intrinsics):
        w, h = calib.image_size(v)
        if rect is None:
            r, p = np.eye(3), np.column_stack([intr.K, np.zeros(3)])
        else:
            r, p = rect.rect_R_view[v], rectified_projection(rect.K_r, rect.P[v])
        info = {"image_width": int(w), "image_height": int(h), "camera_name": calib.grid.name(v),
                "camera_matrix": _matrix(intr.K), "distortion_model": ROS_DISTORTION_MODELS[intr.lens],
                "distortion_coefficients": _matrix(intr.dist_cv.reshape(1, -1)),
                "rectification_matrix": _matrix(r), "projection_matrix": _matrix(p)}
        out[f"{calib.grid.name(v)}.yaml"] = yaml.safe_dump(info, sort_keys=False, default_flow_style=None)
    return out


def write(calib: Calibration, path: Path) -> None:
    """Write one ROS ``camera_info`` YAML file per view into the folder ``path`` (`camera_infos`)."""
    write_folder(path, camera_infos(calib), lambda name: VIEW_FILE.match(name) is not None,
                 "a ROS camera_info folder")
