"""Issue 28: the library as a researcher scripts it — settings validated at construction with messages naming the
argument, the headline metric in `evaluate`, fixed report columns, warnings at WARNING."""

import logging

import numpy as np
import pytest

import lfgraph as lf
from lfgraph.core.camera import project_world
from lfgraph.datasets.rig import RigConfig, ShakeConfig, make_rig, shake_rig

SAME_PX = 1e-9  # px: one transfer computation against another
FAR_M = 1e9  # m: a point this far projects as a point at infinity ...
FAR_PX = 1e-4  # px: ... to within this (a 5 cm baseline at 1e9 m and f 500 px: 2.5e-8 px)
JSON_ROUND_TRIP = 1e-15  # m and rotation entries: a float written to JSON and read back
KNOCK_PX = 0.5  # px: a 0.3 deg knock moves some view by more than this at infinity


@pytest.fixture(scope="module")
def rigs():
    rig = make_rig(RigConfig(rows=2, cols=3, pitch_m=0.05, image_size_px=(640, 480), focal_px=500.0),
                   np.random.default_rng(1))
    return rig, shake_rig(rig, ShakeConfig(rot_deg=0.3, trans_mm=1.0, axis="any"), np.random.default_rng(2))


def test_drift_and_hooks_take_the_forms_a_script_writes():
    assert lf.RefineConfig(drift={"roll_deg": 2}).drift == lf.DriftModel(roll_deg=2)
    assert lf.RefineConfig(drift="roll_deg=2").drift == lf.DriftModel(roll_deg=2)
    with pytest.raises(ValueError, match="unknown drift sigma rol_deg"):
        lf.RefineConfig(drift={"rol_deg": 2})
    with pytest.raises(TypeError, match="drift must be a DriftModel"):
        lf.RefineConfig(drift=2)

    def hook(ctx):
        pass

    assert lf.RefineConfig(graph_hooks=hook).graph_hooks == (hook,)  # one function is a list of one
    assert lf.CalibrateConfig(graph_hooks=hook).graph_hooks == (hook,)
    with pytest.raises(TypeError, match="RefineConfig.graph_hooks must be a function"):
        lf.RefineConfig(graph_hooks=3)


def test_evaluate_reports_the_transfer_error_at_infinity(rigs):
    rig, truth = rigs
    errors = lf.evaluate(rig, truth)
    assert errors.transfer_px.shape == (rig.num_views,) and errors.transfer_px[rig.grid.reference] == 0.0
    # independently: the reference pixels (24 x 24 over 5-95 % of the image) sent 1e9 m away and projected with the
    # full camera model (translation included, negligible there) of each calibration
    w, h = rig.image_size_px
    ref = rig.grid.reference
    gx, gy = np.meshgrid(np.linspace(0.05 * (w - 1), 0.95 * (w - 1), 24),
                         np.linspace(0.05 * (h - 1), 0.95 * (h - 1), 24))
    px = np.column_stack([gx.ravel(), gy.ravel()])

    def far_projections(calib, v):
        xy = calib.intrinsics[ref].undistort(px)
        rays = np.column_stack([xy, np.ones(len(xy))])
        return project_world(calib.intrinsics[v], calib.view_T_ref(v), rays * FAR_M)

    for v in range(rig.num_views):
        d = np.linalg.norm(far_projections(rig, v) - far_projections(truth, v), axis=1)
        assert errors.transfer_px[v] == pytest.approx(np.sqrt(np.mean(d**2)), abs=FAR_PX)
    assert np.max(errors.transfer_px) > KNOCK_PX  # the knock shows
    s = errors.summary()
    assert list(s)[-2:] == ["rms_transfer_px", "max_transfer_px"]
    assert s["max_transfer_px"] == pytest.approx(float(np.max(errors.transfer_px)), abs=SAME_PX)
    # the same figure with the truth expressed relative to another view (evaluate re-anchors it)
    other = lf.evaluate(rig, truth.with_reference(2))
    np.testing.assert_allclose(other.transfer_px, errors.transfer_px, atol=SAME_PX)


def test_with_reference_keeps_the_rig(rigs):
    rig, _ = rigs
    moved = rig.with_reference(4)
    assert moved.grid.reference == 4 and np.allclose(moved.ref_T_view[4], np.eye(4))
    back = moved.with_reference(rig.grid.reference)
    np.testing.assert_allclose(back.ref_T_view, rig.ref_T_view, atol=1e-12)
    with pytest.raises(ValueError, match="reference must be a view index"):
        rig.with_reference(6)


def test_verdict_counts_keep_their_columns():
    report = lf.RefinementReport.__new__(lf.RefinementReport)
    object.__setattr__(report, "verdicts", ())
    assert report.verdict_counts() == {"OK": 0, "DRIFTED": 0, "UNCERTAIN": 0, "REFERENCE": 0}


def test_library_warnings_are_logged_at_warning(caplog):
    with caplog.at_level(logging.INFO, logger="lfgraph"):
        lf.BaseObserver().log("warning: tracks cover only 3 % of the reference image")
        lf.BaseObserver().log("stage poses: 100 landmarks")
    levels = {r.getMessage(): r.levelno for r in caplog.records}
    assert levels["tracks cover only 3 % of the reference image"] == logging.WARNING
    assert levels["stage poses: 100 landmarks"] == logging.INFO


