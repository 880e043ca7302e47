"""Multi-view rectification: alignment at infinity and as seen, LUTs, storage, CLI, real stereo data."""

import dataclasses
import json
import shutil

import cv2
import numpy as np
import pytest

from lfgraph.cli import EXIT_BAD_INPUT, EXIT_DRIFT, main
from lfgraph.core.calibration import Calibration
from lfgraph.core.geometry import make_T
from lfgraph.datasets.board_render import render_checkerboard_view
from lfgraph.datasets.checkerboard import (
    CheckerboardConfig,
    make_checkerboard_truth,
    make_corner_observations,
)
from lfgraph.datasets.rig import RigConfig, make_rig
from lfgraph.datasets.scenes import get_scene
from lfgraph.detect.board import BoardSpec
from lfgraph.detect.chessboard import detect_board
from lfgraph.detect.detections import observations_from_arrays
from lfgraph.judge.alignment import align_points, infinity_alignment
from lfgraph.pattern import CalibrateConfig, calibrate
from lfgraph.rectification.rectify import (
    RectificationError,
    attach,
    build_maps,
    compute_rectification,
    rectify_points,
    remap_views,
    stored_rectification,
)

TRUE_INFINITY_PX = 0.01  # issue 4: misalignment at infinity with the true calibration
ESTIMATED_INFINITY_PX = 0.05  # ... with a calibration estimated by lfgraph
FAR_BOARD_PX = 0.1  # corners detected in rectified renders of a board at >= 20 m
COMPENSATED_PX = 0.15  # parallax-compensated misalignment of detected corners
LUT_VS_POINTS_PX = 0.02  # OpenCV's fixed-point LUT (1/32 px) against the exact point mapping


@pytest.fixture(scope="module")
def paper_rig():
    scene = get_scene("paper-4x4")
    rng = np.random.default_rng(5)
    calib = make_rig(scene.rig, rng)
    truth = make_checkerboard_truth(calib, scene.checkerboard, rng)
    return calib, truth


def test_true_calibration_aligns_at_infinity(paper_rig):
    calib, _ = paper_rig
    rect = compute_rectification(calib)
    a = infinity_alignment(calib, rect)
    assert a.n_points > 100
    assert a.row_px <= TRUE_INFINITY_PX and a.col_px <= TRUE_INFINITY_PX
    assert a.proportionality_px <= TRUE_INFINITY_PX  # zero disparity at infinity


@pytest.mark.slow
def test_estimated_calibration_aligns_at_infinity_within_its_accuracy(paper_rig):
    calib, truth = paper_rig
    corners, valid = make_corner_observations(truth, 0.1, np.random.default_rng(1))
    obs = observations_from_arrays(truth.board, calib.grid, calib.image_size_px, corners, valid)
    est, _ = calibrate(obs)
    rect = compute_rectification(est)
    a = infinity_alignment(est, rect, seen_by=calib)
    assert a.row_px <= ESTIMATED_INFINITY_PX and a.col_px <= ESTIMATED_INFINITY_PX
    assert a.proportionality_px <= ESTIMATED_INFINITY_PX
    # the paper's route is far less accurate: its rig shows up at infinity
    paper, _ = calibrate(obs, CalibrateConfig(method="paper"))
    assert infinity_alignment(paper, compute_rectification(paper), seen_by=calib).row_px > a.row_px


def test_true_corners_align_once_the_off_grid_parallax_is_removed(paper_rig):
    calib, truth = paper_rig
    rect = compute_rectification(calib)
    n = calib.num_views
    report = align_points(calib, rect, truth.corners_px.reshape(n, -1, 2), truth.corner_valid.reshape(n, -1))
    assert report.before.row_px > 1.0  # the raw views do not line up
    assert report.after.row_px > 0.05  # parallax of the real (off-grid) rig at board distance
    assert report.compensated.row_px < 1e-6 and report.compensated.col_px < 1e-6
    assert report.parallax.row_px == pytest.approx(report.after.row_px, rel=1e-6)


