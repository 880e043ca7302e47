"""Judges: errors against ground truth (``evaluation``), alignment at infinity and of rectified points
(``alignment``), the drift check of a stored calibration (``check``), depth error (``depth``) and OpenCV's
``calibrateMultiview`` as the peer (``peers``)."""
