"""Shared pieces of the synthetic renderers: cached per-lens sample rays and planar-quad bookkeeping.

Both renderers point-sample the scene along the rays of a regular grid of sub-pixel samples in the *distorted*
image and average them. Undistorting those samples (Newton iteration in `Intrinsics.undistort`) is by far the
most expensive step and depends only on the lens, so it is done once per (intrinsics, image size, supersampling)
and cached (`sample_rays`). A planar surface maps undistorted normalised coordinates to its own coordinates by a
homography, which OpenCV applies in one C++ pass (`cv2.perspectiveTransform`); its inverse depth is affine in the
same coordinates (`cv2.transform`), which gives an exact per-sample z-buffer.

Both renderers finish an image the same way (`to_uint8`): Gaussian sensor noise drawn by inverse-CDF lookup (one
random 16-bit index per pixel into a table of equiprobable Gaussian quantiles), added and rounded to 8 bits in one
OpenCV pass.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from statistics import NormalDist

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from lfgraph.core.camera import Intrinsics

NEAR_PLANE_M = 1e-3  # surfaces are clipped to z >= this before their image footprint is bounded
RAY_CACHE_SIZE = 4  # lenses kept in the cache; a 960x960 view at 1 sample per pixel holds ~22 MB
UNDISTORT_GRID_STRIDE_PX = 8  # pixels between exactly undistorted nodes (interpolated in between)
LAGRANGE_TAPS = 6  # nodes per axis in the interpolation stencil (5th-order polynomial, exact for the model's k2 r^4)
NOISE_LEVELS = 1 << 16  # equiprobable Gaussian quantiles the sensor noise is drawn from (tails cut at 4.3 sigma)


@dataclass(frozen=True, eq=False)
class LensRays:
    """Undistorted normalised coordinates of a grid of sample points of one view (cached: treat as read-only).

    Sample ``(i, j)`` sits at pixel ``((j + 0.5) / n - 0.5, (i + 0.5) / n - 0.5)`` for ``n = supersample``, i.e.
    ``n x n`` samples centred in every pixel; ``n = 1`` gives the pixel centres.

    Attributes:
        supersample: samples per pixel along each axis.
        xy: (H n, W n, 2) undistorted normalised coordinates (NaN where the lens model has no inverse); float64
            for ``n = 1`` (exact depth maps, board edges), float32 for supersampled grids (rendering only).
        xy32: the same as float32 (enough for rendering: 1e-7 relative, ~1e-4 px).
        row_y_range: (H n, 2) least and largest y of each sample row (NaN for rows without a valid sample).
        col_x_range: (W n, 2) least and largest x of each sample column.
    """

    supersample: int
    xy: np.ndarray
    xy32: np.ndarray
    row_y_range: np.ndarray
    col_x_range: np.ndarray

    def roi(self, corners_xy: np.ndarray, margin: int = 0) -> tuple[slice, slice] | None:
        """Rows and columns of the sample grid that can see a convex polygon given by its normalised corners.

        Conservative and exact for any lens: a sample inside the polygon has its x inside the polygon's x range,
        so its column's x range overlaps it (same for rows). ``margin`` samples are added on every side.
        """
        x0, y0 = corners_xy.min(axis=0)
        x1, y1 = corners_xy.max(axis=0)
        with np.errstate(invalid="ignore"):
            rows = np.flatnonzero((self.row_y_range[:, 1] >= y0) & (self.row_y_range[:, 0] <= y1))
            cols = np.flatnonzero((self.col_x_range[:, 1] >= x0) & (self.col_x_range[:, 0] <= x1))
        if rows.size == 0 or cols.size == 0:
            return None
        h, w = self.xy.shape[:2]
        return (slice(max(rows[0] - margin, 0), min(rows[-1] + 1 + margin, h)),
                slice(max(cols[0] - margin, 0), min(cols[-1] + 1 + margin, w)))


@lru_cache(maxsize=RAY_CACHE_SIZE)
def sample_rays(intrinsics: Intrinsics, image_size_px: tuple[int, int], supersample: int = 1) -> LensRays:
    """The view's `LensRays` for ``supersample x supersample`` samples per pixel, computed once per lens.

    The lens is undistorted exactly (`Intrinsics.undistort`, Newton) on a coarse grid, one node per
    ``UNDISTORT_GRID_STRIDE_PX`` pixels, and interpolated to every sample by separable 6-point Lagrange polynomials
    (6-tap sums along x, then y, by phase). The undistortion is smooth: the interpolation error is ~1e-7 px in float64
    (pixel centres) and ~1e-4 px in float32 (supersampled grids), at a small fraction of the cost of Newton
    iteration at every sample. Samples whose stencil holds a node beyond the lens fold (NaN) are undistorted
    exactly.
    """
    w, h = image_size_px
    n = int(supersample)
    s = UNDISTORT_GRID_STRIDE_PX * n  # in samples
    pad = LAGRANGE_TAPS // 2
    # Node k sits at sample index k s, k = -pad .. ceil(size / s) + pad, so every sample has a full stencil.
    kx = np.arange(-pad, -(-w * n // s) + pad + 1)
    ky = np.arange(-pad, -(-h * n // s) + pad + 1)
    nodes = _undistort_grid(intrinsics, _sample_to_pixel(kx * s, n), _sample_to_pixel(ky * s, n))
    bad = ~np.isfinite(nodes[..., 0])
    # Pixel centres (n = 1: boards, depth maps) in float64; supersampled grids are only rendered, float32 suffices.
    dtype = np.float64 if n == 1 else np.float32
    nodes = np.where(bad[..., None], 0.0, nodes).astype(dtype)
    # Sample i = k s + p (phase p < s) interpolates nodes k + 1 .. k + TAPS (indices into kx, ky) with weights that
    # depend on p only: one (s, TAPS) table, applied to a sliding window of nodes by einsum. einsum's own loops, not
    # BLAS: BLAS (numpy's and cv2.gemm's) rounds differently with different thread counts, and renders must not
    # depend on the executor's threading.
    first, weights = _lagrange_taps(np.arange(s) / s + pad, dtype)
    assert np.all(first == first[0])
    k0 = int(first[0])
    blocks_x, blocks_y = -(-w * n // s), -(-h * n // s)
    windows = sliding_window_view(nodes, LAGRANGE_TAPS, axis=1)[:, k0 : k0 + blocks_x]  # (Ky, Bx, 2, TAPS)
    along_x = np.einsum("ykcj,pj->ykpc", windows, weights).reshape(len(ky), blocks_x * s, 2)[:, : w * n]
    windows = sliding_window_view(along_x, LAGRANGE_TAPS, axis=0)[k0 : k0 + blocks_y]  # (By, W n, 2, TAPS)
    xy = np.einsum("kwcj,pj->kpwc", windows, weights).reshape(blocks_y * s, w * n, 2)[: h * n]
    xy = np.ascontiguousarray(xy)
    planes = [xy[..., 0], xy[..., 1]]
    if bad.any():
        # Samples whose stencil holds a node beyond the lens fold: undistort them exactly.
        base_x, _ = _lagrange_taps(np.arange(w * n) / s + pad, dtype)
        base_y, _ = _lagrange_taps(np.arange(h * n) / s + pad, dtype)
        bad_x = np.logical_or.reduce([bad[:, base_x + j] for j in range(LAGRANGE_TAPS)])
        rows, cols = np.nonzero(np.logical_or.reduce([bad_x[base_y + j] for j in range(LAGRANGE_TAPS)]))
        exact = intrinsics.undistort(np.column_stack([_sample_to_pixel(cols, n), _sample_to_pixel(rows, n)]))
        for c in range(2):
            planes[c][rows, cols] = exact[:, c]
    with np.errstate(invalid="ignore"):  # rows/columns all beyond the lens fold stay NaN and are never selected
        # reductions over contiguous memory (SIMD), ~6x faster than over the strided plane: y copied out first,
        # x reduced along axis 0 on both channels at once (elementwise over rows)
        y = np.ascontiguousarray(planes[1])
        row_y = np.stack([np.fmin.reduce(y, axis=1), np.fmax.reduce(y, axis=1)], axis=1)
        col_x = np.stack([np.fmin.reduce(xy, axis=0)[:, 0], np.fmax.reduce(xy, axis=0)[:, 0]], axis=1)
    xy32 = xy if dtype == np.float32 else xy.astype(np.float32)
    for arr in (xy, xy32, row_y, col_x):
        arr.setflags(write=False)
    return LensRays(n, xy, xy32, row_y, col_x)


def _sample_to_pixel(index: np.ndarray, n: int) -> np.ndarray:
    return (np.asarray(index, dtype=np.float64) + 0.5) / n - 0.5


def _lagrange_taps(pos: np.ndarray, dtype: type) -> tuple[np.ndarray, np.ndarray]:
    """First node and (M, LAGRANGE_TAPS) weights of local Lagrange interpolation at node coordinates ``pos``."""
    base = np.floor(pos).astype(np.int64) - (LAGRANGE_TAPS // 2 - 1)
    frac = pos - base  # position relative to the first tap, in [TAPS/2 - 1, TAPS/2)
    weights = np.ones((len(pos), LAGRANGE_TAPS))
    for j in range(LAGRANGE_TAPS):
        for m in range(LAGRANGE_TAPS):
            if m != j:
                weights[:, j] *= (frac - m) / (j - m)
    return base, weights.astype(dtype)


def _undistort_grid(intrinsics: Intrinsics, x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray:
    uu, vv = np.meshgrid(x_px, y_px)
    return intrinsics.undistort(np.column_stack([uu.ravel(), vv.ravel()])).reshape(len(y_px), len(x_px), 2)


def clip_polygon_near(points: np.ndarray, near_m: float = NEAR_PLANE_M) -> np.ndarray:
    """Clip a convex polygon (k, 3) in a camera frame to ``z >= near_m`` (Sutherland-Hodgman); may return (0, 3)."""
    out = []
    k = len(points)
    for i in range(k):
        p, q = points[i], points[(i + 1) % k]
        p_in, q_in = p[2] >= near_m, q[2] >= near_m
        if p_in:
            out.append(p)
        if p_in != q_in:
            t = (near_m - p[2]) / (q[2] - p[2])
            out.append(p + t * (q - p))
    return np.array(out).reshape(-1, 3)


def inverse_from_columns(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Inverse of the 3x3 matrix with columns ``a, b, c``, by cross products.

    Elementwise arithmetic only, so the result does not depend on the BLAS/LAPACK thread count (OpenBLAS's LU
    rounds differently with 1 and 2 threads, which made renders differ between process pools and Dask workers).
    """
    rows = np.stack([cross3(b, c), cross3(c, a), cross3(a, b)])
    return rows / float(np.sum(a * rows[0]))


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of two 3-vectors: the same products and differences, without its ~10 us of overhead."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def plane_maps(origin: np.ndarray, axis_u: np.ndarray, axis_v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Homography and inverse-depth row of the plane ``origin + s axis_u + t axis_v`` (camera frame).

    Returns:
        ``H`` (3, 3) mapping normalised image coordinates (x, y, 1) to plane coordinates (s, t, 1) up to scale,
        and ``inv_depth`` (1, 3) with ``1 / z = inv_depth @ (x, y, 1)`` for the ray's hit of the plane (<= 0 when
        the hit is behind the camera or the ray is parallel to the plane).
    """
    normal = cross3(axis_u, axis_v)
    # normal @ origin = 0 only for a plane through the camera centre, seen edge-on; callers skip those.
    return inverse_from_columns(axis_u, axis_v, origin), (normal / float(np.sum(normal * origin)))[None, :]


@lru_cache(maxsize=1)
def _unit_gaussian_quantiles() -> np.ndarray:
    """(NOISE_LEVELS,) float64 quantiles of N(0, 1) at probabilities (k + 0.5) / NOISE_LEVELS, rescaled to unit std.

    Drawing one of them uniformly is a Gaussian draw up to the discretisation (neighbouring quantiles are 4e-5 sigma
    apart near 0) and the tails beyond 4.3 sigma (1 draw in 65536 would have gone further): after adding to an
    image and rounding to whole grey levels nothing of either is left. The table is symmetric (mean exactly 0).
    """
    half = NormalDist().inv_cdf
    upper = np.array([half((k + 0.5) / NOISE_LEVELS) for k in range(NOISE_LEVELS // 2, NOISE_LEVELS)])
    z = np.concatenate([-upper[::-1], upper])
    return z / np.sqrt(np.mean(z * z))


def to_uint8(img: np.ndarray, noise_sigma: float = 0.0, rng: np.random.Generator | None = None) -> np.ndarray:
    """Grey levels (float32, (H, W)) plus Gaussian noise of std ``noise_sigma`` (only with ``rng``), rounded to the
    nearest integer (ties to even, as `np.rint`) and saturated to [0, 255], as uint8.

    The noise is one uniform 16-bit draw per pixel from ``rng`` (`Generator.bytes`, little-endian) looked up in the
    table of Gaussian quantiles: ~4x cheaper than `Generator.standard_normal`, same statistics (see
    `_unit_gaussian_quantiles`), and seeded by ``rng`` alone.
    """
    img = np.ascontiguousarray(img, dtype=np.float32)
    # cv2.add to 8 bits: saturate_cast<uchar>, i.e. round half to even and clip, in one pass
    if rng is None or noise_sigma <= 0:
        return cv2.add(img, 0.0, dtype=cv2.CV_8U)
    index = np.frombuffer(rng.bytes(2 * img.size), dtype="<u2").reshape(img.shape)
    noise = np.take(_noise_table(float(noise_sigma)), index)  # ~2x faster than fancy indexing
    return cv2.add(img, noise, dtype=cv2.CV_8U)


@lru_cache(maxsize=4)
def _noise_table(sigma: float) -> np.ndarray:
    return (sigma * _unit_gaussian_quantiles()).astype(np.float32)
