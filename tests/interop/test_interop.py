"""Calibration import/export (lfgraph.interop, lfgraph.cli.interop): round trips, file layouts, real Middlebury
files, and every validation error."""

import argparse
import dataclasses
import re
import time

import cv2
import numpy as np
import pytest
import yaml

from lfgraph.cli import main as cli_main
from lfgraph.cli.args import UsageError
from lfgraph.cli.interop import add_parsers
from lfgraph.core.calibration import Calibration, CalibrationFileError
from lfgraph.core.geometry import invert_T, make_T
from lfgraph.core.grid import ViewGrid
from lfgraph.datasets.rig import RigConfig, make_rig
from lfgraph.interop import (
    COLMAP_PIXEL_OFFSET_PX,
    EXPORT_FORMATS,
    IMPORT_FORMATS,
    export_calibration,
    import_calibration,
)
from lfgraph.interop.colmap import rotation_from_wxyz
from lfgraph.interop.common import MAX_IMPORT_VIEWS
from lfgraph.rectification.rectify import attach, build_maps, compute_rectification, stored_rectification

ROUND_TRIP_TOLERANCE = 1e-9  # px and m; every format here writes 17 significant digits
CHAIN_TOLERANCE = 1e-12  # m, unitless rotation entries: composing 4x4 transforms costs a few ulps per step
# build_maps stores OpenCV's fixed-point maps (1/32 px steps); maps from the exported K_i, D_i, R_rect_i, P_i must
# land on the same steps, so anything below one step means "the same rectified image"
FIXED_POINT_MAP_STEP_PX = 1.0 / cv2.INTER_TAB_SIZE
REFUSAL_TIME_LIMIT_S = 0.5  # an absurd grid is refused from the header, without reading per-view data
IMPORT_20X20_TIME_LIMIT_S = 1.0  # 400 views; minutes were spent on a 300x300 grid before the one-pass reader
MIDDLEBURY_SCENES = 6  # scenes in tests/data/middlebury2014
# real file suffixes, so the OpenCV writer must force YAML where the name does not say it
FILE_NAMES = {"opencv-yaml": "calib.yml", "kalibr": "camchain.yaml", "colmap": "sparse", "json": "calibration.json"}
ROUND_TRIP_FORMATS = tuple(f for f in EXPORT_FORMATS if f in IMPORT_FORMATS)  # ros and mrcal are export-only


def _rig(reference: int = 0) -> Calibration:
    calib = make_rig(RigConfig(rows=2, cols=3, reference=reference), np.random.default_rng(0))
    # make_rig draws no tangential distortion; give every view some so p1, p2 are checked too
    rng = np.random.default_rng(1)
    intrinsics = [dataclasses.replace(i, p1=p1, p2=p2) for i, (p1, p2) in
                  zip(calib.intrinsics, 1e-3 * rng.standard_normal((calib.num_views, 2)), strict=True)]
    return calib.replace(intrinsics=tuple(intrinsics))


@pytest.fixture
def calib() -> Calibration:
    return _rig()


def _assert_same(a: Calibration, b: Calibration, tol: float = ROUND_TRIP_TOLERANCE) -> None:
    assert a.grid == b.grid
    assert a.image_size_px == b.image_size_px
    for ia, ib in zip(a.intrinsics, b.intrinsics, strict=True):
        assert np.max(np.abs(ia.as_vector() - ib.as_vector())) < tol
    assert np.max(np.abs(a.ref_T_view - b.ref_T_view)) < tol


def _no_temporaries(folder) -> None:
    assert not [p.name for p in folder.iterdir() if p.name.startswith(".")], "temporary file or folder left behind"


# ============================================================================================== round trips
@pytest.mark.parametrize("reference", [0, 4])
@pytest.mark.parametrize("fmt", ROUND_TRIP_FORMATS)
def test_round_trip(tmp_path, fmt, reference):
    calib = _rig(reference)
    path = export_calibration(calib, fmt, tmp_path / FILE_NAMES[fmt])
    assert path == tmp_path / FILE_NAMES[fmt]
    grid = ViewGrid(2, 3, reference) if fmt == "kalibr" else None  # Kalibr stores no grid
    _assert_same(import_calibration(path, fmt, grid), calib)
    _no_temporaries(tmp_path)


@pytest.mark.parametrize("fmt", ROUND_TRIP_FORMATS)
def test_round_trip_with_matching_grid(tmp_path, calib, fmt):
    path = export_calibration(calib, fmt, tmp_path / FILE_NAMES[fmt])
    _assert_same(import_calibration(path, fmt, (2, 3)), calib)
    _assert_same(import_calibration(path, fmt, ViewGrid(2, 3, 0)), calib)


@pytest.mark.parametrize("fmt", ROUND_TRIP_FORMATS)
def test_import_moves_to_the_grids_reference(tmp_path, calib, fmt):
    path = export_calibration(calib, fmt, tmp_path / FILE_NAMES[fmt])
    back = import_calibration(path, fmt, ViewGrid(2, 3, 4))
    assert back.grid == ViewGrid(2, 3, 4)
    expected = np.einsum("ij,vjk->vik", invert_T(calib.ref_T_view[4]), calib.ref_T_view)
    assert np.max(np.abs(back.ref_T_view - expected)) < ROUND_TRIP_TOLERANCE
    assert np.array_equal(back.ref_T_view[4], np.eye(4))


def test_json_keeps_rectification_and_metrics(tmp_path, calib):
    rectified = attach(calib, compute_rectification(calib)).replace(metrics={"rig_rms_px": 0.25})
    path = export_calibration(rectified, "json", tmp_path / "c.json")
    back = import_calibration(path, "json")
    assert back.rectification == rectified.rectification
    assert back.metrics["rig_rms_px"] == 0.25
    with pytest.raises(CalibrationFileError, match=r"c\.json: rectification: .*reference view 0"):
        import_calibration(path, "json", ViewGrid(2, 3, 1))


