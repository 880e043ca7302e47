"""Consistent corner order for boards that look the same turned by 180°, decided from the rig's geometry.

A checkerboard with ``cols + rows`` even (e.g. 13x9 inner corners) has no mark telling corner 0 from corner C-1, so
a detector may report the corners of one view-frame in reverse. Each view's own calibration does not care (every
frame has its own board pose), but a rig does: reversing the corners in view b of frame f turns the board pose
seen by b by 180° about the board normal through the board centre, and the relative pose ``a_T_b`` from that frame
no longer agrees with the other frames. This module picks, per view-frame, the order that makes the relative poses
agree:

1. per view, Zhang's calibration (``cv2.calibrateCamera``) gives the board pose in every frame it sees;
2. per pair of views, each shared frame offers two relative poses (as detected, or with one side reversed); the
   true relative pose is the one most frames agree on (a wrong hypothesis is off by 180° from the true one, and
   wrong hypotheses of two frames agree only if the board did not move between them);
3. a spanning tree of the best-supported pairs gives every view's pose in the reference view;
4. per frame, one view keeps its detected order (the reference view when it sees the frame: the choice is free,
   the board's pose in each frame is unknown anyway) and every other view takes the order whose board pose agrees
   with it through the rig.

What cannot be decided is reported and left as detected: a view linked to no other view by a pair with a clear
majority (e.g. sharing no frame, or only frames with the board in one pose), or a view-frame where neither order
agrees with the rig.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from lfgraph.core.geometry import invert_T, make_T, rotation_from_rotvec
from lfgraph.detect.detections import BoardObservations

ROT_TOL_DEG = 10.0  # two relative poses agree within this rotation (the wrong order is 180° off)
TRANS_TOL_BOARDS = 0.5  # ... and (relative poses of two frames) within this translation, in board diagonals: a
#                          wrong order moves the board's far corners by up to two diagonals
MIN_ZHANG_FRAMES = 3  # fewer frames in a view: a nominal camera (focal = larger image side) and PnP instead
MONO_FLAGS = cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST

# per view-frame status
UNSEEN = "unseen"  # the board was not seen
ANCHOR = "anchor"  # order kept: fixes the frame's free choice (the reference view when it sees the frame)
DECIDED = "decided"  # order chosen by agreement with the anchor through the rig
ALONE = "alone"  # the only linked view seeing this frame: its order does not matter to the rig
UNLINKED = "unlinked"  # the view's pose in the rig could not be decided: order left as detected
AMBIGUOUS = "ambiguous"  # neither order agrees with the rig (a mis-detection?): left as detected


@dataclass(frozen=True)
class BoardOrderReport:
    """What `order_symmetric_boards` did.

    Attributes:
        reversed: (V, F) the detected corner order was reversed.
        status: (V, F) one of `UNSEEN`, `ANCHOR`, `DECIDED`, `ALONE`, `UNLINKED`, `AMBIGUOUS`.
        pair_support: (V, V) number of shared frames agreeing on the relative pose of each pair of views.
        pair_frames: (V, V) number of frames each pair shares.
        messages: one line per undecidable view or view-frame (empty when everything was decided).
    """

    reversed: np.ndarray
    status: np.ndarray
    pair_support: np.ndarray
    pair_frames: np.ndarray
    messages: tuple[str, ...]

    @property
    def undecidable(self) -> np.ndarray:
        """(V, F) view-frames whose order could not be decided (`UNLINKED` or `AMBIGUOUS`)."""
        return (self.status == UNLINKED) | (self.status == AMBIGUOUS)


def flip_transform(cols: int, rows: int, square_m: float) -> np.ndarray:
    """(4, 4) board-frame map taking corner ``j`` to corner ``C-1-j``: 180° about z through the board centre."""
    centre = np.array([(cols - 1) * square_m, (rows - 1) * square_m, 0.0])
    return make_T(np.diag([-1.0, -1.0, 1.0]), centre)


def _rotation_deg(rotation: np.ndarray) -> np.ndarray:
    """Angle of (..., 3, 3) rotations in degrees."""
    cos = (np.trace(rotation, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _agree(a: np.ndarray, b: np.ndarray, trans_tol_m: float) -> np.ndarray:
    """(N, M) poses a (N, 4, 4) and b (M, 4, 4) agree within `ROT_TOL_DEG` and ``trans_tol_m``."""
    rel = np.einsum("nji,mjk->nmik", a[:, :3, :3], b[:, :3, :3])
    dt = np.linalg.norm(a[:, None, :3, 3] - b[None, :, :3, 3], axis=-1)
    return (_rotation_deg(rel) < ROT_TOL_DEG) & (dt < trans_tol_m)


def _view_poses(obs: BoardObservations) -> np.ndarray:
    """(V, F, 4, 4) ``view_T_board`` in the detected order (NaN where unseen), from each view's own calibration."""
    obj_all = obs.board.object_points()
    seen = obs.seen
    out = np.full((obs.num_views, obs.num_frames, 4, 4), np.nan)
    w, h = obs.image_size_px
    for v in range(obs.num_views):
        frames = np.nonzero(seen[v])[0]
        objs = [obj_all[obs.valid[v, f]].astype(np.float32) for f in frames]
        imgs = [obs.corners_px[v, f][obs.valid[v, f]].astype(np.float32) for f in frames]
        if len(frames) >= MIN_ZHANG_FRAMES:
            _, K, dist, rvecs, tvecs = cv2.calibrateCamera(objs, imgs, obs.image_size_px, None, None,  # noqa: N806
                                                           flags=MONO_FLAGS)
        else:
            K, dist = np.array([[max(w, h), 0, w / 2], [0, max(w, h), h / 2], [0, 0, 1.0]]), np.zeros(5)  # noqa: N806
            rvecs, tvecs = [], []
            for o, i in zip(objs, imgs, strict=True):
                _, r, t = cv2.solvePnP(o, i, K, dist)
                rvecs.append(r)
                tvecs.append(t)
        for f, r, t in zip(frames, rvecs, tvecs, strict=True):
            out[v, f] = make_T(rotation_from_rotvec(np.ravel(r)), np.ravel(t))
    return out


