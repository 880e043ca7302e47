"""``json`` (export, import): lfgraph's own ``calibration.json`` (`Calibration.save` / `Calibration.load`), the
only format that keeps the rectification and the metrics."""

from __future__ import annotations

from pathlib import Path

from lfgraph.core.calibration import Calibration
from lfgraph.interop.common import GridLike, fit_grid


def write(calib: Calibration, path: Path) -> None:
    """Write ``calib`` as lfgraph's own ``calibration.json`` (atomically)."""
    calib.save(path)


def read(path: Path, grid: GridLike) -> Calibration:
    """Read an lfgraph ``calibration.json``; ``grid`` is checked against it (or moves its reference)."""
    return fit_grid(Calibration.load(path), grid, path, "views")
