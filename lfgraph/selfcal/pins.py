"""Pins of a self-calibration: what fixes the common zoom that scene frames leave to the design focal length.

Scene frames fix everything of a near-parallel array but its common zoom (every focal length x s with every depth:
the same images); the design pitch fixes its scale, not its zoom. A pin is a measurement that sees the zoom, added
to the final stage's graph as factors with its own sigma:

- `BoardPin`: a few frames of a known board (even one, seen by one view or more; tilted: a board facing the array
  squarely sees only the scale, which the pitch already fixes); its corners tie the focal length through the board's
  known geometry and perspective.
- `DistancePin`: two scene points marked in one view of one frame and their distance in metres (at different
  depths: under the zoom their depths scale, their distance with them).
- `ViewPin`: one view's intrinsics from a factory or an earlier calibration, with that calibration's sigmas.

`lfgraph.selfcal.pinned` fits them and refuses one that disagrees with the scene beyond its sigmas.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import gtsam
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.camera import Intrinsics
from lfgraph.core.files import input_problem
from lfgraph.core.grid import ViewGrid
from lfgraph.engine.triangulate import per_coordinate_sigma, triangulate_dlt
from lfgraph.factors import selfcal_graph
from lfgraph.factors.keys import pin_point_key
from lfgraph.factors.values import insert_board_corners, insert_board_poses
from lfgraph.selfcal.marks import (
    MARK_FORWARD_BACKWARD_PX,
    consistent_marks,
    follow_marks,
)
from lfgraph.selfcal.retrack import Patches, cut_patches, retrack

MIN_PIN_CORNERS = 6  # a pin frame seen by a view with fewer corners than this is not used in that view
CORNER_NOISE_FLOOR_PX = 0.01  # a board pin's estimated corner noise is never taken below this
FACING_DEG = 0.5  # a known depth's plane faces the reference view to within this (its marks' depths differ by at most
# this tilt times their distance, 1 sigma): e.g. a wall the array was squared to


class PinError(ValueError):
    """A pin that cannot be used (its file, its frame, its views); the message names the pin and the field."""


@dataclass(frozen=True)
class BoardPin:
    """A few frames of a known board seen by one or more views (its corners tie the focal length).

    Attributes:
        corners_px: (V, F, C, 2) corners in pixels (NaN where not seen); valid: (V, F, C).
        object_points_m: (C, 3) the board's corners in its own frame (metres).
        sigma_px: corner noise per coordinate (None: measured from the corners' own homography residuals).
        name: how the report and a refusal name it.
    """

    corners_px: np.ndarray
    valid: np.ndarray
    object_points_m: np.ndarray
    sigma_px: float | None = None
    name: str = "board"

    def __post_init__(self) -> None:
        corners = np.asarray(self.corners_px, dtype=np.float64)
        valid = np.asarray(self.valid, dtype=bool)
        obj = np.asarray(self.object_points_m, dtype=np.float64)
        if corners.ndim != 4 or corners.shape[3] != 2 or valid.shape != corners.shape[:3]:
            raise PinError(f"pin {self.name}: corners_px must be (views, frames, corners, 2) with valid (views, "
                           f"frames, corners); got {corners.shape} and {valid.shape}")
        if obj.shape != (corners.shape[2], 3):
            raise PinError(f"pin {self.name}: object_points_m must be ({corners.shape[2]}, 3), got {obj.shape}")
        if self.sigma_px is not None and not (np.isfinite(self.sigma_px) and self.sigma_px > 0):
            raise PinError(f"pin {self.name}: sigma_px must be positive, got {self.sigma_px}")
        valid = valid & np.all(np.isfinite(corners), axis=3)
        valid &= (valid.sum(axis=2) >= MIN_PIN_CORNERS)[..., None]
        if not valid.any():
            raise PinError(f"pin {self.name}: no view sees the board with at least {MIN_PIN_CORNERS} corners")
        object.__setattr__(self, "corners_px", np.where(valid[..., None], corners, np.nan))
        object.__setattr__(self, "valid", valid)
        object.__setattr__(self, "object_points_m", obj)

    @classmethod
    def from_observations(cls, obs, sigma_px: float | None = None, name: str | None = None) -> BoardPin:
        """From detections (`lfgraph.detect_capture`'s `BoardObservations`); named after its first file's folder."""
        where = next((Path(s).parent for files in obs.sources for s in files if s != "(missing)"), None)
        return cls(obs.corners_px, obs.valid, obs.board.object_points(), sigma_px,
                   name or (f"board {where}" if where is not None else "board"))

    def corner_sigma_px(self, calib: Calibration) -> float:
        """``sigma_px``, or the corners' noise measured from a homography fitted per view and frame to the corners
        undistorted by ``calib`` (8 parameters: it absorbs any focal length, so the zoom does not enter it)."""
        if self.sigma_px is not None:
            return float(self.sigma_px)
        sq, dof = 0.0, 0
        for v, f in zip(*np.nonzero(self.valid.any(axis=2)), strict=True):
            ok = self.valid[v, f]
            intr = calib.intrinsics[v]
            xy = intr.undistort(self.corners_px[v, f, ok])
            h, _ = cv2.findHomography(self.object_points_m[ok, :2], xy, 0)
            if h is None or not np.all(np.isfinite(xy)):
                continue
            p = np.column_stack([self.object_points_m[ok, :2], np.ones(int(ok.sum()))]) @ h.T
            r = (p[:, :2] / p[:, 2:] - xy) * np.array([intr.fx, intr.fy])
            sq, dof = sq + float(np.sum(r**2)), dof + 2 * int(ok.sum()) - 8
        return max(float(np.sqrt(sq / dof)) if dof > 0 else CORNER_NOISE_FLOOR_PX, CORNER_NOISE_FLOOR_PX)

    def factors(self, calib: Calibration, values: gtsam.Values, track_sigma_px: float,
                first_point: int) -> gtsam.NonlinearFactorGraph:
        """The pin's factors (`selfcal_graph.board_pin_factors`) with its board poses and corners inserted in
        ``values`` (each frame's pose from PnP in the view seeing most of its corners)."""
        frames = np.nonzero(self.valid.any(axis=(0, 2)))[0]
        board_T_ref = np.tile(np.eye(4), (self.valid.shape[1], 1, 1))  # noqa: N806
        for f in frames:
            v = int(np.argmax(self.valid[:, f].sum(axis=1)))
            ok = self.valid[v, f]
            intr = calib.intrinsics[v]
            xy = intr.undistort(self.corners_px[v, f, ok])
            good, rvec, tvec = cv2.solvePnP(self.object_points_m[ok], xy, np.eye(3), None)
            if not good:
                raise PinError(f"pin {self.name}: the board pose of frame {f} cannot be found in view "
                               f"{calib.grid.name(v)}")
            view_T_board = np.eye(4)  # noqa: N806
            view_T_board[:3, :3], view_T_board[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
            board_T_ref[f] = np.linalg.inv(calib.ref_T_view[v] @ view_T_board)
        insert_board_poses(values, board_T_ref, frames)
        insert_board_corners(values, self.object_points_m)
        return selfcal_graph.board_pin_factors(self.corners_px, self.valid, self.object_points_m,
                                               self.corner_sigma_px(calib), [i.lens for i in calib.intrinsics])

    def describe(self) -> str:
        """One line: frames and views."""
        seen = self.valid.any(axis=2)
        return (f"{int(seen.any(axis=0).sum())} board frame(s) of {self.valid.shape[2]} corners seen "
                f"{int(seen.sum())} times")


@dataclass(frozen=True)
class DistancePin:
    """Two scene points and their distance; optionally the known depth of the plane they lie on.

    Either marked in one view of one frame (``view``, ``frame``, ``marked_px``: `calibrate_scene` follows them into
    every view of that frame and re-tracks them as it does every track) or given in every view (``pixels``,
    ``valid``: `calibrate_tracks`).

    Attributes:
        distance_m, sigma_m: the measured distance and its 1-sigma (metres).
        depth_m, depth_sigma_m: optionally, the depth of the plane both points lie on (a wall facing the reference
            view to within `FACING_DEG`: its distance along the reference view's optical axis) and its 1-sigma.
            With it the pin is the angle the distance subtends at that depth, which every pinhole view sees through
            its focal length alone; without it, a distance fixes one combination of the zoom and the hidden
            principal-point gauge (`lfgraph.selfcal.pinned`).
        view, frame, marked_px: the view (index), the frame (index among the frames read) and the (2, 2) pixels.
        pixels: (V, 2, 2) the two points in every view; valid: (V, 2).
        patches: the image patches around them (for the re-tracking; set when followed from the images).
        name: how the report and a refusal name it.
        pixel_sigma_px: the marks' pixel noise per coordinate (None: measured from their own residuals through the
            scene's calibration, `checked`, never below the tracks' noise).
    """

    distance_m: float
    sigma_m: float
    view: int | None = None
    frame: int | None = None
    marked_px: np.ndarray | None = None
    pixels: np.ndarray | None = None
    valid: np.ndarray | None = None
    patches: Patches | None = field(default=None, repr=False)
    name: str = "distance"
    depth_m: float | None = None
    depth_sigma_m: float | None = None
    pixel_sigma_px: float | None = None

    def __post_init__(self) -> None:
        if (self.depth_m is None) != (self.depth_sigma_m is None):
            raise PinError(f"pin {self.name}: a plane's depth needs both depth_m and depth_sigma_m")
        for what in ("distance_m", "sigma_m") + (("depth_m", "depth_sigma_m") if self.depth_m is not None else ()):
            value = getattr(self, what)
            if not (isinstance(value, int | float) and np.isfinite(value) and value > 0):
                raise PinError(f"pin {self.name}: {what} must be a positive number of metres, got {value!r}")
        if self.pixels is None:
            marked = None if self.marked_px is None else np.asarray(self.marked_px, dtype=np.float64)
            if marked is None or marked.shape != (2, 2) or not np.all(np.isfinite(marked)) \
                    or self.view is None or self.frame is None:
                raise PinError(f"pin {self.name}: give the two points as marked_px [[u, v], [u, v]] in one view "
                               f"and frame, or pixels in every view")
            if np.linalg.norm(marked[0] - marked[1]) < 1.0:
                raise PinError(f"pin {self.name}: the two marked points are the same pixel")
            object.__setattr__(self, "marked_px", marked)
            return
        pixels = np.asarray(self.pixels, dtype=np.float64)
        valid = np.ones(pixels.shape[:2], dtype=bool) if self.valid is None else np.asarray(self.valid, dtype=bool)
        if pixels.ndim != 3 or pixels.shape[1:] != (2, 2) or valid.shape != pixels.shape[:2]:
            raise PinError(f"pin {self.name}: pixels must be (views, 2, 2) with valid (views, 2), got "
                           f"{pixels.shape} and {valid.shape}")
        valid = valid & np.all(np.isfinite(pixels), axis=2)
        if np.any(valid.sum(axis=0) < 2):
            raise PinError(f"pin {self.name}: each point must be seen by at least two views "
                           f"(seen by {valid.sum(axis=0).tolist()})")
        object.__setattr__(self, "pixels", pixels)
        object.__setattr__(self, "valid", valid)

    @classmethod
    def load(cls, path: str | Path, grid: ViewGrid) -> DistancePin:
        """A distance file: JSON ``{"view": "r00_c00", "frame": 0, "points_px": [[u, v], [u, v]],
        "distance_m": 1.0, "sigma_m": 0.001}`` (``frame``: its index among the capture's frames, from 0).

        Raises:
            PinError: the file is missing or malformed (names the file and the field).
        """
        p = Path(path)
        problem = input_problem(p)
        if problem:
            raise PinError(f"{p}: {problem}")
        try:
            doc = json.loads(p.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise PinError(f"{p}: not a readable JSON distance file: {exc}") from None
        if not isinstance(doc, dict):
            raise PinError(f"{p}: a distance file holds one JSON object, got {type(doc).__name__}")
        missing = [k for k in ("view", "frame", "points_px", "distance_m", "sigma_m") if k not in doc]
        missing += [k for k in ("depth_m", "depth_sigma_m") if ("depth_m" in doc or "depth_sigma_m" in doc)
                    and k not in doc]
        if missing:
            raise PinError(f"{p}: missing field(s) {', '.join(missing)}")
        view = grid.find(doc["view"], f"{p}: field view", PinError)
        frame = doc["frame"]
        if not isinstance(frame, int) or isinstance(frame, bool) or frame < 0:
            raise PinError(f"{p}: field frame must be a frame index >= 0, got {frame!r}")
        try:
            marked = np.asarray(doc["points_px"], dtype=np.float64)
        except (TypeError, ValueError):
            marked = None
        if marked is None or marked.shape != (2, 2):
            raise PinError(f"{p}: field points_px must be [[u, v], [u, v]], got {doc['points_px']!r}")
        try:
            return cls(doc["distance_m"], doc["sigma_m"], view, frame, marked, name=f"distance {p.name}",
                       depth_m=doc.get("depth_m"), depth_sigma_m=doc.get("depth_sigma_m"))
        except PinError as exc:
            raise PinError(f"{p}: {exc}") from None

    @property
    def needs_images(self) -> bool:
        """Whether the points are still to be followed from the marked view (`followed`)."""
        return self.pixels is None

    def followed(self, images: np.ndarray, grid: ViewGrid) -> DistancePin:
        """The marked points followed into every view of their frame's (V, H, W) ``images`` (`follow_marks`)."""
        pixels, valid = follow_marks(images, grid, int(self.view), self.marked_px)
        if np.any(valid.sum(axis=0) < 2) or not valid[grid.reference].all():
            lost = [k for k in range(2) if valid[:, k].sum() < 2 or not valid[grid.reference, k]]
            raise PinError(f"pin {self.name}: marked point(s) {lost} of frame {self.frame} could not be followed "
                           f"into the reference view and another (seen by {valid.sum(axis=0).tolist()} views); "
                           f"mark points on texture every view sees")
        return replace(self, pixels=pixels, valid=valid,
                       patches=cut_patches(np.asarray(images), pixels, valid, grid.reference))

    def retracked(self, calib: Calibration) -> DistancePin:
        """The points re-tracked from the reference view with ``calib``'s local maps (`lfgraph.selfcal.retrack`), as
        every track is before the final stage (observations it cannot re-track are dropped); unchanged without
        patches."""
        if self.patches is None:
            return self
        points = triangulate_dlt(calib, self.pixels, self.valid)
        pixels, valid, done, _ = retrack(self.pixels, self.valid, self.patches, calib, points)
        ref_view = np.arange(calib.num_views)[:, None] == calib.grid.reference
        # a re-track that moves a mark further than the following's own forward-backward tolerance disagrees with
        # the following (a window across a depth edge): that observation is dropped, not trusted
        moved = np.linalg.norm(np.nan_to_num(pixels - self.pixels), axis=2)
        valid = valid & (done | ref_view) & (moved <= MARK_FORWARD_BACKWARD_PX)
        if np.any(valid.sum(axis=0) < 2):
            return self
        return replace(self, pixels=pixels, valid=valid, patches=None)

    def checked(self, calib: Calibration) -> DistancePin:
        """The marks' observations that ``calib``'s geometry explains, and their measured noise.

        Each mark is triangulated through ``calib`` (the scene's calibration) and its worst observation dropped
        while its reprojection error exceeds `MARK_OUTLIER_FACTOR` times the mark's median and
        `MARK_OUTLIER_FLOOR_PX` (a mark followed along an edge); ``pixel_sigma_px``, unless given, is measured from
        the rest (`per_coordinate_sigma`: a mark's window is not a typical track's, and its noise is the pin's).

        Raises:
            PinError: a mark is left with fewer than two consistent views.
        """
        if self.pixels is None:
            return self
        pixels, valid, points, errors = consistent_marks(calib, self.pixels, self.valid)
        if np.any(valid.sum(axis=0) < 2) or not np.all(np.isfinite(points)):
            raise PinError(f"pin {self.name}: its marks are not seen consistently by two views (consistent views "
                           f"{valid.sum(axis=0).tolist()}); mark points on texture every view sees")
        sigma = self.pixel_sigma_px
        if sigma is None:
            sigma = per_coordinate_sigma(np.where(valid, errors, np.nan), 2, 0)
        return replace(self, pixels=np.where(valid[..., None], pixels, np.nan), valid=valid,
                       pixel_sigma_px=float(sigma) if np.isfinite(sigma) else None)

    def factors(self, calib: Calibration, values: gtsam.Values, track_sigma_px: float,
                first_point: int) -> gtsam.NonlinearFactorGraph:
        """The pin's factors (`selfcal_graph.distance_pin_factors`, at the marks' noise, never below the tracks')
        with its two points inserted in ``values`` (triangulated through ``calib``)."""
        if self.pixels is None:
            raise PinError(f"pin {self.name}: its marked points were not followed into the views (frame "
                           f"{self.frame} was not read)")
        points = triangulate_dlt(calib, self.pixels, self.valid)
        if not np.all(np.isfinite(points)) or np.any(points[:, 2] <= 0):
            raise PinError(f"pin {self.name}: its points do not triangulate in front of the views")
        for k in range(2):
            values.insert(pin_point_key(first_point + k), points[k])
        sigma_px = max(track_sigma_px, self.pixel_sigma_px or 0.0)
        graph = selfcal_graph.distance_pin_factors(first_point, self.pixels, self.valid, self.distance_m, self.sigma_m,
                                                   sigma_px, [i.lens for i in calib.intrinsics])
        if self.depth_m is not None:
            graph.push_back(selfcal_graph.plane_depth_factors(first_point, self.depth_m, self.depth_sigma_m,
                                                              np.tan(np.radians(FACING_DEG)) * self.distance_m))
        return graph

    def fitted_distance_m(self, values: gtsam.Values, first_point: int) -> tuple[float, float]:
        """The two points' distance and the first one's depth in ``values``."""
        a, b = (np.asarray(values.atPoint3(pin_point_key(first_point + k))) for k in range(2))
        return float(np.linalg.norm(a - b)), float(a[2])

    def describe(self) -> str:
        """One line: the distance and its sigma."""
        where = "" if self.frame is None else f" (frame {self.frame})"
        plane = "" if self.depth_m is None else \
            f" on a plane {self.depth_m:g} m +- {1e3 * self.depth_sigma_m:g} mm deep"
        return f"{self.distance_m:g} m +- {1e3 * self.sigma_m:g} mm between two scene points{plane}{where}"


@dataclass(frozen=True)
class ViewPin:
    """One view's intrinsics known from a factory or an earlier calibration.

    Attributes:
        view: the view (index); intrinsics: its known intrinsics (of the design's lens model);
        sigmas: (6,) 1-sigma of fx, fy, cx, cy (px), k1, k2; name: how the report and a refusal name it.
    """

    view: int
    intrinsics: Intrinsics
    sigmas: tuple[float, ...]
    name: str = "view"

    def __post_init__(self) -> None:
        s = np.asarray(self.sigmas, dtype=np.float64)
        if s.shape != (6,) or not np.all(np.isfinite(s)) or np.any(s[:4] <= 0) or np.any(s < 0):
            raise PinError(f"pin {self.name}: sigmas must be 6 numbers (fx, fy, cx, cy > 0, k1, k2 >= 0), got "
                           f"{self.sigmas!r}")
        object.__setattr__(self, "sigmas", tuple(float(x) for x in s))

    @classmethod
    def from_file(cls, view: str | int, path: str | Path, grid: ViewGrid) -> ViewPin:
        """View ``view`` of ``grid`` pinned to a ``calibration.json``: its view of the same name, or its only view;
        the sigmas are those the file stores (``metrics.sigmas``: `calibrate` and `calibrate-scene` write them).

        Raises:
            PinError: no such view, or the file has no sigmas for it (names the file and the field).
        """
        p = Path(path)
        v = grid.find(view, f"pin view {p}", PinError)
        calib = Calibration.load(p)
        name = grid.name(v)
        names = [calib.grid.name(i) for i in range(calib.num_views)]
        if name in names:
            src = names.index(name)
        elif calib.num_views == 1:
            src = 0
        else:
            raise PinError(f"{p}: has no view {name} (views {', '.join(names)}) and more than one view")
        sig = calib.sigmas
        if sig is None:
            raise PinError(f"{p}: field metrics.sigmas is missing: a pinned view needs its calibration's sigmas "
                           f"(lfgraph calibrate and calibrate-scene store them)")
        k1, k2 = (float(sig.distortion.get(k, np.full(calib.num_views, np.nan))[src]) for k in ("k1", "k2"))
        return cls(v, calib.intrinsics[src], (*sig.intrinsics[src], k1 if np.isfinite(k1) else 0.0,
                                              k2 if np.isfinite(k2) else 0.0), name=f"view {name}={p.name}")

    def factors(self, calib: Calibration, values: gtsam.Values, track_sigma_px: float,
                first_point: int) -> gtsam.NonlinearFactorGraph:
        """The prior on the view's calibration (`selfcal_graph.view_pin_factor`)."""
        if self.intrinsics.lens != calib.intrinsics[self.view].lens:
            raise PinError(f"pin {self.name}: a {self.intrinsics.lens} lens, the design's views are "
                           f"{calib.intrinsics[self.view].lens}")
        floor = 1e-7
        return selfcal_graph.view_pin_factor(self.view, self.intrinsics, np.maximum(self.sigmas, floor))

    def describe(self) -> str:
        """One line: the view's focal length and its sigma."""
        return f"fx {self.intrinsics.fx:.2f} +- {self.sigmas[0]:.2g} px of one view"


Pin = BoardPin | DistancePin | ViewPin
PIN_TYPES = (BoardPin, DistancePin, ViewPin)
