"""The paper's pattern calibration (Section 3.2): per-view Zhang (``cv2.calibrateCamera``, k1 and k2)
-> **E_mono**; each view's pose relative to the reference from every frame both see (PnP averaged, then
Levenberg–Marquardt with intrinsics fixed, ``cv2.stereoCalibrate(CALIB_FIX_INTRINSIC)``) -> **E_PnP**."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from lfgraph.camera import Intrinsics
from lfgraph.detections import MIN_CORNERS_PER_BOARD, BoardObservations
from lfgraph.geometry import invert_T, make_T, rotation_from_rotvec
from lfgraph.pattern.initial import (
    MIN_FRAMES_PER_VIEW,
    CalibrationInputError,
    borrowed_intrinsics,
    check_observations,
    masked_object_points,
    pnp_all,
    relative_poses,
    weak_views,
)

MONO_FLAGS = cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST  # the paper's model: k1, k2, no tangential, no skew


@dataclass(frozen=True)
class PaperResult:
    """The paper route's rig and figures; ``view_T_board`` (V, F, 4, 4) from Zhang (NaN where unseen)."""

    intrinsics: tuple[Intrinsics, ...]
    ref_T_view: np.ndarray
    view_T_board: np.ndarray
    view_e_mono_px: np.ndarray
    view_e_pnp_px: np.ndarray
    e_mono_px: float
    e_pnp_px: float | None
    warnings: tuple[str, ...]


def calibrate_paper(obs: BoardObservations) -> PaperResult:
    """The paper's Section 3.2: per-view Zhang (k1, k2) then relative poses by PnP + LM with intrinsics fixed.

    A view that saw the board in fewer than `MIN_FRAMES_PER_VIEW` frames cannot be calibrated alone: the route
    skips its Zhang step (no E_mono), starts its intrinsics from its neighbours (`borrowed_intrinsics`) and its pose
    from PnP through the shared frames, and says so in a warning.
    """
    check_observations(obs)
    n_views, n_frames = obs.num_views, obs.num_frames
    ref = obs.grid.reference
    seen = obs.seen
    weak = weak_views(obs)
    if weak.all():
        raise CalibrationInputError(
            f"no view saw the board in {MIN_FRAMES_PER_VIEW} frames or more, so the paper route (Zhang per view) "
            f"cannot start; use the joint route from design values (--init design --focal-px F) or show the board "
            f"more often")
    known: dict[int, Intrinsics] = {}
    view_T_board = np.full((n_views, n_frames, 4, 4), np.nan)  # noqa: N806
    e_mono = np.full(n_views, np.nan)
    n_points = np.zeros(n_views)
    for v in np.nonzero(~weak)[0]:
        frames = np.nonzero(seen[v])[0]
        objs = [masked_object_points(obs, obs.valid[v, f]) for f in frames]
        imgs = [obs.corners_px[v, f][obs.valid[v, f]].astype(np.float32) for f in frames]
        try:
            rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(objs, imgs, obs.image_size_px, None, None,  # noqa: N806
                                                             flags=MONO_FLAGS)
        except cv2.error as exc:
            raise CalibrationInputError(f"{obs.describe(v)}: OpenCV's calibrateCamera failed ({exc.err})") from None
        known[int(v)] = Intrinsics.from_opencv(K, np.concatenate([dist.ravel()[:4], [0.0]]))
        for f, r, t in zip(frames, rvecs, tvecs, strict=True):
            view_T_board[v, f] = make_T(rotation_from_rotvec(r.ravel()), t.ravel())
        e_mono[v] = rms
        n_points[v] = sum(len(p) for p in imgs)
    warnings = []
    for v in np.nonzero(weak)[0]:
        known[int(v)], source = borrowed_intrinsics(obs, int(v), {k: i for k, i in known.items() if not weak[k]})
        view_T_board[v] = pnp_all(obs, (known[int(v)],) * n_views)[v]
        warnings.append(f"{obs.describe(int(v))} saw the board in only {int(seen[v].sum())} frame(s) (Zhang needs "
                        f"{MIN_FRAMES_PER_VIEW}): the paper route skips its own calibration; its intrinsics start from "
                        f"{source} and its pose from PnP through the rig")
    intrinsics = [known[v] for v in range(n_views)]
    ref_T_view, parent = relative_poses(view_T_board, ref)  # noqa: N806  the PnP average, the LM start
    unlinked = [obs.describe(v) for v in range(n_views) if parent[v] < 0]
    if unlinked:
        raise CalibrationInputError(f"no chain of shared frames links {', '.join(unlinked)} to the reference view; "
                                    f"show the board to these views together with others")
    e_pnp = np.full(n_views, np.nan)
    pnp_points = np.zeros(n_views)
    ref_K, ref_d = intrinsics[ref].K, intrinsics[ref].dist_cv  # noqa: N806
    for v in range(n_views):
        if v == ref:
            continue
        frames = np.nonzero(seen[v] & seen[ref])[0]
        masks = [obs.valid[v, f] & obs.valid[ref, f] for f in frames]
        keep = [i for i, m in enumerate(masks) if m.sum() >= MIN_CORNERS_PER_BOARD]
        if not keep:
            warnings.append(f"{obs.describe(v)} shares no frame with the reference view; its pose is chained "
                            f"through view {parent[v]} and has no E_PnP")
            continue
        objs = [masked_object_points(obs, masks[i]) for i in keep]
        ref_pts = [obs.corners_px[ref, frames[i]][masks[i]].astype(np.float32) for i in keep]
        view_pts = [obs.corners_px[v, frames[i]][masks[i]].astype(np.float32) for i in keep]
        view_T_ref = invert_T(ref_T_view[v])  # noqa: N806
        rms, *_, R, T, _, _ = cv2.stereoCalibrate(  # noqa: N806
            objs, ref_pts, view_pts, ref_K, ref_d, intrinsics[v].K, intrinsics[v].dist_cv, obs.image_size_px,
            view_T_ref[:3, :3].copy(), view_T_ref[:3, 3].copy(), flags=cv2.CALIB_FIX_INTRINSIC,
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
        ref_T_view[v] = invert_T(make_T(R, T.ravel()))
        e_pnp[v] = rms
        pnp_points[v] = 2 * sum(len(p) for p in objs)
    mono = np.isfinite(e_mono)  # weak views have no Zhang step
    pooled_mono = float(np.sqrt(np.sum(e_mono[mono] ** 2 * n_points[mono]) / np.sum(n_points[mono])))
    has = np.isfinite(e_pnp)
    pooled_pnp = float(np.sqrt(np.sum(e_pnp[has] ** 2 * pnp_points[has]) / np.sum(pnp_points[has]))) \
        if has.any() else None
    return PaperResult(tuple(intrinsics), ref_T_view, view_T_board, e_mono, e_pnp, pooled_mono, pooled_pnp,
                       tuple(warnings))
