"""Starting values of pattern calibration: input checks, per-frame PnP, relative poses through a
maximum spanning tree of shared frames, board poses, design values."""

from __future__ import annotations

import cv2
import numpy as np

from lfgraph.core.camera import Intrinsics
from lfgraph.core.geometry import invert_T, make_T, rotation_from_rotvec
from lfgraph.detect.detections import BoardObservations
from lfgraph.lenses import DEFAULT_LENS
from lfgraph.pattern.pose_fit import board_pose

MIN_FRAMES_PER_VIEW = 3  # Zhang's method needs >= 3 board poses for fx, fy, cx, cy, k1, k2


class CalibrationInputError(ValueError):
    """Observations that cannot be calibrated; the message names the view (and file) and what is missing."""


# ------------------------------------------------------------------------------------------------- checks
def check_observations(obs: BoardObservations) -> None:
    """Refuse observations that cannot calibrate every view: a view that never saw the board. (A view that saw it
    in fewer than `MIN_FRAMES_PER_VIEW` frames is calibrated through the rig, see `weak_views`.)

    Raises:
        CalibrationInputError: the message names each such view and one of its files.
    """
    seen = obs.seen
    counts = seen.sum(axis=1)
    problems = []
    for v in np.nonzero(counts == 0)[0]:
        files = ""
        if obs.sources:
            first = obs.sources[0]
            files = f" (e.g. {first[v] if len(first) == obs.num_views else first[0]})"
        problems.append(f"{obs.describe(int(v))}{files}: no board detected in any frame")
    if problems:
        raise CalibrationInputError(
            f"cannot calibrate the {obs.grid} array with the {obs.board} board: " + "; ".join(problems)
            + ". Check the board size (--board, inner corners) and that the board is inside these views.")


def weak_views(obs: BoardObservations) -> np.ndarray:
    """(V,) bool: views that saw the board in 1 to `MIN_FRAMES_PER_VIEW` - 1 frames — too few for Zhang's method
    alone; they are calibrated through the rig (board poses from the other views) with priors on their intrinsics."""
    counts = obs.seen.sum(axis=1)
    return (counts > 0) & (counts < MIN_FRAMES_PER_VIEW)


_BORROWED = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4", "xi")  # tangential terms start at 0


def borrowed_intrinsics(obs: BoardObservations, view: int, known: dict[int, Intrinsics],
                        lens: str = DEFAULT_LENS) -> tuple[Intrinsics, str]:
    """Starting intrinsics of a weakly seen view: the mean of its calibrated grid neighbours with the same lens
    model, else of every calibrated view with it, else design values (focal length = the larger image side,
    centred principal point, no distortion).

    Returns:
        the intrinsics and a phrase saying where they came from (for the warning).
    """
    same = {n: i for n, i in known.items() if i.lens == lens}
    for pool, source in (([n for n in obs.grid.neighbours(view) if n in same], "its neighbours"),
                         (sorted(same), "the other views")):
        if pool:
            fields = np.mean([[getattr(same[n], k) for k in _BORROWED] for n in pool], axis=0)
            return (Intrinsics(**dict(zip(_BORROWED, (float(x) for x in fields), strict=True)), lens=lens),
                    f"{source} ({', '.join(obs.grid.name(n) for n in pool)})")
    w, h = obs.image_size(view)
    f = float(max(w, h))
    return (Intrinsics(f, f, (w - 1) / 2.0, (h - 1) / 2.0).with_distortion(lens),
            "design values (focal length = the larger image side)")


# ------------------------------------------------------------------------------------------------- helpers
def masked_object_points(obs: BoardObservations, mask: np.ndarray) -> np.ndarray:
    """(K, 3) float32 board corners (m, board frame) where ``mask`` (C,) is set: what OpenCV's calibration functions
    take."""
    return obs.board.object_points()[mask].astype(np.float32)


