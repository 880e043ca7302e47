"""Chain matching through the grid (paper Section 4.1): Shi–Tomasi in the reference view, pyramidal KLT from view to
view along the paper's chain, the duplicate filter, and fundamental-matrix RANSAC between adjacent views."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from lfgraph.core.grid import ViewGrid

DUPLICATE_PX = float(np.sqrt(2.0))  # the paper's duplicate filter: features closer than sqrt(2) px are one


@dataclass(frozen=True)
class MatchSettings:
    """Feature detection and tracking options.

    Attributes:
        max_features: Shi–Tomasi corners kept in the reference view.
        quality_level: Shi–Tomasi quality relative to the best corner.
        min_distance_px: minimum spacing of detected corners.
        block_size_px: Shi–Tomasi structure-tensor window.
        klt_window_px: KLT window side; klt_levels: pyramid levels above the image.
        ransac_threshold_px: distance to the epipolar line for a fundamental-matrix inlier.
        ransac_confidence: RANSAC confidence.
        min_views: keep tracks seen in at least this many views (None = all views, the paper's rule).
        forward_backward_px: track each step back and drop points that do not return within this distance
            (None: off). Chain tracking through 24 steps of an occluding scene otherwise keeps ~1/3 wrong tracks.
        anchor_px: after the chain, re-track every view from the reference patch (started at the chain's
            estimate) and drop points that move more than this (None: keep the chained positions). Measured on
            paper-5x5 (4 frames): transfer error at infinity 0.024-0.035 px with it, 0.015-0.089 px without.
        unique_margin: the repeated-texture filter (None: off). A track is dropped when its reference patch
            (``klt_window_px`` square) matches another place within ``unique_radius_px`` no worse than
            ``unique_margin`` (NCC) below its worst match in the other views, at a peak of its own (separated by a
            valley of `UNIQUE_VALLEY`): on a periodic texture KLT locks whole periods off, every patch matches at
            NCC > 0.99, and when most tracks lock alike no later filter sees it (issue 24's sweep, keyboard
            texture: 250 of 1007 tracks of a pair and 654 of 659 of a 3x1 line were wrong).
        unique_radius_px: how far the repeated-texture filter looks: the periods that locked KLT's 3-level
            pyramid in the sweep were 30-60 px, in any direction (knocked views are not rectified).
        deep_klt_levels: when the chain follows fewer than `DEEP_RETRY_SHARE` of the detected features through
            the grid, the frame is tracked again with this many pyramid levels and the run that follows more is kept
            (a knock larger than the pyramid's reach: a 4 deg knock of paper-5x5's cameras in a 3x3 kept 1 % with
            3 levels, 34 % with 5; None: never).
    """

    max_features: int = 2000
    quality_level: float = 0.005
    min_distance_px: float = 5.0
    block_size_px: int = 7
    klt_window_px: int = 15
    klt_levels: int = 3  # 2 lost ~40 % more tracks on paper-5x5 (35 px steps) even with the initial-flow guess
    ransac_threshold_px: float = 1.0
    ransac_confidence: float = 0.999
    min_views: int | None = None
    forward_backward_px: float | None = 0.5
    anchor_px: float | None = 1.0
    unique_margin: float | None = 0.02
    unique_radius_px: int = 64
    deep_klt_levels: int | None = 5


DEEP_RETRY_SHARE = 0.05  # as the refinement's warning (`schedule.CHAIN_WARN`): below it the tracker has lost the grid


@dataclass(frozen=True)
class Tracks:
    """Features tracked through the grid.

    Attributes:
        points_px: (V, N, 2) positions in the original views (NaN where lost).
        valid: (V, N) where each track is seen.
        counts: tracks left after each filter, in order (``detected``, ``chain``, ``dedup``, ``ransac``, ``unique``).
    """

    points_px: np.ndarray
    valid: np.ndarray
    counts: dict[str, int] = field(default_factory=dict)

    @property
    def num_tracks(self) -> int:
        """Number of tracks (N)."""
        return self.points_px.shape[1]

    def subset(self, keep: np.ndarray) -> Tracks:
        """The tracks where ``keep`` (N,) is set, with the same filter counts."""
        return Tracks(self.points_px[:, keep], self.valid[:, keep], dict(self.counts))


def _duplicates(points: np.ndarray, alive: np.ndarray, radius: float) -> np.ndarray:
    """Bool mask of tracks (among ``alive``) lying within ``radius`` of an earlier alive track."""
    idx = np.nonzero(alive)[0]
    out = np.zeros(len(points), dtype=bool)
    if len(idx) < 2:
        return out
    p = points[idx].astype(np.float32)
    order = np.argsort(p[:, 0], kind="stable")
    ps = p[order]
    dup_sorted = np.zeros(len(ps), dtype=bool)
    # compare each point with the following ones whose x is within the radius (sorted sweep, vectorised per lag)
    lag = 1
    while lag < len(ps):
        dx = ps[lag:, 0] - ps[:-lag, 0]
        if not np.any(dx <= radius):
            break
        close = (dx <= radius) & (np.hypot(dx, ps[lag:, 1] - ps[:-lag, 1]) < radius)
        dup_sorted[lag:] |= close & ~dup_sorted[:-lag]
        lag += 1
    out[idx[order]] = dup_sorted
    return out


def _step_guess(previous: np.ndarray | None, idx: np.ndarray) -> np.ndarray:
    """(len(idx), 2) KLT start offsets: each track's previous step in the same grid direction (its median where a
    track has none; zeros before the first step in that direction)."""
    if previous is None:
        return np.zeros((len(idx), 2))
    known = previous[idx]
    has = np.all(np.isfinite(known), axis=1)
    return np.where(has[:, None], known, np.nan_to_num(np.nanmedian(previous, axis=0))[None])


def _klt_step(image_a: np.ndarray, image_b: np.ndarray, from_px: np.ndarray, start_px: np.ndarray, s: MatchSettings,
              win: tuple, criteria: tuple) -> tuple[np.ndarray, np.ndarray]:
    """One chain step: (N, 2) points of ``image_a`` tracked into ``image_b`` from ``start_px``; returns their (N, 2)
    positions and where they held (KLT's status, inside the image and, with ``s.forward_backward_px``, back within
    it of where they came from). The check runs back only from the points whose forward track held: KLT follows
    every point on its own, so the answer is that of tracking all back, for fewer points."""
    p0 = from_px.astype(np.float32).reshape(-1, 1, 2)
    p1, status, _ = cv2.calcOpticalFlowPyrLK(image_a, image_b, p0, start_px.astype(np.float32).reshape(-1, 1, 2),
                                             winSize=win, maxLevel=s.klt_levels, criteria=criteria,
                                             flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    out = p1.reshape(-1, 2).astype(np.float64)
    h, w = image_b.shape[:2]
    ok = (status.ravel() == 1) & (out[:, 0] >= 0) & (out[:, 0] <= w - 1) & (out[:, 1] >= 0) & (out[:, 1] <= h - 1)
    back_idx = np.nonzero(ok)[0]
    if s.forward_backward_px is not None and len(back_idx):
        p0b, status_b, _ = cv2.calcOpticalFlowPyrLK(image_b, image_a, p1[back_idx], p0[back_idx].copy(), winSize=win,
                                                    maxLevel=s.klt_levels, criteria=criteria,
                                                    flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        back = np.linalg.norm(p0b.reshape(-1, 2) - p0[back_idx].reshape(-1, 2), axis=1)
        ok[back_idx] = (status_b.ravel() == 1) & (back <= s.forward_backward_px)
    return out, ok


def _anchor(images: np.ndarray, ref: int, pts: np.ndarray, todo: np.ndarray, anchor_px: float, win: tuple,
            criteria: tuple, alive: np.ndarray) -> None:
    """Chained KLT drifts coherently (small biases add up over up to V-1 steps): re-track every view's ``todo``
    points (V, N) directly from the reference patch, started at the chain's estimate, and keep the points that stay
    within ``anchor_px`` of it (``pts`` and ``alive`` updated in place)."""
    ref_pts = pts[ref].astype(np.float32).reshape(-1, 1, 2)
    for b in range(len(images)):
        if b == ref or not todo[b].any():
            continue
        idx = np.nonzero(todo[b])[0]
        start = pts[b, idx].astype(np.float32).reshape(-1, 1, 2)
        p1, status, _ = cv2.calcOpticalFlowPyrLK(images[ref], images[b], ref_pts[idx], start.copy(),
                                                 winSize=win, maxLevel=1, criteria=criteria,
                                                 flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        p1 = p1.reshape(-1, 2).astype(np.float64)
        moved = np.linalg.norm(p1 - pts[b, idx], axis=1)
        ok = (status.ravel() == 1) & (moved <= anchor_px)
        pts[b, idx[ok]] = p1[ok]
        alive[b, idx[~ok]] = False


def _ransac(grid: ViewGrid, pts: np.ndarray, alive: np.ndarray, keep: np.ndarray, s: MatchSettings) -> None:
    """Fundamental-matrix RANSAC between the chain's adjacent views: ``keep`` loses every track an adjacent pair's
    consensus rejects (in place); pairs sharing fewer than 8 tracks are skipped."""
    for a, b in grid.chain():
        both = keep & alive[a] & alive[b]
        if both.sum() < 8:
            continue
        _, mask = cv2.findFundamentalMat(pts[a, both], pts[b, both], cv2.FM_RANSAC, s.ransac_threshold_px,
                                         s.ransac_confidence)
        if mask is None:
            continue
        keep[np.nonzero(both)[0][mask.ravel() == 0]] = False


UNIQUE_VALLEY = 0.2  # NCC: another place is separate when every path to it from the patch's own peak dips this far


def _patches(image: np.ndarray, points: np.ndarray, half: int) -> np.ndarray:
    """(N, 2 half + 1, 2 half + 1) float32 patches of ``image`` centred on ``points`` (N, 2), bilinear."""
    o = np.arange(-half, half + 1, dtype=np.float32)
    k, n = len(o), len(points)
    map_x = np.broadcast_to(points[:, 0, None, None].astype(np.float32) + o[None, None, :], (n, k, k))
    map_y = np.broadcast_to(points[:, 1, None, None].astype(np.float32) + o[None, :, None], (n, k, k))
    out = cv2.remap(image, np.ascontiguousarray(map_x.reshape(n * k, k)), np.ascontiguousarray(map_y.reshape(n * k, k)),
                    cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT101)
    return out.reshape(n, k, k).astype(np.float32)


def _ncc(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) normalised cross-correlation of paired patches (N, k, k)."""
    a, b = a.reshape(len(a), -1), b.reshape(len(b), -1)
    a, b = a - a.mean(axis=1, keepdims=True), b - b.mean(axis=1, keepdims=True)
    return np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1) + 1e-9)