# ============================================================================================== file layouts
def test_opencv_yaml_is_read_by_filestorage(tmp_path, calib):
    rectified = attach(calib, compute_rectification(calib))
    path = export_calibration(rectified, "opencv-yaml", tmp_path / "calib.yml")
    assert path.read_text().startswith("%YAML")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        assert fs.isOpened()
        assert [int(fs.getNode(k).real()) for k in ("grid_rows", "grid_cols", "reference", "num_views")] == [2, 3, 0, 6]
        assert (fs.getNode("image_width").real(), fs.getNode("image_height").real()) == calib.image_size_px
        for i in range(calib.num_views):
            intr, view_T_ref = calib.intrinsics[i], calib.view_T_ref(i)  # noqa: N806
            assert np.array_equal(fs.getNode(f"K_{i}").mat(), intr.K)
            assert fs.getNode(f"D_{i}").mat().shape == (1, 5)
            assert np.array_equal(fs.getNode(f"D_{i}").mat().ravel(), intr.dist_cv)
            assert np.array_equal(fs.getNode(f"R_{i}").mat(), view_T_ref[:3, :3])
            assert fs.getNode(f"T_{i}").mat().shape == (3, 1)
            assert np.array_equal(fs.getNode(f"T_{i}").mat().ravel(), view_T_ref[:3, 3])
            rect_view = rectified.rectification["views"][i]
            assert np.array_equal(fs.getNode(f"R_rect_{i}").mat(), np.array(rect_view["R_rect_from_view"]))
            assert fs.getNode(f"P_{i}").mat().shape == (3, 4)  # its convention: test_opencv_yaml_rectification_*
        assert np.array_equal(fs.getNode("K_r").mat(), np.array(rectified.rectification["K_r"]))
    finally:
        fs.release()
    # the importer reads the calibration and keeps its rectification (tests/interop/test_rectification_import.py)
    back = import_calibration(path, "opencv-yaml")
    _assert_same(back, calib)
    assert back.rectification is not None


def test_opencv_yaml_without_rectification_has_no_rect_keys(tmp_path, calib):
    text = export_calibration(calib, "opencv-yaml", tmp_path / "c.yaml").read_text()
    assert "K_r" not in text and "P_0" not in text and "R_rect_0" not in text


def test_kalibr_layout(tmp_path, calib):
    path = export_calibration(calib, "kalibr", tmp_path / "camchain.yaml")
    data = yaml.safe_load(path.read_text())  # PyYAML, which Kalibr reads its camchain with
    assert list(data) == [f"cam{i}" for i in range(calib.num_views)]
    for i, intr in enumerate(calib.intrinsics):
        cam = data[f"cam{i}"]
        assert cam["camera_model"] == "pinhole" and cam["distortion_model"] == "radtan"
        assert cam["intrinsics"] == [intr.fx, intr.fy, intr.cx, intr.cy]
        assert cam["distortion_coeffs"] == [intr.k1, intr.k2, intr.p1, intr.p2]
        assert cam["resolution"] == list(calib.image_size_px)
        if i == 0:
            assert "T_cn_cnm1" not in cam
        else:
            expected = calib.view_T_ref(i) @ invert_T(calib.view_T_ref(i - 1))
            assert np.max(np.abs(np.array(cam["T_cn_cnm1"]) - expected)) < CHAIN_TOLERANCE
    # PyYAML (YAML 1.1, what Kalibr reads with) takes "1e-05" for a string: every float must hold a "."
    numbers = re.findall(r"-?\d[\d.]*e[-+]?\d+", path.read_text())
    assert all("." in n.split("e")[0] for n in numbers)


def test_colmap_layout(tmp_path, calib):
    calib = _rig(reference=4)
    folder = export_calibration(calib, "colmap", tmp_path / "sparse")
    assert sorted(p.name for p in folder.iterdir()) == ["cameras.txt", "frames.txt", "images.txt", "points3D.txt",
                                                         "rig_config.json", "rigs.txt"]
    cameras = [line.split() for line in (folder / "cameras.txt").read_text().splitlines() if not line.startswith("#")]
    assert len(cameras) == calib.num_views
    for v, tok in enumerate(cameras):
        intr = calib.intrinsics[v]
        assert tok[:4] == [str(v + 1), "OPENCV", *map(str, calib.image_size_px)]
        params = np.array(tok[4:], dtype=float)
        assert np.array_equal(params[[0, 1, 4, 5, 6, 7]], [intr.fx, intr.fy, intr.k1, intr.k2, intr.p1, intr.p2])
        # COLMAP's pixel centres sit at +0.5
        assert np.allclose(params[2:4], [intr.cx + COLMAP_PIXEL_OFFSET_PX, intr.cy + COLMAP_PIXEL_OFFSET_PX],
                           rtol=0, atol=ROUND_TRIP_TOLERANCE)
    rigs = [line.split() for line in (folder / "rigs.txt").read_text().splitlines() if not line.startswith("#")]
    assert len(rigs) == 1
    tok = rigs[0]
    assert tok[:4] == ["1", "6", "CAMERA", "5"]  # reference view 4 is camera 5
    sensors = tok[4:]
    assert len(sensors) == 10 * (calib.num_views - 1)
    for k in range(0, len(sensors), 10):
        assert sensors[k] == "CAMERA" and sensors[k + 2] == "1"
        view = int(sensors[k + 1]) - 1
        q, t = np.array(sensors[k + 3: k + 7], dtype=float), np.array(sensors[k + 7: k + 10], dtype=float)
        sensor_from_rig = make_T(rotation_from_wxyz(q), t)
        assert np.max(np.abs(sensor_from_rig - calib.view_T_ref(view))) < ROUND_TRIP_TOLERANCE
    assert "# lfgraph grid: 2x3" in (folder / "rigs.txt").read_text()


def test_colmap_overwrites_a_model_folder_but_not_other_folders(tmp_path, calib):
    folder = export_calibration(calib, "colmap", tmp_path / "sparse")
    (folder / "cameras.bin").write_bytes(b"stale")  # a stale binary model COLMAP would prefer
    other = _rig(reference=2)
    export_calibration(other, "colmap", folder)
    assert not (folder / "cameras.bin").exists()
    _assert_same(import_calibration(folder, "colmap"), other)
    _no_temporaries(tmp_path)
    (folder / "notes.md").write_text("mine")
    with pytest.raises(ValueError, match=r"notes\.md.*refusing"):
        export_calibration(calib, "colmap", folder)
    assert (folder / "notes.md").read_text() == "mine"
    _assert_same(import_calibration(folder, "colmap"), other)
    with pytest.raises(ValueError, match="is a folder"):
        export_calibration(calib, "colmap", folder / "notes.md")


