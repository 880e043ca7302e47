"""Issue 25: a fisheye array renders, is detected (the wide-view second pass), calibrates from its images with no lens
flag, rectifies with a far board's rows aligned, all against the rendering's truth; pinhole views are untouched."""

import numpy as np
import pytest

from lfgraph.cli import main
from lfgraph.core.calibration import Calibration
from lfgraph.datasets.checkerboard import make_checkerboard_truth
from lfgraph.datasets.rig import make_rig
from lfgraph.datasets.scenes import get_scene
from lfgraph.detect.board import BoardSpec
from lfgraph.detect.detections import detect_capture
from lfgraph.detect.wide_boards import rough_model
from lfgraph.io.capture import open_capture
from lfgraph.judge.evaluation import evaluate_calibration
from lfgraph.rectification.rectify import compute_rectification, rectify_points

pytestmark = pytest.mark.slow  # end-to-end runs (`make test-fast` leaves them out)

BOARD = BoardSpec.parse("9x6", 30)
FRAMES = 24
MAX_CORNER_PX = 0.5  # no detected corner this far from the truth (measured 0.34 px; the first pass alone: 8.8 px)
MEDIAN_CORNER_PX = 0.02  # median corner error (measured 0.006 px; the first pass alone: 0.023 px)
MIN_FOUND_SHARE = 0.7  # boards found / boards wholly inside a view (measured 54 / 71; the first pass alone: 39)
FOCAL_PX = 0.1  # fx, fy against the truth, f = 260 px (measured <= 0.031 px)
PRINCIPAL_PX = 0.1  # cx, cy against the truth (measured <= 0.027 px)
POSITION_MM = 0.1  # view positions against the truth, 40 mm pitch (measured <= 0.025 mm)
ROWS_ALIGNED_PX = 0.05  # issue 25: a far board's points on one rectified row in every view, estimated calibration


@pytest.fixture(scope="module")
def fisheye_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("fisheye")
    capture = root / "capture"
    assert main(["synth", "checkerboard", str(capture), "--scene", "fisheye-1x3", "--frames", str(FRAMES),
                 "--jobs", "2", "--quiet", "--seed", "0"]) == 0
    calib_path = root / "calibration.json"
    assert main(["calibrate", str(capture), "--grid", "1x3", "--reference", "1", "--board", "9x6", "--square-mm", "30",
                 "--quiet", "-o", str(calib_path), "--save", str(root / "calibrate.rrd")]) == 0
    return capture, Calibration.load(calib_path), Calibration.load(capture / "truth.json")


def test_wide_views_find_most_boards_and_no_corner_is_off(fisheye_run):
    capture_dir, _, _ = fisheye_run
    capture = open_capture(capture_dir, (1, 3))
    obs, cached = detect_capture(capture, BOARD, jobs=1, progress=False)  # what calibrate detected (its cache)
    assert cached
    truth = np.load(capture_dir / "truth_corners.npz")
    err = np.linalg.norm(obs.corners_px - truth["corners_px"], axis=-1)[obs.seen]
    print(f"boards {obs.seen.sum()} of {truth['board_visible'].sum()}; corner error median {np.median(err):.4f}, "
          f"max {err.max():.3f} px")
    assert obs.seen.sum() >= MIN_FOUND_SHARE * truth["board_visible"].sum()
    assert err.max() < MAX_CORNER_PX and np.median(err) < MEDIAN_CORNER_PX


def test_a_fisheye_array_calibrates_from_its_renders_and_rectifies_rows_aligned(fisheye_run):
    _, est, truth = fisheye_run
    assert [i.lens for i in est.intrinsics] == ["fisheye"] * 3  # chosen with no lens flag
    err = evaluate_calibration(est, truth)
    print(f"intrinsics off by up to {np.abs(err.intrinsics[:, :4]).max(axis=0)} px, positions by "
          f"{np.abs(err.position_mm).max():.4f} mm")
    assert np.abs(err.intrinsics[:, :2]).max() < FOCAL_PX and np.abs(err.intrinsics[:, 2:4]).max() < PRINCIPAL_PX
    assert np.abs(err.position_mm).max() < POSITION_MM
    rect = compute_rectification(est)
    rng = np.random.default_rng(5)
    far = np.column_stack([rng.uniform(-0.3, 0.3, 200), rng.uniform(-0.2, 0.2, 200), np.ones(200)]) * 1e4
    true_ref = truth.with_reference(truth.grid.reference)
    rows = np.stack([rectify_points(est, rect, v, true_ref.intrinsics[v].project(
        far @ true_ref.view_T_ref(v)[:3, :3].T + true_ref.view_T_ref(v)[:3, 3]))[:, 1] for v in range(3)])
    w, h = rect.image_size_px
    inside = np.all((rows > 1) & (rows < h - 2), axis=0)
    assert inside.sum() > 50
    print(f"far points' rectified rows differ by up to {np.max(np.ptp(rows[:, inside], axis=0)):.4f} px")
    assert np.max(np.ptp(rows[:, inside], axis=0)) < ROWS_ALIGNED_PX