def _pair_consensus(pa: np.ndarray, pb: np.ndarray, flip: np.ndarray,
                    trans_tol_m: float) -> tuple[np.ndarray, int, int]:
    """Relative pose ``a_T_b`` most shared frames agree on.

    Args:
        pa, pb: (S, 4, 4) ``a_T_board`` and ``b_T_board`` of the shared frames, detected order.
        flip: `flip_transform`.
        trans_tol_m: translation tolerance.

    Returns:
        (S,) per frame whether b's order must be reversed relative to a's (-1 where no hypothesis agrees), the
        number of frames agreeing, and the largest number agreeing on a pose 180° away (a rival consensus).
    """
    inv_b = np.stack([invert_T(p) for p in pb])
    hyp = np.concatenate([pa @ inv_b, pa @ flip @ inv_b])  # (2S, 4, 4): as detected, then b reversed vs a
    n = len(pa)
    agree = _agree(hyp, hyp, trans_tol_m)  # (2S, 2S)
    per_frame = agree[:, :n] | agree[:, n:]  # candidate agrees with one of frame f's two hypotheses
    support = per_frame.sum(axis=1)
    best = int(np.argmax(support))
    rot_gap = _rotation_deg(np.einsum("ji,njk->nik", hyp[best, :3, :3], hyp[:, :3, :3]))
    rivals = support[rot_gap > 90.0]
    rival = int(rivals.max()) if rivals.size else 0
    choice = np.where(agree[best, :n], 0, np.where(agree[best, n:], 1, -1))
    choice[agree[best, :n] & agree[best, n:]] = -1
    return choice, int(support[best]), rival


def _pair_poses(seen: np.ndarray, poses: np.ndarray, flip: np.ndarray, trans_tol_m: float,
                support: np.ndarray) -> np.ndarray:
    """(V, V, 4, 4) ``a_T_b`` of every pair of views whose shared frames agree on one corner order by a clear
    majority (NaN otherwise): b's board put in a's order, averaged over those frames (chordal mean of rotations).
    ``support`` (V, V) gets each pair's majority (in place)."""
    n_views = len(seen)
    rel = np.full((n_views, n_views, 4, 4), np.nan)
    for a in range(n_views):
        for b in range(a + 1, n_views):
            frames = np.nonzero(seen[a] & seen[b])[0]
            if len(frames) < 2:
                continue  # one frame supports both hypotheses equally
            choice, best, rival = _pair_consensus(poses[a, frames], poses[b, frames], flip, trans_tol_m)
            if best <= rival:
                continue
            support[a, b] = support[b, a] = best
            keep, flips = frames[choice >= 0], choice[choice >= 0]
            samples = np.stack([poses[a, f] @ (flip if s else np.eye(4)) @ invert_T(poses[b, f])
                                for f, s in zip(keep, flips, strict=True)])
            u, _, vt = np.linalg.svd(samples[:, :3, :3].sum(axis=0))
            rot = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
            rel[a, b] = make_T(rot, samples[:, :3, 3].mean(axis=0))
            rel[b, a] = invert_T(rel[a, b])
    return rel


