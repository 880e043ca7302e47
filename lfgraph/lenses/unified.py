"""``unified``: Mei's unified (omnidirectional) model with radial-tangential terms, GTSAM's ``Cal3Unified`` and
Kalibr's ``omni-radtan``: the point on the unit sphere is shifted by ``xi`` along the axis, then ``radtan``::

    (x, y) -> (x, y) / (1 + xi sqrt(x^2 + y^2 + 1)),  then the radtan distortion with k1, k2, p1, p2
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from lfgraph.lenses.model import LensModel
from lfgraph.lenses.radtan import (
    distort_xy,
    distortion_jacobian,
    radtan_coefficient_jacobian,
    radtan_rows,
    undo_radtan,
)

if TYPE_CHECKING:
    from lfgraph.core.camera import Intrinsics

ROUND_TRIP_TOLERANCE = 1e-8  # normalised units: a ray that a unified lens maps back to itself is truly imaged


def unified_to_plane(x: np.ndarray, y: np.ndarray, xi) -> tuple[np.ndarray, np.ndarray]:
    """Mei's projection of the ray through normalised ``(x, y)`` from the unit sphere shifted by ``xi``."""
    d = 1.0 + xi * np.sqrt(x * x + y * y + 1.0)
    return x / d, y / d


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


def _map(x, y, k1, k2, p1, p2, k3, k4, xi, jacobian: bool) -> tuple[np.ndarray, ...]:
    if not jacobian:
        return distort_xy(*unified_to_plane(x, y, xi), k1, k2, p1, p2)
    return unified_jacobian(x, y, xi, k1, k2, p1, p2)


def _coefficient_jacobian(x: np.ndarray, y: np.ndarray, k1, k2, p1, p2, k3, k4, xi) -> np.ndarray:
    """(*x.shape, 2, 5): d (xd, yd) / d (k1, k2, p1, p2, xi): radtan's at Mei's plane point m, and the distortion's
    Jacobian times d m / d xi = -(x, y) rho / d^2."""
    rho = np.sqrt(x * x + y * y + 1.0)
    d = 1.0 + xi * rho
    mx, my = x / d, y / d
    d00, d01, d11 = distortion_jacobian(mx, my, k1, k2, p1, p2)
    dmx, dmy = -x * rho / (d * d), -y * rho / (d * d)
    dxi = np.stack([d00 * dmx + d01 * dmy, d01 * dmx + d11 * dmy], axis=-1)
    return np.concatenate([radtan_coefficient_jacobian(mx, my, k1, k2, p1, p2), dxi[..., None]], axis=-1)


def _folded(intr: Intrinsics, rays: np.ndarray, xy: np.ndarray, px: np.ndarray) -> np.ndarray:
    """A round trip through `Intrinsics.undistort` must come back to the ray."""
    back = np.full_like(xy, np.nan)
    ok = np.all(np.isfinite(px), axis=1)
    back[ok] = intr.undistort(px[ok])
    with np.errstate(invalid="ignore"):
        return ~(np.max(np.abs(back - xy), axis=1) <= ROUND_TRIP_TOLERANCE * np.maximum(1.0, np.abs(xy).max(1)))


def _off_axis_deg(r: float, xi: float) -> float:
    """Mei's plane radius r back to the unit sphere (`lift_unified`): the angle from the axis (NaN: no lift)."""
    disc = 1.0 + (1.0 - xi**2) * r**2
    if disc < 0:
        return float("nan")
    factor = (xi + np.sqrt(disc)) / (r**2 + 1.0)
    return float(np.degrees(np.arctan2(factor * r, factor - xi)))


def _check(intr: Intrinsics) -> str | None:
    return f"a unified lens needs xi >= 0, got xi={intr.xi}" if intr.xi < 0 else None


MODEL = LensModel(name="unified", gtsam_name="Cal3Unified", coefficients=("xi", "k1", "k2", "p1", "p2"),
                  tangent=("k1", "k2", "p1", "p2", "xi"), bulk_map=_map,
                  undistort=lambda target, intr: lift_unified(undo_radtan(target, radtan_rows(intr)),
                                                              np.array([i.xi for i in intr])[:, None]),
                  folded=_folded, tangential=("p1", "p2"), wide=True, check=_check, off_axis_deg=_off_axis_deg,
                  coefficient_jacobian=_coefficient_jacobian)
