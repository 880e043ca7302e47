"""Exports in each tool's own words (issue 28), read back by the tool's own reader where it installs from PyPI
(OpenCV's FileStorage and stereo functions, pycolmap, PyYAML) and by the format's specification otherwise (mrcal)."""

import ast
import dataclasses

import cv2
import numpy as np
import pytest
import yaml

import lfgraph as lf
from lfgraph.core.camera import project_world
from lfgraph.interop import export_calibration
from lfgraph.rectification.rectify import attach, compute_rectification, stored_rectification

ROW_ALIGNED_PX = 1e-6  # rectified rows of one point in the two views of a pair (both through OpenCV)
DEPTH_REL = 1e-6  # Q's reconstruction against the true point, relative
SAME = 1e-12  # a number written and read back
BASELINE_REL = 0.01  # ROS P[0, 3] against -fx * the pair's true baseline (rectified: its ideal spacing)


def pair(rows: int, cols: int, seed: int = 3, stored: bool = True) -> lf.Calibration:
    """A knocked pair, with its rectification stored (``lfgraph rectify``) or, as ``calibrate`` writes it, without:
    then the export computes the rectification it needs (issue 40: ROS got ``P = [K|0]`` for every view, a zero
    baseline, and OpenCV's pair had no ``Q``)."""
    calib, _ = lf.synth.knocked_rig("small-2x2", seed=seed, rows=rows, cols=cols, pitch_m=0.06)
    return attach(calib, compute_rectification(calib)) if stored else calib


def read_fs(path):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        return {k: fs.getNode(k).mat() for k in ("M1", "D1", "M2", "D2", "R", "T", "R1", "R2", "P1", "P2", "Q")}
    finally:
        fs.release()


@pytest.mark.parametrize("stored", [True, False])
@pytest.mark.parametrize("shape", [(1, 2), (2, 1)])
def test_a_pair_carries_opencvs_stereo_names_and_its_q_reconstructs_points(tmp_path, shape, stored):
    calib = pair(*shape, stored=stored)
    m = read_fs(export_calibration(calib, "opencv-yaml", tmp_path / "stereo.yml"))
    two_T_one = calib.view_T_ref(1) @ np.linalg.inv(calib.view_T_ref(0))
    np.testing.assert_allclose(m["R"], two_T_one[:3, :3], atol=SAME)
    np.testing.assert_allclose(m["T"].ravel(), two_T_one[:3, 3], atol=SAME)
    np.testing.assert_allclose(m["M2"], calib.intrinsics[1].K, atol=SAME)
    # points seen by both views, rectified by OpenCV with the file's matrices, reconstructed by Q
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.8, 3.0, 50)
    pts = np.column_stack([rng.uniform(-0.2, 0.2, (50, 2)) * depth[:, None], depth])
    rect = []
    for i, (k, d, r, p) in enumerate([(m["M1"], m["D1"], m["R1"], m["P1"]), (m["M2"], m["D2"], m["R2"], m["P2"])]):
        px = project_world(calib.intrinsics[i], calib.view_T_ref(i), pts)
        rect.append(cv2.undistortPoints(px.reshape(-1, 1, 2), k, d, R=r, P=p).reshape(-1, 2))
    across = 1 if shape == (1, 2) else 0  # the coordinate that must agree: rows of a horizontal pair
    assert np.max(np.abs(rect[0][:, across] - rect[1][:, across])) < ROW_ALIGNED_PX
    along = 1 - across
    uvd = np.column_stack([rect[0], rect[0][:, along] - rect[1][:, along]])
    xyz_rect1 = cv2.perspectiveTransform(uvd.reshape(-1, 1, 3), m["Q"]).reshape(-1, 3)
    in_cam1 = (calib.view_T_ref(0) @ np.column_stack([pts, np.ones(len(pts))]).T).T[:, :3]
    expected = in_cam1 @ m["R1"].T  # camera 1's rectified frame
    np.testing.assert_allclose(xyz_rect1, expected, rtol=DEPTH_REL, atol=1e-9)


