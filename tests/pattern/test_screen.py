"""The robust screen judges a suspect view-frame by what the rest of the rig predicts for it, with its uncertainty."""

import dataclasses

import numpy as np

from lfgraph.core.geometry import invert_T
from lfgraph.datasets.checkerboard import make_checkerboard_truth, make_corner_observations
from lfgraph.datasets.rig import make_rig
from lfgraph.datasets.scenes import get_scene
from lfgraph.detect.detections import observations_from_arrays
from lfgraph.pattern import CalibrateConfig
from lfgraph.pattern.initial import drop_view_frames
from lfgraph.pattern.joint import calibrate_joint
from lfgraph.pattern.prediction import predict_view_frame, rig_marginals
from lfgraph.pattern.screen import OUTLIER_VIEW_FRAME_MIN_PX, SCREEN_KERNEL, _judged_by_the_rest, witness_sets

SIGMA_PX = 0.1  # corner noise
WEAK_FRAMES = 2  # the weak view sees the board in this many frames
PREDICTED_RMS_REL = 1.5  # a good view-frame's held-out miss within this factor of its predicted RMS (Cramér–Rao)


def _rig_with_a_weak_view():
    """small-2x2, 16 frames, view 2 keeping only its first `WEAK_FRAMES` frames; the truth and the observations."""
    scene = get_scene("small-2x2")
    rng = np.random.default_rng(0)
    calib = make_rig(scene.rig, rng)
    truth = make_checkerboard_truth(calib, dataclasses.replace(scene.checkerboard, frames=16), rng)
    corners, valid = make_corner_observations(truth, SIGMA_PX, np.random.default_rng(1))
    seen = np.nonzero(valid[2].any(axis=1))[0]
    valid[2, seen[WEAK_FRAMES:]] = False
    corners[~valid] = np.nan
    obs = observations_from_arrays(truth.board, calib.grid, calib.image_size_px, corners, valid)
    return calib, truth, obs, int(seen[0])


def _robust_fit(calib, truth, obs):
    boards = invert_T(truth.ref_T_board)
    boards[~obs.seen.any(axis=0)] = np.nan
    return calibrate_joint(obs, calib.intrinsics, calib.ref_T_view, boards,
                           CalibrateConfig(robust=SCREEN_KERNEL, marginals=False))


def test_a_weak_views_good_frame_is_kept_and_a_swapped_one_dropped():
    """Suspects are judged by the rest of the rig: a good frame of a view that saw the board twice (the rest then
    knows that view from one frame and its intrinsics prior) lies within the prediction's uncertainty and is kept;
    a view-frame holding another view's board (a swap) is missed by the rest of the rig and dropped."""
    calib, truth, obs, weak_frame = _rig_with_a_weak_view()
    corners = np.array(obs.corners_px)
    swapped_frame = int(np.nonzero(obs.seen[0] & obs.seen[1] & obs.seen[3])[0][-1])
    corners[1, swapped_frame] = obs.corners_px[0, swapped_frame]
    obs = dataclasses.replace(obs, corners_px=corners)
    screen = _robust_fit(calib, truth, obs)
    suspects = [(2, weak_frame), (1, swapped_frame)]
    dropped, misses = _judged_by_the_rest(obs, screen, suspects, OUTLIER_VIEW_FRAME_MIN_PX, CalibrateConfig())
    assert dropped == [(1, swapped_frame)], misses
    assert misses[2, weak_frame] < OUTLIER_VIEW_FRAME_MIN_PX < misses[1, swapped_frame]


def test_a_held_out_weak_frame_is_predicted_within_its_cramer_rao_rms():
    """The prediction's covariance is honest: the weak view's held-out frame misses the truth-generated corners by
    about the RMS its covariance predicts (the view's and the other views' joint posterior, the board pose's fit,
    the corner noise), not by the corner noise alone."""
    calib, truth, obs, weak_frame = _rig_with_a_weak_view()
    rest = drop_view_frames(obs, [(2, weak_frame)])
    boards = invert_T(truth.ref_T_board)
    boards[~rest.seen.any(axis=0)] = np.nan
    fit = calibrate_joint(rest, calib.intrinsics, calib.ref_T_view, boards, CalibrateConfig(marginals=False))
    marginals = rig_marginals(rest, fit.intrinsics, fit.ref_T_view, fit.board_T_ref, fit.object_points_m,
                              CalibrateConfig())
    helpers = [int(h) for h in np.nonzero(rest.seen[:, weak_frame])[0]]
    pred = predict_view_frame(obs, fit.intrinsics, fit.ref_T_view, marginals, 2, weak_frame, helpers, SIGMA_PX,
                              invert_T(truth.ref_T_board[weak_frame]))
    assert pred.predicted_rms_px > 1.5 * np.sqrt(2) * SIGMA_PX  # the rig's uncertainty counts, not only the noise
    assert pred.rms_px < PREDICTED_RMS_REL * pred.predicted_rms_px


OFF_SYNC_SHIFT_PX = 4.0  # one other view of the suspect's frame is off by this much (out of sync in that frame)


def test_a_good_frame_is_not_blamed_for_another_views_miss():
    """A frame whose views disagree because one *other* view is off in it (caliscope's webcam 1, out of sync in 20 of
    its 48 frames and kept as a systematic misfit, still places the board in frame sync54) does not condemn a good
    view-frame of it: predicted through all the frame's other views, the good one is missed beyond the threshold;
    through the witnesses without the off view it is not, and it is kept. The off view-frame itself, judged as a
    suspect, is dropped: every set of witnesses misses it."""
    calib, truth, obs, _ = _rig_with_a_weak_view()
    frame = int(np.nonzero(obs.seen[0] & obs.seen[1] & obs.seen[3] & ~obs.seen[2])[0][0])  # views 0, 1 and 3
    corners = np.array(obs.corners_px)
    corners[1, frame] += OFF_SYNC_SHIFT_PX
    obs = dataclasses.replace(obs, corners_px=corners)
    screen = _robust_fit(calib, truth, obs)
    config = CalibrateConfig()
    dropped, misses = _judged_by_the_rest(obs, screen, [(3, frame)], OUTLIER_VIEW_FRAME_MIN_PX, config)
    assert dropped == [] and misses[3, frame] < OUTLIER_VIEW_FRAME_MIN_PX, misses
    # the judgement through all the other views at once (the rule before the witness sets) would have dropped it
    rest = drop_view_frames(obs, [(3, frame)])
    boards = invert_T(truth.ref_T_board)
    fit = calibrate_joint(rest, screen.intrinsics, screen.ref_T_view, boards, CalibrateConfig(marginals=False))
    marginals = rig_marginals(rest, fit.intrinsics, fit.ref_T_view, fit.board_T_ref, fit.object_points_m, config)
    everyone = predict_view_frame(obs, fit.intrinsics, fit.ref_T_view, marginals, 3, frame, witness_sets([0, 1])[0],
                                  fit.noise_sigma_px, boards[frame])
    assert everyone.deflated_rms_px > OUTLIER_VIEW_FRAME_MIN_PX
    dropped, misses = _judged_by_the_rest(obs, screen, [(1, frame)], OUTLIER_VIEW_FRAME_MIN_PX, config)
    assert dropped == [(1, frame)], misses
