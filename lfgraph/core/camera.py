"""Per-view intrinsics (paper eq. 1-3 and two wide-angle models), vectorised.

An `Intrinsics` is fx, fy, cx, cy and a lens model with its coefficients; the models themselves (their distortion,
Jacobian, inverse, GTSAM class, OpenCV form) are `lfgraph.lenses`, one module each: ``radtan`` (pinhole + Brown,
``Cal3DS2``), ``fisheye`` (Kannala–Brandt, ``Cal3Fisheye``, ``cv2.fisheye``), ``unified`` (Mei, ``Cal3Unified``).
For every model ``u = fx x_d + cx,  v = fy y_d + cy``, where ``(x_d, y_d)`` is the model's distortion of the
normalised image coordinates ``(x, y) = (X/Z, Y/Z)`` in the camera frame. Pixels follow OpenCV's convention:
``(0, 0)`` is the centre of the top-left pixel, ``x`` right, ``y`` down. The distortion centre is the principal point.
"""

from __future__ import annotations

import dataclasses
import numbers
from dataclasses import dataclass

import gtsam
import numpy as np

from lfgraph.lenses import COEFFICIENTS, DEFAULT_LENS, lens_code, lens_model, lens_names

LENSES = lens_names()  # the models known at import (`lfgraph.lenses.lens_names` also sees later registrations)
# the distortion keys of each model, as calibration.json stores them (OpenCV's names; Kalibr's xi for unified)
DISTORTION_KEYS = {name: lens_model(name).coefficients for name in LENSES}


def _as_points(points: np.ndarray, dims: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] not in dims:
        raise ValueError(f"{name} must have shape (N, {' or '.join(map(str, dims))}), got {arr.shape}")
    return arr


def _float_fields(obj: object) -> None:
    for field in dataclasses.fields(obj):
        if field.name == "lens":
            continue
        raw = getattr(obj, field.name)
        if isinstance(raw, bool | np.bool_) or not isinstance(raw, numbers.Real):
            raise TypeError(f"Intrinsics.{field.name} must be a number, got {raw!r}")
        value = float(raw)
        if not np.isfinite(value):
            raise ValueError(f"Intrinsics.{field.name} must be finite, got {value}")
        object.__setattr__(obj, field.name, value)


