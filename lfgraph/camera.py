"""Pinhole + Brown distortion camera model (paper eq. 1-3), vectorised.

The model is exactly GTSAM's ``Cal3DS2`` and OpenCV's 5-coefficient model with ``k3 = 0``:

    r2 = x^2 + y^2,  radial = 1 + k1 r2 + k2 r2^2
    x_d = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    y_d = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
    u = fx x_d + cx,  v = fy y_d + cy

where ``(x, y)`` are normalised image coordinates (``X/Z, Y/Z`` in the camera frame). Pixels follow OpenCV's
convention: ``(0, 0)`` is the centre of the top-left pixel, ``x`` right, ``y`` down. The paper's distortion centre is
the principal point, as in ``Cal3DS2``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import gtsam
import numpy as np

UNDISTORT_MAX_ITERATIONS = 50
UNDISTORT_TOLERANCE = 1e-15  # normalised units; ~1e-12 px at f = 1000 px
UNDISTORT_RESIDUAL_LIMIT = 1e-11  # normalised units; larger residuals mean the pixel has no inverse


def _as_points(points: np.ndarray, dims: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] not in dims:
        raise ValueError(f"{name} must have shape (N, {' or '.join(map(str, dims))}), got {arr.shape}")
    return arr


def distort_xy(x: np.ndarray, y: np.ndarray, k1, k2, p1, p2) -> tuple[np.ndarray, np.ndarray]:
    """The Cal3DS2 / OpenCV distortion of normalised coordinates (arrays broadcast: one lens or a lens per row)."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + k2 * r2)
    return (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)


