"""Per-frame track selection for the refinement: the triangulation filter, cheirality, coverage; and
`OutlierTracker`, which makes a share of any tracker's matches wrong (a study variable)."""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.grid import ViewGrid
from lfgraph.engine.triangulate import (
    OUTLIER_FACTOR,
    OUTLIER_FLOOR_PX,
    drop_mismatches,
    median_filter,
    reprojection_errors,
    triangulate_dlt,
)
from lfgraph.refinement.config import TriangulationFilter
from lfgraph.refinement.matching import ChainTracker, Tracker, Tracks, as_tracker

COVERAGE_CELLS = 8
MIN_BASELINE_M = 1e-6  # a track needs observing centres at least this far apart


def collect_tracks(calib: Calibration, tracks: Tracks,
                   triangulation_filter: TriangulationFilter) -> tuple[Tracks, dict[str, int]]:
    """Apply the triangulation filter to one frame's tracks; returns the kept tracks and the counts."""
    points = triangulate_dlt(calib, tracks.points_px, tracks.valid)
    errors = reprojection_errors(calib, points, tracks.points_px, tracks.valid)
    if triangulation_filter == TriangulationFilter.MEDIAN:
        keep = median_filter(errors, calib.grid.reference)
    elif triangulation_filter == TriangulationFilter.WORST:
        keep = drop_mismatches(errors)
    else:
        keep = np.all(np.isfinite(points), axis=1)
    return tracks.subset(keep), {**tracks.counts, "triangulation": int(keep.sum())}


