"""calibration.json: round trip, atomic write, and every loading error."""

import json

import numpy as np
import pytest

from lfgraph.core.calibration import Calibration, CalibrationFileError
from lfgraph.core.geometry import rotation_angle_deg
from lfgraph.datasets.rig import RigConfig, ShakeConfig, make_rig, shake_rig

ROUND_TRIP_TOLERANCE = 1e-12  # JSON keeps 17 significant digits; the pose inversion costs a few ulps


@pytest.fixture
def calib():
    return make_rig(RigConfig(rows=2, cols=3, reference=1, image_size_px=(320, 240), focal_px=300),
                    np.random.default_rng(3))


def test_round_trip(tmp_path, calib):
    path = tmp_path / "calibration.json"
    calib.replace(metrics={"rig_rms_px": 0.123}).save(path)
    back = Calibration.load(path)
    assert back.grid == calib.grid and back.image_size_px == calib.image_size_px
    assert np.max(np.abs(back.ref_T_view - calib.ref_T_view)) < ROUND_TRIP_TOLERANCE
    for a, b in zip(back.intrinsics, calib.intrinsics, strict=True):
        assert np.max(np.abs(a.as_vector() - b.as_vector())) < ROUND_TRIP_TOLERANCE
    assert back.metrics["rig_rms_px"] == 0.123 and back.metrics["e_mono_px"] is None
    data = json.loads(path.read_text())
    assert data["format"] == "lfgraph.calibration" and data["version"] == 1
    assert data["views"][4]["row"] == 1 and data["views"][4]["col"] == 1
    assert set(data["views"][0]) >= {"K", "distortion", "R_view_from_ref", "t_view_from_ref_m"}
    # OpenCV convention in the file: x_view = R x_ref + t
    v = data["views"][0]
    x_ref = np.array([0.1, 0.2, 1.0])
    x_view = np.array(v["R_view_from_ref"]) @ x_ref + np.array(v["t_view_from_ref_m"])
    assert np.allclose(calib.ref_T_view[0][:3, :3] @ x_view + calib.ref_T_view[0][:3, 3], x_ref)
    assert not list(tmp_path.glob(".*tmp*")), "temporary file left behind"


def test_rig_is_seeded_and_reference_is_identity(calib):
    again = make_rig(RigConfig(rows=2, cols=3, reference=1, image_size_px=(320, 240), focal_px=300),
                     np.random.default_rng(3))
    assert np.array_equal(again.ref_T_view, calib.ref_T_view)
    assert np.array_equal(calib.ref_T_view[1], np.eye(4))
    # design pitch 6 mm: view 2 is one column right of the reference
    assert abs(calib.ref_T_view[2][0, 3] - 0.006) < 1e-3


def test_shake_moves_only_what_it_should(calib):
    shaken = shake_rig(calib, ShakeConfig(rot_deg=1.0, trans_mm=5.0), np.random.default_rng(0))
    assert np.array_equal(shaken.ref_T_view[1], np.eye(4))
    for v in (0, 2, 3, 4, 5):
        dR = calib.ref_T_view[v][:3, :3].T @ shaken.ref_T_view[v][:3, :3]  # noqa: N806
        assert rotation_angle_deg(dR) <= 1.0 + 1e-9
        # about the optical axis only: the z axis does not move
        assert np.allclose(dR[:, 2], [0, 0, 1], atol=1e-12)
        shift = shaken.ref_T_view[v][:3, 3] - calib.ref_T_view[v][:3, 3]
        assert np.all(np.abs(shift) <= 5e-3 + 1e-12)
    assert shaken.intrinsics == calib.intrinsics
    none = shake_rig(calib, ShakeConfig(), np.random.default_rng(0))
    assert np.allclose(none.ref_T_view, calib.ref_T_view, atol=1e-15)


