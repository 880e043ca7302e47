"""Multi-view rectification of the whole grid (paper Section 3.3): common K_r and rotation, grid pitch, per-view
rectified projections, look-up tables, remapping, the grid-deviation report and alignment metrics.

Frames: ``ref`` is the reference view, ``rect`` the common rectified orientation (``rect_R_ref``). Every rectified
view keeps its own optical centre (an image warp can turn a camera, never move it) and looks along ``rect`` with
intrinsics ``K_r``; its look-up table maps each rectified pixel to the original pixel through
``rect_R_view = rect_R_ref @ ref_R_view`` and the view's lens.

Relation to the paper:
- K_r (paper eq. for K_r): mean fx, mean fy, principal point at the image centre ``((w-1)/2, (h-1)/2)`` in OpenCV's
  pixel convention (the paper writes w/2, h/2). With ``crop="valid"`` the principal point moves with the crop.
  A rig of mixed image sizes is rectified to the rig's ``image_size_px``, each view's focal length scaled to it.
- Common rotation: the paper sums the N Rodrigues vectors (the reference's is zero) and divides by N-1, which
  for small angles is the mean of the *non-reference* rotations — the reference view counts for nothing and a rig
  whose views are all turned the same way relative to the grid stays turned. Here: the chordal L2 mean of all N
  view rotations (projection of the summed matrices onto SO(3); equal to the paper's mean to first order when the
  divisor is N), then the smallest turn that puts the rectified x axis along the fitted row direction and (for
  2-D grids) y along the fitted column direction, so that disparity is purely horizontal between row neighbours
  and purely vertical between column neighbours.
- Grid pitch (paper t^V, t_r, t^p): the paper divides each view's translation by its grid offset and averages;
  here a least-squares fit ``centre_i = o + dc_i * u + dr_i * v`` over all views gives the row step u and column step
  v (the paper's t_r is (|u|, |v|)); the ideal position of view i is ``o + dc_i u + dr_i v`` and its deviation is
  reported in millimetres in the rectified frame.
- P_i = K_r [rect_R_ref | -rect_R_ref c̄_i], c̄_i the ideal grid position in the reference frame: the ideal camera
  of view i, mapping reference-frame points to rectified pixels.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.camera import pinhole_to_view_px, view_to_pinhole_px
from lfgraph.core.errors import RectificationError
from lfgraph.core.geometry import is_rotation, rotation_angle_deg
from lfgraph.core.grid import ViewGrid
from lfgraph.rectification.checks import check_rectifiable

CROPS = ("valid", "full")
VALID_GRID_STEP_PX = 4  # the common valid region is found on a grid of this step (then shrunk by one step)
MIN_CROP_PX = 16  # a common region smaller than this is no rectified image (the views barely overlap)


def _chordal_mean(rotations: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(np.sum(rotations, axis=0))
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt


def fit_grid(grid: ViewGrid, centres_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares ideal grid through the view centres (reference frame).

    Returns:
        origin o (3,), row step u (3,) (from a view to its right neighbour), column step v (3,) (to the view
        below); u or v is zero when the grid has a single column or row.
    """
    offsets = np.array([grid.offset(v) for v in range(grid.num_views)], dtype=np.float64)  # (dr, dc)
    cols = [np.ones(grid.num_views)]
    has_u, has_v = grid.cols > 1, grid.rows > 1
    if has_u:
        cols.append(offsets[:, 1])
    if has_v:
        cols.append(offsets[:, 0])
    design = np.stack(cols, axis=1)
    coef, *_ = np.linalg.lstsq(design, centres_m, rcond=None)
    o = coef[0]
    u = coef[1] if has_u else np.zeros(3)
    v = coef[1 + int(has_u)] if has_v else np.zeros(3)
    return o, u, v


