"""The paper's pattern calibration (Section 3.2): per-view Zhang (``cv2.calibrateCamera``, k1 and k2; for a fisheye
view ``cv2.fisheye.calibrate``, k1..k4) -> **E_mono**; each view's pose relative to the reference from every frame
both see (PnP averaged, then Levenberg–Marquardt with intrinsics fixed, ``cv2.stereoCalibrate(CALIB_FIX_INTRINSIC)``;
for a pair with a non-radtan lens the same on corners undistorted by each view's model) -> **E_PnP**."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from lfgraph.core.camera import Intrinsics
from lfgraph.core.geometry import invert_T, make_T
from lfgraph.core.parallel import thread_map
from lfgraph.detect.detections import MIN_CORNERS_PER_BOARD, BoardObservations
from lfgraph.lenses import DEFAULT_LENS
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
from lfgraph.pattern.joint import pair_pose
from lfgraph.pattern.lenses import FIT_ERRORS, MonoFit, fit_mono, fitter_name


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


def _pair_pose(obs: BoardObservations, ref: int, v: int, pair: tuple[Intrinsics, Intrinsics], frames: list[int],
               masks: list[np.ndarray], start_ref_T_view: np.ndarray,  # noqa: N803
               ref_T_board: np.ndarray) -> tuple[np.ndarray, float, float]:  # noqa: N803
    """View ``v``'s pose relative to the reference with the intrinsics fixed (the paper's PnP + LM) over the shared
    ``frames`` (corner ``masks`` seen by both), started from ``start_ref_T_view`` and the reference's per-frame PnP
    ``ref_T_board`` (F', 4, 4). A pair of pinhole (radtan) views: `lfgraph.pattern.joint.pair_pose`, the problem of
    ``cv2.stereoCalibrate(CALIB_FIX_INTRINSIC)`` on the engine (the same optimum to ~1e-9 of a pixel's precision,
    without OpenCV's per-call setup: ~25 ms a pair, whatever its iterations); another lens: `cv2.stereoCalibrate` on
    corners undistorted by each view's model, with plain K. Returns (ref_T_view, RMS in px (E_PnP), number of
    residual coordinates)."""
    pinhole = all(i.model.opencv == "pinhole" for i in pair)  # cv2 takes their distortion
    if pinhole:
        return pair_pose(obs, ref, v, pair, frames, masks, start_ref_T_view, ref_T_board)
    objs = [masked_object_points(obs, m) for m in masks]
    ref_pts, view_pts = ([(obs.corners_px[u, f][m] if pinhole else
                           intr.undistort_pixels(obs.corners_px[u, f][m])).astype(np.float32)
                          for f, m in zip(frames, masks, strict=True)] for u, intr in zip((ref, v), pair, strict=True))
    usable = [i for i in range(len(frames)) if np.isfinite(ref_pts[i]).all() and np.isfinite(view_pts[i]).all()]
    objs, ref_pts, view_pts = ([x[i] for i in usable] for x in (objs, ref_pts, view_pts))
    dists = [i.dist_cv if pinhole else np.zeros(5) for i in pair]
    view_T_ref = invert_T(start_ref_T_view)  # noqa: N806
    rms, *_, R, T, _, _ = cv2.stereoCalibrate(  # noqa: N806
        objs, ref_pts, view_pts, pair[0].K, dists[0], pair[1].K, dists[1], obs.image_size_px,
        view_T_ref[:3, :3].copy(), view_T_ref[:3, 3].copy(), flags=cv2.CALIB_FIX_INTRINSIC,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
    return invert_T(make_T(R, T.ravel())), float(rms), 2.0 * sum(len(p) for p in objs)


def _fit(obs: BoardObservations, v: int, lens: str) -> MonoFit:
    """`fit_mono`, its failure said as the calibration's input error."""
    try:
        return fit_mono(obs, v, lens)
    except FIT_ERRORS as exc:
        raise CalibrationInputError(f"{obs.describe(v)}: {fitter_name(lens)} failed ({getattr(exc, 'err', exc)})"
                                    ) from None


def calibrate_paper(obs: BoardObservations, lenses: tuple[str, ...] | None = None,
                    mono: dict[tuple[int, str], MonoFit] | None = None, pair_lm: bool = True) -> PaperResult:
    """The paper's Section 3.2: per-view Zhang (k1, k2) then relative poses by PnP + LM with intrinsics fixed.

    ``lenses`` gives each view's model (radtan or fisheye; all radtan by default); ``mono`` Zhang fits of these
    observations made already (by the lens choice), by (view, lens). Without ``pair_lm`` the relative poses are the
    PnP averages (the start of a joint graph, which refines them with everything else): no E_PnP.

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
    lenses = lenses or (DEFAULT_LENS,) * n_views
    strong = [int(v) for v in np.nonzero(~weak)[0]]
    for v, fit in zip(strong, thread_map(lambda v: (mono or {}).get((v, lenses[v])) or _fit(obs, v, lenses[v]), strong),
                      strict=True):
        known[int(v)] = fit.intrinsics
        for f, pose in fit.view_T_board.items():
            view_T_board[v, f] = pose
        e_mono[v] = fit.rms_px
        n_points[v] = obs.valid[v].sum()
    warnings = []
    for v in np.nonzero(weak)[0]:
        known[int(v)], source = borrowed_intrinsics(obs, int(v), {k: i for k, i in known.items() if not weak[k]},
                                                    lenses[v])
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
    pairs = []  # (view, its shared frames with the reference, their common corners)
    for v in range(n_views) if pair_lm else ():
        if v == ref:
            continue
        frames = np.nonzero(seen[v] & seen[ref])[0]
        masks = [obs.valid[v, f] & obs.valid[ref, f] for f in frames]
        keep = [i for i, m in enumerate(masks) if m.sum() >= MIN_CORNERS_PER_BOARD]
        if not keep:
            warnings.append(f"{obs.describe(v)} shares no frame with the reference view; its pose is chained "
                            f"through view {parent[v]} and has no E_PnP")
            continue
        pairs.append((v, [int(frames[i]) for i in keep], [masks[i] for i in keep]))
    fits = thread_map(lambda p: _pair_pose(obs, ref, p[0], (intrinsics[ref], intrinsics[p[0]]), p[1], p[2],
                                           ref_T_view[p[0]], view_T_board[ref, p[1]]), pairs)
    for (v, _, _), fit in zip(pairs, fits, strict=True):
        ref_T_view[v], e_pnp[v], pnp_points[v] = fit
    mono = np.isfinite(e_mono)  # weak views have no Zhang step
    pooled_mono = float(np.sqrt(np.sum(e_mono[mono] ** 2 * n_points[mono]) / np.sum(n_points[mono])))
    has = np.isfinite(e_pnp)
    pooled_pnp = float(np.sqrt(np.sum(e_pnp[has] ** 2 * pnp_points[has]) / np.sum(pnp_points[has]))) \
        if has.any() else None
    return PaperResult(tuple(intrinsics), ref_T_view, view_T_board, e_mono, e_pnp, pooled_mono, pooled_pnp,
                       tuple(warnings))
