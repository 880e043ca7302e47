"""The depth-error command against the paper's printed numbers (Section 5.1)."""

import json

import cv2
import numpy as np
import pytest

from lfgraph.cli import main
from lfgraph.judge.depth import depth_error_m

PAPER_F_PX, PAPER_B_M, PAPER_E_PX = 850.0, 0.018, 0.246
PRINTED_UNIT_M = 0.001  # the paper prints 0.004 and 0.065: one unit of the last printed digit


def test_matches_the_papers_numbers():
    near, far = depth_error_m(PAPER_F_PX, PAPER_B_M, PAPER_E_PX, np.array([0.5, 2.0]))
    assert round(near, 3) == 0.004
    # 0.0644 m: the paper's 0.065 is within one unit of its last digit (it rounds to 0.064; reported in the note)
    assert abs(far - 0.065) <= PRINTED_UNIT_M
    # the printed formula (a sum) would give twice the depth, not an error
    d = PAPER_F_PX * PAPER_B_M / 2.0
    assert PAPER_F_PX * PAPER_B_M / (d - PAPER_E_PX) + PAPER_F_PX * PAPER_B_M / (d + PAPER_E_PX) == pytest.approx(
        4.0, rel=0.01)


def test_properties_and_errors():
    z = np.linspace(0.3, 5.0, 20)
    e = depth_error_m(800.0, 0.1, 0.2, z)
    assert np.all(np.diff(e) > 0)  # grows with depth
    np.testing.assert_allclose(e, z**2 * 0.2 / (800.0 * 0.1), rtol=0.01)  # first-order Z^2 E / (f b)
    assert np.all(depth_error_m(800.0, 0.1, 0.0, z) == 0)
    assert np.isinf(depth_error_m(100.0, 0.01, 2.0, 1.0))  # the error swallows the 1 px disparity
    with pytest.raises(ValueError):
        depth_error_m(0.0, 0.1, 0.2, 1.0)
    with pytest.raises(ValueError):
        depth_error_m(800.0, 0.1, -0.1, 1.0)


def test_cli_json_and_plot(tmp_path, capsys):
    png = tmp_path / "de.png"
    assert main(["depth-error", "--focal-px", "850", "--baseline-m", "0.018", "--error-px", "0.246",
                 "--range-m", "0.5", "2.0", "--json", "--plot", str(png)]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["depth_m"][0] == 0.5 and data["depth_m"][-1] == 2.0
    assert round(data["depth_error_m"][0], 3) == 0.004
    img = cv2.imread(str(png))
    assert img is not None and img.shape[0] > 100
    assert png.with_suffix(".pdf").read_bytes().startswith(b"%PDF")
    with pytest.raises(SystemExit):
        main(["depth-error", "--focal-px", "850", "--baseline-m", "0.018", "--error-px", "0.246",
              "--range-m", "2.0", "0.5"])