def test_colmap_without_grid_comment_needs_a_grid(tmp_path, calib):
    folder = export_calibration(calib, "colmap", tmp_path / "sparse")
    rigs = folder / "rigs.txt"
    rigs.write_text("".join(line for line in rigs.read_text().splitlines(True) if "lfgraph grid" not in line))
    with pytest.raises(CalibrationFileError, match="grid"):
        import_calibration(folder, "colmap")
    _assert_same(import_calibration(folder, "colmap", (2, 3)), calib)
    with pytest.raises(CalibrationFileError, match=r"sparse: cameras\.txt: holds 6 views, but the 2x2 grid needs 4"):
        import_calibration(folder, "colmap", (2, 2))


# ============================================================================================== Middlebury
def _middlebury_numbers(path) -> dict[str, list[float]]:
    """Every KEY=numbers entry of a calib.txt, parsed independently of lfgraph.interop."""
    out = {}
    for line in path.read_text().splitlines():
        key, _, value = line.partition("=")
        out[key.strip()] = [float(x) for x in re.findall(r"[-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?", value)]
    return out


def test_middlebury_real_files(test_data):
    files = sorted((test_data / "middlebury2014").glob("*/calib.txt"))
    assert len(files) == MIDDLEBURY_SCENES
    for path in files:
        numbers = _middlebury_numbers(path)
        calib = import_calibration(path, "middlebury")
        assert calib.grid == ViewGrid(1, 2, 0)
        assert calib.image_size_px == (int(numbers["width"][0]), int(numbers["height"][0]))
        for view, key in enumerate(("cam0", "cam1")):
            K = np.array(numbers[key]).reshape(3, 3)  # noqa: N806
            assert np.array_equal(calib.intrinsics[view].K, K), path
            assert calib.intrinsics[view].dist_cv.tolist() == [0.0] * 5
        baseline_m = numbers["baseline"][0] / 1000.0
        # cam1 is baseline to the right of cam0: x_view1 = x_ref - [b, 0, 0]
        assert np.allclose(calib.view_T_ref(1), make_T(np.eye(3), [-baseline_m, 0.0, 0.0]), rtol=0, atol=1e-15)
        # doffs = cx1 - cx0 in every real file
        assert calib.intrinsics[1].cx - calib.intrinsics[0].cx == pytest.approx(numbers["doffs"][0], abs=1e-9)
    # the scene folder is accepted too, and a grid can move the reference
    calib = import_calibration(files[0].parent, "middlebury", ViewGrid(1, 2, 1))
    assert calib.grid.reference == 1 and calib.ref_T_view[0][0, 3] < 0


MIDDLEBURY_TEXT = """cam0=[1000 0 300; 0 1000 200; 0 0 1]
cam1=[1000 0 340; 0 1000 200; 0 0 1]
doffs=40
baseline=150.5
width=640
height=480
"""


@pytest.mark.parametrize(("edit", "key"), [
    (lambda t: t.replace("baseline=150.5\n", ""), "baseline"),
    (lambda t: t.replace("cam1=", "camX="), "cam1"),
    (lambda t: t.replace("baseline=150.5", "baseline=nan"), "baseline"),
    (lambda t: t.replace("width=640", "width=inf"), "width"),
    (lambda t: t.replace("0 1000 200; 0 0 1]\ncam1", "0 1000 200]\ncam1"), "cam0"),
    (lambda t: t.replace("cam0=[1000 0 300", "cam0=[1000 5 300"), "cam0"),
    (lambda t: t.replace("baseline=150.5", "baseline=-3"), "baseline"),
])
def test_middlebury_errors_name_file_and_key(tmp_path, edit, key):
    path = tmp_path / "calib.txt"
    path.write_text(edit(MIDDLEBURY_TEXT))
    with pytest.raises(CalibrationFileError, match=rf"calib\.txt: {key}: "):
        import_calibration(path, "middlebury")


def test_middlebury_grid_must_match(tmp_path):
    (tmp_path / "calib.txt").write_text(MIDDLEBURY_TEXT)
    with pytest.raises(CalibrationFileError, match=r"calib\.txt: cam0, cam1: holds 2 views, but the 2x2 grid"):
        import_calibration(tmp_path, "middlebury", (2, 2))
    with pytest.raises(CalibrationFileError, match=r"calib\.txt: grid: the file's grid is 1x2, but 2x1"):
        import_calibration(tmp_path, "middlebury", (2, 1))


# ============================================================================================== HCI
HCI_TEXT = """[intrinsics]
focal_length_mm = 50
image_resolution_x_px = 640
image_resolution_y_px = 480
sensor_size_mm = 32
fstop = 100

[extrinsics]
num_cams_x = 3
num_cams_y = 2
baseline_mm = 20
focus_distance_m = 3.5
center_cam_x_m = 0.1
center_cam_y_m = -2.0
center_cam_z_m = 0.3
center_cam_rx_rad = 1.5
center_cam_ry_rad = 0.0
center_cam_rz_rad = 0.2

[meta]
disp_min = -1.5
disp_max = 1.5
"""


def test_hci(tmp_path):
    (tmp_path / "parameters.cfg").write_text(HCI_TEXT)
    calib = import_calibration(tmp_path, "hci")
    assert calib.grid == ViewGrid(2, 3, 0)  # num_cams_y rows, num_cams_x columns, top-left reference
    assert calib.image_size_px == (640, 480)
    focal_px = 50 / 32 * 640
    for intr in calib.intrinsics:
        assert intr.as_vector().tolist() == [focal_px, focal_px, 319.5, 239.5, 0.0, 0.0, 0.0, 0.0]
    for v in range(6):
        r, c = divmod(v, 3)
        assert np.allclose(calib.ref_T_view[v], make_T(np.eye(3), [0.02 * c, 0.02 * r, 0.0]), rtol=0, atol=1e-15)
    centre = import_calibration(tmp_path / "parameters.cfg", "hci", ViewGrid(2, 3, 4))
    assert centre.grid.reference == 4
    assert np.allclose(centre.ref_T_view[0][:3, 3], [-0.02, -0.02, 0.0], rtol=0, atol=1e-15)
    with pytest.raises(CalibrationFileError, match=r"parameters\.cfg: \[extrinsics\] num_cams_x, num_cams_y: "
                                                   r"holds 6 views, but the 3x3 grid needs 9"):
        import_calibration(tmp_path, "hci", (3, 3))
    with pytest.raises(CalibrationFileError, match=r"the file's grid is 2x3, but 3x2"):
        import_calibration(tmp_path, "hci", (3, 2))