def worst_match_ncc(images: np.ndarray, ref: int, pts: np.ndarray, alive: np.ndarray, half: int) -> np.ndarray:
    """(N,) the lowest NCC between each track's reference patch and its patch in another view that sees it."""
    ref_patches = _patches(images[ref], pts[ref], half)
    worst = np.full(pts.shape[1], np.inf)
    for v in range(len(images)):
        seen = alive[v] & (v != ref)
        if seen.any():
            worst[seen] = np.minimum(worst[seen], _ncc(ref_patches[seen], _patches(images[v], pts[v, seen], half)))
    return worst


def repeated_nearby(image: np.ndarray, points: np.ndarray, level: np.ndarray, radius: int, half: int) -> np.ndarray:
    """(N,) True where a point's (2 half + 1)^2 patch matches another place of ``image`` within ``radius`` px
    at NCC >= ``level`` (N,), separated from the patch's own peak by a valley (`UNIQUE_VALLEY` below ``level`` on
    every path between them).

    A place joined to the peak above that level is the same place (a ridge along an edge), not a repeat. One
    `cv2.matchTemplate` per point: a batched FFT correlation in NumPy gave the same map (to 3e-5) but took 15x
    longer on 700 points of a 640x480 image."""
    pad = radius + half
    padded = cv2.copyMakeBorder(image, pad, pad, pad, pad, cv2.BORDER_REFLECT101)
    out = np.zeros(len(points), dtype=bool)
    for i, (x, y) in enumerate(np.rint(points).astype(int) + pad):
        ncc = cv2.matchTemplate(padded[y - pad:y + pad + 1, x - pad:x + pad + 1],
                                padded[y - half:y + half + 1, x - half:x + half + 1], cv2.TM_CCOEFF_NORMED)
        high = ncc >= level[i]
        if np.count_nonzero(high) > 1:
            _, label = cv2.connectedComponents((ncc >= level[i] - UNIQUE_VALLEY).astype(np.uint8), connectivity=8)
            out[i] = bool(np.any(high & (label != label[radius, radius])))
    return out


