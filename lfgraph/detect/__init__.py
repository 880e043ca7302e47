"""Calibration targets and their detection (paper Section 3.2): checkerboards and ChArUco boards, sub-pixel
corners, the wide-lens second pass, the wrong-board probe, symmetric-board ordering, the cached detection of a
whole capture."""
