"""lfgraph: calibrate, rectify and auto-refine light-field cameras built as camera arrays, with GTSAM factor graphs.

The public API (``import lfgraph as lf``)::

    calib = lf.Calibration.load("calibration.json")
    capture = lf.open_capture("scene/", calib.grid)
    refined, report = lf.refine(calib, capture.frames(), lf.RefineConfig(robust="cauchy:0.5"))
    refined.save("refined.json")

Names are loaded on first use, so ``import lfgraph`` (and ``lfgraph --help``) does not import GTSAM, OpenCV or
rerun.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.2.0"

# public name -> module that defines it
_EXPORTS = {
    "Calibration": "lfgraph.core.calibration",
    "CalibrationFileError": "lfgraph.core.calibration",
    "Intrinsics": "lfgraph.core.camera",
    "ViewGrid": "lfgraph.core.grid",
    "BoardSpec": "lfgraph.detect.board",
    "BoardObservations": "lfgraph.detect.detections",
    "detect_capture": "lfgraph.detect.detections",
    "PointBoard": "lfgraph.detect.detections",
    "load_detections": "lfgraph.io.points",
    "CaptureSet": "lfgraph.io.capture",
    "CaptureError": "lfgraph.io.capture",
    "open_capture": "lfgraph.io.capture",
    "calibrate": "lfgraph.pattern.pipeline",
    "CalibrateConfig": "lfgraph.pattern.config",
    "Method": "lfgraph.pattern.config",
    "Init": "lfgraph.pattern.config",
    "CalibrationReport": "lfgraph.pattern.scoring",
    "CalibrationInputError": "lfgraph.pattern.initial",
    "rectify": "lfgraph.rectification.rectify",
    "refine": "lfgraph.refinement.schedule",
    "RefineConfig": "lfgraph.refinement.config",
    "Stage": "lfgraph.refinement.config",
    "TriangulationFilter": "lfgraph.refinement.config",
    "DriftModel": "lfgraph.refinement.config",
    "Tracker": "lfgraph.refinement.matching",
    "ChainTracker": "lfgraph.refinement.matching",
    "SiftTracker": "lfgraph.refinement.unordered",
    "OutlierTracker": "lfgraph.refinement.tracks",
    "tracker_by_name": "lfgraph.refinement.trackers",
    "MatchSettings": "lfgraph.refinement.matching",
    "Tracks": "lfgraph.refinement.matching",
    "RefinementReport": "lfgraph.refinement.report",
    "check": "lfgraph.judge.check",
    "DriftReport": "lfgraph.judge.check",
    "evaluate": "lfgraph.judge.evaluation",
    "CalibrationErrors": "lfgraph.judge.evaluation",
    "RobustKernel": "lfgraph.factors.noise",
    "vectorised_estimator": "lfgraph.engine.bulk_noise",
    "GraphContext": "lfgraph.factors.hooks",
    "view_pose_key": "lfgraph.factors.keys",
    "calib_key": "lfgraph.factors.keys",
    "landmark_key": "lfgraph.factors.keys",
    "pose_noise": "lfgraph.factors.noise",
    "Observer": "lfgraph.core.observer",
    "BaseObserver": "lfgraph.core.observer",
    "Observers": "lfgraph.core.observer",
    "StageEnd": "lfgraph.core.observer",
    "SilentObserver": "lfgraph.core.observer",
    "calibrate_scene": "lfgraph.selfcal.pipeline",
    "export_calibration": "lfgraph.interop",
    "import_calibration": "lfgraph.interop",
    "Design": "lfgraph.selfcal.config",
    "SelfCalConfig": "lfgraph.selfcal.config",
    "SelfCalReport": "lfgraph.selfcal.report",
}
# public submodule -> where it lives
_SUBMODULES = {"viz": "lfgraph.viz", "factors": "lfgraph.factors", "datasets": "lfgraph.datasets",
               "pattern": "lfgraph.pattern", "refinement": "lfgraph.refinement", "synth": "lfgraph.apps.synth",
               "study": "lfgraph.apps.study", "selfcal": "lfgraph.selfcal"}

__all__ = ["__version__", "BaseObserver", "BoardObservations", "BoardSpec", "CalibrateConfig", "Calibration",
           "CalibrationErrors", "CalibrationFileError", "CalibrationInputError", "CalibrationReport", "CaptureError",
           "CaptureSet", "ChainTracker", "Design", "DriftModel", "DriftReport", "GraphContext", "Init", "Intrinsics",
           "MatchSettings", "Method", "Observer", "Observers", "OutlierTracker", "PointBoard", "RefineConfig",
           "RefinementReport", "RobustKernel", "SelfCalConfig", "SelfCalReport", "SiftTracker", "SilentObserver",
           "Stage", "StageEnd", "Tracker", "Tracks", "TriangulationFilter", "ViewGrid", "calib_key", "calibrate",
           "calibrate_scene", "check", "detect_capture", "evaluate", "export_calibration", "import_calibration",
           "landmark_key", "load_detections", "open_capture", "pose_noise", "rectify", "refine", "tracker_by_name",
           "vectorised_estimator", "view_pose_key", "viz", "factors", "datasets", "pattern", "refinement", "synth",
           "study", "selfcal"]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    if name in _SUBMODULES:
        return importlib.import_module(_SUBMODULES[name])
    raise AttributeError(f"module 'lfgraph' has no attribute {name!r}")


def __dir__() -> list[str]:
    return __all__


if TYPE_CHECKING:  # for type checkers and IDEs; at run time the names load lazily above
    from lfgraph.core.calibration import Calibration, CalibrationFileError
    from lfgraph.core.camera import Intrinsics
    from lfgraph.core.grid import ViewGrid
    from lfgraph.core.observer import BaseObserver, Observer, Observers, SilentObserver, StageEnd
    from lfgraph.detect.board import BoardSpec
    from lfgraph.detect.detections import BoardObservations, PointBoard, detect_capture
    from lfgraph.engine.bulk_noise import vectorised_estimator
    from lfgraph.factors.hooks import GraphContext
    from lfgraph.factors.keys import calib_key, landmark_key, view_pose_key
    from lfgraph.factors.noise import RobustKernel, pose_noise
    from lfgraph.interop import export_calibration, import_calibration
    from lfgraph.io.capture import CaptureError, CaptureSet, open_capture
    from lfgraph.io.points import load_detections
    from lfgraph.judge.check import DriftReport, check
    from lfgraph.judge.evaluation import CalibrationErrors, evaluate
    from lfgraph.pattern.config import CalibrateConfig, Init, Method
    from lfgraph.pattern.initial import CalibrationInputError
    from lfgraph.pattern.pipeline import calibrate
    from lfgraph.pattern.scoring import CalibrationReport
    from lfgraph.rectification.rectify import rectify
    from lfgraph.refinement.config import DriftModel, RefineConfig, Stage, TriangulationFilter
    from lfgraph.refinement.matching import ChainTracker, MatchSettings, Tracker, Tracks
    from lfgraph.refinement.report import RefinementReport
    from lfgraph.refinement.schedule import refine
    from lfgraph.refinement.trackers import tracker_by_name
    from lfgraph.refinement.tracks import OutlierTracker
    from lfgraph.refinement.unordered import SiftTracker
    from lfgraph.selfcal.config import Design, SelfCalConfig
    from lfgraph.selfcal.pipeline import calibrate_scene
    from lfgraph.selfcal.report import SelfCalReport
