"""Design values and options of target-less self-calibration, validated once."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from lfgraph.core.calibration import Calibration, image_size_checked
from lfgraph.core.camera import Intrinsics
from lfgraph.core.grid import ViewGrid
from lfgraph.core.sigmas import Sigmas
from lfgraph.factors.groups import SELFCAL_GROUPS
from lfgraph.factors.hooks import as_hooks
from lfgraph.factors.noise import Noise, NoiseSpec, as_noise
from lfgraph.lenses import DEFAULT_LENS, lens_model, lens_names
from lfgraph.refinement.matching import ChainTracker, MatchSettings, Tracker, as_tracker
from lfgraph.selfcal.defaults import (
    FOCAL_TOLERANCE,
    K1_TOLERANCE,
    K2_TOLERANCE,
    POSITION_TOLERANCE_MM,
    PRINCIPAL_TOLERANCE_PX,
    ROTATION_TOLERANCE_DEG,
    TRACKS_PER_FRAME,
)
from lfgraph.selfcal.pins import PIN_TYPES, BoardPin, Pin

# The default order of stages (measured on the benchmark rigs, see README "Calibrating without a target"): poses
# first (a 1 deg rotation moves an image by ~f/60 px, far more than any other error), then the relative focal
# lengths, then principal points, then distortion once tracks reach the image corners.
DEFAULT_STAGES: tuple[tuple[str, ...], ...] = (
    ("rotation", "position"),
    ("rotation", "position", "focal"),
    ("rotation", "position", "focal", "principal"),
    ("rotation", "position", "focal", "principal", "distortion"),
)

FIELD_OF_VIEW_DEG = (1.0, 170.0)  # the horizontal field of view a nominal focal length may give (a camera) ...
WIDE_FIELD_OF_VIEW_DEG = (1.0, 240.0)  # ... and through a fisheye or a unified lens


@dataclass(frozen=True)
class Design:
    """What the maker of the array says: the grid, the nominal pitch, the nominal focal length, the image size.

    Attributes:
        rows, cols, reference: the grid (views row-major; the reference view is the rig frame).
        pitch_mm: distance between adjacent views (millimetres).
        focal_px: nominal focal length in pixels (`focal_from_lens` converts a lens and a sensor).
        image_size_px: (width, height).
        k1, k2: nominal radial distortion (0 when unknown) of the lens model.
        lens: every view's lens model, ``radtan``, ``fisheye`` (Kannala–Brandt k1..k4 in OpenCV's convention; a
            self-calibration frees its k1, k2 and holds k3, k4 at 0) or ``unified`` (Mei's, Kalibr's omni-radtan: a
            self-calibration frees its k1, k2 and holds ``xi`` and p1, p2).
        xi: a unified lens's xi (its maker's value, or one calibrated from a board: scene tracks barely tell it from
            the focal length and k1; held). 0 for the other lenses.
    """

    rows: int
    cols: int
    pitch_mm: float
    focal_px: float
    image_size_px: tuple[int, int]
    reference: int = 0
    k1: float = 0.0
    k2: float = 0.0
    lens: str = DEFAULT_LENS
    xi: float = 0.0

    def __post_init__(self) -> None:
        if self.lens not in lens_names():
            raise ValueError(f"lens must be one of {', '.join(lens_names())} for a self-calibration, got "
                             f"{self.lens!r}")
        if self.xi != 0.0 and "xi" not in lens_model(self.lens).coefficients:
            raise ValueError(f"xi is a unified lens's; a {self.lens} design has none (got xi={self.xi})")
        if not (np.isfinite(self.xi) and self.xi >= 0):
            raise ValueError(f"a unified lens needs xi >= 0, got xi={self.xi}")
        ViewGrid(self.rows, self.cols, self.reference)
        if self.rows * self.cols < 2:
            raise ValueError("self-calibration needs at least two views")
        for name in ("pitch_mm", "focal_px"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be positive, got {value}")
        w, h = image_size_checked(self.image_size_px, "image_size_px")
        fov_deg = self._field_of_view_deg(w / (2 * self.focal_px))
        lo, hi = WIDE_FIELD_OF_VIEW_DEG if lens_model(self.lens).wide else FIELD_OF_VIEW_DEG
        if not lo <= fov_deg <= hi:  # --focal-px 1e9 failed deep in the marginals
            seen = "no field of view (the image reaches beyond the lens's)" if np.isnan(fov_deg) \
                else f"a {fov_deg:.3g} deg field of view"
            raise ValueError(f"focal_px {self.focal_px:g} gives {seen} across {w} px; a "
                             f"{self.lens} camera's is {lo:g}-{hi:g} deg: give the nominal focal length in pixels "
                             f"(or the lens and the sensor width in mm)")
        object.__setattr__(self, "image_size_px", (w, h))

    def _field_of_view_deg(self, half: float) -> float:
        """The angle across the image for a half width of ``half`` focal lengths, through the design's lens without
        distortion (NaN: beyond a unified lens's image)."""
        return 2.0 * lens_model(self.lens).off_axis_deg(half, self.xi)

    @property
    def grid(self) -> ViewGrid:
        """The `ViewGrid` of ``rows``, ``cols`` and ``reference``."""
        return ViewGrid(self.rows, self.cols, self.reference)

    @property
    def intrinsics(self) -> Intrinsics:
        """Nominal focal length, principal point at the image centre, nominal distortion, the design's lens model."""
        w, h = self.image_size_px
        return Intrinsics(self.focal_px, self.focal_px, (w - 1) / 2, (h - 1) / 2, self.k1, self.k2, xi=self.xi,
                          lens=self.lens)

    def ref_T_view(self) -> np.ndarray:  # noqa: N802
        """(V, 4, 4) ideal poses: parallel views, view (r, c) at ((c - c_ref), (r - r_ref), 0) x pitch."""
        grid = self.grid
        poses = np.tile(np.eye(4), (grid.num_views, 1, 1))
        for v in range(grid.num_views):
            dr, dc = grid.offset(v)
            poses[v, :3, 3] = np.array([dc, dr, 0.0]) * self.pitch_mm / 1000.0
        return poses

    def calibration(self) -> Calibration:
        """The ideal grid: parallel views at the nominal pitch, every view with the nominal intrinsics."""
        grid = self.grid
        return Calibration(grid, self.image_size_px, (self.intrinsics,) * grid.num_views,
                           self.ref_T_view(),
                           metrics={"source": "design values"})


def focal_from_lens(focal_mm: float, sensor_width_mm: float, image_width_px: int) -> float:
    """Nominal focal length in pixels from the lens focal length and the sensor width."""
    if min(focal_mm, sensor_width_mm, image_width_px) <= 0:
        raise ValueError("focal length, sensor width and image width must be positive")
    return focal_mm * image_width_px / sensor_width_mm


# Tracking from design values: views may be a few degrees and 15+ px of principal point off the ideal grid, so KLT
# searches two pyramid levels higher than the refinement does (3 levels kept 2 of 922 features through paper-5x5's
# 25 views with 1 deg rotations, 5 levels and a 21 px window 179; 0.1 s per frame either way). The repeated-texture
# filter of `refine` is off here: self-calibration re-tracks every track from the reference patch and its measured
# figures (README, benchmarks/targetless.py) predate the filter; `match=MatchSettings(..., unique_margin=0.02)` turns
# it on.
SELFCAL_MATCH = MatchSettings(klt_levels=5, klt_window_px=21, unique_margin=None)


@dataclass(frozen=True)
class SelfCalConfig:
    """Options of `calibrate_scene`.

    Attributes:
        focal_tolerance: 1-sigma spread of fx, fy about the nominal focal length, relative.
        principal_tolerance_px, k1_tolerance, k2_tolerance, rotation_tolerance_deg, position_tolerance_mm: the
            other design tolerances (1 sigma). Together they are the MAP priors; the report says for every
            parameter whether the frames or the prior determined it.
        stages: parameter groups freed by each stage, in order (groups: rotation, position, focal, principal,
            distortion, k1); when the tracks do not reach the image corners the stages free k1 alone (tracks
            half way out) or no distortion, and the final stage frees both with their design tolerances.
        track_sigma_px: the assumed tracking noise of the early stages; the final stage uses the noise measured
            from the residuals, so the reported sigmas follow the data.
        robust: the measurement kernel of the early stages, scaled by each stage's own residual sigma (default
            Huber at 2 of those sigmas; the final stage is plain least squares on the tracks
            that survive the outlier filter, so the marginals are Gaussian).
        tracks_per_frame: at most this many tracks kept per frame, spread over an 8x8 grid of image cells.
        max_frames: use at most this many frames.
        min_frames: refuse with fewer usable frames.
        max_iterations: Levenberg–Marquardt cap per stage.
        match: options of the default tracker (`lfgraph.refinement.matching.MatchSettings`); every view must see a
            track.
        tracker: what tracks features (`lfgraph.refinement.matching.Tracker`); None: ``ChainTracker(match)``.
        graph_hooks: user functions called with a `lfgraph.factors.GraphContext` (kind ``"selfcal"``) before each
            stage's graph is optimised.
        retrack: before the final stage, track every feature again from the reference view with the window warped
            by the local map the staged calibration gives (`lfgraph.selfcal.retrack`; needs the patches that
            `pool_tracks` keeps).
        pins: measurements that fix the common zoom the scene leaves to the design focal length
            (`lfgraph.selfcal.pins`: `BoardPin`, `DistancePin`, `ViewPin`), each a factor of the final stage with its
            own sigma; a pin that disagrees with the scene beyond their sigmas is refused (`PinRefused`).
    """

    focal_tolerance: float = FOCAL_TOLERANCE
    principal_tolerance_px: float = PRINCIPAL_TOLERANCE_PX
    k1_tolerance: float = K1_TOLERANCE
    k2_tolerance: float = K2_TOLERANCE
    rotation_tolerance_deg: float = ROTATION_TOLERANCE_DEG
    position_tolerance_mm: float = POSITION_TOLERANCE_MM
    stages: tuple[tuple[str, ...], ...] = DEFAULT_STAGES
    track_sigma_px: float = 0.1
    robust: NoiseSpec = "huber:2sigma"
    tracks_per_frame: int = TRACKS_PER_FRAME
    max_frames: int | None = None
    min_frames: int = 3
    max_iterations: int = 50
    match: MatchSettings = field(default_factory=lambda: SELFCAL_MATCH)
    tracker: Tracker | None = None
    graph_hooks: tuple[Callable, ...] = ()
    retrack: bool = True
    pins: tuple[Pin, ...] = ()

    def __post_init__(self) -> None:
        pins = (self.pins,) if isinstance(self.pins, PIN_TYPES) else tuple(self.pins)
        for pin in pins:
            if not isinstance(pin, PIN_TYPES):
                raise TypeError(f"SelfCalConfig.pins must hold BoardPin, DistancePin or ViewPin, got "
                                f"{type(pin).__name__}")
        if sum(isinstance(p, BoardPin) for p in pins) > 1:
            raise ValueError("SelfCalConfig.pins: one BoardPin (it may hold several frames)")
        names = [p.name for p in pins]
        if len(set(names)) != len(names):
            raise ValueError(f"SelfCalConfig.pins: two pins of one name ({', '.join(names)})")
        object.__setattr__(self, "pins", pins)
        for name in ("focal_tolerance", "principal_tolerance_px", "k1_tolerance", "k2_tolerance",
                     "rotation_tolerance_deg", "position_tolerance_mm", "track_sigma_px"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be positive, got {value}")
        stages = tuple(tuple(s) for s in self.stages)
        if not stages:
            raise ValueError("at least one stage is needed")
        for s in stages:
            unknown = set(s) - set(SELFCAL_GROUPS)
            if unknown or not s:
                raise ValueError(f"a stage frees a non-empty set of {', '.join(SELFCAL_GROUPS)}; got {s}")
        object.__setattr__(self, "stages", stages)
        object.__setattr__(self, "robust", as_noise(self.robust))
        object.__setattr__(self, "graph_hooks", as_hooks(self.graph_hooks, "SelfCalConfig.graph_hooks"))
        if not isinstance(self.match, MatchSettings):
            raise TypeError(f"SelfCalConfig.match must be a lfgraph MatchSettings, got {type(self.match).__name__}")
        object.__setattr__(self, "tracker", ChainTracker(self.match) if self.tracker is None
                           else as_tracker(self.tracker, "SelfCalConfig.tracker"))
        for name in ("tracks_per_frame", "min_frames", "max_iterations"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.max_frames is not None and self.max_frames < 1:
            raise ValueError(f"max_frames must be >= 1, got {self.max_frames}")

    @property
    def noise(self) -> Noise:
        """The normalised noise of the early stages (``robust`` after `as_noise`)."""
        return self.robust  # type: ignore[return-value]

    def sigmas(self, design: Design) -> Sigmas:
        """The design tolerances as the one sigma record (`lfgraph.core.sigmas.Sigmas`): every view of the design
        the same, about / along its own axes."""
        return Sigmas.uniform(design.rows * design.cols, float(np.radians(self.rotation_tolerance_deg)),
                              self.position_tolerance_mm / 1000.0, self.focal_tolerance * design.focal_px,
                              self.principal_tolerance_px, {"k1": self.k1_tolerance, "k2": self.k2_tolerance})
