"""The one vocabulary of a view's parameter groups, shared by both staged-MAP wings: what a self-calibration stage
frees (`lfgraph.selfcal`), what a refinement's drift priors, significance tests and verdicts speak of
(`lfgraph.refinement`), and where each group lives in GTSAM's variables. `Group` members are strings (``"focal"``),
so configs and files keep their spelling.
"""

from __future__ import annotations

from enum import StrEnum


class Group(StrEnum):
    """A group of one view's parameters.

    ``PAN_TILT`` (rotation about the view's x and y axes) and ``ROLL`` (about its optical axis) make ``ROTATION``;
    ``FOCAL`` (fx, fy) and ``PRINCIPAL`` (cx, cy) make ``INTRINSICS`` (what a refinement frees); ``DISTORTION`` is
    k1 and k2, ``K1`` k1 alone (a self-calibration that cannot see the image corners holds k2).
    """

    PAN_TILT = "pan_tilt"
    ROLL = "roll"
    ROTATION = "rotation"
    POSITION = "position"
    FOCAL = "focal"
    PRINCIPAL = "principal"
    INTRINSICS = "intrinsics"
    DISTORTION = "distortion"
    K1 = "k1"


# a view's 10 pose-and-intrinsics directions (the refinement's posterior): rotation x y z (body, rad), position x y
# z (m), fx fy cx cy (px)
VIEW_DIRECTIONS = {Group.PAN_TILT: (0, 1), Group.ROLL: (2,), Group.ROTATION: (0, 1, 2), Group.POSITION: (3, 4, 5),
                   Group.FOCAL: (6, 7), Group.PRINCIPAL: (8, 9), Group.INTRINSICS: (6, 7, 8, 9)}
# Cal3DS2's tangent indices (fx fy s cx cy k1 k2 p1 p2) of the intrinsic groups
CAL3DS2_INDICES = {Group.FOCAL: (0, 1), Group.PRINCIPAL: (3, 4), Group.DISTORTION: (5, 6), Group.K1: (5,)}
POSE_GROUPS = (Group.ROTATION, Group.POSITION)  # what a self-calibration stage frees of a pose
SELFCAL_GROUPS = (*POSE_GROUPS, *CAL3DS2_INDICES)  # the groups a self-calibration stage may free
DRIFT_GROUPS = (Group.PAN_TILT, Group.ROLL, Group.POSITION, Group.INTRINSICS)  # a refinement's tested groups
