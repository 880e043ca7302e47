"""Options of the auto-refinement, typed and parsed once (strings from the CLI become enums and kernels here)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from enum import StrEnum

from lfgraph.factors.noise import Noise, NoiseSpec, as_noise
from lfgraph.refinement.matching import MatchSettings


class Stage(StrEnum):
    """One stage of the schedule (see `lfgraph.refinement.stages`)."""

    POINTS = "points"  # cameras constant, only landmarks move
    INTRINSICS = "intrinsics"  # fx, fy, cx, cy free; distortion and poses held
    POSES = "poses"  # poses free except the reference (gauge); intrinsics constant
    ALL = "all"  # poses and fx, fy, cx, cy free; distortion held
    CLEAN = "clean"  # drop outlying tracks, repeat the previous free stage


class TriangulationFilter(StrEnum):
    """Which tracks survive triangulation (`lfgraph.refinement.triangulate`)."""

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


@dataclass(frozen=True)
class RefineConfig:
    """Options of the refinement. Everything is validated and normalised on construction.

    Attributes:
        stages: the schedule: a `Stage` sequence, ``"default"`` (points, poses, clean), ``"paper"`` (points,
            intrinsics, all) or a comma list.
        robust: the measurement noise model of every stage: a kernel name (``"huber:1.345"``, ``"cauchy:0.5"``,
            ``"none"``), a `RobustKernel`, any ``gtsam.noiseModel.mEstimator`` object (wrapped around the isotropic
            ``measurement_sigma_px``), or a full ``gtsam`` noise model (used as it is). Thresholds are in sigmas.
        clean_robust: the ``clean`` stage's own noise model; None (default) uses ``robust``.
        measurement_sigma_px: the feature position noise per coordinate (px).
        triangulation_filter: ``median`` (the paper: keep tracks whose reference-view error is <= the median; it
            halves the tracks and favours the image centre), ``worst`` (drop tracks whose worst error is > 4x the
            median track's and > 0.5 px) or ``none``; default: ``median`` with the paper's schedule, else ``worst``.
        max_frames: use at most this many frames (None: all).
        target_rms_px: stop adding frames once a new frame's tracks fit the current calibration at this RMS.
        scale_sigma_mm: None (default): scale is fixed by one range and the result rescaled to the calibrated
            baselines (least squares); a number: weak priors of this sigma on every view's position instead (the
            simpler scheme, which pulls positions back and biases rotations by ~position error / depth).
        max_iterations: LM cap per stage.
        min_improvement: keep the input calibration unless the refined one lowers the RMS of the kept tracks by at
            least this factor — with no real drift, a refit only chases the tracks' own small biases (1 = always
            accept).
        max_landmarks: cap of the pooled tracks (a seeded random subset is kept when frames bring more): memory and
            time of the adjustment grow with them (~200 MB and ~0.5 s per 1000 landmarks of a 5x5 rig) while the
            accuracy has stopped improving well before (measured in `benchmarks/refine.py`). None: no cap.
        min_view_observations: a view with fewer kept observations is held where it is (its pose alone is too
            weakly determined: on the Middlebury ring, views with 3-9 observations drifted by 10-35 degrees).
        graph_hooks: user functions called with a `lfgraph.factors.GraphContext` after each stage's graph is built
            and before it is optimised: add factors or priors of your own (see `lfgraph.factors.hooks`).
        match: feature tracking options.
    """

    stages: tuple[Stage, ...] | str = "default"
    robust: NoiseSpec = None
    clean_robust: NoiseSpec = None
    measurement_sigma_px: float = 1.0
    triangulation_filter: TriangulationFilter | str | None = None
    max_frames: int | None = None
    target_rms_px: float | None = None
    scale_sigma_mm: float | None = None
    max_iterations: int = 100
    min_improvement: float = 1.1
    max_landmarks: int | None = 2000
    min_view_observations: int = 30
    graph_hooks: tuple[Callable, ...] = ()
    match: MatchSettings = field(default_factory=MatchSettings)

    def __post_init__(self) -> None:
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
        object.__setattr__(self, "graph_hooks", tuple(self.graph_hooks))
        if not (self.measurement_sigma_px > 0):
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
