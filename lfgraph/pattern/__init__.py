"""Pattern calibration (paper Section 3.2): the paper's route and the joint GTSAM graph over board observations.

Modules: `config` (options), `initial` (checks and starting values), `paper` (Zhang + relative PnP/LM),
`joint` (the factor graph with marginals), `scoring` (rig-consistent residuals, coverage, the report),
`pipeline` (`calibrate`, the entry point).
"""

from lfgraph.pattern.config import CalibrateConfig, Init, Method
from lfgraph.pattern.initial import CalibrationInputError, check_observations, design_initial
from lfgraph.pattern.joint import JointResult, calibrate_joint
from lfgraph.pattern.paper import PaperResult, calibrate_paper
from lfgraph.pattern.pipeline import calibrate
from lfgraph.pattern.scoring import CalibrationReport, fit_board_poses, rig_residuals

__all__ = ["CalibrateConfig", "CalibrationInputError", "CalibrationReport", "Init", "JointResult", "Method",
           "PaperResult", "calibrate", "calibrate_joint", "calibrate_paper", "check_observations", "design_initial",
           "fit_board_poses", "rig_residuals"]