@pytest.mark.parametrize(("edit", "key"), [
    (lambda t: t.replace("baseline_mm = 20\n", ""), r"\[extrinsics\] baseline_mm"),
    (lambda t: t.replace("focal_length_mm = 50", "focal_length_mm = nan"), r"\[intrinsics\] focal_length_mm"),
    (lambda t: t.replace("num_cams_x = 3", "num_cams_x = 2.5"), r"\[extrinsics\] num_cams_x"),
    (lambda t: t.replace("[intrinsics]", "[camera]"), r"\[intrinsics\]"),
    (lambda t: t.replace("sensor_size_mm = 32", "sensor_size_mm = 0"), r"\[intrinsics\] sensor_size_mm"),
    (lambda t: t.replace("[meta]", "no section header"), "file"),
])
def test_hci_errors_name_file_and_key(tmp_path, edit, key):
    path = tmp_path / "parameters.cfg"
    path.write_text(edit(HCI_TEXT))
    with pytest.raises(CalibrationFileError, match=rf"parameters\.cfg: {key}"):
        import_calibration(path, "hci")


# ============================================================================================== errors
def test_unknown_format_lists_the_valid_ones(tmp_path, calib):
    with pytest.raises(ValueError, match="opencv-yaml, kalibr, colmap, json, ros, mrcal$"):
        export_calibration(calib, "middlebury", tmp_path / "x")
    with pytest.raises(ValueError, match="unknown export format 'yaml'"):
        export_calibration(calib, "yaml", tmp_path / "x")
    with pytest.raises(ValueError, match="opencv-yaml, kalibr, colmap, json, middlebury, hci$"):
        import_calibration(tmp_path / "x", "bundler")
    assert not list(tmp_path.iterdir())
    assert ROUND_TRIP_FORMATS == ("opencv-yaml", "kalibr", "colmap", "json")


@pytest.mark.parametrize("fmt", ROUND_TRIP_FORMATS)
def test_missing_input(tmp_path, fmt):
    grid = (2, 3) if fmt == "kalibr" else None
    with pytest.raises(CalibrationFileError, match=r"nothing.*(does not exist|is missing)"):
        import_calibration(tmp_path / "nothing", fmt, grid)


@pytest.mark.parametrize("fmt", ROUND_TRIP_FORMATS)
def test_grid_with_a_different_view_count(tmp_path, calib, fmt):
    path = export_calibration(calib, fmt, tmp_path / FILE_NAMES[fmt])
    with pytest.raises(CalibrationFileError, match=rf"{FILE_NAMES[fmt]}: .*6.* 3x3 grid needs 9"):
        import_calibration(path, fmt, (3, 3))


@pytest.mark.parametrize("fmt", ["opencv-yaml", "json", "colmap"])
def test_grid_with_a_different_shape(tmp_path, calib, fmt):
    path = export_calibration(calib, fmt, tmp_path / FILE_NAMES[fmt])
    with pytest.raises(CalibrationFileError, match=r"grid: the file's grid is 2x3, but 3x2 was asked for"):
        import_calibration(path, fmt, (3, 2))


def test_kalibr_needs_a_grid(tmp_path, calib):
    path = export_calibration(calib, "kalibr", tmp_path / "camchain.yaml")
    with pytest.raises(CalibrationFileError, match=r"camchain\.yaml: grid: .*--grid"):
        import_calibration(path, "kalibr")


def _write_filestorage(path, entries: dict) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
    for key, value in entries.items():
        fs.write(key, value)
    fs.release()


def _opencv_entries(calib: Calibration) -> dict:
    entries = {"grid_rows": 2, "grid_cols": 3, "reference": 0, "image_width": calib.image_size_px[0],
               "image_height": calib.image_size_px[1], "num_views": 6}
    for i in range(calib.num_views):
        entries |= {f"K_{i}": calib.intrinsics[i].K, f"D_{i}": calib.intrinsics[i].dist_cv.reshape(1, 5),
                    f"R_{i}": calib.view_T_ref(i)[:3, :3], f"T_{i}": calib.view_T_ref(i)[:3, 3].reshape(3, 1)}
    return entries


def test_opencv_yaml_written_by_hand_reads_back(tmp_path, calib):
    _write_filestorage(tmp_path / "c.yaml", _opencv_entries(calib))
    _assert_same(import_calibration(tmp_path / "c.yaml", "opencv-yaml"), calib)


def _nan_in(matrix: np.ndarray) -> np.ndarray:
    out = matrix.copy()
    out.flat[0] = np.nan
    return out


@pytest.mark.parametrize(("edit", "key"), [
    (lambda e: e.pop("T_3"), "T_3: is missing"),
    (lambda e: e.pop("image_height"), "image_height: is missing"),
    (lambda e: e.update(num_views=5), "num_views: is 5, but"),
    (lambda e: e.update(K_1=_nan_in(e["K_1"])), "K_1: must be finite"),
    (lambda e: e.update(T_2=np.zeros((2, 1))), "T_2: must have shape 3x1"),
    (lambda e: e.update(R_2=2 * e["R_2"]), "R_2: is not a rotation"),
    (lambda e: e.update(R_0=e["R_1"]), "R_0, T_0: belongs to the reference view"),
    (lambda e: e.update(D_1=np.array([[0.1, 0.0, 0.0, 0.0, 0.3]])), "K_1, D_1: .*k3"),
    (lambda e: e.update(reference=6), "reference: reference view 6 is outside"),
    (lambda e: e.update(K_4="not a matrix"), "K_4: must be an !!opencv-matrix"),
])
def test_opencv_yaml_errors_name_file_and_key(tmp_path, calib, edit, key):
    entries = _opencv_entries(calib)
    edit(entries)
    _write_filestorage(tmp_path / "c.yaml", entries)
    with pytest.raises(CalibrationFileError, match=rf"c\.yaml: {key}"):
        import_calibration(tmp_path / "c.yaml", "opencv-yaml")


