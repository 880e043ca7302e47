"""One observer for everything the estimators report while they run: log lines, optimiser iterations, frames,
stages, outliers.

`calibrate` and `refine` take ``observer=``; without one they log through Python's `logging` (logger
``lfgraph``). Subclass `BaseObserver` and override what you need; `lfgraph.viz.RerunLogger` is one; `Observers`
fans out to several. The core never imports rerun.

    class Printer(lf.BaseObserver):
        def iteration(self, i, before, after):
            print(f"LM {i}: {before:.3g} -> {after:.3g}")
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from lfgraph.core.calibration import Calibration

LOG = logging.getLogger("lfgraph")
WARNING_PREFIX = "warning: "  # a progress line that is a warning (logged at WARNING by `BaseObserver`)


@dataclass(frozen=True)
class StageEnd:
    """A refinement stage has run.

    Attributes:
        name: the stage (``points``, ``poses``, ``clean``, ...).
        calib: the calibration after it.
        points_ref_m: (N, 3) landmarks in the reference frame.
        pixels_px: (V, N, 2) the observations it used; valid: (V, N).
        errors_px: (V, N) reprojection errors after it (NaN where not observed).
    """

    name: str
    calib: Calibration
    points_ref_m: np.ndarray
    pixels_px: np.ndarray
    valid: np.ndarray
    errors_px: np.ndarray


@runtime_checkable
class Observer(Protocol):
    """What `calibrate` and `refine` call while they run (every method optional through `BaseObserver`)."""

    def log(self, message: str) -> None:
        """A progress line (stage summaries, warnings)."""

    def iteration(self, iteration: int, error_before: float, error_after: float) -> None:
        """One Levenberg–Marquardt iteration of the graph being optimised."""

    def frame(self, index: int, images: np.ndarray) -> None:
        """Refinement starts on frame ``index``: (V, H, W) images (a list of (H, W) when the views differ in size)."""

    def stage_start(self, name: str, measurements: int) -> None:
        """A refinement stage starts over ``measurements`` 2-D observations."""

    def stage_end(self, event: StageEnd) -> None:
        """A refinement stage has run."""

    def outliers(self, name: str, pixels_px: np.ndarray, valid: np.ndarray) -> None:
        """Observations a stage's outlier rejection dropped: (V, N, 2) and (V, N)."""


class BaseObserver:
    """No-op implementations of every `Observer` method, and `log` through `logging`: subclass and override."""

    def log(self, message: str) -> None:
        """Through `logging` (logger ``lfgraph``): a line starting ``warning:`` at WARNING, the rest at INFO."""
        if message.startswith(WARNING_PREFIX):
            LOG.warning(message[len(WARNING_PREFIX):])
        else:
            LOG.info(message)

    def iteration(self, iteration: int, error_before: float, error_after: float) -> None:
        """Called by ``refine`` (every stage) and ``calibrate`` (its joint graph) after every Levenberg–Marquardt
        iteration: ``iteration`` its number, ``error_before`` / ``error_after`` the graph error (GTSAM's: 0.5 x the sum
        of squared whitened residuals; for ``refine`` in units of the stage's `measurement_sigma`). No-op here."""
        pass

    def frame(self, index: int, images: np.ndarray) -> None:
        """Called by ``refine`` as it starts on frame ``index`` (0-based) with that frame's (V, H, W) images, before its
        tracks are judged. No-op here."""
        pass

    def stage_start(self, name: str, measurements: int) -> None:
        """Called by ``refine`` before each stage is optimised: ``name`` the stage (``points``, ``poses``, ``clean``,
        ...), ``measurements`` the number of valid 2-D observations it uses. No-op here."""
        pass

    def stage_end(self, event: StageEnd) -> None:
        """Called by ``refine`` after each stage has been optimised, with its `StageEnd`. No-op here."""
        pass

    def outliers(self, name: str, pixels_px: np.ndarray, valid: np.ndarray) -> None:
        """Called by ``refine`` after each stage with the observations its outlier rejection dropped: (V, K, 2)
        pixels and (V, K) validity (K = 0 when none was dropped, always after ``clean``). No-op here."""
        pass

    def measurement_sigma(self, sigma_px: float) -> None:
        """The pixel sigma of the stage that starts next: the graph errors of its iterations are in its units
        (optional: called only on observers that have it)."""

    def run_start(self, kind: str, calib: Calibration | None) -> None:
        """A run starts (``kind`` ``refine`` from ``calib``, ``calibrate`` from None) (optional)."""

    def run_end(self, kind: str, before: Calibration | None, after: Calibration, report: Any,
                data: Any = None) -> None:
        """A run ended: ``after`` is what it returns (for ``refine`` the input where nothing was applied),
        ``report`` its report, ``data`` what it ran on (``calibrate``: the board observations) (optional)."""


class SilentObserver(BaseObserver):
    """Hears nothing, logs nothing: for fits whose stages are not the result (held-out refits, screening passes)."""

    def log(self, message: str) -> None:
        """Drop the line."""
        pass


class Observers(BaseObserver):
    """Several observers as one (each gets every call, in order)."""

    def __init__(self, *observers: Observer) -> None:
        self.observers = tuple(o for o in observers if o is not None)

    def log(self, message: str) -> None:
        """Pass the line to every observer, in order."""
        for o in self.observers:
            o.log(message)

    def iteration(self, iteration: int, error_before: float, error_after: float) -> None:
        """Pass the call to every observer, in order."""
        for o in self.observers:
            o.iteration(iteration, error_before, error_after)

    def frame(self, index: int, images: np.ndarray) -> None:
        """Pass the call to every observer, in order."""
        for o in self.observers:
            o.frame(index, images)

    def stage_start(self, name: str, measurements: int) -> None:
        """Pass the call to every observer, in order."""
        for o in self.observers:
            o.stage_start(name, measurements)

    def stage_end(self, event: StageEnd) -> None:
        """Pass the call to every observer, in order."""
        for o in self.observers:
            o.stage_end(event)

    def outliers(self, name: str, pixels_px: np.ndarray, valid: np.ndarray) -> None:
        """Pass the call to every observer, in order."""
        for o in self.observers:
            o.outliers(name, pixels_px, valid)

    def measurement_sigma(self, sigma_px: float) -> None:
        """Pass the call to every observer that has this optional method (`tell`)."""
        for o in self.observers:
            tell(o, "measurement_sigma", sigma_px)

    def run_start(self, kind: str, calib: Calibration | None) -> None:
        """Pass the call to every observer that has this optional method (`tell`)."""
        for o in self.observers:
            tell(o, "run_start", kind, calib)

    def run_end(self, kind: str, before: Calibration | None, after: Calibration, report: Any,
                data: Any = None) -> None:
        """Pass the call to every observer that has this optional method (`tell`)."""
        for o in self.observers:
            tell(o, "run_end", kind, before, after, report, data)


def tell(observer: Observer, method: str, *args: Any) -> None:
    """Call an optional observer method (``measurement_sigma``, ``run_start``, ``run_end``) where it exists."""
    fn = getattr(observer, method, None)
    if callable(fn):
        fn(*args)


def resolve(observer: Observer | None) -> Observer:
    """The observer to call: the given one, or one that logs through `logging`."""
    if observer is not None and not isinstance(observer, Observer):
        raise TypeError(f"observer must be an lfgraph Observer (log, iteration, ...; e.g. lfgraph.viz.RerunLogger or "
                        f"a BaseObserver subclass), got {type(observer).__name__}")
    return BaseObserver() if observer is None else observer