def _write(tmp_path, mutate, calib):
    data = calib.to_dict()
    mutate(data)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize(
    ("mutate", "field"),
    [
        (lambda d: d.update(format="something.else"), "format"),
        (lambda d: d.update(version=2), "version"),
        (lambda d: d.pop("grid"), "grid"),
        (lambda d: d["grid"].update(rows=3), "views"),
        (lambda d: d["grid"].update(reference=9), "grid"),
        (lambda d: d["views"].pop(), "views"),
        (lambda d: d["views"][2].update(R_view_from_ref=[[1, 0, 0], [0, 1, 0], [0, 0, 2]]),
         r"views\[2\]\.R_view_from_ref"),
        (lambda d: d["views"][3]["K"][0].__setitem__(0, -5.0), r"views\[3\]\.K"),
        (lambda d: d["views"][3]["distortion"].pop("k2"), r"views\[3\]\.distortion\.k2"),
        (lambda d: d["views"][0]["t_view_from_ref_m"].append(1.0), r"views\[0\]\.t_view_from_ref_m"),
        (lambda d: d["views"][5].update(index=4), r"views\[5\]\.index"),
        (lambda d: d["views"][5].update(col=0), r"views\[5\]\.col"),
        (lambda d: d.update(image_size_px=[320]), "image_size_px"),
        (lambda d: d["views"][1].update(t_view_from_ref_m=[0.01, 0, 0]), r"views\[1\].*reference"),
        (lambda d: d.update(metrics=[1, 2]), "metrics"),
    ],
)
def test_load_rejects_bad_files(tmp_path, calib, mutate, field):
    path = _write(tmp_path, mutate, calib)
    with pytest.raises(CalibrationFileError, match=field) as info:
        Calibration.load(path)
    assert str(path) in str(info.value)


def test_load_rejects_nan_bad_json_and_missing_file(tmp_path, calib):
    text = calib.to_json().replace(str(calib.intrinsics[0].fx), "NaN", 1)
    (tmp_path / "nan.json").write_text(text)
    with pytest.raises(CalibrationFileError, match="nan.json: JSON: non-finite"):
        Calibration.load(tmp_path / "nan.json")
    (tmp_path / "broken.json").write_text('{"format": ')
    with pytest.raises(CalibrationFileError, match="broken.json: JSON: not valid JSON"):
        Calibration.load(tmp_path / "broken.json")
    with pytest.raises(CalibrationFileError, match="missing.json: file: does not exist"):
        Calibration.load(tmp_path / "missing.json")


def test_save_refuses_non_finite_and_keeps_old_file(tmp_path, calib):
    path = tmp_path / "calibration.json"
    calib.save(path)
    before = path.read_text()
    with pytest.raises(ValueError, match="non-finite"):
        calib.replace(metrics={"rig_rms_px": float("nan")}).save(path)
    assert path.read_text() == before


def test_constructor_validates(calib):
    poses = np.array(calib.ref_T_view)
    poses[2, 0, 0] = 3.0
    with pytest.raises(ValueError, match="rotation"):
        calib.replace(ref_T_view=poses)
    with pytest.raises(ValueError, match="intrinsics"):
        calib.replace(intrinsics=calib.intrinsics[:-1])


def test_stored_sigmas_read_in_either_shape_and_refused_when_broken():
    calib = make_rig(RigConfig(rows=1, cols=2, image_size_px=(320, 240), focal_px=300.0), np.random.default_rng(0))
    view = {"fx_px": 0.5, "fy_px": 0.6, "cx_px": 0.7, "cy_px": 0.8, "k1": 1e-3, "k2": 2e-3,
            "rotation_deg": [0.01, 0.02, 0.03], "position_mm": [0.1, 0.2, 0.3]}
    listed = calib.replace(metrics={"sigmas": [view, view]}).sigmas
    assert listed == calib.replace(metrics={"sigmas": {"views": [view, view]}}).sigmas  # calibrate-scene's old shape
    assert listed.intrinsics[1, 3] == 0.8 and np.allclose(listed.position_mm[1], (0.1, 0.2, 0.3), rtol=1e-15, atol=0)
    assert listed.distortion["k2"][1] == 2e-3 and np.allclose(listed.pose[1, :3], np.radians([0.01, 0.02, 0.03]))
    assert calib.replace(metrics={"sigmas": [view, {**view, "note": "ours"}]}).sigmas == listed  # not a coefficient
    for broken in ([view], [view, {**view, "fx_px": "x"}], [view, {**view, "position_mm": [0.1]}],
                   [view, {**view, "cx_px": float("nan")}], "no"):
        assert calib.replace(metrics={"sigmas": broken}).sigmas is None, broken


def test_a_view_the_grid_does_not_have_and_fractional_sizes_are_refused():
    """Issue 42: ``image_size(4)`` of 4 views and ``image_size(-1)`` answered; fractional image sizes were truncated
    (``Calibration.replace``, ``Design``)."""
    import pytest

    import lfgraph as lf

    calib, _ = lf.synth.knocked_rig("small-2x2", seed=1)
    for view in (4, -1):
        with pytest.raises(ValueError, match="outside a 2x2 grid"):
            calib.image_size(view)
    with pytest.raises(ValueError, match="whole pixels"):
        calib.replace(view_image_sizes_px=((320.5, 240), (320, 240), (320, 240), (320, 240)))
    with pytest.raises(ValueError, match="whole pixels"):
        lf.Design(rows=2, cols=2, pitch_mm=10, focal_px=300, image_size_px=(640.5, 480))