def test_opencv_yaml_unparsable(tmp_path, calib):
    (tmp_path / "c.yaml").write_text("%YAML:1.0\n---\nK_0: [1, 2\n")
    with pytest.raises(CalibrationFileError, match=r"c\.yaml: line 4: not valid YAML"):
        import_calibration(tmp_path / "c.yaml", "opencv-yaml")
    (tmp_path / "c.yaml").write_text("%YAML:1.0\n---\ngrid_rows: 1\ngrid_rows: 2\n")
    with pytest.raises(CalibrationFileError, match=r"c\.yaml: line 4: .*'grid_rows' appears twice"):
        import_calibration(tmp_path / "c.yaml", "opencv-yaml")
    text = export_calibration(calib, "opencv-yaml", tmp_path / "c.yaml").read_text()
    (tmp_path / "c.yaml").write_text(re.sub(r"(K_0: !!opencv-matrix\n(?:.*\n){3}\s*data: )\[[^]]*\]", r"\1[ 1., 2. ]",
                                            text))
    with pytest.raises(CalibrationFileError, match=r"c\.yaml: K_0: !!opencv-matrix of 3x3 holds 2 numbers"):
        import_calibration(tmp_path / "c.yaml", "opencv-yaml")


@pytest.mark.parametrize(("edit", "key"), [
    (lambda t: t.replace("cam2:", "camera2:"), r"cam2: is missing"),
    (lambda t: re.sub(r"(cam1:\n(?:  .*\n|  - .*\n)*?)  intrinsics: .*\n", r"\1", t), r"cam1\.intrinsics: is missing"),
    (lambda t: t.replace("intrinsics: [", "intrinsics: [.nan, ", 1), r"cam0\.intrinsics: "),
    (lambda t: re.sub(r"(cam3:\n  T_cn_cnm1:\n  - \[)[^,]*", r"\g<1>.inf", t), r"cam3\.T_cn_cnm1: must be finite"),
    (lambda t: re.sub(r"(cam3:\n  T_cn_cnm1:\n  - \[)[^,]*", r"\g<1>2.0", t), r"cam3\.T_cn_cnm1: is not a rotation"),
    (lambda t: t.replace("distortion_model: radtan", "distortion_model: fov", 1), r"cam0\.distortion_model"),
    (lambda t: t.replace("camera_model: pinhole", "camera_model: eucm", 1), r"cam0\.camera_model"),
    (lambda t: t.replace("camera_model: pinhole", "camera_model: omni", 1), r"cam0\.intrinsics"),
    (lambda t: t.replace("intrinsics: [", "intrinsics: [[", 1), r"line \d+: not valid YAML"),
    (lambda t: t.replace("intrinsics: [", "intrinsics: [1.0, ", 1), r"cam0\.intrinsics: must have shape 4"),
    (lambda t: re.sub(r"(cam2:\n  T_cn_cnm1:\n)  - \[.*\]\n", r"\1", t), r"cam2\.T_cn_cnm1: must have shape 4x4"),
    (lambda t: t.replace("  rostopic:", "  camera_model: pinhole\n  rostopic:", 1),
     r"line \d+: .*'camera_model' appears twice"),
    (lambda t: t.replace("resolution: [960, 960]", "resolution: [960, .inf]", 1), r"cam0\.resolution: must be finite"),
    (lambda t: "cam0: [1, 2\n", r"line \d+: not valid YAML"),
    (lambda t: "- cam0\n", r"file: must be a YAML mapping"),
])
def test_kalibr_errors_name_file_and_key(tmp_path, calib, edit, key):
    path = export_calibration(calib, "kalibr", tmp_path / "camchain.yaml")
    path.write_text(edit(path.read_text()))
    with pytest.raises(CalibrationFileError, match=rf"camchain\.yaml: ({key})"):
        import_calibration(path, "kalibr", (2, 3))


def test_kalibr_reads_zero_distortion_and_comments(tmp_path, calib):
    path = export_calibration(calib, "kalibr", tmp_path / "camchain.yaml")
    text = path.read_text().replace("distortion_model: radtan", "distortion_model: none  # no lens model")
    path.write_text("---\n" + text)
    back = import_calibration(path, "kalibr", (2, 3))
    assert all(i.dist_cv.tolist() == [0.0] * 5 for i in back.intrinsics)
    assert np.max(np.abs(back.ref_T_view - calib.ref_T_view)) < ROUND_TRIP_TOLERANCE


# Kalibr's kalibr_calibrate_cameras output as written by PyYAML >= 5.1 (yaml.dump's default is block style there):
# every list a block of "- " lines, T_cn_cnm1 a block list of block lists. cam1 sits 0.11 m to the right of cam0,
# turned 2 degrees about y.
_KALIBR_BLOCK_CAMCHAIN = """\
cam0:
  cam_overlaps:
  - 1
  camera_model: pinhole
  distortion_coeffs:
  - -0.2834
  - 0.0739
  - 0.00019
  - 1.76e-05
  distortion_model: radtan
  intrinsics:
  - 458.654
  - 457.296
  - 367.215
  - 248.375
  resolution:
  - 752
  - 480
  rostopic: /cam0/image_raw
  timeshift_cam_imu: 0.0
cam1:
  T_cn_cnm1:
  - - {c}
    - 0.0
    - {s}
    - -0.11
  - - 0.0
    - 1.0
    - 0.0
    - 0.0
  - - {ms}
    - 0.0
    - {c}
    - 0.0
  - - 0.0
    - 0.0
    - 0.0
    - 1.0
  cam_overlaps:
  - 0
  camera_model: pinhole
  distortion_coeffs: [-0.28368, 0.07451, -0.000104, -3.555e-05]
  distortion_model: radtan
  intrinsics: [457.587, 456.134, 379.999, 255.238]
  resolution: [752, 480]
  rostopic: /cam1/image_raw
  timeshift_cam_imu: -1.5e-05
"""


def test_kalibr_reads_block_style_as_kalibr_writes_it(tmp_path):
    angle = np.deg2rad(2.0)
    c, s = float(np.cos(angle)), float(np.sin(angle))
    path = tmp_path / "camchain.yaml"
    path.write_text(_KALIBR_BLOCK_CAMCHAIN.format(c=repr(c), s=repr(s), ms=repr(-s)))
    back = import_calibration(path, "kalibr", (1, 2))
    assert back.image_size_px == (752, 480)
    assert back.intrinsics[0].as_vector().tolist() == [458.654, 457.296, 367.215, 248.375,
                                                       -0.2834, 0.0739, 0.00019, 1.76e-05]
    assert back.intrinsics[1].as_vector().tolist() == [457.587, 456.134, 379.999, 255.238,
                                                       -0.28368, 0.07451, -0.000104, -3.555e-05]
    cam1_T_cam0 = np.array([[c, 0.0, s, -0.11], [0.0, 1.0, 0.0, 0.0], [-s, 0.0, c, 0.0], [0.0, 0.0, 0.0, 1.0]])  # noqa: N806
    assert np.max(np.abs(back.ref_T_view[1] - np.linalg.inv(cam1_T_cam0))) < CHAIN_TOLERANCE
    assert np.array_equal(back.ref_T_view[0], np.eye(4))


