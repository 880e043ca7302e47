"""Graph fragments of target-less self-calibration (`lfgraph.selfcal`): MAP priors from design values.

Every view's pose and intrinsics are variables seen through `GeneralSFMFactor2Cal3DS2` (from
`lfgraph.factors.scene_graph.sfm_factors`). A stage frees some parameter groups; each free parameter is pulled to its
**design value** with its design tolerance (a MAP prior, centred on the design, never on the previous stage's
estimate, so stages do not compound priors); each held parameter is pinned at its current estimate.

Gauges: (1) the reference view's pose is the identity; (2) scale comes from the design pitch through the position
priors (every free view pulled to its ideal grid position) — scene frames alone carry no scale; (3) the hidden
principal-point gauge (a shift of every principal point in proportion to its view's baseline with a shift of every
landmark's inverse depth; exact without distortion) and the common zoom of every focal length (with k1 and k2
scaled alongside; exact for parallel views) are fixed by the principal-point and focal-length priors, weakly helped
by distortion and the views' small rotations; the posterior sigmas say how much the frames added.
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from lfgraph.core.camera import Intrinsics
from lfgraph.core.grid import ViewGrid
from lfgraph.core.sigmas import Sigmas
from lfgraph.factors.board_graph import RIGID_BOARD_SIGMA_M, add_board_observations, add_corner_priors
from lfgraph.factors.groups import CAL3DS2_INDICES, Group
from lfgraph.factors.keys import calib_key, pin_point_key, view_pose_key
from lfgraph.factors.noise import (
    FREE_SIGMA,
    HELD_SIGMA,
    MIN_SIGMA,
    calibration_noise,
    pixel_noise,
    range_noise,
)
from lfgraph.factors.prior_table import (
    POSE_TANGENT,
    calibration_vectors,
)
from lfgraph.lenses import lens_model


def design_tangent_sigmas(sigmas: Sigmas) -> np.ndarray:
    """(V, 9) each view's design tolerances in Cal3DS2's tangent order (fx fy s cx cy k1 k2 p1 p2; the groups' indices
    are every model's): skew and tangential distortion held (not in the model), k1, k2 as the record holds them."""
    n = sigmas.num_views
    k1, k2 = (sigmas.distortion.get(k, np.full(n, MIN_SIGMA)) for k in ("k1", "k2"))
    fx, fy, cx, cy = sigmas.intrinsics.T
    held = np.full(n, MIN_SIGMA)
    return np.stack([fx, fy, held, cx, cy, k1, k2, held, held], axis=1)


def intrinsics_gauges(grid: ViewGrid) -> dict[int, tuple[int, ...]]:
    """The intrinsics an intermediate stage pins to keep the near-gauges out of Levenberg–Marquardt's way (view ->
    Cal3DS2 indices): the reference view's fx, fy, cx, cy (common zoom and shift) and the hidden principal-point
    gauge of `scene_graph.principal_point_gauge`. The final stage releases them to the design priors."""
    ref = grid.reference
    out: dict[int, tuple[int, ...]] = {ref: (0, 1, 3, 4)}
    r0, c0 = grid.position(ref)
    if grid.cols > 1:
        out[grid.index(r0, c0 + 1 if c0 + 1 < grid.cols else c0 - 1)] = (3,)
    if grid.rows > 1:  # the gauge moves cy along columns as it moves cx along rows
        view = grid.index(r0 + 1 if r0 + 1 < grid.rows else r0 - 1, c0)
        out[view] = (*out.get(view, ()), 4)
    return out


def intrinsics_map_priors(current: Sequence[Intrinsics], design: Intrinsics, sigmas: Sigmas,
                          free: frozenset[str],
                          pinned: dict[int, tuple[int, ...]] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The calibration rows of a `PriorTable` (mean, sigmas): one calibration prior per view (Cal3DS2, Cal3Fisheye or
    Cal3Unified, the design's model: the groups' indices are the same): free groups pulled to the design value with
    the design tolerance, everything else (skew, p1, p2 or a fisheye's k3, k4, a unified lens's xi, the groups this
    stage holds and the ``pinned`` indices of some views, e.g. `intrinsics_gauges`) pinned at ``current``."""
    now = calibration_vectors(current)
    mean = now.copy()
    sig = np.full(now.shape, HELD_SIGMA)
    sig[:, [2, 7, 8]] = MIN_SIGMA
    design_vec, tol = calibration_vectors([design])[0], design_tangent_sigmas(sigmas)
    for group, idx in CAL3DS2_INDICES.items():  # the groups a stage may free (`lfgraph.factors.groups`)
        if group in free:
            mean[:, list(idx)] = design_vec[list(idx)]
            sig[:, list(idx)] = tol[:, list(idx)]
    for v, indices in (pinned or {}).items():
        mean[v, list(indices)] = now[v, list(indices)]
        sig[v, list(indices)] = HELD_SIGMA
    return mean, sig


def pose_map_priors(current: np.ndarray, design: np.ndarray, reference: int, sigmas: Sigmas,
                    free: frozenset[str]) -> tuple[np.ndarray, np.ndarray]:
    """The pose rows of a `PriorTable` (mean, sigmas): the reference pose (gauge: the identity); every other
    view's rotation and position pulled to the design grid (parallel views at the nominal pitch) when free, pinned at
    ``current`` when held.

    Args:
        current: (V, 4, 4) current ``ref_T_view``; design: (V, 4, 4) the ideal grid.
    """
    mean = np.array(current, dtype=np.float64)
    mean[reference] = np.eye(4)
    sig = np.full((len(current), POSE_TANGENT), HELD_SIGMA)
    others = np.arange(len(current)) != reference
    if Group.ROTATION in free:
        mean[others, :3, :3] = design[others, :3, :3]
        sig[:, :3] = sigmas.pose[:, :3]
    if Group.POSITION in free:
        mean[others, :3, 3] = design[others, :3, 3]
        # Pose3 priors measure the error in the pose's own frame; with near-identity rotations the position sigma
        # is (to well under a percent) the same along the reference axes. The grid's plane is the reference view's
        # z = 0 plane only up to the reference view's own rotation: depth (z) gets that tilt's spread too (measured
        # on paper-5x5, 400 mm across: without it every view was pulled 4-9 mm towards z = 0)
        baseline = np.linalg.norm(design[:, :3, 3] - design[reference, :3, 3], axis=1)
        sig[:, 3:5] = sigmas.pose[:, 3:5]
        sig[:, 5] = np.hypot(sigmas.pose[:, 5], np.max(sigmas.pose[:, :2], axis=1) * baseline)  # the grid's tilt
    return mean, sig


# ---- pins: what fixes the common zoom (`lfgraph.selfcal.pins`), each a fragment with its own sigma ----------------


def board_pin_factors(corners_px: np.ndarray, valid: np.ndarray, object_points_m: np.ndarray, sigma_px: float,
                      lenses: Sequence[str]) -> gtsam.NonlinearFactorGraph:
    """A board pin: every corner a view sees in a pin frame, projected through ``board_T_ref(f)`` and the view's
    pose and intrinsics (`board_graph.add_board_observations`: GTSAM's `ProjectionFactorPPPC` of the view's lens), the
    corners held at the board's known geometry (`board_graph.RIGID_BOARD_SIGMA_M`): the board's size in pixels
    against its known size ties the focal length through its perspective.

    Args:
        corners_px: (V, F, C, 2); valid: (V, F, C); object_points_m: (C, 3) board frame; sigma_px: corner noise.
    """
    graph = gtsam.NonlinearFactorGraph()
    add_board_observations(graph, corners_px, valid, pixel_noise(sigma_px), lenses)
    add_corner_priors(graph, object_points_m, RIGID_BOARD_SIGMA_M)
    return graph


def distance_pin_factors(first: int, pixels: np.ndarray, valid: np.ndarray, distance_m: float, sigma_m: float,
                         sigma_px: float, lenses: Sequence[str]) -> gtsam.NonlinearFactorGraph:
    """A distance pin: two scene points (`pin_point_key` ``first`` and ``first + 1``) seen by the views
    (`GeneralSFMFactor2` of each view's lens, ``sigma_px``) and GTSAM's `RangeFactor3` between them: their distance,
    ``distance_m`` +- ``sigma_m``. Under the common zoom the points' depths scale, so their distance moves unless they
    lie at one depth.

    Args:
        pixels: (V, 2, 2) the two points in every view; valid: (V, 2).
    """
    graph = gtsam.NonlinearFactorGraph()
    noise = pixel_noise(sigma_px)
    factors = [lens_model(lens).gtsam("GeneralSFMFactor2") for lens in lenses]
    for v, k in zip(*np.nonzero(valid), strict=True):
        graph.add(factors[v](pixels[v, k], noise, view_pose_key(int(v)), pin_point_key(first + int(k)),
                             calib_key(int(v))))
    graph.add(gtsam.RangeFactor3(pin_point_key(first), pin_point_key(first + 1), float(distance_m),
                                 range_noise(sigma_m)))
    return graph


def plane_depth_factors(first: int, depth_m: float, sigma_m: float,
                        facing_sigma_m: float) -> gtsam.NonlinearFactorGraph:
    """A distance pin's plane of known depth: the first point's depth (its z in the reference frame, the rig frame
    whose reference view is the gauge) is ``depth_m`` +- ``sigma_m``, and the second lies at the same depth to
    within ``facing_sigma_m`` (how squarely the plane faces the array); x and y are left free (`FREE_SIGMA`). The
    distance between two points at one known depth is an angle, which a pinhole view sees through its focal length
    alone: the common zoom, whatever the hidden principal-point gauge does to triangulated depths."""
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPoint3(pin_point_key(first), np.array([0.0, 0.0, float(depth_m)]),
                                      gtsam.noiseModel.Diagonal.Sigmas(np.array([FREE_SIGMA, FREE_SIGMA, sigma_m]))))
    graph.add(gtsam.BetweenFactorPoint3(pin_point_key(first), pin_point_key(first + 1), np.zeros(3),
                                        gtsam.noiseModel.Diagonal.Sigmas(np.array([FREE_SIGMA, FREE_SIGMA,
                                                                                   facing_sigma_m]))))
    return graph


def view_pin_factor(view: int, intrinsics: Intrinsics, sigmas: np.ndarray) -> gtsam.NonlinearFactorGraph:
    """A view pin: one view's intrinsics known from a factory or an earlier calibration, a prior on its calibration
    with that calibration's sigmas (``sigmas``: fx, fy, cx, cy (px), k1, k2); the coefficients the self-calibration
    holds (skew, p1, p2, a fisheye's k3, k4, xi) are left to the design priors (`FREE_SIGMA` here)."""
    fx, fy, cx, cy, k1, k2 = (float(s) for s in sigmas)
    model = intrinsics.model
    tail = [k1 if k == "k1" else k2 if k == "k2" else FREE_SIGMA for k in model.tangent]
    graph = gtsam.NonlinearFactorGraph()
    graph.add(model.gtsam("PriorFactor")(calib_key(view), intrinsics.to_gtsam(),
                                         calibration_noise([fx, fy, FREE_SIGMA, cx, cy, *tail])))
    return graph
