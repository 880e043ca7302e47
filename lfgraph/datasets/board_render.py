"""The checkerboard renderer.

The renderer is exact up to the anti-aliasing: every pixel centre is undistorted through the view's lens model
(once per lens, `lfgraph.datasets.render.sample_rays`) and mapped to the board plane by its homography
(`cv2.perspectiveTransform`, only over the pixels that can see the board). Pixels whose 3x3 neighbourhood changes
colour hold an edge and are averaged over their area, with the undistortion linearised inside the pixel (its
curvature over half a pixel is far below 1e-4 px): in closed form where one board line crosses the pixel, exactly
along each of N sub-rows where a u-line and a v-line do (the colour is piecewise constant between the crossings of
square edges and outline), N x N point samples where neither applies. All other pixels take the colour at their
centre. Colours come from a table of the board's cells (squares, margin, beyond the outline).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np

from lfgraph.core.camera import Intrinsics, transform_points
from lfgraph.datasets.render import (
    NEAR_PLANE_M,
    LensRays,
    clip_polygon_near,
    inverse_from_columns,
    sample_rays,
    to_uint8,
)
from lfgraph.detect.board import BoardSpec

BLACK_LEVEL, WHITE_LEVEL = 30.0, 220.0
EDGE_WINDOW_MARGIN_PX = 2  # pixels around the board's footprint in its render window (3x3 edge test + rounding)
EDGE_NEIGHBOURHOOD = np.ones((3, 3), np.uint8)  # a pixel is on an edge when its 3x3 neighbourhood changes colour


@dataclass(frozen=True)
class CheckerboardConfig:
    """How the board is shown to the array and how images look.

    Attributes:
        board: the checkerboard.
        frames: number of captures.
        distance_m: (near, far) distance of the board centre from the reference view.
        max_tilt_deg: largest tilt of the board away from fronto-parallel.
        max_roll_deg: largest in-plane rotation (kept modest so the corner order stays unambiguous).
        coverage_cells: the reference image is cut into this many cells per side; frames cycle through them so the
            board centres cover the whole field of view.
        blur_sigma_px: Gaussian blur of the rendered image (0 = none).
        noise_sigma: sensor noise, grey levels std (0 = none).
        background_level: grey level behind the board.
        supersample: N for the N sub-rows (N x N samples where they do not apply) of edge pixels at a corner
            (pixels crossed by one edge take their exact area).
        margin_px: a board counts as visible in a view when its whole printed outline is this far inside.
    """

    board: BoardSpec = field(default_factory=lambda: BoardSpec(11, 8, 0.020))
    frames: int = 40
    distance_m: tuple[float, float] = (0.35, 0.9)
    max_tilt_deg: float = 40.0
    max_roll_deg: float = 20.0
    coverage_cells: int = 3
    blur_sigma_px: float = 0.8
    noise_sigma: float = 1.0
    background_level: float = 120.0
    supersample: int = 8
    margin_px: float = 3.0

    def __post_init__(self) -> None:
        near, far = self.distance_m
        if not (0 < near <= far):
            raise ValueError(f"distance range must satisfy 0 < near <= far, got {self.distance_m}")
        if self.frames < 1 or self.supersample < 1 or self.coverage_cells < 1:
            raise ValueError("frames, supersample and coverage_cells must be >= 1")
        if not 0 <= self.max_tilt_deg < 80:
            raise ValueError(f"max_tilt_deg must be in [0, 80), got {self.max_tilt_deg}")


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
        """The pixel-centre rays of a view with ``intrinsics`` and ``image_size_px`` (width, height), from the per-lens
        cache of `sample_rays`."""
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
    """Grey level (float32) at board coordinates ``uv`` (..., 2) in squares (corner (0, 0) at 0); NaN = off-board.

    Each coordinate's cell (`_cells`) indexes a table of the cells' grey levels (`_cell_grey_table`).
    """
    m = float(board.margin_squares)
    return _cell_grey(_cell_grey_table(board, background), _cells(uv[..., 0], board.cols, m),
                      _cells(uv[..., 1], board.rows, m))


def _cell_grey(table: np.ndarray, iu: np.ndarray, iv: np.ndarray) -> np.ndarray:
    """Grey levels of cells ``(iu, iv)`` (float32 arrays from `_cells`) from `_cell_grey_table`."""
    return np.take(table, ((iv + 3) * np.float32(table.shape[1]) + (iu + 3)).astype(np.int32))


def _edge_pixels(board: BoardSpec, rays: ViewRays, rows: np.ndarray, cols: np.ndarray, uv: np.ndarray,
                 ys: np.ndarray, xs: np.ndarray, to_squares: np.ndarray, n: int, background: float,
                 partly_behind: bool) -> np.ndarray:
    """Mean grey level over the area of each edge pixel, the lens and homography linearised inside the pixel.

    ``uv`` holds the board coordinates (squares) of every pixel centre of the render window; the edge pixels sit at
    ``(ys, xs)`` in it and at ``(rows, cols)`` in the image. A pixel's footprint on the board is the parallelogram
    spanned by the derivatives of ``uv`` along x and y (central differences of the neighbouring centres), and the
    board's lines (square edges, the squares' border, the outline) are straight across it. A footprint inside one
    cell takes its colour; one crossed by a single line takes the exact area on either side (`_single_line`).
    Footprints crossed by a u-line and a v-line (at the corners) are integrated along n sub-rows, each exactly over
    the at most three pieces between its crossings (`_sub_rows`). Pixels whose sub-rows cross more lines (squares
    narrower than two pixels) and boards partly behind the camera are point-sampled N x N.
    """
    out = np.empty(len(rows), dtype=np.float32)
    s = np.arange(len(rows))
    if not partly_behind:
        h, w = uv.shape[:2]
        flat = uv.reshape(-1, 2)
        at = ys * w + xs
        x0, x1 = np.where(xs > 0, at - 1, at), np.where(xs < w - 1, at + 1, at)
        y0, y1 = np.where(ys > 0, at - w, at), np.where(ys < h - 1, at + w, at)
        # (E, 2) d(u, v) / d(pixel x) and / d(pixel y): central differences (one-sided at the window's border)
        j_x = (np.take(flat, x1, axis=0) - np.take(flat, x0, axis=0)) / (x1 - x0)[:, None].astype(np.float32)
        j_y = (np.take(flat, y1, axis=0) - np.take(flat, y0, axis=0)) / ((y1 - y0) // w)[:, None].astype(np.float32)
        uv0 = np.take(flat, at, axis=0)
        values, done = _single_line(board, uv0, j_x, j_y, background)
        out[done] = values[done]
        s = np.flatnonzero(~done)
        values, ok = _sub_rows(board, uv0[s], j_x[s], j_y[s], n, background)
        out[s[ok]] = values[ok]
        s = s[~ok]
    if len(s):
        d_dx, d_dy = rays.derivatives(rows[s], cols[s])
        xy0 = rays.lens.xy[rows[s], cols[s]]
        offsets = (np.arange(n) + 0.5) / n - 0.5
        ox, oy = (o.ravel() for o in np.meshgrid(offsets, offsets))
        samples = xy0[:, None, :] + d_dx[:, None, :] * ox[None, :, None] + d_dy[:, None, :] * oy[None, :, None]
        uv_s = cv2.perspectiveTransform(samples.reshape(-1, 1, 2), to_squares).reshape(len(s), n * n, 2)
        if partly_behind:
            g = to_squares
            uv_s[(samples[..., 0] * g[2, 0] + samples[..., 1] * g[2, 1] + g[2, 2]) <= 0] = np.nan
        out[s] = _board_grey(board, uv_s, background).mean(axis=1)
    return out


def _cells(coord: np.ndarray, size: int, margin: float) -> np.ndarray:
    """Index of the board cell along one axis holding ``coord`` (squares), clipped to [-3, size + 1] (NaN: size + 1).

    Cells -1 .. size - 1 are squares (cell k spans [k, k + 1)), -2 and ``size`` the white margin on either side,
    -3 and ``size + 1`` beyond the outline. Returned as float32 (exact small integers).
    """
    cell = np.floor(coord)
    if margin != 1.0:  # the margin cells span ``margin`` squares
        below, above = coord < -1, coord >= size
        cell[below] = -1 + np.floor((coord[below] + 1) / margin)
        cell[above] = size + np.floor((coord[above] - size) / margin)
    # fmin / fmax rather than clip: NaN (no hit) becomes size + 1, beyond the outline
    return np.fmax(np.fmin(cell, np.float32(size + 1), out=cell), np.float32(-3), out=cell)


def _cell_start(cell: np.ndarray, size: int, margin: float) -> np.ndarray:
    """Coordinate (squares) of the line where cell ``cell`` (from `_cells`) starts."""
    if margin == 1.0:
        return cell
    return cell + (margin - 1) * (np.minimum(cell + 1, 0) + np.maximum(cell - size, 0))


@lru_cache(maxsize=8)
def _cell_grey_table(board: BoardSpec, background: float) -> np.ndarray:
    """(rows + 5, cols + 5) float32 grey level of cell (iv, iu) at [iv + 3, iu + 3] (cells as in `_cells`)."""
    iv, iu = np.mgrid[-3 : board.rows + 2, -3 : board.cols + 2]
    printed = (iu >= -2) & (iu <= board.cols) & (iv >= -2) & (iv <= board.rows)
    squares = (iu >= -1) & (iu < board.cols) & (iv >= -1) & (iv < board.rows)
    table = np.where(printed, np.float32(WHITE_LEVEL), np.float32(background))
    table[squares & ((iu + iv) & 1 == 0)] = BLACK_LEVEL  # floor(u) + floor(v) even: black
    table.setflags(write=False)
    return table


def _single_line(board: BoardSpec, uv0: np.ndarray, j_x: np.ndarray, j_y: np.ndarray,
                 background: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact mean grey (float32) of footprints inside one cell or crossed by one line, and True for those.

    Over the pixel ``[-1/2, 1/2]^2`` a coordinate is ``c0 + a x + b y``; with ``p >= q`` the larger and smaller of
    ``|a|, |b|`` and ``t`` the line's offset from ``c0``, the share of the pixel beyond the line is ``1/2 - t/p``
    while the line crosses two opposite sides (``|t| <= (p - q)/2``), else a corner triangle of area
    ``((p + q)/2 - |t|)^2 / (2 p q)``.
    """
    m = float(board.margin_squares)
    table = _cell_grey_table(board, background)
    reach = np.float32(0.5) * (np.abs(j_x) + np.abs(j_y))  # (E, 2) half extent of the footprint along u and v
    lo = [_cells(uv0[:, c] - reach[:, c], size, m) for c, size in enumerate((board.cols, board.rows))]
    hi = [_cells(uv0[:, c] + reach[:, c], size, m) for c, size in enumerate((board.cols, board.rows))]
    crossed = [hi[c] - lo[c] for c in range(2)]
    one_u, one_v = (crossed[0] == 1) & (crossed[1] == 0), (crossed[0] == 0) & (crossed[1] == 1)
    done = ((crossed[0] == 0) & (crossed[1] == 0)) | one_u | one_v
    c = np.where(one_v, 1, 0)  # the crossed axis (0 for footprints in one cell: no crossing, share 0)
    rows = np.arange(len(uv0))
    a, b = np.abs(j_x[rows, c]), np.abs(j_y[rows, c])
    p, q = np.maximum(a, b), np.minimum(a, b)
    line = np.where(one_v, _cell_start(hi[1], board.rows, m), _cell_start(hi[0], board.cols, m))
    t = line - uv0[rows, c]  # offset of the line from the pixel centre, board units
    half = np.float32(0.5) * (p + q)
    with np.errstate(divide="ignore", invalid="ignore"):
        corner = np.square(np.maximum(half - np.abs(t), 0)) / (2 * p * q)
        beyond = np.where(np.abs(t) <= np.float32(0.5) * (p - q), np.float32(0.5) - t / p,
                          np.where(t > 0, corner, 1 - corner))
    beyond = np.where(one_u | one_v, np.clip(beyond, 0, 1), 0).astype(np.float32)
    below = _cell_grey(table, lo[0], lo[1])
    above = _cell_grey(table, hi[0], hi[1])
    return below + beyond * (above - below), done


