"""Issue 42: the grid as a checked design. A rig whose streams are wrong — cables swapped, a stream duplicated, a
camera's image mirrored — calibrated without a word; `calibrate` now refuses each by name and cause, a grid numbered
the other way round is said and calibrated, and `--view-order` re-labels swapped streams."""

import dataclasses

import numpy as np
import pytest

from lfgraph.cli import EXIT_BAD_INPUT, main
from lfgraph.core.grid_design import grid_problems
from lfgraph.datasets.checkerboard import make_checkerboard_truth, make_corner_observations
from lfgraph.datasets.rig import make_rig
from lfgraph.datasets.scenes import get_scene
from lfgraph.detect.detections import observations_from_arrays
from lfgraph.pattern import CalibrateConfig, CalibrationInputError, calibrate
from lfgraph.pattern.design_check import _mirrored, view_order

SIGMA_PX = 0.1  # corner noise of the synthetic observations
SAME_MM = 1e-6  # the swapped streams re-labelled: the calibration of the rightly cabled rig, to round-off


def rig_observations(rows: int = 2, cols: int = 2, seed: int = 0):
    scene = get_scene("small-2x2")
    rng = np.random.default_rng(seed)
    calib = make_rig(dataclasses.replace(scene.rig, rows=rows, cols=cols), rng)
    truth = make_checkerboard_truth(calib, dataclasses.replace(scene.checkerboard, frames=12), rng)
    corners, valid = make_corner_observations(truth, SIGMA_PX, np.random.default_rng(seed + 1))
    return calib, observations_from_arrays(truth.board, calib.grid, calib.image_size_px, corners, valid)


def streams(obs, order):
    """The observations with view i holding the stream of view ``order[i]`` (a wrong cabling)."""
    return dataclasses.replace(obs, corners_px=obs.corners_px[list(order)], valid=obs.valid[list(order)])


@pytest.mark.slow
def test_swapped_cables_are_refused_by_name_and_view_order_repairs_them():
    _, obs = rig_observations()
    swapped = streams(obs, (1, 0, 2, 3))
    with pytest.raises(CalibrationInputError, match=r"r00_c00 and r00_c01 are each calibrated where the grid puts "
                                                    r"the other.*swapped cables"):
        calibrate(swapped)
    fixed, _ = calibrate(view_order(swapped, ["r00_c01", "r00_c00", "r01_c00", "r01_c01"]))
    right, _ = calibrate(obs)
    assert np.max(np.abs(fixed.ref_T_view - right.ref_T_view)) * 1e3 < SAME_MM


def test_a_duplicated_stream_is_refused():
    _, obs = rig_observations()
    with pytest.raises(CalibrationInputError, match=r"r00_c00 and r00_c01 are calibrated at one place.*duplicated"):
        calibrate(streams(obs, (0, 0, 2, 3)))


def test_a_mirrored_stream_is_refused():
    """A mirrored image of a checkerboard is labelled by the detector's own rule: `_mirrored` gives exactly those
    corners (flipping back is the same map)."""
    _, obs = rig_observations()
    with pytest.raises(CalibrationInputError, match=r"view 1 \(r00_c01\): its images are mirrored"):
        calibrate(_mirrored(obs, 1))


def test_a_grid_numbered_the_other_way_round_is_said_not_refused():
    """OpenCV's own OneLine set numbers its line of cameras right to left: a consistent lattice, calibrated."""
    _, obs = rig_observations(1, 3)
    reversed_line = streams(obs, (2, 1, 0))
    calib, report = calibrate(reversed_line)
    assert any("numbered the other way round along its rows" in w for w in report.warnings)
    errors, notes = grid_problems(calib.grid, calib.ref_T_view)
    assert not errors and notes
    assert calib.ref_T_view[1][0, 3] < 0  # really to the left: nothing was re-ordered behind the user's back


@pytest.mark.slow
def test_check_grid_off_accepts_what_the_check_refuses():
    _, obs = rig_observations()
    calib, _ = calibrate(streams(obs, (1, 0, 2, 3)), CalibrateConfig(check_grid=False))
    assert grid_problems(calib.grid, calib.ref_T_view)[0]


@pytest.mark.slow
def test_cli_names_the_swap_and_takes_the_true_order(tmp_path, capsys):
    cb = tmp_path / "cb"
    assert main(["-q", "synth", "checkerboard", str(cb), "--grid", "2x2", "--image-size", "320x240", "--frames", "8",
                 "--board", "7x5", "--square-mm", "15"]) == 0
    for frame in sorted(p for p in cb.iterdir() if p.is_dir()):
        a, b = frame / "r00_c00.png", frame / "r00_c01.png"
        data = a.read_bytes()
        a.write_bytes(b.read_bytes())
        b.write_bytes(data)
    out = tmp_path / "c.json"
    args = ["calibrate", str(cb), "--grid", "2x2", "--board", "7x5", "--square-mm", "15", "--quiet", "-o", str(out)]
    assert main(args) == EXIT_BAD_INPUT
    assert "swapped cables" in capsys.readouterr().err and not out.exists()
    assert main([*args, "--view-order", "r00_c01,r00_c00,r01_c00,r01_c01"]) == 0
    assert main(["evaluate", str(out), "--truth", str(cb / "truth.json"), "--json"]) == 0


@pytest.mark.slow
def test_a_swapped_calibration_is_not_rectified():
    """Issue 42: the swapped capture, calibrated anyway, was rectified with the views ~32 deg off the common
    orientation and a 0.3 mm row pitch, exit 0."""
    from lfgraph.core.errors import RectificationError
    from lfgraph.rectification.rectify import rectify

    _, obs = rig_observations()
    swapped, _ = calibrate(streams(obs, (1, 0, 2, 3)), CalibrateConfig(check_grid=False))
    with pytest.raises(RectificationError, match="contradicts its grid.*swapped cables"):
        rectify(swapped)
