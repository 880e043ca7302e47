"""What the rerun recordings look like: colours, sizes and one default blueprint per command (used by
`lfgraph.viz.rerun_log`)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import rerun.blueprint as rrb

from lfgraph.core.calibration import Calibration
from lfgraph.core.grid import ViewGrid
from lfgraph.viz.framing import (  # noqa: F401  (FRUSTUM_*, smallest_baseline_m: re-exported)
    FRUSTUM_BASELINE_SHARE,
    FRUSTUM_DEPTH_M,
    rig_eye,
    smallest_baseline_m,
)

RESIDUAL_ARROW_SCALE = 50.0  # residual arrows are drawn this many times longer than they are (sub-pixel otherwise)
RESIDUAL_COLOUR_MAX_PX = 1.0  # residual colour map saturates here
CHANGE_ARROW_BASELINE_SHARE = 0.5  # the longest input -> refined arrow is drawn this share of the smallest baseline
GUIDE_SPACING_PX = 40
JPEG_QUALITY = 80  # per-frame images are stored as JPEG (a recording of every frame stays small)
POINT_RADIUS_UI = 2.0  # observed points, in screen points (negative radii in rerun), whatever the zoom
VIEWS_COLUMN_SHARES = [1.0, 1.15]  # the 3-D view and charts : the 2-D views
MAX_FULL_TITLE_COLUMNS = 4  # a wider grid titles its 2-D views r0c4 (for r00_c04): a 5x5's r00_c0… told none apart
MAX_LEGEND_VIEWS = 6  # the per-frame RMS chart has a legend up to this many views
MAX_LINE_COLUMNS = 4  # a line of views (1xN) is laid out in rows of this many 2-D views (a 1x8 in one row: slivers)
OUTLIER_COLOUR = (255, 40, 40)
OBSERVED_COLOUR = (80, 160, 255)
REPROJECTED_COLOUR = (255, 255, 255)
GUIDE_COLOUR = (0, 255, 255)
CHANGE_COLOUR = (255, 0, 255)
ERROR_COLOUR = (31, 119, 180)
RMS_COLOUR = (255, 127, 14)
STAGE_COLOURS = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (148, 103, 189), (140, 86, 75), (227, 119, 194))
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


def _title(grid: ViewGrid, v: int) -> str:
    """A 2-D view's title: its name (``r00_c04``), or ``r0c4`` in a grid too wide for names."""
    if grid.cols <= MAX_FULL_TITLE_COLUMNS:
        return grid.name(v)
    r, c = grid.position(v)
    return f"r{r}c{c}"


def _view_grid(grid: ViewGrid, space: str) -> rrb.Tabs:
    """The 2-D views laid out like the grid (a line wraps after `MAX_LINE_COLUMNS`), each titled with its name
    only (`_title`: a 5x5's titles have room for no more), under one tab saying what they show."""
    views = [rrb.Spatial2DView(origin=f"{space}/{grid.name(v)}", name=_title(grid, v)) for v in range(grid.num_views)]
    columns = grid.cols if grid.rows > 1 else min(grid.cols, MAX_LINE_COLUMNS)
    title = (f"views on the frame timeline: observed (blue), reprojected (white), residual arrows x"
             f"{RESIDUAL_ARROW_SCALE:g} (coloured by size), outliers (red)" if space == "views"
             else f"rectified views, guide lines every {GUIDE_SPACING_PX} px")
    return rrb.Tabs(rrb.Grid(*views, grid_columns=columns, name=title), name=space)


def _optimiser_views() -> list:
    # one bar chart per stage name under each (`lfgraph.viz.optimiser_log`): the legend names the stages
    return [rrb.BarChartView(origin="optimizer_summary/error_decades", name="LM: error fall (decades)"),
            rrb.BarChartView(origin="optimizer_summary/rms_px", name="LM: RMS (px)")]


def _text_view(kind: str) -> rrb.TextLogView:
    """refine: where each stage starts; calibrate: the progress lines and warnings (the text only, full width)."""
    hide = ["EntityPath", "LogLevel"] if kind == "refine" else ["EntityPath"]
    columns = rrb.TextLogColumns(text_log_columns=[rrb.components.TextLogColumn(k, visible=k not in hide)
                                                   for k in ("EntityPath", "LogLevel", "Body")])
    if kind == "refine":
        return rrb.TextLogView(origin="optimizer/stages", name="stages", columns=columns)
    return rrb.TextLogView(origin="log", name="log", columns=columns)


def default_blueprint(grid: ViewGrid | None, kind: str = "calibrate",
                      calib: Calibration | None = None) -> rrb.Blueprint:
    """The layout a recording opens with: one per command, each showing everything that command logs.

    Args:
        grid: the array (lays out the 2-D views; a line of views wraps after `MAX_LINE_COLUMNS`); None for a study.
        kind: ``calibrate`` (3-D calibrated rig and boards, per-frame views, per-frame RMS, optimiser, log),
            ``refine`` (input and refined rig, landmarks, per-frame views, per-frame RMS, optimiser, stages),
            ``rectify`` (3-D rig, rectified views with guide lines) or ``study`` (the study's curves per level).
        calib: the array, when known: the 3-D view's eye is then on the rig (`lfgraph.viz.framing.rig_eye`: the rig
            fills the view, landmarks and boards further out do not set the framing).
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
                           column_shares=[1, 1]),
            collapse_panels=True)
    # the 2-D views are cameras of the 3-D scene too (their images in the frustums, one entity in both views)
    three_d = rrb.Spatial3DView(origin="world", name="input (grey) and refined (green) rig, change (magenta), "
                                "landmarks" if kind == "refine" else "calibrated rig and board poses",
                                eye_controls=eye, contents=["$origin/**", "+ /views/**"])
    # a legend of 25 views hides the curves: hover names them
    rms = rrb.TimeSeriesView(origin="rms", name="RMS per frame (px)",
                             plot_legend=rrb.PlotLegend(visible=grid.num_views <= MAX_LEGEND_VIEWS))
    side = rrb.Vertical(three_d, rrb.Horizontal(*_optimiser_views()), rrb.Horizontal(rms, _text_view(kind)),
                        row_shares=[3, 1.3, 1])
    return rrb.Blueprint(
        rrb.Horizontal(side, _view_grid(grid, "views"), column_shares=VIEWS_COLUMN_SHARES),
        rrb.TimePanel(timeline="frame", state="collapsed"),
        collapse_panels=True,
    )


def nice_factor(value: float) -> float:
    """The largest of 1, 2, 5 x 10^k that is at most ``value`` (arrow exaggerations read as round numbers)."""
    if not np.isfinite(value) or value <= 0:
        return 1.0
    k = np.floor(np.log10(value))
    return float(max(m * 10**k for m in (1.0, 2.0, 5.0) if m * 10**k <= value))