@pytest.mark.parametrize("stored", [True, False])
def test_ros_camera_info_per_view_rectifies_as_lfgraph_does(tmp_path, stored):
    calib = pair(1, 2, stored=stored)
    folder = export_calibration(calib, "ros", tmp_path / "ros")
    assert sorted(p.name for p in folder.iterdir()) == ["r00_c00.yaml", "r00_c01.yaml"]
    rect = stored_rectification(calib) if stored else compute_rectification(calib)
    for v in range(2):
        info = yaml.safe_load((folder / f"{calib.grid.name(v)}.yaml").read_text())
        assert set(info) == {"image_width", "image_height", "camera_name", "camera_matrix", "distortion_model",
                             "distortion_coefficients", "rectification_matrix", "projection_matrix"}
        assert (info["image_width"], info["image_height"]) == calib.image_size_px
        assert info["distortion_model"] == "plumb_bob"

        def mat(key, info=info):
            node = info[key]
            return np.array(node["data"], dtype=float).reshape(node["rows"], node["cols"])

        k, d, r, p = mat("camera_matrix"), mat("distortion_coefficients"), mat("rectification_matrix"), \
            mat("projection_matrix")
        np.testing.assert_allclose(k, calib.intrinsics[v].K, atol=SAME)
        # OpenCV with the file's matrices puts pixels where lfgraph's rectification does
        px = np.random.default_rng(v).uniform([20, 20], [300, 220], (30, 2))
        ours = cv2.undistortPoints(px.reshape(-1, 1, 2), k, d, R=r, P=p).reshape(-1, 2)
        theirs = cv2.undistortPoints(px.reshape(-1, 1, 2), calib.intrinsics[v].K, calib.intrinsics[v].dist_cv,
                                     R=rect.rect_R_view[v], P=rect.K_r).reshape(-1, 2)
        np.testing.assert_allclose(ours, theirs, atol=1e-9)
        if v == 0:  # the reference: zero last column (ROS's left camera); the other: -fx * baseline
            np.testing.assert_allclose(p[:, 3], 0.0, atol=SAME)
        else:  # ROS's -fx' B, B the baseline (the rectified grid's ideal spacing: its fit of the knocked pair)
            baseline = np.linalg.norm(calib.ref_T_view[1][:3, 3] - calib.ref_T_view[0][:3, 3])
            assert p[0, 3] == pytest.approx(-rect.K_r[0, 0] * baseline, rel=BASELINE_REL)
            assert abs(p[1, 3]) < 1e-9 * abs(p[0, 3])


def test_mrcal_cameramodel_per_view_follows_the_format(tmp_path):
    calib = lf.synth.knocked_rig("small-2x2", seed=1)[0]
    folder = export_calibration(calib, "mrcal", tmp_path / "mrcal")
    assert sorted(p.name for p in folder.iterdir()) == [f"{calib.grid.name(v)}.cameramodel" for v in range(4)]
    for v in range(4):
        model = ast.literal_eval((folder / f"{calib.grid.name(v)}.cameramodel").read_text())  # a Python literal
        assert model["lensmodel"] == "LENSMODEL_OPENCV5"
        intr = calib.intrinsics[v]
        assert model["intrinsics"] == [intr.fx, intr.fy, intr.cx, intr.cy, intr.k1, intr.k2, intr.p1, intr.p2, 0.0]
        assert model["imagersize"] == list(calib.image_size_px)
        rt = np.array(model["extrinsics"])  # rt_fromref: reference coordinates -> camera coordinates
        rot = cv2.Rodrigues(rt[:3])[0]
        np.testing.assert_allclose(rot, calib.view_T_ref(v)[:3, :3], atol=1e-12)
        np.testing.assert_allclose(rt[3:], calib.view_T_ref(v)[:3, 3], atol=SAME)
    fisheye = calib.replace(intrinsics=tuple(i.with_distortion("fisheye", k1=0.01) for i in calib.intrinsics))
    with pytest.raises(ValueError, match="mrcal has no Kannala-Brandt"):
        export_calibration(fisheye, "mrcal", tmp_path / "fish")
    assert not (tmp_path / "fish").exists()


