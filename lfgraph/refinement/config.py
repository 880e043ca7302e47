"""Options of the auto-refinement, typed and parsed once (strings from the CLI become enums and kernels here)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, fields
from enum import StrEnum

import numpy as np

from lfgraph.core.sigmas import Sigmas
from lfgraph.factors import groups
from lfgraph.factors.groups import Group
from lfgraph.factors.hooks import as_hooks
from lfgraph.factors.noise import Noise, NoiseSpec, as_noise
from lfgraph.refinement.matching import MatchSettings, Tracker, as_tracker
from lfgraph.refinement.trackers import AutoTracker


class Stage(StrEnum):
    """One stage of the schedule (see `lfgraph.refinement.stages`)."""

    POINTS = "points"  # cameras constant, only landmarks move
    INTRINSICS = "intrinsics"  # fx, fy, cx, cy free; distortion and poses held
    POSES = "poses"  # poses free except the reference (gauge); intrinsics constant
    ALL = "all"  # poses and fx, fy, cx, cy free; distortion held
    CLEAN = "clean"  # drop outlying tracks, repeat the previous free stage

    @property
    def groups(self) -> frozenset[Group]:
        """What the stage frees of each free view (`lfgraph.factors.groups`): the pose (``poses``), fx fy cx cy
        (``intrinsics``), both (``all``), nothing (``points``; ``clean`` repeats the stage before it)."""
        pose, intrinsics = {Group.ROTATION, Group.POSITION}, {Group.INTRINSICS}
        return frozenset({Stage.POSES: pose, Stage.INTRINSICS: intrinsics, Stage.ALL: pose | intrinsics}.get(self, ()))

    @property
    def frees_poses(self) -> bool:
        """Whether the stage frees the views' poses (``poses``, ``all``)."""
        return groups.frees_pose(self.groups)

    @property
    def frees_intrinsics(self) -> bool:
        """Whether the stage frees fx, fy, cx, cy (``intrinsics``, ``all``)."""
        return groups.frees_intrinsics(self.groups)

    @property
    def free_per_view(self) -> int:
        """Parameters this stage frees per free view: 6 (pose) and/or 4 (fx, fy, cx, cy); 0 for points/clean."""
        return groups.parameters_per_view(self.groups)


class TriangulationFilter(StrEnum):
    """Which tracks survive triangulation (`lfgraph.engine.triangulate`)."""

    MEDIAN = "median"  # the paper's: keep tracks whose reference-view error is <= the median
    WORST = "worst"  # drop tracks whose worst error is > 4x the median track's and > 0.5 px
    NONE = "none"


SCHEDULES: dict[str, tuple[Stage, ...]] = {
    "paper": (Stage.POINTS, Stage.INTRINSICS, Stage.ALL),
    "default": (Stage.POINTS, Stage.POSES, Stage.CLEAN),
}


def parse_stages(spec: str | Iterable[str | Stage]) -> tuple[Stage, ...]:
    """``"paper"``, ``"default"``, a comma list such as ``"points,poses"`` or a sequence of stages.

    Raises:
        ValueError: an empty schedule, an unknown stage (named), or ``clean`` first.
    """
    if isinstance(spec, str):
        if spec in SCHEDULES:
            return SCHEDULES[spec]
        names: tuple = tuple(s.strip() for s in spec.split(",") if s.strip())
    else:
        names = tuple(spec)
    if not names:
        raise ValueError("the stage schedule is empty")
    stages = []
    for n in names:
        try:
            stages.append(Stage(n))
        except ValueError:
            raise ValueError(f"unknown stage {n!r}; stages are {', '.join(Stage)} (or the schedules "
                             f"{', '.join(SCHEDULES)})") from None
    if stages[0] is Stage.CLEAN:
        raise ValueError("'clean' repeats a previous stage, so it cannot come first")
    return tuple(stages)


def schedule_name(stages: tuple[Stage, ...]) -> str:
    """``paper``/``default`` for the named schedules, else the comma list."""
    for name, s in SCHEDULES.items():
        if s == stages:
            return name
    return ",".join(stages)


