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
# how many of a view's parameters each leaf group holds, and what the unions are made of
LEAF_SIZES = {Group.PAN_TILT: 2, Group.ROLL: 1, Group.POSITION: 3, Group.FOCAL: 2, Group.PRINCIPAL: 2,
              Group.DISTORTION: 2, Group.K1: 1}
UNIONS = {Group.ROTATION: (Group.PAN_TILT, Group.ROLL), Group.INTRINSICS: (Group.FOCAL, Group.PRINCIPAL)}
POSE_LEAVES = frozenset({Group.PAN_TILT, Group.ROLL, Group.POSITION})


def leaves(groups) -> frozenset[Group]:
    """The leaf groups of ``groups`` (unions expanded; ``k1`` inside ``distortion`` counts once, as ``distortion``)."""
    out = set()
    for g in map(Group, groups):
        out.update(UNIONS.get(g, (g,)))
    if Group.DISTORTION in out:
        out.discard(Group.K1)
    return frozenset(out)


def frees_pose(groups) -> bool:
    """Whether ``groups`` free any part of a view's pose."""
    return bool(leaves(groups) & POSE_LEAVES)


def frees_intrinsics(groups) -> bool:
    """Whether ``groups`` free any intrinsic parameter (focal length, principal point, distortion)."""
    return bool(leaves(groups) - POSE_LEAVES)


def parameters_per_view(groups) -> int:
    """How many of one view's parameters ``groups`` free."""
    return sum(LEAF_SIZES[g] for g in leaves(groups))
