"""``middlebury`` (import): Middlebury 2014 ``calib.txt`` (or the scene folder holding it).

``cam0=[f 0 cx0; 0 f cy; 0 0 1]``, ``cam1=..``, ``baseline=`` (mm), ``width=``, ``height=`` and others (``doffs``,
``ndisp``, ... are not needed). A rectified 1x2 grid: cam1 sits ``baseline`` to the right of cam0 with the same
orientation, ``x_view1 = x_ref - [b, 0, 0]``; no distortion. Assumes Middlebury pixels follow OpenCV's convention
(its ``doffs = cx1 - cx0`` does not depend on it).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.geometry import make_T
from lfgraph.core.grid import ViewGrid
from lfgraph.interop.common import (
    MM_PER_M,
    GridLike,
    PathLike,
    array,
    build,
    fail,
    finite,
    fit_grid,
    in_folder,
    intrinsics,
    read_text,
    whole,
)

CALIB_FILE = "calib.txt"


def _matrix(text: str, path: PathLike, key: str) -> np.ndarray:
    """``[a b c; d e f; g h i]`` (spaces or commas between numbers) -> (3, 3)."""
    body = text.strip()
    if not (body.startswith("[") and body.endswith("]")):
        raise fail(path, key, f"must be a matrix [a b c; d e f; g h i], got {text.strip()!r}")
    rows = [r.replace(",", " ").split() for r in body[1:-1].split(";")]
    return array(rows, (3, 3), path, key)


def read(path: Path, grid: GridLike) -> Calibration:
    """Read a Middlebury 2014 ``calib.txt`` (the file or its scene folder) as a 1x2 calibration (``cam0``, ``cam1``,
    ``baseline`` in mm)."""
    path = in_folder(path, CALIB_FILE)
    entries: dict[str, str] = {}
    for lineno, line in enumerate(read_text(path).splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        key, eq, value = line.partition("=")
        if not eq:
            raise fail(path, f"line {lineno}", f"must be KEY=VALUE, got {line!r}")
        entries[key.strip()] = value.strip()
    for key in ("cam0", "cam1", "baseline", "width", "height"):
        if key not in entries:
            raise fail(path, key, "is missing")
    views = [intrinsics(path, key, _matrix(entries[key], path, key), None)
                  for key in ("cam0", "cam1")]
    size = (whole(entries["width"], path, "width"), whole(entries["height"], path, "height"))
    baseline_m = finite(entries["baseline"], path, "baseline") / MM_PER_M
    if baseline_m <= 0:
        raise fail(path, "baseline", f"must be positive (mm), got {entries['baseline']!r}")
    ref_T_view = np.stack([np.eye(4), make_T(np.eye(3), [baseline_m, 0.0, 0.0])])  # noqa: N806 - cam1 to the right
    calib = build(path, "cam0, cam1", ViewGrid(1, 2, 0), size, views, ref_T_view)
    return fit_grid(calib, grid, path, "cam0, cam1")