def test_grid_deviation_matches_the_rig(paper_rig):
    calib, _ = paper_rig
    rect = compute_rectification(calib)
    pitch = get_scene("paper-4x4").rig.pitch_m
    np.testing.assert_allclose(rect.pitch_m, pitch, rtol=0.02)
    assert np.max(np.abs(rect.deviation_mm)) < 1.0  # jitter 0.15 mm per axis
    assert np.all(rect.rotation_deviation_deg < 3.0)
    # a perfect grid has no deviation
    perfect = calib.replace(ref_T_view=np.stack([make_T(np.eye(3), [c * pitch, r * pitch, 0.0])
                                                 for r in range(4) for c in range(4)]))
    r2 = compute_rectification(perfect)
    assert np.max(np.abs(r2.deviation_mm)) < 1e-9 and np.max(r2.rotation_deviation_deg) < 1e-6


def test_luts_agree_with_point_mapping_and_crop(paper_rig):
    calib, _ = paper_rig
    for crop in ("valid", "full"):
        rect = compute_rectification(calib, crop)
        maps = build_maps(calib, rect)
        w, h = rect.image_size_px
        assert maps.map_xy[0].shape == (h, w, 2) and maps.map_xy[0].dtype == np.int16
        view = 6
        pts = np.array([[120.0, 80.0], [w / 2, h / 2], [w - 150.0, h - 90.0]])
        intr = calib.intrinsics[view]
        fx, fy = cv2.initUndistortRectifyMap(intr.K, intr.dist_cv, rect.rect_R_view[view], rect.K_r,
                                             rect.image_size_px, cv2.CV_32FC1)
        src = np.column_stack([fx[pts[:, 1].astype(int), pts[:, 0].astype(int)],
                               fy[pts[:, 1].astype(int), pts[:, 0].astype(int)]]).astype(np.float64)
        back = rectify_points(calib, rect, view, src)
        np.testing.assert_allclose(back, np.floor(pts), atol=LUT_VS_POINTS_PX)
    full = compute_rectification(calib, "full")
    valid = compute_rectification(calib, "valid")
    assert full.image_size_px == calib.image_size_px
    assert valid.image_size_px[0] <= full.image_size_px[0] and valid.image_size_px[1] <= full.image_size_px[1]


def test_rectification_round_trips_through_the_calibration_file(paper_rig, tmp_path):
    calib, _ = paper_rig
    rect = compute_rectification(calib)
    attach(calib, rect).save(tmp_path / "c.json")
    back = stored_rectification(Calibration.load(tmp_path / "c.json"))
    np.testing.assert_allclose(back.rect_R_view, rect.rect_R_view, atol=1e-15)
    np.testing.assert_allclose(back.P, rect.P, atol=1e-9)
    assert back.image_size_px == rect.image_size_px and back.crop == rect.crop
    with pytest.raises(RectificationError, match="crop"):
        compute_rectification(calib, "tight")


def test_far_board_corners_line_up_in_rectified_renders():
    """A big board at 20+ m (off-grid parallax < 0.03 px) rendered, rectified, detected: rows/cols agree."""
    scene = get_scene("small-2x2")
    calib = make_rig(scene.rig, np.random.default_rng(2))
    board = BoardSpec(9, 6, 1.2)
    cfg = CheckerboardConfig(board=board, noise_sigma=0.0, blur_sigma_px=0.8)
    rows, cols = [], []
    for tilt_deg, dist in ((0.0, 22.0), (15.0, 25.0)):
        R = cv2.Rodrigues(np.array([np.radians(tilt_deg), 0.0, 0.0]))[0]  # noqa: N806
        ref_T_board = make_T(R, [-4.8, -3.0, dist])  # noqa: N806
        images = np.stack([render_checkerboard_view(calib.intrinsics[v], calib.image_size_px,
                                                    calib.view_T_ref(v) @ ref_T_board, board, cfg)
                           for v in range(calib.num_views)])
        rect = compute_rectification(calib)
        rectified = remap_views(images, build_maps(calib, rect))
        corners = [detect_board(img, board) for img in rectified]
        assert all(c is not None for c in corners)
        for a, b in calib.grid.horizontal_pairs():
            rows.append(corners[a][:, 1] - corners[b][:, 1])
        for a, b in calib.grid.vertical_pairs():
            cols.append(corners[a][:, 0] - corners[b][:, 0])
    print(f"far board: rows {np.sqrt(np.mean(np.concatenate(rows) ** 2)):.4f} px, "
          f"cols {np.sqrt(np.mean(np.concatenate(cols) ** 2)):.4f} px")
    assert np.sqrt(np.mean(np.concatenate(rows) ** 2)) <= FAR_BOARD_PX
    assert np.sqrt(np.mean(np.concatenate(cols) ** 2)) <= FAR_BOARD_PX


