"""What an optimisation did: the result type shared by GTSAM's optimiser (`lfgraph.engine.optimize`) and the
Schur-complement one (`lfgraph.engine.schur`), kept apart so that neither imports the other's module for it."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam


@dataclass(frozen=True)
class OptimizationResult:
    """What an optimisation did. ``values`` must not be modified (copy before inserting)."""

    values: gtsam.Values
    initial_error: float
    final_error: float
    iterations: int
    converged: bool
    seconds: float
    error_history: tuple[float, ...]
