"""A second checkerboard pass for wide (fisheye) views: boards the first pass (`detect_board`) missed or got wrong,
looked for again in a virtual pinhole turned towards them.

Why: near the edge of a wide fisheye a board is squeezed twice, by the lens (an equidistant lens shrinks it radially
by cos^2 of the angle against a pinhole) and by foreshortening (boards there are seen 63-85 deg off their normal), so
findChessboardCorners and the SB fallback both find nothing, or SB returns a corner slipped by a square that the
median-normalised off-grid check lets through (rendered ``fisheye-1x3``: 33 of 72 boards missed, one corner 8.8 px
off).

How: per view, a rough fisheye model from the first pass's boards (`fit_rough_fisheye`; a board it cannot explain is
flagged). Then, for each image without a trustworthy board, the image is resampled into a virtual pinhole at the same
centre turned towards where the board should be, with the focal length that fits the board's angular size
(`turned_pinhole`, `virtual_view`); there the board is a plain perspective grid, magnified. The first pass's locate,
order and sub-pixel steps run unchanged on it; corners go back through the same model. Where to look: a flagged
board's own corners, the same frame's board in the other views (near-parallel rigs), the image's strongest saddle
points (`saddle_probe`). The first pass's good boards are refined again in a virtual pinhole turned towards each.
Views no wider than `WIDE_MIN_HALF_DIAGONAL_DEG` are not touched: pinhole captures come out exactly as the first pass
made them. Measured on ``fisheye-1x3`` (seed 0): 39 -> 54 of 72 boards, worst corner 8.8 -> 0.34 px, median corner
error 0.023 -> 0.006 px; the boards still missed are seen 75-85 deg off their normal.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from lfgraph.core.camera import Intrinsics, pinhole_to_view_px, view_to_pinhole_px
from lfgraph.detect.board import BoardSpec
from lfgraph.detect.chessboard import _canonical_order, _locate_board, _refine_corners

WIDE_MIN_HALF_DIAGONAL_DEG = 60.0  # second pass only for views seeing further off-axis at the image corners, deg
#                                    (pinhole scenes: 34-41 deg; OpenCV's ~80 deg OneLine lenses: ~40; fisheye-1x3: ~83)
VIRTUAL_ATTEMPTS = ((640, 0.7), (960, 0.9))  # (virtual image side px, board angular radius / half field), in turn
MAX_VIRTUAL_HALF_FOV_DEG = 75.0  # widest half field of a virtual pinhole, deg
RING_SAMPLES = 8  # points on the saddle probe's circle whose rays give the probed board's angular radius
PROBE_SIGMA_PX = 1.5  # Gaussian scale of the probe's Hessian: corners of squares from ~4 px
PROBE_MIN_SHARE = 0.25  # probe keeps pixels whose saddle response is >= this share of the image's strongest
PROBE_SPREAD_QUANTILE = 0.95  # probed board radius: this quantile of the kept pixels' distances from their median
ROUGH_MIN_BOARDS = 4  # first-pass boards a view needs for its rough model
ROUGH_MAX_BOARDS = 24  # boards (spread over the view's frames) the rough model is fitted to; the rest are checked
# k1, k2 only: k3, k4 add nothing a rough model needs and wander (k3 = 0.027 with a bad board in)
ROUGH_FLAGS = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_K4
ROUGH_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)
MODEL_MAX_CORNER_PX = 1.0  # a board with a corner further than this from its best pose under the model is wrong
#                            (fisheye-1x3: good boards <= 0.33 px, slipped corners 2.1 and 7.1 px)
MODEL_SWAP_MIN_PX = 0.25  # a corner refined in the virtual view this far from the model may take the original's


# ------------------------------------------------------------------------------------------ virtual pinhole
def turned_pinhole(direction: np.ndarray, half_fov: float, side_px: int) -> tuple[np.ndarray, np.ndarray]:
    """(R, K): rotation whose columns are the virtual camera's axes in the view frame (z along ``direction``, x as
    near the view's x as possible) and the camera matrix of a ``side_px`` square image with half field ``half_fov``
    (rad)."""
    z = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z])  # noqa: N806
    f, c = (side_px / 2) / np.tan(half_fov), (side_px - 1) / 2
    return R, np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])


def virtual_view(gray: np.ndarray, intr: Intrinsics, R: np.ndarray, K: np.ndarray,  # noqa: N803
                 side_px: int) -> np.ndarray:
    """The image resampled (bilinear) into the virtual pinhole; what the view does not see is its median grey."""
    i = np.arange(side_px, dtype=np.float64)
    uu, vv = np.meshgrid(i, i)
    src = pinhole_to_view_px(np.column_stack([uu.ravel(), vv.ravel()]), K, R.T, intr).reshape(side_px, side_px, 2)
    src = np.nan_to_num(src, nan=-1e6).astype(np.float32)
    return cv2.remap(gray, src[..., 0], src[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=float(np.median(gray)))


# ------------------------------------------------------------------------------------------ where to look
def _rays(intr: Intrinsics, px: np.ndarray) -> np.ndarray:
    """(N, 3) unit rays of pixels (NaN rows where the model has no inverse)."""
    xy = intr.undistort(np.asarray(px, dtype=np.float64).reshape(-1, 2))
    r = np.column_stack([xy, np.ones(len(xy))])
    return r / np.linalg.norm(r, axis=1, keepdims=True)


def _cone(rays: np.ndarray) -> tuple[np.ndarray, float] | None:
    """(unit axis, half angle rad) of the cone about the rays' mean that holds them all; None without rays."""
    rays = rays[np.all(np.isfinite(rays), axis=1)]
    if len(rays) == 0:
        return None
    d = rays.mean(axis=0) / np.linalg.norm(rays.mean(axis=0))
    return d, float(np.max(np.arccos(np.clip(rays @ d, -1.0, 1.0))))


