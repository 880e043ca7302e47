"""Issue 24: refinement after real knocks (pan, tilt and roll about random axes), gauges by structure, a practical
tolerance, and a fixed-seed subset of the randomized sweep (`benchmarks/sweep.py`), each against the truth."""

import sys
from pathlib import Path

import numpy as np
import pytest

from lfgraph.core.camera import project_world
from lfgraph.datasets.rig import RigConfig, ShakeConfig, make_rig, shake_rig
from lfgraph.engine.triangulate import reprojection_errors, triangulate_dlt
from lfgraph.factors.scene_graph import rotation_gauge
from lfgraph.judge.alignment import transfer_error_at_infinity
from lfgraph.refinement import DriftModel, RefineConfig
from lfgraph.refinement.assess import assess, group_significance
from lfgraph.refinement.config import Stage
from lfgraph.refinement.matching import ChainTracker, MatchSettings
from lfgraph.refinement.posterior import Posterior, held_directions
from lfgraph.refinement.priors import view_priors
from lfgraph.refinement.report import DRIFTED, OK

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import sweep  # noqa: E402

TRACK_NOISE_PX = 0.05  # synthetic track noise per coordinate
KNOCK_FIXED_PX = 0.05  # a knock of several px at infinity, refined from exact tracks: within this of the truth
NOT_WORSE_PX = 0.05  # "never worse" margin of transfer at infinity in the sweep subset (px)
MISMATCH_PX = 1.0  # a track whose DLT point, with the true cameras, reprojects worse than this is a mismatch
LOCKED_WITHOUT_FILTER = 0.15  # share of sweep #169's first-frame tracks locked one period off (measured 25 %)
LOCKED_WITH_FILTER = 0.05  # ... left by the repeated-texture filter (measured 1 of 26)
POOR_KEPT_SHARE = 0.7  # of sweep #17's (poor texture) first-frame tracks kept by that filter (measured 77 %)
# seeds of small scenarios (<= 6 Mpx rendered each) spanning grids 1x2..4x3, lines 1x5/1x8, the three textures,
# 1-8 frames, knocked and unknocked; 159 and 169 (a 2x1 and a 1x2 on repeated texture) were written worse than
# their input before the repeated-texture filter
SWEEP_SUBSET = (4, 6, 8, 18, 21, 23, 37, 42, 45, 56, 159, 169)


class _Quiet:
    def __getattr__(self, name):
        return lambda *a, **k: None


def exact_tracks(truth, n=400, seed=3, near=1.5, far=5.0):
    rng = np.random.default_rng(seed)
    depth = rng.uniform(near, far, n)
    w, h = truth.image_size_px
    f = truth.intrinsics[0].fx
    half = 0.45 * np.array([w, h]) / f
    pts = np.column_stack([rng.uniform(-1, 1, (n, 2)) * half * depth[:, None], depth])
    pix = np.stack([project_world(truth.intrinsics[v], truth.view_T_ref(v), pts) for v in range(truth.num_views)])
    pix += TRACK_NOISE_PX * rng.standard_normal(pix.shape)
    return pix, np.all(np.isfinite(pix), axis=-1)


def test_pan_and_tilt_knocks_are_repaired_not_moved_into_positions():
    """The issue's first row: a 2x2 rig knocked about random axes; the pan of the reference's row neighbour is not a
    gauge with the intrinsics held, so it must be refitted (before: held, and a 13 mm position error absorbed it)."""
    original = make_rig(RigConfig(rows=2, cols=2, reference=3, pitch_m=0.05, image_size_px=(1280, 960),
                                  focal_px=1400.0), np.random.default_rng(0))
    truth = shake_rig(original, ShakeConfig(rot_deg=1.0, trans_mm=3.0, axis="any"), np.random.default_rng(1))
    pix, valid = exact_tracks(truth)
    result = assess(original, pix, valid, RefineConfig(), _Quiet(), 1.0, 1)
    before = transfer_error_at_infinity(original, truth)
    after = transfer_error_at_infinity(result.calib, truth)
    assert before.max() > 1.0  # a real knock
    assert after.max() < KNOCK_FIXED_PX
    _, pos_before = sweep.body_errors(original, truth)
    _, pos_after = sweep.body_errors(result.calib, truth)
    assert np.linalg.norm(pos_after, axis=1).max() <= np.linalg.norm(pos_before, axis=1).max()
    assert [v.verdict for v in result.verdicts if before[v.view] > 1.0] == [DRIFTED] * int((before > 1.0).sum())


