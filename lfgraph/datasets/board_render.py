"""The checkerboard renderer.

The renderer is exact up to the anti-aliasing: every pixel centre is undistorted through the view's lens model
(once per lens, `lfgraph.datasets.render.sample_rays`) and mapped to the board plane by its homography
(`cv2.perspectiveTransform`, only over the pixels that can see the board). Pixels whose 3x3 neighbourhood changes
colour hold an edge and are averaged over their area, with the undistortion linearised inside the pixel (its
curvature over half a pixel is far below 1e-4 px): exactly along each of N sub-rows (the colour is piecewise
constant between the crossings of square edges and outline), N x N point samples where that does not apply. All
other pixels take the colour at their centre.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from lfgraph.board import BoardSpec
from lfgraph.camera import Intrinsics, transform_points
from lfgraph.datasets.render import (
    NEAR_PLANE_M,
    LensRays,
    clip_polygon_near,
    inverse_from_columns,
    sample_rays,
    to_uint8,
)

if TYPE_CHECKING:  # the config type only annotates (checkerboard.py imports this module)
    from lfgraph.datasets.checkerboard import CheckerboardConfig

BLACK_LEVEL, WHITE_LEVEL = 30.0, 220.0
EDGE_WINDOW_MARGIN_PX = 2  # pixels around the board's footprint in its render window (3x3 edge test + rounding)
ANALYTIC_MAX_SQUARES_PER_PX = 0.5  # edge pixels integrated in closed form span less than this along a row
EDGE_NEIGHBOURHOOD = np.ones((3, 3), np.uint8)  # a pixel is on an edge when its 3x3 neighbourhood changes colour


@dataclass(frozen=True)
class ViewRays:
    """A view's undistorted pixel-centre rays (`LensRays` with one sample per pixel, cached per lens)."""

    lens: LensRays

    @property
    def xy(self) -> np.ndarray:
        """(H, W, 2) undistorted normalised coordinates of the pixel centres (read-only)."""
        return self.lens.xy

    @classmethod
    def compute(cls, intrinsics: Intrinsics, image_size_px: tuple[int, int]) -> ViewRays:
        return cls(sample_rays(intrinsics, (int(image_size_px[0]), int(image_size_px[1])), 1))

    def derivatives(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) derivatives of ``xy`` along x and y at the given pixels (as `np.gradient`: central inside)."""
        xy = self.lens.xy
        h, w = xy.shape[:2]
        c0, c1 = np.maximum(cols - 1, 0), np.minimum(cols + 1, w - 1)
        r0, r1 = np.maximum(rows - 1, 0), np.minimum(rows + 1, h - 1)
        d_dx = (xy[rows, c1] - xy[rows, c0]) / (c1 - c0)[:, None]
        d_dy = (xy[r1, cols] - xy[r0, cols]) / (r1 - r0)[:, None]
        return d_dx, d_dy


def _board_grey(board: BoardSpec, uv: np.ndarray, background: float) -> np.ndarray:
    """Grey level (float32) at board coordinates ``uv`` (..., 2) in squares (corner (0, 0) at 0); NaN = off-board."""
    u, v = uv[..., 0], uv[..., 1]
    m = board.margin_squares
    with np.errstate(invalid="ignore"):
        on_board = (u >= -1 - m) & (u <= board.cols + m) & (v >= -1 - m) & (v <= board.rows + m)
        in_squares = (u >= -1) & (u < board.cols) & (v >= -1) & (v < board.rows)
        # squares where floor(u) + floor(v) is even are black (as the detector's corner order expects)
        black = in_squares & ((np.floor(u) + np.floor(v)).astype(np.int32) & 1 == 0)
    out = np.where(on_board, np.float32(WHITE_LEVEL), np.float32(background))
    out[black] = BLACK_LEVEL
    return out


def _edge_pixels(board: BoardSpec, rays: ViewRays, rows: np.ndarray, cols: np.ndarray, uv: np.ndarray,
                 to_squares: np.ndarray, n: int, background: float, partly_behind: bool) -> np.ndarray:
    """Mean grey level over the area of each edge pixel, the lens linearised inside the pixel.

    Pixels well inside the squares (their whole footprint) are integrated exactly along n sub-rows: along a
    sub-row both board coordinates are linear, so the colour flips where u or v crosses an integer, and the
    covered fraction follows in closed form (`_checker_rows`). Pixels near the squares' border or the board's
    outline are integrated along sub-rows too, over the pieces between the crossings of any colour boundary
    (`_outline_rows`). The rest (squares or margins narrower than `ANALYTIC_MAX_SQUARES_PER_PX`, a board partly
    behind the camera) are point-sampled N x N.
    """
    d_dx, d_dy = rays.derivatives(rows, cols)
    xy0 = rays.lens.xy[rows, cols]
    # Jacobian of the homography (normalised -> squares) at the pixel centre, chained with the lens derivatives
    g = to_squares
    # elementwise, not BLAS: the same rounding on any thread count
    w0, u0, v0 = (xy0[:, 0] * g[r, 0] + xy0[:, 1] * g[r, 1] + g[r, 2] for r in (2, 0, 1))
    uv0 = np.stack([u0, v0], axis=1) / w0[:, None]
    dp = (g[None, :2, :2] - uv0[:, :, None] * g[None, 2:3, :2]) / w0[:, None, None]  # (E, 2, 2)
    j_x = np.einsum("eij,ej->ei", dp, d_dx)  # (E, 2) d(u, v) / d(pixel x)
    j_y = np.einsum("eij,ej->ei", dp, d_dy)
    reach = 0.5 * (np.abs(j_x) + np.abs(j_y))  # half extent of the pixel's footprint along u and v, squares
    with np.errstate(invalid="ignore"):
        analytic = ((not partly_behind) & np.all(np.abs(j_x) < ANALYTIC_MAX_SQUARES_PER_PX, axis=1)
                    & (uv0[:, 0] - reach[:, 0] > -1) & (uv0[:, 0] + reach[:, 0] < board.cols)
                    & (uv0[:, 1] - reach[:, 1] > -1) & (uv0[:, 1] + reach[:, 1] < board.rows))
    out = np.empty(len(rows), dtype=np.float32)
    offsets = (np.arange(n) + 0.5) / n - 0.5
    a = np.flatnonzero(analytic)
    out[a] = _checker_rows(uv0[a], j_x[a], j_y[a], offsets)
    s = np.flatnonzero(~analytic)
    if len(s) and not partly_behind:
        values, ok = _outline_rows(board, uv0[s], j_x[s], j_y[s], offsets, background)
        out[s[ok]] = values[ok]
        s = s[~ok]
    if len(s):
        ox, oy = (o.ravel() for o in np.meshgrid(offsets, offsets))
        samples = xy0[s, None, :] + d_dx[s, None, :] * ox[None, :, None] + d_dy[s, None, :] * oy[None, :, None]
        uv_s = cv2.perspectiveTransform(samples.reshape(-1, 1, 2), to_squares).reshape(len(s), n * n, 2)
        if partly_behind:
            uv_s[(samples[..., 0] * g[2, 0] + samples[..., 1] * g[2, 1] + g[2, 2]) <= 0] = np.nan
        out[s] = _board_grey(board, uv_s, background).mean(axis=1)
    return out


def _outline_rows(board: BoardSpec, uv0: np.ndarray, j_x: np.ndarray, j_y: np.ndarray, offsets: np.ndarray,
                  background: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact mean grey along sub-rows at ``offsets`` (pixels) of each pixel, for any part of the board.

    The colour is constant between consecutive boundary lines along u (the outline, the squares' border, the
    squares' edges) and along v. A sub-row crossing at most one line of each kind splits into at most three
    pieces, each coloured by its midpoint (`_board_grey`) and weighted by its length.

    Returns:
        (E,) float32 grey levels and (E,) True where every sub-row crossed at most one line of each kind (the
        others are not computed).
    """
    m = board.margin_squares
    start = uv0[:, None, :] + offsets[None, :, None] * j_y[:, None, :] - 0.5 * j_x[:, None, :]  # (E, n, 2)
    step = np.broadcast_to(j_x[:, None, :], start.shape)
    t = np.ones(start.shape)
    ok = np.ones(len(uv0), dtype=bool)
    for c, size in enumerate((board.cols, board.rows)):
        lines = np.unique(np.r_[-1.0 - m, np.arange(-1, size + 1, dtype=float), size + m])
        i_start = np.searchsorted(lines, start[..., c], side="right")
        i_end = np.searchsorted(lines, start[..., c] + step[..., c], side="right")
        ok &= np.abs(i_start - i_end).max(axis=1) <= 1
        crossed = i_start != i_end
        line = lines[np.clip(np.maximum(i_start, i_end) - 1, 0, len(lines) - 1)]
        with np.errstate(divide="ignore", invalid="ignore"):
            t[..., c] = np.where(crossed, (line - start[..., c]) / step[..., c], 1.0)
    t1, t2 = np.minimum(t[..., 0], t[..., 1]), np.maximum(t[..., 0], t[..., 1])
    grey = np.zeros(t1.shape)
    for weight, mid in ((t1, 0.5 * t1), (t2 - t1, 0.5 * (t1 + t2)), (1.0 - t2, 0.5 * (t2 + 1.0))):
        grey += weight * _board_grey(board, start + mid[..., None] * step, background)
    return grey.mean(axis=1).astype(np.float32), ok