def half_diagonal_deg(intr: Intrinsics, image_size_px: tuple[int, int]) -> float:
    """Largest angle off the axis of the rays through the image corners, deg (90 beyond the model's reach)."""
    w, h = image_size_px
    rays = _rays(intr, [[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]])
    return float(np.degrees(np.max(np.arccos(rays[:, 2])))) if np.all(np.isfinite(rays)) else 90.0


def saddle_probe(gray: np.ndarray) -> tuple[np.ndarray, float] | None:
    """(centre (2,), radius) px of the image's strongest saddle points (-det Hessian > 0: a checkerboard's corners),
    or None without saddles. Median centre: a few saddles elsewhere do not move it."""
    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), PROBE_SIGMA_PX)
    gxx, gyy = cv2.Sobel(g, cv2.CV_32F, 2, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 2, ksize=3)
    gxy = cv2.Sobel(g, cv2.CV_32F, 1, 1, ksize=3)
    s = np.maximum(gxy * gxy - gxx * gyy, 0.0)
    if float(s.max()) <= 0:
        return None
    ys, xs = np.nonzero(s >= PROBE_MIN_SHARE * float(s.max()))
    pts = np.column_stack([xs, ys]).astype(np.float64)
    centre = np.median(pts, axis=0)
    return centre, float(np.quantile(np.linalg.norm(pts - centre, axis=1), PROBE_SPREAD_QUANTILE))


def _probe_cone(gray: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, float] | None:
    """The cone of rays through the saddle probe's centre holding its circle."""
    probe = saddle_probe(gray)
    if probe is None:
        return None
    a = np.linspace(0, 2 * np.pi, RING_SAMPLES, endpoint=False)
    rays = _rays(intr, np.vstack([probe[0], probe[0] + probe[1] * np.column_stack([np.cos(a), np.sin(a)])]))
    ring = _cone(rays[1:])
    return None if ring is None or not np.all(np.isfinite(rays[0])) else (rays[0], ring[1])


