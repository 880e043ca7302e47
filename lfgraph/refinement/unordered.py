"""Tracks for views that need descriptors: SIFT features matched between chosen view pairs, fundamental-matrix
RANSAC per pair, tracks by union-find; nothing here assumes a grid. `SiftTracker` is the matcher as a
`lfgraph.refinement.matching.Tracker` (``RefineConfig(tracker=...)``, ``--tracker sift``): on a grid it matches
every pair of grid neighbours, on a free arrangement (a ring, a dome, a loose set: `lfgraph.core.grid.free_grid`)
every pair its poses link. `match_unordered` matches any pairs you choose (`ring_pairs`, `nearest_pairs`).

KLT along a chain needs small steps between neighbours; views tens of degrees apart (22.5° between the Middlebury
ring's views) need descriptors (`lfgraph.refinement.trackers.AutoTracker` chooses by the links' angles).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from lfgraph.core.grid import ViewGrid
from lfgraph.refinement.matching import Tracks

RATIO_TEST = 0.75  # Lowe's ratio test
RANSAC_THRESHOLD_PX = 1.0
MIN_PAIR_MATCHES = 15
GRID_MIN_VIEWS = 3  # a grid's SIFT tracks: seen in 3 views at least (each one's neighbours see most of its scene)
FREE_MIN_VIEWS = 2  # a ring's: a pair (a rendered 12-view ring, 30 deg apart: in 3 views, 2 views kept 0-1 tracks;
# in 2, every view 82-316, residuals with the true cameras 0.10 px median)
SIFT_CONTRAST = 0.01  # below OpenCV's 0.04: plaster and other low-contrast objects give 3-5x more features
SIFT_PRECISE_UPSCALE = True  # OpenCV's SIFT doubles the image for its first octave and, by default, maps upscaled
# pixel 2x back to x, while its resize put it at x - 0.25: every keypoint is reported 0.25 px too far right and down
# (measured on rendered ring views: a keypoint and its mirror image's disagree by 0.49-0.50 px, 0.00 with this). A
# grid's views, near-parallel, take a common shift as a common turn the reference gauge absorbs; a ring's views turn
# it into a tilt growing around the ring (sweep seed 78: 0.09 deg, 5 sigma, on the views opposite the reference)


def ring_pairs(n_views: int, reach: int = 2, closed: bool = True) -> list[tuple[int, int]]:
    """Pairs (i, i + k) for k = 1..reach along a ring (wrapping around when ``closed``)."""
    pairs = []
    for k in range(1, reach + 1):
        for i in range(n_views):
            j = i + k
            if j >= n_views:
                if not closed:
                    continue
                j -= n_views
            if i != j and (j, i) not in pairs:
                pairs.append((i, j))
    return pairs


def nearest_pairs(ref_T_view: np.ndarray, k: int = 2) -> list[tuple[int, int]]:  # noqa: N803
    """Each view paired with its ``k`` nearest views by the angle between optical axes (then centre distance).

    For sets whose file order is not their spatial order (the Middlebury rings jump by up to 165° between files).
    """
    axes = ref_T_view[:, :3, 2]
    centres = ref_T_view[:, :3, 3]
    angle = np.degrees(np.arccos(np.clip(axes @ axes.T, -1.0, 1.0)))
    dist = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    score = angle + 1e-3 * dist / max(float(dist.max()), 1e-12)
    np.fill_diagonal(score, np.inf)
    pairs = set()
    for i in range(len(ref_T_view)):
        for j in np.argsort(score[i])[:k]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def _find(parent: np.ndarray, x: int) -> int:
    while parent[x] != x:
        parent[x] = parent[parent[x]]
        x = parent[x]
    return x


def sift_features(image: np.ndarray, max_features: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) SIFT keypoints of an (H, W) grayscale image in pixels (the centre of the top-left pixel at (0, 0), as
    every track), and their (N, 128) descriptors."""
    sift = cv2.SIFT_create(nfeatures=max_features, contrastThreshold=SIFT_CONTRAST,
                           enable_precise_upscale=SIFT_PRECISE_UPSCALE)
    kp, des = sift.detectAndCompute(image, None)
    pts = np.array([k.pt for k in kp], dtype=np.float64).reshape(-1, 2)
    return pts, des if des is not None else np.zeros((0, 128), np.float32)


