"""The lens models' arithmetic on arrays of normalised coordinates (`lfgraph.core.camera` documents the models): each
model's distortion, its Jacobian, and the iterative inverses, vectorised over points and views."""

from __future__ import annotations

import numpy as np

UNDISTORT_MAX_ITERATIONS = 50
UNDISTORT_TOLERANCE = 1e-15  # normalised units; ~1e-12 px at f = 1000 px
UNDISTORT_RESIDUAL_LIMIT = 1e-11  # normalised units; larger residuals mean the pixel has no inverse


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


def unified_to_plane(x: np.ndarray, y: np.ndarray, xi) -> tuple[np.ndarray, np.ndarray]:
    """Mei's projection of the ray through normalised ``(x, y)`` from the unit sphere shifted by ``xi``."""
    d = 1.0 + xi * np.sqrt(x * x + y * y + 1.0)
    return x / d, y / d


FISHEYE_SMALL_R = 1e-6  # normalised radius below which the fisheye Jacobian takes its limit at the axis


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


def unified_jacobian(x: np.ndarray, y: np.ndarray, xi, k1, k2, p1, p2) -> tuple[np.ndarray, ...]:
    """(xd, yd, d xd/dx, d xd/dy, d yd/dx, d yd/dy) of Mei's model: `unified_to_plane`, then `distort_xy`."""
    rho = np.sqrt(x * x + y * y + 1.0)
    d = 1.0 + xi * rho
    c = xi / (rho * d * d)
    mx, my = x / d, y / d
    m00, m01, m11 = 1.0 / d - c * x * x, -c * x * y, 1.0 / d - c * y * y  # d m / d (x, y), symmetric
    d00, d01, d11 = distortion_jacobian(mx, my, k1, k2, p1, p2)
    xd, yd = distort_xy(mx, my, k1, k2, p1, p2)
    return xd, yd, d00 * m00 + d01 * m01, d00 * m01 + d01 * m11, d01 * m00 + d11 * m01, d01 * m01 + d11 * m11


def undo_radtan(target: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Newton inverse of `distort_xy` for (V, N, 2) distorted normalised coordinates, k (V, 4, 1) = k1 k2 p1 p2.

    The loop runs until the largest step of all views is below the tolerance. Results that are not true inverses on
    the unfolded branch (residual ~0 and d(r radial)/dr > 0) are NaN."""
    k1, k2, p1, p2 = (k[:, i] for i in range(4))
    xy = target.copy()
    distorted = np.any(k[:, :, 0] != 0.0, axis=1)
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
    with np.errstate(invalid="ignore", over="ignore"):
        x, y = xy[..., 0], xy[..., 1]
        xd, yd = distort_xy(x, y, k1, k2, p1, p2)
        residual = np.maximum(np.abs(xd - target[..., 0]), np.abs(yd - target[..., 1]))
        r2 = x * x + y * y
        radial_derivative = 1.0 + r2 * (3.0 * k1 + 5.0 * k2 * r2)
        bad = (~(residual < UNDISTORT_RESIDUAL_LIMIT) | ~(radial_derivative > 0)) & distorted[:, None]
    xy[bad] = np.nan
    return xy


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


def lift_unified(m: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Inverse of `unified_to_plane` for (V, N, 2) plane points, xi (V, 1): back to the unit sphere, then X/Z, Y/Z.
    NaN for points off the model's image (no real lift) or behind the camera."""
    r2 = m[..., 0] ** 2 + m[..., 1] ** 2
    with np.errstate(invalid="ignore"):
        disc = 1.0 + (1.0 - xi * xi) * r2
        factor = (xi + np.sqrt(disc)) / (r2 + 1.0)
        z = factor - xi
        ok = (disc >= 0) & (z > 0)
        xy = m * (factor / np.where(ok, z, 1.0))[..., None]
    xy[~ok] = np.nan
    return xy


def _radtan_map(x, y, k1, k2, p1, p2, k3, k4, xi, jacobian: bool) -> tuple[np.ndarray, ...]:
    xd, yd = distort_xy(x, y, k1, k2, p1, p2)
    if not jacobian:
        return xd, yd
    d00, d01, d11 = distortion_jacobian(x, y, k1, k2, p1, p2)
    return xd, yd, d00, d01, d01, d11


def _fisheye_map(x, y, k1, k2, p1, p2, k3, k4, xi, jacobian: bool) -> tuple[np.ndarray, ...]:
    if not jacobian:
        return distort_fisheye_xy(x, y, k1, k2, k3, k4)
    xd, yd, d00, d01, d11 = fisheye_jacobian(x, y, k1, k2, k3, k4)
    return xd, yd, d00, d01, d01, d11


def _unified_map(x, y, k1, k2, p1, p2, k3, k4, xi, jacobian: bool) -> tuple[np.ndarray, ...]:
    if not jacobian:
        return distort_xy(*unified_to_plane(x, y, xi), k1, k2, p1, p2)
    return unified_jacobian(x, y, xi, k1, k2, p1, p2)


_MAPS = (_radtan_map, _fisheye_map, _unified_map)  # in `lfgraph.core.camera.LENSES` order


def lens_distort(code: np.ndarray, coef: np.ndarray, x: np.ndarray, y: np.ndarray,
                 jacobian: bool = False) -> tuple[np.ndarray, ...]:
    """Each point's own lens applied to normalised coordinates, all models at once.

    Args:
        code: lens of each point, its index in `lfgraph.core.camera.LENSES` (0 radtan, 1 fisheye, 2 unified); same shape
            as ``x``.
        coef: (7, *x.shape) k1, k2, p1, p2, k3, k4, xi of each point's lens.
        x, y: undistorted normalised coordinates.
        jacobian: also return the Jacobian of the map.

    Returns:
        (xd, yd), or (xd, yd, d xd/dx, d xd/dy, d yd/dx, d yd/dy) with ``jacobian``.
    """
    out = [np.empty(np.shape(x)) for _ in range(6 if jacobian else 2)]
    for c, lens_map in enumerate(_MAPS):
        m = code == c
        if m.any():
            for o, value in zip(out, lens_map(x[m], y[m], *(k[m] for k in coef), jacobian=jacobian), strict=True):
                o[m] = value
    return tuple(out)
