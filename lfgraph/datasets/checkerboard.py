"""Synthetic checkerboard captures of a camera array: board poses, true corners, noisy corners, rendered images.

The renderer is exact up to the anti-aliasing: every pixel centre is undistorted through the view's lens model
(once per lens, `lfgraph.datasets.render.sample_rays`) and mapped to the board plane by its homography
(`cv2.perspectiveTransform`, only over the pixels that can see the board). Pixels whose 3x3 neighbourhood changes
colour hold an edge and are averaged over their area, with the undistortion linearised inside the pixel (its
curvature over half a pixel is far below 1e-4 px): exactly along each of N sub-rows (the colour is piecewise
constant between the crossings of square edges and outline), N x N point samples where that does not apply. All
other pixels take the colour at their centre.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from lfgraph.board import BoardSpec
from lfgraph.calibration import Calibration
from lfgraph.camera import Intrinsics, transform_points
from lfgraph.datasets.render import NEAR_PLANE_M, LensRays, clip_polygon_near, inverse_from_columns, sample_rays
from lfgraph.geometry import make_T, rotation_from_rotvec
from lfgraph.io_utils import atomic_path
from lfgraph.parallel import run_tasks

BLACK_LEVEL, WHITE_LEVEL = 30.0, 220.0
OUTLINE_SAMPLES_PER_EDGE = 24  # points per printed-board edge checked for visibility (edges bend under distortion)
MAX_POSE_TRIES = 2000
EDGE_WINDOW_MARGIN_PX = 2  # pixels around the board's footprint in its render window (3x3 edge test + rounding)
ANALYTIC_MAX_SQUARES_PER_PX = 0.5  # edge pixels integrated in closed form span less than this along a row
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
        supersample: N for the N sub-rows (N x N samples where sub-rows do not apply) of pixels on an edge.
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
class CheckerboardTruth:
    """Ground truth of a checkerboard capture.

    Attributes:
        board: the checkerboard.
        ref_T_board: (F, 4, 4) board pose in the reference view's frame per frame.
        corners_px: (V, F, C, 2) true corner projections (NaN behind a camera).
        corner_valid: (V, F, C) corner in front of the view and inside its image.
        board_visible: (V, F) the whole printed board is inside the view (where chessboard detection can work).
    """

    board: BoardSpec
    ref_T_board: np.ndarray
    corners_px: np.ndarray
    corner_valid: np.ndarray
    board_visible: np.ndarray

    def __post_init__(self) -> None:
        f = self.ref_T_board.shape[0]
        if self.ref_T_board.shape != (f, 4, 4):
            raise ValueError(f"ref_T_board must be (F, 4, 4), got {self.ref_T_board.shape}")
        v = self.corners_px.shape[0]
        c = self.board.num_corners
        if self.corners_px.shape != (v, f, c, 2):
            raise ValueError(f"corners_px must be ({v}, {f}, {c}, 2), got {self.corners_px.shape}")
        if self.corner_valid.shape != (v, f, c) or self.board_visible.shape != (v, f):
            raise ValueError(f"corner_valid must be ({v}, {f}, {c}) and board_visible ({v}, {f}), got "
                             f"{self.corner_valid.shape} and {self.board_visible.shape}")

    def save_npz(self, path: str | os.PathLike) -> None:
        """Write to ``.npz`` atomically."""
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(
                fh, board=np.array([self.board.cols, self.board.rows, self.board.square_m, self.board.margin_squares]),
                ref_T_board=self.ref_T_board, corners_px=self.corners_px, corner_valid=self.corner_valid,
                board_visible=self.board_visible)

    @classmethod
    def load_npz(cls, path: str | os.PathLike) -> CheckerboardTruth:
        """Read what `save_npz` wrote; raises ValueError naming the file on a missing key or bad shape."""
        try:
            with np.load(path) as data:
                missing = {"board", "ref_T_board", "corners_px", "corner_valid", "board_visible"} - set(data.files)
                if missing:
                    raise ValueError(f"{path}: missing arrays {sorted(missing)}")
                b = data["board"]
                if b.shape != (4,):
                    raise ValueError(f"{path}: board must hold 4 numbers (cols, rows, square_m, margin), got {b.shape}")
                board = BoardSpec(int(b[0]), int(b[1]), float(b[2]), float(b[3]))
                return cls(board, data["ref_T_board"], data["corners_px"], data["corner_valid"].astype(bool),
                           data["board_visible"].astype(bool))
        except (OSError, EOFError) as exc:
            raise ValueError(f"{path}: cannot read ground-truth corners ({exc})") from None
        except ValueError as exc:
            if str(exc).startswith(str(path)):
                raise
            raise ValueError(f"{path}: {exc}") from None


# ---------------------------------------------------------------------------------------------- geometry
def _outline_points(board: BoardSpec) -> np.ndarray:
    """(4 * OUTLINE_SAMPLES_PER_EDGE, 3) points along the printed board's outline, board frame."""
    corners = board.outline()
    t = np.linspace(0.0, 1.0, OUTLINE_SAMPLES_PER_EDGE, endpoint=False)[:, None]
    return np.concatenate([corners[i] + t * (corners[(i + 1) % 4] - corners[i]) for i in range(4)])