def _spanning_tree(seen: np.ndarray, support: np.ndarray, rel: np.ndarray,
                   ref: int) -> tuple[np.ndarray, np.ndarray]:
    """The maximum spanning tree of supported pairs grown from the reference view: (V, 4, 4) ``ref_T_view`` (NaN
    where not linked) and (V,) which views it links."""
    n_views = len(seen)
    ref_T_view = np.full((n_views, 4, 4), np.nan)  # noqa: N806
    linked = np.zeros(n_views, dtype=bool)
    if seen[ref].any():
        ref_T_view[ref], linked[ref] = np.eye(4), True
    while True:
        score = np.where(linked[:, None] & ~linked[None, :], support, 0)
        a, b = np.unravel_index(np.argmax(score), score.shape)
        if score[a, b] == 0:
            break
        ref_T_view[b] = ref_T_view[a] @ rel[a, b]
        linked[b] = True
    return ref_T_view, linked


def order_symmetric_boards(obs: BoardObservations) -> tuple[BoardObservations, BoardOrderReport]:
    """Make the corner order of a 180°-symmetric board consistent over all views and frames, from the geometry.

    Observations of a board that is not symmetric (`BoardSpec.is_symmetric`) are returned unchanged.

    Args:
        obs: corners in the detector's order (any mix of reversed view-frames).

    Returns:
        the re-ordered observations and the decisions (`BoardOrderReport`; its ``messages`` name what could
        not be decided, which is left as detected).
    """
    n_views, n_frames = obs.num_views, obs.num_frames
    seen = obs.seen
    status = np.where(seen, ALONE, UNSEEN).astype(object)
    flipped = np.zeros((n_views, n_frames), dtype=bool)
    support = np.zeros((n_views, n_views), dtype=int)
    shared = (seen[:, None, :] & seen[None, :, :]).sum(axis=-1)
    if not obs.board.is_symmetric:
        return obs, BoardOrderReport(flipped, np.where(seen, ANCHOR, UNSEEN).astype(object), support, shared, ())
    board = obs.board
    flip = flip_transform(board.cols, board.rows, board.square_m)
    diagonal_m = board.square_m * np.hypot(board.cols - 1, board.rows - 1)
    trans_tol_m = TRANS_TOL_BOARDS * diagonal_m
    poses = _view_poses(obs)

    rel = _pair_poses(seen, poses, flip, trans_tol_m, support)
    ref = obs.grid.reference
    ref_T_view, linked = _spanning_tree(seen, support, rel, ref)  # noqa: N806

    messages = []
    for v in np.nonzero(~linked & seen.any(axis=1))[0]:
        status[v, seen[v]] = UNLINKED
        messages.append(f"{obs.describe(int(v))}: its corner order cannot be decided (no other view shares at least "
                        f"two frames with it in which the board moved); left as detected")

    # per frame: the anchor keeps its order, the others follow it through the rig
    for f in range(n_frames):
        views = [v for v in range(n_views) if seen[v, f] and linked[v]]
        if len(views) < 2:
            continue
        anchor = ref if ref in views else views[0]
        status[anchor, f] = ANCHOR
        board_in_ref = ref_T_view[anchor] @ poses[anchor, f]
        for v in views:
            if v == anchor:
                continue
            hyp = np.stack([ref_T_view[v] @ poses[v, f], ref_T_view[v] @ poses[v, f] @ flip])
            # the two orders' board rotations are 180° apart: rotation alone decides, and a board that agrees with
            # neither within the tolerance is a mis-detection (or a rig too rough to tell), not a guess
            gap_deg = _rotation_deg(np.einsum("ji,njk->nik", board_in_ref[:3, :3], hyp[:, :3, :3]))
            ok = gap_deg < ROT_TOL_DEG
            if not ok.any():
                status[v, f] = AMBIGUOUS
                messages.append(f"{obs.describe(v, f)}: neither corner order agrees with {obs.describe(anchor)} "
                                f"through the rig (by {gap_deg.min():.0f}°, a mis-detected board?); left as detected")
                continue
            status[v, f] = DECIDED
            flipped[v, f] = bool(ok[1])

    corners = obs.corners_px.copy()
    valid = obs.valid.copy()
    corners[flipped] = corners[flipped][:, ::-1]
    valid[flipped] = valid[flipped][:, ::-1]
    out = dataclasses.replace(obs, corners_px=corners, valid=valid)  # every other field (sizes, sources) kept
    return out, BoardOrderReport(flipped, status, support, shared, tuple(messages))
