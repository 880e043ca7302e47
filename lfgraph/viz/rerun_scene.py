"""What `lfgraph.viz.RerunLogger` draws: the rigs and boards in 3-D, every view's image, points and residuals in
2-D (each view a camera of the 3-D scene), the results of a calibration and a refinement, study rows and rectified
images (the `SceneLog` mix-in; the logger itself, its sinks and the observer calls are in `lfgraph.viz.rerun_log`).

A view's `Pinhole` is its K alone; rerun knows no lens model. A radtan view is shown as captured (its small
distortion is ignored in 3-D). A wide view (fisheye, unified) is shown undistorted to the pinhole of its own K: its
image, points, residuals and outliers in that pinhole's pixels, so the 3-D scene places them on the right rays; what
lies outside that pinhole's field (a fisheye's periphery) is not shown: points are drawn only inside the image as
shown."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import rerun as rr

from lfgraph.core.calibration import Calibration
from lfgraph.core.camera import Intrinsics, pinhole_to_view_px, view_to_pinhole_px
from lfgraph.viz.blueprint import (
    CHANGE_ARROW_BASELINE_SHARE,
    CHANGE_COLOUR,
    GUIDE_COLOUR,
    GUIDE_SPACING_PX,
    JPEG_QUALITY,
    OBSERVED_COLOUR,
    OUTLIER_COLOUR,
    POINT_RADIUS_UI,
    REPROJECTED_COLOUR,
    RESIDUAL_ARROW_SCALE,
    RESIDUAL_COLOUR_MAX_PX,
    RIG_COLOURS,
    colour_by,
    nice_factor,
    rms_of,
)
from lfgraph.viz.framing import frustum_depth_m, rig_frame, smallest_baseline_m, spaced_labels
from lfgraph.viz.sources import frames_from_sources

CAMERA_RIGS = ("input_rig", "calibrated_rig", "refined_rig")  # rigs whose poses place the 2-D views in 3-D
FRAMES_AHEAD = 2  # a calibration's frames are read and encoded this many ahead of the one being logged
# a calibration's images: a capture (its ``load_frame``), a loader ``f -> (V, H, W)`` or a sequence of frames
FrameSource = Callable[[int], np.ndarray] | Sequence[np.ndarray] | object


def jpeg_image(image: np.ndarray) -> rr.EncodedImage | rr.Image:
    """A grayscale (H, W) or OpenCV BGR (H, W, 3) image as JPEG at `JPEG_QUALITY`."""
    colour = "BGR" if image.ndim == 3 and image.shape[2] == 3 else None
    return rr.Image(image, color_model=colour).compress(jpeg_quality=JPEG_QUALITY)


def frame_images(frames: Callable[[int], np.ndarray] | Sequence[np.ndarray] | None, f: int) -> np.ndarray | None:
    """Frame ``f``'s images from ``frames`` (a loader ``f -> (V, H, W)`` or a sequence); None without frames."""
    if frames is None:
        return None
    return frames(f) if callable(frames) else frames[f]