def _inside(px: np.ndarray, size: tuple[int, int], margin: float) -> np.ndarray:
    w, h = size
    with np.errstate(invalid="ignore"):
        return ((px[..., 0] >= margin) & (px[..., 0] <= w - 1 - margin)
                & (px[..., 1] >= margin) & (px[..., 1] <= h - 1 - margin))


def _board_faces_view(view_T_board: np.ndarray) -> bool:  # noqa: N803
    # The board's +z points into the board; the camera sees the printed side when that axis points away from it.
    return float(view_T_board[:3, 2] @ view_T_board[:3, 3]) > 0


def board_visible_in_view(intrinsics: Intrinsics, image_size_px: tuple[int, int], view_T_board: np.ndarray,  # noqa: N803
                          board: BoardSpec, margin_px: float) -> bool:
    """True when the whole printed board (outline sampled densely) lies inside the image and faces the view."""
    if not _board_faces_view(view_T_board):
        return False
    px = intrinsics.project(transform_points(view_T_board, _outline_points(board)))
    return bool(np.all(_inside(px, image_size_px, margin_px)))


def make_board_poses(calib: Calibration, config: CheckerboardConfig, rng: np.random.Generator) -> np.ndarray:
    """Board poses spread over the reference view's field of view.

    Frame f aims the board centre at a random point of image cell ``f mod cells^2`` (cells of the reference image),
    at a random distance in ``config.distance_m``, tilted by up to ``max_tilt_deg`` about a random in-plane axis
    and rolled by up to ``max_roll_deg``; poses are redrawn until the whole board is inside the reference view.

    Returns:
        (F, 4, 4) ``ref_T_board``.

    Raises:
        ValueError: no pose keeps the board inside the reference view (board too large for the distance range).
    """
    ref = calib.grid.reference
    intr = calib.intrinsics[ref]
    w, h = calib.image_size_px
    board = config.board
    centre_b = np.array([(board.cols - 1) * board.square_m / 2, (board.rows - 1) * board.square_m / 2, 0.0])
    n = config.coverage_cells
    order = rng.permutation(n * n)
    poses = np.zeros((config.frames, 4, 4))
    for f in range(config.frames):
        cell = order[f % (n * n)]
        cy_cell, cx_cell = divmod(int(cell), n)
        for attempt in range(MAX_POSE_TRIES):
            # After many failures (a corner cell the board cannot reach at this distance) widen towards the centre.
            shrink = min(1.0, attempt / 200.0)
            u = (cx_cell + rng.uniform(0.1, 0.9)) / n * w
            v = (cy_cell + rng.uniform(0.1, 0.9)) / n * h
            u, v = u + shrink * ((w - 1) / 2 - u), v + shrink * ((h - 1) / 2 - v)
            ray = intr.undistort(np.array([[u, v]]))[0]
            if not np.all(np.isfinite(ray)):
                continue
            z = rng.uniform(*config.distance_m)
            roll = np.radians(rng.uniform(-config.max_roll_deg, config.max_roll_deg))
            axis_angle = rng.uniform(0, 2 * np.pi)
            tilt = np.radians(config.max_tilt_deg) * np.sqrt(rng.uniform(0, 1))
            R = (rotation_from_rotvec(tilt * np.array([np.cos(axis_angle), np.sin(axis_angle), 0.0]))  # noqa: N806
                 @ rotation_from_rotvec([0.0, 0.0, roll]))
            centre = z * np.array([ray[0], ray[1], 1.0])
            ref_T_board = make_T(R, centre - R @ centre_b)  # noqa: N806
            if board_visible_in_view(intr, (w, h), ref_T_board, board, config.margin_px):
                poses[f] = ref_T_board
                break
        else:
            raise ValueError(f"could not place the {board} board inside the reference view at "
                             f"{config.distance_m} m; move it further away or use a smaller board")
    return poses


def make_checkerboard_truth(calib: Calibration, config: CheckerboardConfig, rng: np.random.Generator,
                            ref_T_board: np.ndarray | None = None) -> CheckerboardTruth:  # noqa: N803
    """Board poses (drawn unless given) and the true corner projections in every view. Seeded and pure."""
    poses = make_board_poses(calib, config, rng) if ref_T_board is None else np.asarray(ref_T_board, dtype=float)
    board = config.board
    obj = board.object_points()
    n_views, n_frames = calib.num_views, poses.shape[0]
    corners = np.full((n_views, n_frames, board.num_corners, 2), np.nan)
    visible = np.zeros((n_views, n_frames), dtype=bool)
    for v in range(n_views):
        view_T_ref = calib.view_T_ref(v)  # noqa: N806
        for f in range(n_frames):
            view_T_board = view_T_ref @ poses[f]  # noqa: N806
            if _board_faces_view(view_T_board):
                corners[v, f] = calib.intrinsics[v].project(transform_points(view_T_board, obj))
                visible[v, f] = board_visible_in_view(calib.intrinsics[v], calib.image_size_px, view_T_board, board,
                                                      config.margin_px)
    valid = _inside(corners, calib.image_size_px, 0.0)
    return CheckerboardTruth(board, poses, corners, valid, visible)


