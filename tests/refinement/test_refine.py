"""Auto-refinement: triangulation, filters, the hidden intrinsics gauge, staged graphs, rendered shaken scenes, CLI."""

import dataclasses

import numpy as np
import pytest

from lfgraph.cli import EXIT_BAD_INPUT, main
from lfgraph.core.calibration import Calibration
from lfgraph.core.camera import project_world
from lfgraph.datasets.rig import RigConfig, ShakeConfig, ideal_ref_T_view, make_rig, shake_rig
from lfgraph.datasets.scenes import get_scene
from lfgraph.engine.triangulate import median_filter, reprojection_errors, triangulate_dlt, worst_error_filter
from lfgraph.factors.noise import RobustKernel
from lfgraph.io.capture import open_capture
from lfgraph.judge.alignment import transfer_error_at_infinity
from lfgraph.judge.evaluation import evaluate_calibration
from lfgraph.refinement import RefineConfig, Stage, parse_stages, refine, refine_tracks
from lfgraph.refinement.matching import track_chain
from lfgraph.refinement.stages import run_stage

EXACT_M = 1e-9  # noise-free triangulation
REFINED_TRANSFER_PX = 0.1  # issue 5: transfer error at infinity after refinement (small rig here)
REFINED_ROTATION_DEG = 0.02  # small-2x2 (10 mm pitch, 3 frames) is weaker than paper-5x5; bound with margin
NO_SHAKE_ROTATION_DEG = 0.01


def points_and_rig(n=400, seed=0, shake=None):
    rig = make_rig(RigConfig(rows=3, cols=3, pitch_m=0.05, image_size_px=(512, 512), focal_px=600.0),
                   np.random.default_rng(seed))
    rng = np.random.default_rng(seed + 1)
    depth = rng.uniform(1.5, 5.0, n)
    xy = rng.uniform(-0.35, 0.35, (n, 2))
    pts = np.column_stack([xy * depth[:, None], depth])
    pix = np.stack([project_world(rig.intrinsics[v], rig.view_T_ref(v), pts) for v in range(rig.num_views)])
    valid = np.all(np.isfinite(pix), axis=-1)
    w, h = rig.image_size_px
    valid &= (pix[..., 0] >= 0) & (pix[..., 0] < w) & (pix[..., 1] >= 0) & (pix[..., 1] < h)
    return rig, pts, pix, valid


def test_dlt_triangulation_is_exact_without_noise():
    rig, pts, pix, valid = points_and_rig()
    est = triangulate_dlt(rig, pix, valid)
    ok = valid.sum(axis=0) >= 2
    assert np.max(np.abs(est[ok] - pts[ok])) < EXACT_M
    assert np.nanmax(reprojection_errors(rig, est, pix, valid)) < 1e-6


def test_filters():
    errors = np.array([[0.1, 0.2, 0.3, 0.4, np.nan], [0.1, 0.1, 0.1, 5.0, 0.2]])
    np.testing.assert_array_equal(median_filter(errors, 0), [True, True, False, False, False])
    np.testing.assert_array_equal(worst_error_filter(errors, 4.0, 0.5), [True, True, True, False, True])


def test_hidden_intrinsics_gauge_exists_and_is_held():
    """cx_i += fx_i b_i delta with every landmark's inverse depth += delta leaves all images unchanged."""
    grid_rig = make_rig(RigConfig(rows=1, cols=3, pitch_m=0.05, image_size_px=(512, 512), focal_px=600.0,
                                  k1=0.0, k2=0.0, distortion_jitter=0.0, focal_jitter_px=0.0, rot_jitter_deg=0.0,
                                  trans_jitter_mm=0.0),
                        np.random.default_rng(0))
    rig = grid_rig.replace(ref_T_view=ideal_ref_T_view(grid_rig.grid, 0.05))
    rng = np.random.default_rng(3)
    depth = rng.uniform(1.5, 5.0, 200)
    xy = rng.uniform(-0.3, 0.3, (200, 2))
    pts = np.column_stack([xy * depth[:, None], depth])
    pix = np.stack([project_world(rig.intrinsics[v], rig.view_T_ref(v), pts) for v in range(3)])
    delta = 0.01  # 1/m
    shifted_intr = tuple(dataclasses.replace(i, cx=i.cx + i.fx * rig.ref_T_view[v][0, 3] * delta)
                         for v, i in enumerate(rig.intrinsics))
    inv_depth = 1.0 / depth + delta
    pts2 = np.column_stack([pts[:, :2] / depth[:, None] / inv_depth[:, None], 1.0 / inv_depth])
    moved = rig.replace(intrinsics=shifted_intr)
    pix2 = np.stack([project_world(moved.intrinsics[v], moved.view_T_ref(v), pts2) for v in range(3)])
    np.testing.assert_allclose(pix2, pix, atol=1e-9)  # the images cannot tell the two apart
    # start the 'all' stage from the gauge-shifted rig: the held cx keeps the solution where it started
    valid = np.ones(pix.shape[:2], dtype=bool)
    out, _, _ = run_stage(Stage.ALL, moved, pix, valid, pts2, RobustKernel("none"), max_iterations=50)
    assert abs(out.intrinsics[1].cx - moved.intrinsics[1].cx) < 1e-6
    assert abs(out.intrinsics[2].cx - moved.intrinsics[2].cx) < 1e-3


