"""The joint route's robust screen: view-frames the rig cannot explain (a swapped or mis-detected image) are found by a
robust fit and dropped by name before the reported least-squares fit.

A robust fit misses a view-frame for two reasons: the image is bad, or the view-frame is merely weakly constrained
(a view that sees few board positions, the one frame that covers part of a view's image). A Cauchy fit started from
per-view estimates can then settle where that view fits its other frames and gives up on this one, and its residual
under that fit says nothing about the image. So a suspect is judged by what the rest of the rig predicts for it,
with the prediction's uncertainty (`lfgraph.pattern.prediction`): the rig fitted by least squares without the
suspects, the suspect's board pose fitted through its frame's other views, the miss measured in the metric of the
prediction's covariance (`ViewFramePrediction.deflated_rms_px`). A bad image is missed by the rest of the rig as
well; a weakly constrained one lies within what the rest of the rig knows about it and is kept. The frame's other
views are witnesses, and one of them can be off in that frame itself (caliscope's webcam 1, out of sync in 20 of its
48 frames, is kept as a systematic misfit and still placed the board): the suspect is blamed only when the rest
misses it through every `witness_sets` — all the frame's other views, and each of them left out in turn.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from lfgraph.core.observer import Observer
from lfgraph.detect.detections import BoardObservations
from lfgraph.engine.schur_system import NotReducible
from lfgraph.factors.noise import RobustKernel
from lfgraph.pattern.config import CalibrateConfig
from lfgraph.pattern.initial import CalibrationInputError, check_observations, drop_view_frames
from lfgraph.pattern.joint import JointResult, calibrate_joint
from lfgraph.pattern.prediction import predict_view_frame, rig_marginals
from lfgraph.pattern.scoring import rig_residuals, rms_px

SCREEN_KERNEL = RobustKernel("cauchy", 1.0)  # the screening fit's kernel, threshold in px (corner sigma 1 px)
OUTLIER_VIEW_FRAME_FACTOR = 5.0  # a view-frame the robust rig misses by this many times the median view-frame RMS ...
OUTLIER_VIEW_FRAME_MIN_PX = 1.0  # ... and by at least this much is a suspect; dropped when the rest of the rig's
# prediction misses it by as much beyond its own uncertainty (`_judged_by_the_rest`)
SCREEN_MAX_SHARE = 0.25  # ... unless that view would lose more than this share of its view-frames: then the misfit is
# systematic (caliscope's webcams: view 1 missed in 25+ of its ~49 frames, its frames up to 20 ms out of sync), not a
# swapped or mis-detected image; dropping them moved camera 1's fx 11 % and the held-out error 1.272 -> 1.354 px


def witness_sets(helpers: list[int]) -> list[list[int]]:
    """The sets of a frame's other views a suspect is predicted through: all of them and, when there are two or more,
    each with one left out. A suspect is blamed only when every set misses it (`_judged_by_the_rest`): a frame whose
    views disagree because one *other* view is off in it (a webcam out of sync in that frame) is not the suspect's
    fault when the frame's other views predict the suspect well without that one."""
    if len(helpers) < 2:
        return [helpers]
    return [helpers] + [[h for h in helpers if h != left] for left in helpers]


def _judged_by_the_rest(obs: BoardObservations, screen: JointResult, suspects: list[tuple[int, int]],
                        threshold_px: float, config: CalibrateConfig) -> tuple[list[tuple[int, int]], dict]:
    """Which ``suspects`` the rest of the rig misses beyond its uncertainty by more than ``threshold_px``, and each
    suspect's miss (px, `ViewFramePrediction.deflated_rms_px`): the smallest over the `witness_sets` of its frame's
    other views. Where the rest cannot be fitted or its posterior is indeterminate, every suspect is dropped (the
    screen's rule without the judgement)."""
    rest = drop_view_frames(obs, suspects)
    boards = screen.board_T_ref.copy()
    boards[~rest.seen.any(axis=0)] = np.nan
    try:
        check_observations(rest)
        fit = calibrate_joint(rest, screen.intrinsics, screen.ref_T_view, boards,
                              dataclasses.replace(config, marginals=False))
        marginals = rig_marginals(rest, fit.intrinsics, fit.ref_T_view, fit.board_T_ref, fit.object_points_m, config)
    except (CalibrationInputError, NotReducible, RuntimeError, np.linalg.LinAlgError):
        return suspects, {}
    misses = {}
    for v, f in suspects:
        helpers = [int(h) for h in np.nonzero(rest.seen[:, f])[0]] or \
            [int(h) for h in np.nonzero(obs.seen[:, f])[0] if h != v]
        misses[v, f] = min(predict_view_frame(obs, fit.intrinsics, fit.ref_T_view, marginals, v, f, w,
                                              max(fit.noise_sigma_px, 1e-6), screen.board_T_ref[f]).deflated_rms_px
                           for w in witness_sets(helpers))
    return [p for p in suspects if misses[p] > threshold_px], misses


