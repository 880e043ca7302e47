"""The renderers as they were before issue 16, kept verbatim as the baseline of `benchmarks/render.py`.

Checkerboards: every pixel centre undistorted by Newton iteration and intersected with the board plane, pixels on an
edge supersampled N x N. Scenes: every sub-pixel sample undistorted by Newton iteration and cast against every quad.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from lfgraph.core.camera import Intrinsics
from lfgraph.datasets.board_render import BLACK_LEVEL, WHITE_LEVEL
from lfgraph.datasets.checkerboard import CheckerboardConfig
from lfgraph.datasets.scene import Scene, SceneConfig
from lfgraph.detect.board import BoardSpec


@dataclass(frozen=True)
class ViewRays:
    """Per-pixel undistorted normalised coordinates of one view and their derivative along x and y (per pixel)."""

    xy: np.ndarray  # (H, W, 2)
    d_dx: np.ndarray  # (H, W, 2)
    d_dy: np.ndarray  # (H, W, 2)

    @classmethod
    def compute(cls, intrinsics: Intrinsics, image_size_px: tuple[int, int]) -> ViewRays:
        w, h = image_size_px
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        xy = intrinsics.undistort(np.column_stack([u.ravel(), v.ravel()])).reshape(h, w, 2)
        d_dy, d_dx = np.gradient(xy, axis=(0, 1))
        return cls(xy, d_dx, d_dy)


def _board_colour(board: BoardSpec, H_inv: np.ndarray, xy: np.ndarray, background: float) -> np.ndarray:  # noqa: N803
    """Grey level of the scene along normalised rays ``xy`` (..., 2), given ``H_inv`` mapping rays to the board."""
    x, y = xy[..., 0], xy[..., 1]
    bx = H_inv[0, 0] * x + H_inv[0, 1] * y + H_inv[0, 2]
    by = H_inv[1, 0] * x + H_inv[1, 1] * y + H_inv[1, 2]
    bw = H_inv[2, 0] * x + H_inv[2, 1] * y + H_inv[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = bx / bw / board.square_m
        v = by / bw / board.square_m
    m = board.margin_squares
    in_front = bw > 0
    on_board = in_front & (u >= -1 - m) & (u <= board.cols + m) & (v >= -1 - m) & (v <= board.rows + m)
    in_squares = on_board & (u >= -1) & (u < board.cols) & (v >= -1) & (v < board.rows)
    black = in_squares & ((np.floor(u) + np.floor(v)) % 2 == 0)
    out = np.full(x.shape, background)
    out[on_board] = WHITE_LEVEL
    out[black] = BLACK_LEVEL
    return out


def render_checkerboard_view_reference(intrinsics: Intrinsics, image_size_px: tuple[int, int],  # noqa: N803
                                       view_T_board: np.ndarray, board: BoardSpec, config: CheckerboardConfig,
                                       rng: np.random.Generator | None = None,
                                       rays: ViewRays | None = None) -> np.ndarray:
    """Render one view of the board as an anti-aliased (H, W) uint8 image.

    Args:
        intrinsics: the view's lens.
        image_size_px: (width, height).
        view_T_board: (4, 4) board pose in the view frame.
        board: the checkerboard.
        config: blur, noise, background, supersampling.
        rng: noise source (None = no noise even if ``config.noise_sigma`` > 0).
        rays: the view's precomputed `ViewRays` (computed when None; pass them when rendering many frames).
    """
    rays = rays or ViewRays.compute(intrinsics, image_size_px)
    H = np.column_stack([view_T_board[:3, 0], view_T_board[:3, 1], view_T_board[:3, 3]])  # noqa: N806
    H_inv = np.linalg.inv(H)  # noqa: N806
    img = _board_colour(board, H_inv, rays.xy, config.background_level)
    # Pixels whose 3x3 neighbourhood is not one colour hold an edge: supersample them.
    pad = np.pad(img, 1, mode="edge")
    lo = np.minimum.reduce([pad[1 + dy : pad.shape[0] - 1 + dy, 1 + dx : pad.shape[1] - 1 + dx]
                            for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    hi = np.maximum.reduce([pad[1 + dy : pad.shape[0] - 1 + dy, 1 + dx : pad.shape[1] - 1 + dx]
                            for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    ys, xs = np.nonzero(hi > lo)
    n = config.supersample
    if len(ys) and n > 1:
        offsets = (np.arange(n) + 0.5) / n - 0.5
        ox, oy = np.meshgrid(offsets, offsets)
        ox, oy = ox.ravel(), oy.ravel()
        base = rays.xy[ys, xs][:, None, :]
        sub = (base + rays.d_dx[ys, xs][:, None, :] * ox[None, :, None]
               + rays.d_dy[ys, xs][:, None, :] * oy[None, :, None])
        img[ys, xs] = _board_colour(board, H_inv, sub, config.background_level).mean(axis=1)
    if config.blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), config.blur_sigma_px)
    if rng is not None and config.noise_sigma > 0:
        img = img + config.noise_sigma * rng.standard_normal(img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)




def _bilinear(texture: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear texture lookup at texel coordinates (x, y), edges replicated."""
    th, tw = texture.shape
    x = np.clip(x, 0, tw - 1)
    y = np.clip(y, 0, th - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), tw - 2)
    y0 = np.minimum(np.floor(y).astype(np.int64), th - 2)
    fx, fy = x - x0, y - y0
    t = texture.astype(np.float32)
    top = t[y0, x0] * (1 - fx) + t[y0, x0 + 1] * fx
    bottom = t[y0 + 1, x0] * (1 - fx) + t[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


def _cast(scene: Scene, view_T_ref: np.ndarray, xy: np.ndarray, want_texture: bool):  # noqa: N803
    """Ray-cast normalised rays ``xy`` (N, 2) of a view: returns depth (N,) and grey level (N,) (NaN: no hit)."""
    n = xy.shape[0]
    depth = np.full(n, np.inf)
    grey = np.full(n, np.nan)
    d = np.column_stack([xy, np.ones(n)])
    R, t = view_T_ref[:3, :3], view_T_ref[:3, 3]  # noqa: N806
    for q in scene.quads:
        c = R @ q.centre + t
        a, b = R @ q.axis_u, R @ q.axis_v
        normal = np.cross(a, b)
        denom = d @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (c @ normal) / denom  # ray parameter = depth, as d_z = 1
            p = d * lam[:, None] - c
            s = (p @ a) / (a @ a)
            u = (p @ b) / (b @ b)
            hit = (lam > 0) & (np.abs(s) <= 1) & (np.abs(u) <= 1) & (lam < depth)
        if not np.any(hit):
            continue
        depth[hit] = lam[hit]
        if want_texture:
            th, tw = q.texture.shape
            mx = (s[hit] + 1) / 2 * tw - 0.5  # texel centres at (k + 0.5) / tw
            my = (u[hit] + 1) / 2 * th - 0.5
            grey[hit] = _bilinear(q.texture, mx, my)
    depth[~np.isfinite(depth)] = np.nan
    return depth, grey


def render_scene_depth_reference(scene: Scene, intrinsics: Intrinsics, image_size_px: tuple[int, int],
                       view_T_ref: np.ndarray) -> np.ndarray:  # noqa: N803
    """(H, W) depth (z in the view frame, metres) at pixel centres; NaN where no surface is hit."""
    w, h = image_size_px
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    xy = intrinsics.undistort(np.column_stack([u.ravel(), v.ravel()]))
    depth, _ = _cast(scene, view_T_ref, xy, want_texture=False)
    return depth.reshape(h, w)


def render_scene_view_reference(scene: Scene, intrinsics: Intrinsics, image_size_px: tuple[int, int],
                                view_T_ref: np.ndarray, config: SceneConfig,  # noqa: N803
                                rng: np.random.Generator | None = None) -> np.ndarray:
    """Render one view as (H, W) uint8, supersampled; blur and noise per ``config`` (noise only with ``rng``)."""
    w, h = image_size_px
    n = config.supersample
    offsets = (np.arange(n) + 0.5) / n - 0.5
    u = (np.arange(w)[None, :, None, None] + offsets[None, None, None, :]) + 0 * offsets[None, None, :, None]
    v = (np.arange(h)[:, None, None, None] + offsets[None, None, :, None]) + 0 * offsets[None, None, None, :]
    u, v = np.broadcast_arrays(u, v)
    xy = intrinsics.undistort(np.column_stack([u.ravel(), v.ravel()]))
    _, grey = _cast(scene, view_T_ref, xy, want_texture=True)
    grey = np.nan_to_num(grey, nan=0.0).reshape(h, w, n * n).mean(axis=2)
    if config.blur_sigma_px > 0:
        grey = cv2.GaussianBlur(grey, (0, 0), config.blur_sigma_px)
    if rng is not None and config.noise_sigma > 0:
        grey = grey + config.noise_sigma * rng.standard_normal(grey.shape)
    return np.clip(np.rint(grey), 0, 255).astype(np.uint8)


