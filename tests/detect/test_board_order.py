"""Corner order of boards that look the same turned by 180°, decided from the rig's geometry."""

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from lfgraph.core.grid import ViewGrid
from lfgraph.datasets.checkerboard import make_checkerboard_truth, make_corner_observations
from lfgraph.datasets.rig import make_rig
from lfgraph.datasets.scenes import get_scene
from lfgraph.detect.board import BoardSpec
from lfgraph.detect.board_order import (
    ALONE,
    AMBIGUOUS,
    ANCHOR,
    DECIDED,
    UNLINKED,
    UNSEEN,
    flip_transform,
    order_symmetric_boards,
)
from lfgraph.detect.chessboard import detect_board
from lfgraph.detect.detections import BoardObservations, observations_from_arrays

TRINOCULAR = Path(__file__).resolve().parents[1] / "data" / "trinocular"
TRINOCULAR_FRAMES = (1, 6, 11, 16, 21)
TRINOCULAR_BOARD = BoardSpec(13, 9, 0.01)  # ECoCheck 14x10 squares; unit squares (no physical size published)
TRINOCULAR_SIZE = (1224, 1024)
SYMMETRIC = BoardSpec(11, 7, 0.020)  # 12x8 squares: the same turned by 180°
SIGMA_PX = 0.1
STEREO_CONSISTENT_PX = 0.5  # OpenCV's stereo RMS on these 5 frames with a consistent order (0.19-0.31 px measured)
STEREO_REVERSED_PX = 10.0  # ... and with one side's order reversed in some frames (hundreds of px)
FLIP_EXACT = 1e-12


def _symmetric_rig(frames: int = 12, seed: int = 0) -> tuple[BoardObservations, np.ndarray]:
    """Noisy synthetic observations of a 2x2 rig with a symmetric board, and the true corners (NaN where unseen)."""
    scene = get_scene("small-2x2")
    rng = np.random.default_rng(seed)
    calib = make_rig(scene.rig, rng)
    truth = make_checkerboard_truth(calib, dataclasses.replace(scene.checkerboard, frames=frames, board=SYMMETRIC),
                                    rng)
    corners, valid = make_corner_observations(truth, SIGMA_PX, np.random.default_rng(seed + 1))
    return observations_from_arrays(SYMMETRIC, calib.grid, calib.image_size_px, corners, valid), corners


def _reversed(obs: BoardObservations, which: np.ndarray) -> BoardObservations:
    corners = obs.corners_px.copy()
    corners[which] = corners[which][:, ::-1]
    valid = obs.valid.copy()
    valid[which] = valid[which][:, ::-1]
    return dataclasses.replace(obs, corners_px=corners, valid=valid)


def _consistent_per_frame(ordered: BoardObservations, true_corners: np.ndarray) -> bool:
    """Every frame's corners equal the truth in every view, or the truth reversed in every view (the free choice)."""
    for f in range(ordered.num_frames):
        views = np.nonzero(ordered.seen[:, f])[0]
        got, want = ordered.corners_px[views, f], true_corners[views, f]
        if not (np.allclose(got, want) or np.allclose(got, want[:, ::-1])):
            return False
    return True


def test_flip_maps_corner_j_to_its_opposite():
    obj = SYMMETRIC.object_points()
    flip = flip_transform(SYMMETRIC.cols, SYMMETRIC.rows, SYMMETRIC.square_m)
    np.testing.assert_allclose(obj @ flip[:3, :3].T + flip[:3, 3], obj[::-1], atol=FLIP_EXACT)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_reversals_are_undone(seed):
    obs, true_corners = _symmetric_rig(seed=seed)
    scramble = np.random.default_rng(100 + seed).random(obs.seen.shape) < 0.5
    assert not _consistent_per_frame(_reversed(obs, scramble & obs.seen), true_corners)
    ordered, report = order_symmetric_boards(_reversed(obs, scramble & obs.seen))
    assert _consistent_per_frame(ordered, true_corners)
    assert report.messages == () and not report.undecidable.any()
    shared = obs.seen.sum(axis=0) >= 2
    assert np.all(np.isin(report.status[:, shared][obs.seen[:, shared]], [ANCHOR, DECIDED]))
    assert np.all(report.status[:, ~shared][obs.seen[:, ~shared]] == ALONE)
    assert np.all(report.status[~obs.seen] == UNSEEN)


def test_whole_view_reversed_is_undone():
    obs, true_corners = _symmetric_rig()
    which = np.zeros(obs.seen.shape, dtype=bool)
    which[2] = obs.seen[2]  # a camera mounted upside down: its detector reverses every frame
    ordered, report = order_symmetric_boards(_reversed(obs, which))
    assert _consistent_per_frame(ordered, true_corners)
    assert report.messages == ()


def test_view_without_two_shared_frames_is_undecidable():
    obs, true_corners = _symmetric_rig()
    valid = obs.valid.copy()
    both = np.nonzero(obs.seen[3] & obs.seen[0])[0]
    valid[3, both[1:]] = False  # view 3 keeps a single frame shared with the others
    valid[3, ~obs.seen[0]] = False
    lonely = dataclasses.replace(obs, valid=valid, corners_px=np.where(valid[..., None], obs.corners_px, np.nan))
    assert (lonely.seen[3] & lonely.seen[[0, 1, 2]].any(axis=0)).sum() == 1
    ordered, report = order_symmetric_boards(lonely)
    assert np.all(report.status[3][lonely.seen[3]] == UNLINKED)
    assert report.undecidable[3].sum() == 1 and len(report.messages) == 1 and "view 3" in report.messages[0]
    np.testing.assert_array_equal(ordered.corners_px[3], lonely.corners_px[3])  # left as detected
    assert _consistent_per_frame(ordered.subset_frames(np.nonzero(~lonely.seen[3])[0]),
                                 true_corners[:, ~lonely.seen[3]])


