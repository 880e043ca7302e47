"""Detections from other tools: OpenCV's multi-view JSON and the points .npz, read and calibrated end to end on
real corners (opencv_contrib's stereo data, tests/data/omnidir_stereo), judged against OpenCV's own calibration."""

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from lfgraph.cli import EXIT_BAD_INPUT, EXIT_USAGE, main
from lfgraph.core.calibration import Calibration
from lfgraph.detect.detections import PointBoard
from lfgraph.io.points import PointsError, load_detections, read_opencv_multiview, read_points_npz, write_points_npz
from lfgraph.pattern import CalibrateConfig, calibrate

DATA = Path(__file__).resolve().parents[1] / "data" / "omnidir_stereo"
OBJ = DATA / "object_points.npy"
SIZE = (704, 576)
GRID = ["--grid", "1x2", "--image-size", "704x576"]
RMS_TOLERANCE_PX = 1e-3  # the joint route's rig RMS may exceed cv2.stereoCalibrate's by at most this
FX_TOLERANCE = 2e-3  # relative focal length difference to OpenCV's, at the same minimum
BASELINE_TOLERANCE_M = 1e-3
FLAGS = cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST  # lfgraph's model: k1, k2, no tangential, no k3
TIGHT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 300, 1e-14)


def raw_points() -> tuple[np.ndarray, np.ndarray]:
    """Object points (C, 3) and image points (2, F, C, 2) read straight from the fixture with cv2.FileStorage."""
    obj = np.load(OBJ)
    views = []
    for cam in (0, 1):
        fs = cv2.FileStorage(str(DATA / f"cam_{cam}.json"), cv2.FILE_STORAGE_READ)
        frames = []
        f = 0
        while not fs.getNode(f"frame_{f}").empty():
            node = fs.getNode(f"frame_{f}")
            frames.append([node.at(i).real() for i in range(node.size())])
            f += 1
        fs.release()
        views.append(np.asarray(frames).reshape(len(frames), -1, 2))
    return obj, np.stack(views)


@pytest.fixture(scope="module")
def opencv_stereo():
    """OpenCV's reference: per-view calibrateCamera, then stereoCalibrate refining everything (same lens model)."""
    obj, img = raw_points()
    o = [obj.astype(np.float32)] * img.shape[1]
    a = [p.astype(np.float32) for p in img[0]]
    b = [p.astype(np.float32) for p in img[1]]
    _, k1, d1, _, _ = cv2.calibrateCamera(o, a, SIZE, None, None, flags=FLAGS, criteria=TIGHT)
    _, k2, d2, _, _ = cv2.calibrateCamera(o, b, SIZE, None, None, flags=FLAGS, criteria=TIGHT)
    rms, k1, d1, k2, d2, r, t, _, _ = cv2.stereoCalibrate(o, a, b, k1, d1, k2, d2, SIZE, criteria=TIGHT,
                                                          flags=FLAGS | cv2.CALIB_USE_INTRINSIC_GUESS)
    return {"rms": rms, "K": (k1, k2), "R": r, "t": t.ravel()}


def test_multiview_json_reads_what_opencv_reads():
    obj, img = raw_points()
    obs = load_detections(DATA, "opencv-multiview", (1, 2), SIZE, OBJ)
    assert isinstance(obs.board, PointBoard) and obs.board.num_corners == 48
    np.testing.assert_array_equal(obs.board.object_points(), obj)
    assert obs.corners_px.shape == (2, 15, 48, 2) and obs.valid.all()
    np.testing.assert_array_equal(obs.corners_px, img)
    assert obs.frame_names[3] == "frame_3" and obs.describe(1, 3).endswith("cam_1.json")


