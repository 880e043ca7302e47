"""The fisheye and unified lens models against GTSAM's Cal3Fisheye / Cal3Unified and OpenCV's cv2.fisheye
(independent implementations), their inverses, and what each model refuses."""

import cv2
import numpy as np
import pytest

from lfgraph.core.camera import Intrinsics, undistort_views
from lfgraph.lenses import FISHEYE, RADTAN, UNIFIED

MATCH_PX = 1e-9  # our projection vs GTSAM's / OpenCV's, pixels (both double precision)
ROUND_TRIP = 1e-10  # undistort(project(x)) - x, normalised units

FISH = Intrinsics(600.0, 598.0, 640.0, 480.0, 0.05, -0.01, k3=0.004, k4=-0.0007, lens=FISHEYE)
UNI = Intrinsics(900.0, 905.0, 640.0, 480.0, -0.2, 0.05, 1e-3, -5e-4, xi=0.9, lens=UNIFIED)
RAD = Intrinsics(800.0, 801.0, 640.0, 480.0, -0.2, 0.05, 1e-3, -5e-4)


def _rays(n: int = 400, max_deg: float = 80.0, seed: int = 0) -> np.ndarray:
    """(n, 2) normalised coordinates of rays up to max_deg off the axis."""
    rng = np.random.default_rng(seed)
    theta = np.radians(rng.uniform(0, max_deg, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    return np.tan(theta)[:, None] * np.stack([np.cos(phi), np.sin(phi)], axis=1)


@pytest.mark.parametrize("intr", [FISH, UNI, RAD], ids=lambda i: i.lens)
def test_projection_matches_gtsam(intr):
    xy = _rays(max_deg=70.0 if intr.lens != RADTAN else 35.0)
    cal = intr.to_gtsam()
    expected = np.array([cal.uncalibrate(p) for p in xy])
    np.testing.assert_allclose(intr.project(xy), expected, atol=MATCH_PX, rtol=0)
    assert Intrinsics.from_gtsam(cal) == intr


def test_fisheye_matches_opencv_fisheye():
    xy = _rays(max_deg=80.0)
    pts = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)[None]
    cv_px, _ = cv2.fisheye.projectPoints(pts, np.zeros(3), np.zeros(3), FISH.K, FISH.dist_cv)
    np.testing.assert_allclose(FISH.project(pts[0]), cv_px[0], atol=1e-6, rtol=0)  # OpenCV's output is float64
    cv_xy = cv2.fisheye.undistortPoints(cv_px, FISH.K, FISH.dist_cv,
                                        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14))[0]
    np.testing.assert_allclose(FISH.undistort(cv_px[0]), cv_xy, atol=1e-8, rtol=0)


@pytest.mark.parametrize("intr", [FISH, UNI, RAD], ids=lambda i: i.lens)
def test_undistort_inverts_project(intr):
    xy = _rays(max_deg=75.0 if intr.lens != RADTAN else 35.0)
    back = intr.undistort(intr.project(xy))
    err = np.abs(back - xy) / np.maximum(1.0, np.abs(xy))
    assert np.nanmax(err) < ROUND_TRIP and not np.isnan(back).any()


def test_mixed_lenses_in_one_call_match_each_view():
    px = np.stack([i.project(_rays(50, 60.0 if i.lens != RADTAN else 30.0, seed=s))
                   for s, i in enumerate((RAD, FISH, UNI))])
    both = undistort_views((RAD, FISH, UNI), px)
    for v, intr in enumerate((RAD, FISH, UNI)):
        np.testing.assert_array_equal(both[v], intr.undistort(px[v]))


def test_fisheye_beyond_its_field_is_nan_not_wrong():
    strong = Intrinsics(400.0, 400.0, 500.0, 500.0, -0.3, 0.0, lens=FISHEYE)  # theta_d peaks before 90 deg
    far = strong.undistort(np.array([[500.0 + 400.0 * 1.5, 500.0]]))
    assert np.isnan(far).all()


def test_each_model_refuses_coefficients_it_lacks():
    with pytest.raises(ValueError, match="fisheye lens has no p1"):
        Intrinsics(1, 1, 0, 0, p1=0.1, lens=FISHEYE)
    with pytest.raises(ValueError, match="radtan lens has no k3"):
        Intrinsics(1, 1, 0, 0, k3=0.1)
    with pytest.raises(ValueError, match="xi >= 0"):
        Intrinsics(1, 1, 0, 0, xi=-0.5, lens=UNIFIED)
    with pytest.raises(ValueError, match="lens must be one of"):
        Intrinsics(1, 1, 0, 0, lens="kb8")
    with pytest.raises(ValueError, match="unified lens has no OpenCV"):
        _ = UNI.dist_cv


def test_unified_with_xi_zero_is_radtan():
    same = Intrinsics(RAD.fx, RAD.fy, RAD.cx, RAD.cy, RAD.k1, RAD.k2, RAD.p1, RAD.p2, lens=UNIFIED)
    xy = _rays(max_deg=35.0)
    np.testing.assert_allclose(same.project(xy), RAD.project(xy), atol=MATCH_PX, rtol=0)