def test_static_board_is_undecidable():
    """The board never moves: the reversed hypotheses agree as well as the true ones, nothing can be decided."""
    obs, _ = _symmetric_rig()
    f0 = int(np.nonzero(obs.seen.all(axis=0))[0][0])
    rng = np.random.default_rng(5)
    corners = np.repeat(obs.corners_px[:, f0 : f0 + 1], 6, axis=1)
    corners = corners + SIGMA_PX * rng.standard_normal(corners.shape)
    static = observations_from_arrays(SYMMETRIC, obs.grid, obs.image_size_px, corners, np.isfinite(corners[..., 0]))
    _, report = order_symmetric_boards(static)
    assert report.undecidable[1:].all() and len(report.messages) == obs.num_views - 1


def test_asymmetric_board_is_left_alone():
    obs, _ = _symmetric_rig()
    board = BoardSpec(11, 8, 0.020)
    corners = np.concatenate([obs.corners_px, np.full(obs.corners_px.shape[:2] + (11, 2), np.nan)], axis=2)
    valid = np.concatenate([obs.valid, np.zeros(obs.valid.shape[:2] + (11,), dtype=bool)], axis=2)
    asym = observations_from_arrays(board, obs.grid, obs.image_size_px, corners, valid)
    ordered, report = order_symmetric_boards(asym)
    assert ordered is asym and not report.reversed.any()


# --------------------------------------------------------------------------------------------- real data
@pytest.fixture(scope="module")
def trinocular() -> BoardObservations:
    corners = np.full((3, len(TRINOCULAR_FRAMES), TRINOCULAR_BOARD.num_corners, 2), np.nan)
    for v, name in enumerate(("left", "middle", "right")):
        for f, n in enumerate(TRINOCULAR_FRAMES):
            found = detect_board(cv2.imread(str(TRINOCULAR / name / f"{name}{n}.jpg"), cv2.IMREAD_GRAYSCALE),
                                 TRINOCULAR_BOARD)
            assert found is not None, f"{name}{n}.jpg"
            corners[v, f] = found
    return BoardObservations(TRINOCULAR_BOARD, ViewGrid(1, 3), TRINOCULAR_SIZE, corners,
                             np.ones(corners.shape[:3], dtype=bool), tuple(str(n) for n in TRINOCULAR_FRAMES))


def _stereo_rms_px(obs: BoardObservations) -> list[float]:
    """OpenCV's own rig check: per-view calibrateCamera, then stereoCalibrate of each pair on the same corners."""
    obj = [obs.board.object_points().astype(np.float32)] * obs.num_frames
    pts = [[obs.corners_px[v, f].astype(np.float32) for f in range(obs.num_frames)] for v in range(obs.num_views)]
    cams = [cv2.calibrateCamera(obj, pts[v], obs.image_size_px, None, None,
                                flags=cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST)[1:3] for v in range(3)]
    return [cv2.stereoCalibrate(obj, pts[a], pts[b], *cams[a], *cams[b], obs.image_size_px,
                                flags=cv2.CALIB_FIX_INTRINSIC)[0] for a, b in ((0, 1), (0, 2), (1, 2))]


def test_trinocular_order_is_restored(trinocular):
    which = np.zeros((3, len(TRINOCULAR_FRAMES)), dtype=bool)
    which[2] = True  # the right view reversed throughout (the 184 px case) ...
    which[1, 2] = True  # ... and one middle frame
    scrambled = _reversed(trinocular, which)
    assert min(_stereo_rms_px(scrambled)) > STEREO_REVERSED_PX
    ordered, report = order_symmetric_boards(scrambled)
    assert report.messages == () and not report.undecidable.any()
    assert max(_stereo_rms_px(ordered)) < STEREO_CONSISTENT_PX
    assert _consistent_per_frame(ordered, trinocular.corners_px)


def test_mis_detected_board_is_reported_not_guessed():
    obs, true_corners = _symmetric_rig()
    full = np.nonzero(obs.seen.all(axis=0))[0]
    f_bad, f_other = int(full[0]), int(full[-1])
    corners = obs.corners_px.copy()
    corners[1, f_bad] = obs.corners_px[1, f_other]  # view 1 reports another frame's board in this frame
    bad = dataclasses.replace(obs, corners_px=corners)
    ordered, report = order_symmetric_boards(bad)
    assert report.status[1, f_bad] == AMBIGUOUS and report.undecidable.sum() == 1
    assert len(report.messages) == 1 and f"frame {obs.frame_names[f_bad]}" in report.messages[0]
    np.testing.assert_array_equal(ordered.corners_px[1, f_bad], corners[1, f_bad])
    rest = np.setdiff1d(np.arange(obs.num_frames), [f_bad])
    assert _consistent_per_frame(ordered.subset_frames(rest), true_corners[:, rest])
