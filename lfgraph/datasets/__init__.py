"""Synthetic and published-truth data: rigs with ground truth and their shakes, rendered checkerboards and textured
scenes, named scenes, and Middlebury's published calibrations."""