def test_colmap_rig_config_is_read_by_pycolmap(tmp_path):
    import pycolmap  # COLMAP's own reader (the test extra installs it from PyPI)

    calib = lf.synth.knocked_rig("small-2x2", seed=1)[0]
    folder = export_calibration(calib, "colmap", tmp_path / "sparse")
    rec = pycolmap.Reconstruction(str(folder))
    assert len(rec.cameras) == 4 and len(rec.rigs) == 1
    (rig,) = pycolmap.read_rig_config(str(folder / "rig_config.json"))
    by_prefix = {c.image_prefix: c for c in rig.cameras}
    assert set(by_prefix) == {f"{calib.grid.name(v)}/" for v in range(4)}
    for v in range(4):
        cam = by_prefix[f"{calib.grid.name(v)}/"]
        assert cam.ref_sensor == (v == calib.grid.reference)
        if v != calib.grid.reference:
            np.testing.assert_allclose(cam.cam_from_rig.matrix(), calib.view_T_ref(v)[:3], atol=1e-12)
        np.testing.assert_allclose(cam.camera.params[:2], [calib.intrinsics[v].fx, calib.intrinsics[v].fy])


# ---------------------------------------------------------------- issue 40's done-means, against cv2.stereoRectify
Q_SAME_REL = 1e-9  # Q's focal length and 1/baseline against stereoRectify's on the same K, D, R, T (measured ~1e-16)
BASELINE_AXIS_RAD = 1e-9  # the turn between lfgraph's and stereoRectify's rectified frames leaves the baseline fixed
P_SAME_REL = 1e-9  # a rectified projection's -f' B against stereoRectify's P2 (measured ~1e-15)


def square_pixel_pair(rows: int, cols: int, seed: int) -> lf.Calibration:
    """A pair knocked 3 deg / 5 mm (the views not parallel) with fx = fy per view, as ``calibrate`` writes it (no
    rectification stored). Square pixels because stereoRectify makes its rectified pixels square (f = the mean fy of
    a horizontal pair, mean fx of a vertical one) where lfgraph's K_r keeps the mean fx and the mean fy."""
    _, calib = lf.synth.knocked_rig("small-2x2", shake_rot_deg=3, shake_trans_mm=5, seed=seed, rows=rows, cols=cols,
                                    pitch_m=0.06)
    return calib.replace(intrinsics=tuple(dataclasses.replace(i, fy=i.fx) for i in calib.intrinsics))


def stereo_rectify(m: dict) -> dict:
    """The file's pair with OpenCV's own rectification in place of the file's (zero disparity at infinity: one
    principal point)."""
    size = (320, 240)  # small-2x2's image size
    r1, r2, p1, p2, q, *_ = cv2.stereoRectify(m["M1"], m["D1"], m["M2"], m["D2"], size, m["R"], m["T"],
                                              flags=cv2.CALIB_ZERO_DISPARITY)
    return {**m, "R1": r1, "R2": r2, "P1": p1, "P2": p2, "Q": q}


