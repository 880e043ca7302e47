"""The one stage schedule (`lfgraph.engine.schedule`): its order, its outlier rule, its records, the one refit loop,
and both tracked wings reporting their stages through it."""

from __future__ import annotations

import numpy as np
import pytest

from lfgraph.core.observer import BaseObserver
from lfgraph.datasets.rig import ShakeConfig, make_rig, shake_rig
from lfgraph.engine.schedule import Step, TrackState, at_supported_sigma, run_schedule
from lfgraph.engine.triangulate import reprojection_errors
from lfgraph.refinement import RefineConfig, refine_tracks
from tests.refinement.test_refine import points_and_rig

NOISE_PX = 0.2  # the synthetic tracks' noise per coordinate
OUTLIER_PX = 40.0  # a wrong match: this far off in one view


class Heard(BaseObserver):
    """Every stage event, in order."""

    def __init__(self):
        self.events = []

    def stage_start(self, name, measurements):
        self.events.append(("start", name, measurements))

    def stage_end(self, event):
        self.events.append(("end", event.name, event.points_ref_m.shape[0]))

    def outliers(self, name, pixels_px, valid):
        self.events.append(("outliers", name, pixels_px.shape[1]))


@pytest.fixture(scope="module")
def tracks():
    rig, points, pixels, valid = points_and_rig(n=300, seed=3)
    rng = np.random.default_rng(3)
    pixels = pixels + rng.normal(0.0, NOISE_PX, pixels.shape)
    pixels[1, :4] += OUTLIER_PX  # four wrong matches in view 1
    return rig, points, pixels, valid


def _keep_still(state: TrackState) -> tuple[TrackState, int]:
    return state, 0


def test_schedule_runs_steps_in_order_drops_the_wrong_matches_and_skips_what_prepare_refuses(tracks):
    rig, points, pixels, valid = tracks
    heard = Heard()
    steps = [Step("skipped", _keep_still, prepare=lambda s: None),
             Step("one", _keep_still),
             Step("two", _keep_still, outliers=False)]
    state, records = run_schedule(steps, TrackState.start(rig, pixels, valid, points), heard)
    assert [r.name for r in records] == ["one", "two"]
    # the truth's landmarks: the wrong matches are the only tracks far off, and the mismatch rule drops exactly them
    assert set(np.nonzero(records[0].dropped)[0]) == {0, 1, 2, 3}
    assert not records[1].dropped.any()
    assert np.array_equal(state.kept(pixels.shape[1]), np.arange(pixels.shape[1]) >= 4)
    for record, first in zip(records, (0, 4), strict=True):  # the RMS of the tracks each step saw, from the truth
        errors = reprojection_errors(rig, points[first:], pixels[:, first:], valid[:, first:])
        assert record.rms_after_px == pytest.approx(np.sqrt(np.nanmean(errors**2)))
    assert [e[:2] for e in heard.events] == [("start", "one"), ("end", "one"), ("outliers", "one"),
                                            ("start", "two"), ("end", "two"), ("outliers", "two")]
    assert heard.events[2][2] == 4 and heard.events[5][2] == 0


def test_refit_loop_stops_where_the_residuals_support_the_sigma_it_assumed():
    fits = []

    def fit(sigma, k):  # a fit whose residuals support the mean of what it assumed and 0.5 px
        fits.append(sigma)
        return 0.5 * (sigma + 0.5)

    result, used = at_supported_sigma(fit, 2.0, lambda r: r, lambda m, a, _: abs(m / a - 1) < 0.01, 10)
    assert used == fits[-1] and abs(result / used - 1) < 0.01 and 0.5 < used < 0.51
    assert len(fits) < 10
    fits.clear()
    _, used = at_supported_sigma(fit, 2.0, lambda r: r, lambda *_: False, 2)  # a probe, then the fit that counts
    assert fits == [2.0, 1.25] and used == 1.25


def test_refine_reports_every_stage_through_the_schedule(tracks):
    rig, _, pixels, valid = tracks
    shaken = shake_rig(rig, ShakeConfig(), np.random.default_rng(4))
    heard = Heard()
    _, reports, keep = refine_tracks(shaken, pixels, valid, RefineConfig(measurement_sigma_px=NOISE_PX), heard)
    names = [str(s) for s in RefineConfig().stages]
    assert [e[1] for e in heard.events if e[0] == "start"] == names
    assert [r.name for r in reports] == list(RefineConfig().stages)
    assert not keep[:4].any()  # the wrong matches are dropped by the schedule's mismatch rule


def test_self_calibration_reports_every_stage_through_the_schedule():
    from lfgraph.selfcal import SelfCalConfig, calibrate_tracks
    from tests.selfcal.test_selfcal import DESIGN, RIG, gauge_matched, synthetic_tracks

    truth = gauge_matched(make_rig(RIG, np.random.default_rng(5)), DESIGN)
    pooled = synthetic_tracks(truth, 6, 60, NOISE_PX, np.random.default_rng(2))
    heard = Heard()
    config = SelfCalConfig()
    _, report = calibrate_tracks(pooled, DESIGN, config, heard)
    starts = [e for e in heard.events if e[0] == "start"]
    assert [s[1] for s in starts] == ["+".join(sorted(g)) for g in config.stages]
    assert len(report.stages) > len(starts)  # and the final stage's passes after them


def test_calibrate_runs_its_screen_and_joint_fit_through_the_schedule():
    import lfgraph as lf
    from lfgraph.datasets.checkerboard import make_checkerboard_truth, make_corner_observations
    from lfgraph.datasets.scenes import get_scene
    from lfgraph.detect.detections import observations_from_arrays

    scene = get_scene("paper-4x4")
    rig = make_rig(scene.rig, np.random.default_rng(1))
    truth = make_checkerboard_truth(rig, scene.checkerboard, np.random.default_rng(1))
    corners, valid = make_corner_observations(truth, 0.1, np.random.default_rng(2))
    obs = observations_from_arrays(truth.board, rig.grid, rig.image_size_px, corners, valid).subset_frames(
        np.arange(8))
    heard = Heard()
    _, report = lf.calibrate(obs, observer=heard)
    assert [e[:2] for e in heard.events if e[0] == "start"] == [("start", "screen"), ("start", "joint")]
    ends = [e for e in heard.events if e[0] == "end"]
    assert [e[2] for e in ends] == [obs.num_frames * obs.board.num_corners] * 2  # every corner of every frame
    assert report.optimization.iterations > 0