def distortion_jacobian(x: np.ndarray, y: np.ndarray, k1, k2, p1, p2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(d xd/dx, d xd/dy = d yd/dx, d yd/dy) of `distort_xy` (the map's Jacobian is symmetric)."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + k2 * r2)
    dradial = 2.0 * (k1 + 2.0 * k2 * r2)  # d radial / d(x or y) divided by the coordinate
    return (radial + x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x,
            x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y,
            radial + y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x)


@dataclass(frozen=True)
class Intrinsics:
    """One view's intrinsics: focal lengths and principal point in pixels, Brown k1, k2, p1, p2 (no skew, no k3)."""

    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = float(getattr(self, field.name))
            if not np.isfinite(value):
                raise ValueError(f"Intrinsics.{field.name} must be finite, got {value}")
            object.__setattr__(self, field.name, value)
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")

    # ----------------------------------------------------------------------------------------- conversions
    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the matrix is called K everywhere in the field
        """(3, 3) camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_cv(self) -> np.ndarray:
        """(5,) OpenCV distortion vector ``[k1, k2, p1, p2, k3]`` with ``k3 = 0``."""
        return np.array([self.k1, self.k2, self.p1, self.p2, 0.0])

    def as_vector(self) -> np.ndarray:
        """(8,) ``[fx, fy, cx, cy, k1, k2, p1, p2]``."""
        return np.array([self.fx, self.fy, self.cx, self.cy, self.k1, self.k2, self.p1, self.p2])

    @classmethod
    def from_vector(cls, v: np.ndarray) -> Intrinsics:
        v = np.asarray(v, dtype=np.float64).ravel()
        if v.shape not in ((4,), (6,), (8,)):
            raise ValueError(f"intrinsics vector must have 4, 6 or 8 entries (fx fy cx cy [k1 k2 [p1 p2]]), "
                             f"got {v.shape}")
        return cls(*v.tolist())

    def to_gtsam(self) -> gtsam.Cal3DS2:
        """``gtsam.Cal3DS2(fx, fy, s=0, u0, v0, k1, k2, p1, p2)``."""
        return gtsam.Cal3DS2(self.fx, self.fy, 0.0, self.cx, self.cy, self.k1, self.k2, self.p1, self.p2)

    @classmethod
    def from_gtsam(cls, cal: gtsam.Cal3DS2) -> Intrinsics:
        """From a ``gtsam.Cal3DS2``; raises if it has skew (this model has none)."""
        if abs(cal.skew()) > 1e-12:
            raise ValueError(f"Cal3DS2 has skew {cal.skew()}, but lfgraph's model has none")
        k = cal.k()
        return cls(cal.fx(), cal.fy(), cal.px(), cal.py(), float(k[0]), float(k[1]), float(k[2]), float(k[3]))

    @classmethod
    def from_opencv(cls, K: np.ndarray, dist: np.ndarray | None = None) -> Intrinsics:  # noqa: N803
        """From an OpenCV camera matrix and distortion vector (4, 5 or more coefficients; extra ones must be 0).

        Raises:
            ValueError: K has skew or is not a camera matrix, or ``dist`` uses coefficients this model lacks.
        """
        K = np.asarray(K, dtype=np.float64)  # noqa: N806
        if K.shape != (3, 3) or abs(K[0, 1]) > 1e-12 or np.any(np.abs(K[2] - [0, 0, 1]) > 1e-12) or K[1, 0] != 0:
            raise ValueError(f"K must be a skew-free 3x3 camera matrix [[fx,0,cx],[0,fy,cy],[0,0,1]], got {K.tolist()}")
        d = np.zeros(4) if dist is None else np.asarray(dist, dtype=np.float64).ravel()
        if d.size < 4:
            raise ValueError(f"distortion needs at least 4 coefficients (k1 k2 p1 p2), got {d.size}")
        if np.any(np.abs(d[4:]) > 0):
            raise ValueError(f"distortion coefficients beyond k1 k2 p1 p2 must be 0 (k3 and higher are not modelled), "
                             f"got {d[4:].tolist()}")
        return cls(K[0, 0], K[1, 1], K[0, 2], K[1, 2], *d[:4].tolist())

    # ----------------------------------------------------------------------------------------- model
    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Apply distortion to normalised coordinates.

        Args:
            xy: (N, 2) undistorted normalised coordinates.

        Returns:
            (N, 2) distorted normalised coordinates.
        """
        xy = _as_points(xy, (2,), "xy")
        return np.stack(distort_xy(xy[:, 0], xy[:, 1], self.k1, self.k2, self.p1, self.p2), axis=1)

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

        Newton's method on the 2-D distortion map with its analytic Jacobian, started from the distorted
        coordinates; converges to ~1e-15 for the radial strengths of real lenses (|k1| <= 0.3 over the image).
        Pixels the model cannot reach (beyond the radius where strong barrel distortion folds back on itself), or
        whose solution lies on the folded branch, give NaN rather than a wrong answer.
        """
        px = _as_points(pixels, (2,), "pixels")
        return undistort_views((self,), px[None])[0]

    def undistort_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) distorted pixels -> (N, 2) pixels of the same camera without distortion."""
        xy = self.undistort(pixels)
        return np.stack([self.fx * xy[:, 0] + self.cx, self.fy * xy[:, 1] + self.cy], axis=1)


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
    """`Intrinsics.undistort` of (V, N, 2) pixels, view v with ``intrinsics[v]``, all views in one Newton loop (a
    loop per view costs ~25x the Python overhead for the few hundred tracks of a frame).

    NaN pixels stay NaN. Same model, iteration and validity rule as the method; the loop runs until the largest step
    of all views is below the tolerance, so values agree with the method to round-off."""
    px = np.asarray(pixels, dtype=np.float64)
    k = np.array([i.as_vector() for i in intrinsics]).reshape(-1, 8, 1)
    fx, fy, cx, cy, k1, k2, p1, p2 = (k[:, i] for i in range(8))
    target = np.stack([(px[..., 0] - cx) / fx, (px[..., 1] - cy) / fy], axis=-1)
    xy = target.copy()
    distorted = np.any(k[:, 4:, 0] != 0.0, axis=1)
    if not distorted.any():
        return xy
    for _ in range(UNDISTORT_MAX_ITERATIONS):
        x, y = xy[..., 0], xy[..., 1]
        xd, yd = distort_xy(x, y, k1, k2, p1, p2)
        j00, j01, j11 = distortion_jacobian(x, y, k1, k2, p1, p2)
        fx_, fy_ = xd - target[..., 0], yd - target[..., 1]
        det = j00 * j11 - j01 * j01
        dx = (j11 * fx_ - j01 * fy_) / det
        dy = (-j01 * fx_ + j00 * fy_) / det
        dx[~distorted], dy[~distorted] = 0.0, 0.0
        xy[..., 0] -= dx
        xy[..., 1] -= dy
        if np.nanmax(np.abs(np.concatenate([dx.ravel(), dy.ravel()])), initial=0.0) < UNDISTORT_TOLERANCE:
            break
    # keep only true inverses on the unfolded branch: residual ~0 and d(r radial)/dr > 0 (before the fold)
    with np.errstate(invalid="ignore", over="ignore"):
        x, y = xy[..., 0], xy[..., 1]
        xd, yd = distort_xy(x, y, k1, k2, p1, p2)
        residual = np.maximum(np.abs(xd - target[..., 0]), np.abs(yd - target[..., 1]))
        r2 = x * x + y * y
        radial_derivative = 1.0 + r2 * (3.0 * k1 + 5.0 * k2 * r2)
        bad = (~(residual < UNDISTORT_RESIDUAL_LIMIT) | ~(radial_derivative > 0)) & distorted[:, None]
    xy[bad] = np.nan
    return xy