def rectangular_grid(grid: ViewGrid, centres_m: np.ndarray,
                     rect_R_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # noqa: N803
    """The ideal grid of a rectified light field: rectangular in the rectified frame.

    In rectified coordinates x = o_x + dc * a, y = o_y + dr * b, z = o_z, fitted by least squares (a, b are the
    paper's t_r). Shear or tilt of the real grid is left in the deviations, where it belongs.

    Returns:
        origin o, row step u = a x_rect, column step v = b y_rect, all (3,) in the reference frame.
    """
    p = centres_m @ rect_R_ref.T
    off = np.array([grid.offset(i) for i in range(grid.num_views)], dtype=np.float64)  # (dr, dc)

    def line(t: np.ndarray, y: np.ndarray) -> tuple[float, float]:
        if np.ptp(t) == 0:
            return float(np.mean(y)), 0.0
        slope, intercept = np.polyfit(t, y, 1)
        return float(intercept), float(slope)

    ox, a = line(off[:, 1], p[:, 0])
    oy, b = line(off[:, 0], p[:, 1])
    origin = rect_R_ref.T @ np.array([ox, oy, float(np.mean(p[:, 2]))])
    return origin, rect_R_ref.T @ np.array([a, 0.0, 0.0]), rect_R_ref.T @ np.array([0.0, b, 0.0])


def common_rotation(ref_R_view: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:  # noqa: N803
    """``rect_R_ref``: the chordal mean of the views' orientations, turned so x follows u and y follows v."""
    mean_ref_R_view = _chordal_mean(ref_R_view)  # noqa: N806  the average view orientation
    x_axis, y_axis = mean_ref_R_view[:, 0], mean_ref_R_view[:, 1]
    if np.linalg.norm(u) > 0:
        x_axis = u / np.linalg.norm(u)
        if x_axis @ mean_ref_R_view[:, 0] < 0:  # a grid whose columns run against the cameras' x
            x_axis = -x_axis
    if np.linalg.norm(v) > 0:
        y_axis = v / np.linalg.norm(v)
        if y_axis @ mean_ref_R_view[:, 1] < 0:
            y_axis = -y_axis
    if np.linalg.norm(u) == 0 and np.linalg.norm(v) > 0:  # a single column: y leads
        x_axis = x_axis - (x_axis @ y_axis) * y_axis
        x_axis /= np.linalg.norm(x_axis)
    else:
        y_axis = y_axis - (y_axis @ x_axis) * x_axis
        y_axis /= np.linalg.norm(y_axis)
    z_axis = np.cross(x_axis, y_axis)
    ref_R_rect = np.stack([x_axis, y_axis, z_axis], axis=1)  # noqa: N806
    return ref_R_rect.T


@dataclass(frozen=True)
class Rectification:
    """The rectification of an array (stored in ``calibration.json`` under ``rectification``).

    Attributes:
        source_size_px: (w, h) of the original views.
        image_size_px: (w, h) of the rectified views (smaller than the source with ``crop="valid"``).
        crop: ``valid`` (the rectangle every view fills) or ``full`` (the source size, black where a view has no
            pixel); crop_rect_px: (x0, y0, w, h) of the output inside the full-size rectified frame.
        K_r: (3, 3) common rectified intrinsics of the output images.
        rect_R_ref: (3, 3) common orientation.
        rect_R_view: (V, 3, 3) per-view rectifying rotations (OpenCV's R1/R2 role).
        P: (V, 3, 4) rectified projections of the ideal cameras, reference-frame points to output pixels.
        pitch_m: (2,) grid step along rows (|u|) and columns (|v|).
        grid_origin_m, grid_u_m, grid_v_m: (3,) the fitted ideal grid (reference frame).
        deviation_mm: (V, 3) each view's centre minus its ideal grid position, in the rectified frame.
        rotation_deviation_deg: (V,) angle between each view's orientation and the common one.
    """

    source_size_px: tuple[int, int]
    image_size_px: tuple[int, int]
    crop: str
    crop_rect_px: tuple[int, int, int, int]
    K_r: np.ndarray
    rect_R_ref: np.ndarray
    rect_R_view: np.ndarray
    P: np.ndarray
    pitch_m: np.ndarray
    grid_origin_m: np.ndarray
    grid_u_m: np.ndarray
    grid_v_m: np.ndarray
    deviation_mm: np.ndarray
    rotation_deviation_deg: np.ndarray

    @property
    def num_views(self) -> int:
        """Number of rectified views."""
        return self.rect_R_view.shape[0]

    def to_dict(self) -> dict[str, Any]:
        """The JSON-ready ``rectification`` entry of ``calibration.json`` (read by `from_dict`); pitch in mm."""
        return {
            "source_size_px": list(self.source_size_px), "image_size_px": list(self.image_size_px),
            "crop": self.crop, "crop_rect_px": list(self.crop_rect_px),
            "K_r": self.K_r.tolist(), "R_rect_from_ref": self.rect_R_ref.tolist(),
            "pitch_mm": (1e3 * self.pitch_m).tolist(),
            "grid_origin_m": self.grid_origin_m.tolist(), "grid_u_m": self.grid_u_m.tolist(),
            "grid_v_m": self.grid_v_m.tolist(),
            "views": [{"R_rect_from_view": self.rect_R_view[i].tolist(), "P": self.P[i].tolist(),
                       "deviation_mm": self.deviation_mm[i].tolist(),
                       "rotation_deviation_deg": float(self.rotation_deviation_deg[i])}
                      for i in range(self.num_views)],
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], num_views: int) -> Rectification:
        """Parse what `to_dict` wrote; raises RectificationError naming the field."""
        def arr(key: str, shape: tuple[int, ...], src: Mapping[str, Any] = data, where: str = "rectification"):
            if key not in src:
                raise RectificationError(f"{where}.{key} is missing")
            a = np.asarray(src[key], dtype=np.float64)
            if a.shape != shape or not np.all(np.isfinite(a)):
                raise RectificationError(f"{where}.{key} must be a finite array of shape {shape}")
            return a

        views = data.get("views")
        if not isinstance(views, list) or len(views) != num_views:
            raise RectificationError(f"rectification.views must list {num_views} views")
        rect_R_view = np.stack([arr("R_rect_from_view", (3, 3), v, f"rectification.views[{i}]")  # noqa: N806
                                for i, v in enumerate(views)])
        for i, R in enumerate(rect_R_view):  # noqa: N806
            if not is_rotation(R):
                raise RectificationError(f"rectification.views[{i}].R_rect_from_view is not a rotation")
        crop = data.get("crop")
        if crop not in CROPS:
            raise RectificationError(f"rectification.crop must be one of {CROPS}, got {crop!r}")
        return cls(
            tuple(int(x) for x in arr("source_size_px", (2,))), tuple(int(x) for x in arr("image_size_px", (2,))),
            crop, tuple(int(x) for x in arr("crop_rect_px", (4,))), arr("K_r", (3, 3)),
            arr("R_rect_from_ref", (3, 3)), rect_R_view,
            np.stack([arr("P", (3, 4), v, f"rectification.views[{i}]") for i, v in enumerate(views)]),
            arr("pitch_mm", (2,)) / 1e3, arr("grid_origin_m", (3,)), arr("grid_u_m", (3,)), arr("grid_v_m", (3,)),
            np.stack([arr("deviation_mm", (3,), v, f"rectification.views[{i}]") for i, v in enumerate(views)]),
            np.array([float(v.get("rotation_deviation_deg", 0.0)) for v in views]))


# --------------------------------------------------------------------------------------------- building
def _largest_valid_rect(valid: np.ndarray) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) inclusive rectangle with every cell valid: shrink the side holding most invalid cells."""
    h, w = valid.shape
    bad = (~valid).astype(np.int64)
    integral = np.pad(bad.cumsum(0).cumsum(1), ((1, 0), (1, 0)))

    def count(x0: int, y0: int, x1: int, y1: int) -> int:
        return int(integral[y1 + 1, x1 + 1] - integral[y0, x1 + 1] - integral[y1 + 1, x0] + integral[y0, x0])

    x0, y0, x1, y1 = 0, 0, w - 1, h - 1
    while x0 <= x1 and y0 <= y1 and count(x0, y0, x1, y1) > 0:
        sides = [count(x0, y0, x0, y1) / (y1 - y0 + 1), count(x1, y0, x1, y1) / (y1 - y0 + 1),
                 count(x0, y0, x1, y0) / (x1 - x0 + 1), count(x0, y1, x1, y1) / (x1 - x0 + 1)]
        k = int(np.argmax(sides))
        if k == 0:
            x0 += 1
        elif k == 1:
            x1 -= 1
        elif k == 2:
            y0 += 1
        else:
            y1 -= 1
    if x0 > x1 or y0 > y1:
        raise RectificationError("the views share no common image region after rectification")
    return x0, y0, x1, y1


def compute_rectification(calib: Calibration, crop: str = "valid") -> Rectification:
    """The paper's rectification of a calibrated array (module docstring for the formulas).

    Raises:
        RectificationError: unknown crop mode, a grid of one view, views with no common region, views at one
            position, a lens model that folds over inside the image (`check_rectifiable`).
        TypeError: ``calib`` is not a `Calibration`.
    """
    if not isinstance(calib, Calibration):
        raise TypeError(f"rectify: calib must be a lfgraph.Calibration "
                        f"(load a file with lfgraph.Calibration.load), got {type(calib).__name__}")
    if crop not in CROPS:
        raise RectificationError(f"crop must be one of {', '.join(CROPS)}, got {crop!r}")
    grid = calib.grid
    if grid.num_views < 2:
        raise RectificationError("rectification needs at least two views")
    w, h = calib.image_size_px
    ref_R_view = calib.ref_T_view[:, :3, :3]  # noqa: N806
    centres = calib.ref_T_view[:, :3, 3]
    check_rectifiable(calib)
    _, u_fit, v_fit = fit_grid(grid, centres)
    rect_R_ref = common_rotation(ref_R_view, u_fit, v_fit)  # noqa: N806
    o, u, v = rectangular_grid(grid, centres, rect_R_ref)
    rect_R_view = rect_R_ref[None] @ ref_R_view  # noqa: N806
    sizes = np.array([calib.image_size(i) for i in range(grid.num_views)], dtype=np.float64)
    focal = np.array([(i.fx, i.fy) for i in calib.intrinsics])
    fx, fy = (float(x) for x in np.mean(focal * (w, h) / sizes, axis=0))  # each focal at the output's size
    K_full = np.array([[fx, 0.0, (w - 1) / 2.0], [0.0, fy, (h - 1) / 2.0], [0.0, 0.0, 1.0]])  # noqa: N806
    if crop == "valid":
        step = VALID_GRID_STEP_PX
        xs, ys = np.arange(0, w, step, dtype=np.float64), np.arange(0, h, step, dtype=np.float64)
        gx, gy = np.meshgrid(xs, ys)
        pts = np.column_stack([gx.ravel(), gy.ravel()])
        valid = np.ones(len(pts), dtype=bool)
        for i in range(grid.num_views):
            src = pinhole_to_view_px(pts, K_full, rect_R_view[i], calib.intrinsics[i])
            wi, hi = calib.image_size(i)  # a rig of mixed sizes: each view's own image bounds its pixels
            valid &= (src[:, 0] >= 0) & (src[:, 0] <= wi - 1) & (src[:, 1] >= 0) & (src[:, 1] <= hi - 1)
        x0, y0, x1, y1 = _largest_valid_rect(valid.reshape(gy.shape))
        # grid cells are `step` apart: stay one step inside so every pixel between samples is valid too
        px0, py0 = int(xs[min(x0 + 1, x1)]), int(ys[min(y0 + 1, y1)])
        px1, py1 = int(xs[max(x1 - 1, x0)]), int(ys[max(y1 - 1, y0)])
        crop_rect = (px0, py0, px1 - px0 + 1, py1 - py0 + 1)
        if min(crop_rect[2], crop_rect[3]) < MIN_CROP_PX:
            raise RectificationError(
                f"the views share only a {max(crop_rect[2], 0)}x{max(crop_rect[3], 0)} px region of the {w}x{h} px "
                f"images after rectification (views turned by up to "
                f"{float(np.max(rotation_angle_deg(rect_R_view))):.1f} deg from the common orientation): they barely "
                f"overlap; check the calibration, or keep the source size with --crop full")
    else:
        crop_rect = (0, 0, w, h)
    K_r = K_full.copy()  # noqa: N806
    K_r[0, 2] -= crop_rect[0]
    K_r[1, 2] -= crop_rect[1]
    offsets = np.array([grid.offset(i) for i in range(grid.num_views)], dtype=np.float64)
    ideal = o[None] + offsets[:, 1:2] * u[None] + offsets[:, 0:1] * v[None]
    P = np.stack([K_r @ np.column_stack([rect_R_ref, -rect_R_ref @ c]) for c in ideal])  # noqa: N806
    deviation_mm = 1e3 * (centres - ideal) @ rect_R_ref.T
    rot_dev = np.asarray(rotation_angle_deg(rect_R_view))
    return Rectification((w, h), (crop_rect[2], crop_rect[3]), crop, crop_rect, K_r, rect_R_ref, rect_R_view, P,
                         np.array([np.linalg.norm(u), np.linalg.norm(v)]), o, u, v, deviation_mm, rot_dev)


def attach(calib: Calibration, rect: Rectification) -> Calibration:
    """The calibration with its rectification stored (for ``calibration.json``)."""
    return calib.replace(rectification=rect.to_dict())


def rectify(calib: Calibration, crop: str = "valid") -> Calibration:
    """The paper's rectification (Section 3.3) computed and stored in the calibration.

    Rectify images with ``maps = build_maps(calib, stored_rectification(calib))`` and ``remap_views(images, maps)``.

    Args:
        calib: a calibration of at least two views.
        crop: ``valid`` (the rectangle every view fills) or ``full`` (the source size).

    Raises:
        RectificationError: unknown crop mode, a grid of one view, views with no common region.
    """
    return attach(calib, compute_rectification(calib, crop))


def stored_rectification(calib: Calibration) -> Rectification | None:
    """The rectification stored in ``calib`` (by `rectify` or a file), or None."""
    if calib.rectification is None:
        return None
    return Rectification.from_dict(calib.rectification, calib.num_views)


def rectification_for_export(calib: Calibration, required: bool) -> Rectification | None:
    """The rectification an export writes: the stored one, else the one `rectify` would store (computed here, not
    stored), so an exported pair always carries its rectified matrices and no format is given a zero baseline.

    None for a single view, and where none can be computed but the format can do without one (``required`` False:
    a warning says why). Raises `RectificationError` (naming the cause) where the format needs one."""
    rect = stored_rectification(calib)
    if rect is not None or calib.num_views < 2:
        return rect
    try:
        return compute_rectification(calib)
    except RectificationError as exc:
        if required:
            raise RectificationError(f"this format needs the rectified views' matrices, and this calibration cannot "
                                     f"be rectified: {exc}") from None
        logging.getLogger("lfgraph").warning("the export carries no rectification: %s", exc)
        return None


# --------------------------------------------------------------------------------------------- look-up tables
@dataclass(frozen=True)
class RectificationMaps:
    """Per-view look-up tables in OpenCV's compact fixed-point form (``CV_16SC2`` + ``CV_16UC1``: integer source
    pixel plus a 5-bit sub-pixel index, 6 bytes per pixel instead of 8 for float maps)."""

    map_xy: tuple[np.ndarray, ...]
    map_frac: tuple[np.ndarray, ...]
    image_size_px: tuple[int, int]


def build_maps(calib: Calibration, rect: Rectification) -> RectificationMaps:
    """``cv2.initUndistortRectifyMap`` per radtan view with its K, distortion, rectifying rotation and ``K_r``; for a
    fisheye or unified view the same map from the view's own model (`lfgraph.core.camera.pinhole_to_view_px`; -1 where
    no ray reaches it)."""
    xy, frac = [], []
    w, h = rect.image_size_px
    for i in range(calib.num_views):
        intr = calib.intrinsics[i]
        if intr.model.opencv == "pinhole":
            m1, m2 = cv2.initUndistortRectifyMap(intr.K, intr.dist_cv, rect.rect_R_view[i], rect.K_r,
                                                 rect.image_size_px, cv2.CV_16SC2)
        else:
            u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
            src = pinhole_to_view_px(np.column_stack([u.ravel(), v.ravel()]), rect.K_r, rect.rect_R_view[i], intr)
            src = np.where(np.isfinite(src), src, -1.0).reshape(h, w, 2).astype(np.float32)
            m1, m2 = cv2.convertMaps(src, None, cv2.CV_16SC2)
        xy.append(m1)
        frac.append(m2)
    return RectificationMaps(tuple(xy), tuple(frac), rect.image_size_px)


def remap_views(images: np.ndarray | Sequence[np.ndarray], maps: RectificationMaps) -> np.ndarray:
    """(V, H, W[, 3]) original views -> (V, h, w[, 3]) rectified views (bilinear, black outside)."""
    if len(images) != len(maps.map_xy):
        raise RectificationError(f"{len(images)} views given but the rectification has {len(maps.map_xy)}")
    out = [cv2.remap(img, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
           for img, m1, m2 in zip(images, maps.map_xy, maps.map_frac, strict=True)]
    return np.stack(out)


# --------------------------------------------------------------------------------------------- point mapping
def rectify_points(calib: Calibration, rect: Rectification, view: int, pixels: np.ndarray) -> np.ndarray:
    """(N, 2) original pixels of a view -> (N, 2) rectified output pixels (NaN where the lens has no inverse)."""
    return view_to_pinhole_px(pixels, rect.K_r, rect.rect_R_view[view], calib.intrinsics[view])
