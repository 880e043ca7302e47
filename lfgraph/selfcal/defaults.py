"""Design tolerances (1 sigma) used as MAP priors by default; plain numbers (the CLI reads them without importing
GTSAM). Wider than the benchmark's spreads (3 %, 15 px, 1 deg, 0.3 mm) so the benchmark does not hand the solver
its own truth."""

FOCAL_TOLERANCE = 0.05  # relative
PRINCIPAL_TOLERANCE_PX = 20.0
K1_TOLERANCE = 0.2
K2_TOLERANCE = 0.1
ROTATION_TOLERANCE_DEG = 2.0
POSITION_TOLERANCE_MM = 1.0
TRACKS_PER_FRAME = 150  # tracks kept per frame, spread over the image