def test_staged_refinement_on_exact_tracks_recovers_a_shaken_rig():
    truth, pts, pix, valid = points_and_rig(n=600, seed=4)
    original = shake_rig(truth, ShakeConfig(rot_deg=0.0, trans_mm=0.0), np.random.default_rng(0))
    shaken = shake_rig(truth, ShakeConfig(rot_deg=1.0, trans_mm=5.0), np.random.default_rng(1))
    pix = np.stack([project_world(shaken.intrinsics[v], shaken.view_T_ref(v), pts) for v in range(9)])
    noisy = pix + 0.05 * np.random.default_rng(2).standard_normal(pix.shape)
    refined, stages, keep = refine_tracks(original, noisy, valid, RefineConfig())
    e = evaluate_calibration(refined, shaken)
    assert np.sqrt(np.mean(e.rotation_deg**2)) < 0.005
    assert np.sqrt(np.mean(transfer_error_at_infinity(refined, shaken) ** 2)) < 0.05
    assert [s.name for s in stages] == ["points", "poses", "clean"]
    assert stages[1].rms_after_px < 0.1 < stages[1].rms_before_px


def test_stage_schedules_parse_and_refuse_nonsense():
    assert parse_stages("paper") == ("points", "intrinsics", "all")
    assert parse_stages("points,poses") == ("points", "poses")
    for bad in ("points,bundle", "clean,poses", ""):
        with pytest.raises(ValueError):
            parse_stages(bad)
    assert RefineConfig(stages="paper").triangulation_filter == "median"
    assert RefineConfig().triangulation_filter == "worst"


@pytest.fixture(scope="module")
def shaken_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene") / "small"
    assert main(["synth", "scene", str(out), "--scene", "small-2x2", "--frames", "3", "--shake-rot-deg", "0.5",
                 "--shake-trans-mm", "1", "--jobs", "2", "--quiet", "--seed", "0"]) == 0
    return out


@pytest.mark.slow
def test_refine_rendered_shaken_scene(shaken_scene):
    truth = Calibration.load(shaken_scene / "truth.json")
    original = Calibration.load(shaken_scene / "original.json")
    capture = open_capture(shaken_scene, truth.grid)
    refined, report = refine(original, (capture.load_frame(f) for f in range(len(capture))))
    before = np.sqrt(np.mean(transfer_error_at_infinity(original, truth) ** 2))
    after = np.sqrt(np.mean(transfer_error_at_infinity(refined, truth) ** 2))
    assert before > 0.3  # the shake is visible
    assert after <= REFINED_TRANSFER_PX, f"transfer error {before:.3f} -> {after:.3f} px"
    e = evaluate_calibration(refined, truth)
    assert np.sqrt(np.mean(e.rotation_deg**2)) <= REFINED_ROTATION_DEG
    assert report.frames_used == 3 and set(report.frame_counts[0]) >= {"detected", "chain", "dedup", "ransac",
                                                                        "triangulation"}
    assert report.rms_after_px < report.rms_before_px
    assert refined.metrics["refinement"]["frames_used"] == 3


def test_refine_without_shake_changes_nothing_measurable(tmp_path):
    out = tmp_path / "still"
    assert main(["synth", "scene", str(out), "--scene", "small-2x2", "--frames", "2", "--jobs", "2", "--quiet",
                 "--seed", "1"]) == 0
    truth = Calibration.load(out / "truth.json")
    capture = open_capture(out, truth.grid)
    frames = [capture.load_frame(f) for f in range(len(capture))]
    refined, report = refine(truth, frames)
    # the data do not support a change: the input is kept, every view says why, and the report says so
    assert not report.accepted and any("no view changed" in w for w in report.warnings)
    np.testing.assert_array_equal(refined.ref_T_view, truth.ref_T_view)
    assert {v.verdict for v in report.verdicts} <= {"REFERENCE", "OK", "UNCERTAIN"}
    assert all(v.reason for v in report.verdicts)
    # what the refit alone would have done (every change applied) stays small too
    forced, _ = refine(truth, frames, RefineConfig(significance_sigma=1e-6, folds=0))
    e = evaluate_calibration(forced, truth)
    assert np.max(e.rotation_deg) < NO_SHAKE_ROTATION_DEG
    assert np.max(np.linalg.norm(e.position_mm, axis=1)) < 0.5


