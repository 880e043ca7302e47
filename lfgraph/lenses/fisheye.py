"""``fisheye``: equidistant Kannala–Brandt, GTSAM's ``Cal3Fisheye`` and OpenCV's ``cv2.fisheye`` (k1..k4)::

    theta = atan(r),  theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
    (x_d, y_d) = (x, y) theta_d / r
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from lfgraph.lenses.model import UNDISTORT_MAX_ITERATIONS, UNDISTORT_RESIDUAL_LIMIT, UNDISTORT_TOLERANCE, LensModel

if TYPE_CHECKING:
    from lfgraph.core.camera import Intrinsics

FISHEYE_SMALL_R = 1e-6  # normalised radius below which the fisheye Jacobian takes its limit at the axis
FOLD_SAMPLES = 2048  # angles sampled over [0, pi] for the first fold of a fisheye lens model


def fisheye_theta_d(theta: np.ndarray, k1, k2, k3, k4) -> np.ndarray:
    """Kannala–Brandt: the distorted angle ``theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``."""
    t2 = theta * theta
    return theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))


def distort_fisheye_xy(x: np.ndarray, y: np.ndarray, k1, k2, k3, k4) -> tuple[np.ndarray, np.ndarray]:
    """The Cal3Fisheye / ``cv2.fisheye`` distortion of normalised coordinates (arrays broadcast)."""
    r = np.hypot(x, y)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(r > 1e-12, fisheye_theta_d(np.arctan(r), k1, k2, k3, k4) / np.where(r > 1e-12, r, 1.0),
                         1.0)
    return x * scale, y * scale


def fisheye_jacobian(x: np.ndarray, y: np.ndarray, k1, k2, k3, k4) -> tuple[np.ndarray, ...]:
    """(xd, yd, d xd/dx, d xd/dy = d yd/dx, d yd/dy) of `distort_fisheye_xy`.

    With r = |(x, y)|, theta = atan r and s = theta_d / r, the map is s (x, y); its Jacobian is s I + g (x, y)(x, y)^T
    with g = (ds/dr) / r, which tends to 2 (k1 - 1/3) on the axis."""
    r = np.hypot(x, y)
    small = r < FISHEYE_SMALL_R
    rs = np.where(small, 1.0, r)
    theta = np.arctan(rs)
    t2 = theta * theta
    theta_d = fisheye_theta_d(theta, k1, k2, k3, k4)
    dtheta_d = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
    s = np.where(small, 1.0, theta_d / rs)
    g = np.where(small, 2.0 * (k1 - 1.0 / 3.0), (dtheta_d * rs / (1.0 + rs * rs) - theta_d) / rs**3)
    return x * s, y * s, s + g * x * x, g * x * y, s + g * y * y


def _coefficient_jacobian(x: np.ndarray, y: np.ndarray, k1, k2, p1, p2, k3, k4, xi) -> np.ndarray:
    """(*x.shape, 2, 4): d (xd, yd) / d (k1, k2, k3, k4) = (x, y) theta^(2i+1) / r (0 on the axis)."""
    r = np.hypot(x, y)
    small = r < FISHEYE_SMALL_R
    rs = np.where(small, 1.0, r)
    theta = np.arctan(rs)
    t2 = theta * theta
    powers = np.stack([theta * t2, theta * t2**2, theta * t2**3, theta * t2**4], axis=-1) / rs[..., None]
    powers[small] = 0.0  # theta^3 / r ~ r^2 -> 0
    return np.stack([x[..., None] * powers, y[..., None] * powers], axis=-2)


def undo_fisheye(target: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Newton inverse of `distort_fisheye_xy` for (V, N, 2), k (V, 4, 1) = k1..k4: solve theta_d(theta) = r_d, then
    r = tan(theta). NaN where theta would reach 90 degrees, the polynomial is not increasing, or no root is found."""
    k1, k2, k3, k4 = (k[:, i] for i in range(4))
    rd = np.hypot(target[..., 0], target[..., 1])
    theta = np.minimum(rd, 1.5)
    for _ in range(UNDISTORT_MAX_ITERATIONS):
        t2 = theta * theta
        f = fisheye_theta_d(theta, k1, k2, k3, k4) - rd
        df = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
        with np.errstate(invalid="ignore", divide="ignore"):
            step = f / df
        theta = theta - step
        if np.nanmax(np.abs(step), initial=0.0) < UNDISTORT_TOLERANCE:
            break
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        t2 = theta * theta
        df = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
        residual = np.abs(fisheye_theta_d(theta, k1, k2, k3, k4) - rd)
        ok = (residual < UNDISTORT_RESIDUAL_LIMIT) & (df > 0) & (theta >= 0) & (theta < np.pi / 2)
        scale = np.where(rd > 1e-12, np.tan(theta) / np.where(rd > 1e-12, rd, 1.0), 1.0)
    xy = target * scale[..., None]
    xy[~ok] = np.nan
    return xy


def _map(x, y, k1, k2, p1, p2, k3, k4, xi, jacobian: bool) -> tuple[np.ndarray, ...]:
    if not jacobian:
        return distort_fisheye_xy(x, y, k1, k2, k3, k4)
    xd, yd, d00, d01, d11 = fisheye_jacobian(x, y, k1, k2, k3, k4)
    return xd, yd, d00, d01, d01, d11


def _folded(intr: Intrinsics, rays: np.ndarray, xy: np.ndarray, px: np.ndarray) -> np.ndarray:
    """theta_d(theta) must rise all the way from 0 to the ray's angle."""
    t = np.linspace(0.0, np.pi, FOLD_SAMPLES)
    t2 = t * t
    slope = 1.0 + t2 * (3 * intr.k1 + t2 * (5 * intr.k2 + t2 * (7 * intr.k3 + t2 * 9 * intr.k4)))
    fold = t[np.argmax(slope <= 0)] if np.any(slope <= 0) else np.inf
    return ~(np.arctan2(np.hypot(rays[:, 0], rays[:, 1]), rays[:, 2]) < fold)


MODEL = LensModel(name="fisheye", gtsam_name="Cal3Fisheye", coefficients=("k1", "k2", "k3", "k4"),
                  tangent=("k1", "k2", "k3", "k4"), bulk_map=_map,
                  undistort=lambda target, intr: undo_fisheye(
                      target, np.array([[i.k1, i.k2, i.k3, i.k4] for i in intr])[:, :, None]),
                  folded=_folded, wide=True, opencv="fisheye",
                  off_axis_deg=lambda r, xi: float(np.degrees(r)),  # equidistant: the angle is the radius
                  coefficient_jacobian=_coefficient_jacobian)
