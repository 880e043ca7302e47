"""Multi-view rectification (paper Section 3.3): a common K_r and rotation, grid-proportional translations,
per-view lookup tables (``rectify``), and whether a calibration can be rectified or fits a capture (``checks``)."""
