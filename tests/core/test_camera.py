"""Camera model against OpenCV and GTSAM, and its own inverse."""

import cv2
import gtsam
import numpy as np
import pytest

from lfgraph.core.camera import Intrinsics, project_world
from lfgraph.core.geometry import make_T, rotation_from_rotvec

PROJECTION_AGREEMENT_PX = 1e-9  # our project vs OpenCV / GTSAM, pixels
ROUND_TRIP_NORMALISED = 1e-9  # undistort(project(x)) vs x, normalised units (~1e-6 px at f = 1000)
ROUND_TRIP_PX = 1e-9


def _lens(k1: float, k2: float = 0.02, p1: float = 0.0, p2: float = 0.0) -> Intrinsics:
    return Intrinsics(850.0, 853.0, 481.3, 476.9, k1, k2, p1, p2)


def _points(n: int = 500, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-0.4, 0.4, n), rng.uniform(-0.4, 0.4, n), rng.uniform(0.5, 3.0, n)])


@pytest.mark.parametrize("lens", [_lens(-0.25), _lens(0.1, -0.05, 1e-3, -5e-4), _lens(0.0, 0.0)])
def test_project_matches_opencv(lens):
    world = _points()
    view_T_world = make_T(rotation_from_rotvec([0.05, -0.1, 0.2]), [0.01, -0.02, 0.3])  # noqa: N806
    ours = project_world(lens, view_T_world, world)
    rvec, _ = cv2.Rodrigues(view_T_world[:3, :3])
    cv, _ = cv2.projectPoints(world, rvec, view_T_world[:3, 3], lens.K, lens.dist_cv)
    assert np.max(np.abs(ours - cv.reshape(-1, 2))) < PROJECTION_AGREEMENT_PX


@pytest.mark.parametrize("lens", [_lens(-0.25), _lens(0.1, -0.05, 1e-3, -5e-4)])
def test_project_matches_gtsam(lens):
    world = _points(100)
    camera = gtsam.PinholeCameraCal3DS2(gtsam.Pose3(), lens.to_gtsam())
    ref = np.array([camera.project(p) for p in world])
    assert np.max(np.abs(lens.project(world) - ref)) < PROJECTION_AGREEMENT_PX


@pytest.mark.parametrize("k1", [-0.3, -0.1, 0.1, 0.3])
def test_undistort_inverts_project_over_whole_image(k1):
    # f = 1100 px on 960x960: the image corner is at r = 0.62, inside the radius (0.70) where k1 = -0.3 folds.
    lens = Intrinsics(1100.0, 1102.0, 481.3, 476.9, k1, 0.0)
    w, h = 960, 960
    u, v = np.meshgrid(np.linspace(0, w - 1, 61), np.linspace(0, h - 1, 61))
    pixels = np.column_stack([u.ravel(), v.ravel()])
    xy = lens.undistort(pixels)
    assert np.max(np.abs(lens.project(xy) - pixels)) < ROUND_TRIP_PX
    # and the other direction, from normalised points spanning the image
    assert np.max(np.abs(lens.undistort(lens.project(xy)) - xy)) < ROUND_TRIP_NORMALISED


def test_undistort_gives_nan_where_the_lens_has_no_inverse():
    # r(1 - 0.3 r^2) peaks at r_d = 0.703: a pixel at normalised radius 0.8 is beyond what the lens can image.
    lens = Intrinsics(850.0, 850.0, 480.0, 480.0, -0.3, 0.0)
    out = lens.undistort(np.array([[480.0 + 0.8 * 850.0, 480.0], [480.0 + 0.5 * 850.0, 480.0]]))
    assert np.all(np.isnan(out[0])) and np.all(np.isfinite(out[1]))


def test_undistort_matches_opencv():
    lens = _lens(-0.2, 0.05, 5e-4, -2e-4)
    pixels = np.random.default_rng(1).uniform(0, 960, (300, 2))
    cv = cv2.undistortPoints(pixels.reshape(-1, 1, 2), lens.K, lens.dist_cv,
                             criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)).reshape(-1, 2)
    assert np.max(np.abs(lens.undistort(pixels) - cv)) < 1e-7  # OpenCV's own iteration stops near here


def test_conversions_round_trip():
    lens = _lens(-0.2, 0.05, 1e-3, 2e-3)
    assert Intrinsics.from_gtsam(lens.to_gtsam()) == lens
    assert Intrinsics.from_opencv(lens.K, lens.dist_cv) == lens
    assert Intrinsics.from_opencv(lens.K, lens.dist_cv[:4]) == lens
    assert Intrinsics.from_vector(lens.as_vector()) == lens


def test_points_behind_camera_give_nan():
    out = _lens(0.0).project(np.array([[0.0, 0.0, -1.0], [0.1, 0.0, 1.0]]))
    assert np.all(np.isnan(out[0])) and np.all(np.isfinite(out[1]))


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: Intrinsics(-1.0, 1.0, 0.0, 0.0), "positive"),
        (lambda: Intrinsics(1.0, 1.0, float("nan"), 0.0), "finite"),
        (lambda: Intrinsics.from_opencv(np.eye(3), [0.1, 0, 0, 0, 0.01]), "k3"),
        (lambda: Intrinsics.from_opencv([[1, 0.5, 0], [0, 1, 0], [0, 0, 1]]), "skew-free"),
        (lambda: Intrinsics.from_opencv(np.eye(3), [0.1]), "at least 4"),
        (lambda: Intrinsics.from_gtsam(gtsam.Cal3DS2(1, 1, 0.2, 0, 0, 0, 0, 0, 0)), "skew"),
        (lambda: Intrinsics.from_vector([1, 2, 3]), "4, 6 or 8"),
        (lambda: _lens(0.1).project(np.zeros((3, 4))), r"\(N, 2 or 3\)"),
        (lambda: _lens(0.1).undistort(np.zeros(5)), r"\(N, 2\)"),
    ],
)
def test_bad_input_is_rejected(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_a_flag_or_a_string_is_no_focal_length():
    """Issue 42: ``Intrinsics(True, 300, 160, 120)`` was a camera with fx = 1."""
    for bad in (True, "300", None):
        with pytest.raises(TypeError, match="Intrinsics.fx must be a number"):
            Intrinsics(bad, 300.0, 160.0, 120.0)
    assert Intrinsics(np.float32(300), np.int64(300), 160, 120).fx == 300.0  # numpy numbers are numbers