@dataclass(frozen=True)
class Intrinsics:
    """One view's intrinsics: focal lengths and principal point in pixels, the lens model and its coefficients.

    ``lens`` is one of `LENSES`; each model uses the coefficients `DISTORTION_KEYS` names and the others must be
    0: ``radtan`` k1, k2, p1, p2; ``fisheye`` k1..k4 (OpenCV's ``cv2.fisheye`` convention); ``unified`` xi, k1, k2,
    p1, p2 (Kalibr's ``omni-radtan``). No skew. ``Intrinsics(fx, fy, cx, cy, k1, k2, p1, p2)`` is a radtan lens."""

    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    xi: float = 0.0
    lens: str = DEFAULT_LENS

    def __post_init__(self) -> None:
        try:
            model = lens_model(self.lens)
        except ValueError:
            raise ValueError(f"Intrinsics.lens must be one of {', '.join(lens_names())}, got {self.lens!r}") from None
        _float_fields(self)
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        unused = [name for name in COEFFICIENTS if name not in model.coefficients and getattr(self, name) != 0.0]
        if unused:
            raise ValueError(f"a {self.lens} lens has no {', '.join(unused)} (its distortion is "
                             f"{', '.join(model.coefficients)}); got {unused[0]}={getattr(self, unused[0])}")
        problem = model.check(self) if model.check else None
        if problem:
            raise ValueError(problem)

    @property
    def model(self):  # -> lfgraph.lenses.LensModel
        """The lens model (`lfgraph.lenses.LensModel`): its coefficients, GTSAM class, distortion and inverse."""
        return lens_model(self.lens)

    # ----------------------------------------------------------------------------------------- conversions
    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the matrix is called K everywhere in the field
        """(3, 3) camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distortion(self) -> dict[str, float]:
        """The model's coefficients by name (`DISTORTION_KEYS`), as ``calibration.json`` stores them."""
        return {k: getattr(self, k) for k in self.model.coefficients}

    @property
    def dist_cv(self) -> np.ndarray:
        """OpenCV's distortion vector: ``[k1, k2, p1, p2, k3=0]`` (radtan, for ``cv2``) or ``[k1, k2, k3, k4]``
        (fisheye, for ``cv2.fisheye``). The unified model has none in OpenCV's main modules (ValueError)."""
        return self.model.opencv_distortion(self)

    def as_vector(self) -> np.ndarray:
        """(8,) ``[fx, fy, cx, cy, k1, k2, p1, p2]`` of a radtan lens (the fast solvers' layout)."""
        if self.lens != DEFAULT_LENS:
            raise ValueError(f"as_vector is the {DEFAULT_LENS} layout; this lens is {self.lens}")
        return np.array([self.fx, self.fy, self.cx, self.cy, self.k1, self.k2, self.p1, self.p2])

    @classmethod
    def from_vector(cls, v: np.ndarray) -> Intrinsics:
        """A radtan `Intrinsics` from fx, fy, cx, cy (px) [, k1, k2 [, p1, p2]] (the inverse of `as_vector`)."""
        v = np.asarray(v, dtype=np.float64).ravel()
        if v.shape not in ((4,), (6,), (8,)):
            raise ValueError(f"intrinsics vector must have 4, 6 or 8 entries (fx fy cx cy [k1 k2 [p1 p2]]), "
                             f"got {v.shape}")
        return cls(*v.tolist())

    def with_distortion(self, lens: str, **coefficients: float) -> Intrinsics:
        """The same fx, fy, cx, cy with another lens model and its coefficients (the others 0)."""
        zero = dict.fromkeys(COEFFICIENTS, 0.0)
        return Intrinsics(self.fx, self.fy, self.cx, self.cy, **{**zero, **coefficients, "lens": lens})

    def pinhole(self) -> Intrinsics:
        """fx, fy, cx, cy without distortion (a radtan lens with zero coefficients)."""
        return Intrinsics(self.fx, self.fy, self.cx, self.cy)

    def to_gtsam(self) -> gtsam.Cal3:
        """The GTSAM calibration of this lens (skew 0), of its model's class (`LensModel.gtsam_name`)."""
        return self.model.to_gtsam(self)

    @classmethod
    def from_gtsam(cls, cal: gtsam.Cal3, max_skew_px: float = 1e-12) -> Intrinsics:
        """From a GTSAM calibration of a registered model; raises if its skew exceeds ``max_skew_px`` (these
        models have none; an optimiser that held it at 0 by a prior leaves round-off: pass that bound)."""
        if abs(cal.skew()) > max_skew_px:
            raise ValueError(f"{type(cal).__name__} has skew {cal.skew()}, but lfgraph's models have none")
        model = next((lens_model(n) for n in lens_names() if lens_model(n).gtsam_name == type(cal).__name__), None)
        if model is None:
            raise ValueError(f"{type(cal).__name__} is no registered lens model's GTSAM calibration")
        return cls(**model.from_gtsam(cal), lens=model.name)

    @classmethod
    def from_opencv(cls, K: np.ndarray, dist: np.ndarray | None = None, lens: str = DEFAULT_LENS) -> Intrinsics:  # noqa: N803
        """From an OpenCV camera matrix and distortion vector: radtan (4, 5 or more coefficients; those beyond
        k1 k2 p1 p2 must be 0) or fisheye (``cv2.fisheye``'s 4 coefficients k1..k4).

        Raises:
            ValueError: K has skew or is not a camera matrix, or ``dist`` uses coefficients this model lacks.
        """
        K = np.asarray(K, dtype=np.float64)  # noqa: N806
        if K.shape != (3, 3) or abs(K[0, 1]) > 1e-12 or np.any(np.abs(K[2] - [0, 0, 1]) > 1e-12) or K[1, 0] != 0:
            raise ValueError(f"K must be a skew-free 3x3 camera matrix [[fx,0,cx],[0,fy,cy],[0,0,1]], got {K.tolist()}")
        d = np.zeros(4) if dist is None else np.asarray(dist, dtype=np.float64).ravel()
        model = lens_model(lens)
        return cls(K[0, 0], K[1, 1], K[0, 2], K[1, 2], **model.from_opencv_distortion(d), lens=model.name)

    # ----------------------------------------------------------------------------------------- model
    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Apply the lens to normalised coordinates.

        Args:
            xy: (N, 2) undistorted normalised coordinates (``X/Z, Y/Z``).

        Returns:
            (N, 2) distorted normalised coordinates (pixels are ``fx x_d + cx, fy y_d + cy``).
        """
        xy = _as_points(xy, (2,), "xy")
        return np.stack(distort_lens_xy(self, xy[:, 0], xy[:, 1]), axis=1)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Project camera-frame points or normalised coordinates to pixels.

        Args:
            points: (N, 3) points in this camera's frame (metres, Z > 0) or (N, 2) normalised coordinates.

        Returns:
            (N, 2) pixel coordinates. Points with Z <= 0 give NaN.
        """
        pts = _as_points(points, (2, 3), "points")
        if pts.shape[1] == 3:
            z = pts[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                xy = pts[:, :2] / np.where(z > 0, z, np.nan)[:, None]
        else:
            xy = pts
        d = self.distort(xy)
        return np.stack([self.fx * d[:, 0] + self.cx, self.fy * d[:, 1] + self.cy], axis=1)

    def undistort(self, pixels: np.ndarray) -> np.ndarray:
        """Invert :meth:`project` for (N, 2) pixels: returns (N, 2) normalised coordinates.

        Newton's method on the model's distortion with its analytic Jacobian; converges to ~1e-15 for real lenses.
        Pixels the model cannot reach (beyond the radius where strong barrel distortion folds back on itself, rays
        at 90 degrees or more from the axis), or whose solution lies on the folded branch, give NaN rather than a
        wrong answer.
        """
        px = _as_points(pixels, (2,), "pixels")
        return undistort_views((self,), px[None])[0]

    def undistort_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) distorted pixels -> (N, 2) pixels of the same camera without distortion."""
        xy = self.undistort(pixels)
        return np.stack([self.fx * xy[:, 0] + self.cx, self.fy * xy[:, 1] + self.cy], axis=1)


def distort_lens_xy(intr: Intrinsics, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distortion of one lens (any model) applied to normalised coordinates."""
    return intr.model.distort(intr, x, y)