class SceneLog:
    """The drawing methods of `lfgraph.viz.RerunLogger` (a mix-in: it uses the logger's recording ``rec``, its
    frame, its outlier and track book-keeping and its optimiser summary)."""

    # ------------------------------------------------------------------------------------------- 3-D
    def rig(self, calib: Calibration, images: np.ndarray | None = None, name: str = "rig") -> None:
        """Every view's pose and intrinsics under ``world/<name>`` (static), in that rig's colour; ``images`` (frame
        0, optional) go to the 2-D views on the ``frame`` timeline."""
        colour = RIG_COLOURS.get(name.removesuffix("_rig"), RIG_COLOURS["rig"])
        base = f"world/{name}"
        self.grid = self.grid or calib.grid
        depth_m = frustum_depth_m(calib)
        for v in range(calib.num_views):
            self._camera(f"{base}/{calib.grid.name(v)}", calib, v, depth_m, colour)
        self.rec.log(f"{base}/centres", rr.Points3D(calib.ref_T_view[:, :3, 3], colors=colour,
                                                    radii=0.05 * smallest_baseline_m(calib),
                                                    labels=[f"{name}: {calib.grid.name(v)}"
                                                            for v in range(calib.num_views)],
                                                    show_labels=False), static=True)
        if name in CAMERA_RIGS:
            self._view_cameras(calib, depth_m)
        if images is not None:
            self.rec.set_time("frame", sequence=0)
            self._log_images(images)
        if self._eye_calib is None:
            # rerun's own eye frames everything (landmarks metres away, a rig a few pixels wide): look at the rig
            if self._kind is not None:
                self._send_layout(self._kind, calib)
            else:
                self._eye_calib = calib

    def _view_cameras(self, calib: Calibration, depth_m: float) -> None:
        """Each 2-D view (``views/rRR_cCC``: its images, tracks and residuals) made a camera of the 3-D scene at the
        rig's pose: the images show inside the frustums, and a point picked in one view is the same entity in the
        other (static; a later rig — refine's result — replaces an earlier one)."""
        for v in range(calib.num_views):
            self._camera(f"views/{calib.grid.name(v)}", calib, v, depth_m)
        self._shown_lenses = tuple(calib.intrinsics)
        self._shown_sizes = tuple(calib.image_sizes)

    def _shown_px(self, v: int, px: np.ndarray, intr: Intrinsics | None = None) -> np.ndarray:
        """(N, 2) pixels of view ``v`` where its 2-D view shows them (module docstring: a wide view's pinhole)."""
        intr = intr or (self._shown_lenses[v] if v < len(self._shown_lenses) else None)
        if intr is None or not intr.model.wide or len(px) == 0:
            return px
        return view_to_pinhole_px(px, intr.K, np.eye(3), intr)

    def _inside(self, v: int, *pixels: np.ndarray) -> np.ndarray:
        """(N,) which of the (N, 2) shown pixels (`_shown_px`; several arrays: all of them) lie inside view ``v``'s
        image as shown (a fisheye's periphery maps far outside its pinhole image)."""
        ok = np.ones(len(pixels[0]), dtype=bool)
        size = self._shown_sizes[v] if v < len(self._shown_sizes) else None
        for px in pixels:
            ok &= np.all(np.isfinite(px), axis=1)
            if size is not None:
                with np.errstate(invalid="ignore"):
                    ok &= (px[:, 0] >= -0.5) & (px[:, 0] <= size[0] - 0.5) & (px[:, 1] >= -0.5) & \
                        (px[:, 1] <= size[1] - 0.5)
        return ok

    def _shown_outliers(self, v: int, px: np.ndarray, intr: Intrinsics | None = None) -> np.ndarray:
        """View ``v``'s outlying observations where its 2-D view shows them, those inside its image."""
        shown = self._shown_px(v, px, intr)
        return shown[self._inside(v, shown)]

    def _clear_points(self, n_views: int) -> None:
        """Every view's points, arrows and outliers emptied at the current time."""
        empty = np.zeros((0, 2))
        for v in range(n_views):
            base = f"views/{self.grid.name(v)}"
            for part in ("observed", "reprojected", "outliers"):
                self.rec.log(f"{base}/{part}", rr.Points2D(empty))
            self.rec.log(f"{base}/residuals", rr.Arrows2D(origins=empty, vectors=empty))

    def _shown_image(self, v: int, image: np.ndarray) -> np.ndarray:
        """View ``v``'s image as its 2-D view shows it: a wide view's resampled into the pinhole of its K."""
        if v >= len(self._shown_lenses) or not self._shown_lenses[v].model.wide:
            return image
        intr, (h, w) = self._shown_lenses[v], image.shape[:2]
        cache = self._pinhole_maps
        if (v, intr, w, h) not in cache:
            u, r = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
            src = pinhole_to_view_px(np.column_stack([u.ravel(), r.ravel()]), intr.K, np.eye(3), intr)
            src = np.nan_to_num(src, nan=-1.0).reshape(h, w, 2).astype(np.float32)
            cache[(v, intr, w, h)] = cv2.convertMaps(src, None, cv2.CV_16SC2)
        m1, m2 = cache[(v, intr, w, h)]
        return cv2.remap(image, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def _camera(self, path: str, calib: Calibration, v: int, depth_m: float,
                colour: Sequence[int] | None = None) -> None:
        """View ``v`` of ``calib`` at ``path``: its pose and pinhole (a frustum ``depth_m`` deep), static."""
        pose = calib.ref_T_view[v]
        self.rec.log(path, rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]), static=True)
        self.rec.log(path, rr.Pinhole(image_from_camera=calib.intrinsics[v].K, resolution=list(calib.image_size(v)),
                                      image_plane_distance=depth_m, color=colour), static=True)

    def rig_change(self, before: Calibration, after: Calibration, report=None) -> None:
        """Arrows from each view's input centre to its refined centre, exaggerated by a round factor so that the
        longest is about `CHANGE_ARROW_BASELINE_SHARE` of the smallest baseline, each labelled with the change of
        rotation (deg), position (mm) and focal length (px, where it changed), the reference view's with the factor
        (``world/change``: the labels show on hover). ``world/change/labels`` shows what fits side by side in the
        default eye's picture (`spaced_labels`): a caption with the factor above the rig, then the labels of the
        changed views (with ``report``: the views not judged OK), largest change first."""
        from lfgraph.core.geometry import rotation_angle_deg

        rot_deg = np.array([rotation_angle_deg(a[:3, :3] @ b[:3, :3].T)
                            for a, b in zip(after.ref_T_view, before.ref_T_view, strict=True)])
        pos_mm = 1e3 * np.linalg.norm(after.ref_T_view[:, :3, 3] - before.ref_T_view[:, :3, 3], axis=1)
        focal_px = np.array([np.hypot(a.fx - b.fx, a.fy - b.fy)
                             for a, b in zip(after.intrinsics, before.intrinsics, strict=True)])
        start = before.ref_T_view[:, :3, 3]
        move = after.ref_T_view[:, :3, 3] - start
        longest_m = float(np.max(np.linalg.norm(move, axis=1)))
        scale = nice_factor(CHANGE_ARROW_BASELINE_SHARE * smallest_baseline_m(before) / longest_m) \
            if longest_m > 0 else 1.0
        # one short label per view: the focal change only where there is one, the arrows' exaggeration once, on the
        # reference view (which does not move)
        ref = after.grid.reference
        focal = [f" f {focal_px[v]:.2f} px" if focal_px[v] >= 0.005 else "" for v in range(after.num_views)]
        labels = [f"{after.grid.name(v)} {rot_deg[v]:.2f}° {pos_mm[v]:.1f} mm{focal[v]}"
                  if v != ref else f"{after.grid.name(v)}: reference (arrows x{scale:g})"
                  for v in range(after.num_views)]
        radius = 0.02 * smallest_baseline_m(before)
        self.rec.log("world/change", rr.Arrows3D(origins=start, vectors=move * scale, colors=CHANGE_COLOUR,
                                                 labels=labels, radii=radius, show_labels=False), static=True)
        verdicts = {vd.view: vd.verdict for vd in getattr(report, "verdicts", ())}
        changed = [v for v in range(after.num_views) if v != ref and verdicts.get(v) != "OK"
                   and (rot_deg[v] > 0 or pos_mm[v] > 0)]
        # the caption (the arrows' factor) centred above the rig, then the changed views, largest change first
        frame = rig_frame(self._eye_calib or before)
        anchors = np.vstack([frame.caption_anchor(), start + 0.45 * move * scale])  # rerun: 0.45 along an arrow
        texts = [f"change arrows x{scale:g} (reference {after.grid.name(ref)})", *labels]
        order = [0, *(1 + v for v in sorted(changed, key=lambda v: (-rot_deg[v], -pos_mm[v])))]
        shown = spaced_labels(frame, anchors, texts, order)
        radii = [0.0 if i == 0 else radius for i in shown]  # the caption's anchor is no point of the scene
        self.rec.log("world/change/labels", rr.Points3D(anchors[shown], labels=[texts[i] for i in shown],
                                                        colors=CHANGE_COLOUR, radii=radii, show_labels=True),
                     static=True)

    def boards(self, ref_T_board: np.ndarray, object_points_m: np.ndarray) -> None:  # noqa: N803
        """Each frame's board pose ``ref_T_board`` (F, 4, 4) and its corners ``object_points_m`` (C, 3, metres) under
        ``world/boards`` (static); frames with a non-finite pose are skipped."""
        for f, pose in enumerate(ref_T_board):
            if not np.all(np.isfinite(pose)):
                continue
            path = f"world/boards/frame_{f:03d}"
            self.rec.log(path, rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]), static=True)
            self.rec.log(f"{path}/corners", rr.Points3D(object_points_m, radii=0.0008), static=True)

    def landmarks(self, points_ref: np.ndarray, mean_error_px: np.ndarray) -> None:
        """The (N, 3) landmarks ``points_ref`` (reference frame) as ``world/landmarks``, coloured by their (N,) mean
        reprojection error (px); non-finite points are left out."""
        ok = np.all(np.isfinite(points_ref), axis=1)
        self.rec.log("world/landmarks", rr.Points3D(points_ref[ok], colors=colour_by(mean_error_px[ok],
                                                                                       RESIDUAL_COLOUR_MAX_PX),
                                                    radii=0.01))

    # ------------------------------------------------------------------------------------------- 2-D
    def observations(self, calib: Calibration, observed: np.ndarray, projected: np.ndarray, valid: np.ndarray,
                     outliers: np.ndarray | list[np.ndarray] | None = None) -> None:
        """Per view, at the current ``frame`` time: observed and reprojected points, residual arrows, outliers
        and the view's RMS. Arrays (V, N, 2) / (V, N); ``outliers`` per view (K, 2) pixels. Empty entities are
        logged too, so that nothing of an earlier frame lingers."""
        for v in range(calib.num_views):
            name = calib.grid.name(v)
            base = f"views/{name}"
            m = valid[v] & np.all(np.isfinite(observed[v]), axis=-1) & np.all(np.isfinite(projected[v]), axis=-1)
            intr = calib.intrinsics[v]
            obs, proj = self._shown_px(v, observed[v][m], intr), self._shown_px(v, projected[v][m], intr)
            inside = self._inside(v, obs, proj)
            obs, proj = obs[inside], proj[inside]
            res = obs - proj
            mag = np.linalg.norm(res, axis=1)
            self.rec.log(f"{base}/observed", rr.Points2D(obs, radii=-POINT_RADIUS_UI, colors=OBSERVED_COLOUR))
            self.rec.log(f"{base}/reprojected", rr.Points2D(proj, radii=-0.6 * POINT_RADIUS_UI,
                                                            colors=REPROJECTED_COLOUR))
            self.rec.log(f"{base}/residuals", rr.Arrows2D(origins=proj, vectors=res * RESIDUAL_ARROW_SCALE,
                                                          colors=colour_by(mag, RESIDUAL_COLOUR_MAX_PX)))
            out = np.zeros((0, 2)) if outliers is None else self._shown_outliers(v, outliers[v], intr)
            self.rec.log(f"{base}/outliers", rr.Points2D(out, radii=-1.5 * POINT_RADIUS_UI, colors=OUTLIER_COLOUR))
            if mag.size:
                self.rec.log(f"rms/{name}", rr.Scalars(rms_of(mag)))

    def calibration_result(self, calib: Calibration, obs, report,
                           frames: Callable[[int], np.ndarray] | Sequence[np.ndarray] | None = None) -> None:
        """After `lfgraph.calibrate`: the calibrated rig and board poses, and on the ``frame`` timeline each frame's
        images (``frames``: a loader ``f -> (V, H, W)`` such as ``capture.load_frame``, or a sequence), corners,
        reprojections, residuals and (outlier frames) the corners in red; the optimiser summary.

        Args:
            calib: the calibration; obs: its `lfgraph.detect.detections.Observations`; report: its `CalibrationReport`.
            frames: per-frame images; by default the files ``obs`` was detected in (`frames_from_sources`), and
                without those the 2-D views show the points only.
        """
        from lfgraph.core.geometry import invert_T

        self.grid = self.grid or calib.grid
        self._adopt_kind("calibrate")
        self.rig(calib, name="calibrated_rig")
        if frames is None:
            frames = frames_from_sources(obs)
        if report.board_T_ref is not None:
            ref_T_board = np.stack([invert_T(T) if np.all(np.isfinite(T)) else np.full((4, 4), np.nan)  # noqa: N806
                                    for T in report.board_T_ref])
            self.boards(ref_T_board, obs.board.object_points())
        outlier_frames = set(report.outlier_frames)
        for f, encoded in self._encoded_frames(frames, obs.corners_px.shape[1]):
            self.rec.set_time("frame", sequence=f)
            if encoded is not None:
                self._log_encoded(encoded)
            if report.residuals_px is None:
                continue
            observed = obs.corners_px[:, f]
            projected = observed - report.residuals_px[:, f]
            valid = obs.valid[:, f]
            outliers = [observed[v][valid[v]] if f in outlier_frames else np.zeros((0, 2))
                        for v in range(calib.num_views)]
            self.observations(calib, observed, projected, valid, outliers)
        self.optimiser_summary()

    def _encoded_frames(self, frames, n: int) -> Iterator[tuple[int, list | None]]:
        """(f, frame f's images as their 2-D views show them, JPEG-encoded) for f < n (None without ``frames``).
        Frames are read on one thread, in order (a video reader is not thread-safe), and encoded on another, up to
        `FRAMES_AHEAD` ahead of the frame being logged: reading (PNG decoding) and encoding run side by side, as
        OpenCV and the JPEG encoder release the GIL."""
        if frames is None:
            yield from ((f, None) for f in range(n))
            return

        def encode(load) -> list | None:
            images = load.result()
            if images is None:  # a frame the source could not read (`frames_from_sources`)
                return None
            return [jpeg_image(self._shown_image(v, images[v])) for v in range(len(images))]

        with ThreadPoolExecutor(1) as reader, ThreadPoolExecutor(1) as encoder:
            pending: deque = deque()
            for f in range(n):
                while len(pending) + f < min(n, f + FRAMES_AHEAD + 1):
                    pending.append(encoder.submit(encode, reader.submit(frame_images, frames, len(pending) + f)))
                yield f, pending.popleft().result()

    def refinement_result(self, before: Calibration, after: Calibration, report=None) -> None:
        """After `lfgraph.refine`: the input and the refined rig side by side, the change per view, the optimiser
        summary. ``after`` is `refine`'s return value (the input itself when the refinement was not accepted);
        ``report`` its report (its verdicts choose which views' changes are labelled)."""
        self.grid = self.grid or before.grid
        self._adopt_kind("refine")
        self.rig(before, name="input_rig")
        self.rig(after, name="refined_rig")
        self.rig_change(before, after, report)
        self.optimiser_summary()
        if report is not None and not getattr(report, "accepted", True):
            self.rec.log("log", rr.TextLog("refinement not accepted: the refined rig is the input", level="WARN"))

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
        """Rectified views (static) with horizontal guide lines every `GUIDE_SPACING_PX`."""
        h, w = images.shape[1:3]
        ys = np.arange(GUIDE_SPACING_PX, h, GUIDE_SPACING_PX, dtype=np.float32)
        lines = [np.array([[0, y], [w - 1, y]], dtype=np.float32) for y in ys]
        for v in range(calib.num_views):
            base = f"rectified/{calib.grid.name(v)}"
            self.rec.log(f"{base}/image", jpeg_image(images[v]), static=True)
            self.rec.log(f"{base}/guides", rr.LineStrips2D(lines, colors=GUIDE_COLOUR, radii=0.5), static=True)