@pytest.mark.parametrize("method", ["joint", "paper"])
def test_real_stereo_points_against_opencv(opencv_stereo, method):
    """The same lens model as OpenCV's stereoCalibrate (radtan k1, k2): the same minimum or better."""
    obs = load_detections(DATA, "opencv-multiview", (1, 2), SIZE, OBJ)
    calib, report = calibrate(obs, CalibrateConfig(method=method, lens="radtan", screen=False))
    if method == "joint":
        # the joint graph minimises the same rig reprojection error as stereoCalibrate: it must do at least as well
        assert report.rig_rms_px <= opencv_stereo["rms"] + RMS_TOLERANCE_PX
        for v in (0, 1):
            assert calib.intrinsics[v].fx == pytest.approx(opencv_stereo["K"][v][0, 0], rel=FX_TOLERANCE)
            assert calib.intrinsics[v].cy == pytest.approx(opencv_stereo["K"][v][1, 2], abs=1.0)
        # OpenCV's R, t map view 0 to view 1: x1 = R x0 + t, i.e. view1_T_view0; lfgraph stores ref_T_view
        view1_T_ref = np.linalg.inv(calib.ref_T_view[1])
        np.testing.assert_allclose(view1_T_ref[:3, 3], opencv_stereo["t"], atol=BASELINE_TOLERANCE_M)
        np.testing.assert_allclose(view1_T_ref[:3, :3], opencv_stereo["R"], atol=1e-3)
    else:
        assert report.rig_rms_px < opencv_stereo["rms"] * 1.1  # the paper's route is close, not optimal
    assert report.residuals_px.shape == obs.corners_px.shape and len(report.frame_rms_px) == 15


@pytest.mark.slow
def test_wide_stereo_gets_a_wide_lens_model_by_itself(opencv_stereo):
    """These omnidirectional-test points leave OpenCV's radtan k1, k2 fit at ~2 px; the default lens choice finds the
    fisheye model for both views and a rig 3x more consistent than stereoCalibrate's with radtan."""
    obs = load_detections(DATA, "opencv-multiview", (1, 2), SIZE, OBJ)
    calib, report = calibrate(obs)
    assert [i.lens for i in calib.intrinsics] == ["fisheye", "fisheye"]
    assert report.rig_rms_px < opencv_stereo["rms"] / 3
    held = calib.metrics["lens_choice"]["heldout_px"]
    assert all(f < r / 3 for f, r in zip(held["fisheye"], held["radtan"], strict=True))


@pytest.mark.slow
def test_npz_round_trip_and_cli(tmp_path, opencv_stereo, capsys):
    obs = load_detections(DATA, "opencv-multiview", (1, 2), SIZE, OBJ)
    path = write_points_npz(tmp_path / "points.npz", obs)
    with np.load(path) as data:
        assert set(data.files) == {"object_points", "image_points", "valid"}
        assert data["image_points"].shape == (2, 15, 48, 2) and data["valid"].dtype == bool
    back = read_points_npz(path, (1, 2), SIZE)
    np.testing.assert_array_equal(back.corners_px, obs.corners_px)
    out = tmp_path / "calibration.json"
    assert main(["calibrate", str(path), "--detections", "npz", *GRID, "-o", str(out)]) == 0
    assert "rig-consistent RMS" in capsys.readouterr().out
    calib = Calibration.load(out)
    assert calib.metrics["rig_rms_px"] <= opencv_stereo["rms"] + RMS_TOLERANCE_PX
    assert calib.image_size_px == SIZE


@pytest.mark.slow
def test_cli_multiview(tmp_path, opencv_stereo, capsys):
    out = tmp_path / "calibration.json"
    code = main(["calibrate", str(DATA), "--detections", "opencv-multiview", "--object-points", str(OBJ), *GRID,
                 "--method", "joint", "-o", str(out)])
    assert code == 0, capsys.readouterr().err
    assert "opencv-multiview detections, 15 frames x 2 views" in capsys.readouterr().out
    assert Calibration.load(out).metrics["rig_rms_px"] <= opencv_stereo["rms"] + RMS_TOLERANCE_PX


