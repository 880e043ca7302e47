"""``radtan``: pinhole + Brown distortion (paper eq. 1-3), GTSAM's ``Cal3DS2`` and OpenCV's 5-coefficient model with
``k3 = 0``::

    r2 = x^2 + y^2,  radial = 1 + k1 r2 + k2 r2^2
    x_d = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    y_d = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from lfgraph.lenses.model import UNDISTORT_MAX_ITERATIONS, UNDISTORT_RESIDUAL_LIMIT, UNDISTORT_TOLERANCE, LensModel

if TYPE_CHECKING:
    from lfgraph.core.camera import Intrinsics


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


def radtan_coefficient_jacobian(x: np.ndarray, y: np.ndarray, k1, k2, p1, p2, k3=0.0, k4=0.0,
                                xi=0.0) -> np.ndarray:
    """(*x.shape, 2, 4): d (xd, yd) / d (k1, k2, p1, p2) of `distort_xy` (the distortion is linear in them)."""
    r2 = x * x + y * y
    r4, xy2 = r2 * r2, 2.0 * x * y
    return np.stack([np.stack([x * r2, x * r4, xy2, r2 + 2.0 * x * x], axis=-1),
                     np.stack([y * r2, y * r4, r2 + 2.0 * y * y, xy2], axis=-1)], axis=-2)


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


def radtan_rows(intrinsics: Sequence[Intrinsics]) -> np.ndarray:
    """(V, 4, 1) k1 k2 p1 p2 of each view, as `undo_radtan` takes them."""
    return np.array([[i.k1, i.k2, i.p1, i.p2] for i in intrinsics])[:, :, None]


def _map(x, y, k1, k2, p1, p2, k3, k4, xi, jacobian: bool) -> tuple[np.ndarray, ...]:
    xd, yd = distort_xy(x, y, k1, k2, p1, p2)
    if not jacobian:
        return xd, yd
    d00, d01, d11 = distortion_jacobian(x, y, k1, k2, p1, p2)
    return xd, yd, d00, d01, d01, d11


def _folded(intr: Intrinsics, rays: np.ndarray, xy: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Beyond the radius where d(r radial)/dr stops being positive."""
    r2 = np.sum(xy**2, axis=1)
    return ~(1.0 + r2 * (3.0 * intr.k1 + 5.0 * intr.k2 * r2) > 0)


MODEL = LensModel(name="radtan", gtsam_name="Cal3DS2", coefficients=("k1", "k2", "p1", "p2"),
                  tangent=("k1", "k2", "p1", "p2"), bulk_map=_map,
                  undistort=lambda target, intr: undo_radtan(target, radtan_rows(intr)), folded=_folded,
                  tangential=("p1", "p2"), opencv="pinhole",
                  coefficient_jacobian=radtan_coefficient_jacobian)
