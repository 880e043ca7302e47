"""The one boundary between lfgraph's objects and `gtsam.Values`: every insert and every read-back of view poses,
intrinsics, board poses, board corners and landmarks goes through here (round-trip tested)."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence

import gtsam
import numpy as np

from lfgraph.core.camera import Intrinsics
from lfgraph.core.geometry import from_pose3, to_pose3
from lfgraph.factors.keys import (
    board_corner_key,
    board_point_key,
    board_pose_key,
    calib_key,
    landmark_key,
    view_pose_key,
)
from lfgraph.lenses import DEFAULT_LENS, lens_model


def insert_view_poses(values: gtsam.Values, ref_T_view: np.ndarray) -> None:  # noqa: N803
    """(V, 4, 4) ``ref_T_view`` as Pose3 under `view_pose_key`."""
    for v, pose in enumerate(ref_T_view):
        values.insert(view_pose_key(v), to_pose3(pose))


def insert_intrinsics(values: gtsam.Values, intrinsics: Sequence[Intrinsics]) -> None:
    """Per-view calibration (its lens model's GTSAM class: Cal3DS2, Cal3Fisheye, ...) under `calib_key`."""
    for v, intr in enumerate(intrinsics):
        values.insert(calib_key(v), intr.to_gtsam())


def insert_board_poses(values: gtsam.Values, board_T_ref: np.ndarray, frames: Iterable[int]) -> None:  # noqa: N803
    """``board_T_ref`` of the given frames under `board_pose_key`."""
    for f in frames:
        values.insert(board_pose_key(f), to_pose3(board_T_ref[f]))


def insert_board_corners(values: gtsam.Values, object_points_m: np.ndarray) -> None:
    """(C, 3) board corners (board frame, metres) under `board_corner_key`."""
    for j, p in enumerate(np.asarray(object_points_m, dtype=np.float64)):
        values.insert(board_corner_key(j), p)


def insert_board_points(values: gtsam.Values, points: Sequence[tuple[int, int]], board_T_ref: np.ndarray,  # noqa: N803
                        object_points_m: np.ndarray) -> None:
    """Each (frame, corner) board point at ``board_T_ref(f)^-1`` corner (reference frame; `board_point_key`)."""
    n = len(object_points_m)
    for f, c in points:
        ref_T_board = np.linalg.inv(board_T_ref[f])  # noqa: N806
        values.insert(board_point_key(f, c, n), ref_T_board[:3, :3] @ object_points_m[c] + ref_T_board[:3, 3])


def insert_landmarks(values: gtsam.Values, points_ref_m: np.ndarray) -> None:
    """(N, 3) landmarks (reference frame, metres) under `landmark_key`."""
    for j, p in enumerate(np.asarray(points_ref_m, dtype=np.float64)):
        values.insert(landmark_key(j), p)


def read_view_poses(values: gtsam.Values, n_views: int) -> np.ndarray:
    """(V, 4, 4) ``ref_T_view``."""
    return np.stack([from_pose3(values.atPose3(view_pose_key(v))) for v in range(n_views)])


SKEW_ROUNDOFF_PX = 1e-6  # a skew held at 0 by a prior of `lfgraph.factors.noise.MIN_SIGMA` moves by ~1e-12: dropped


def read_intrinsics(values: gtsam.Values, n_views: int, keep: Sequence[Intrinsics] | None = None,
                    tangential: bool = True, lenses: Sequence[str] | None = None) -> tuple[Intrinsics, ...]:
    """Per-view intrinsics from their GTSAM calibrations (each view's model's class, `lfgraph.lenses`).

    Args:
        keep: when given, the distortion (every coefficient of the model) is taken from these instead (stages that
            hold it).
        tangential: False clears the model's tangential coefficients (p1, p2: held at 0 by priors; this removes
            their ~1e-13 round-off).
        lenses: each view's lens model (`lfgraph.lenses.lens_names`); all the default (radtan, Cal3DS2) when None.
    """
    out = []
    for v in range(n_views):
        model = lens_model(DEFAULT_LENS if lenses is None else lenses[v])
        cal = getattr(values, "at" + model.gtsam_name)(calib_key(v))
        if abs(cal.skew()) > SKEW_ROUNDOFF_PX:
            raise ValueError(f"view {v}: {model.gtsam_name} has skew {cal.skew()}, but lfgraph's models have none")
        if keep is not None:  # the stage held the distortion: the input's, without round-off
            out.append(dataclasses.replace(keep[v], fx=cal.fx(), fy=cal.fy(), cx=cal.px(), cy=cal.py()))
            continue
        params = model.from_gtsam(cal)
        if not tangential:
            params.update(dict.fromkeys(model.tangential, 0.0))
        out.append(Intrinsics(**params, lens=model.name))
    return tuple(out)


def read_board_poses(values: gtsam.Values, n_frames: int, frames: Iterable[int]) -> np.ndarray:
    """(F, 4, 4) ``board_T_ref``, NaN for frames not in ``frames``."""
    out = np.full((n_frames, 4, 4), np.nan)
    for f in frames:
        out[f] = from_pose3(values.atPose3(board_pose_key(f)))
    return out


def read_board_corners(values: gtsam.Values, n_corners: int) -> np.ndarray:
    """(C, 3) board corners."""
    return np.stack([np.asarray(values.atPoint3(board_corner_key(j))) for j in range(n_corners)])


def read_landmarks(values: gtsam.Values, n: int) -> np.ndarray:
    """(N, 3) landmarks (an empty (0, 3) array for none)."""
    if n == 0:
        return np.zeros((0, 3))
    return np.stack([np.asarray(values.atPoint3(landmark_key(j))) for j in range(n)])
