"""Rerun logging for visual debugging. The only module that imports rerun; the core offers hooks, this subscribes.

Coordinates: ``world`` is declared `rr.ViewCoordinates.RDF` (the OpenCV camera convention: x right, y down,
z forward = depth), so the rig stands upright in the 3-D view with depth pointing into the scene.

Layout: the recording carries the default blueprint (`default_blueprint`) of what it records — the ``kind`` given,
else the first run it hears (``run_start``) or result it logs — with the 3-D eye on the first rig it logs. A file
recording gets it once, when it is closed; a live one at once and again, made active, when the run's kind or rig
becomes known.

Entity tree:

- ``world/input_rig/rRR_cCC`` and ``world/refined_rig/rRR_cCC`` (refine), ``world/calibrated_rig/rRR_cCC``
  (calibrate), ``world/rig/rRR_cCC`` (rectify): `Transform3D` (the view's pose in the reference frame) + `Pinhole`
  (K, image size), each rig in its own colour (`RIG_COLOURS`); ``world/<rig>/centres`` labels the view centres;
- ``world/change``: per view an arrow from the input to the refined centre, drawn longer than
  the change (a round factor), each labelled with the rotation (deg) and translation (mm) change (shown on hover);
  ``world/change/labels`` shows what fits side by side in the default eye's picture: a caption with the factor
  above the rig, then the labels of the changed views, largest change first;
- ``world/boards/frame_FFF``: each board pose (`Transform3D`) with its corners (`Points3D`, board frame);
- ``world/landmarks``: refinement landmarks (`Points3D`, coloured by mean reprojection error), on the ``frame``
  timeline;
- ``views/rRR_cCC``: 2-D space of a view, on the ``frame`` timeline: ``image`` (that frame's image, JPEG),
  ``observed`` and ``reprojected`` (`Points2D`), ``residuals`` (`Arrows2D` scaled by `RESIDUAL_ARROW_SCALE`,
  coloured by magnitude) and ``outliers`` (`Points2D`, red) of that frame only, and only what lies inside the image
  as shown (entities are re-logged, empty where there is nothing, on every frame — a refinement empties them with
  the frame's images — so that nothing of an earlier frame lingers);
- ``rms/rRR_cCC``: `Scalars`, the view's RMS reprojection error (px) per frame on the ``frame`` timeline;
- ``optimizer/error`` and ``optimizer/rms_px``: `Scalars` on the ``iteration`` timeline while the optimiser runs
  (live), and at the end ``optimizer_summary/error_decades/<stage>`` (decades the error fell since its stage began)
  and ``optimizer_summary/rms_px/<stage>`` as `BarChart` per iteration, one per stage name (time-independent, so they
  show whichever timeline is selected);
  ``optimizer/stages`` (`TextLog`); ``log`` (`TextLog`): the progress lines;
- ``rectified/rRR_cCC``: rectified views (``image``) with horizontal guide lines (``guides``) every
  `GUIDE_SPACING_PX`;
- ``study/<stages>_<robust>/<metric>``: study results on the ``level`` timeline.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
import rerun as rr

from lfgraph.core.calibration import Calibration
from lfgraph.core.files import check_replaceable, record_created
from lfgraph.core.grid import ViewGrid
from lfgraph.core.observer import WARNING_PREFIX, BaseObserver, StageEnd
from lfgraph.viz.blueprint import (
    APP_ID,
    ERROR_COLOUR,
    KINDS,
    OUTLIER_COLOUR,
    POINT_RADIUS_UI,
    RMS_COLOUR,
    check_save_path,
    default_blueprint,
)
from lfgraph.viz.optimiser_log import OptimiserLog
from lfgraph.viz.rerun_scene import FrameSource, SceneLog, jpeg_image


def _check_kind(kind: str | None) -> None:
    if kind is not None and kind not in KINDS:
        raise ValueError(f"unknown blueprint kind {kind!r}; one of {', '.join(KINDS)}")


def _first_layout(grid: ViewGrid | None, kind: str | None, calib: Calibration | None = None):
    """The default blueprint of ``kind`` (a study's without a grid), or None while the kind is not known."""
    if kind is None or (grid is None and kind != "study"):
        return None
    return default_blueprint(grid, kind, calib)


def _loader(frames: FrameSource | None) -> Callable[[int], np.ndarray] | Sequence[np.ndarray] | None:
    """A capture's ``load_frame``, or ``frames`` itself (a loader or a sequence)."""
    load = getattr(frames, "load_frame", None)
    return load if callable(load) else frames


class StdoutClosed(OSError):
    """A `RerunLogger.stdout` recording lost its reader."""


class _StdoutPump:
    """File descriptor 1 replaced by a pipe whose contents a thread copies to the real standard output; after a
    broken pipe the thread keeps reading and discards, so the writer of fd 1 never blocks or fails."""

    def __init__(self) -> None:
        import threading

        sys.stdout.flush()
        self._real = os.dup(1)
        self._read, write = os.pipe()
        os.dup2(write, 1)
        os.close(write)
        self.broken = False
        self._thread = threading.Thread(target=self._copy, name="lfgraph-stdout", daemon=True)
        self._thread.start()

    def _copy(self) -> None:
        while True:
            chunk = os.read(self._read, 1 << 16)
            if not chunk:
                return
            view = memoryview(chunk)
            while view and not self.broken:
                try:
                    view = view[os.write(self._real, view):]
                except OSError:  # EPIPE: the reader went away; drain from now on
                    self.broken = True

    def finish(self) -> bool:
        """Restore fd 1, let the copy drain; True when the reader went away."""
        sys.stdout.flush()
        os.dup2(self._real, 1)  # closes our pipe's write end on fd 1: the copier sees the end
        self._thread.join(timeout=60.0)
        os.close(self._read)
        os.close(self._real)
        return self.broken


class RerunLogger(SceneLog, OptimiserLog, BaseObserver):
    """Logs lfgraph's data to one explicit `rr.RecordingStream` (never the global one); an `lfgraph.Observer`.

    Make one with `to_file` (written atomically when closed), `from_stream` (your own stream), `serve`, `connect`
    or `stdout`; use it as a context manager (closed at the end; a failure discards a file recording) and pass it
    as ``observer=`` to `lfgraph.calibrate` / `lfgraph.refine`: the run logs its own result (the rigs, the change,
    every frame's points, the optimiser summary) and the recording opens in that command's layout, the 3-D view
    on the rig. `calibration_result` and `refinement_result` are for results you did not run with the logger.

    A calibration's images come from ``frames`` (a capture, a loader ``f -> (V, H, W)`` or a sequence), else from
    the files the observations were detected in (`lfgraph.detect_capture` records them); a refinement's from the
    frames it is given.
    """

    def __init__(self, rec: rr.RecordingStream, grid: ViewGrid | None = None, final_path: Path | None = None,
                 tmp_path: Path | None = None, kind: str | None = None, frames: FrameSource | None = None,
                 live: bool = True) -> None:
        _check_kind(kind)
        self.rec = rec
        self.grid = grid
        self._kind = kind  # the default blueprint's kind (None: the first run or result logged decides)
        self._run_kind: str | None = None  # the command running (`run_start`)
        self._live = live  # a viewer may watch: layouts are sent as they become known (else once, at `close`)
        self._eye_calib: Calibration | None = None  # the rig the 3-D eye frames (the first one logged)
        # where a calibration's images come from (``f -> (V, H, W)``); None: the observations' files
        self.frames_source = _loader(frames)
        self._final, self._tmp = final_path, tmp_path
        self._reset_optimiser()
        self._frame = 0  # the frame refinement is on
        self._track_frame: dict[bytes, int] = {}  # refinement track (its pixel bytes) -> the frame it came from
        self._outliers: dict[int, list[np.ndarray]] = {}  # frame -> (V, K, 2) outlying observations, NaN elsewhere
        self._last: StageEnd | None = None
        self._shown_lenses: tuple = ()  # each view's lens, from the rig placing the 2-D views (`SceneLog._shown_px`)
        self._shown_sizes: tuple = ()  # ... and its image size (points outside it are not drawn)
        self._pinhole_maps: dict = {}  # (view, lens, w, h) -> remap tables of a wide view's pinhole image
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
        self.rec.log("optimizer/error", rr.SeriesLines(names="graph error", colors=ERROR_COLOUR), static=True)
        self.rec.log("optimizer/rms_px", rr.SeriesLines(names="RMS (px)", colors=RMS_COLOUR), static=True)

    @classmethod
    def to_file(cls, path: str | os.PathLike, grid: ViewGrid | None = None, kind: str | None = None,
                frames: FrameSource | None = None) -> RerunLogger:
        """Record to ``path`` (.rrd): written next to it and renamed on a successful `close`, so a failed run leaves
        no half-written file. ``kind`` chooses the default blueprint (`default_blueprint`; None: the kind of the
        first run the logger hears, or of the first result logged); ``frames`` a calibration's images (a capture
        such as `lfgraph.open_capture`'s, a loader ``f -> (V, H, W)`` or a sequence; by default the files the
        observations were detected in).

        Raises:
            ValueError: the path is a folder, its folder does not exist or is not writable.
        """
        final = Path(path)
        check_save_path(final)
        _check_kind(kind)
        tmp = final.with_name(f".{final.name}.{os.getpid()}.tmp")
        rec = rr.RecordingStream(APP_ID)
        rec.save(str(tmp))  # the layout is added once what is recorded is known (`close`)
        return cls(rec, grid, final, tmp, kind=kind, frames=frames, live=False)

    @classmethod
    def from_stream(cls, rec: rr.RecordingStream, grid: ViewGrid | None = None, kind: str | None = None,
                    frames: FrameSource | None = None) -> RerunLogger:
        """Log to a stream you opened (and whose sink you chose); ``grid`` and ``kind`` send the default blueprint
        at once (else once a run starts)."""
        if grid is not None and kind is not None:
            rec.send_blueprint(default_blueprint(grid, kind), make_active=False, make_default=True)
        return cls(rec, grid, kind=kind, frames=frames)

    @classmethod
    def serve(cls, grid: ViewGrid | None = None, kind: str | None = None,
              frames: FrameSource | None = None) -> RerunLogger:
        """Host a gRPC server and web viewer for the recording."""
        rec = rr.RecordingStream(APP_ID)
        rec.serve_grpc(default_blueprint=_first_layout(grid, kind))
        return cls(rec, grid, kind=kind, frames=frames)

    @classmethod
    def connect(cls, url: str | None = None, grid: ViewGrid | None = None, kind: str | None = None,
                frames: FrameSource | None = None) -> RerunLogger:
        """Stream to a running viewer (rerun's default address unless ``url``)."""
        rec = rr.RecordingStream(APP_ID)
        rec.connect_grpc(url, default_blueprint=_first_layout(grid, kind))
        return cls(rec, grid, kind=kind, frames=frames)

    @classmethod
    def stdout(cls, grid: ViewGrid | None = None, kind: str | None = None,
               frames: FrameSource | None = None) -> RerunLogger:
        """Write the recording to standard output (pipe it into ``rerun -``); print nothing else there.

        rerun writes into a pipe of ours that a thread copies to the real standard output: when the reader goes away
        (``| head``) the copy stops and the rest is discarded, so rerun's writer never meets the broken pipe (which
        killed it and left every later log call blocked on it); `close` then raises `StdoutClosed`."""
        pump = _StdoutPump()
        rec = rr.RecordingStream(APP_ID)
        rec.stdout(default_blueprint=_first_layout(grid, kind))
        logger = cls(rec, grid, kind=kind, frames=frames)
        logger._pump = pump
        return logger

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
        """Into the recording and, as `lfgraph.BaseObserver` does, through `logging` (the console stays informed)."""
        warning = message.startswith(WARNING_PREFIX)
        self.rec.log("log", rr.TextLog(message, level="WARN" if warning else "INFO"))
        super().log(message)

    def run_start(self, kind: str, calib: Calibration | None) -> None:
        """A run starts: its layout (`default_blueprint` of ``kind``, the 3-D eye on ``calib`` when given) becomes
        the recording's, and for ``refine`` the input rig is shown."""
        self._run_kind = kind
        grid = self.grid or (None if calib is None else calib.grid)
        if kind in KINDS and grid is not None:
            self.grid = grid
            if kind != self._kind or (calib is not None and self._eye_calib is None):
                self._send_layout(kind, calib if self._eye_calib is None else self._eye_calib)
        if kind == "refine" and calib is not None:
            self.rig(calib, name="input_rig")

    def _send_layout(self, kind: str, calib: Calibration | None) -> None:
        """``kind``'s `default_blueprint`, its 3-D eye on ``calib``'s rig when given, becomes the recording's layout:
        sent now, and made active, to a live viewer (at most twice a run: when the kind and when the rig becomes
        known); a file gets the last one when it is closed."""
        self._kind = kind
        if calib is not None:
            self._eye_calib = calib
        if self._live and self.grid is not None:
            self.rec.send_blueprint(default_blueprint(self.grid, kind, self._eye_calib), make_active=True,
                                    make_default=True)

    def _adopt_kind(self, kind: str) -> None:
        """A result of ``kind`` is logged: the layout is that command's unless a kind was chosen."""
        if self._kind is None and self.grid is not None:
            self._send_layout(kind, self._eye_calib)

    def run_end(self, kind: str, before: Calibration | None, after: Calibration, report: Any,
                data: Any = None) -> None:
        """A run ended: for ``refine`` the refined rig, the change per view and the optimiser summaries
        (`refinement_result`); for ``calibrate`` the calibrated rig, the boards and every frame's corners
        (`calibration_result`, with the images of `frames_source` when set)."""
        if kind == "refine":
            self.refinement_result(before, after, report)
        elif kind == "calibrate" and data is not None:
            self.calibration_result(after, data, report, self.frames_source)

    def iteration(self, iteration: int, error_before: float, error_after: float) -> None:
        """`Observer.iteration`: one step on the ``iteration`` timeline (`on_iteration`)."""
        self.on_iteration(iteration, error_before, error_after)

    def frame(self, index: int, images: np.ndarray) -> None:
        """Refinement starts on frame ``index``: its images go on the ``frame`` timeline, with the views' points
        emptied until its first stage ends (so that the frame's images never show the last frame's tracks)."""
        self._frame = int(index)
        self.rec.set_time("frame", sequence=self._frame)
        self._log_images(images)
        if self._frame > 0 and self.grid is not None:
            self._clear_points(len(images))

    def stage_start(self, name: str, measurements: int) -> None:
        """A stage starts: a line on ``optimizer/stages`` at its first iteration, in the colour of its bars in the
        optimiser charts, and ``measurements`` set for the RMS (`set_measurements`)."""
        colour = self._stage_starts(name)
        self.rec.set_time("iteration", sequence=self.iteration_count + 1)
        self.rec.log("optimizer/stages", rr.TextLog(f"frame {self._frame}: stage {name} starts", level="INFO",
                                                    color=colour))
        self.set_measurements(measurements)

    def stage_end(self, event: StageEnd) -> None:
        """Landmarks, and on every frame so far that frame's tracks with the calibration after this stage (not for
        ``calibrate``, whose landmarks are the boards' corners: `calibration_result` logs them per frame at its end)."""
        from lfgraph.core.camera import project_world

        if self._run_kind == "calibrate":
            return
        calib, points, valid = event.calib, event.points_ref_m, event.valid
        with np.errstate(invalid="ignore"):
            mean_err = np.nanmean(np.where(valid, event.errors_px, np.nan), axis=0)
        self.landmarks(points, mean_err)
        projected = np.stack([project_world(calib.intrinsics[v], calib.view_T_ref(v), points)
                              for v in range(calib.num_views)])
        frames = self._frames_of_tracks(event.pixels_px)
        for g in range(self._frame + 1):
            sel = frames == g
            self.rec.set_time("frame", sequence=g)
            self.observations(calib, event.pixels_px[:, sel], projected[:, sel], valid[:, sel],
                              self._outlier_pixels(g, calib.num_views))
        self.rec.set_time("frame", sequence=self._frame)
        self._last = event

    def outliers(self, name: str, pixels_px: np.ndarray, valid: np.ndarray) -> None:
        """Dropped tracks, in red on the frame they came from (kept for every later stage)."""
        if pixels_px.shape[1] == 0:
            return
        frames = self._frames_of_tracks(pixels_px)
        px = np.where(valid[..., None], pixels_px, np.nan)
        for g in np.unique(frames):
            self._outliers.setdefault(int(g), []).append(px[:, frames == g])
            self.rec.set_time("frame", sequence=int(g))
            for v in range(px.shape[0]):
                shown = self._shown_outliers(v, self._outlier_pixels(int(g), px.shape[0])[v])
                self.rec.log(f"views/{self._name(v)}/outliers",
                             rr.Points2D(shown, radii=-1.5 * POINT_RADIUS_UI, colors=OUTLIER_COLOUR))
        self.rec.set_time("frame", sequence=self._frame)

    # ------------------------------------------------------------------------------------------- helpers
    def _name(self, v: int) -> str:
        if self.grid is None:
            raise ValueError("this logger was made without a grid; pass grid= to name the views")
        return self.grid.name(v)

    def _track_keys(self, pixels_px: np.ndarray) -> list[bytes]:
        cols = np.ascontiguousarray(np.transpose(pixels_px, (1, 0, 2)))
        return [c.tobytes() for c in cols]

    def _frames_of_tracks(self, pixels_px: np.ndarray) -> np.ndarray:
        """(N,) the frame each pooled track came from: a track never seen before belongs to the current frame (the
        pool only grows by the current frame's tracks; a dropped track never returns)."""
        return np.array([self._track_frame.setdefault(k, self._frame) for k in self._track_keys(pixels_px)],
                        dtype=int)

    def _outlier_pixels(self, frame: int, n_views: int) -> list[np.ndarray]:
        """Per view the finite outlying observations of ``frame``."""
        parts = self._outliers.get(frame)
        if not parts:
            return [np.zeros((0, 2)) for _ in range(n_views)]
        px = np.concatenate(parts, axis=1)
        return [px[v][np.all(np.isfinite(px[v]), axis=1)] for v in range(n_views)]

    def _log_images(self, images) -> None:  # (V, H, W), or a list of (H, W) for views of different sizes
        self._log_encoded([jpeg_image(self._shown_image(v, images[v])) for v in range(len(images))])

    def _log_encoded(self, encoded: list) -> None:  # every view's image, JPEG-encoded (`jpeg_image`)
        for v, image in enumerate(encoded):
            self.rec.log(f"views/{self._name(v)}/image", image)

    def close(self, success: bool = True) -> None:
        """Flush and finish; a file recording appears only now, and only when ``success``.

        Raises:
            StdoutClosed: a `stdout` recording whose reader stopped reading (the recording is incomplete)."""
        if not self._live and success:
            layout = _first_layout(self.grid, self._kind, self._eye_calib)
            if layout is not None:  # the file's one layout: what it records, the 3-D eye on its rig
                self.rec.send_blueprint(layout, make_active=True, make_default=True)
        self.rec.flush(timeout_sec=60.0)
        self.rec.disconnect()
        pump = getattr(self, "_pump", None)
        if pump is not None:
            self._pump = None
            if pump.finish() and success:
                raise StdoutClosed("the reader of standard output stopped reading (a closed pipe): the recording is "
                                   "incomplete")
        if self._tmp is not None:
            if success:
                check_replaceable(self._final)
                existed = self._final.exists()
                os.replace(self._tmp, self._final)
                if not existed:
                    record_created(self._final)  # a command failing after this removes it (`run_outputs`)
            else:
                self._tmp.unlink(missing_ok=True)
