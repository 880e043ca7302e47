"""Auto-refinement (paper Section 4): grid-chain tracks, filters, staged GTSAM graphs, frame after frame.

Modules: `config` (`RefineConfig`, `Stage`, schedules), `matching` (chain KLT tracks), `triangulate` (DLT and the
triangulation filters), `tracks` (per-frame selection), `stages` (one stage's graph), `schedule` (`refine`,
`refine_tracks`), `priors` (MAP priors centred on the input), `assess` (posterior, significance, held-out folds,
per-view verdicts), `report`, `unordered` (tracks for views that are not a grid).
"""

from lfgraph.refinement.config import SCHEDULES, DriftModel, RefineConfig, Stage, TriangulationFilter, parse_stages
from lfgraph.refinement.fit import refine_tracks
from lfgraph.refinement.report import RefinementReport, StageReport
from lfgraph.refinement.schedule import refine, with_reference
from lfgraph.refinement.verdicts import ViewVerdict

__all__ = ["SCHEDULES", "DriftModel", "RefineConfig", "RefinementReport", "Stage", "StageReport", "TriangulationFilter",
           "ViewVerdict", "parse_stages", "refine", "refine_tracks", "with_reference"]
