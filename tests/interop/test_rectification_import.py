"""Issue 40: an import keeps a stored rectification where the format carries one (opencv-yaml, json); formats with no
place for one (kalibr, colmap, mrcal) say on export that they leave it out."""

import logging

import cv2
import numpy as np
import pytest

import lfgraph as lf
from lfgraph.core.calibration import CalibrationFileError
from lfgraph.interop import export_calibration, import_calibration
from lfgraph.rectification.rectify import attach, compute_rectification, rectify_points, stored_rectification

GRID_SAME_M = 1e-12  # the ideal grid rebuilt from the P_i's last columns (measured ~4e-17 m)
DEVIATION_SAME_MM = 1e-9  # each view's deviation from it (measured ~4e-14 mm)
SAME_DEG = 1e-12  # rotation deviations, computed again from the same rotations
OPENCV_POINT_PX = 1e-6  # lfgraph's rectified pixel of a point against cv2.undistortPoints with the file's R1/P1
PITCH_REL = 1e-9  # the imported pitch against the pair's baseline |T|


def knocked(rows: int, cols: int, reference: int = 0) -> lf.Calibration:
    _, calib = lf.synth.knocked_rig("small-2x2", shake_rot_deg=1, shake_trans_mm=2, seed=2, rows=rows, cols=cols,
                                    pitch_m=0.06)
    return calib.with_reference(reference) if reference else calib


@pytest.mark.parametrize(("shape", "reference", "crop"), [((2, 3), 0, "valid"), ((2, 3), 4, "full"),
                                                          ((1, 2), 0, "valid"), ((2, 1), 1, "valid")])
def test_opencv_yaml_round_trip_keeps_the_rectification(tmp_path, shape, reference, crop):
    calib = knocked(*shape, reference)
    original = compute_rectification(calib, crop)
    path = export_calibration(attach(calib, original), "opencv-yaml", tmp_path / "c.yml")
    back = import_calibration(path, "opencv-yaml")
    rect = stored_rectification(back)
    assert rect is not None
    assert (rect.crop, rect.crop_rect_px, rect.image_size_px, rect.source_size_px) == \
        (original.crop, original.crop_rect_px, original.image_size_px, original.source_size_px)
    for name in ("K_r", "rect_R_ref", "rect_R_view", "P"):  # written at 17 digits: the same to the bit
        assert np.array_equal(getattr(rect, name), getattr(original, name)), name
    for name in ("pitch_m", "grid_origin_m", "grid_u_m", "grid_v_m"):
        np.testing.assert_allclose(getattr(rect, name), getattr(original, name), rtol=0, atol=GRID_SAME_M)
    np.testing.assert_allclose(rect.deviation_mm, original.deviation_mm, rtol=0, atol=DEVIATION_SAME_MM)
    np.testing.assert_allclose(rect.rotation_deviation_deg, original.rotation_deviation_deg, rtol=0, atol=SAME_DEG)
    # the file's reference holds the rectification: moving it is refused, as for json
    with pytest.raises(CalibrationFileError, match=r"c\.yml: rectification: is tied to reference view"):
        import_calibration(path, "opencv-yaml", lf.ViewGrid(*shape, (reference + 1) % (shape[0] * shape[1])))