# ------------------------------------------------------------------------------------------ rough lens model
def _obj(board: BoardSpec) -> np.ndarray:
    return board.object_points().reshape(1, -1, 3).astype(np.float64)


def board_residuals_px(corners: np.ndarray, board: BoardSpec, intr: Intrinsics) -> np.ndarray:
    """(C,) px distances of the corners from the board's best pose under the fisheye model (PnP, reprojection)."""
    obj, K, D = _obj(board), intr.K, intr.dist_cv  # noqa: N806
    ok, rvec, tvec = cv2.fisheye.solvePnP(obj, corners.reshape(1, -1, 2).astype(np.float64), K, D)
    if not ok:
        return np.full(len(corners), np.inf)
    return np.linalg.norm(cv2.fisheye.projectPoints(obj, rvec, tvec, K, D)[0][0] - corners, axis=1)


def fit_rough_fisheye(boards: list[np.ndarray], board: BoardSpec,
                      image_size_px: tuple[int, int]) -> tuple[Intrinsics, list[int]] | None:
    """A fisheye `Intrinsics` fitted to one view's first-pass boards ((C, 2) each) and the indices of the boards it
    cannot explain (a corner > `MODEL_MAX_CORNER_PX` from the board's fitted pose; dropped worst first, refitting
    after each); None with too few boards or a failed fit."""
    keep = list(range(len(boards)))
    while len(keep) >= ROUGH_MIN_BOARDS:
        try:
            _, K, D, rvecs, tvecs = cv2.fisheye.calibrate(  # noqa: N806
                [_obj(board)] * len(keep), [boards[i].reshape(1, -1, 2).astype(np.float64) for i in keep],
                image_size_px, None, None, flags=ROUGH_FLAGS, criteria=ROUGH_CRITERIA)
        except cv2.error:
            return None
        worst = [float(np.max(np.linalg.norm(cv2.fisheye.projectPoints(_obj(board), r, t, K, D)[0][0] - boards[i],
                                             axis=1))) for i, r, t in zip(keep, rvecs, tvecs, strict=True)]
        j = int(np.argmax(worst))
        if worst[j] <= MODEL_MAX_CORNER_PX:
            d = D.ravel()
            intr = Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], d[0], d[1], k3=d[2], k4=d[3], lens="fisheye")
            return intr, [i for i in range(len(boards)) if i not in keep]
        keep.pop(j)
    return None


# ------------------------------------------------------------------------------------------ detection
def refine_turned(gray: np.ndarray, virt: np.ndarray, board: BoardSpec, intr: Intrinsics, R: np.ndarray,  # noqa: N803
                  K: np.ndarray, start: np.ndarray) -> np.ndarray:  # noqa: N803
    """(C, 2) view pixels: ``start`` (virtual px, board order) refined in the virtual view by `_refine_corners`,
    mapped back. A corner the model puts further than `MODEL_SWAP_MIN_PX` away takes the original image's
    refinement instead where that agrees better with the model (at the far end of very oblique boards the
    magnified virtual view is too blurred for the small windows the grid allows)."""
    out = pinhole_to_view_px(_refine_corners(virt, start.astype(np.float32), board), K, R.T, intr)
    res = board_residuals_px(out, board, intr)
    if np.max(res) <= MODEL_SWAP_MIN_PX or not np.all(np.isfinite(out)):
        return out
    other = _refine_corners(gray, out.astype(np.float32), board)
    swap = (res > MODEL_SWAP_MIN_PX) & (board_residuals_px(other, board, intr) < res)
    return np.where(swap[:, None], other, out)