def test_refine_cli_and_bad_input(shaken_scene, tmp_path, capsys):
    out_json = tmp_path / "refined.json"
    assert main(["refine", str(shaken_scene / "original.json"), str(shaken_scene), "-o", str(out_json),
                 "--max-frames", "2", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "changes per view" in text and "triangulation" in text
    assert Calibration.load(out_json).metrics["refinement"]["frames_used"] == 2
    with pytest.raises(SystemExit):
        main(["refine", str(shaken_scene / "original.json"), str(shaken_scene), "-o", str(tmp_path / "x.json"),
              "--stages", "points,bundle"])
    # a scene without texture: a clear error and nothing written
    blank = tmp_path / "blank" / "000"
    blank.mkdir(parents=True)
    import cv2

    for v in ("r00_c00", "r00_c01", "r01_c00", "r01_c01"):
        cv2.imwrite(str(blank / f"{v}.png"), np.full((240, 320), 90, np.uint8))
    never = tmp_path / "never.json"
    assert main(["refine", str(shaken_scene / "original.json"), str(blank.parent), "-o", str(never),
                 "--quiet"]) == EXIT_BAD_INPUT
    assert "no usable feature tracks" in capsys.readouterr().err and not never.exists()
    # a calibration of another grid
    other = make_rig(dataclasses.replace(get_scene("small-2x2").rig, cols=3), np.random.default_rng(0))
    other.save(tmp_path / "other.json")
    assert main(["refine", str(tmp_path / "other.json"), str(shaken_scene), "-o", str(never),
                 "--quiet"]) == EXIT_BAD_INPUT
    assert not never.exists()


def test_tracks_follow_the_grid(shaken_scene):
    truth = Calibration.load(shaken_scene / "truth.json")
    images = open_capture(shaken_scene, truth.grid).load_frame(0)
    tracks = track_chain(images, truth.grid)
    assert tracks.points_px.shape == (4, tracks.num_tracks, 2) and tracks.valid.all()
    c = tracks.counts
    assert c["detected"] >= c["chain"] >= c["dedup"] >= c["ransac"] >= c["unique"] == tracks.num_tracks > 100
    pts = triangulate_dlt(truth, tracks.points_px, tracks.valid)
    err = reprojection_errors(truth, pts, tracks.points_px, tracks.valid)
    assert np.median(err) < 0.1  # tracks agree with the true cameras


@pytest.mark.slow
def test_unordered_matching_on_the_middlebury_ring(test_data):
    """Tracks for views that are not a grid (16 views on a ring, 22.5° apart) agree with the published cameras."""
    from lfgraph.datasets.middlebury import load_mview
    from lfgraph.refinement.unordered import match_unordered, ring_pairs

    truth, images = load_mview(test_data / "middlebury_temple")  # templeSparseRing, images stored as grayscale
    tracks = match_unordered(images, ring_pairs(truth.num_views, 2), min_views=3)
    assert tracks.num_tracks > 100 and np.all(tracks.valid.sum(axis=0) >= 3)
    err = reprojection_errors(truth, triangulate_dlt(truth, tracks.points_px, tracks.valid), tracks.points_px,
                              tracks.valid)
    assert np.nanmedian(err) < 0.3  # most tracks are right; the outliers are what the filters are for


def test_a_verdict_without_a_posterior_is_saved_with_nulls(tmp_path):
    """A fit whose posterior could not be computed reports NaN sigmas; the refined calibration must still save (its
    metrics carry null there, JSON has no NaN) rather than fail after the whole refinement ran."""
    import json

    from lfgraph.refinement.verdicts import ViewVerdict

    nan3 = np.full(3, np.nan)
    verdict = ViewVerdict(1, "r00_c01", "UNCERTAIN", 0.0, np.zeros(3), np.zeros(3), np.zeros(4), 0.0, nan3, nan3,
                          np.full(4, np.nan), float("nan"), 12, False, "no posterior")
    data = verdict.as_dict()
    json.dumps(data, allow_nan=False)
    assert data["sigma_rotation_deg"] == [None] * 3 and data["predicted_transfer_px"] is None
    rig = make_rig(RigConfig(rows=1, cols=2), np.random.default_rng(0))
    rig.replace(metrics={"refinement": {"verdicts": [data]}}).save(tmp_path / "calib.json")
    stored = Calibration.load(tmp_path / "calib.json").metrics["refinement"]["verdicts"][0]
    assert stored["sigma_position_mm"][0] is None
