"""The newcomer's tests (issue 39): a lens model, a robust kernel and a file format of one's own are each one new file
(this one) and one registration line, then reached everywhere the built-in ones are — the calibration, its file,
the noise options, `export_calibration` and ``lfgraph export``. (A tracker: tests/refinement/test_tracker.py.)"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import gtsam
import numpy as np
import pytest

import lfgraph as lf
from lfgraph.cli import main as cli_main
from lfgraph.datasets.board_render import CheckerboardConfig
from lfgraph.datasets.checkerboard import make_checkerboard_truth, make_corner_observations
from lfgraph.datasets.rig import RigConfig, make_rig
from lfgraph.detect.board import BoardSpec
from lfgraph.detect.detections import observations_from_arrays
from lfgraph.lenses.model import LensModel

SAME_PX = 1e-6  # a model with another name but the same mathematics calibrates to the same intrinsics (px)
SAME_REL = 1e-9  # a kernel registered under another name gives the same fit (relative)


# ------------------------------------------------------------------------------------------- a lens of one's own
def _brown(x, y, k1, k2, p1, p2, k3, k4, xi, jacobian: bool):
    """Brown–Conrady written out again (the radtan model's mathematics under another name)."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + k2 * r2)
    xd, yd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    if not jacobian:
        return xd, yd
    dr = 2.0 * (k1 + 2.0 * k2 * r2)
    d01 = x * y * dr + 2 * p1 * x + 2 * p2 * y
    d00, d11 = radial + x * x * dr + 2 * p1 * y + 6 * p2 * x, radial + y * y * dr + 6 * p1 * y + 2 * p2 * x
    return xd, yd, d00, d01, d01, d11


def _brown_coefficients(x, y, k1, k2, p1, p2, k3, k4, xi):
    r2 = x * x + y * y
    return np.stack([np.stack([x * r2, x * r2 * r2, 2 * x * y, r2 + 2 * x * x], -1),
                     np.stack([y * r2, y * r2 * r2, r2 + 2 * y * y, 2 * x * y], -1)], -2)


def _brown_undistort(target, intrinsics):
    from lfgraph.lenses.radtan import radtan_rows, undo_radtan  # the inverse is the radtan one (same map)
    return undo_radtan(target, radtan_rows(intrinsics))


BROWN = LensModel(name="brown-conrady", gtsam_name="Cal3DS2", coefficients=("k1", "k2", "p1", "p2"),
                  tangent=("k1", "k2", "p1", "p2"), bulk_map=_brown, undistort=_brown_undistort,
                  folded=lambda intr, rays, xy, px: np.zeros(len(rays), dtype=bool), tangential=("p1", "p2"),
                  opencv="pinhole", coefficient_jacobian=_brown_coefficients)


@pytest.fixture(scope="module")
def brown():
    from lfgraph import lenses

    lenses.register(BROWN)  # the one registration line
    yield BROWN.name
    lenses._MODELS.pop(BROWN.name)


@pytest.fixture(scope="module")
def corners():
    """Corner-only 1x3 rig, 12 frames, 0.1 px noise."""
    rig = RigConfig(rows=1, cols=3, reference=1, pitch_m=0.05, image_size_px=(640, 480), focal_px=600.0, k1=-0.1,
                    k2=0.02)
    rng = np.random.default_rng(7)
    truth = make_rig(rig, rng)
    boards = make_checkerboard_truth(truth, CheckerboardConfig(board=BoardSpec(8, 6, 0.03), frames=12,
                                                               distance_m=(0.4, 0.8)), rng)
    c, v = make_corner_observations(boards, 0.1, np.random.default_rng(8))
    return observations_from_arrays(boards.board, truth.grid, truth.image_size_px, c, v)


def test_a_lens_model_is_one_module_and_one_registration_line(brown, corners, tmp_path):
    radtan, _ = lf.calibrate(corners, lf.CalibrateConfig(lens="radtan"))
    ours, report = lf.calibrate(corners, lf.CalibrateConfig(lens=brown))
    assert {i.lens for i in ours.intrinsics} == {brown}
    for a, b in zip(radtan.intrinsics, ours.intrinsics, strict=True):
        assert np.allclose([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], atol=SAME_PX, rtol=0)
        assert np.allclose(list(a.distortion.values()), list(b.distortion.values()), atol=SAME_PX / a.fx, rtol=0)
    assert report.sigmas is not None
    ours.save(tmp_path / "calibration.json")  # the file names the model, and reads back
    assert json.loads((tmp_path / "calibration.json").read_text())["views"][0]["lens"] == brown
    assert lf.Calibration.load(tmp_path / "calibration.json").intrinsics == ours.intrinsics


# ------------------------------------------------------------------------------------------ a kernel of one's own
def test_a_robust_kernel_is_one_registration_line(corners):
    from lfgraph.factors import noise

    noise.register_kernel("cauchy-again", gtsam.noiseModel.mEstimator.Cauchy.Create, 2.385)  # the one line
    try:
        ours, _ = lf.calibrate(corners, lf.CalibrateConfig(lens="radtan", robust="cauchy-again"))
        theirs, _ = lf.calibrate(corners, lf.CalibrateConfig(lens="radtan", robust="cauchy"))
        assert str(lf.RobustKernel.parse("cauchy-again:1.5sigma")) == "cauchy-again:1.5sigma"
        with pytest.raises(ValueError, match="a robust kernel needs a new lower-case name"):
            noise.register_kernel("cauchy", gtsam.noiseModel.mEstimator.Cauchy.Create, 1.0)
    finally:
        noise._KERNELS.pop("cauchy-again")
        noise.DEFAULT_THRESHOLDS.pop("cauchy-again")
    for a, b in zip(ours.intrinsics, theirs.intrinsics, strict=True):
        assert a.fx == pytest.approx(b.fx, rel=SAME_REL)
    with pytest.raises(ValueError, match="unknown robust kernel 'cauchy-again'"):
        lf.RobustKernel("cauchy-again")


# ------------------------------------------------------------------------------------------ a format of one's own
def _write_csv(calib: lf.Calibration, path: Path) -> None:
    rows = ["view,fx_px,fy_px,cx_px,cy_px,x_m,y_m,z_m"]
    rows += [f"{calib.grid.name(v)},{i.fx!r},{i.fy!r},{i.cx!r},{i.cy!r},"
             + ",".join(repr(float(t)) for t in calib.ref_T_view[v, :3, 3]) for v, i in enumerate(calib.intrinsics)]
    path.write_text("\n".join(rows) + "\n")


def test_an_export_format_is_one_function_and_one_registration_line(tmp_path, corners):
    from lfgraph import interop

    interop.register_format(interop.FileFormat("csv-for-a-test", write=_write_csv))  # the one line
    try:
        calib, _ = lf.calibrate(corners, lf.CalibrateConfig(lens="radtan"))
        calib.save(tmp_path / "calibration.json")
        loaded = lf.Calibration.load(tmp_path / "calibration.json")
        lf.export_calibration(loaded, "csv-for-a-test", tmp_path / "api.csv")
        assert cli_main(["-q", "export", str(tmp_path / "calibration.json"), "--to", "csv-for-a-test", "-o",
                         str(tmp_path / "cli.csv")]) == 0
        assert "csv-for-a-test" in interop.export_formats() and "csv-for-a-test" not in interop.import_formats()
    finally:
        interop._FORMATS.pop("csv-for-a-test")
    table = np.genfromtxt(tmp_path / "cli.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    assert np.array_equal(table["fx_px"], [i.fx for i in calib.intrinsics])
    assert (tmp_path / "api.csv").read_text() == (tmp_path / "cli.csv").read_text()
    with pytest.raises(ValueError, match="unknown export format 'csv-for-a-test'"):
        lf.export_calibration(calib, "csv-for-a-test", tmp_path / "again.csv")
    assert dataclasses.is_dataclass(interop.FileFormat)
