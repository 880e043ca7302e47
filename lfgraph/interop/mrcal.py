"""``mrcal`` (export): a folder of mrcal ``.cameramodel`` files, one per view (``<view name>.cameramodel``).

The format is mrcal's native one (mrcal docs, "cameramodels", and the models it ships): a Python dict literal
with ``'lensmodel'`` (``LENSMODEL_OPENCV5``: OpenCV's k1 k2 p1 p2 k3, with k3 = 0), ``'intrinsics'`` (fx, fy, cx,
cy, then the distortion), ``'extrinsics'`` (``rt_fromref``: the transform from the reference view's coordinates to
the camera's, as a Rodrigues rotation then a translation in metres: lfgraph's ``view_T_ref``; the reference view's
is zero) and ``'imagersize'`` (width, height). Pixels follow OpenCV's convention, as mrcal's. mrcal has no
Kannala–Brandt or unified model: fisheye and unified views are refused (export them to Kalibr).
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.interop.common import num, write_folder

VIEW_FILE = re.compile(r"^r\d+_c\d+\.cameramodel$")  # what an export writes (and may replace)
MRCAL_LENS_MODELS = {"radtan": "LENSMODEL_OPENCV5"}  # lfgraph lens -> mrcal lensmodel


def cameramodel(calib: Calibration, v: int) -> str:
    """View ``v`` as a ``.cameramodel`` text."""
    intr = calib.intrinsics[v]
    view_T_ref = calib.view_T_ref(v)  # noqa: N806
    r = cv2.Rodrigues(np.ascontiguousarray(view_T_ref[:3, :3]))[0].ravel()
    w, h = calib.image_size(v)

    def listed(values) -> str:
        return "[ " + ", ".join(num(float(x)) for x in values) + " ]"

    return "\n".join([
        f"# {calib.grid.name(v)} of a {calib.grid} lfgraph array (reference {calib.grid.name(calib.grid.reference)})",
        "{",
        f"    'lensmodel':  '{MRCAL_LENS_MODELS[intr.lens]}',",
        "    # intrinsics are fx,fy,cx,cy,distortion0,distortion1,....",
        f"    'intrinsics': {listed([intr.fx, intr.fy, intr.cx, intr.cy, *intr.dist_cv.ravel()])},",
        "    # extrinsics are rt_fromref",
        f"    'extrinsics': {listed([*r, *view_T_ref[:3, 3]])},",
        f"    'imagersize': [ {int(w)}, {int(h)} ],",
        "}",
        "",
    ])


def write(calib: Calibration, path: Path) -> None:
    """Write one mrcal ``.cameramodel`` per view into the folder ``path`` (`cameramodel`).

    Raises:
        ValueError: a fisheye or unified view (mrcal has neither model)."""
    other = [calib.grid.name(v) for v, i in enumerate(calib.intrinsics) if i.lens not in MRCAL_LENS_MODELS]
    if other:
        raise ValueError(f"{path}: mrcal has no Kannala-Brandt (fisheye) or unified lens model, which views "
                         f"{', '.join(other)} use; export them to Kalibr (pinhole-equi / omni-radtan) instead")
    files = {f"{calib.grid.name(v)}.cameramodel": cameramodel(calib, v) for v in range(calib.num_views)}
    write_folder(path, files, lambda name: VIEW_FILE.match(name) is not None, "an mrcal model folder")
