"""Pins of a self-calibration (issue 43): a board frame, a known distance, a known view fix the common zoom; a pin
that disagrees with the scene is refused by name. Exact synthetic tracks plus noise; boards from the generators."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lfgraph.core.calibration import Calibration
from lfgraph.core.camera import project_world
from lfgraph.datasets.board_render import CheckerboardConfig
from lfgraph.datasets.checkerboard import make_checkerboard_truth, make_corner_observations
from lfgraph.datasets.rig import RigConfig, make_rig
from lfgraph.detect.board import BoardSpec
from lfgraph.selfcal import (
    BoardPin,
    Design,
    DistancePin,
    PinError,
    PinRefused,
    SelfCalConfig,
    ViewPin,
    calibrate_tracks,
    pin_scene,
)
from lfgraph.selfcal.pinned import PIN_DISAGREEMENT_SIGMAS, UNCHECKED_PCT
from tests.selfcal.test_selfcal import synthetic_tracks

# a 3x3 array with a wide baseline for its depths (10 cm pitch, scenes at 1-3 m: a point's depth to ~0.3 %), so that
# one known distance can fix the zoom; the spreads of focal length, principal point, k1, rotation, position
WIDE = RigConfig(rows=3, cols=3, reference=0, pitch_m=0.1, image_size_px=(320, 240), focal_px=300.0, k1=-0.1, k2=0.0,
                 focal_jitter_px=9.0, principal_jitter_px=10.0, distortion_jitter=0.01, rot_jitter_deg=1.0,
                 trans_jitter_mm=0.3)
WIDE_DESIGN = Design(3, 3, pitch_mm=100.0, focal_px=300.0, image_size_px=(320, 240), k1=-0.1)
DEPTH_M = (1.0, 3.0)
TRACK_NOISE_PX = 0.1
CORNER_NOISE_PX = 0.1
HONEST_SIGMAS = 3.0  # a pinned zoom lies within this many of its posterior sigmas of the truth
FIXED = 0.5  # a pin that fixes the zoom leaves at most this fraction of the scene's zoom sigma
WRONG = 0.05  # a mismeasured view pin: 5 % off
# a board of 20 % larger squares: the board's size against its disparity is a depth, which this rig's scene holds only
# through the hidden principal-point gauge (~1.1 px per grid step, ~4 % of inverse depth at 0.8 m), so a 5 % wrong
# board lies within the sigmas (measured: 0.1 sigma) and a 20 % wrong one does not (4.6 sigma)
WRONG_SQUARES = 0.2
# two scene points 1.0 and 2.0 m deep (reference frame, m), about 1.01 m apart
POINTS_M = np.array([[0.10, 0.05, 1.0], [-0.05, 0.10, 2.0]])
DISTANCE_SIGMA_M = 1e-3


def zoom_px(calib: Calibration) -> float:
    return float(np.mean([[i.fx, i.fy] for i in calib.intrinsics]))


@pytest.fixture(scope="module")
def truth() -> Calibration:
    return make_rig(WIDE, np.random.default_rng(11))


@pytest.fixture(scope="module")
def scene(truth):
    """The unpinned self-calibration the pins are added to (`pin_scene`)."""
    tracks = synthetic_tracks(truth, 5, 50, TRACK_NOISE_PX, np.random.default_rng(12), depth_m=DEPTH_M)
    return calibrate_tracks(tracks, WIDE_DESIGN)


def board_pin(truth: Calibration, square_m: float = 0.05) -> BoardPin:
    """One board frame 42 deg tilted (seeded), seen whole by the views it fits in; ``square_m`` what the maker says
    (the board's true squares are 50 mm)."""
    cfg = CheckerboardConfig(board=BoardSpec(9, 6, 0.05), frames=1, distance_m=(0.7, 0.9), max_tilt_deg=45.0)
    board = make_checkerboard_truth(truth, cfg, np.random.default_rng(16))
    corners, valid = make_corner_observations(board, CORNER_NOISE_PX, np.random.default_rng(14))
    assert valid.any(axis=(1, 2)).sum() >= 2
    return BoardPin(corners, valid, BoardSpec(9, 6, square_m).object_points(),
                    name="one board frame" if square_m == 0.05 else "a board of other squares")


def distance_pin(truth: Calibration, error: float = 0.0) -> DistancePin:
    px = np.stack([project_world(truth.intrinsics[v], truth.view_T_ref(v), POINTS_M) for v in range(truth.num_views)])
    px += TRACK_NOISE_PX * np.random.default_rng(15).standard_normal(px.shape)
    true_m = float(np.linalg.norm(POINTS_M[0] - POINTS_M[1]))
    return DistancePin(true_m * (1.0 + error), DISTANCE_SIGMA_M, pixels=px, name=f"tape {100 * error:+.0f} %")


def test_a_board_frame_fixes_the_zoom(truth, scene):
    calib, report = scene
    pinned, pinned_report = pin_scene(report, WIDE_DESIGN, [board_pin(truth)])
    (result,) = pinned_report.pins
    sigma = pinned_report.modes[0].posterior_sigma
    assert result.fixes_zoom and sigma < FIXED * report.modes[0].posterior_sigma
    assert abs(zoom_px(pinned) - zoom_px(truth)) < HONEST_SIGMAS * sigma
    assert pinned_report.zoom_from == "pin one board frame" and report.zoom_from == "design focal length"
    assert pinned.metrics["zoom_from"] == "pin one board frame"
    assert "one board frame" in pinned_report.text() and pinned_report.as_dict()["pins"][0]["fixes_zoom"]
    assert result.check_pct is None  # a board's mistake (its square size) is not a figure the report gives


def test_a_known_distance_fixes_the_near_gauge_the_scene_sees_least(truth, scene):
    """A distance fixes one combination of the two near-gauges (the zoom scales depths, the hidden principal-point
    gauge shifts inverse depths); on this wide rig the scene holds the zoom better than the hidden gauge, which the
    distance then fixes (a cx slope per grid step: the disparity of infinity)."""
    calib, report = scene
    pinned, pinned_report = pin_scene(report, WIDE_DESIGN, [distance_pin(truth)])
    slope = [m for m in pinned_report.modes if m.name.startswith("cx per grid column")][0]
    before = [m for m in report.modes if m.name.startswith("cx per grid column")][0]
    assert slope.posterior_sigma < FIXED * before.posterior_sigma
    cols = np.array([truth.grid.offset(v)[1] for v in range(truth.num_views)], dtype=float)
    err = np.array([e.cx - t.cx for e, t in zip(pinned.intrinsics, truth.intrinsics, strict=True)])
    fitted_slope = np.polyfit(cols, err, 1)[0]
    assert abs(fitted_slope) < HONEST_SIGMAS * slope.posterior_sigma
    assert abs(zoom_px(pinned) - zoom_px(truth)) < HONEST_SIGMAS * pinned_report.modes[0].posterior_sigma
    # the scene holds this distance only through the hidden gauge: it cannot check it to a few per cent, and says so
    assert pinned_report.pins[0].check_pct > UNCHECKED_PCT
    assert "warning: pin tape +0 % could not be checked" in pinned_report.text()


# two marks on a wall facing the array 1.5 m deep, 0.63 m apart; the wall's depth known to 1 mm per metre
WALL_M = 1.5
WALL_POINTS_M = np.array([[-0.3, 0.1, WALL_M], [0.3, -0.1, WALL_M]])
WRONG_DISTANCE = 0.05  # a mismeasured distance: 5 % off


def wall_pin(truth: Calibration, error: float = 0.0) -> DistancePin:
    px = np.stack([project_world(truth.intrinsics[v], truth.view_T_ref(v), WALL_POINTS_M)
                   for v in range(truth.num_views)])
    px += TRACK_NOISE_PX * np.random.default_rng(15).standard_normal(px.shape)
    true_m = float(np.linalg.norm(WALL_POINTS_M[0] - WALL_POINTS_M[1]))
    return DistancePin(true_m * (1.0 + error), DISTANCE_SIGMA_M * true_m, pixels=px, depth_m=WALL_M,
                       depth_sigma_m=DISTANCE_SIGMA_M * WALL_M, name=f"wall {100 * error:+.0f} %")


def test_a_distance_on_a_plane_of_known_depth_fixes_the_zoom(truth, scene):
    """Two marks at one known depth subtend an angle that every pinhole view sees through its focal length alone:
    the zoom (1.1 % -> 0.19 % measured), whatever the hidden gauge does to triangulated depths; a distance 5 % wrong
    is then a zoom 5 % off, refused (measured 3.2 sigma: this rig's scene holds the zoom only to 1.1 %)."""
    calib, report = scene
    pinned, pinned_report = pin_scene(report, WIDE_DESIGN, [wall_pin(truth)])
    (result,) = pinned_report.pins
    assert result.fixes_zoom and "fitted depth" in result.residual
    assert abs(zoom_px(pinned) - zoom_px(truth)) < HONEST_SIGMAS * pinned_report.modes[0].posterior_sigma
    with pytest.raises(PinRefused, match=r"pin wall \+5 % disagrees with the scene by .* on a plane 1.5 m"):
        pin_scene(report, WIDE_DESIGN, [wall_pin(truth, WRONG_DISTANCE)])


SLID_PX = 5.0  # a mark followed along an edge: slid this far in one view (measured on a rendered wall: 5-6 px)


def test_a_mark_followed_along_an_edge_is_dropped(truth, scene):
    """A mark on an edge can be followed along it; the views where it slid are those the scene's calibration cannot
    explain (dropped, worst first), and the wall pin is accepted with the right zoom."""
    calib, report = scene
    right = wall_pin(truth)
    pixels = right.pixels.copy()
    pixels[8, 1, 0] += SLID_PX
    slid = DistancePin(right.distance_m, right.sigma_m, pixels=pixels, depth_m=WALL_M,
                       depth_sigma_m=right.depth_sigma_m, name="slid")
    checked = slid.checked(report.scene.calib)
    assert not checked.valid[8, 1] and checked.valid.sum() == slid.valid.sum() - 1
    assert checked.pixel_sigma_px < 2 * TRACK_NOISE_PX
    pinned, pinned_report = pin_scene(report, WIDE_DESIGN, [slid])
    assert abs(zoom_px(pinned) - zoom_px(truth)) < HONEST_SIGMAS * pinned_report.modes[0].posterior_sigma


CHECK_MARGIN = 2.0  # a mistake this many times what the report says the scene can check is refused, one this many
# times smaller is accepted (the right measurement's own noise moves the line: measured 2.1-2.3 sigma at 1x)


def test_the_report_says_how_far_the_scene_can_check_a_distance(truth, scene):
    """The report says how large a mistake in a distance the scene can see (`PinResult.check_pct`, linearised from
    the pinned posterior); well beyond it a wrong distance is refused, well below it passes."""
    calib, report = scene
    (result,) = pin_scene(report, WIDE_DESIGN, [wall_pin(truth)])[1].pins
    assert 0 < result.check_pct < 100 * WRONG_DISTANCE and "can check this distance only to" in result.text()
    assert not any("could not be checked" in w for w in pin_scene(report, WIDE_DESIGN, [wall_pin(truth)])[1].warnings)
    assert result.as_dict()["check_pct"] == result.check_pct
    with pytest.raises(PinRefused):
        pin_scene(report, WIDE_DESIGN, [wall_pin(truth, CHECK_MARGIN * result.check_pct / 100)])
    pin_scene(report, WIDE_DESIGN, [wall_pin(truth, result.check_pct / 100 / CHECK_MARGIN)])


def test_a_board_of_other_squares_is_refused_by_name(truth, scene):
    with pytest.raises(PinRefused, match=r"pin a board of other squares disagrees with the scene by .* sigma"):
        pin_scene(scene[1], WIDE_DESIGN, [board_pin(truth, 0.05 * (1 + WRONG_SQUARES))])


def test_a_known_view_fixes_the_zoom_and_another_cameras_is_refused(truth, scene):
    calib, report = scene
    v = 4
    sigmas = (0.3, 0.3, 0.5, 0.5, 0.002, 0.005)  # an earlier board calibration's
    right = ViewPin(v, truth.intrinsics[v], sigmas, name="factory")
    pinned, pinned_report = pin_scene(report, WIDE_DESIGN, [right])
    assert pinned_report.pins[0].fixes_zoom
    assert abs(zoom_px(pinned) - zoom_px(truth)) < HONEST_SIGMAS * pinned_report.modes[0].posterior_sigma
    assert pinned_report.pins[0].check_pct < 100 * WRONG  # the report says a 5 % wrong focal length can be seen ...
    other = truth.intrinsics[v]
    wrong = ViewPin(v, type(other)(other.fx * (1 + WRONG), other.fy * (1 + WRONG), other.cx, other.cy, other.k1),
                    sigmas, name="another camera")
    with pytest.raises(PinRefused, match="pin another camera disagrees"):  # ... and it is refused
        pin_scene(report, WIDE_DESIGN, [wrong])


def test_pins_pass_through_calibrate_tracks(truth):
    tracks = synthetic_tracks(truth, 5, 50, TRACK_NOISE_PX, np.random.default_rng(12), depth_m=DEPTH_M)
    with pytest.raises(PinRefused, match="a board of other squares"):
        calibrate_tracks(tracks, WIDE_DESIGN, SelfCalConfig(pins=(board_pin(truth, 0.05 * (1 + WRONG_SQUARES)),)))


def test_pins_are_validated(tmp_path, truth):
    with pytest.raises(PinError, match="corners_px must be"):
        BoardPin(np.zeros((9, 1, 4)), np.ones((9, 1, 4), bool), np.zeros((4, 3)))
    with pytest.raises(PinError, match="no view sees the board"):
        BoardPin(np.zeros((9, 1, 4, 2)), np.ones((9, 1, 4), bool), np.zeros((4, 3)))
    with pytest.raises(PinError, match="sigma_m must be a positive"):
        DistancePin(1.0, 0.0, pixels=np.zeros((9, 2, 2)))
    with pytest.raises(PinError, match="at least two views"):
        DistancePin(1.0, 0.001, pixels=np.zeros((9, 2, 2)), valid=np.eye(9, 2, dtype=bool))
    with pytest.raises(PinError, match="marked_px"):
        DistancePin(1.0, 0.001, view=0, frame=0)
    with pytest.raises(PinError, match="needs both depth_m and depth_sigma_m"):
        DistancePin(1.0, 0.001, pixels=np.zeros((9, 2, 2)), depth_m=2.0)
    with pytest.raises(PinError, match="depth_sigma_m must be a positive"):
        DistancePin(1.0, 0.001, pixels=np.zeros((9, 2, 2)), depth_m=2.0, depth_sigma_m=-1.0)
    with pytest.raises(ValueError, match="one BoardPin"):
        SelfCalConfig(pins=(board_pin(truth), board_pin(truth)))
    with pytest.raises(TypeError, match="pins must hold"):
        SelfCalConfig(pins=("board",))
    grid = WIDE_DESIGN.grid
    path = tmp_path / "distance.json"
    path.write_text(json.dumps({"view": "r00_c00", "frame": 0, "points_px": [[1, 2]], "distance_m": 1.0,
                                "sigma_m": 0.001}))
    with pytest.raises(PinError, match=r"distance.json: field points_px"):
        DistancePin.load(path, grid)
    path.write_text(json.dumps({"view": "r09_c00", "frame": 0}))
    with pytest.raises(PinError, match=r"distance.json: missing field\(s\) points_px, distance_m, sigma_m"):
        DistancePin.load(path, grid)
    path.write_text(json.dumps({"view": "r09_c00", "frame": 0, "points_px": [[1, 2], [30, 40]], "distance_m": 1.0,
                                "sigma_m": 0.001}))
    with pytest.raises(PinError, match="r09_c00"):
        DistancePin.load(path, grid)
    path.write_text(json.dumps({"view": "r01_c01", "frame": 2, "points_px": [[1, 2], [30, 40]], "distance_m": 1.5,
                                "sigma_m": 0.002}))
    pin = DistancePin.load(path, grid)
    assert pin.view == 4 and pin.frame == 2 and pin.needs_images and pin.name == "distance distance.json"
    path.write_text(json.dumps({"view": "r01_c01", "frame": 2, "points_px": [[1, 2], [30, 40]], "distance_m": 1.5,
                                "sigma_m": 0.002, "depth_m": 2.0}))
    with pytest.raises(PinError, match=r"distance.json: missing field\(s\) depth_sigma_m"):
        DistancePin.load(path, grid)
    path.write_text(json.dumps({"view": "r01_c01", "frame": 2, "points_px": [[1, 2], [30, 40]], "distance_m": 1.5,
                                "sigma_m": 0.002, "depth_m": 2.0, "depth_sigma_m": 0.002}))
    assert DistancePin.load(path, grid).depth_m == 2.0
    calib_path = tmp_path / "calib.json"
    truth.save(calib_path)  # no stored sigmas
    with pytest.raises(PinError, match="calib.json: field metrics.sigmas is missing"):
        ViewPin.from_file("r00_c01", calib_path, grid)


FOLLOW_PX = 0.5  # a marked point followed into the other views lies this close to its true projection


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """The six rendered frames of test_selfcal's 2x2 array, written as a capture folder."""
    from tests.selfcal.test_selfcal import SMALL, render_small

    root = tmp_path_factory.mktemp("scenes")
    return (*render_small(SMALL, root), root)


@pytest.mark.slow
def test_marked_points_are_followed_to_their_true_projections(rendered):
    import cv2

    from lfgraph.datasets.scene import SceneConfig, make_scene, render_scene_depth
    from tests.selfcal.test_selfcal import BANDS_M

    truth, frames, _ = rendered
    f = 2  # as render_small drew it
    near, far = BANDS_M[f % 3]
    scene = make_scene(SceneConfig(depth_m=(near, far), background_depth_m=far * 1.4, objects=6),
                       np.random.default_rng([11, f]))
    depth = render_scene_depth(scene, truth.intrinsics[0], truth.image_size_px, truth.view_T_ref(0))
    marks = cv2.goodFeaturesToTrack(frames[f][0], 40, 0.01, 10).reshape(-1, 2)
    d = depth[np.rint(marks[:, 1]).astype(int), np.rint(marks[:, 0]).astype(int)]
    from lfgraph.selfcal.pins import follow_marks

    pixels, valid = follow_marks(frames[f], truth.grid, 0, marks)
    xy = truth.intrinsics[0].undistort(marks)
    points = np.column_stack([xy, np.ones(len(xy))]) * d[:, None]
    true = np.stack([project_world(truth.intrinsics[v], truth.view_T_ref(v), points) for v in range(4)])
    err = np.linalg.norm(pixels - true, axis=2)[:, valid.all(axis=0)]
    assert valid.all(axis=0).mean() > 0.5
    assert np.median(err) < FOLLOW_PX / 2 and np.mean(err < FOLLOW_PX) > 0.8  # depth edges aside


@pytest.mark.slow
def test_cli_takes_a_view_pin_and_refuses_another_cameras_writing_nothing(rendered, tmp_path, capsys):
    from lfgraph.cli import main

    truth, _, root = rendered
    sigmas = [{"fx_px": 0.3, "fy_px": 0.3, "cx_px": 0.5, "cy_px": 0.5, "k1": 0.002, "k2": 0.005,
               "rotation_deg": [0.01] * 3, "position_mm": [0.1] * 3}] * 4
    truth.replace(metrics={"sigmas": sigmas}).save(tmp_path / "factory.json")
    i = truth.intrinsics[1]
    other = type(i)(i.fx * 1.1, i.fy * 1.1, i.cx, i.cy, i.k1)
    truth.replace(intrinsics=(truth.intrinsics[0], other, *truth.intrinsics[2:]),
                  metrics={"sigmas": sigmas}).save(tmp_path / "other.json")
    args = ["calibrate-scene", str(root), "--grid", "2x2", "--pitch-mm", "30", "--focal-px", "280", "--quiet",
            "--no-rectify"]
    out, report = tmp_path / "c.json", tmp_path / "r.json"
    assert main([*args, "--pin-view", f"r00_c01={tmp_path / 'other.json'}", "-o", str(out),
                 "--report-json", str(report)]) == 1
    assert "pin view r00_c01=other.json disagrees with the scene by" in capsys.readouterr().err
    assert not out.exists() and not report.exists()
    assert main([*args, "--pin-view", f"r00_c01={tmp_path / 'factory.json'}", "-o", str(out),
                 "--report-json", str(report)]) == 0
    doc = json.loads(report.read_text())
    assert doc["pins"][0]["name"] == "view r00_c01=factory.json" and doc["zoom_from"] == "pin view r00_c01=factory.json"
    assert Calibration.load(out).metrics["zoom_from"] == doc["zoom_from"]


PIN_BOARD = BoardSpec(9, 6, 0.03)  # the CLI test's pin board: 9x6 inner corners of 30 mm
PIN_BOARD_TILT_DEG = 40.0  # held this tilted about the board's vertical axis (a board facing the array sees no zoom)
PIN_BOARD_DEPTH_M = 0.5


def render_pin_board(truth: Calibration, root) -> None:
    """One frame of `PIN_BOARD`, tilted by `PIN_BOARD_TILT_DEG` in front of the reference view, rendered into every
    view (blur, sensor noise) and written as a capture folder."""
    from lfgraph.datasets.checkerboard import iter_view_images
    from lfgraph.io.capture import write_frame

    cfg = CheckerboardConfig(board=PIN_BOARD, frames=1)
    a = np.radians(PIN_BOARD_TILT_DEG)
    ref_T_board = np.eye(4)  # noqa: N806
    ref_T_board[:3, :3] = [[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]]
    centre = PIN_BOARD.object_points().mean(axis=0)
    ref_T_board[:3, 3] = np.array([0.0, 0.0, PIN_BOARD_DEPTH_M]) - ref_T_board[:3, :3] @ centre
    board = make_checkerboard_truth(truth, cfg, np.random.default_rng(0), ref_T_board=ref_T_board[None])
    assert board.board_visible[:, 0].all()  # every view sees it whole
    images = np.stack([next(iter_view_images(truth, board, cfg, 5, v))[1] for v in range(truth.num_views)])
    write_frame(root, "000", images, truth.grid)


@pytest.mark.slow
def test_cli_takes_a_board_pin(rendered, tmp_path, capsys):
    """`--pin-board DIR --board --square-mm`: a rendered board frame is detected, fitted with the scene and named in
    the report, the zoom within its sigmas of the truth; a pin board without its square size is a usage error."""
    from lfgraph.cli import main

    truth, _, root = rendered
    boards = tmp_path / "pin-board"
    render_pin_board(truth, boards)
    args = ["calibrate-scene", str(root), "--grid", "2x2", "--pitch-mm", "30", "--focal-px", "280", "--quiet",
            "--no-rectify", "--pin-board", str(boards), "--board", "9x6"]
    out, report = tmp_path / "c.json", tmp_path / "r.json"
    with pytest.raises(SystemExit) as usage:
        main([*args, "-o", str(out)])
    assert usage.value.code == 2 and "--pin-board needs the board" in capsys.readouterr().err and not out.exists()
    assert main([*args, "--square-mm", "30", "-o", str(out), "--report-json", str(report)]) == 0
    doc = json.loads(report.read_text())
    (pin,) = doc["pins"]
    assert pin["kind"] == "board" and pin["name"] == f"board {boards}" and pin["sigma_px"] < pin["scene_sigma_px"]
    assert "corners" in pin["residual"] and abs(pin["disagreement_sigmas"]) < PIN_DISAGREEMENT_SIGMAS
    calib = Calibration.load(out)
    assert calib.metrics["zoom_from"] == doc["zoom_from"]
    assert abs(zoom_px(calib) - zoom_px(truth)) < HONEST_SIGMAS * pin["sigma_px"]