# ------------------------------------------------------------------------------------------------ CLI
@pytest.fixture(scope="module")
def small_capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("rect") / "small"
    assert main(["synth", "checkerboard", str(out), "--scene", "small-2x2", "--frames", "12", "--jobs", "2",
                 "--quiet", "--seed", "8"]) == 0
    calib_path = out.parent / "calibration.json"
    assert main(["calibrate", str(out), "--grid", "2x2", "--board", "7x5", "--square-mm", "15", "--quiet",
                 "-o", str(calib_path)]) == 0
    return out, calib_path


@pytest.mark.slow
def test_rectify_command_and_detected_corner_alignment(small_capture, tmp_path, capsys):
    src, calib_path = small_capture
    out = tmp_path / "rectified"
    assert main(["rectify", str(calib_path), str(src), "-o", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "grid deviation" in text and "K_r" in text
    stored = Calibration.load(out / "calibration.json")
    rect = stored_rectification(stored)
    first = cv2.imread(str(out / "000" / "r00_c00.png"))
    assert first.shape[:2] == (rect.image_size_px[1], rect.image_size_px[0])
    assert len(list(out.glob("*/r01_c01.png"))) == 12
    # detected corners at board distance: parallax-compensated misalignment small, as-seen reported beside it
    board = BoardSpec(7, 5, 0.015)
    frames = sorted(p.name for p in src.iterdir() if p.is_dir())
    pix = np.full((4, len(frames) * board.num_corners, 2), np.nan)
    for f, name in enumerate(frames):
        for v in range(4):
            img = cv2.imread(str(src / name / f"{stored.grid.name(v)}.png"), cv2.IMREAD_GRAYSCALE)
            c = detect_board(img, board)
            if c is not None:
                pix[v, f * board.num_corners:(f + 1) * board.num_corners] = c
    report = align_points(stored, rect, pix, np.all(np.isfinite(pix), axis=-1))
    assert report.compensated.row_px <= COMPENSATED_PX and report.compensated.col_px <= COMPENSATED_PX
    assert report.before.row_px > report.after.row_px


def test_rectify_refuses_mismatched_captures(small_capture, tmp_path, capsys):
    src, calib_path = small_capture
    calib = Calibration.load(calib_path)
    other_grid = make_rig(dataclasses.replace(get_scene("small-2x2").rig, cols=3), np.random.default_rng(0))
    other_grid.save(tmp_path / "3.json")
    out = tmp_path / "never"
    assert main(["rectify", str(tmp_path / "3.json"), str(src), "-o", str(out), "--quiet"]) == EXIT_BAD_INPUT
    assert "grid" in capsys.readouterr().err and not out.exists()
    bigger = calib.replace(image_size_px=(640, 480))
    bigger.save(tmp_path / "big.json")
    assert main(["rectify", str(tmp_path / "big.json"), str(src), "-o", str(out), "--quiet"]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "320x240" in err and "640x480" in err and not out.exists()
    # an unreadable image half way: no partial output folder
    broken = tmp_path / "broken"
    shutil.copytree(src, broken)
    (broken / "006" / "r00_c01.png").write_bytes(b"junk")
    assert main(["rectify", str(calib_path), str(broken), "-o", str(out), "--jobs", "1",
                 "--quiet"]) == EXIT_BAD_INPUT
    assert "r00_c01.png" in capsys.readouterr().err
    assert not out.exists() and not list(tmp_path.glob(".never*"))
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("keep me")
    with pytest.raises(SystemExit):
        main(["rectify", str(calib_path), str(src), "-o", str(tmp_path / "full")])
    assert (tmp_path / "full" / "x").read_text() == "keep me"


def test_check_command_flags_a_shaken_rig(tmp_path, capsys):
    scene_dir = tmp_path / "scene"
    assert main(["synth", "scene", str(scene_dir), "--scene", "small-2x2", "--frames", "1", "--shake-rot-deg",
                 "0.5", "--shake-trans-mm", "1", "--jobs", "2", "--quiet"]) == 0
    assert main(["check", str(scene_dir / "truth.json"), str(scene_dir)]) == 0
    good = capsys.readouterr().out
    assert main(["check", str(scene_dir / "original.json"), str(scene_dir)]) == EXIT_DRIFT
    bad = capsys.readouterr().out
    assert "OK: " in good and "DRIFTED: " in bad and "parallax removed" in good
    # issue 39: one tolerance, one name, applied once: 0 (every significant change) is refine's rule and check's too;
    # the JSON verdict is the library's (`DriftReport.verdict`) in the one vocabulary
    assert main(["check", str(scene_dir / "original.json"), str(scene_dir), "--tolerance-px", "0", "--json"]) == 3
    report = json.loads(capsys.readouterr().out)
    assert report["verdict"] == "DRIFTED" and report["tolerance_px"] == 0
    assert any(v["verdict"] == "DRIFTED" for v in report["views"])
    with pytest.raises(SystemExit):
        main(["check", str(scene_dir / "original.json"), str(scene_dir), "--tolerance-px", "-1"])


# ------------------------------------------------------------------------------------------------ real data
@pytest.mark.slow
def test_opencv_stereo_rows_no_worse_than_stereo_rectify(test_data, tmp_path):
    src = tmp_path / "stereo"
    shutil.copytree(test_data / "opencv_stereo", src)
    assert main(["calibrate", str(src), "--grid", "1x2", "--board", "9x6", "--square-mm", "1", "--quiet",
                 "-o", str(tmp_path / "c.json")]) == 0
    calib = Calibration.load(tmp_path / "c.json")
    rect = compute_rectification(calib)
    board = BoardSpec(9, 6, 0.001)
    ids = [1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 14]
    left = np.concatenate([detect_board(cv2.imread(str(src / f"left{i:02d}.jpg"), 0), board) for i in ids])
    right = np.concatenate([detect_board(cv2.imread(str(src / f"right{i:02d}.jpg"), 0), board) for i in ids])
    ours = np.sqrt(np.mean((rectify_points(calib, rect, 0, left)[:, 1] - rectify_points(calib, rect, 1, right)[:, 1])
                           ** 2))
    K0, K1 = calib.intrinsics[0], calib.intrinsics[1]  # noqa: N806
    T = calib.view_T_ref(1)  # noqa: N806
    R1, R2, P1, P2, *_ = cv2.stereoRectify(K0.K, K0.dist_cv, K1.K, K1.dist_cv, calib.image_size_px,  # noqa: N806
                                           T[:3, :3].copy(), T[:3, 3].reshape(3, 1).copy())
    l_cv = cv2.undistortPoints(left.reshape(-1, 1, 2), K0.K, K0.dist_cv, R=R1, P=P1,
                               criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)).reshape(-1, 2)
    r_cv = cv2.undistortPoints(right.reshape(-1, 1, 2), K1.K, K1.dist_cv, R=R2, P=P2,
                               criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)).reshape(-1, 2)
    opencv = np.sqrt(np.mean((l_cv[:, 1] - r_cv[:, 1]) ** 2))
    print(f"row misalignment of corners: lfgraph {ours:.4f} px, cv2.stereoRectify {opencv:.4f} px")
    assert ours <= opencv * 1.0001, f"lfgraph {ours:.4f} px vs cv2.stereoRectify {opencv:.4f} px"
    assert ours < 0.5


def test_degenerate_rigs_are_refused_by_name():
    """Issue 27: two views at one position, or k1 = 50, gave rectified images and a grid deviation with no warning."""
    from lfgraph.rectification.rectify import RectificationError, compute_rectification

    rig = make_rig(RigConfig(rows=2, cols=2, image_size_px=(320, 240), focal_px=300.0), np.random.default_rng(0))
    poses = np.array(rig.ref_T_view)
    poses[3] = poses[2]  # r01_c01 at r01_c00's position
    with pytest.raises(RectificationError, match="r01_c00 and r01_c01 are at one position"):
        compute_rectification(rig.replace(ref_T_view=poses))
    for k1, k2 in ((50.0, 0.0), (-1.5, 0.0)):  # absurd pincushion; a barrel lens that folds over inside the image
        bad = rig.replace(intrinsics=(dataclasses.replace(rig.intrinsics[0], k1=k1, k2=k2), *rig.intrinsics[1:]))
        with pytest.raises(RectificationError, match="r00_c00: its lens model"):
            compute_rectification(bad)
    compute_rectification(rig)  # the rig itself rectifies
