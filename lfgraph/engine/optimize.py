"""The one optimiser entry point: Levenberg–Marquardt with an iteration callback and a frozen result."""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import gtsam

from lfgraph.engine.result import OptimizationResult
from lfgraph.engine.schur import optimize_schur
from lfgraph.engine.schur_system import NotReducible

IterationCallback = Callable[[int, float, float], None]  # (iteration, error before, error after)


@dataclass(frozen=True)
class OptimizerSettings:
    """Levenberg–Marquardt settings.

    Attributes:
        max_iterations: iteration cap.
        relative_error_tol: stop when the relative decrease of the error falls below this.
        absolute_error_tol: stop when the absolute decrease falls below this.
        error_tol: stop when the error itself falls below this.
        landmark_iterations: with ``eliminate``: after every step re-solve the landmarks with the cameras held, this
            many Gauss–Newton iterations (`lfgraph.engine.schur.GraphProblem`; 0 = plain Levenberg–Marquardt).
        diagonal_damping: GTSAM's optimiser damps each variable in proportion to its own curvature (Marquardt's
            scaling) instead of uniformly (the schur loop ignores it). Self-calibration reruns a stage with it when
            the plain run threw its landmarks behind the views (`lfgraph.selfcal.stages.MIN_FRONT_SHARE`).
    """

    max_iterations: int = 100
    relative_error_tol: float = 1e-10
    absolute_error_tol: float = 1e-12
    error_tol: float = 0.0
    landmark_iterations: int = 0
    diagonal_damping: bool = False


@contextmanager
def gtsam_quiet() -> Iterator[None]:
    """Silence what GTSAM's C++ prints to standard output (e.g. "CheiralityException: Landmark l3 behind Camera x1"
    for every point that a bad step puts behind a camera — the factor already handles it) around GTSAM calls only.

    Python's own output inside the block (a user's iteration callback) still reaches the terminal: ``sys.stdout``
    is pointed at a duplicate of the real descriptor while descriptor 1 goes to /dev/null.
    """
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # captured or replaced stdout: nothing native reaches it
        yield
        return
    sys.stdout.flush()
    saved = os.dup(fd)
    python_stdout = sys.stdout
    proxy = open(saved, "w", closefd=False, buffering=1, encoding=getattr(python_stdout, "encoding", None))  # noqa: SIM115
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), fd)
            sys.stdout = proxy
            yield
    finally:
        proxy.flush()
        sys.stdout = python_stdout
        proxy.close()
        os.dup2(saved, fd)
        os.close(saved)


def optimize(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, settings: OptimizerSettings | None = None,
             callback: IterationCallback | None = None, eliminate: str | None = None) -> OptimizationResult:
    """Run Levenberg–Marquardt on ``graph`` from ``initial``.

    Args:
        graph: the factor graph.
        initial: initial values for every key in the graph.
        settings: stopping rules; defaults to `OptimizerSettings()`.
        callback: called after every iteration with (iteration, error before, error after) — the hook that
            `lfgraph.viz` subscribes to.
        eliminate: the symbol character of 3-D landmarks to eliminate by a vectorised Schur complement
            (`lfgraph.engine.schur`: the same Levenberg–Marquardt, several times faster when every landmark is seen by
            many views); None, or a graph it cannot reduce: GTSAM's own optimiser.

    Raises:
        RuntimeError: GTSAM failed (indeterminate system, missing key); the message says which.
    """
    settings = settings or OptimizerSettings()
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(settings.max_iterations)
    params.setRelativeErrorTol(settings.relative_error_tol)
    params.setAbsoluteErrorTol(settings.absolute_error_tol)
    params.setErrorTol(settings.error_tol)
    if settings.diagonal_damping:
        params.setDiagonalDamping(True)
    history: list[float] = []

    def hook(iteration: int, before: float, after: float) -> None:
        if not history:
            history.append(before)
        history.append(after)
        if callback is not None:
            callback(iteration, before, after)

    params.iterationHook = hook
    start = time.perf_counter()
    if eliminate is not None:

        try:
            with gtsam_quiet():
                res = optimize_schur(graph, initial, eliminate, settings.max_iterations, settings.relative_error_tol,
                                     settings.absolute_error_tol, settings.error_tol, callback,
                                     settings.landmark_iterations)
        except NotReducible:
            pass
        except RuntimeError as exc:
            raise RuntimeError(f"optimisation failed: {exc}") from exc
        else:
            return res
    try:
        with gtsam_quiet():
            optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
            initial_error = graph.error(initial)
            values = optimizer.optimize()
            final_error = graph.error(values)
    except RuntimeError as exc:
        raise RuntimeError(f"optimisation failed: {exc}") from exc
    seconds = time.perf_counter() - start
    iterations = optimizer.iterations()
    converged = iterations < settings.max_iterations
    return OptimizationResult(values, initial_error, final_error, iterations, converged, seconds,
                              tuple(history) or (initial_error,))
