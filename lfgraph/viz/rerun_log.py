"""Rerun logging for visual debugging. The only module that imports rerun; the core offers hooks, this subscribes.

Entity tree (a newcomer opening the ``.rrd`` gets the default blueprint: the rig in 3-D, the views in a grid, the
optimiser's curves):

- ``world/rig/view_rRR_cCC``: `Transform3D` (the view's pose in the reference frame) + `Pinhole` (K, image size),
  with the view's image under ``.../image``;
- ``world/boards/frame_FFF``: each board pose (`Transform3D`) with its corners (`Points3D`, board frame);
- ``world/landmarks``: refinement landmarks (`Points3D`, coloured by mean reprojection error);
- ``views/rRR_cCC``: 2-D space of a view: ``image``, ``observed`` and ``reprojected`` (`Points2D`), ``residuals``
  (`Arrows2D` scaled by `RESIDUAL_ARROW_SCALE`, coloured by magnitude), ``outliers`` (`Points2D`, red);
- ``optimizer/error`` and ``optimizer/rms_px`` (`Scalars` on the ``iteration`` timeline), ``optimizer/stages``
  (`TextLog` at each stage's first iteration), ``rms/view_rRR_cCC`` (`Scalars`, per frame on the ``frame``
  timeline during refinement);
- ``rectified/rRR_cCC``: rectified views with horizontal guide lines (`LineStrips2D`) every `GUIDE_SPACING_PX`.
"""

from __future__ import annotations

import os
from pathlib import Path
from types import TracebackType

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from lfgraph.calibration import Calibration
from lfgraph.grid import ViewGrid
from lfgraph.observer import BaseObserver, StageEnd

RESIDUAL_ARROW_SCALE = 50.0  # residual arrows are drawn this many times longer than they are (sub-pixel otherwise)
RESIDUAL_COLOUR_MAX_PX = 1.0  # residual colour map saturates here
GUIDE_SPACING_PX = 40
OUTLIER_COLOUR = (255, 40, 40)
APP_ID = "lfgraph"
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


def _colour_by(values: np.ndarray, vmax: float) -> np.ndarray:
    """(N,) values -> (N, 3) uint8 colours from green (0) through yellow to red (>= vmax)."""
    t = np.clip(np.nan_to_num(values, nan=vmax) / vmax, 0.0, 1.0)
    r = np.clip(2.0 * t, 0.0, 1.0)
    g = np.clip(2.0 * (1.0 - t), 0.0, 1.0)
    return (np.stack([r, g, np.zeros_like(t)], axis=1) * 255).astype(np.uint8)


def default_blueprint(grid: ViewGrid) -> rrb.Blueprint:
    """3-D view of the rig and landmarks, the 2-D views in the grid's layout, the optimiser's curves."""
    views = [rrb.Spatial2DView(origin=f"views/{grid.name(v)}", name=grid.name(v)) for v in range(grid.num_views)]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(rrb.Spatial3DView(origin="world", name="rig, boards and landmarks"),
                         rrb.TimeSeriesView(origin="optimizer", name="optimiser")),
            rrb.Grid(*views, grid_columns=grid.cols, name="views"),
            column_shares=[1, 1],
        ),
        collapse_panels=True,
    )


