"""Graph fragments of pattern calibration: board-corner observations, corner priors, the gauge, intrinsics pins.

Each frame's board is that frame's world. A corner j seen by view v in frame f projects through the camera at
``board_T_ref(f).compose(ref_T_view(v))`` (`gtsam_unstable.ProjectionFactorPPPCCal3DS2`: pose, transform, point,
calibration), so one ``ref_T_view`` per view and one calibration per view are shared by every frame. The factor
follows each view's lens: `ProjectionFactorPPPCCal3DS2` (radtan) or `ProjectionFactorPPPCCal3Fisheye` (fisheye);
GTSAM has no such factor for Cal3Unified: a unified view observes the corner as a point of the reference frame,
``board_point_key(f, j)`` (`gtsam.GeneralSFMFactor2Cal3Unified` with the camera at ``ref_T_view(v)``), and a stiff
`gtsam.ReferenceFrameFactorPoint3Pose3` ties that point to the board corner through the frame's board pose
(point = ``board_T_ref(f)^-1`` corner, `BOARD_POINT_SIGMA_M`): the same model, all in GTSAM's C++ factors.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import gtsam
import gtsam_unstable
import numpy as np

from lfgraph.core.camera import Intrinsics
from lfgraph.core.geometry import to_pose3
from lfgraph.factors.keys import board_corner_key, board_point_key, board_pose_key, calib_key, view_pose_key
from lfgraph.factors.noise import FREE_SIGMA, GAUGE_SIGMA, MIN_SIGMA, lens_noise, point_noise
from lfgraph.lenses import DEFAULT_LENS, lens_model

RIGID_BOARD_SIGMA_M = 1e-6  # a printed board treated as rigid and flat: 1 µm
BOARD_POINT_SIGMA_M = 1e-6  # a unified view's board point is its frame's board corner (1 µm, as a rigid board)


def board_factor(lens: str):
    """The projection factor of a board corner seen by a view of this model (pose, rig transform, point,
    calibration: `gtsam_unstable.ProjectionFactorPPPC` of its class), or None where GTSAM has none (Cal3Unified:
    the view observes per-frame board points, module docstring)."""
    return lens_model(lens).gtsam("ProjectionFactorPPPC", gtsam_unstable)


def add_board_observations(graph: gtsam.NonlinearFactorGraph, corners_px: np.ndarray, valid: np.ndarray,
                           noise: gtsam.noiseModel.Base, lenses: Sequence[str] | None = None) -> int:
    """One projection factor (`board_factor`, by the view's lens; unified: module docstring) per valid corner
    observation. Unified views need their board points in the values (`unified_board_points`).

    Args:
        graph: extended in place.
        corners_px: (V, F, C, 2) observed corners, pixels.
        valid: (V, F, C) which observations exist.
        noise: measurement noise (possibly robust), shared by every factor.
        lenses: each view's lens model; all radtan when None.

    Returns:
        the number of factors added.
    """
    vs, fs, cs = np.nonzero(valid)
    pts = corners_px[vs, fs, cs]
    lenses = tuple(lenses or (DEFAULT_LENS,) * corners_px.shape[0])
    n_corners = corners_px.shape[2]
    factors = [board_factor(lens) for lens in lenses]
    points = [lens_model(lens).gtsam("GeneralSFMFactor2") for lens in lenses]
    for v, f, c, uv in zip(vs.tolist(), fs.tolist(), cs.tolist(), pts, strict=True):
        if factors[v] is None:
            graph.add(points[v](uv, noise, view_pose_key(v), board_point_key(f, c, n_corners), calib_key(v)))
        else:
            graph.add(factors[v](uv, noise, board_pose_key(f), view_pose_key(v), board_corner_key(c), calib_key(v)))
    tie = gtsam.noiseModel.Isotropic.Sigma(3, BOARD_POINT_SIGMA_M)
    for f, c in unified_board_points(valid, lenses):
        graph.add(gtsam.ReferenceFrameFactorPoint3Pose3(board_point_key(f, c, n_corners), board_pose_key(f),
                                                        board_corner_key(c), tie))
    return len(vs)


def unified_board_points(valid: np.ndarray, lenses: Sequence[str]) -> list[tuple[int, int]]:
    """(frame, corner) of every board point a view without a board factor (unified) observes (each once), from the
    (V, F, C) mask."""
    unified = np.array([board_factor(lens) is None for lens in lenses], dtype=bool)
    if not unified.any():
        return []
    fs, cs = np.nonzero(np.any(valid[unified], axis=0))
    return list(zip(fs.tolist(), cs.tolist(), strict=True))


def add_fixed_rig_observations(graph: gtsam.NonlinearFactorGraph, corners_px: np.ndarray, valid: np.ndarray,
                               intrinsics: Sequence[Intrinsics], ref_T_view: np.ndarray,  # noqa: N803
                               noise: gtsam.noiseModel.Base) -> int:
    """Corner observations through a *given* rig: only board poses (and corners) are unknown.

    Uses `GenericProjectionFactorCal3DS2` (or its Cal3Fisheye / Cal3Unified twin, by each view's lens) with
    ``body_P_sensor = ref_T_view``, so the camera is again ``board_T_ref.compose(ref_T_view)``. This is how a
    calibration from any route is scored as one rig.
    """
    cals = [intr.to_gtsam() for intr in intrinsics]
    factors = [intr.model.gtsam("GenericProjectionFactor") for intr in intrinsics]
    bodies = [to_pose3(T) for T in ref_T_view]
    vs, fs, cs = np.nonzero(valid)
    pts = corners_px[vs, fs, cs]
    for v, f, c, uv in zip(vs.tolist(), fs.tolist(), cs.tolist(), pts, strict=True):
        graph.add(factors[v](uv, noise, board_pose_key(f), board_corner_key(c), cals[v], False, False, bodies[v]))
    return len(vs)


def add_corner_priors(graph: gtsam.NonlinearFactorGraph, object_points_m: np.ndarray, sigma_m: float) -> None:
    """Board corners at their nominal positions: tight for a rigid board, the flatness tolerance otherwise.

    Without these priors the board's scale and shape are free (only the square size fixes metric scale).
    """
    noise = point_noise(sigma_m)
    for j, p in enumerate(np.asarray(object_points_m, dtype=np.float64)):
        graph.add(gtsam.PriorFactorPoint3(board_corner_key(j), p, noise))


def add_gauge_prior(graph: gtsam.NonlinearFactorGraph, reference: int) -> None:
    """The reference view defines the array's frame: ``ref_T_view(reference) = I``.

    `Isotropic` (not `Diagonal` with sigmas < 1e-8, which GTSAM turns into a slow constrained model).
    """
    graph.add(gtsam.PriorFactorPose3(view_pose_key(reference), gtsam.Pose3(),
                                     gtsam.noiseModel.Isotropic.Sigma(6, GAUGE_SIGMA)))


# A weakly seen view (the board in 1-2 frames) does not determine all of fx, fy, cx, cy, k1, k2 by itself (one
# plane at a known pose gives a homography: 8 constraints for 12 unknowns). Its intrinsics get a prior centred on
# the start (its calibrated neighbours' mean): the spread of one lens model across units.
WEAK_FOCAL_SIGMA_REL = 0.05  # 5 % of the focal length
WEAK_PRINCIPAL_SIGMA_REL = 0.03  # 3 % of the image width
WEAK_RADIAL_SIGMA = 0.1  # k1, k2
# A board constrains the unified model's xi only weakly: xi, the focal length and k1, k2 trade off to ~0.01 px over
# the field a board covers (fisheye-1x3 as unified, xi 0.8: fits with xi 0.6-1.2 and f 66-138 px off agree). A prior
# about the start (xi = 1 from a fisheye fit) keeps that direction determined; the marginals then report it. Like
# every prior of this graph its sigma is at the model's 1 px corner noise: at a real 0.1 px it holds xi ~10x tighter.
UNIFIED_XI_SIGMA = 0.5


def add_intrinsics_pins(graph: gtsam.NonlinearFactorGraph, intrinsics: Sequence[Intrinsics],
                        tangential: bool, weak: Sequence[bool] | None = None,
                        image_width_px: float | Sequence[float] = 0.0) -> None:
    """Hold what the model lacks: skew at 0 always; p1, p2 at 0 unless ``tangential`` (radtan and unified).

    The other components get a ``FREE_SIGMA`` prior (no information), which keeps one factor per view — except for
    views flagged ``weak``, whose fx, fy, cx, cy and distortion get the ``WEAK_*`` prior around their start.
    """
    widths = np.broadcast_to(np.asarray(image_width_px, dtype=np.float64), (len(intrinsics),))
    for v, intr in enumerate(intrinsics):
        if not tangential:
            intr = dataclasses.replace(intr, **dict.fromkeys(intr.model.tangential, 0.0))
        if weak is not None and weak[v]:
            focal, principal, radial = WEAK_FOCAL_SIGMA_REL * intr.fx, WEAK_PRINCIPAL_SIGMA_REL * widths[v], \
                WEAK_RADIAL_SIGMA
        else:
            focal = principal = radial = FREE_SIGMA
        noise = lens_noise(intr.lens, focal, principal, radial, tangential=FREE_SIGMA if tangential else MIN_SIGMA,
                           xi=UNIFIED_XI_SIGMA)
        graph.add(intr.model.gtsam("PriorFactor")(calib_key(v), intr.to_gtsam(), noise))