def detect_turned(gray: np.ndarray, board: BoardSpec, intr: Intrinsics,
                  cone: tuple[np.ndarray, float]) -> np.ndarray | None:
    """The board (C, 2, view px, `BoardSpec` order) located in a virtual pinhole turned along the cone's axis with
    the cone filling `VIRTUAL_ATTEMPTS`' share of its field, refined (`refine_turned`) and checked against the
    model (every corner within `MODEL_MAX_CORNER_PX` of the board's best pose); None if no attempt passes."""
    for side, fill in VIRTUAL_ATTEMPTS:
        half_fov = min(np.arctan(np.tan(cone[1]) / fill), np.radians(MAX_VIRTUAL_HALF_FOV_DEG))
        R, K = turned_pinhole(cone[0], half_fov, side)  # noqa: N806
        virt = virtual_view(gray, intr, R, K, side)
        located = _locate_board(virt, board)
        if located is None:
            continue
        start = _canonical_order(virt, located.astype(np.float64), board)
        corners = refine_turned(gray, virt, board, intr, R, K, start)
        if np.all(np.isfinite(corners)) and np.max(board_residuals_px(corners, board, intr)) <= MODEL_MAX_CORNER_PX:
            return corners
    return None


def rerefine_turned(gray: np.ndarray, board: BoardSpec, intr: Intrinsics, corners: np.ndarray) -> np.ndarray:
    """A first-pass board (C, 2) refined again in the first virtual pinhole of `VIRTUAL_ATTEMPTS` turned towards
    it (no new locate: its corners are mapped in); the first pass's corners if that fails the model check."""
    side, fill = VIRTUAL_ATTEMPTS[0]
    cone = _cone(_rays(intr, corners))
    if cone is None:
        return corners
    half_fov = min(np.arctan(np.tan(cone[1]) / fill), np.radians(MAX_VIRTUAL_HALF_FOV_DEG))
    R, K = turned_pinhole(cone[0], half_fov, side)  # noqa: N806
    out = refine_turned(gray, virtual_view(gray, intr, R, K, side), board, intr, R, K,
                        view_to_pinhole_px(corners, K, R.T, intr))
    ok = np.all(np.isfinite(out)) and np.max(board_residuals_px(out, board, intr)) <= MODEL_MAX_CORNER_PX
    return out if ok else corners


# ------------------------------------------------------------------------------------------ the pass
@dataclass
class WidePassReport:
    """What the second pass did, in view-frames.

    Attributes:
        wide_views: the views whose rough model is wide enough for the pass.
        flagged: first-pass boards their view's rough model could not explain (a corner > `MODEL_MAX_CORNER_PX`).
        recovered: flagged or missed boards found in a turned virtual pinhole.
        dropped: flagged boards not found again (left out).
        rerefined: good first-pass boards whose corners the turned view refined again.
    """

    wide_views: tuple[int, ...] = ()
    flagged: int = 0
    recovered: int = 0
    dropped: int = 0
    rerefined: int = 0
    models: list[Intrinsics | None] = field(default_factory=list, repr=False)


def rough_model(corners: np.ndarray, board: BoardSpec, image_size_px: tuple[int, int]
                ) -> tuple[Intrinsics, np.ndarray] | None:
    """A wide view's rough fisheye model from its first-pass boards and the frames it cannot explain.

    Args:
        corners: (F, C, 2) one view's first-pass corners, NaN where no board.
        board: the board.
        image_size_px: the view's (width, height).

    Returns:
        (model, flagged frame indices), or None when the view has too few boards, the fit fails or the model is no
        wider than `WIDE_MIN_HALF_DIAGONAL_DEG` (a pinhole view: nothing to do).
    """
    frames = np.flatnonzero(np.all(np.isfinite(corners), axis=(1, 2)))
    sample = frames[np.unique(np.linspace(0, len(frames) - 1, min(len(frames), ROUGH_MAX_BOARDS)).astype(int))] \
        if len(frames) else frames
    fit = fit_rough_fisheye([corners[f] for f in sample], board, image_size_px)
    if fit is None or half_diagonal_deg(fit[0], image_size_px) < WIDE_MIN_HALF_DIAGONAL_DEG:
        return None
    intr, unexplained = fit
    rest = np.setdiff1d(frames, sample)
    bad = [f for f in rest if np.max(board_residuals_px(corners[f], board, intr)) > MODEL_MAX_CORNER_PX]
    return intr, np.sort(np.concatenate([sample[unexplained], np.asarray(bad, dtype=int)])).astype(int)