def _unique(images: np.ndarray, ref: int, pts: np.ndarray, alive: np.ndarray, keep: np.ndarray,
            s: MatchSettings) -> None:
    """The repeated-texture filter (`MatchSettings.unique_margin`): ``keep`` loses every track whose reference patch
    has another place within ``s.unique_radius_px`` that matches it about as well as its own matches do (in
    place)."""
    idx = np.nonzero(keep)[0]
    if s.unique_margin is None or not len(idx):
        return
    half = s.klt_window_px // 2
    worst = worst_match_ncc(images, ref, pts[:, idx], alive[:, idx], half)
    keep[idx[repeated_nearby(images[ref], pts[ref, idx], worst - s.unique_margin, s.unique_radius_px, half)]] = False


def track_chain(images: np.ndarray, grid: ViewGrid, settings: MatchSettings | None = None) -> Tracks:
    """Track Shi–Tomasi features of the reference view through every view along ``grid.chain()``.

    Args:
        images: (V, H, W) uint8 grayscale views of one frame, row-major.
        grid: the view grid (its reference view is where features are detected).
        settings: options; `MatchSettings()` by default.

    Returns:
        tracks seen in all views (or in ``settings.min_views``), with the counts after each filter (``detected``,
        ``chain``, ``dedup``, ``ransac``, ``unique``).
    """
    s = settings or MatchSettings()
    n_views = grid.num_views
    if len(images) != n_views:
        raise ValueError(f"a {grid} grid needs {n_views} images, got {len(images)}")
    ref = grid.reference
    corners = cv2.goodFeaturesToTrack(images[ref], s.max_features, s.quality_level, s.min_distance_px,
                                      blockSize=s.block_size_px)
    n = 0 if corners is None else len(corners)
    pts = np.full((n_views, n, 2), np.nan)
    if n:
        pts[ref] = corners.reshape(-1, 2)
    alive = np.zeros((n_views, n), dtype=bool)
    alive[ref] = True
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
    win = (s.klt_window_px, s.klt_window_px)
    dup = np.zeros(n, dtype=bool)
    # In a grid the disparity of a point is (nearly) the same for every step in one direction: the previous step
    # in the same direction is the KLT start of the next (its median where a track has none), so the pyramid only
    # has to correct small changes even when neighbours are tens of pixels apart.
    steps: dict[tuple[int, int], np.ndarray] = {}
    for a, b in grid.chain():
        src = alive[a]
        if not src.any():
            continue
        (ra, ca), (rb, cb) = grid.position(a), grid.position(b)
        direction = (a, b) if grid.is_free else (rb - ra, cb - ca)  # a free arrangement's steps share no direction
        idx = np.nonzero(src)[0]
        guess = _step_guess(steps.get(direction), idx)
        p1, ok = _klt_step(images[a], images[b], pts[a, idx], pts[a, idx] + guess, s, win, criteria)
        pts[b, idx[ok]] = p1[ok]
        alive[b, idx[ok]] = True
        step = np.full((n, 2), np.nan)
        step[idx[ok]] = p1[ok] - pts[a, idx[ok]]
        steps[direction] = step
        dup |= _duplicates(pts[b], alive[b], DUPLICATE_PX)
    min_views = n_views if s.min_views is None else s.min_views
    if s.anchor_px is not None:  # only tracks the chain kept in enough views: re-tracking can only lose views
        _anchor(images, ref, pts, alive & (alive.sum(axis=0) >= min_views), s.anchor_px, win, criteria, alive)
    seen = alive.sum(axis=0)
    counts = {"detected": n}
    keep = seen >= min_views
    counts["chain"] = int(keep.sum())
    dup |= _duplicates(pts[ref], alive[ref], DUPLICATE_PX)
    keep &= ~dup
    counts["dedup"] = int(keep.sum())
    _ransac(grid, pts, alive, keep, s)
    counts["ransac"] = int(keep.sum())
    _unique(images, ref, pts, alive, keep, s)
    counts["unique"] = int(keep.sum())
    valid = alive[:, keep]
    out = pts[:, keep].copy()
    out[~valid] = np.nan
    return Tracks(out, valid, counts)


