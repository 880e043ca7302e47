"""What the rerun recordings look like: colours, sizes and one default blueprint per command (used by
`lfgraph.viz.rerun_log`)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import rerun.blueprint as rrb

from lfgraph.core.calibration import Calibration
from lfgraph.core.grid import ViewGrid

RESIDUAL_ARROW_SCALE = 50.0  # residual arrows are drawn this many times longer than they are (sub-pixel otherwise)
RESIDUAL_COLOUR_MAX_PX = 1.0  # residual colour map saturates here
CHANGE_ARROW_BASELINE_SHARE = 0.5  # the longest input -> refined arrow is drawn this share of the smallest baseline
GUIDE_SPACING_PX = 40
JPEG_QUALITY = 80  # per-frame images are stored as JPEG (a recording of every frame stays small)
POINT_RADIUS_UI = 2.0  # observed points, in screen points (negative radii in rerun), whatever the zoom
FRUSTUM_BASELINE_SHARE = 0.4  # each camera's frustum is drawn this share of the smallest baseline deep
FRUSTUM_DEPTH_M = 0.02  # frustum depth of a single view (no baseline)
RIG_EYE_BASELINES = (-0.3, -0.45, -1.7)  # the default 3-D eye: a little left of, above and behind the rig centre, in
# rig sizes: nearly along the views, so that the grid spreads over the picture (from further up and to the side a
# 5x5's rows fell onto each other, labels and all)
OUTLIER_COLOUR = (255, 40, 40)
OBSERVED_COLOUR = (80, 160, 255)
REPROJECTED_COLOUR = (255, 255, 255)
GUIDE_COLOUR = (0, 255, 255)
CHANGE_COLOUR = (255, 0, 255)
ERROR_COLOUR = (31, 119, 180)
RMS_COLOUR = (255, 127, 14)
RIG_COLOURS = {"input": (160, 160, 160), "refined": (0, 200, 80), "calibrated": (0, 200, 80), "rig": (0, 200, 80)}
APP_ID = "lfgraph"
KINDS = ("calibrate", "refine", "rectify", "study")  # one default blueprint per command


def check_save_path(path: str | os.PathLike) -> None:
    """Fail before any work when a recording cannot be written there (missing folder, not writable, a folder)."""
    p = Path(path)
    if p.is_dir():
        raise ValueError(f"{p}: is a folder; give a recording file name such as {p / 'run.rrd'}")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise ValueError(f"{p}: folder {parent} does not exist")
    if not os.access(parent, os.W_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise ValueError(f"{p}: not writable")


def colour_by(values: np.ndarray, vmax: float) -> np.ndarray:
    """(N,) values -> (N, 3) uint8 colours from green (0) through yellow to red (>= vmax)."""
    t = np.clip(np.nan_to_num(values, nan=vmax) / vmax, 0.0, 1.0)
    r = np.clip(2.0 * t, 0.0, 1.0)
    g = np.clip(2.0 * (1.0 - t), 0.0, 1.0)
    return (np.stack([r, g, np.zeros_like(t)], axis=1) * 255).astype(np.uint8)


def rms_of(values_px: np.ndarray) -> float:
    """RMS of residual lengths (px); NaN when there are none."""
    return float(np.sqrt(np.mean(values_px**2))) if values_px.size else float("nan")


def _view_grid(grid: ViewGrid, space: str) -> rrb.Grid:
    # the views' residual arrows are exaggerated: the titles say by how much
    note = f" (residual arrows x{RESIDUAL_ARROW_SCALE:g})" if space == "views" else ""
    views = [rrb.Spatial2DView(origin=f"{space}/{grid.name(v)}", name=grid.name(v) + note)
             for v in range(grid.num_views)]
    return rrb.Grid(*views, grid_columns=grid.cols, name=space)


def _optimiser_views() -> list:
    return [rrb.BarChartView(origin="optimizer_summary/error_log10",
                             name="log10 graph error per LM iteration (a gap between stages)"),
            rrb.BarChartView(origin="optimizer_summary/rms_px",
                             name="RMS (px) per LM iteration (a gap between stages)")]


def rig_eye(calib: Calibration) -> rrb.EyeControls3D:
    """A 3-D eye on the rig: left of, above and behind its centre by `RIG_EYE_BASELINES` of its smallest baseline,
    looking at the centre, image-down (-y) up, so that the views (not landmarks metres away) fill the picture."""
    centres = calib.ref_T_view[:, :3, 3]
    centre = centres.mean(axis=0)
    scale = max(smallest_baseline_m(calib), float(np.max(np.linalg.norm(centres - centre, axis=1))))
    return rrb.EyeControls3D(position=centre + scale * np.asarray(RIG_EYE_BASELINES), look_target=centre,
                             eye_up=(0.0, -1.0, 0.0))


def default_blueprint(grid: ViewGrid | None, kind: str = "calibrate",
                      calib: Calibration | None = None) -> rrb.Blueprint:
    """The layout a recording opens with: one per command, each showing everything that command logs.

    Args:
        grid: the array (lays out the 2-D views); None for a study.
        kind: ``calibrate`` (3-D calibrated rig and boards, per-frame views, per-frame RMS, optimiser),
            ``refine`` (input and refined rig, landmarks, per-frame views, per-frame RMS, optimiser, stages),
            ``rectify`` (3-D rig, rectified views with guide lines) or ``study`` (the study's curves per level).
        calib: the array, when known: the 3-D view's eye is then on the rig (`rig_eye`).
    """
    eye = None if calib is None else rig_eye(calib)
    if kind not in KINDS:
        raise ValueError(f"unknown blueprint kind {kind!r}; one of {', '.join(KINDS)}")
    if kind == "study" or grid is None:
        return rrb.Blueprint(rrb.TimeSeriesView(origin="study", name="study results per shake level"),
                             rrb.TimePanel(timeline="level", state="collapsed"), collapse_panels=True)
    if kind == "rectify":
        return rrb.Blueprint(
            rrb.Horizontal(rrb.Spatial3DView(origin="world", name="rig (calibration)", eye_controls=eye),
                           _view_grid(grid, "rectified"),
                           column_shares=[1, 2]),
            collapse_panels=True)
    # the 2-D views are cameras of the 3-D scene too (their images in the frustums, one entity in both views)
    three_d = rrb.Spatial3DView(origin="world", name="input (grey) and refined (green) rig, landmarks"
                                if kind == "refine" else "calibrated rig and board poses", eye_controls=eye,
                                contents=["$origin/**", "+ /views/**"])
    side = [three_d, rrb.TimeSeriesView(origin="rms", name="RMS reprojection error per frame (px)"),
            *_optimiser_views()]
    if kind == "refine":
        side.append(rrb.TextLogView(origin="optimizer/stages", name="stages"))
    return rrb.Blueprint(
        rrb.Horizontal(rrb.Vertical(*side, row_shares=[3] + [1] * (len(side) - 1)), _view_grid(grid, "views"),
                       column_shares=[1, 2]),
        rrb.TimePanel(timeline="frame", state="collapsed"),
        collapse_panels=True,
    )


def smallest_baseline_m(calib: Calibration) -> float:
    """The smallest distance between two view centres (m); `FRUSTUM_DEPTH_M` for a single view."""
    centres = calib.ref_T_view[:, :3, 3]
    d = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    d = d[~np.eye(len(centres), dtype=bool)]
    d = d[d > 0]
    return float(d.min()) if d.size else FRUSTUM_DEPTH_M


def nice_factor(value: float) -> float:
    """The largest of 1, 2, 5 x 10^k that is at most ``value`` (arrow exaggerations read as round numbers)."""
    if not np.isfinite(value) or value <= 0:
        return 1.0
    k = np.floor(np.log10(value))
    return float(max(m * 10**k for m in (1.0, 2.0, 5.0) if m * 10**k <= value))