def write_views(folder: Path, frames_per_view: list[dict[str, object]]) -> Path:
    """cam_N.json files written with cv2.FileStorage: each frame a flat sequence, or a matrix when given one."""
    folder.mkdir(parents=True, exist_ok=True)
    for cam, frames in enumerate(frames_per_view):
        fs = cv2.FileStorage(str(folder / f"cam_{cam}.json"), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_JSON)
        for name, value in frames.items():
            if isinstance(value, np.ndarray):
                fs.write(name, value)
            elif isinstance(value, str):
                fs.write(name, value)
            else:
                fs.startWriteStruct(name, cv2.FileNode_SEQ)
                for x in value:
                    fs.write("", x)
                fs.endWriteStruct()
        fs.release()
    return folder


def test_missing_nodes_and_points_are_unseen(tmp_path):
    _, img = raw_points()
    flat = [[img[v, f].ravel().tolist() for f in range(15)] for v in (0, 1)]
    partial = np.array(flat[1][4]).reshape(-1, 2)
    partial[:10] = -1  # OpenCV's "not detected"
    partial[10:44] = -1  # ... leaving 4 points: fewer than lfgraph needs, the view-frame counts as not seen
    views = [{f"frame_{f}": flat[0][f] for f in range(15) if f != 2},  # view 0 did not see frame 2
             {**{f"frame_{f}": flat[1][f] for f in range(15) if f != 4},
              "frame_4": partial.ravel().tolist(), "frame_20": flat[1][5],  # a later frame only view 1 saw
              "image_size": [704, 576]}]  # other nodes are ignored
    views[1]["frame_3"] = np.asarray(flat[1][3], np.float64).reshape(1, -1)  # an opencv-matrix node
    obs = read_opencv_multiview(write_views(tmp_path / "pts", views), PointBoard(np.load(OBJ)), (1, 2), SIZE)
    assert obs.num_frames == 21
    assert not obs.seen[0, 2] and obs.seen[1, 2]
    assert not obs.valid[1, 4].any()
    assert obs.seen[1, 20] and not obs.seen[0, 20] and not obs.seen[:, 15:20].any()
    np.testing.assert_array_equal(obs.corners_px[1, 3], img[1, 3])


@pytest.mark.parametrize(("frames", "message"), [
    ({"frame_0": list(range(95))}, "frame_0 holds 95 numbers, expected 96"),
    ({"frame_0": "text"}, "frame_0 must be a sequence of 96 numbers"),
    ({"frame_0": [1.0] * 95 + ["x"]}, "frame_0, element 95 is not a number"),
    ({"frame_0": [5000.0] * 96}, "frame_0, point 0 at (5000.0, 5000.0) px lies outside the 704x576 image"),
])
def test_malformed_nodes_name_file_and_node(tmp_path, frames, message):
    folder = write_views(tmp_path / "bad", [frames, {"frame_0": [10.0] * 96}])
    with pytest.raises(PointsError, match=r"cam_0\.json: node " + message.replace("(", r"\(").replace(")", r"\)")
                       .replace(".", r"\.")):
        read_opencv_multiview(folder, PointBoard(np.load(OBJ)), (1, 2), SIZE)


def test_bad_files_name_the_file(tmp_path):
    board = PointBoard(np.load(OBJ))
    folder = tmp_path / "broken"
    folder.mkdir()
    (folder / "cam_0.json").write_text("{ \"frame_0\": [1, 2, ")
    (folder / "cam_1.json").write_text("{}")
    with pytest.raises(PointsError, match=r"cam_0\.json: not a readable OpenCV FileStorage JSON file"):
        read_opencv_multiview(folder, board, (1, 2), SIZE)
    with pytest.raises(PointsError, match=r"2 cam_\*\.json files \(cam_0\.json, cam_1\.json\) but the 2x2 grid has 4"):
        read_opencv_multiview(DATA, board, (2, 2), SIZE)
    with pytest.raises(PointsError, match="no cam_"):
        read_opencv_multiview(tmp_path, board, (1, 2), SIZE)