def _stereo_rectify_file(path, calib: lf.Calibration) -> dict:
    """A pair's file as someone writes it from cv2.stereoRectify: the calibration plus R1 R2 P1 P2 under the
    per-view names (R_rect_0 = R1, P_0 = P1, ...), K_r = P1's left 3x3."""
    k1, d1, k2, d2 = (x for i in range(2) for x in (calib.intrinsics[i].K, calib.intrinsics[i].dist_cv))
    two_T_one = calib.view_T_ref(1)  # the reference is view 0
    r1, r2, p1, p2, *_ = cv2.stereoRectify(k1, d1, k2, d2, calib.image_size_px, two_T_one[:3, :3],
                                           two_T_one[:3, 3].reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
    w, h = calib.image_size_px
    for key, value in (("grid_rows", 1), ("grid_cols", 2), ("reference", 0), ("image_width", w),
                       ("image_height", h), ("num_views", 2), ("rect_image_width", w), ("rect_image_height", h),
                       ("K_r", p1[:, :3]), ("R_rect_0", r1), ("R_rect_1", r2), ("P_0", p1), ("P_1", p2)):
        fs.write(key, value)
    for i in range(2):
        fs.write(f"K_{i}", calib.intrinsics[i].K)
        fs.write(f"D_{i}", calib.intrinsics[i].dist_cv.reshape(1, -1))
        fs.write(f"R_{i}", calib.view_T_ref(i)[:3, :3])
        fs.write(f"T_{i}", calib.view_T_ref(i)[:3, 3].reshape(3, 1))
    fs.release()
    return {"R1": r1, "R2": r2, "P1": p1, "P2": p2}


def test_a_rectification_opencv_computed_is_kept_as_opencv_rectifies(tmp_path):
    """Not lfgraph's own output read back: a file holding cv2.stereoRectify's matrices imports as a rectification
    that puts each view's pixels where cv2.undistortPoints with R1/P1 (R2/P2) puts them, at stereoRectify's
    baseline."""
    calib = knocked(1, 2)
    cv = _stereo_rectify_file(tmp_path / "stereo.yml", calib)
    back = import_calibration(tmp_path / "stereo.yml", "opencv-yaml")
    rect = stored_rectification(back)
    px = np.random.default_rng(0).uniform([20, 20], [300, 220], (40, 2))
    for v, (r, p) in enumerate([(cv["R1"], cv["P1"]), (cv["R2"], cv["P2"])]):
        intr = calib.intrinsics[v]
        theirs = cv2.undistortPoints(px.reshape(-1, 1, 2), intr.K, intr.dist_cv, R=r, P=p).reshape(-1, 2)
        np.testing.assert_allclose(rectify_points(back, rect, v, px), theirs, rtol=0, atol=OPENCV_POINT_PX)
    assert rect.pitch_m[0] == pytest.approx(np.linalg.norm(calib.view_T_ref(1)[:3, 3]), rel=PITCH_REL)
    assert rect.crop == "valid"  # stereoRectify's principal point is not the image centre


def _entries(path) -> dict:
    """Every top-level entry of a FileStorage file: numbers, text and matrices."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        nodes = {key: fs.getNode(key) for key in fs.root().keys()}
        return {key: n.string() if n.isString() else n.mat() if n.isMap() else int(n.real()) if n.isInt() else n.real()
                for key, n in nodes.items()}
    finally:
        fs.release()


def _write(path, entries: dict) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
    for key, value in entries.items():
        fs.write(key, value)
    fs.release()


def _turned(rotation: np.ndarray, angle_deg: float) -> np.ndarray:
    return cv2.Rodrigues(np.array([0.0, np.radians(angle_deg), 0.0]))[0] @ rotation


def _scaled_left(p: np.ndarray) -> np.ndarray:
    out = p.copy()
    out[0, 0] *= 1.01
    return out


@pytest.mark.parametrize(("edit", "key"), [
    (lambda e: e.pop("P_1"), "P_1: is missing"),
    (lambda e: e.pop("rect_image_height"), "rect_image_height: is missing"),
    (lambda e: e.pop("K_r"), "K_r: is missing"),
    (lambda e: e.update(rect_crop="square"), "rect_crop: must be valid or full"),
    (lambda e: e.update(K_r=e["K_r"] + np.eye(3)[[1, 0, 2]]), "K_r: "),
    (lambda e: e.update(R_rect_0=2 * e["R_rect_0"]), "R_rect_0: is not a rotation"),
    # a rectification of other extrinsics: view 1 turned 0.5 deg against the reference's R_rect
    (lambda e: e.update(R_rect_1=_turned(e["R_rect_1"], 0.5)), "R_rect_1: does not rectify this calibration's view 1"),
    (lambda e: e.update(P_1=_scaled_left(e["P_1"])), r"P_1: must be \[K_r \| p\]"),
])
def test_a_rectification_that_is_incomplete_or_not_this_calibrations_is_refused(tmp_path, edit, key):
    path = export_calibration(lf.rectify(knocked(1, 2)), "opencv-yaml", tmp_path / "c.yml")
    entries = _entries(path)
    edit(entries)
    _write(path, entries)
    with pytest.raises(CalibrationFileError, match=rf"c\.yml: {key}"):
        import_calibration(path, "opencv-yaml")


def test_the_file_read_by_filestorage_and_written_again_keeps_it(tmp_path):
    """The refusals above edit a file re-written by FileStorage: unedited, that file imports whole."""
    calib = lf.rectify(knocked(1, 2))
    path = export_calibration(calib, "opencv-yaml", tmp_path / "c.yml")
    _write(path, _entries(path))
    assert import_calibration(path, "opencv-yaml").rectification["crop"] == calib.rectification["crop"]


@pytest.mark.parametrize("fmt", ["kalibr", "colmap", "mrcal"])
def test_formats_without_a_place_for_it_say_they_leave_it_out(tmp_path, fmt, caplog):
    with caplog.at_level(logging.WARNING, logger="lfgraph"):
        export_calibration(lf.rectify(knocked(1, 2)), fmt, tmp_path / "out")
    assert f"{fmt} has no place for a rectification" in caplog.text