def make_corner_observations(truth: CheckerboardTruth, sigma_px: float, rng: np.random.Generator,
                             full_boards_only: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The corner-only variant: true projections plus Gaussian noise (for fast tests and Monte-Carlo studies).

    Args:
        truth: ground truth.
        sigma_px: noise std per coordinate, pixels.
        rng: random generator.
        full_boards_only: keep only view-frames where the whole board is visible (as chessboard detection does).

    Returns:
        corners_px (V, F, C, 2) with NaN where invalid, and valid (V, F, C).
    """
    valid = truth.corner_valid & (truth.board_visible[..., None] if full_boards_only else True)
    noisy = truth.corners_px + sigma_px * rng.standard_normal(truth.corners_px.shape)
    noisy[~valid] = np.nan
    return noisy, valid


# ---------------------------------------------------------------------------------------------- rendering
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
        img = cv2.GaussianBlur(img, (0, 0), config.blur_sigma_px)
    if rng is not None and config.noise_sigma > 0:
        noise = rng.standard_normal(img.shape)  # float64, the same stream as before issue 16
        noise *= config.noise_sigma
        noise += img
        img = noise
    np.rint(img, out=img)
    return np.clip(img, 0, 255, out=img).astype(np.uint8)


def iter_view_images(calib: Calibration, truth: CheckerboardTruth, config: CheckerboardConfig, seed: int,
                     view: int, frames: range | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """Yield ``(frame, image)`` for one view, reusing its rays. Noise is seeded by (seed, frame, view)."""
    intr = calib.intrinsics[view]
    rays = ViewRays.compute(intr, calib.image_size_px)
    view_T_ref = calib.view_T_ref(view)  # noqa: N806
    for f in frames if frames is not None else range(truth.ref_T_board.shape[0]):
        rng = np.random.default_rng([seed, f, view])
        yield f, render_checkerboard_view(intr, calib.image_size_px, view_T_ref @ truth.ref_T_board[f], truth.board,
                                          config, rng, rays)


def frame_name(frame: int) -> str:
    return f"{frame:03d}"


def _render_view_task(args: tuple) -> int:
    calib_json, truth_path, config, seed, view, out_dir = args
    import json

    calib = Calibration.from_dict(json.loads(calib_json))
    truth = CheckerboardTruth.load_npz(truth_path)
    name = calib.grid.name(view)
    for f, img in iter_view_images(calib, truth, config, seed, view):
        path = Path(out_dir) / frame_name(f) / f"{name}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            if not cv2.imwrite(str(tmp), img):
                raise OSError(f"could not write {path}")
    return view


def write_checkerboard_dataset(out_dir: str | os.PathLike, calib: Calibration, truth: CheckerboardTruth,
                               config: CheckerboardConfig, seed: int, layout: str = "folders", jobs: int | None = None,
                               progress: bool = True) -> None:
    """Render every view of every frame to ``out_dir`` with ``truth.json`` and ``truth_corners.npz``.

    Layouts: ``folders`` writes ``OUT/<frame>/rRR_cCC.png``; ``mosaic`` writes ``OUT/<frame>.png`` with the views
    tiled row-major. Images are rendered view by view in a process pool (each worker keeps one view's rays), every
    file is written atomically, and no more than one image per worker is held in memory (mosaics are assembled
    from per-view files afterwards). Output is identical for any ``jobs``.
    """
    if layout not in ("folders", "mosaic"):
        raise ValueError(f"layout must be 'folders' or 'mosaic', got {layout!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    truth_path = out / "truth_corners.npz"
    truth.save_npz(truth_path)
    render_dir = out if layout == "folders" else Path(tempfile.mkdtemp(prefix=".render-", dir=out))
    tasks = [(calib.to_json(), str(truth_path), config, seed, v, str(render_dir)) for v in range(calib.num_views)]
    try:
        run_tasks(_render_view_task, tasks, jobs, "rendering views", "view", progress)
        if layout == "mosaic":
            rows, cols = calib.grid.rows, calib.grid.cols
            w, h = calib.image_size_px
            for f in range(truth.ref_T_board.shape[0]):
                mosaic = np.zeros((rows * h, cols * w), dtype=np.uint8)
                for v in range(calib.num_views):
                    r, c = calib.grid.position(v)
                    mosaic[r * h : (r + 1) * h, c * w : (c + 1) * w] = cv2.imread(
                        str(render_dir / frame_name(f) / f"{calib.grid.name(v)}.png"), cv2.IMREAD_GRAYSCALE)
                with atomic_path(out / f"{frame_name(f)}.png") as tmp:
                    cv2.imwrite(str(tmp), mosaic)
    finally:
        if render_dir != out:
            shutil.rmtree(render_dir, ignore_errors=True)
    calib.save(out / "truth.json")