def _checker_rows(uv0: np.ndarray, j_x: np.ndarray, j_y: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Exact mean grey of the checker squares along sub-rows at ``offsets`` (pixels) of each pixel.

    A sub-row runs from ``uv0 + oy j_y - j_x / 2`` to ``+ j_x / 2``; with |j_x| < 1 square it crosses at most
    one integer u and one integer v, each flipping the colour, so black covers t1 + (1 - t2) of it when it starts
    black (t1 <= t2 the crossings as fractions of the sub-row, 1 when none) and t2 - t1 otherwise.
    """
    # float32: board coordinates below ~100 squares keep 1e-5 squares (< 1e-3 px) of precision
    uv0, j_x, j_y, offsets = (a.astype(np.float32) for a in (uv0, j_x, j_y, offsets))
    t = []
    parity = 0
    for c in range(2):  # u, then v: (E, n) arrays
        start = uv0[:, c, None] + offsets[None, :] * j_y[:, c, None] - 0.5 * j_x[:, c, None]
        end = start + j_x[:, c, None]
        f_start, f_end = np.floor(start), np.floor(end)
        with np.errstate(divide="ignore", invalid="ignore"):
            t.append(np.where(f_start != f_end, (np.maximum(f_start, f_end) - start) / j_x[:, c, None], 1.0))
        parity = parity + f_start.astype(np.int32)
    t1, t2 = np.minimum(t[0], t[1]), np.maximum(t[0], t[1])
    black = np.where((parity & 1) == 0, 1.0 - (t2 - t1), t2 - t1).mean(axis=1)
    return (BLACK_LEVEL * black + WHITE_LEVEL * (1.0 - black)).astype(np.float32)


def render_checkerboard_view(intrinsics: Intrinsics, image_size_px: tuple[int, int], view_T_board: np.ndarray,  # noqa: N803
                             board: BoardSpec, config: CheckerboardConfig, rng: np.random.Generator | None = None,
                             rays: ViewRays | None = None) -> np.ndarray:
    """Render one view of the board as an anti-aliased (H, W) uint8 image.

    Every pixel centre's ray (undistorted once per lens, `ViewRays`) is mapped to the board by the plane's
    homography (`cv2.perspectiveTransform`, only over the window of pixels that can see the board) and takes the
    colour there. Pixels whose 3x3 neighbourhood changes colour hold an edge and take their mean colour over N
    sub-rows, each integrated exactly with the lens and homography linearised inside the pixel (`_edge_pixels`).

    Args:
        intrinsics: the view's lens.
        image_size_px: (width, height).
        view_T_board: (4, 4) board pose in the view frame.
        board: the checkerboard.
        config: blur, noise, background, supersampling.
        rng: noise source (None = no noise even if ``config.noise_sigma`` > 0).
        rays: the view's precomputed `ViewRays` (cached per lens when None).
    """
    w, h = image_size_px
    rays = rays or ViewRays.compute(intrinsics, image_size_px)
    img = np.full((h, w), config.background_level, dtype=np.float32)
    outline = transform_points(view_T_board, board.outline())
    visible = clip_polygon_near(outline)
    # the 3x3 edge test needs one pixel of background around the board; one more absorbs rounding
    window = rays.lens.roi(visible[:, :2] / visible[:, 2:], margin=EDGE_WINDOW_MARGIN_PX) if len(visible) else None
    if window is not None:
        # normalised coordinates -> board squares: the inverse of the homography [r1 r2 t], rows scaled
        to_squares = inverse_from_columns(view_T_board[:3, 0], view_T_board[:3, 1], view_T_board[:3, 3])
        to_squares[:2] /= board.square_m
        xy = rays.lens.xy32[window]
        uv = cv2.perspectiveTransform(xy, to_squares)
        if len(visible) != 4 or np.any(outline[:, 2] < NEAR_PLANE_M):
            # Part of the board is behind the camera: rays meeting its plane behind the camera see background.
            uv[cv2.transform(xy, to_squares[2:]) <= 0] = np.nan
        sub = _board_grey(board, uv, config.background_level)
        lo = cv2.erode(sub, EDGE_NEIGHBOURHOOD)
        hi = cv2.dilate(sub, EDGE_NEIGHBOURHOOD)
        ys, xs = np.nonzero(hi > lo)
        n = config.supersample
        if len(ys) and n > 1:
            rows, cols = ys + window[0].start, xs + window[1].start
            partly_behind = len(visible) != 4 or bool(np.any(outline[:, 2] < NEAR_PLANE_M))
            sub[ys, xs] = _edge_pixels(board, rays, rows, cols, uv[ys, xs], to_squares, n, config.background_level,
                                       partly_behind)
        img[window] = sub
        if config.blur_sigma_px > 0:
            # Outside the window the image is uniform background, which the blur keeps: blur only the window grown
            # by twice the kernel's reach (what the grown part reflects at its border is background too).
            grow = 2 * _blur_radius_px(config.blur_sigma_px) + 1
            rows, cols = window
            grown = (slice(max(rows.start - grow, 0), min(rows.stop + grow, h)),
                     slice(max(cols.start - grow, 0), min(cols.stop + grow, w)))
            img[grown] = cv2.GaussianBlur(img[grown], (0, 0), config.blur_sigma_px)
    return to_uint8(img, config.noise_sigma, rng)


def _blur_radius_px(sigma: float) -> int:
    """Half the kernel width `cv2.GaussianBlur` picks for a float image when ksize is (0, 0)."""
    return (int(round(sigma * 4 * 2 + 1)) | 1) // 2
