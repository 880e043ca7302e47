"""The one stage schedule below the tracked wings: `refine` / `check` (`lfgraph.refinement.fit`) and
`calibrate-scene` (`lfgraph.selfcal.pipeline`).

A schedule is a list of `Step` values run in order on a `TrackState` (the calibration, the tracks still used and their
landmarks). For every step `run_schedule` owns what the wings used to spell each in their own loop:

1. the step's ``prepare`` (refine: DLT landmarks from the calibration so far, `triangulated`, and its clean stage's
   worst-error filter; calibrate-scene: which groups the tracks' coverage lets it free — or None, skipping the step);
2. the reprojection RMS before, ``observer.stage_start``;
3. the step's ``solve``: the wing's `lfgraph.engine.stage_engine.StagePlan` on `run_plan`, returning the new state and
   the optimiser's iterations;
4. the step's ``tidy`` (calibrate-scene: landmarks behind a view or without depth);
5. the reprojection errors after, the outlier rule (the one mismatch rule, `drop_mismatches`, unless the step says
   ``outliers=False``), one `StageRecord`, ``observer.stage_end`` / ``outliers`` and the step's log line;
6. the kept tracks, and the step's ``check`` (calibrate-scene: enough tracks left, the coverage after the poses).

`at_supported_sigma` is the one "refit at the sigma the residuals support" loop: refine's first pass at 1 px or at
the sigma the previous frames supported, and calibrate-scene's final stage repeated until its residuals agree with the
noise it assumed.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, TypeVar

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.observer import Observer, StageEnd
from lfgraph.engine.triangulate import (
    drop_mismatches,
    finite_rms,
    normalized_coordinates,
    reprojection_errors,
    triangulate_dlt,
)


@dataclass(frozen=True)
class TrackState:
    """What a schedule carries from stage to stage: the calibration, the tracks still used — (V, N, 2) ``pixels``,
    (V, N) ``valid`` and ``index`` (N,), each track's column in the schedule's input — their (N, 3) landmarks in the
    reference frame (m), and ``tracks``: a wing's own record of them (anything with ``subset(mask)``, kept in step)."""
    calib: Calibration
    pixels: np.ndarray
    valid: np.ndarray
    points: np.ndarray
    index: np.ndarray
    tracks: Any = None

    @classmethod
    def start(cls, calib: Calibration, pixels: np.ndarray, valid: np.ndarray, points: np.ndarray | None = None,
              tracks: Any = None) -> TrackState:
        """Every input track, with ``points`` (None: none yet, ``prepare`` triangulates them)."""
        n = valid.shape[1]
        return cls(calib, pixels, valid, np.full((n, 3), np.nan) if points is None else points, np.arange(n), tracks)

    def subset(self, keep: np.ndarray) -> TrackState:
        """The tracks where ``keep`` (N,) is true."""
        return replace(self, pixels=self.pixels[:, keep], valid=self.valid[:, keep], points=self.points[keep],
                       index=self.index[keep], tracks=None if self.tracks is None else self.tracks.subset(keep))

    def errors(self) -> np.ndarray:
        """(V, N) reprojection errors (px; NaN where a view does not see the track)."""
        return reprojection_errors(self.calib, self.points, self.pixels, self.valid)

    def kept(self, num_tracks: int) -> np.ndarray:
        """(num_tracks,) mask of the schedule's input tracks still used."""
        keep = np.zeros(num_tracks, dtype=bool)
        keep[self.index] = True
        return keep


def _same(state: TrackState) -> TrackState:
    return state


def _nothing(state: TrackState, record: StageRecord) -> None:
    return None


@dataclass(frozen=True)
class Step:
    """One stage of a schedule, as a wing passes it: its name, its ``solve`` (the stage's plan on
    `lfgraph.engine.stage_engine.run_plan`: the state -> the new state and the iterations), and the wing's small steps
    around it (see the module's order): ``prepare`` (None skips the step), ``tidy``, ``check``; ``outliers``: whether
    the one mismatch rule drops tracks after it; ``describe``: the stage's log line from its record."""
    name: str
    solve: Callable[[TrackState], tuple[TrackState, int]]
    prepare: Callable[[TrackState], TrackState | None] = _same
    tidy: Callable[[TrackState], TrackState] = _same
    check: Callable[[TrackState, StageRecord], None] = _nothing
    outliers: bool = True
    describe: Callable[[StageRecord], str] | None = None