def reconstruct(calib: lf.Calibration, m: dict, pts: np.ndarray, along: int) -> np.ndarray:
    """Points seen by both views, rectified by OpenCV with ``m``'s R1 R2 P1 P2, reprojected by its Q and taken back
    to camera 1's (unrectified) frame."""
    rect = []
    for i, (k, d, r, p) in enumerate([(m["M1"], m["D1"], m["R1"], m["P1"]), (m["M2"], m["D2"], m["R2"], m["P2"])]):
        px = project_world(calib.intrinsics[i], calib.view_T_ref(i), pts)
        rect.append(cv2.undistortPoints(px.reshape(-1, 1, 2), k, d, R=r, P=p).reshape(-1, 2))
    uvd = np.column_stack([rect[0], rect[0][:, along] - rect[1][:, along]])
    return cv2.perspectiveTransform(uvd.reshape(-1, 1, 3), m["Q"]).reshape(-1, 3) @ m["R1"]


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("shape", [(1, 2), (2, 1)])
def test_a_calibrated_pairs_q_is_stereo_rectifys(tmp_path, shape, seed):
    """Issue 40: ``lfgraph export CALIB --to opencv-yaml`` of a calibrated pair (no rectify run) has Q in
    cv2.stereoRectify's convention: the same focal length, baseline and sign, -cx' and -cy' of its own P1, and the
    same 3-D points from the same scene."""
    calib = square_pixel_pair(*shape, seed)
    assert calib.rectification is None
    ours = read_fs(export_calibration(calib, "opencv-yaml", tmp_path / "stereo.yml"))
    cv = stereo_rectify(ours)
    along = 0 if shape == (1, 2) else 1  # the disparity's axis
    for m in (ours, cv):  # stereoRectify's Q = [1 0 0 -cx1; 0 1 0 -cy1; 0 0 0 f; 0 0 -1/T (cx1 - cx2)/T]
        np.testing.assert_allclose(m["Q"][:3, :3], np.diag([1.0, 1.0, 0.0]), atol=SAME)
        np.testing.assert_allclose(m["Q"][:2, 3], -m["P1"][:2, 2], atol=SAME)
        np.testing.assert_allclose(m["Q"][3, [0, 1, 3]], 0.0, atol=SAME)
    assert ours["Q"][2, 3] == pytest.approx(cv["Q"][2, 3], rel=Q_SAME_REL)  # f
    assert ours["Q"][3, 2] == pytest.approx(cv["Q"][3, 2], rel=Q_SAME_REL)  # -1 / T: the baseline and its sign
    # the rectified frames may differ by a turn about the baseline (any such turn rectifies), the same for both views
    turn = ours["R1"] @ cv["R1"].T
    np.testing.assert_allclose(ours["R2"] @ cv["R2"].T, turn, atol=BASELINE_AXIS_RAD)
    np.testing.assert_allclose(turn[:, along], np.eye(3)[along], atol=BASELINE_AXIS_RAD)
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.8, 3.0, 50)
    pts = np.column_stack([rng.uniform(-0.2, 0.2, (50, 2)) * depth[:, None], depth])
    np.testing.assert_allclose(reconstruct(calib, ours, pts, along), reconstruct(calib, cv, pts, along),
                               rtol=DEPTH_REL, atol=1e-9)


@pytest.mark.parametrize("shape", [(1, 2), (2, 1)])
def test_ros_p_of_a_calibrated_pair_is_minus_f_times_the_baseline(tmp_path, shape):
    """Issue 40: a ROS export of a pair without a stored rectification has P[0, 3] = -fx' B (P[1, 3] = -fy' B for a
    vertical pair), B the distance between the views' centres: stereoRectify's P2 on the same pair."""
    calib = square_pixel_pair(*shape, seed=1)
    folder = export_calibration(calib, "ros", tmp_path / "ros")
    p = [np.array(yaml.safe_load((folder / f"{calib.grid.name(v)}.yaml").read_text())["projection_matrix"]["data"])
         .reshape(3, 4) for v in range(2)]
    along = 0 if shape == (1, 2) else 1
    baseline_m = np.linalg.norm(calib.ref_T_view[1][:3, 3] - calib.ref_T_view[0][:3, 3])
    np.testing.assert_allclose(p[0][:, 3], 0.0, atol=SAME)  # the reference: ROS's left (upper) camera
    assert p[1][along, 3] == pytest.approx(-p[1][along, along] * baseline_m, rel=P_SAME_REL)
    assert abs(p[1][1 - along, 3]) < 1e-9 * abs(p[1][along, 3]) and abs(p[1][2, 3]) < SAME
    cv = stereo_rectify(read_fs(export_calibration(calib, "opencv-yaml", tmp_path / "stereo.yml")))
    assert p[1][along, 3] == pytest.approx(cv["P2"][along, 3], rel=P_SAME_REL)
