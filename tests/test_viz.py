"""rerun logging: `calibrate` and `refine` with --save write .rrd files that rerun's own server reads back."""

import pytest
import rerun as rr

from lfgraph.calibration import Calibration
from lfgraph.cli import main

SMALL = ["--grid", "2x2", "--board", "7x5", "--square-mm", "15", "--quiet"]


def read_rrd(path):
    """Every logged row of a recording as pandas frames: timeless/static, per iteration, per log_time."""
    with rr.server.Server(datasets={"run": [str(path)]}) as server:
        ds = server.client().get_dataset("run")
        columns = [c.name for c in ds.schema()]
        by_iteration = ds.reader(index="iteration").to_pandas() if any("optimizer/error" in c for c in columns) \
            else None
        by_time = ds.reader(index="log_time").to_pandas()
    return columns, by_iteration, by_time


@pytest.fixture(scope="module")
def board_capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("viz") / "small"
    assert main(["synth", "checkerboard", str(out), "--scene", "small-2x2", "--frames", "10", "--jobs", "2",
                 "--quiet", "--seed", "5"]) == 0
    return out


def test_calibrate_save_rrd(board_capture, tmp_path):
    rrd = tmp_path / "calib.rrd"
    out = tmp_path / "c.json"
    assert main(["calibrate", str(board_capture), *SMALL, "-o", str(out), "--save", str(rrd)]) == 0
    assert rrd.exists() and not list(tmp_path.glob(".*.tmp"))
    calib = Calibration.load(out)
    columns, by_iteration, by_time = read_rrd(rrd)
    names = {calib.grid.name(v) for v in range(4)}
    rig = {c.split(":")[0] for c in columns if c.startswith("/world/rig/view_") and "Transform3D" in c}
    assert rig == {f"/world/rig/view_{n}" for n in names}
    assert any(c.startswith("/world/rig/view_r00_c00:Pinhole") for c in columns)
    assert any(c.startswith("/views/r00_c00/outliers:Points2D") for c in columns)  # corners of outlier frames
    boards = {c.split(":")[0] for c in columns if c.startswith("/world/boards/frame_") and "Transform3D" in c}
    assert len(boards) == 10
    # one residual arrow per detected corner, per view
    for v in range(4):
        rows = by_time[f"/views/{calib.grid.name(v)}/residuals:Arrows2D:vectors"].dropna()
        assert len(rows) == 1
        assert len(rows.iloc[0]) == calib.metrics["frames_per_view"][v] * 35  # 7x5 corners, full boards
    # the iteration timeline has as many steps as the optimiser reported
    steps = by_iteration["/optimizer/error:Scalars:scalars"].dropna()
    assert len(steps) == calib.metrics["iterations"] > 0
    assert sorted(by_iteration["iteration"].dropna().astype(int).unique().tolist())[-1] == calib.metrics["iterations"]


def test_refine_save_rrd(tmp_path):
    scene = tmp_path / "scene"
    assert main(["synth", "scene", str(scene), "--scene", "small-2x2", "--frames", "2", "--shake-rot-deg", "0.5",
                 "--shake-trans-mm", "1", "--jobs", "2", "--quiet"]) == 0
    rrd = tmp_path / "refine.rrd"
    out = tmp_path / "r.json"
    assert main(["refine", str(scene / "original.json"), str(scene), "-o", str(out), "--quiet",
                 "--save", str(rrd)]) == 0
    m = Calibration.load(out).metrics["refinement"]
    columns, by_iteration, by_time = read_rrd(rrd)
    assert len(by_iteration["/optimizer/error:Scalars:scalars"].dropna()) == m["total_iterations"] > 0
    stages = by_iteration["/optimizer/stages:TextLog:text"].dropna()
    assert len(stages) == 2 * 3  # two frames x three stages
    landmarks = by_time["/world/landmarks:Points3D:positions"].dropna()
    assert len(landmarks.iloc[-1]) == m["stages"][-1]["landmarks"]
    assert any(c.startswith("/views/r01_c01/residuals:Arrows2D") for c in columns)
    assert any(c.startswith("/views/r01_c01/outliers:Points2D") for c in columns)  # filtered tracks, in red
    assert any(c.startswith("/rms/view_r00_c01:Scalars") for c in columns)


def test_no_flags_no_recording(board_capture, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["calibrate", str(board_capture), *SMALL, "-o", str(tmp_path / "c.json")]) == 0
    assert not list(tmp_path.glob("*.rrd")) and rr.get_global_data_recording() is None


@pytest.mark.parametrize("target", ["missing/dir/run.rrd", "."])
def test_unwritable_save_path_fails_before_work(board_capture, tmp_path, capsys, target):
    out = tmp_path / "c.json"
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", str(board_capture), *SMALL, "-o", str(out), "--save", str(tmp_path / target)])
    assert exc.value.code == 2
    assert "--save" in capsys.readouterr().err
    assert not out.exists()