DRIFT_SIGMA_RANGE = (1e-3, 1e4)  # deg, mm or px: below, a group is held (numerically, not by choice); above, free


@dataclass(frozen=True)
class DriftModel:
    """How far a calibrated view may plausibly have moved since calibration: the 1-sigma of the drift prior, per
    parameter group. Every refined parameter gets a prior centred on the input calibration whose sigma is this drift
    combined (root sum of squares) with the input's own uncertainty (``metrics["sigmas"]`` stored by ``calibrate``,
    when present). Directions the scene does not determine therefore stay where they were (MAP, not a free fit).

    Attributes:
        roll_deg: rotation about the view's optical axis (body z).
        pan_tilt_deg: rotation about the view's x and y axes (these trade against position when tracks are few or
            all at one depth).
        position_mm: optical centre, per axis.
        focal_px: fx, fy (only when a stage frees intrinsics).
        principal_px: cx, cy (only when a stage frees intrinsics).
    """

    roll_deg: float = 1.0
    pan_tilt_deg: float = 0.5
    position_mm: float = 5.0
    focal_px: float = 3.0
    principal_px: float = 3.0

    def __post_init__(self) -> None:
        for name in ("roll_deg", "pan_tilt_deg", "position_mm", "focal_px", "principal_px"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and DRIFT_SIGMA_RANGE[0] <= value <= DRIFT_SIGMA_RANGE[1]):
                raise ValueError(f"drift sigma {name} must be a number from {DRIFT_SIGMA_RANGE[0]:g} to "
                                 f"{DRIFT_SIGMA_RANGE[1]:g}, got {value!r}")

    @classmethod
    def of(cls, value: DriftModel | str | Mapping[str, float] | None) -> DriftModel:
        """A `DriftModel` from itself, its text form (`parse`), a mapping of field names to sigmas, or None (the
        defaults).

        Raises:
            TypeError: another kind of value; ValueError: an unknown field or a sigma out of range.
        """
        if value is None:
            return cls()
        if isinstance(value, DriftModel):
            return value
        if isinstance(value, str):
            return cls.parse(value)
        if isinstance(value, Mapping):
            names = {f.name for f in fields(cls)}
            unknown = sorted(set(map(str, value)) - names)
            if unknown:
                raise ValueError(f"unknown drift sigma {', '.join(unknown)}; the fields are {', '.join(sorted(names))}")
            return cls(**value)
        raise TypeError(f"drift must be a DriftModel, a text such as 'roll_deg=2' or a mapping such as "
                        f"{{'roll_deg': 2}}; got {type(value).__name__}")

    def sigmas(self, num_views: int) -> Sigmas:
        """The drift as the one sigma record: pan/tilt about each view's x and y, roll about z, position along each
        axis, fx fy cx cy, the same for every view."""
        pan_tilt, roll = np.radians(self.pan_tilt_deg), np.radians(self.roll_deg)
        return Sigmas.uniform(num_views, (pan_tilt, pan_tilt, roll), 1e-3 * self.position_mm, self.focal_px,
                              self.principal_px)

    @classmethod
    def parse(cls, spec: str | None) -> DriftModel:
        """``"roll_deg=2,position_mm=3"`` (any subset of the fields; empty or None: the defaults).

        Raises:
            ValueError: an unknown field (named) or a value that is not a positive number.
        """
        if not spec:
            return cls()
        kwargs = {}
        names = {f.name for f in fields(cls)}
        for item in spec.split(","):
            key, _, value = item.strip().partition("=")
            if key not in names:
                raise ValueError(f"unknown drift sigma {key!r}; choose from {', '.join(sorted(names))}")
            try:
                kwargs[key] = float(value)
            except ValueError:
                raise ValueError(f"drift sigma {key} must be a number, got {value!r}") from None
        return cls(**kwargs)