def test_gauges_follow_the_graph_structure_not_sigma_sizes():
    line = make_rig(RigConfig(rows=1, cols=3, image_size_px=(320, 240), focal_px=300.0), np.random.default_rng(0))
    priors = view_priors(line, DriftModel())
    held_poses = held_directions(line, Stage.POSES, frozenset(), priors)
    assert held_poses[0].all()  # the reference view
    assert not held_poses[1:, :6].any() and held_poses[:, 6:].all()  # poses free (pans too), intrinsics held
    assert rotation_gauge(line) == (1, 1)
    # intrinsics free under MAP priors: nothing of the neighbour is held exactly (the priors split its pan and cx)
    assert not held_directions(line, Stage.ALL, frozenset(), priors)[1:].any()
    # the free fit (no priors) holds the neighbour's cx: the exact principal-point gauge
    held_free = held_directions(line, Stage.ALL, frozenset(), None)
    assert held_free[1, 8] and not held_free[1, [0, 1, 2, 3, 4, 5, 6, 7, 9]].any() and not held_free[2].any()
    # in a stereo pair the hidden mode is the second view's pan alone: held even with the intrinsics held
    pair = make_rig(RigConfig(rows=1, cols=2, image_size_px=(320, 240), focal_px=300.0), np.random.default_rng(0))
    held_pair = held_directions(pair, Stage.POSES, frozenset(), view_priors(pair, DriftModel()))
    assert held_pair[1, 1] and not held_pair[1, [0, 2, 3, 4, 5]].any()
    # a roll changed by 0.57 deg and known to 2e-6 rad (well below rad/m/px thresholds) is highly significant
    cov = np.diag([1e-8, 1e-8, (2e-6) ** 2, 1e-8, 1e-8, 1e-8])
    post = Posterior(np.stack([np.zeros((6, 6)), cov, cov]), np.zeros((3, 4, 4)), np.zeros((3, 6, 4)), False, 0.1,
                     held_poses)
    turned = shake_rig(line, ShakeConfig(rot_deg=0.57), np.random.default_rng(5))
    z = group_significance(line, turned, post, 1)
    assert z["roll"] > 100


def test_a_significant_change_within_the_tolerance_is_ok_and_not_applied():
    original = make_rig(RigConfig(rows=2, cols=2, pitch_m=0.05, image_size_px=(640, 480), focal_px=600.0),
                        np.random.default_rng(2))
    truth = shake_rig(original, ShakeConfig(rot_deg=0.02, axis="any"), np.random.default_rng(3))
    pix, valid = exact_tracks(truth, n=1500)
    knock = transfer_error_at_infinity(original, truth)
    assert 0.02 < knock.max() < 0.3  # a real but small knock
    loose = assess(original, pix, valid, RefineConfig(tolerance_px=1.0), _Quiet(), 1.0, 1)
    assert all(v.verdict in (OK, "REFERENCE") and not v.applied for v in loose.verdicts)
    np.testing.assert_array_equal(loose.calib.ref_T_view, original.ref_T_view)
    assert any("within the tolerance" in v.reason for v in loose.verdicts)
    strict = assess(original, pix, valid, RefineConfig(tolerance_px=0.0), _Quiet(), 1.0, 1)
    assert any(v.applied for v in strict.verdicts)
    assert transfer_error_at_infinity(strict.calib, truth).max() < knock.max()
    with pytest.raises(ValueError, match="tolerance_px"):
        RefineConfig(tolerance_px=-1.0)


def _first_frame_tracks(seed: int, settings: MatchSettings):
    s = sweep.draw(seed)
    _, truth = sweep.rigs(s)
    images = sweep.render(s, truth)[0]
    tracks = ChainTracker(settings).track(images, truth.grid)
    err = reprojection_errors(truth, triangulate_dlt(truth, tracks.points_px, tracks.valid), tracks.points_px,
                              tracks.valid)
    worst = np.where(np.isfinite(err), err, -np.inf).max(axis=0)
    mismatched = ~((worst >= 0) & (worst <= MISMATCH_PX))  # no finite error (a point behind a camera) is one too
    return tracks, mismatched


def test_tracks_locked_one_period_off_on_a_repeated_texture_are_dropped():
    """Sweep #169 (a pair before a keyboard texture): KLT locks a quarter of the tracks one key off, on the
    epipolar line, where F-RANSAC and triangulation cannot see it; the repeated-texture filter drops them."""
    tracks, bad = _first_frame_tracks(169, MatchSettings(unique_margin=None))
    assert bad.mean() > LOCKED_WITHOUT_FILTER, bad.mean()  # the failure is there without the filter
    tracks, bad = _first_frame_tracks(169, MatchSettings())
    assert tracks.num_tracks >= 20 and bad.mean() <= LOCKED_WITH_FILTER, (tracks.num_tracks, bad.mean())
    assert tracks.counts["unique"] == tracks.num_tracks