@dataclass(frozen=True)
class StageFigures:
    """One stage's figures, as every wing reports them: its name, the tracks (landmarks) and observations it used,
    the reprojection RMS before and after (px), the optimiser's iterations and the seconds."""
    name: str
    landmarks: int
    observations: int
    rms_before_px: float
    rms_after_px: float
    iterations: int
    seconds: float


@dataclass(frozen=True)
class StageRecord(StageFigures):
    """One stage as the schedule ran it: its figures, and ``before`` / ``state``: the calibration it started from and
    the state it ended in (before the outlier rule); ``errors``: (V, N) reprojection errors of that state (px);
    ``dropped``: (N,) the tracks the outlier rule dropped after it."""
    before: Calibration = field(repr=False)
    state: TrackState = field(repr=False)
    errors: np.ndarray = field(repr=False)
    dropped: np.ndarray = field(repr=False)


def run_schedule(steps: Sequence[Step], state: TrackState,
                 observer: Observer) -> tuple[TrackState, list[StageRecord]]:
    """Run ``steps`` in order from ``state`` (see the module's docstring). Returns the last state (outliers dropped)
    and one record per step run."""
    records: list[StageRecord] = []
    for step in steps:
        t0 = time.perf_counter()
        prepared = step.prepare(state)
        if prepared is None:
            continue
        state = prepared
        rms_before = finite_rms(state.errors())
        observer.stage_start(step.name, int(state.valid.sum()))
        before = state.calib
        state, iterations = step.solve(state)
        state = step.tidy(state)
        errors = state.errors()
        good = drop_mismatches(errors) if step.outliers else np.ones(errors.shape[1], dtype=bool)
        record = StageRecord(step.name, int(state.valid.shape[1]), int(state.valid.sum()), rms_before,
                             finite_rms(errors), iterations, time.perf_counter() - t0, before, state, errors, ~good)
        records.append(record)
        observer.stage_end(StageEnd(step.name, state.calib, state.points, state.pixels, state.valid, errors))
        if step.describe is not None:
            observer.log(step.describe(record))
        observer.outliers(step.name, state.pixels[:, ~good], state.valid[:, ~good])
        state = state.subset(good)
        step.check(state, record)
    return state, records


class Triangulator:
    """A refinement stage's landmarks: N-view DLT from the calibration so far, the observations' undistorted
    coordinates recomputed only when a stage has moved the intrinsics."""

    def __init__(self, pixels: np.ndarray, valid: np.ndarray):
        self._pixels, self._valid = pixels, valid
        self._norm, self._intrinsics = None, None

    def __call__(self, state: TrackState) -> TrackState:
        """``state`` with DLT landmarks for its tracks."""
        calib = state.calib
        if self._intrinsics != calib.intrinsics:
            self._norm, self._intrinsics = normalized_coordinates(calib, self._pixels, self._valid), calib.intrinsics
        points = triangulate_dlt(calib, state.pixels, state.valid, self._norm[:, state.index])
        return replace(state, points=points)


R = TypeVar("R")


def at_supported_sigma(fit: Callable[[float, int], R], sigma: float, supported: Callable[[R], float],
                       agree: Callable[[float, float, R], bool], passes: int) -> tuple[R, float]:
    """The one refit loop: fit at ``sigma`` (``fit(sigma, pass)``); while the sigma the fit's residuals support
    (``supported``) disagrees with the one it assumed (``agree(supported, assumed, fit)`` false) and passes remain, fit
    again at the supported one. Returns the last fit and the sigma it assumed (what its marginals scale with)."""
    for k in range(passes):
        result = fit(sigma, k)
        measured = supported(result)
        if k == passes - 1 or agree(measured, sigma, result):
            return result, sigma
        sigma = measured
    raise ValueError("at_supported_sigma needs at least one pass")