@dataclass(frozen=True)
class RefineConfig:
    """Options of the refinement. Everything is validated and normalised on construction.

    Attributes:
        stages: the schedule: a `Stage` sequence, ``"default"`` (points, poses, clean), ``"paper"`` (points,
            intrinsics, all) or a comma list.
        robust: the measurement noise model of every stage: a kernel name (``"huber:0.2"`` — thresholds in
            pixels —, ``"cauchy"`` — its usual constant, in measurement sigmas —, ``"huber:1.345sigma"``,
            ``"none"``), a `RobustKernel`, any ``gtsam.noiseModel.mEstimator`` object (wrapped around the isotropic
            ``measurement_sigma_px``: its threshold is then in sigmas), or a full ``gtsam`` noise model (used as it
            is). Every one runs on the bulk solver (`lfgraph.engine.bulk_noise`). It governs the gates too: under a
            kernel the estimated sigma is the residuals' robust scale, and the held-out and another-camera tests
            compare the kernel's cost (`lfgraph.refinement.assess`).
        clean_robust: the ``clean`` stage's own noise model; None (default) uses ``robust``.
        measurement_sigma_px: the feature position noise per coordinate (px); None (default): estimated from the
            residuals of a first fit (their mean square; their median under a robust kernel; floored at
            ``MIN_MEASUREMENT_SIGMA_PX``), so the priors weigh what they should.
        drift: the drift model (`DriftModel`): sigmas of the priors centred on the input calibration.
        priors: True (default): maximum a posteriori with the drift priors; False: the free fit of the paper (every
            freed parameter moves without a pull; scale by one range), still judged by the acceptance below.
        folds: held-out validation: tracks are split into this many folds; each fold is refitted without its tracks
            and must predict them at least as well as the input calibration does (0: no held-out test).
        significance_sigma: a view's change counts only if its Mahalanobis distance under the posterior covariance
            exceeds the chi-square quantile equivalent to this many sigmas (one-sided normal); otherwise the view
            keeps its input parameters.
        uncertain_transfer_px: a view whose change is not significant, or significant but within
            ``tolerance_px``, is OK when its posterior predicts at most this transfer error at infinity (1-sigma,
            px), else UNCERTAIN (the data could hide a drift that large). (A
            significant change is applied only if what the fit leaves undetermined at infinity is at most its size /
            ``significance_sigma``.)
        tolerance_px: a practical tolerance (px of transfer at infinity, RMS over the reference image; default
            0.1): a view is DRIFTED, and its change applied, only when the change is significant *and* moves the
            view's transfer at infinity by more than this. A significant change within it is reported as OK with its
            size and not applied (0: apply every significant change).
        triangulation_filter: ``median`` (the paper: keep tracks whose reference-view error is <= the median; it
            halves the tracks and favours the image centre), ``worst`` (drop tracks whose worst error is > 4x the
            median track's and > 0.5 px) or ``none``; default: ``median`` with the paper's schedule, else ``worst``.
        max_frames: use at most this many frames (None: all).
        target_rms_px: stop adding frames once a new frame's tracks fit the current calibration at this RMS.
        scale_sigma_mm: None (default): scale is fixed by one range and the result rescaled to the calibrated
            baselines (least squares); a number: weak priors of this sigma on every view's position instead (the
            simpler scheme, which pulls positions back and biases rotations by ~position error / depth).
        max_iterations: LM cap per stage.
        min_improvement: keep the input calibration unless the refits predict the held-out tracks better by at least
            this factor (held-out RMS input / refined; 1 = not worse). The RMS of the tracks a fit used is never the
            test: any refit lowers it.
        max_landmarks: cap of the pooled tracks (a seeded random subset is kept when frames bring more): memory and
            time of the adjustment grow with them (~200 MB and ~0.5 s per 1000 landmarks of a 5x5 rig) while the
            accuracy has stopped improving well before (measured in `benchmarks/refine.py`). None: no cap.
        min_view_observations: a view with fewer kept observations is held where it is (its pose alone is too
            weakly determined: on the Middlebury ring, views with 3-9 observations drifted by 10-35 degrees).
        graph_hooks: user functions called with a `lfgraph.factors.GraphContext` after each stage's graph is built
            and before it is optimised: add factors or priors of your own (see `lfgraph.factors.hooks`).
        match: the options of the default tracker's chain KLT.
        tracker: what tracks features through the grid (`lfgraph.refinement.matching.Tracker`: an object with
            ``track(images, grid) -> Tracks``); None (default): ``AutoTracker(match)``, on a grid the paper's chain
            KLT, on a free arrangement (a ring) KLT or SIFT by the angle between linked views.
            ``lfgraph.refinement.tracks.OutlierTracker`` wraps one with a share of wrong matches (a study).
    """

    stages: tuple[Stage, ...] | str = "default"
    robust: NoiseSpec = None
    clean_robust: NoiseSpec = None
    measurement_sigma_px: float | None = None
    triangulation_filter: TriangulationFilter | str | None = None
    max_frames: int | None = None
    target_rms_px: float | None = None
    scale_sigma_mm: float | None = None
    max_iterations: int = 100
    min_improvement: float = 1.0
    max_landmarks: int | None = 2000
    min_view_observations: int = 30
    graph_hooks: tuple[Callable, ...] = ()
    match: MatchSettings = field(default_factory=MatchSettings)
    tracker: Tracker | None = None
    drift: DriftModel = field(default_factory=DriftModel)
    priors: bool = True
    folds: int = 3
    significance_sigma: float = 3.0
    uncertain_transfer_px: float = 0.2
    tolerance_px: float = 0.1

    def __post_init__(self) -> None:
        if not isinstance(self.match, MatchSettings):
            raise TypeError(f"RefineConfig.match must be a lfgraph MatchSettings, got {type(self.match).__name__}")
        object.__setattr__(self, "tracker", AutoTracker(self.match) if self.tracker is None
                           else as_tracker(self.tracker, "RefineConfig.tracker"))
        stages = parse_stages(self.stages)
        object.__setattr__(self, "stages", stages)
        if self.triangulation_filter is None:  # the paper's schedule comes with the paper's filter
            tf = TriangulationFilter.MEDIAN if stages == SCHEDULES["paper"] else TriangulationFilter.WORST
        else:
            try:
                tf = TriangulationFilter(self.triangulation_filter)
            except ValueError:
                raise ValueError(f"triangulation_filter must be one of {', '.join(TriangulationFilter)}, "
                                 f"got {self.triangulation_filter!r}") from None
        object.__setattr__(self, "triangulation_filter", tf)
        object.__setattr__(self, "robust", as_noise(self.robust))
        if self.clean_robust is not None:
            object.__setattr__(self, "clean_robust", as_noise(self.clean_robust))
        object.__setattr__(self, "graph_hooks", as_hooks(self.graph_hooks, "RefineConfig.graph_hooks"))
        object.__setattr__(self, "drift", DriftModel.of(self.drift))
        if self.folds < 0 or self.folds == 1:
            raise ValueError(f"folds must be 0 (no held-out test) or >= 2, got {self.folds}")
        if not (np.isfinite(self.tolerance_px) and self.tolerance_px >= 0):
            raise ValueError(f"tolerance_px must be a number >= 0, got {self.tolerance_px}")
        if not self.significance_sigma > 0:
            raise ValueError(f"significance_sigma must be positive, got {self.significance_sigma}")
        if self.measurement_sigma_px is not None and not (self.measurement_sigma_px > 0):
            raise ValueError(f"measurement_sigma_px must be positive, got {self.measurement_sigma_px}")
        if self.max_frames is not None and self.max_frames < 1:
            raise ValueError(f"max_frames must be >= 1, got {self.max_frames}")
        if self.max_landmarks is not None and self.max_landmarks < 10:
            raise ValueError(f"max_landmarks must be >= 10, got {self.max_landmarks}")
        if self.scale_sigma_mm is not None and self.scale_sigma_mm <= 0:
            raise ValueError(f"scale_sigma_mm must be positive, got {self.scale_sigma_mm}")

    @property
    def noise(self) -> Noise:
        """The normalised noise of the free stages."""
        return self.robust  # type: ignore[return-value]

    @property
    def clean_noise(self) -> Noise:
        """The normalised noise of the clean stage (the stages' own unless set)."""
        return self.robust if self.clean_robust is None else self.clean_robust  # type: ignore[return-value]
