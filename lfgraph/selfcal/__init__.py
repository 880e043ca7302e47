"""Target-less self-calibration of a camera array from design values and ordinary scene frames (issue 17).

    from lfgraph.selfcal import Design, calibrate_scene
    design = Design(rows=5, cols=5, pitch_mm=100, focal_px=700, image_size_px=(512, 512))
    calib, report = calibrate_scene(lf.open_capture("scenes/", design.grid).frames(), design)
    print(report.text())

Names load on first use (the CLI reads `lfgraph.selfcal.defaults` without importing GTSAM).
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "Design": "lfgraph.selfcal.config",
    "SelfCalConfig": "lfgraph.selfcal.config",
    "focal_from_lens": "lfgraph.selfcal.config",
    "SelfCalibrationError": "lfgraph.selfcal.stages",
    "calibrate_scene": "lfgraph.selfcal.pipeline",
    "calibrate_tracks": "lfgraph.selfcal.pipeline",
    "pin_scene": "lfgraph.selfcal.pipeline",
    "BoardPin": "lfgraph.selfcal.pins",
    "DistancePin": "lfgraph.selfcal.pins",
    "ViewPin": "lfgraph.selfcal.pins",
    "PinError": "lfgraph.selfcal.pins",
    "PinRefused": "lfgraph.selfcal.pinned",
    "PinResult": "lfgraph.selfcal.pinned",
    "Mode": "lfgraph.selfcal.report",
    "SelfCalReport": "lfgraph.selfcal.report",
    "Coverage": "lfgraph.selfcal.tracks",
    "PooledTracks": "lfgraph.selfcal.tracks",
    "pool_tracks": "lfgraph.selfcal.tracks",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'lfgraph.selfcal' has no attribute {name!r}")


def __dir__() -> list[str]:
    return __all__
