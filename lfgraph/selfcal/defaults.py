"""Design tolerances (1 sigma) used as MAP priors by default; plain numbers (the CLI reads them without importing
GTSAM). Wider than the benchmark's spreads (3 %, 15 px, 1 deg, 0.3 mm) so the benchmark does not hand the solver
its own truth."""

FOCAL_TOLERANCE = 0.05  # relative
PRINCIPAL_TOLERANCE_PX = 20.0
K1_TOLERANCE = 0.2
K2_TOLERANCE = 0.1
ROTATION_TOLERANCE_DEG = 2.0
POSITION_TOLERANCE_MM = 1.0
# tracks kept per frame, spread over the image. Measured on paper-4x4 with 20 frames (re-tracked): 150 -> 300 moved
# the transfer error at infinity 0.29 -> 0.14 px and cx 0.17 -> 0.12 px, at ~3x the graph's time
TRACKS_PER_FRAME = 300