@runtime_checkable
class Tracker(Protocol):
    """What tracks features through a grid: ``track(images, grid) -> Tracks``.

    ``images`` is one frame, (V, H, W) uint8 grayscale views in the grid's row-major order; the result holds (V, N, 2)
    positions (NaN where a view does not see a track) and the counts after each of its filters. `ChainTracker` (the
    paper's chain KLT) is the default of `lfgraph.RefineConfig`, `lfgraph.check` and `lfgraph.SelfCalConfig`;
    give ``tracker=`` another object with this method (a learned matcher, an oracle for a study) to swap it
    everywhere at once. It must be picklable to run in a process pool (studies, fleets).
    """

    def track(self, images: np.ndarray, grid: ViewGrid) -> Tracks:
        """Track features through one frame's (V, H, W) uint8 views of ``grid``: (V, N, 2) positions, filter counts."""


@dataclass(frozen=True)
class ChainTracker:
    """The paper's tracker (`track_chain`): Shi–Tomasi in the reference view, pyramidal KLT along the grid's chain,
    the forward-backward, duplicate and F-RANSAC filters, with these `MatchSettings`."""

    settings: MatchSettings = field(default_factory=MatchSettings)

    def __post_init__(self) -> None:
        if not isinstance(self.settings, MatchSettings):
            raise TypeError(f"ChainTracker settings must be a lfgraph MatchSettings, got "
                            f"{type(self.settings).__name__}")

    def track(self, images: np.ndarray, grid: ViewGrid) -> Tracks:
        """`track_chain` of one frame's (V, H, W) uint8 views with this tracker's settings; where the chain loses
        the grid (fewer than `DEEP_RETRY_SHARE` of the features followed through it), again with
        ``settings.deep_klt_levels`` pyramid levels, keeping the run that follows more features."""
        tracks = track_chain(images, grid, self.settings)
        s = self.settings
        if s.deep_klt_levels is None or s.deep_klt_levels <= s.klt_levels or _chained(tracks) >= DEEP_RETRY_SHARE:
            return tracks
        deep = track_chain(images, grid, dataclasses.replace(s, klt_levels=s.deep_klt_levels))
        logging.getLogger("lfgraph").info(
            "the chain followed %.0f %% of the features through the grid with %d pyramid levels (a large knock or "
            "disparity); with %d: %.0f %%", 100 * _chained(tracks), s.klt_levels, s.deep_klt_levels,
            100 * _chained(deep))
        return deep if _chained(deep) > _chained(tracks) else tracks


def _chained(tracks: Tracks) -> float:
    """The share of detected features the chain followed through the grid."""
    return tracks.counts.get("chain", 0) / max(tracks.counts.get("detected", 0), 1)


def as_tracker(tracker: object, what: str) -> Tracker:
    """``tracker`` checked to be a `Tracker` (a clear TypeError naming ``what`` otherwise)."""
    if not isinstance(tracker, Tracker):
        raise TypeError(f"{what} must have a track(images, grid) method returning Tracks (a lfgraph Tracker such as "
                        f"ChainTracker), got {type(tracker).__name__}")
    return tracker
