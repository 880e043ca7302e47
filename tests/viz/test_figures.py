"""matplotlib figures: spread over seeds, distinguishable series, log axes across decades, legend outside the data,
units on the axes; the calibration report written by ``calibrate --plots``."""

import cv2
import numpy as np
import pytest
from matplotlib.collections import PolyCollection

from lfgraph.cli import main
from lfgraph.viz.figures import (
    make_calibration_figure,
    make_depth_error_figure,
    make_shake_figure,
    spread,
    style,
)

SEEDS = 3


def shake_rows(identical: bool = False):
    """Two configurations x three levels x SEEDS seeds; ``identical``: both configurations give the same numbers."""
    rows = []
    for stages in ("paper", "default"):
        for level, rot in enumerate((0.0, 0.5, 1.0)):
            for seed in range(SEEDS):
                scale = 1.0 if identical or stages == "paper" else 0.01  # default: a hundred times better
                value = (0.01 + rot) * scale * (1 + 0.1 * seed)
                rows.append({"config": f"{stages} / none", "stages": stages, "robust": "none", "level": level,
                             "rot_deg": rot, "seed": seed, "transfer_px": value, "rot_err_deg": value,
                             "rms_after_px": 0.1 + 0.01 * seed,
                             "transfer_before_px": 1 + rot, "rot_err_before_deg": rot})
    return rows


def test_spread_is_median_and_range_over_seeds():
    (xs, med, lo, hi, n), = [v for k, v in spread(shake_rows(), ("stages",), "rot_deg", "transfer_px").items()
                             if k == ("paper",)]
    np.testing.assert_allclose(xs, [0.0, 0.5, 1.0])
    np.testing.assert_allclose(med, (0.01 + xs) * 1.1)
    np.testing.assert_allclose(lo, 0.01 + xs)
    np.testing.assert_allclose(hi, (0.01 + xs) * 1.2)
    assert n == SEEDS


def test_series_styles_are_distinct():
    styles = {(style(k)["marker"], style(k)["linestyle"], style(k)["markerfacecolor"]) for k in range(8)}
    assert len(styles) == 8


def legend_right_of_axes(fig) -> bool:
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    legend = fig.legends[0].get_window_extent(renderer)
    return all(legend.x0 >= ax.get_window_extent(renderer).x1 for ax in fig.axes)


def test_shake_figure():
    fig = make_shake_figure(shake_rows())
    transfer, rot, rms = fig.axes
    assert transfer.get_yscale() == "log"  # errors span decades
    zero = [{**r, "transfer_px": 0.0} if r["rot_deg"] == 0 else r for r in shake_rows()]
    assert make_shake_figure(zero).axes[0].get_yscale() == "symlog"  # no shake, no error: zero stays on the axis
    assert rms.get_yscale() == "linear"  # 0.1..0.12 px
    assert "(px)" in transfer.get_ylabel() and "(deg)" in rot.get_ylabel() and "(deg" in transfer.get_xlabel()
    assert sum(isinstance(c, PolyCollection) for c in rms.collections) == 2  # one spread band per configuration
    assert legend_right_of_axes(fig)


def test_identical_series_both_visible():
    fig = make_shake_figure(shake_rows(identical=True))
    lines = [ln for ln in fig.axes[2].get_lines() if ln.get_label().endswith("/ none")]
    assert len(lines) == 2
    np.testing.assert_allclose(lines[0].get_ydata(), lines[1].get_ydata())  # same data...
    assert (lines[0].get_marker(), lines[0].get_linestyle(), lines[0].get_markerfacecolor()) != \
        (lines[1].get_marker(), lines[1].get_linestyle(), lines[1].get_markerfacecolor())  # ...drawn differently


def test_calibration_figure():
    rows = [{"method": m, "frames": f, "sigma_px": s, "seed": seed, "fx_err_px": k * s / f * (1 + seed),
             "pos_err_mm": 0.1 * k, "rot_err_deg": 0.01 * k * s}
            for k, m in enumerate(("paper", "joint", "cramer-rao"), 1) for f in (5, 50) for s in (0.1, 1.0)
            for seed in range(SEEDS)]
    fig = make_calibration_figure(rows)
    assert len(fig.axes) == 2 * 3  # one row per noise level
    assert fig.axes[0].get_yscale() == "log"
    assert fig.axes[1].get_ylabel() == "view position error (mm)"
    assert legend_right_of_axes(fig)


def test_depth_error_figure():
    z = np.linspace(0.5, 5.0, 20)
    e = z**2 * 0.25 / (850 * 0.018)
    fig = make_depth_error_figure(z, e, 850.0, 0.018, 0.25)
    ax = fig.axes[0]
    assert ax.get_yscale() == "log" and ax.get_ylabel() == "depth error (mm)" and ax.get_xlabel() == "depth Z (m)"
    np.testing.assert_allclose(ax.get_lines()[0].get_ydata(), 1e3 * e)


@pytest.fixture(scope="module")
def board_capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("fig") / "small"
    assert main(["synth", "checkerboard", str(out), "--scene", "small-2x2", "--frames", "6", "--jobs", "2",
                 "--quiet", "--seed", "3"]) == 0
    return out


@pytest.mark.slow
def test_calibrate_plots(board_capture, tmp_path):
    plots = tmp_path / "report"
    assert main(["calibrate", str(board_capture), "--grid", "2x2", "--board", "7x5", "--square-mm", "15", "--quiet",
                 "-o", str(tmp_path / "c.json"), "--plots", str(plots)]) == 0
    for name in ("coverage", "residuals", "frame_rms", "grid_deviation"):
        img = cv2.imread(str(plots / f"{name}.png"))
        assert img is not None and min(img.shape[:2]) > 200
        assert len(np.unique(img.reshape(-1, 3), axis=0)) > 10  # something was drawn
        assert (plots / f"{name}.pdf").read_bytes().startswith(b"%PDF")


def test_calibrate_plots_must_be_a_folder(board_capture, tmp_path):
    not_a_folder = tmp_path / "file.txt"
    not_a_folder.write_text("x")
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", str(board_capture), "--grid", "2x2", "--board", "7x5", "--square-mm", "15", "--quiet",
              "-o", str(tmp_path / "c.json"), "--plots", str(not_a_folder)])
    assert exc.value.code == 2