class RerunLogger(BaseObserver):
    """Logs lfgraph's data to one explicit `rr.RecordingStream` (never the global one); an `lfgraph.Observer`.

    Make one with `to_file` (written atomically when closed), `from_stream` (your own stream), `serve`, `connect`
    or `stdout`; use it as a context manager (closed at the end; a failure discards a file recording) and pass it
    as ``observer=`` to `lfgraph.calibrate` / `lfgraph.refine`.
    """

    def __init__(self, rec: rr.RecordingStream, grid: ViewGrid | None = None, final_path: Path | None = None,
                 tmp_path: Path | None = None) -> None:
        self.rec = rec
        self.grid = grid
        self._final, self._tmp = final_path, tmp_path
        self.iteration_count = 0
        self._calib: Calibration | None = None  # the latest refined calibration (for naming views of outliers)
        self.rec.log("optimizer/error", rr.SeriesLines(names="graph error"), static=True)
        self.rec.log("optimizer/rms_px", rr.SeriesLines(names="RMS (px, from the error)"), static=True)
        self._n_measurements = 0

    @classmethod
    def to_file(cls, path: str | os.PathLike, grid: ViewGrid | None = None) -> RerunLogger:
        """Record to ``path`` (.rrd): written next to it and renamed on a successful `close`, so a failed run leaves
        no half-written file.

        Raises:
            ValueError: the path is a folder, its folder does not exist or is not writable.
        """
        final = Path(path)
        check_save_path(final)
        tmp = final.with_name(f".{final.name}.{os.getpid()}.tmp")
        rec = rr.RecordingStream(APP_ID)
        rec.save(str(tmp), default_blueprint=None if grid is None else default_blueprint(grid))
        return cls(rec, grid, final, tmp)

    @classmethod
    def from_stream(cls, rec: rr.RecordingStream, grid: ViewGrid | None = None) -> RerunLogger:
        """Log to a stream you opened (and whose sink you chose); ``grid`` sends the default blueprint."""
        if grid is not None:
            rec.send_blueprint(default_blueprint(grid))
        return cls(rec, grid)

    @classmethod
    def serve(cls, grid: ViewGrid | None = None) -> RerunLogger:
        """Host a gRPC server and web viewer for the recording."""
        rec = rr.RecordingStream(APP_ID)
        rec.serve_grpc(default_blueprint=None if grid is None else default_blueprint(grid))
        return cls(rec, grid)

    @classmethod
    def connect(cls, url: str | None = None, grid: ViewGrid | None = None) -> RerunLogger:
        """Stream to a running viewer (rerun's default address unless ``url``)."""
        rec = rr.RecordingStream(APP_ID)
        rec.connect_grpc(url, default_blueprint=None if grid is None else default_blueprint(grid))
        return cls(rec, grid)

    @classmethod
    def stdout(cls, grid: ViewGrid | None = None) -> RerunLogger:
        """Write the recording to standard output (pipe it into ``rerun -``)."""
        rec = rr.RecordingStream(APP_ID)
        rec.stdout(default_blueprint=None if grid is None else default_blueprint(grid))
        return cls(rec, grid)

    @property
    def path(self) -> Path | None:
        """The recording file (`to_file`), else None."""
        return self._final

    def __enter__(self) -> RerunLogger:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close(success=exc_type is None)

    # ------------------------------------------------------------------------------------------- observer
    def log(self, message: str) -> None:
        """Into the recording only (combine with `lfgraph.BaseObserver` in `lfgraph.Observers` for the console)."""
        self.rec.log("log", rr.TextLog(message, level="INFO"))

    def iteration(self, iteration: int, error_before: float, error_after: float) -> None:
        self.on_iteration(iteration, error_before, error_after)

    def frame(self, index: int, images: np.ndarray) -> None:
        self.rec.set_time("frame", sequence=index)

    def stage_start(self, name: str, measurements: int) -> None:
        self.rec.set_time("iteration", sequence=self.iteration_count + 1)
        self.rec.log("optimizer/stages", rr.TextLog(f"stage {name} starts", level="INFO"))
        self.set_measurements(measurements)

    def stage_end(self, event: StageEnd) -> None:
        from lfgraph.camera import project_world

        calib, points, valid = event.calib, event.points_ref_m, event.valid
        with np.errstate(invalid="ignore"):
            mean_err = np.nanmean(np.where(valid, event.errors_px, np.nan), axis=0)
        self.landmarks(points, mean_err)
        projected = np.stack([project_world(calib.intrinsics[v], calib.view_T_ref(v), points)
                              for v in range(calib.num_views)])
        self.observations(calib, event.pixels_px, projected, valid)
        self._calib = calib

    def outliers(self, name: str, pixels_px: np.ndarray, valid: np.ndarray) -> None:
        if self._calib is None:
            return
        for v in range(self._calib.num_views):
            self.rec.log(f"views/{self._calib.grid.name(v)}/outliers",
                         rr.Points2D(pixels_px[v][valid[v]], radii=2.0, colors=OUTLIER_COLOUR))

    # ------------------------------------------------------------------------------------------- optimiser
    def set_measurements(self, n: int) -> None:
        """Number of 2-D measurements of the graph being optimised (turns the error into an RMS in pixels)."""
        self._n_measurements = int(n)

    def on_iteration(self, _iteration: int, _before: float, after: float) -> None:
        """`lfgraph.optimize` callback: one step on the ``iteration`` timeline per optimiser iteration."""
        self.iteration_count += 1
        self.rec.set_time("iteration", sequence=self.iteration_count)
        self.rec.log("optimizer/error", rr.Scalars(after))
        if self._n_measurements:
            # graph error = 0.5 sum |r|^2 at 1 px sigma (priors are negligible): RMS per point = sqrt(2 e / N)
            self.rec.log("optimizer/rms_px", rr.Scalars(float(np.sqrt(2.0 * after / self._n_measurements))))

    def rig(self, calib: Calibration, images: np.ndarray | None = None) -> None:
        """Every view's pose, intrinsics and (optionally) an image, static."""
        w, h = calib.image_size_px
        for v in range(calib.num_views):
            path = f"world/rig/view_{calib.grid.name(v)}"
            pose = calib.ref_T_view[v]
            self.rec.log(path, rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]), static=True)
            self.rec.log(path, rr.Pinhole(image_from_camera=calib.intrinsics[v].K, resolution=[w, h],
                                          image_plane_distance=0.02), static=True)
            if images is not None:
                self.rec.log(f"{path}/image", rr.Image(images[v]), static=True)
                self.rec.log(f"views/{calib.grid.name(v)}/image", rr.Image(images[v]), static=True)

    def boards(self, ref_T_board: np.ndarray, object_points_m: np.ndarray) -> None:  # noqa: N803
        for f, pose in enumerate(ref_T_board):
            if not np.all(np.isfinite(pose)):
                continue
            path = f"world/boards/frame_{f:03d}"
            self.rec.log(path, rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]), static=True)
            self.rec.log(f"{path}/corners", rr.Points3D(object_points_m, radii=0.0008), static=True)

    def landmarks(self, points_ref: np.ndarray, mean_error_px: np.ndarray) -> None:
        ok = np.all(np.isfinite(points_ref), axis=1)
        self.rec.log("world/landmarks", rr.Points3D(points_ref[ok], colors=_colour_by(mean_error_px[ok],
                                                                                       RESIDUAL_COLOUR_MAX_PX),
                                                    radii=0.01))

    def observations(self, calib: Calibration, observed: np.ndarray, projected: np.ndarray, valid: np.ndarray,
                     outliers: np.ndarray | None = None) -> None:
        """Per view: observed and reprojected points and residual arrows. Arrays (V, N, 2) / (V, N)."""
        for v in range(calib.num_views):
            base = f"views/{calib.grid.name(v)}"
            m = valid[v] & np.all(np.isfinite(observed[v]), axis=-1) & np.all(np.isfinite(projected[v]), axis=-1)
            obs, proj = observed[v][m], projected[v][m]
            res = obs - proj
            mag = np.linalg.norm(res, axis=1)
            self.rec.log(f"{base}/observed", rr.Points2D(obs, radii=1.0, colors=(80, 160, 255)))
            self.rec.log(f"{base}/reprojected", rr.Points2D(proj, radii=0.8, colors=(255, 255, 255)))
            self.rec.log(f"{base}/residuals", rr.Arrows2D(origins=proj, vectors=res * RESIDUAL_ARROW_SCALE,
                                                          colors=_colour_by(mag, RESIDUAL_COLOUR_MAX_PX)))
            if outliers is not None:
                o = outliers[v] & np.all(np.isfinite(observed[v]), axis=-1)
                self.rec.log(f"{base}/outliers", rr.Points2D(observed[v][o], radii=2.0, colors=OUTLIER_COLOUR))
            rms = float(np.sqrt(np.mean(mag**2))) if mag.size else float("nan")
            self.rec.log(f"rms/view_{calib.grid.name(v)}", rr.Scalars(rms))

    def calibration_result(self, calib: Calibration, obs, report, images: np.ndarray | None = None) -> None:
        """After `lfgraph.calibrate`: rig, board poses, per-view corners, reprojections and residuals."""
        from lfgraph.geometry import invert_T

        self.rig(calib, images)
        if report.board_T_ref is not None:
            ref_T_board = np.stack([invert_T(T) if np.all(np.isfinite(T)) else np.full((4, 4), np.nan)  # noqa: N806
                                    for T in report.board_T_ref])
            self.boards(ref_T_board, obs.board.object_points())
        if report.residuals_px is not None:
            n = calib.num_views
            observed = obs.corners_px.reshape(n, -1, 2)
            projected = (obs.corners_px - report.residuals_px).reshape(n, -1, 2)
            outliers = np.zeros(obs.valid.shape, dtype=bool)
            outliers[:, list(report.outlier_frames)] = obs.valid[:, list(report.outlier_frames)]
            self.observations(calib, observed, projected, obs.valid.reshape(n, -1), outliers.reshape(n, -1))

    def study_rows(self, rows: list[dict]) -> None:
        """Study results as scalars: ``study/<stages>_<robust>/<metric>`` on the ``level`` timeline."""
        for r in rows:
            name = f"{r['stages']}_{r['robust']}".replace(":", "_").replace(",", "_")
            self.rec.set_time("level", sequence=int(r["level"]))
            self.rec.set_time("seed", sequence=int(r["seed"]))
            for metric in ("transfer_px", "rot_err_deg", "rms_after_px"):
                value = float(r[metric])
                if np.isfinite(value):
                    self.rec.log(f"study/{name}/{metric}", rr.Scalars(value))

    def rectified(self, calib: Calibration, images: np.ndarray) -> None:
        h, w = images.shape[1:3]
        ys = np.arange(GUIDE_SPACING_PX, h, GUIDE_SPACING_PX, dtype=np.float32)
        lines = [np.array([[0, y], [w - 1, y]], dtype=np.float32) for y in ys]
        for v in range(calib.num_views):
            base = f"rectified/{calib.grid.name(v)}"
            self.rec.log(f"{base}/image", rr.Image(images[v]), static=True)
            self.rec.log(f"{base}/guides", rr.LineStrips2D(lines, colors=(0, 255, 255), radii=0.5), static=True)

    def close(self, success: bool = True) -> None:
        """Flush and finish; a file recording appears only now, and only when ``success``."""
        self.rec.flush(timeout_sec=60.0)
        self.rec.disconnect()
        if self._tmp is not None:
            if success:
                os.replace(self._tmp, self._final)
            else:
                self._tmp.unlink(missing_ok=True)