def screen_view_frames(obs: BoardObservations, intrinsics: tuple, ref_T_view: np.ndarray,  # noqa: N803
                       board_T_ref: np.ndarray, config: CalibrateConfig, say: Observer  # noqa: N803
                       ) -> tuple[BoardObservations, tuple, np.ndarray, np.ndarray, list[str], int]:
    """The robust screening fit (`SCREEN_KERNEL`, no marginals), its suspects, and those the rest of the rig cannot
    explain either (`_judged_by_the_rest`).

    Returns:
        the observations without the dropped view-frames, the start of the final fit — the robust fit's intrinsics,
        poses and board poses (NaN for frames no view sees any more) when it dropped any, else the start it was
        given (the screen then changes nothing: the default is ``screen=False``'s fit) —, one warning per dropped
        view-frame, and the robust fit's iterations.
    """
    screen = calibrate_joint(obs, intrinsics, ref_T_view, board_T_ref,
                             dataclasses.replace(config, robust=SCREEN_KERNEL, marginals=False))
    res = rig_residuals(screen.intrinsics, screen.ref_T_view, screen.board_T_ref, obs, screen.object_points_m)
    vf = np.asarray(rms_px(res, axis=2))
    median = float(np.nanmedian(vf))
    threshold = max(OUTLIER_VIEW_FRAME_FACTOR * median, OUTLIER_VIEW_FRAME_MIN_PX)
    with np.errstate(invalid="ignore"):
        bad = vf > threshold
    systematic = bad.sum(axis=1) > SCREEN_MAX_SHARE * obs.seen.sum(axis=1)
    messages = [f"{obs.describe(int(v))}: the robust rig misses its board in {int(bad[v].sum())} of "
                f"{int(obs.seen[v].sum())} frames by more than {OUTLIER_VIEW_FRAME_FACTOR:g}x the median view-frame: a "
                f"systematic misfit (frames out of sync, a rolling shutter, a lens model that does not fit), not bad "
                f"images: kept" for v in np.nonzero(systematic)[0]]
    bad[systematic] = False
    suspects = [(int(v), int(f)) for v, f in zip(*np.nonzero(bad), strict=True)]
    pairs, misses = _judged_by_the_rest(obs, screen, suspects, threshold, config) if suspects else ([], {})
    for v, f in suspects:
        if (v, f) not in pairs:
            say.log(f"{obs.describe(v, f)}: the robust rig misses its board by {vf[v, f]:.2f} px RMS, but the rest of "
                    f"the rig predicts it (miss beyond its uncertainty {misses[v, f]:.2f} px): a weakly constrained "
                    f"view-frame, or another view off in that frame, kept")
    messages += [f"{obs.describe(v, f)}: the rig misses its board by {vf[v, f]:.2f} px RMS (the median view-frame: "
                 f"{median:.2f} px)" + (f", the rest of the rig by {misses[v, f]:.2f} px beyond its uncertainty"
                                        if (v, f) in misses else "")
                 + ": dropped from the calibration (a swapped or mis-detected image?)" for v, f in pairs]
    for m in messages:
        say.log(m)
    if not pairs:  # nothing to drop: the screen changes nothing, not even the start (the least-squares fit has flat
        # directions, a weak view's distortion where it never saw the board: from the robust fit's end it stopped
        # elsewhere in them, and caliscope's camera 3 predicted a board position no frame showed it 49 px off, 7.9 px
        # from the route's start)
        return obs, intrinsics, ref_T_view, board_T_ref, messages, screen.optimization.iterations
    boards = screen.board_T_ref.copy()
    obs = drop_view_frames(obs, pairs)
    check_observations(obs)
    boards[~obs.seen.any(axis=0)] = np.nan
    return obs, screen.intrinsics, screen.ref_T_view, boards, messages, screen.optimization.iterations