@dataclass(frozen=True)
class WideModels:
    """Each view's rough fisheye model (None: not a wide view) and the first-pass boards it flags, (V, F) bool."""

    models: tuple[Intrinsics | None, ...]
    flagged: np.ndarray

    @property
    def wide_views(self) -> tuple[int, ...]:
        """The views the second pass looks at again."""
        return tuple(v for v, m in enumerate(self.models) if m is not None)


def wide_models(first: np.ndarray, board: BoardSpec, sizes: Sequence[tuple[int, int]]) -> WideModels:
    """`rough_model` of every view of the (V, F, C, 2) first-pass corners; ``sizes`` (V,) (width, height), px."""
    fits = [rough_model(first[v], board, sizes[v]) for v in range(first.shape[0])]
    flagged = np.zeros(first.shape[:2], dtype=bool)
    for v, fit in enumerate(fits):
        if fit is not None:
            flagged[v, fit[1]] = True
    return WideModels(tuple(None if fit is None else fit[0] for fit in fits), flagged)


def frame_pass(images: dict[int, np.ndarray], board: BoardSpec, wide: WideModels, first: np.ndarray,
               frame: int) -> tuple[np.ndarray, np.ndarray]:
    """One frame's second pass (frames are independent: `lfgraph.detect.detections` runs one per task on its pool).

    Args:
        images: each wide view's (H, W) uint8 grayscale image of this frame.
        first: (V, C, 2) this frame's first-pass corners.

    Returns:
        (V, C, 2) corners (NaN where no board) and the counts (flagged, recovered, dropped, rerefined).
    """
    out = first.copy()
    found = np.all(np.isfinite(first), axis=(1, 2))
    counts = np.zeros(4, dtype=int)
    for v in (v for v in wide.wide_views if found[v]):  # refined again, or looked for again if flagged
        intr = wide.models[v]
        if wide.flagged[v, frame]:
            cone = _cone(_rays(intr, first[v]))
            corners = None if cone is None else detect_turned(images[v], board, intr, cone)
            out[v], found[v] = (np.nan, False) if corners is None else (corners, True)
            counts[:3] += (1, corners is not None, corners is None)
        else:
            out[v] = rerefine_turned(images[v], board, intr, first[v])
            counts[3] += int(not np.array_equal(out[v], first[v]))
    for v in (v for v in wide.wide_views if not found[v]):  # missed: where the other views saw it, or saddles say
        corners = _look_again(images[v], board, v, out, found, wide.models)
        if corners is not None:
            out[v], found[v] = corners, True
            counts[1] += 1
    return out, counts


def pass_report(wide: WideModels, counts: np.ndarray) -> WidePassReport:
    """The `WidePassReport` of summed `frame_pass` counts."""
    return WidePassReport(wide.wide_views, *(int(c) for c in counts), models=list(wide.models))


def _look_again(gray: np.ndarray, board: BoardSpec, v: int, corners: np.ndarray, found: np.ndarray,
                models: Sequence[Intrinsics | None]) -> np.ndarray | None:
    """A missed board of view ``v``, looked for towards the other wide views' boards of the same frame ((V, C, 2)
    ``corners``, (V,) ``found``), then towards the image's strongest saddle points; None if no turned view finds it."""
    cones = [_cone(_rays(models[u], corners[u])) for u in range(len(models))
             if u != v and models[u] is not None and found[u]] + [_probe_cone(gray, models[v])]
    for cone in (c for c in cones if c is not None):
        located = detect_turned(gray, board, models[v], cone)
        if located is not None:
            return located
    return None