def test_the_repeated_texture_filter_keeps_a_poor_texture():
    """Sweep #17 (poor, blurred texture): blobs of one shape look alike; the filter drops those with a twin within
    reach (they are ambiguous to KLT too) and keeps the rest."""
    tracks, bad = _first_frame_tracks(17, MatchSettings())
    assert tracks.counts["unique"] >= POOR_KEPT_SHARE * tracks.counts["ransac"], tracks.counts
    assert bad.mean() <= 0.01


@pytest.mark.slow
@pytest.mark.parametrize("seed", SWEEP_SUBSET)
def test_sweep_subset_never_worse_no_false_alarm_no_miss(seed):
    """Rendered scenes of rigs drawn at random (grid, size, focal, lens, knock axis, frames, noise, texture): the
    written calibration is never worse than the input (transfer at infinity and scale-aligned positions, beyond
    1 sigma; no view beyond 3 of its sigmas), an unknocked rig has no DRIFTED view, and no view knocked by >= 3x
    the tolerance is left OK."""
    s = sweep.draw(seed)
    row = sweep.run(s)
    if row.get("error"):  # nothing written: never worse; but only texture-poor scenes may refuse
        assert s.texture != "rich", row["error"]
        return
    assert row["worse_calibration"] == 0 and row["worse_views_3sigma"] == 0, row
    assert row["transfer_out_max_px"] <= row["transfer_in_max_px"] + NOT_WORSE_PX
    if not s.knocked:
        assert row["drifted_views"] == 0
    assert row["missed_views"] == 0


# small scenarios of the sweep through wide lenses (`benchmarks/sweep.py --lens`): knocked lines, grids and an
# unknocked rig, poor and rich texture, 1-7 frames
WIDE_SUBSET = ((21, "fisheye"), (44, "fisheye"), (56, "fisheye"), (7, "unified"), (10, "unified"), (54, "unified"))


@pytest.mark.slow
@pytest.mark.parametrize("seed, lens", WIDE_SUBSET)
def test_wide_lens_sweep_subset_never_worse_no_false_alarm_no_miss(seed, lens):
    """The same scenarios rendered through fisheye and unified lenses (fields ~55-125 deg across): never worse, no
    false alarm, no miss, as above."""
    s = sweep.draw(seed)
    row = sweep.run(s, lens=lens)
    assert not row.get("error"), row["error"]
    assert row["worse_calibration"] == 0 and row["worse_views_3sigma"] == 0, row
    assert row["transfer_out_max_px"] <= row["transfer_in_max_px"] + NOT_WORSE_PX
    if not s.knocked:
        assert row["drifted_views"] == 0
    assert row["missed_views"] == 0


@pytest.mark.slow
def test_a_calibration_of_another_camera_is_not_refined_and_said(tmp_path):
    """Issue 27: another camera's calibration (f 851 px on an f 300 px capture) was reported 'DRIFTED ... refined'
    with fx still 550 px off. Nothing is written changed, and the warning says what is wrong."""
    import dataclasses

    from lfgraph.cli import main
    from lfgraph.core.calibration import Calibration
    from lfgraph.io.capture import open_capture
    from lfgraph.refinement import refine

    out = tmp_path / "scene"
    assert main(["synth", "scene", str(out), "--scene", "small-2x2", "--frames", "2", "--shake-rot-deg", "0.5",
                 "--quiet", "--jobs", "1"]) == 0
    calib = Calibration.load(out / "original.json")
    wrong = calib.replace(intrinsics=tuple(dataclasses.replace(i, fx=851.0, fy=851.0) for i in calib.intrinsics))
    refined, report = refine(wrong, open_capture(out, calib.grid).frames())
    np.testing.assert_array_equal(refined.ref_T_view, wrong.ref_T_view)
    assert DRIFTED not in {v.verdict for v in report.verdicts}
    assert any("is this calibration for this camera" in w for w in report.warnings)


@pytest.mark.slow
def test_another_unit_of_the_same_model_is_not_refined_into_worse_poses(tmp_path):
    """Issue 27's trial: the calibration of another unit of the same model (small-2x2 drawn with seed 0, the capture
    from seed 7: focal lengths, principal points and poses a little different) was refined to rotations 0.61 ->
    1.17 deg and positions 0.35 -> 7.7 mm from that unit's truth, 'DRIFTED'. Poses cannot explain other
    intrinsics: the input is kept, no view is DRIFTED, and the warning asks."""
    from lfgraph.cli import main
    from lfgraph.core.calibration import Calibration
    from lfgraph.io.capture import open_capture
    from lfgraph.judge.evaluation import evaluate_calibration
    from lfgraph.refinement import refine

    for name, seed in (("ours", "0"), ("other", "7")):
        assert main(["synth", "scene", str(tmp_path / name), "--scene", "small-2x2", "--frames", "2", "--seed", seed,
                     "--shake-rot-deg", "0.5", "--quiet", "--jobs", "1"]) == 0
    ours = Calibration.load(tmp_path / "ours" / "original.json")
    truth = Calibration.load(tmp_path / "other" / "truth.json")
    refined, report = refine(ours, open_capture(tmp_path / "other", ours.grid).frames())
    before, after = evaluate_calibration(ours, truth), evaluate_calibration(refined, truth)
    assert np.sqrt(np.mean(after.rotation_deg**2)) <= np.sqrt(np.mean(before.rotation_deg**2)) + 0.02  # deg
    assert np.max(np.linalg.norm(after.position_mm, axis=1)) <= np.max(np.linalg.norm(before.position_mm, axis=1))
    assert DRIFTED not in {v.verdict for v in report.verdicts}
    assert any("is this calibration for this camera" in w for w in report.warnings)