@pytest.mark.parametrize("reference", [0, 4])
def test_kalibr_block_style_round_trip(tmp_path, reference):
    calib = _rig(reference)
    path = export_calibration(calib, "kalibr", tmp_path / "camchain.yaml")
    # re-written by PyYAML in block style, as Kalibr's yaml.dump writes it with PyYAML >= 5.1
    path.write_text(yaml.safe_dump(yaml.safe_load(path.read_text()), default_flow_style=False))
    assert "\n  - - " in path.read_text()
    _assert_same(import_calibration(path, "kalibr", ViewGrid(2, 3, reference)), calib)


def _edit_camera_1(folder, edit) -> None:
    path = folder / "cameras.txt"
    lines = path.read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith("1 "))
    lines[i] = " ".join(edit(lines[i].split()))
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize(("edit", "file", "key"), [
    (lambda f: (f / "rigs.txt").unlink(), "sparse", r"rigs\.txt: is missing"),
    (lambda f: (f / "cameras.txt").write_text((f / "cameras.txt").read_text().replace("OPENCV", "FISHEYE", 1)),
     r"cameras\.txt", "camera 1 MODEL: 'FISHEYE' is not supported"),
    (lambda f: _edit_camera_1(f, lambda tok: [*tok[:-1], "nan"]), r"cameras\.txt", "camera 1 p2: must be finite"),
    (lambda f: _edit_camera_1(f, lambda tok: tok[:-1]), r"cameras\.txt", "camera 1 PARAMS: OPENCV needs 8"),
    (lambda f: (f / "rigs.txt").write_text((f / "rigs.txt").read_text().replace("CAMERA 3 1 ", "CAMERA 3 1 2")),
     r"rigs\.txt", "sensor 3 QW QX QY QZ: must be a unit quaternion"),
    (lambda f: (f / "rigs.txt").write_text((f / "rigs.txt").read_text() + "2 1 CAMERA 7\n"),
     r"rigs\.txt", "rigs: must hold exactly one rig"),
])
def test_colmap_errors_name_file_and_key(tmp_path, calib, edit, file, key):
    folder = export_calibration(calib, "colmap", tmp_path / "sparse")
    edit(folder)
    with pytest.raises(CalibrationFileError, match=rf"{file}: {key}"):
        import_calibration(folder, "colmap")


def test_colmap_reads_simpler_camera_models(tmp_path):
    calib = make_rig(RigConfig(rows=1, cols=2), np.random.default_rng(2))
    folder = export_calibration(calib, "colmap", tmp_path / "sparse")
    lines = (folder / "cameras.txt").read_text().splitlines()
    lines[-2] = "1 SIMPLE_RADIAL 960 960 800.0 480.0 470.0 -0.1"
    lines[-1] = "2 PINHOLE 960 960 801.0 802.0 481.0 471.0"
    (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
    back = import_calibration(folder, "colmap")
    assert back.intrinsics[0].as_vector().tolist() == [800.0, 800.0, 479.5, 469.5, -0.1, 0.0, 0.0, 0.0]
    assert back.intrinsics[1].as_vector().tolist() == [801.0, 802.0, 480.5, 470.5, 0.0, 0.0, 0.0, 0.0]


# ============================================================================================== CLI
def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="command", required=True)
    add_parsers(sub)
    return p


@pytest.mark.parametrize("fmt", ROUND_TRIP_FORMATS)
def test_cli_export_then_import(tmp_path, calib, fmt, capsys):
    calib.save(tmp_path / "in.json")
    out = tmp_path / FILE_NAMES[fmt]
    args = _parser().parse_args(["export", str(tmp_path / "in.json"), "--to", fmt, "-o", str(out)])
    assert args.func(args) == 0
    assert str(out) in capsys.readouterr().out
    back_path = tmp_path / "back.json"
    args = _parser().parse_args(["import", str(out), "--from", fmt, "--grid", "2x3", "-o", str(back_path)])
    assert args.func(args) == 0
    _assert_same(Calibration.load(back_path), calib)
    args = _parser().parse_args(["import", str(out), "--from", fmt, "--grid", "2x3", "--reference", "5",
                                 "-o", str(back_path)])
    assert args.func(args) == 0
    assert Calibration.load(back_path).grid == ViewGrid(2, 3, 5)


def test_cli_import_middlebury(test_data, tmp_path):
    scene = test_data / "middlebury2014" / "Teddy"
    args = _parser().parse_args(["import", str(scene / "calib.txt"), "--from", "middlebury", "-o",
                                 str(tmp_path / "teddy.json")])
    assert args.func(args) == 0
    teddy = Calibration.load(tmp_path / "teddy.json")
    assert teddy.intrinsics[0].fx == 1500.0 and teddy.image_size_px == (450, 375)
    assert teddy.ref_T_view[1][0, 3] == pytest.approx(0.080, abs=1e-15)


def test_cli_errors(tmp_path, calib):
    calib.save(tmp_path / "in.json")
    export_calibration(calib, "kalibr", tmp_path / "camchain.yaml")
    parser = _parser()
    args = parser.parse_args(["import", str(tmp_path / "camchain.yaml"), "--from", "kalibr", "-o",
                              str(tmp_path / "o.json")])
    with pytest.raises(ValueError, match="grid"):
        args.func(args)
    args = parser.parse_args(["import", str(tmp_path / "in.json"), "--from", "json", "--reference", "1", "-o",
                              str(tmp_path / "o.json")])
    with pytest.raises(ValueError, match="--reference needs --grid"):
        args.func(args)
    args = parser.parse_args(["import", str(tmp_path / "in.json"), "--from", "json", "--grid", "2x3",
                              "--reference", "6", "-o", str(tmp_path / "o.json")])
    with pytest.raises(ValueError, match="reference view 6 is outside"):
        args.func(args)
    args = parser.parse_args(["export", str(tmp_path / "missing.json"), "--to", "json", "-o", str(tmp_path / "o")])
    with pytest.raises(ValueError, match=r"missing\.json: file: does not exist"):
        args.func(args)
    assert not (tmp_path / "o.json").exists() and not (tmp_path / "o").exists()
    for argv, message in ((["export", "in.json", "--to", "middlebury", "-o", "x"], "--to: unknown export format "
                           "'middlebury'; valid formats: opencv-yaml, kalibr"),
                          (["import", "x", "--from", "bogus", "-o", "y"], "--from: unknown import format 'bogus'")):
        args = parser.parse_args(argv)  # the format registry is asked when the command runs (plugins register)
        with pytest.raises(UsageError, match=message):
            args.func(args)
    for argv in (["import", "x", "--from", "json", "--grid", "2by3", "-o", "y"],
                 ["import", "x", "--from", "json", "--grid", "2x3", "--reference", "-1", "-o", "y"],
                 ["export", "in.json", "--to", "json"]):
        with pytest.raises(SystemExit):
            parser.parse_args(argv)