@pytest.mark.slow
def test_a_synthetic_capture_in_memory_is_the_one_the_cli_writes(tmp_path):
    from lfgraph.cli import main

    out = tmp_path / "sc"
    args = ["synth", "scene", str(out), "--scene", "small-2x2", "--frames", "2", "--shake-rot-deg", "0.5",
            "--shake-trans-mm", "1", "--shake-axis", "any", "--seed", "3", "--jobs", "1", "--quiet"]
    assert main(args) == 0
    cap = lf.synth.scene_capture("small-2x2", frames=2, shake_rot_deg=0.5, shake_trans_mm=1.0, shake_axis="any",
                                 seed=3)
    assert cap.knocked
    # the same rigs (to the JSON file's last digit) ...
    np.testing.assert_allclose(cap.truth.ref_T_view, lf.Calibration.load(out / "truth.json").ref_T_view,
                               atol=JSON_ROUND_TRIP)
    np.testing.assert_allclose(cap.original.ref_T_view, lf.Calibration.load(out / "original.json").ref_T_view,
                               atol=JSON_ROUND_TRIP)
    written = lf.open_capture(out, cap.truth.grid)
    for f, frame in enumerate(cap.frames):
        np.testing.assert_array_equal(frame, written.load_frame(f))  # ... and the same pixels, noise included
    plain = lf.synth.scene_capture("small-2x2", frames=1, seed=3)
    assert not plain.knocked and plain.frames[0].shape == (4, 240, 320) and plain.frames[0].dtype == np.uint8
    with pytest.raises(ValueError, match="unknown scene"):
        lf.synth.scene_capture("paper-9x9")


@pytest.mark.slow
def test_a_study_swaps_in_any_noise_object_or_hook(tmp_path):
    import gtsam

    calls = []

    def hook(ctx):  # a study of user factors: here it only records that it ran
        calls.append(ctx.stage)

    cauchy = gtsam.noiseModel.mEstimator.Custom.Create(lambda d: 1.0 / (1.0 + (d / 2.385) ** 2),
                                                        lambda d: 0.5 * 2.385**2 * np.log1p((d / 2.385) ** 2))
    configs = {"least squares": lf.RefineConfig(), "huber 0.1 px": lf.RefineConfig(robust="huber:0.1"),
               "custom cauchy": lf.RefineConfig(robust=cauchy), "with a hook": lf.RefineConfig(graph_hooks=hook)}
    rows = lf.study.shake_study(configs, scene="small-2x2", rot_deg=(0.5,), trans_mm=(1.0,), trials=1, frames=2,
                                out_csv=tmp_path / "s.csv")
    assert sorted(r["config"] for r in rows) == sorted(configs)
    assert calls  # the hook ran in this process
    for r in rows:  # errors against the knocked truth; refinement never made it worse
        assert float(r["transfer_px"]) <= float(r["transfer_before_px"])
    assert (tmp_path / "s.csv").read_text().count("\n") == len(configs) + 1
    with pytest.raises(ValueError, match="custom cauchy.*mEstimator.Custom.*jobs=1"):
        lf.study.shake_study({"custom cauchy": configs["custom cauchy"]}, scene="small-2x2", rot_deg=(0.5,),
                             trans_mm=(1.0,), trials=1, frames=1, jobs=2)
    with pytest.raises(TypeError, match="must be a lfgraph.RefineConfig"):
        lf.study.shake_study(["huber"], scene="small-2x2")


def test_a_calibration_recorded_from_the_library_shows_its_result(tmp_path):
    from tests.test_api import corner_observations
    from tests.viz.test_rerun import read_blueprint, read_rrd

    _, obs = corner_observations()
    with lf.viz.RerunLogger.to_file(tmp_path / "cal.rrd", obs.grid) as rec:
        calib, _ = lf.calibrate(obs, lf.CalibrateConfig(marginals=False), observer=rec)
    columns, static, _ = read_rrd(tmp_path / "cal.rrd", None)
    np.testing.assert_allclose(static["/world/calibrated_rig/r00_c01:Transform3D:translation"][0][0],
                               calib.ref_T_view[1][:3, 3], atol=1e-9)
    assert any(c.startswith("/world/boards/") for c in columns)
    eye = []
    read_blueprint(tmp_path / "cal.rrd", eye)
    assert eye  # the layout opens on the calibrated rig


def test_the_names_synth_documents_exist():
    """Issue 40: ``help(lf.synth.scene_capture)`` named ``RigConfig``, which ``lf.synth`` did not hold."""
    import lfgraph as lf

    assert {"rows", "cols", "image_size_px"} <= set(lf.synth.RigConfig.__dataclass_fields__)
    cap = lf.synth.scene_capture("small-2x2", frames=1, rows=1, cols=3)
    assert cap.truth.grid.num_views == 3 and len(cap.frames[0]) == 3