STRAIGHT_PX = 0.05  # a board row's logged corners off their straight line, in the pinhole the view is shown in
MIN_WHOLE_BOARDS = 20  # boards drawn whole in the undistorted views (40 before issue 40: fisheye points are drawn
# only inside the image as shown, so boards reaching past the pinhole image are drawn in part; measured 23)
CURVED_PX = 1.0  # ... while the same rows curve by more than this in the fisheye images (median over boards)
JPEG_CORNER_PX = 0.5  # as tests/viz/test_rerun.py: OpenCV's corners on the logged JPEG against the logged ones


def _row_bends_px(corners: np.ndarray) -> np.ndarray:
    """(rows,) largest distance of a board row's corners from their best straight line, px."""
    rows = corners.reshape(BOARD.rows, BOARD.cols, 2)
    centred = rows - rows.mean(axis=1, keepdims=True)
    normal = np.linalg.svd(centred)[2][:, 1]  # per row, the direction across the fitted line
    return np.max(np.abs(np.einsum("rcj,rj->rc", centred, normal)), axis=1)


def test_rerun_shows_fisheye_views_undistorted_to_their_pinhole(fisheye_run):
    """rerun's Pinhole is K alone: the 2-D views of a fisheye rig are logged undistorted, so a board's rows are
    straight there, and the logged points sit on the logged image's corners."""
    import cv2

    from tests.viz.test_rerun import last_per_frame, read_rrd

    capture_dir, calib, _ = fisheye_run
    _, _, rows = read_rrd(capture_dir.parent / "calibrate.rrd", "frame")
    obs, _ = detect_capture(open_capture(capture_dir, (1, 3)), BOARD, jobs=1, progress=False)
    straight, curved, gaps = [], [], []
    for v in range(3):
        name = calib.grid.name(v)
        observed = last_per_frame(rows, f"/views/{name}/observed:Points2D:positions")
        images = last_per_frame(rows, f"/views/{name}/image:EncodedImage:blob")
        for f, points in observed.items():
            if len(points) != BOARD.num_corners or not obs.seen[v, f]:
                continue
            straight.append(_row_bends_px(np.asarray(points)).max())
            curved.append(_row_bends_px(obs.corners_px[v, f]).max())
            image = cv2.imdecode(np.asarray(images[f][0], dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
            found, corners = cv2.findChessboardCorners(image, BOARD.pattern_size)
            if found:
                gaps.append(np.median(np.linalg.norm(corners.reshape(-1, 1, 2) - np.asarray(points)[None],
                                                     axis=-1).min(axis=1)))
    print(f"{len(straight)} boards: rows bend {np.median(straight):.4f} px logged, {np.median(curved):.2f} px in the "
          f"fisheye images; {len(gaps)} found again on the logged images, median gap {np.median(gaps):.3f} px")
    assert len(straight) >= MIN_WHOLE_BOARDS and np.median(straight) < STRAIGHT_PX and np.median(curved) > CURVED_PX
    assert len(gaps) >= 10 and np.max(gaps) < JPEG_CORNER_PX


@pytest.mark.parametrize("scene", ["small-2x2", "paper-4x4"])
def test_pinhole_views_get_no_second_pass(scene):
    named = get_scene(scene)
    calib = make_rig(named.rig, np.random.default_rng(0))
    truth = make_checkerboard_truth(calib, named.checkerboard, np.random.default_rng(1))
    corners = np.where(truth.corner_valid[..., None] & truth.board_visible[..., None, None], truth.corners_px, np.nan)
    for v in range(calib.num_views):
        assert rough_model(corners[v], named.checkerboard.board, calib.image_size(v)) is None


FAR_BOARD_PX = 0.05  # issue 25: a far board rendered through the true fisheye lenses, rectified with the estimate


def test_a_far_board_rendered_through_the_fisheye_lenses_lines_up_after_rectification(fisheye_run):
    import cv2

    from lfgraph.core.geometry import make_T
    from lfgraph.datasets.board_render import render_checkerboard_view
    from lfgraph.datasets.checkerboard import CheckerboardConfig
    from lfgraph.detect.chessboard import detect_board
    from lfgraph.rectification.rectify import build_maps, remap_views

    _, est, truth = fisheye_run
    truth = truth.with_reference(truth.grid.reference)
    far = BoardSpec(9, 6, 1.2)
    cfg = CheckerboardConfig(board=far, noise_sigma=0.0, blur_sigma_px=0.8)
    maps = build_maps(est, compute_rectification(est))
    rows = []
    for tilt_deg, dist in ((0.0, 22.0), (15.0, 25.0)):
        ref_T_board = make_T(cv2.Rodrigues(np.array([np.radians(tilt_deg), 0.0, 0.0]))[0], [-4.8, -3.0, dist])  # noqa: N806
        images = [render_checkerboard_view(truth.intrinsics[v], truth.image_size(v), truth.view_T_ref(v) @ ref_T_board,
                                           far, cfg) for v in range(3)]
        corners = [detect_board(img, far) for img in remap_views(images, maps)]
        assert all(c is not None for c in corners)
        rows += [corners[a][:, 1] - corners[b][:, 1] for a, b in est.grid.horizontal_pairs()]
    rms = float(np.sqrt(np.mean(np.concatenate(rows) ** 2)))
    print(f"far board through the fisheye lenses, rectified with the estimate: rows agree to {rms:.4f} px RMS")
    assert rms < FAR_BOARD_PX
