"""Every GTSAM key lfgraph uses. Business code calls these helpers and never builds symbols itself."""

from __future__ import annotations

import gtsam

_VIEW_POSE = "x"  # ref_T_view of view v
_CALIB = "k"  # Cal3DS2 of view v
_BOARD_POSE = "b"  # board_T_ref of frame f (the reference view's pose in that frame's board)
_BOARD_CORNER = "c"  # board corner j (board frame), shared by all frames
_LANDMARK = "l"  # scene landmark j (reference frame)
_BOARD_POINT = "q"  # board corner j of frame f in the reference frame (views whose lens has no board factor)
_PIN_POINT = "p"  # a scene point a self-calibration pin measures (reference frame; not eliminated with the landmarks)
LANDMARK_CHAR = _LANDMARK  # for solvers that eliminate landmarks (`lfgraph.engine.schur`)
BOARD_CORNER_CHAR = _BOARD_CORNER  # the board's corners: the landmarks of a calibration's joint graph


def view_pose_key(view: int) -> int:
    """Key of view ``view``'s pose ``ref_T_view`` (Pose3)."""
    return gtsam.symbol(_VIEW_POSE, view)


def calib_key(view: int) -> int:
    """Key of view ``view``'s intrinsics (Cal3DS2)."""
    return gtsam.symbol(_CALIB, view)


def board_pose_key(frame: int) -> int:
    """Key of frame ``frame``'s ``board_T_ref`` (Pose3)."""
    return gtsam.symbol(_BOARD_POSE, frame)


def board_corner_key(corner: int) -> int:
    """Key of board corner ``corner`` (Point3 in the board frame)."""
    return gtsam.symbol(_BOARD_CORNER, corner)


def board_point_key(frame: int, corner: int, n_corners: int) -> int:
    """Key of corner ``corner`` of frame ``frame``'s board in the reference frame (Point3; ``n_corners`` per board)."""
    return gtsam.symbol(_BOARD_POINT, frame * n_corners + corner)


def landmark_key(index: int) -> int:
    """Key of scene landmark ``index`` (Point3 in the reference frame)."""
    return gtsam.symbol(_LANDMARK, index)


def pin_point_key(index: int) -> int:
    """Key of the self-calibration pins' scene point ``index`` (Point3 in the reference frame): a point whose distance
    is known, kept apart from the landmarks because a factor joins two of them."""
    return gtsam.symbol(_PIN_POINT, index)


def describe_key(key: int) -> str:
    """Readable name of a key, e.g. ``view pose 3`` — for error messages."""
    sym = gtsam.Symbol(key)
    names = {_VIEW_POSE: "view pose", _CALIB: "intrinsics of view", _BOARD_POSE: "board pose of frame",
             _BOARD_CORNER: "board corner", _LANDMARK: "landmark",
             _BOARD_POINT: "board point (frame x corners + corner)", _PIN_POINT: "pinned scene point"}
    return f"{names.get(chr(sym.chr()), chr(sym.chr()))} {sym.index()}"