def test_opencv_yaml_export_refuses_an_incomplete_rectification(tmp_path, calib):
    rect = attach(calib, compute_rectification(calib)).rectification
    broken = {**rect, "views": [{"P": v["P"]} for v in rect["views"]]}
    with pytest.raises(ValueError, match=r"rectification\.views\[0\]\.R_rect_from_view is missing"):
        export_calibration(calib.replace(rectification=broken), "opencv-yaml", tmp_path / "c.yaml")
    assert not list(tmp_path.iterdir())


# ============================================================================================== issue 19
def test_opencv_yaml_rectification_maps_match_lfgraph(tmp_path, calib):
    """OpenCV users rectify with initUndistortRectifyMap(K_i, D_i, R_rect_i, P_i) as with stereoRectify's P1/P2; that
    must give lfgraph's own rectified views (build_maps), not images off by pixels."""
    rectified = attach(calib, compute_rectification(calib))
    rect = stored_rectification(rectified)
    lfgraph_maps = build_maps(rectified, rect)
    path = export_calibration(rectified, "opencv-yaml", tmp_path / "calib.yml")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        size = (int(fs.getNode("rect_image_width").real()), int(fs.getNode("rect_image_height").real()))
        assert size == rect.image_size_px
        for i in range(calib.num_views):
            K, D, R_rect, P = (fs.getNode(f"{k}_{i}").mat() for k in ("K", "D", "R_rect", "P"))  # noqa: N806
            m1, m2 = cv2.initUndistortRectifyMap(K, D, R_rect, P, size, cv2.CV_16SC2)
            opencv_xy, _ = cv2.convertMaps(m1, m2, cv2.CV_32FC1)
            ours_x, ours_y = cv2.convertMaps(lfgraph_maps.map_xy[i], lfgraph_maps.map_frac[i], cv2.CV_32FC1)
            error_px = max(np.max(np.abs(opencv_xy - ours_x)), np.max(np.abs(_ - ours_y)))
            assert error_px < FIXED_POINT_MAP_STEP_PX, f"view {i}: rectified maps differ by {error_px} px"
            # P_i in stereoRectify's convention: rectified reference frame -> rectified pixels of view i, so a
            # reference-frame point projects where lfgraph's own projection P (reference frame) puts it
            X_ref = np.array([0.1, -0.05, 2.0, 1.0])  # noqa: N806
            X_rect = np.append(rect.rect_R_ref @ X_ref[:3], 1.0)  # noqa: N806
            expected = rect.P[i] @ X_ref
            got = P @ X_rect
            assert np.max(np.abs(got[:2] / got[2] - expected[:2] / expected[2])) < ROUND_TRIP_TOLERANCE
    finally:
        fs.release()


def _opencv_header_only(path, rows: int, cols: int) -> None:
    path.write_text(f"%YAML:1.0\n---\ngrid_rows: {rows}\ngrid_cols: {cols}\nreference: 0\nimage_width: 960\n"
                    f"image_height: 960\nnum_views: {rows * cols}\n")


def test_opencv_yaml_refuses_an_absurd_grid_quickly(tmp_path):
    _opencv_header_only(tmp_path / "c.yaml", 300, 300)
    start = time.perf_counter()
    with pytest.raises(CalibrationFileError, match=rf"c\.yaml: num_views: declares 90000 views; .* {MAX_IMPORT_VIEWS}"):
        import_calibration(tmp_path / "c.yaml", "opencv-yaml")
    assert time.perf_counter() - start < REFUSAL_TIME_LIMIT_S


def test_opencv_yaml_imports_a_20x20_grid_quickly(tmp_path):
    calib = make_rig(RigConfig(rows=20, cols=20, reference=210), np.random.default_rng(3))
    path = export_calibration(calib, "opencv-yaml", tmp_path / "c.yml")
    start = time.perf_counter()
    back = import_calibration(path, "opencv-yaml")
    elapsed_s = time.perf_counter() - start
    _assert_same(back, calib)
    assert elapsed_s < IMPORT_20X20_TIME_LIMIT_S, f"20x20 import took {elapsed_s:.2f} s"


def test_opencv_yaml_reads_old_opencv_headers_and_refuses_xml(tmp_path, calib):
    _write_filestorage(tmp_path / "c.yaml", _opencv_entries(calib))
    text = (tmp_path / "c.yaml").read_text()
    assert text.startswith("%YAML 1.2")  # what OpenCV 5 writes; OpenCV 3 and 4 wrote %YAML:1.0
    (tmp_path / "old.yaml").write_text(text.replace("%YAML 1.2", "%YAML:1.0", 1))
    _assert_same(import_calibration(tmp_path / "old.yaml", "opencv-yaml"), calib)
    fs = cv2.FileStorage(str(tmp_path / "c.xml"), cv2.FILE_STORAGE_WRITE)
    fs.write("grid_rows", 2)
    fs.release()
    with pytest.raises(CalibrationFileError, match=r"c\.xml: file: is FileStorage XML or JSON"):
        import_calibration(tmp_path / "c.xml", "opencv-yaml")


def test_hci_refuses_an_absurd_grid(tmp_path):
    (tmp_path / "parameters.cfg").write_text(
        "[intrinsics]\nfocal_length_mm = 100\nsensor_size_mm = 35\nimage_resolution_x_px = 512\n"
        "image_resolution_y_px = 512\n[extrinsics]\nnum_cams_x = 100000\nnum_cams_y = 100000\nbaseline_mm = 1\n")
    with pytest.raises(CalibrationFileError, match=r"parameters\.cfg: \[extrinsics\] num_cams_x, num_cams_y: "
                                                   r"declares 10000000000 views"):
        import_calibration(tmp_path, "hci")


