"""The lfgraph command: synth and info end to end, and clear failures on bad input."""

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from lfgraph.cli import EXIT_BAD_INPUT, main
from lfgraph.core.calibration import Calibration
from lfgraph.datasets.checkerboard import CheckerboardTruth


def test_synth_checkerboard_then_info(tmp_path, capsys):
    out = tmp_path / "small"
    code = main(["synth", "checkerboard", str(out), "--scene", "small-2x2", "--frames", "3", "--board", "5x4",
                 "--square-mm", "20", "--jobs", "1", "--quiet", "--seed", "4"])
    assert code == 0
    calib = Calibration.load(out / "truth.json")
    assert calib.grid.rows == 2 and calib.image_size_px == (320, 240)
    truth = CheckerboardTruth.load_npz(out / "truth_corners.npz")
    assert truth.board.pattern_size == (5, 4) and abs(truth.board.square_m - 0.02) < 1e-12
    img = cv2.imread(str(out / "002" / "r01_c01.png"), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (240, 320)
    assert main(["info", str(out / "truth.json")]) == 0
    text = capsys.readouterr().out
    assert "r01_c01" in text and "fx_px" in text and "grid 2x2" in text


def test_global_quiet_hides_progress_bars_and_info_logs(tmp_path, capsys):
    """`lfgraph -q CMD` shows neither progress bars nor info lines on standard error, and (issue 40) nothing on
    standard output: the exit code says how it went (every command: tests/cli/test_quiet.py)."""
    assert main(["-q", "synth", "checkerboard", str(tmp_path / "q"), "--scene", "small-2x2", "--frames", "2",
                 "--jobs", "1"]) == 0
    captured = capsys.readouterr()
    assert captured.err == "" and captured.out == ""
    assert (tmp_path / "q" / "truth.json").is_file()
    assert main(["synth", "checkerboard", str(tmp_path / "loud"), "--scene", "small-2x2", "--frames", "2",
                 "--jobs", "1"]) == 0
    assert "rendering" in capsys.readouterr().err  # the bar is there without -q


def test_synth_mosaic_with_grid_override(tmp_path):
    out = tmp_path / "mosaic"
    assert main(["synth", "checkerboard", str(out), "--scene", "small-2x2", "--grid", "1x3", "--frames", "2",
                 "--layout", "mosaic", "--jobs", "1", "--quiet"]) == 0
    assert cv2.imread(str(out / "000.png"), cv2.IMREAD_GRAYSCALE).shape == (240, 960)


def test_synth_shaken_scene_writes_truth_and_original(tmp_path):
    out = tmp_path / "scene"
    assert main(["synth", "scene", str(out), "--scene", "small-2x2", "--frames", "1", "--image-size", "96x64",
                 "--shake-rot-deg", "1", "--shake-trans-mm", "5", "--jobs", "1", "--quiet"]) == 0
    truth, original = Calibration.load(out / "truth.json"), Calibration.load(out / "original.json")
    moved_mm = 1e3 * np.abs(truth.ref_T_view[:, :3, 3] - original.ref_T_view[:, :3, 3])
    assert moved_mm[0].max() == 0 and 0 < moved_mm.max() <= 5 + 1e-9
    assert cv2.imread(str(out / "000" / "r01_c01.png"), 0).shape == (64, 96)


def test_info_bad_json_exits_nonzero_naming_the_file(tmp_path, capsys):
    bad = tmp_path / "calib.json"
    bad.write_text(json.dumps({"format": "lfgraph.calibration", "version": 7}))
    assert main(["info", str(bad)]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "calib.json: version: unknown version 7" in err


@pytest.mark.parametrize(
    "argv",
    [
        ["synth", "checkerboard", "OUT", "--grid", "4by4"],
        ["synth", "checkerboard", "OUT", "--image-size", "960"],
        ["synth", "checkerboard", "OUT", "--frames", "0"],
    ],
)
def test_usage_errors_exit_2(argv, tmp_path):
    argv = [str(tmp_path / "o") if a == "OUT" else a for a in argv]
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    assert not (tmp_path / "o").exists()


def test_unknown_scene_and_bad_board_write_nothing(tmp_path, capsys):
    assert main(["synth", "checkerboard", str(tmp_path / "a"), "--scene", "paper-9x9"]) == EXIT_BAD_INPUT
    assert "unknown scene 'paper-9x9'" in capsys.readouterr().err
    assert main(["synth", "checkerboard", str(tmp_path / "b"), "--scene", "small-2x2", "--board", "1x4"]) == 1
    assert "at least 3x3 inner corners" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_console_script_runs():
    proc = subprocess.run([sys.executable, "-m", "lfgraph.cli", "--help"], capture_output=True, text=True, check=False)
    assert proc.returncode == 0 and "synth" in proc.stdout and "info" in proc.stdout


def test_demo_on_the_small_scene(tmp_path, capsys):
    assert main(["demo", "--scene", "small-2x2", "--out", str(tmp_path), "--jobs", "1", "--quiet", "--no-refine"]) == 0
    text = capsys.readouterr().out
    assert "[4/5]" in text and "parallax removed" in text and "paper / joint" in text and "rig-consistent RMS" in text
    calib = Calibration.load(tmp_path / "calibration.json")
    assert calib.metrics["method"] == "joint" and calib.num_views == 4


def test_info_shows_each_views_lens_and_image_size(tmp_path, capsys):
    """Issue 42: ``info`` showed no lens model (nor fisheye k3, k4 or a unified xi) and one image size for a rig of
    mixed sizes."""
    import lfgraph as lf

    calib, _ = lf.synth.knocked_rig("fisheye-1x3", seed=1)
    calib = calib.replace(view_image_sizes_px=((640, 480), (1280, 720), (640, 480)))
    path = tmp_path / "c.json"
    calib.save(path)
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "fisheye" in out and "1280x720" in out and "640x480" in out
    assert main(["info", str(path), "--json"]) == 0
    views = json.loads(capsys.readouterr().out)["views"]
    assert [v["image_size_px"] for v in views] == [[640, 480], [1280, 720], [640, 480]]
    assert all(v["lens"] == "fisheye" and "k4" in v for v in views)