def match_unordered(images: Sequence[np.ndarray], pairs: Sequence[tuple[int, int]], max_features: int = 4000,
                    min_views: int = 3) -> Tracks:
    """Tracks over arbitrary views from SIFT matches on ``pairs``.

    Args:
        images: (H, W) grayscale views.
        pairs: view pairs to match.
        max_features: SIFT features per view.
        min_views: keep tracks seen in at least this many views.

    Returns:
        `Tracks` with a partial mask; counts ``detected`` (features of the first view), ``matches`` (pairwise,
        after RANSAC), ``tracks`` (after union-find, conflicts and ``min_views``).
    """
    keypoints, descriptors = [], []
    for img in images:
        pts, des = sift_features(img, max_features)
        keypoints.append(pts)
        descriptors.append(des)
    offsets = np.concatenate([[0], np.cumsum([len(k) for k in keypoints])])
    parent = np.arange(offsets[-1])
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    n_matches = 0
    for a, b in pairs:
        if len(descriptors[a]) < 2 or len(descriptors[b]) < 2:
            continue
        knn = matcher.knnMatch(descriptors[a], descriptors[b], k=2)
        good = [m[0] for m in knn if len(m) == 2 and m[0].distance < RATIO_TEST * m[1].distance]
        if len(good) < MIN_PAIR_MATCHES:
            continue
        ia = np.array([m.queryIdx for m in good])
        ib = np.array([m.trainIdx for m in good])
        _, mask = cv2.findFundamentalMat(keypoints[a][ia], keypoints[b][ib], cv2.FM_RANSAC, RANSAC_THRESHOLD_PX,
                                         0.999)
        if mask is None:
            continue
        keep = mask.ravel() == 1
        n_matches += int(keep.sum())
        for x, y in zip(ia[keep] + offsets[a], ib[keep] + offsets[b], strict=True):
            rx, ry = _find(parent, int(x)), _find(parent, int(y))
            if rx != ry:
                parent[ry] = rx
    roots = np.array([_find(parent, i) for i in range(len(parent))])
    view_of = np.repeat(np.arange(len(images)), np.diff(offsets))
    unique_roots, track_of = np.unique(roots, return_inverse=True)
    n_tracks = len(unique_roots)
    counts = np.zeros((n_tracks, len(images)), dtype=int)
    np.add.at(counts, (track_of, view_of), 1)
    consistent = np.all(counts <= 1, axis=1)  # a track may not hold two features of one view
    seen = (counts > 0).sum(axis=1)
    keep_track = consistent & (seen >= min_views)
    index = -np.ones(n_tracks, dtype=int)
    index[keep_track] = np.arange(keep_track.sum())
    pts = np.full((len(images), int(keep_track.sum()), 2), np.nan)
    valid = np.zeros((len(images), int(keep_track.sum())), dtype=bool)
    all_pts = np.concatenate(keypoints) if offsets[-1] else np.zeros((0, 2))
    sel = keep_track[track_of]
    pts[view_of[sel], index[track_of[sel]]] = all_pts[sel]
    valid[view_of[sel], index[track_of[sel]]] = True
    return Tracks(pts, valid, {"detected": len(keypoints[0]) if keypoints else 0, "matches": n_matches,
                               "tracks": int(keep_track.sum())})


@dataclass(frozen=True)
class SiftTracker:
    """SIFT features matched between neighbouring views (`match_unordered`), as a tracker: on a grid every pair of
    grid neighbours (rows and columns), ``reach`` steps along them; on a free arrangement every pair its poses link
    (``grid.links``); tracks seen in at least ``min_views`` views (None: `GRID_MIN_VIEWS` on a grid,
    `FREE_MIN_VIEWS` on a free arrangement). For views too far apart for KLT's small steps (tens of degrees, a wide
    baseline)."""

    max_features: int = 4000
    min_views: int | None = None
    reach: int = 1

    def track(self, images: np.ndarray, grid: ViewGrid) -> Tracks:
        """SIFT tracks of one frame's (V, H, W) uint8 views of ``grid``; counts ``detected``, ``matches``, ``chain``
        (tracks kept: seen in ``min_views`` views) and ``tracks``."""
        pairs = list(grid.links) if grid.is_free else [
            (a, b) for a in range(grid.num_views) for b in range(a + 1, grid.num_views)
            if _grid_steps(grid, a, b) <= self.reach]
        min_views = self.min_views or (FREE_MIN_VIEWS if grid.is_free else GRID_MIN_VIEWS)
        tracks = match_unordered(list(images), pairs, self.max_features, min(min_views, grid.num_views))
        return Tracks(tracks.points_px, tracks.valid, {**tracks.counts, "chain": tracks.counts["tracks"]})


def _grid_steps(grid: ViewGrid, a: int, b: int) -> int:
    """Grid steps between two views along one row or column (a large number for any other pair)."""
    (ra, ca), (rb, cb) = grid.position(a), grid.position(b)
    return abs(ca - cb) if ra == rb else abs(ra - rb) if ca == cb else 1 << 30