def in_image(px: np.ndarray, image_size_px: tuple[int, int], margin_px: float = 0.0) -> np.ndarray:
    """Whether pixel positions (..., 2) lie at least ``margin_px`` inside an image of (width, height) (NaN: no)."""
    w, h = image_size_px
    with np.errstate(invalid="ignore"):
        return ((px[..., 0] >= margin_px) & (px[..., 0] <= w - 1 - margin_px)
                & (px[..., 1] >= margin_px) & (px[..., 1] <= h - 1 - margin_px))


def transform_points(a_T_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:  # noqa: N803
    """Map (N, 3) points from frame b to frame a with a (4, 4) transform ``a_T_b``."""
    pts = _as_points(points_b, (3,), "points_b")
    return pts @ a_T_b[:3, :3].T + a_T_b[:3, 3]


def project_world(intrinsics: Intrinsics, view_T_world: np.ndarray, points_world: np.ndarray) -> np.ndarray:  # noqa: N803
    """Project (N, 3) world points into a view whose extrinsics are ``view_T_world`` (4, 4). Returns (N, 2) px."""
    return intrinsics.project(transform_points(view_T_world, points_world))


def undistort_views(intrinsics: list[Intrinsics] | tuple[Intrinsics, ...], pixels: np.ndarray) -> np.ndarray:
    """`Intrinsics.undistort` of (V, N, 2) pixels, view v with ``intrinsics[v]``, all views of one lens model in one
    Newton loop (a loop per view costs ~25x the Python overhead for the few hundred tracks of a frame).

    NaN pixels stay NaN. Same models, iteration and validity rules as the method; values agree with it to
    round-off."""
    px = np.asarray(pixels, dtype=np.float64)
    f = np.array([[i.fx, i.fy] for i in intrinsics])[:, None, :]
    c = np.array([[i.cx, i.cy] for i in intrinsics])[:, None, :]
    target = (px - c) / f
    lenses = np.array([i.lens for i in intrinsics])
    if np.all(lenses == DEFAULT_LENS):  # the common case without copies
        return lens_model(DEFAULT_LENS).undistort(target, intrinsics)
    out = np.full(target.shape, np.nan)
    for lens in dict.fromkeys(lenses.tolist()):
        idx = np.nonzero(lenses == lens)[0]
        out[idx] = lens_model(lens).undistort(target[idx], [intrinsics[v] for v in idx])
    return out


def lens_table(intrinsics: list[Intrinsics] | tuple[Intrinsics, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Every view's lens in one array, for the bulk solvers: ((V, 11) fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, xi;
    (V,) each view's lens code, `lfgraph.lenses.lens_code`). `lfgraph.lenses.lens_distort` applies them."""
    table = np.array([[i.fx, i.fy, i.cx, i.cy, i.k1, i.k2, i.p1, i.p2, i.k3, i.k4, i.xi] for i in intrinsics],
                     dtype=np.float64).reshape(-1, 11)
    return table, np.array([lens_code(i.lens) for i in intrinsics], dtype=np.int64)


def _folded(intr: Intrinsics, rays: np.ndarray, px: np.ndarray) -> np.ndarray:
    """(N,) whether ``project`` gave a pixel beyond the radius where the lens model folds back (plausible but
    wrong: the lens does not image that ray there); each model says where (`lfgraph.lenses.LensModel.folded`)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        xy = rays[:, :2] / rays[:, 2:3]
    return intr.model.folded(intr, rays, xy, px)


def pinhole_to_view_px(px: np.ndarray, K: np.ndarray, pinhole_R_view: np.ndarray,  # noqa: N803
                       intr: Intrinsics) -> np.ndarray:
    """(N, 2) pixels of a pinhole camera ``K`` (no skew) at the view's centre, turned by ``pinhole_R_view`` (view to
    pinhole coordinates) -> (N, 2) pixels of the view on the same rays, NaN behind the view or beyond its lens
    model's fold. The rectified views, a wide view's virtual pinholes and rerun's undistorted views all use it."""
    px = np.asarray(px, dtype=np.float64).reshape(-1, 2)
    rays_pinhole = np.column_stack([(px[:, 0] - K[0, 2]) / K[0, 0], (px[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(px))])
    rays = rays_pinhole @ pinhole_R_view  # pinhole_R_view.T @ ray, row-wise
    out = intr.project(rays)
    out[_folded(intr, rays, out) | ~(rays[:, 2] > 0)] = np.nan
    return out


def view_to_pinhole_px(px: np.ndarray, K: np.ndarray, pinhole_R_view: np.ndarray,  # noqa: N803
                       intr: Intrinsics) -> np.ndarray:
    """(N, 2) pixels of the view -> (N, 2) pixels of the pinhole camera of `pinhole_to_view_px` (NaN where the lens
    has no inverse)."""
    xy = intr.undistort(np.asarray(px, dtype=np.float64).reshape(-1, 2))
    rays = np.column_stack([xy, np.ones(len(xy))]) @ pinhole_R_view.T
    with np.errstate(invalid="ignore", divide="ignore"):
        n = rays[:, :2] / rays[:, 2:3]
    return np.column_stack([K[0, 0] * n[:, 0] + K[0, 2], K[1, 1] * n[:, 1] + K[1, 2]])
