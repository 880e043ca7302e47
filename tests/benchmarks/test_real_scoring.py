"""The real-data benchmark's scoring (benchmarks/real.py) on synthetic corners with a known truth."""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from lfgraph.datasets.checkerboard import make_checkerboard_truth, make_corner_observations
from lfgraph.datasets.rig import make_rig
from lfgraph.datasets.scenes import get_scene
from lfgraph.detect.detections import observations_from_arrays

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "real.py"
_SPEC = importlib.util.spec_from_file_location("real_bench", _PATH)
real = importlib.util.module_from_spec(_SPEC)
sys.modules["real_bench"] = real  # dataclasses look their module up
_SPEC.loader.exec_module(real)

NOISE_PX = 0.2  # per coordinate


def small_rig(sigma_px: float):
    scene = get_scene("small-2x2")
    rng = np.random.default_rng(7)
    calib = make_rig(scene.rig, rng)
    truth = make_checkerboard_truth(calib, scene.checkerboard, rng)
    corners, valid = make_corner_observations(truth, sigma_px, np.random.default_rng(8))
    return calib, observations_from_arrays(truth.board, calib.grid, calib.image_size_px, corners, valid)


def test_rig_fit_residuals_of_the_true_rig_are_the_noise():
    calib, obs = small_rig(0.0)
    res = real.rig_fit_residuals(calib, obs)
    assert np.nanmax(np.abs(res)) < 1e-6


@pytest.mark.slow
@pytest.mark.parametrize("solver", ["lf", "cv"])
def test_lofo_is_the_prediction_error(solver):
    """Noise-free corners are predicted exactly; noisy ones no better than the noise (Euclidean RMS = sqrt(2)
    sigma): the held-out frame took no part in the calibration. The joint graph stays near that floor
    (calibrateMultiview, intrinsics frozen after per-camera Zhang on 7 frames, does not)."""
    _, clean = small_rig(0.0)
    folds = real.lofo_folds(clean, clean, 4)
    assert len(folds) == 4
    rms, per_fold = real.lofo(real.SOLVERS[solver], clean, folds)
    assert rms < 1e-3 and per_fold.shape == (4,)
    _, noisy = small_rig(NOISE_PX)
    rms, _ = real.lofo(real.SOLVERS[solver], noisy, folds)
    assert rms > np.sqrt(2) * NOISE_PX * 0.8
    if solver == "lf":
        assert rms < np.sqrt(2) * NOISE_PX * 1.5


def test_missing_data_is_skipped(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr("sys.argv", ["real.py", "--data", str(tmp_path / "absent")])
    assert real.main() == 0
    assert "skipping" in capsys.readouterr().out