@pytest.mark.parametrize("bad, message", [
    (np.zeros((4, 240, 320), np.uint16), "16-bit"),
    (np.zeros((4, 240, 320, 3), np.uint8), "colour"),
    (np.zeros((4, 240, 320), np.float32), "floats"),
    (np.zeros((240, 320), np.uint8), "shape"),
    ([[0]], "numpy array"),
])
def test_refine_and_check_name_a_frame_they_cannot_use(bad, message):
    """Issue 27/28: float, uint16 or RGB frames raised raw OpenCV assertions, one (H, W) frame an IndexError."""
    from lfgraph.judge.check import check
    from lfgraph.refinement import refine

    rig = make_rig(RigConfig(rows=2, cols=2, image_size_px=(320, 240), focal_px=300.0), np.random.default_rng(0))
    for run in (lambda: refine(rig, [bad]), lambda: check(rig, [bad])):
        with pytest.raises((ValueError, TypeError), match=message):
            run()


@pytest.mark.slow
def test_check_names_another_units_calibration_a_mismatch(tmp_path, capsys):
    """`check` of another unit's calibration (same model) on this unit's capture: exit 3, MISMATCH, not UNCERTAIN."""
    import json

    from lfgraph.cli import EXIT_DRIFT, main

    for name, seed in (("ours", "0"), ("other", "7")):
        assert main(["synth", "scene", str(tmp_path / name), "--scene", "small-2x2", "--frames", "2", "--seed", seed,
                     "--quiet", "--jobs", "1"]) == 0
    capsys.readouterr()
    assert main(["check", str(tmp_path / "ours" / "truth.json"), str(tmp_path / "other"), "--json"]) == EXIT_DRIFT
    data = json.loads(capsys.readouterr().out)
    assert data["verdict"] == "MISMATCH"
    rms = data["intrinsics_mismatch_rms_px"]
    assert rms["intrinsics_free"] < 0.5 * rms["poses_alone"]
    # and this unit's own calibration on its own capture is no mismatch
    assert main(["check", str(tmp_path / "other" / "truth.json"), str(tmp_path / "other"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["intrinsics_mismatch_rms_px"] is None


LARGE_KNOCK_DEG, LARGE_KNOCK_MM = 4.0, 3.0  # issue 40: a 3x3 of paper-5x5's cameras knocked by up to 4 deg / 3 mm
LARGE_KNOCK_FIXED_PX = 0.1  # ... repaired with the defaults to within this at infinity, worst view (measured 0.059)
LARGE_KNOCK_LOST_PX = 1.0  # ... and left worse than this when the tracker keeps its 3-level pyramid (41 px: refused)


@pytest.mark.slow
def test_a_knock_beyond_the_pyramids_reach_is_tracked_with_a_deeper_one():
    """Seed 0 of the issue's 3x3: the chain followed 1 % of the features through the grid with 3 pyramid levels
    and the refinement kept the 41 px input with advice to use a farther scene; `ChainTracker` now tracks such a
    frame again with `MatchSettings.deep_klt_levels` and keeps the deeper run."""
    import lfgraph as lf
    from lfgraph.judge.evaluation import evaluate_calibration

    cap = lf.synth.scene_capture("paper-5x5", 2, shake_rot_deg=LARGE_KNOCK_DEG, shake_trans_mm=LARGE_KNOCK_MM,
                                 seed=0, rows=3, cols=3)
    refined, report = lf.refine(cap.original, cap.frames)
    assert evaluate_calibration(refined, cap.truth).summary()["max_transfer_px"] < LARGE_KNOCK_FIXED_PX
    assert report.verdict_counts()[DRIFTED] == cap.truth.num_views - 1
    shallow = RefineConfig(tracker=ChainTracker(MatchSettings(deep_klt_levels=None)))
    kept, _ = lf.refine(cap.original, cap.frames, shallow)
    assert evaluate_calibration(kept, cap.truth).summary()["max_transfer_px"] > LARGE_KNOCK_LOST_PX
