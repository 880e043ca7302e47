"""A stereo pair's reported transfer sigma includes the pan it holds (issue 40): the scene cannot tell a pair's pan
from depth, so the knock's pan stays uncorrected, and the reported sigma must say so (the sweep's three pairs were
reported at 33-47x their sigma)."""

import pytest

import lfgraph as lf
from lfgraph.judge.alignment import transfer_error_at_infinity

MAX_ERROR_OVER_SIGMA = 3.0  # the sweep's per-view goal (measured 1.2-1.7 on seeds 0-2)


@pytest.mark.slow
def test_a_pairs_reported_sigma_includes_its_held_pan():
    cap = lf.synth.scene_capture("paper-5x5", 2, shake_rot_deg=1.0, shake_trans_mm=3.0, seed=1, rows=1, cols=2)
    refined, report = lf.refine(cap.original, cap.frames)
    error = transfer_error_at_infinity(refined, cap.truth)
    view = next(v for v in report.verdicts if v.view != cap.original.grid.reference)
    assert view.applied  # the knock's other parts were repaired and written ...
    assert error[view.view] <= MAX_ERROR_OVER_SIGMA * view.predicted_transfer_px  # ... and the rest is in the sigma