def in_front(calib: Calibration, points_ref: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(N,) finite points in front of every view that observes them, seen from at least two distinct centres
    (views that share a centre — the Middlebury rings hold such pairs, one turned by 180° — give no depth)."""
    ok = np.all(np.isfinite(points_ref), axis=1)
    centres = calib.ref_T_view[:, :3, 3]
    lo = np.where(valid[..., None], centres[:, None, :], np.inf).min(axis=0)
    hi = np.where(valid[..., None], centres[:, None, :], -np.inf).max(axis=0)
    ok &= np.max(hi - lo, axis=1) > MIN_BASELINE_M
    for v in range(calib.num_views):
        m = valid[v] & ok
        if m.any():
            T = calib.view_T_ref(v)  # noqa: N806
            depth = points_ref[m] @ T[2, :3] + T[2, 3]
            bad = np.nonzero(m)[0][~(depth > 0)]
            ok[bad] = False
    return ok


def track_coverage(calib: Calibration, pixels: np.ndarray, valid: np.ndarray, cells: int = COVERAGE_CELLS) -> float:
    """Share of an 8x8 grid of reference-image cells holding at least one kept track."""
    ref = calib.grid.reference
    w, h = calib.image_size(ref)
    pts = pixels[ref][valid[ref]]
    if not len(pts):
        return 0.0
    cx = np.clip((pts[:, 0] / w * cells).astype(int), 0, cells - 1)
    cy = np.clip((pts[:, 1] / h * cells).astype(int), 0, cells - 1)
    grid = np.zeros((cells, cells), dtype=bool)
    grid[cy, cx] = True
    return float(grid.mean())


FRAME_OUTLIER_FACTOR = 3.0  # a frame whose median track error is > 3x the pooled median track's ...
FRAME_OUTLIER_FLOOR_PX = 0.5  # ... and > 0.5 px is mostly mismatches (a repetitive pattern): dropped whole


def pooled_filter(calib: Calibration, pixels: np.ndarray, valid: np.ndarray,
                  frame_of: np.ndarray) -> tuple[np.ndarray, list[int]]:
    """Mismatch filter over the tracks of all frames at once: (N,) kept mask and the frames dropped whole.

    A frame's own median cannot reject its tracks when most of them are wrong (a board's repeated corners matched
    one square off); against the pooled median of every frame such a frame stands out and is dropped, and single
    tracks are dropped as `worst_error_filter` does, with the pooled median.
    """
    errors = reprojection_errors(calib, triangulate_dlt(calib, pixels, valid), pixels, valid)
    worst = np.where(np.isfinite(errors), errors, -np.inf).max(axis=0)
    finite = np.isfinite(worst) & (worst >= 0)
    if not finite.any():
        return finite, []
    pooled = float(np.median(worst[finite]))
    keep = finite & (worst <= max(OUTLIER_FACTOR * pooled, OUTLIER_FLOOR_PX))
    dropped = []
    for f in np.unique(frame_of):
        m = (frame_of == f) & finite
        if m.any() and np.median(worst[m]) > max(FRAME_OUTLIER_FACTOR * pooled, FRAME_OUTLIER_FLOOR_PX):
            keep &= frame_of != f
            dropped.append(int(f))
    return keep, dropped


@dataclass(frozen=True)
class OutlierTracker:
    """Wrong matches as a study variable: the tracks of ``inner`` (any `Tracker`; the paper's chain KLT by default)
    with ``share`` of the non-reference observations moved by ``min_px`` to ``max_px`` (uniform) in uniformly random
    directions, as a tracker that locks onto the wrong place would (the reference view's detections stay). Give it
    as ``RefineConfig(tracker=...)`` (or ``check``'s, ``SelfCalConfig``'s): every wing sees the same wrong matches.

    The moves of a frame are drawn from ``seed`` and a checksum of the frame's images: the same frame gets the same
    wrong matches in every run, process and wing, different frames (and trials) different ones. Picklable.

    ``OutlierTracker.parse("0.05:2-8")``: 5 % of the observations, 2-8 px.
    """

    inner: Tracker = field(default_factory=ChainTracker)
    share: float = 0.05
    min_px: float = 2.0
    max_px: float = 8.0
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "inner", as_tracker(self.inner, "OutlierTracker.inner"))
        if not 0.0 <= self.share <= 1.0:
            raise ValueError(f"the share of wrong matches must be from 0 to 1, got {self.share!r}")
        if not (np.isfinite(self.max_px) and 0.0 <= self.min_px <= self.max_px):
            raise ValueError(f"wrong matches need 0 <= min_px <= max_px (finite), got {self.min_px!r}-{self.max_px!r}")

    @classmethod
    def parse(cls, spec: str, inner: Tracker | None = None, seed: int = 0) -> OutlierTracker:
        """``SHARE:MIN-MAX`` (``0.05:2-8``: 5 % of the observations, 2-8 px), ``SHARE:PX`` (all moved by PX) or
        ``SHARE`` (2-8 px) around ``inner`` (None: the chain tracker).

        Raises:
            ValueError: a spec of another form, or values out of range (named).
        """
        share, _, size = str(spec).strip().partition(":")
        lo, _, hi = size.partition("-")
        try:
            values = float(share), float(lo) if lo else 2.0, float(hi) if hi else float(lo) if lo else 8.0
        except ValueError:
            raise ValueError(f"wrong matches are SHARE:MIN-MAX (e.g. 0.05:2-8: 5 % moved by 2-8 px), got "
                             f"{spec!r}") from None
        return cls(ChainTracker() if inner is None else inner, *values, seed=seed)

    def __str__(self) -> str:
        return f"{self.share:g}:{self.min_px:g}-{self.max_px:g}"

    def track(self, images: np.ndarray, grid: ViewGrid) -> Tracks:
        """``inner``'s tracks of this frame with ``share`` of the non-reference observations moved."""
        tracks = self.inner.track(images, grid)
        seen = tracks.valid.copy()
        seen[grid.reference] = False
        where = np.argwhere(seen)
        rng = np.random.default_rng([self.seed, zlib.crc32(np.ascontiguousarray(images).tobytes())])
        n = int(round(self.share * len(where)))
        if n == 0:
            return tracks
        moved = where[rng.choice(len(where), n, replace=False)]
        size = rng.uniform(self.min_px, self.max_px, n)
        angle = rng.uniform(0.0, 2.0 * np.pi, n)
        points = tracks.points_px.copy()
        points[moved[:, 0], moved[:, 1]] += np.column_stack([size * np.cos(angle), size * np.sin(angle)])
        return Tracks(points, tracks.valid, dict(tracks.counts))
