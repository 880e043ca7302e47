"""Tracks of self-calibration: chain KLT through the grid per frame, spread over the image, pooled over frames; and
what the pooled tracks cover (depths, image regions, radius), with the refusal rules."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.grid import ViewGrid
from lfgraph.refinement.matching import Tracker
from lfgraph.selfcal.retrack import Patches, cut_patches

SPREAD_CELLS = 8  # tracks are thinned per cell of an 8x8 grid of the reference image
REGIONS = 3  # coverage is reported per cell of a 3x3 grid of every image (corners, edges, centre)
REGION_NAMES = (("top-left", "top", "top-right"), ("left", "centre", "right"),
                ("bottom-left", "bottom", "bottom-right"))
MIN_REGION_TRACKS = 5  # a region is covered when every view sees at least this many tracks in it
MIN_TRACKS = 150  # fewer pooled tracks cannot hold 10+ parameters per view
MIN_REGIONS = 7  # of 9: fewer covered regions leave focal lengths and principal points to the priors
MIN_DEPTH_RATIO = 1.3  # far / near (5th-95th percentile of depths): below it rotation and position trade freely
CORNER_RADIUS = 0.7  # tracks must reach this fraction of the half diagonal for distortion to be estimated ...
MIN_CORNER_TRACKS = 10  # ... with at least this many observations beyond it per view (on average over views)
# tracks reaching only this far still let the stages estimate k1 (k2 held at the design until the final stage, which
# frees both with their design tolerances). A judgement, not tuned; what it replaced was measured on paper-5x5 (20
# frames, tracks to 68 % of the half diagonal): k1 and k2 held at the design's 0 to the end, against the true
# k1 = -0.1, left cx 7.5 px and rotation 0.8 deg off, with sigmas 17-37x too small
K1_RADIUS = 0.5


@dataclass(frozen=True)
class PooledTracks:
    """Tracks of several frames, one landmark each.

    Attributes:
        pixels: (V, N, 2) positions (NaN where not seen); valid: (V, N); frame: (N,) the frame of each track.
        frames_seen: frames read; frames_used: frames that gave tracks.
        patches: image patches around every track for re-tracking with the calibrated geometry (None: not kept).
    """

    pixels: np.ndarray
    valid: np.ndarray
    frame: np.ndarray
    frames_seen: int
    frames_used: int
    patches: Patches | None = None

    @property
    def num_tracks(self) -> int:
        """Number of pooled tracks, N."""
        return self.pixels.shape[1]

    def subset(self, keep: np.ndarray) -> PooledTracks:
        """The tracks ``keep`` selects, with their patches; ``frames_used`` is counted again from the kept tracks."""
        return PooledTracks(self.pixels[:, keep], self.valid[:, keep], self.frame[keep], self.frames_seen,
                            int(len(np.unique(self.frame[keep]))),
                            None if self.patches is None else self.patches.subset(keep))


def spread(points_px: np.ndarray, image_size_px: tuple[int, int], limit: int, rng: np.random.Generator,
           cells: int = SPREAD_CELLS) -> np.ndarray:
    """Indices of at most ``limit`` of (N, 2) points, taken round-robin over image cells so sparse regions keep
    theirs (random order inside a cell, seeded)."""
    n = len(points_px)
    if n <= limit:
        return np.arange(n)
    w, h = image_size_px
    cx = np.clip((points_px[:, 0] / w * cells).astype(int), 0, cells - 1)
    cy = np.clip((points_px[:, 1] / h * cells).astype(int), 0, cells - 1)
    cell = cy * cells + cx
    order = rng.permutation(n)
    rank = np.zeros(n, dtype=int)
    seen: dict[int, int] = {}
    for i in order:  # rank of each point inside its cell
        rank[i] = seen.get(int(cell[i]), 0)
        seen[int(cell[i])] = rank[i] + 1
    chosen = np.lexsort((order.argsort(), rank))[:limit]
    return np.sort(chosen)


def pool_tracks(frames: Iterable[np.ndarray], grid: ViewGrid, image_size_px: tuple[int, int], per_frame: int,
                tracker: Tracker, max_frames: int | None = None, seed: int = 0,
                keep_patches: bool = True) -> PooledTracks:
    """Track every frame through the grid and keep at most ``per_frame`` tracks of each, spread over the image
    (with the image patches around them when ``keep_patches``, for `lfgraph.selfcal.retrack`).

    Raises:
        ValueError: a frame with the wrong number of views or image size.
    """
    rng = np.random.default_rng(seed)
    chunks, valids, owner, patches = [], [], [], []
    seen = used = 0
    w, h = image_size_px
    for f, images in enumerate(frames):
        if max_frames is not None and f >= max_frames:
            break
        images = np.asarray(images)
        if images.shape[:1] != (grid.num_views,) or images.shape[1:3] != (h, w):
            raise ValueError(f"frame {f}: expected {grid.num_views} views of {w}x{h} px, got {images.shape}")
        seen += 1
        tracks = tracker.track(images, grid)
        if tracks.num_tracks == 0:
            continue
        keep = spread(tracks.points_px[grid.reference], image_size_px, per_frame, rng)
        chunks.append(tracks.points_px[:, keep])
        valids.append(tracks.valid[:, keep])
        owner.append(np.full(len(keep), f))
        if keep_patches:
            patches.append(cut_patches(images, chunks[-1], valids[-1], grid.reference))
        used += 1
    if not chunks:
        return PooledTracks(np.zeros((grid.num_views, 0, 2)), np.zeros((grid.num_views, 0), dtype=bool),
                            np.zeros(0, dtype=int), seen, 0)
    return PooledTracks(np.concatenate(chunks, axis=1), np.concatenate(valids, axis=1), np.concatenate(owner),
                        seen, used, Patches.concatenate(patches) if keep_patches else None)


@dataclass(frozen=True)
class Coverage:
    """What the pooled tracks cover.

    Attributes:
        frames: frames that gave tracks; tracks: pooled tracks.
        depth_m: (5th, 50th, 95th) percentile of the landmarks' depths in the reference view (metres, on the
            design scale).
        disparity_px: the same as disparity per grid step (px; nominal focal length x pitch / depth).
        regions: (3, 3) fewest tracks any view sees in each region of its image.
        corner_tracks: observations beyond `CORNER_RADIUS` of the half diagonal, per view (mean over views).
        k1_tracks: the same beyond `K1_RADIUS`.
        max_radius: largest observed radius as a fraction of the half diagonal (99th percentile over all views).
    """

    frames: int
    tracks: int
    depth_m: tuple[float, float, float]
    disparity_px: tuple[float, float, float]
    regions: np.ndarray
    corner_tracks: int
    max_radius: float
    k1_tracks: int = 0

    @property
    def depth_ratio(self) -> float:
        """Far over near depth (95th over 5th percentile); NaN when the near depth is not positive."""
        return self.depth_m[2] / self.depth_m[0] if self.depth_m[0] > 0 else float("nan")

    def missing_regions(self) -> list[str]:
        """Names of the image regions (``top-left`` ... ``bottom-right``) in which some view sees fewer than
        `MIN_REGION_TRACKS` tracks."""
        return [REGION_NAMES[r][c] for r in range(REGIONS) for c in range(REGIONS)
                if self.regions[r, c] < MIN_REGION_TRACKS]

    @property
    def distortion_covered(self) -> bool:
        """Whether enough observations (`MIN_CORNER_TRACKS` per view) reach `CORNER_RADIUS` to estimate k1 and k2."""
        return self.corner_tracks >= MIN_CORNER_TRACKS

    @property
    def k1_covered(self) -> bool:
        """Whether enough observations (`MIN_CORNER_TRACKS` per view) reach `K1_RADIUS` to estimate k1."""
        return self.k1_tracks >= MIN_CORNER_TRACKS

    def problems(self, min_frames: int, depths: bool = True) -> list[str]:
        """Why these frames cannot determine the parameters (empty when they can); ``depths``: with the depth span
        (only the final fit's depths are right: `lfgraph.selfcal.stages.depths_suffice`)."""
        out = []
        if self.frames < min_frames:
            out.append(f"only {self.frames} frame(s) gave tracks through every view; at least {min_frames} "
                       "are needed")
        if self.tracks < MIN_TRACKS:
            out.append(f"only {self.tracks} tracks survived; at least {MIN_TRACKS} are needed (textured scenes, "
                       "more frames)")
        if depths and self.tracks and not self.depth_ratio >= MIN_DEPTH_RATIO:
            out.append(f"the depths span only {self.depth_m[0]:.3g}-{self.depth_m[2]:.3g} m (far/near "
                       f"{self.depth_ratio:.2f} < {MIN_DEPTH_RATIO}); rotations and positions cannot be told apart "
                       "- add frames of nearer and farther scenes")
        missing = self.missing_regions()
        if len(missing) > REGIONS * REGIONS - MIN_REGIONS:
            out.append(f"image regions without tracks in every view: {', '.join(missing)}; focal lengths and "
                       "principal points need texture across the image - add frames with texture there that every "
                       "view sees (more frames of varied scenes)")
        return out

    def as_dict(self) -> dict:
        """The figures, ``depth_ratio``, the missing regions and both coverage flags as a JSON-ready dict."""
        return {"frames": self.frames, "tracks": self.tracks, "depth_m": list(self.depth_m),
                "disparity_px_per_step": list(self.disparity_px), "depth_ratio": self.depth_ratio,
                "missing_regions": self.missing_regions(), "corner_tracks": self.corner_tracks,
                "max_radius_of_half_diagonal": self.max_radius, "distortion_covered": self.distortion_covered,
                "k1_covered": self.k1_covered}


def measure_coverage(calib: Calibration, tracks: PooledTracks, points_ref: np.ndarray, focal_px: float,
                     pitch_m: float) -> Coverage:
    """Coverage of ``tracks`` whose landmarks are ``points_ref`` (N, 3) in the reference frame."""
    w, h = calib.image_size_px
    z = points_ref[:, 2]
    z = z[np.isfinite(z) & (z > 0)]
    depth = tuple(float(x) for x in np.percentile(z, [5, 50, 95])) if len(z) else (np.nan,) * 3
    disparity = tuple(focal_px * pitch_m / d for d in depth)
    regions = np.full((REGIONS, REGIONS), np.iinfo(np.int64).max, dtype=np.int64)
    for v in range(calib.num_views):
        p = tracks.pixels[v][tracks.valid[v]]
        cx = np.clip((p[:, 0] / w * REGIONS).astype(int), 0, REGIONS - 1)
        cy = np.clip((p[:, 1] / h * REGIONS).astype(int), 0, REGIONS - 1)
        counts = np.zeros((REGIONS, REGIONS), dtype=np.int64)
        np.add.at(counts, (cy, cx), 1)
        regions = np.minimum(regions, counts)
    seen = tracks.pixels[tracks.valid]
    half_diag = 0.5 * np.hypot(w - 1, h - 1)
    radius = np.hypot(seen[:, 0] - (w - 1) / 2, seen[:, 1] - (h - 1) / 2) / half_diag
    return Coverage(tracks.frames_used, tracks.num_tracks, depth, disparity, regions,
                    int(np.sum(radius >= CORNER_RADIUS) // calib.num_views),
                    float(np.percentile(radius, 99)) if len(radius) else 0.0,
                    int(np.sum(radius >= K1_RADIUS) // calib.num_views))