def _sub_rows(board: BoardSpec, uv0: np.ndarray, j_x: np.ndarray, j_y: np.ndarray, n: int,
              background: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact mean grey along n sub-rows of each pixel (float32), and True where that applies.

    Sub-row k runs from ``uv0 + o_k j_y - j_x / 2`` to ``+ j_x / 2`` (o_k the sub-row's offset in pixels). Along it
    the cell index changes by at most one along u and along v (else: False), at fractions t_u and t_v of its length
    (1 when it does not change): the pieces [0, t1], [t1, t2], [t2, 1] (t1 <= t2) each lie in one cell, whose grey
    level a lookup table gives.
    """
    offsets = ((np.arange(n) + 0.5) / n - 0.5).astype(np.float32)[None, :]
    m = float(board.margin_squares)
    ok = np.ones(len(uv0), dtype=bool)
    axes = []
    for c, size in enumerate((board.cols, board.rows)):  # u, then v: contiguous (E, n) arrays
        step = j_x[:, c, None]
        start = uv0[:, c, None] + offsets * j_y[:, c, None] - np.float32(0.5) * step
        first = _cells(start, size, m)
        last = _cells(start + step, size, m)
        ok &= np.all(np.abs(last - first) <= 1, axis=1)
        line = _cell_start(np.maximum(first, last), size, m)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(first != last, (line - start) / step, np.float32(1.0))
        axes.append((first, last, np.clip(t, 0.0, 1.0, out=t)))
    (first_u, last_u, t_u), (first_v, last_v, t_v) = axes
    t1, t2 = np.minimum(t_u, t_v), np.maximum(t_u, t_v)
    u_first = t_u < t_v  # the middle piece: past the first crossing, before the second
    table = _cell_grey_table(board, background)
    a, c = _cell_grey(table, first_u, first_v), _cell_grey(table, last_u, last_v)
    b = _cell_grey(table, np.where(u_first, last_u, first_u), np.where(u_first, first_v, last_v))
    # t1 a + (t2 - t1) b + (1 - t2) c
    mean = c + t1 * (a - b) + t2 * (b - c)
    return mean.mean(axis=1, dtype=np.float32), ok


def render_checkerboard_view(intrinsics: Intrinsics, image_size_px: tuple[int, int], view_T_board: np.ndarray,  # noqa: N803
                             board: BoardSpec, config: CheckerboardConfig, rng: np.random.Generator | None = None,
                             rays: ViewRays | None = None) -> np.ndarray:
    """Render one view of the board as an anti-aliased (H, W) uint8 image.

    Every pixel centre's ray (undistorted once per lens, `ViewRays`) is mapped to the board by the plane's
    homography (`cv2.perspectiveTransform`, only over the window of pixels that can see the board) and takes the
    colour there. Pixels whose 3x3 neighbourhood changes colour hold an edge and take their mean colour over their
    area, the lens and homography linearised inside the pixel (`_edge_pixels`). Blur and noise per ``config``.

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
            sub[ys, xs] = _edge_pixels(board, rays, rows, cols, uv, ys, xs, to_squares, n, config.background_level,
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
