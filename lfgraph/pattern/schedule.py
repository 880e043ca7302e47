"""Calibrate's joint route on the one stage schedule (`lfgraph.engine.schedule`), as refine and calibrate-scene run
theirs: every board corner of every frame is a track whose landmark is that corner in the reference frame (the frame's
board pose applied to the printed corner), so each stage is recorded, reported to the observer and logged the same
way. Two steps: the robust screen (`lfgraph.pattern.screen.screen_view_frames`: calibrate's outlier rule, judged per
view-frame, not per track — a swapped image spoils a whole view-frame) and the least-squares joint graph
(`lfgraph.pattern.joint.calibrate_joint`, the reported fit). The track mismatch rule is off for both: a board's
corners are not matched, they are detected."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.observer import Observer
from lfgraph.detect.detections import BoardObservations
from lfgraph.engine.schedule import StageRecord, Step, TrackState, run_schedule
from lfgraph.pattern.config import CalibrateConfig
from lfgraph.pattern.joint import JointResult, calibrate_joint
from lfgraph.pattern.screen import screen_view_frames


@dataclass(frozen=True)
class BoardRun:
    """What calibrate's steps carry: the observations (without the view-frames the screen dropped), the rig and board
    poses the next step starts from, the joint fit once it ran, and one warning per dropped view-frame."""
    obs: BoardObservations
    intrinsics: tuple
    ref_T_view: np.ndarray
    board_T_ref: np.ndarray
    joint: JointResult | None = None
    dropped: tuple[str, ...] = ()

    def subset(self, keep: np.ndarray) -> BoardRun:
        """Itself: the steps drop view-frames, never corners (the schedule's mismatch rule is off)."""
        if not np.all(keep):
            raise ValueError("calibrate's schedule drops view-frames (the screen), not single corners")
        return self


def board_state(run: BoardRun) -> TrackState:
    """``run`` as the schedule's state: (V, F*C) corner tracks, their landmarks the board's corners (the joint fit's
    when it ran, else as printed) in the reference frame through each frame's board pose (NaN where no view sees the
    frame)."""
    obs = run.obs
    n_views, n_frames, n_corners = obs.valid.shape
    calib = Calibration(obs.grid, obs.image_size_px, tuple(run.intrinsics), np.asarray(run.ref_T_view), None, {},
                        obs.view_image_sizes_px)
    corners = obs.board.object_points() if run.joint is None else run.joint.object_points_m
    ref_T_board = np.linalg.inv(np.where(np.isfinite(run.board_T_ref), run.board_T_ref, np.eye(4)))  # noqa: N806
    points = np.einsum("fij,cj->fci", ref_T_board[:, :3, :3], corners) + ref_T_board[:, None, :3, 3]
    points[~np.all(np.isfinite(run.board_T_ref), axis=(1, 2))] = np.nan
    valid = obs.valid.reshape(n_views, n_frames * n_corners)
    return TrackState.start(calib, obs.corners_px.reshape(n_views, n_frames * n_corners, 2), valid,
                            points.reshape(n_frames * n_corners, 3), run)


def joint_schedule(run: BoardRun, config: CalibrateConfig, screens: bool, say: Observer) -> BoardRun:
    """The screen (when ``screens``) and the joint fit on the one schedule from ``run``'s start; the run after them
    (its ``joint`` the reported fit)."""

    dropped_view_frames: list[int] = []

    def screen(state: TrackState) -> tuple[TrackState, int]:
        r = state.tracks
        obs, intr, poses, boards, dropped, iterations = screen_view_frames(r.obs, r.intrinsics, r.ref_T_view,
                                                                           r.board_T_ref, config, say)
        dropped_view_frames.append(int(r.obs.seen.sum() - obs.seen.sum()))
        return board_state(BoardRun(obs, intr, poses, boards, None, tuple(dropped))), iterations

    def joint(state: TrackState) -> tuple[TrackState, int]:
        r = state.tracks
        fit = calibrate_joint(r.obs, r.intrinsics, r.ref_T_view, r.board_T_ref, config, say.iteration)
        return board_state(replace(r, intrinsics=fit.intrinsics, ref_T_view=fit.ref_T_view,
                                   board_T_ref=fit.board_T_ref, joint=fit)), fit.optimization.iterations

    def screened(r: StageRecord) -> str:
        return (f"calibrate stage screen: a robust fit in {r.iterations} iterations, {dropped_view_frames[-1]} "
                f"view-frames dropped" + (f", the start RMS {r.rms_before_px:.4f} -> {r.rms_after_px:.4f} px"
                                          if dropped_view_frames[-1] else " (the start unchanged)"))

    steps = [Step("screen", screen, prepare=lambda s: s if screens else None, outliers=False, describe=screened),
             Step("joint", joint, outliers=False)]  # its line is the route's (`lfgraph.pattern.pipeline.calibrate`)
    state, _ = run_schedule(steps, board_state(run), say)
    return state.tracks
