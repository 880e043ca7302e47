"""``hci`` (import): the HCI 4D light-field benchmark's ``parameters.cfg`` (or the scene folder holding it).

An INI file. ``[intrinsics]``: ``focal_length_mm``, ``sensor_size_mm``, ``image_resolution_x_px``,
``image_resolution_y_px``; ``[extrinsics]``: ``num_cams_x`` (columns), ``num_cams_y`` (rows), ``baseline_mm``. Focal
length in pixels = ``focal_length_mm / sensor_size_mm * max(width, height)`` (Blender's automatic sensor fit);
principal point at the image centre ``((w - 1) / 2, (h - 1) / 2)``; no distortion; parallel views on a regular grid of
pitch ``baseline_mm``, row-major, column index along camera +x (right), row index along camera +y (down); reference
= the top-left view unless ``grid`` names another. Assumptions: the benchmark renders with shifted sensors so that
disparity is zero at ``focus_distance_m``; that shift is not modelled here (disparities measured with this
calibration differ from HCI's ground truth by a constant), and ``center_cam_*`` (the rig's place in the Blender
scene), ``fstop`` and ``[meta]`` are not used.
"""

from __future__ import annotations

import configparser
from pathlib import Path

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.camera import Intrinsics
from lfgraph.core.grid import ViewGrid
from lfgraph.interop.common import (
    MM_PER_M,
    GridLike,
    build,
    check_view_count,
    fail,
    finite,
    fit_grid,
    in_folder,
    read_text,
    whole,
)

PARAMETERS_FILE = "parameters.cfg"


def read(path: Path, grid: GridLike) -> Calibration:
    """Read an HCI 4D light-field benchmark ``parameters.cfg`` (the file or its scene folder) as a calibration on
    ``grid`` (the module docstring gives the conventions)."""
    path = in_folder(path, PARAMETERS_FILE)
    parser = configparser.ConfigParser(interpolation=None)  # a '%' in a value is text
    try:
        parser.read_string(read_text(path), source=str(path))
    except configparser.Error as exc:
        raise fail(path, "file", f"not a valid INI file ({' '.join(str(exc).split())})") from None

    def get(section: str, key: str) -> str:
        if not parser.has_section(section):
            raise fail(path, f"[{section}]", "section is missing")
        if not parser.has_option(section, key):
            raise fail(path, f"[{section}] {key}", "is missing")
        return parser.get(section, key)

    def positive(section: str, key: str) -> float:
        x = finite(get(section, key), path, f"[{section}] {key}")
        if x <= 0:
            raise fail(path, f"[{section}] {key}", f"must be positive, got {x}")
        return x

    focal_mm = positive("intrinsics", "focal_length_mm")
    sensor_mm = positive("intrinsics", "sensor_size_mm")
    w = whole(get("intrinsics", "image_resolution_x_px"), path, "[intrinsics] image_resolution_x_px")
    h = whole(get("intrinsics", "image_resolution_y_px"), path, "[intrinsics] image_resolution_y_px")
    cols = whole(get("extrinsics", "num_cams_x"), path, "[extrinsics] num_cams_x")
    rows = whole(get("extrinsics", "num_cams_y"), path, "[extrinsics] num_cams_y")
    check_view_count(rows * cols, path, "[extrinsics] num_cams_x, num_cams_y")
    pitch_m = positive("extrinsics", "baseline_mm") / MM_PER_M
    focal_px = focal_mm / sensor_mm * max(w, h)  # the sensor size spans the longer image side
    intr = Intrinsics(focal_px, focal_px, (w - 1) / 2.0, (h - 1) / 2.0)
    view_grid = ViewGrid(rows, cols, 0)
    ref_T_view = np.tile(np.eye(4), (view_grid.num_views, 1, 1))  # noqa: N806
    for v in range(view_grid.num_views):
        r, c = view_grid.position(v)
        ref_T_view[v, :3, 3] = [c * pitch_m, r * pitch_m, 0.0]  # +x right along a row, +y down the columns
    calib = build(path, "[extrinsics]", view_grid, (w, h), [intr] * view_grid.num_views, ref_T_view)
    return fit_grid(calib, grid, path, "[extrinsics] num_cams_x, num_cams_y")