def mean_rotation(rotations: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of (N, 3, 3) rotations (projection of the sum onto SO(3))."""
    u, _, vt = np.linalg.svd(np.sum(rotations, axis=0))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def mean_pose(poses: np.ndarray) -> np.ndarray:
    """The mean of (N, 4, 4) poses: chordal mean of the rotations, mean of the translations (m)."""
    return make_T(mean_rotation(poses[:, :3, :3]), poses[:, :3, 3].mean(axis=0))


def pnp_all(obs: BoardObservations, intrinsics: tuple[Intrinsics, ...]) -> np.ndarray:
    """(V, F, 4, 4) ``view_T_board`` from PnP in every seen view-frame (NaN elsewhere)."""
    out = np.full((obs.num_views, obs.num_frames, 4, 4), np.nan)
    seen = obs.seen
    for v, f in zip(*np.nonzero(seen), strict=True):
        mask = obs.valid[v, f]
        if intrinsics[v].model.opencv != "pinhole":  # PnP on undistorted corners, then the pixel error (any model)
            pose = board_pose(intrinsics[v], obs.board.object_points()[mask], obs.corners_px[v, f][mask])
            if pose is not None:
                out[v, f] = pose
            continue
        ok, rvec, tvec = cv2.solvePnP(masked_object_points(obs, mask), obs.corners_px[v, f][mask].astype(np.float32),
                                      intrinsics[v].K, intrinsics[v].dist_cv, flags=cv2.SOLVEPNP_ITERATIVE)
        if ok:
            out[v, f] = make_T(rotation_from_rotvec(rvec.ravel()), tvec.ravel())
    return out


def relative_poses(view_T_board: np.ndarray, reference: int) -> tuple[np.ndarray, np.ndarray]:  # noqa: N803
    """``ref_T_view`` of every view from per-frame board poses, through a tree of most-shared frames.

    Views that share frames with the reference get the average over those frames; others are linked through the
    view they share most frames with (a maximum spanning tree grown from the reference).

    Returns:
        (V, 4, 4) ``ref_T_view`` and (V,) the view each was linked through (itself for the reference).
    """
    n_views = view_T_board.shape[0]
    have = np.all(np.isfinite(view_T_board.reshape(n_views, view_T_board.shape[1], -1)), axis=-1)
    shared = (have[:, None, :] & have[None, :, :]).sum(axis=-1)
    ref_T_view = np.full((n_views, 4, 4), np.nan)  # noqa: N806
    ref_T_view[reference] = np.eye(4)
    parent = np.full(n_views, -1)
    parent[reference] = reference
    while np.any(parent < 0):
        linked = parent >= 0
        score = np.where(linked[:, None] & ~linked[None, :], shared, 0)
        a, b = np.unravel_index(np.argmax(score), score.shape)
        if score[a, b] == 0:
            break
        frames = np.nonzero(have[a] & have[b])[0]
        # a_T_b = a_T_board @ board_T_b, averaged over the shared frames
        a_T_b = mean_pose(np.stack([view_T_board[a, f] @ invert_T(view_T_board[b, f]) for f in frames]))  # noqa: N806
        ref_T_view[b] = ref_T_view[a] @ a_T_b
        parent[b] = a
    return ref_T_view, parent


DUPLICATE_TOLERANCE_PX = 1e-3  # a board whose corners all match an earlier frame's to this is the same picture


def duplicate_view_frames(obs: BoardObservations) -> list[tuple[int, int, int]]:
    """(view, frame, earlier frame) of each view-frame whose board repeats an earlier frame's corner for corner (a
    copied image): it adds no new board pose, only weight, and a set of copies would let Zhang's method "fit" a
    single pose."""
    out = []
    for v in range(obs.num_views):
        frames = np.nonzero(obs.seen[v])[0]
        valid, corners = obs.valid[v, frames], obs.corners_px[v, frames]
        same_mask = np.all(valid[:, None] == valid[None, :], axis=-1)
        with np.errstate(invalid="ignore"):
            gap = np.nanmax(np.abs(corners[:, None] - corners[None, :]), axis=(2, 3), initial=0.0)
        match = same_mask & (gap <= DUPLICATE_TOLERANCE_PX)
        kept: list[int] = []
        for i, f in enumerate(frames):
            same = next((j for j in kept if match[i, j]), None)
            if same is None:
                kept.append(i)
            else:
                out.append((v, int(f), int(frames[same])))
    return out


def drop_view_frames(obs: BoardObservations, pairs: list[tuple[int, int]]) -> BoardObservations:
    """``obs`` with the boards of the given (view, frame) pairs marked not observed."""
    import dataclasses

    valid = np.array(obs.valid)
    for v, f in pairs:
        valid[v, f] = False
    return dataclasses.replace(obs, valid=valid)


CONSENSUS_MIN_FRAMES = 3  # per-frame rig estimates needed before one can be called the odd one out
CONSENSUS_MAD_FACTOR = 6.0  # a frame's relative pose is inconsistent beyond this many robust sigmas (1.4826 MAD) ...
CONSENSUS_MIN_ROT_DEG = 1.0  # ... and beyond 1 degree of rotation ...
CONSENSUS_MIN_TRANS_REL = 0.05  # ... or 5 % of the baseline in position


def inconsistent_view_frames(view_T_board: np.ndarray, reference: int) -> list[tuple[int, int, float, float]]:  # noqa: N803
    """View-frames whose board pose contradicts the rig that the other frames agree on.

    For every view sharing at least `CONSENSUS_MIN_FRAMES` frames with the reference, each shared frame gives an
    estimate of ``ref_T_view`` (PnP in both views); the medoid of those is the consensus, and a frame whose
    estimate lies beyond `CONSENSUS_MAD_FACTOR` robust sigmas of the others *and* beyond 1 degree or 5 % of the
    baseline is inconsistent (a mis-detected board, or an image of another camera). The view is blamed; when one
    frame is inconsistent for every view (two or more) that shares it with the reference, the reference view's board
    in that frame is blamed instead (two views swapped in one frame blame those two, not the reference).

    Returns:
        (view, frame, rotation off (deg), position off (m)) of each view-frame to drop.
    """
    n_views = view_T_board.shape[0]
    have = np.all(np.isfinite(view_T_board.reshape(n_views, view_T_board.shape[1], -1)), axis=-1)
    flagged: list[tuple[int, int, float, float]] = []
    shared_count = np.zeros(view_T_board.shape[1], dtype=int)
    for v in range(n_views):
        if v == reference:
            continue
        frames = np.nonzero(have[v] & have[reference])[0]
        shared_count[frames] += 1
        if len(frames) < CONSENSUS_MIN_FRAMES:
            continue
        est = view_T_board[reference, frames] @ invert_T(view_T_board[v, frames])
        rot = _angles_deg(est[:, :3, :3])
        pos = np.linalg.norm(est[:, None, :3, 3] - est[None, :, :3, 3], axis=-1)
        baseline = float(np.median(np.linalg.norm(est[:, :3, 3], axis=1)))
        scale = max(baseline, 1e-9)
        medoid = int(np.argmin(np.median(rot / CONSENSUS_MIN_ROT_DEG + pos / (CONSENSUS_MIN_TRANS_REL * scale),
                                         axis=1)))
        d_rot, d_pos = rot[medoid], pos[medoid]
        mad_rot = 1.4826 * float(np.median(d_rot)) + 1e-12
        mad_pos = 1.4826 * float(np.median(d_pos)) + 1e-12
        for i, f in enumerate(frames):
            off_rot = d_rot[i] > max(CONSENSUS_MAD_FACTOR * mad_rot, CONSENSUS_MIN_ROT_DEG)
            off_pos = d_pos[i] > max(CONSENSUS_MAD_FACTOR * mad_pos, CONSENSUS_MIN_TRANS_REL * scale)
            if off_rot or off_pos:
                flagged.append((v, int(f), float(d_rot[i]), float(d_pos[i])))
    out: list[tuple[int, int, float, float]] = []
    per_frame: dict[int, list[tuple[int, int, float, float]]] = {}
    for item in flagged:
        per_frame.setdefault(item[1], []).append(item)
    for f, items in sorted(per_frame.items()):
        if len(items) >= 2 and len(items) == shared_count[f]:
            worst = max(items, key=lambda x: x[3])
            out.append((reference, f, worst[2], worst[3]))
        else:
            out.extend(items)
    return out


def _angles_deg(R: np.ndarray) -> np.ndarray:  # noqa: N803
    """(N, N) angle (deg) between every two of the (N, 3, 3) rotations: trace(Ra^T Rb) = sum of Ra * Rb."""
    return np.degrees(np.arccos(np.clip((np.einsum("aij,bij->ab", R, R) - 1.0) / 2.0, -1.0, 1.0)))


def initial_board_T_ref(view_T_board: np.ndarray, ref_T_view: np.ndarray, counts: np.ndarray) -> np.ndarray:  # noqa: N802, N803
    """(F, 4, 4) per frame ``board_T_ref`` from the view that saw the most corners of it."""
    n_frames = view_T_board.shape[1]
    out = np.full((n_frames, 4, 4), np.nan)
    for f in range(n_frames):
        order = np.argsort(-counts[:, f], kind="stable")
        for v in order:
            if counts[v, f] == 0 or not np.all(np.isfinite(view_T_board[v, f])) \
                    or not np.all(np.isfinite(ref_T_view[v])):
                continue
            out[f] = invert_T(view_T_board[v, f]) @ invert_T(ref_T_view[v])
            break
    return out



# ------------------------------------------------------------------------------------------------- design start
def design_initial(obs: BoardObservations, focal_px: float | None = None,
                   pitch_m: float | None = None) -> tuple[tuple[Intrinsics, ...], np.ndarray, np.ndarray]:
    """Design values: focal length (given, or the larger image side), centred principal point, no distortion;
    poses from the ideal grid (``pitch_m``) or, without it, PnP averages under the design intrinsics.

    Returns:
        intrinsics, ``ref_T_view`` (V, 4, 4) and ``view_T_board`` (V, F, 4, 4) from PnP.
    """
    sizes = [obs.image_size(v) for v in range(obs.num_views)]
    intrinsics = tuple(Intrinsics(f, f, (w - 1) / 2.0, (h - 1) / 2.0) for w, h in sizes
                       for f in [float(focal_px) if focal_px is not None else float(max(w, h))])
    view_T_board = pnp_all(obs, intrinsics)  # noqa: N806
    if pitch_m is not None:
        ref_T_view = np.stack([make_T(np.eye(3), np.array([*obs.grid.offset(v)[::-1], 0.0]) * pitch_m)  # noqa: N806
                               for v in range(obs.num_views)])
    else:
        ref_T_view, parent = relative_poses(view_T_board, obs.grid.reference)  # noqa: N806
        if np.any(parent < 0):
            bad = [obs.describe(v) for v in np.nonzero(parent < 0)[0]]
            raise CalibrationInputError(f"no chain of shared frames links {', '.join(bad)} to the reference view")
    return intrinsics, ref_T_view, view_T_board