def _run_cli(argv: list[str], capsys) -> tuple[int, str]:
    try:
        code = cli_main([str(a) for a in argv])
    except SystemExit as exc:  # argparse usage errors (exit code 2)
        code = int(exc.code)
    return code, capsys.readouterr().err


@pytest.mark.parametrize(("command", "fmt"), [("import", "json"), ("export", "json"), ("import", "opencv-yaml")])
def test_cli_refuses_to_overwrite_its_input(tmp_path, calib, capsys, command, fmt):
    path = tmp_path / ("c.json" if fmt == "json" else "c.yml")
    if fmt == "json":
        calib.save(path)
    else:
        export_calibration(calib, fmt, path)
    before = path.read_bytes()
    flag = "--from" if command == "import" else "--to"
    # the same file through another spelling of its path
    code, err = _run_cli([command, path, flag, fmt, "-o", tmp_path / "." / path.name], capsys)
    assert code == 1
    assert f"is the input {path}" in err
    assert path.read_bytes() == before


def test_cli_import_refuses_to_overwrite_a_scene_file(tmp_path, capsys):
    scene = tmp_path / "scene"
    scene.mkdir()
    text = "cam0=[1000 0 300; 0 1000 200; 0 0 1]\ncam1=[1000 0 310; 0 1000 200; 0 0 1]\nbaseline=100\nwidth=600\n" \
           "height=400\n"
    (scene / "calib.txt").write_text(text)
    code, err = _run_cli(["import", scene, "--from", "middlebury", "-o", scene / "calib.txt"], capsys)
    assert code == 1 and "calib.txt" in err
    assert (scene / "calib.txt").read_text() == text


def test_cli_refuses_a_missing_output_folder_before_reading(tmp_path, calib, capsys):
    missing = tmp_path / "missing"
    # the input does not exist either: the output must be the first thing checked
    for argv in (["import", tmp_path / "nowhere.json", "--from", "json", "-o", missing / "o.json"],
                 ["export", tmp_path / "nowhere.json", "--to", "kalibr", "-o", missing / "camchain.yaml"],
                 ["export", tmp_path / "nowhere.json", "--to", "colmap", "-o", missing / "sparse"]):
        code, err = _run_cli(argv, capsys)
        assert code == 2
        assert f"folder {missing} does not exist" in err
        assert not missing.exists()


def test_cli_refuses_an_output_of_the_wrong_kind(tmp_path, calib, capsys):
    calib.save(tmp_path / "in.json")
    (tmp_path / "folder").mkdir()
    code, err = _run_cli(["import", tmp_path / "in.json", "--from", "json", "-o", tmp_path / "folder"], capsys)
    assert code == 2 and f"{tmp_path / 'folder'} is a folder" in err
    code, err = _run_cli(["export", tmp_path / "in.json", "--to", "opencv-yaml", "-o", tmp_path / "folder"], capsys)
    assert code == 2 and "is a folder" in err
    (tmp_path / "file.txt").write_text("x")
    code, err = _run_cli(["export", tmp_path / "in.json", "--to", "colmap", "-o", tmp_path / "file.txt"], capsys)
    assert code == 2 and "is a file" in err
    assert (tmp_path / "file.txt").read_text() == "x"


def test_the_cli_lists_the_formats_the_library_has():
    from lfgraph.cli import interop as cli_interop

    assert cli_interop.EXPORT_FORMATS == EXPORT_FORMATS and cli_interop.IMPORT_FORMATS == IMPORT_FORMATS


@pytest.mark.parametrize("fmt", ["opencv-yaml", "kalibr", "colmap", "json"])
def test_a_rig_of_mixed_image_sizes_keeps_each_views_size(tmp_path, fmt):
    """Issue 42: views of 640x480 beside 320x240 ones came back from opencv-yaml, kalibr and colmap at one size."""
    calib = make_rig(RigConfig(rows=2, cols=2, image_size_px=(320, 240), focal_px=300.0), np.random.default_rng(1))
    sizes = ((320, 240), (640, 480), (320, 240), (400, 300))
    mixed = calib.replace(view_image_sizes_px=sizes)
    back = import_calibration(export_calibration(mixed, fmt, tmp_path / ("out" if fmt == "colmap" else "c.yaml")),
                              fmt, (2, 2))
    assert tuple(back.image_size(v) for v in range(4)) == sizes
    if fmt == "kalibr":  # as Kalibr reads it: each camera's own resolution
        data = yaml.safe_load((tmp_path / "c.yaml").read_text())
        assert [tuple(data[f"cam{v}"]["resolution"]) for v in range(4)] == list(sizes)


def test_a_horizontal_pair_is_not_read_as_a_vertical_grid(tmp_path):
    """Issue 42: ``import --from kalibr --grid 2x1`` of a horizontal pair was accepted as a vertical grid."""
    pair = make_rig(RigConfig(rows=1, cols=2, pitch_m=0.06, image_size_px=(320, 240), focal_px=300.0),
                    np.random.default_rng(2))
    path = export_calibration(pair, "kalibr", tmp_path / "camchain.yaml")
    assert import_calibration(path, "kalibr", (1, 2)).num_views == 2
    with pytest.raises(CalibrationFileError, match=r"run across the 2x1 grid.*Give it as 1x2"):
        import_calibration(path, "kalibr", (2, 1))
    assert cli_main(["import", str(path), "--from", "kalibr", "--grid", "2x1", "-o", str(tmp_path / "c.json")]) == 1
    assert not (tmp_path / "c.json").exists()


def test_translations_in_millimetres_are_named(tmp_path, caplog):
    """Issue 42: a file whose baselines are 1000x an array's (translations in mm where the format says m) is read
    with a warning naming the likely unit."""
    rig = make_rig(RigConfig(rows=1, cols=2, pitch_m=0.06, image_size_px=(320, 240), focal_px=300.0),
                   np.random.default_rng(3))
    poses = rig.ref_T_view.copy()
    poses[:, :3, 3] *= 1000.0  # as if the file held millimetres
    path = export_calibration(rig.replace(ref_T_view=poses), "kalibr", tmp_path / "camchain.yaml")
    with caplog.at_level("WARNING", logger="lfgraph"):
        import_calibration(path, "kalibr", (1, 2))
    assert "translations in millimetres" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="lfgraph"):
        import_calibration(export_calibration(rig, "kalibr", tmp_path / "ok.yaml"), "kalibr", (1, 2))
    assert "millimetres" not in caplog.text
