"""Target-less self-calibration of a camera array from design values and ordinary scene frames (issue 17).

    design = Design(rows=5, cols=5, pitch_mm=100, focal_px=700, image_size_px=(512, 512))
    calib, report = calibrate_scene(lf.open_capture("scenes/", design.grid).frames(), design)
    print(report.text())
"""

from lfgraph.selfcal.config import Design, SelfCalConfig, focal_from_lens
from lfgraph.selfcal.pipeline import SelfCalibrationError, calibrate_scene, calibrate_tracks
from lfgraph.selfcal.report import Mode, SelfCalReport
from lfgraph.selfcal.tracks import Coverage, PooledTracks, pool_tracks

__all__ = ["Coverage", "Design", "Mode", "PooledTracks", "SelfCalConfig", "SelfCalReport", "SelfCalibrationError",
           "calibrate_scene", "calibrate_tracks", "focal_from_lens", "pool_tracks"]