@pytest.mark.parametrize(("points", "message"), [
    (np.zeros((48, 2)), r"must be a \(C, 3\) array in metres, got shape \(48, 2\)"),
    (np.c_[np.load(OBJ)[:, :2], np.linspace(0, 0.1, 48)], "must lie in the target's z = 0 plane"),
    (np.c_[np.linspace(0, 1, 48), np.zeros((48, 2))], "lie on one line"),
    (np.load(OBJ)[:4], "at least 6 points"),
])
def test_object_points_are_checked(tmp_path, points, message):
    np.save(tmp_path / "obj.npy", points)
    with pytest.raises(PointsError, match=r"obj\.npy: .*" + message):
        load_detections(DATA, "opencv-multiview", (1, 2), SIZE, tmp_path / "obj.npy")


def test_millimetre_object_points_are_refused_and_odd_spacings_flagged(tmp_path, caplog):
    """Issue 27: object points in mm were taken as metres ("spanning 560000 x 400000 mm") with a warning only."""
    np.save(tmp_path / "obj_mm.npy", np.load(OBJ) * 1000)
    with pytest.raises(PointsError, match=r"obj_mm\.npy: the object points span .* m.*millimetres"):
        load_detections(DATA, "opencv-multiview", (1, 2), SIZE, tmp_path / "obj_mm.npy")
    np.save(tmp_path / "obj_big.npy", np.load(OBJ) * 15)  # 1.2 m apart: a big target, or a unit slip
    load_detections(DATA, "opencv-multiview", (1, 2), SIZE, tmp_path / "obj_big.npy")
    assert "obj_big.npy: neighbouring object points are 1.2 m apart" in caplog.text


def test_npz_errors_name_the_key(tmp_path):
    obs = load_detections(DATA, "opencv-multiview", (1, 2), SIZE, OBJ)
    good = {"object_points": obs.board.object_points(), "image_points": obs.corners_px, "valid": obs.valid}
    cases = [({k: v for k, v in good.items() if k != "valid"}, "missing valid"),
             ({**good, "image_points": obs.corners_px[..., :1]}, r"image_points must be numeric \(V, F, C=48, 2\)"),
             ({**good, "valid": obs.valid[:, :3]}, r"valid must be booleans of shape \(2, 15, 48\)"),
             ({**good, "image_points": np.where(np.arange(48)[:, None] == 7, np.nan, obs.corners_px)},
              r"image_points\[0, 0, 7\] is not finite but valid"),
             ({**good, "object_points": good["object_points"][:40]}, r"image_points must be numeric \(V, F, C=40")]
    for i, (arrays, message) in enumerate(cases):
        path = tmp_path / f"bad{i}.npz"
        np.savez(path, **arrays)
        with pytest.raises(PointsError, match=rf"bad{i}\.npz: {message}"):
            read_points_npz(path, (1, 2), SIZE)
    np.savez(tmp_path / "good.npz", **good)
    with pytest.raises(PointsError, match=r"image_points has 2 views but the 1x3 grid has 3"):
        read_points_npz(tmp_path / "good.npz", (1, 3), SIZE)


def test_cli_bad_input_exits_without_writing(tmp_path, capsys):
    out = tmp_path / "calibration.json"
    shutil.copytree(DATA, tmp_path / "pts")
    node = json.loads((tmp_path / "pts" / "cam_1.json").read_text())
    node["frame_2"] = node["frame_2"][:-1]
    (tmp_path / "pts" / "cam_1.json").write_text(json.dumps(node))
    code = main(["calibrate", str(tmp_path / "pts"), "--detections", "opencv-multiview", "--object-points", str(OBJ),
                 *GRID, "-o", str(out)])
    assert code == EXIT_BAD_INPUT and not out.exists()
    assert "cam_1.json: node frame_2 holds 95 numbers, expected 96" in capsys.readouterr().err
    usage = [["--detections", "opencv-multiview", *GRID],  # no --object-points
             ["--detections", "npz", "--grid", "1x2"],  # no --image-size
             ["--detections", "npz", *GRID, "--board", "7x5"],  # a board with points
             ["--grid", "1x2", "--board", "7x5"]]  # images without --square-mm
    for extra in usage:
        with pytest.raises(SystemExit) as exc:
            main(["calibrate", str(DATA), *extra, "-o", str(out)])
        assert exc.value.code == EXIT_USAGE, extra
        assert not out.exists()
