"""Exports in each tool's own words (issue 28), read back by the tool's own reader where it installs from PyPI
(OpenCV's FileStorage and stereo functions, pycolmap, PyYAML) and by the format's specification otherwise (mrcal)."""

import ast

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
