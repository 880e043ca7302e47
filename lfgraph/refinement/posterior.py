"""The posterior of a refinement fit: marginals of the MAP graph, the predicted transfer error at infinity they
imply, and the chi-square deviate used by the significance tests (`lfgraph.refinement.assess`)."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.geometry import make_T, rotation_from_rotvec, to_pose3
from lfgraph.engine.optimize import gtsam_quiet
from lfgraph.engine.schur import CameraMarginals
from lfgraph.engine.schur_system import camera_block, schur_layout
from lfgraph.factors.groups import DRIFT_GROUPS, VIEW_DIRECTIONS, Group
from lfgraph.factors.keys import LANDMARK_CHAR, calib_key, view_pose_key
from lfgraph.factors.noise import measurement_noise
from lfgraph.factors.scene_graph import holds_rotation_gauge, principal_point_gauge, rotation_gauge
from lfgraph.judge.evaluation import reference_pixels
from lfgraph.refinement.config import RefineConfig, Stage
from lfgraph.refinement.priors import ViewPriors
from lfgraph.refinement.scatter import (
    bending_functionals,
    prior_information,
    track_scores_bulk,
    track_scores_graph,
    widen_bending,
)
from lfgraph.refinement.stages import stage_graph, stage_problem

GROUPS = {g: VIEW_DIRECTIONS[g] for g in DRIFT_GROUPS}  # of the 10 directions (`lfgraph.factors.groups`)
ROTATION = VIEW_DIRECTIONS[Group.ROTATION]  # also tested jointly: a tilt and a roll each just short of significance
#                                            can be clear together
TRANSFER_SAMPLES = 7  # reference pixels per axis for the predicted transfer error at infinity
JACOBIAN_STEP = 1e-6  # rad and px: numerical derivative of the transfer at infinity
INTRINSIC_COLUMNS = (0, 1, 3, 4)  # fx, fy, cx, cy in a calibration variable's tangent (skew at 2, then the lens)


def chi2_sigma(d2: float, dof: int) -> float:
    """The one-sided normal deviate equivalent to a chi-square value (Wilson-Hilferty; no scipy needed)."""
    if dof <= 0 or not np.isfinite(d2):
        return 0.0
    a = 2.0 / (9.0 * dof)
    return float(((max(d2, 0.0) / dof) ** (1.0 / 3.0) - (1.0 - a)) / np.sqrt(a))


@dataclass(frozen=True)
class Posterior:
    """Marginal covariances of the refinement graph at its solution, per view.

    ``pose_cov``: (V, 6, 6) body-frame Pose3 covariance (rotation x, y, z in rad, then position in m);
    ``intr_cov``: (V, 4, 4) fx, fy, cx, cy (px^2) — from the graph when a stage freed them, else zeros (held);
    ``cross``: (V, 6, 4) pose-intrinsics cross covariance (zeros when intrinsics were held);
    ``intrinsics_free``: whether the graph freed fx, fy, cx, cy;
    ``held``: (V, 10) which of rotation x, y, z, position x, y, z, fx, fy, cx, cy the graph held by its structure
    (the reference view, held views, gauges, intrinsics a stage does not free: `held_directions`) —
    never inferred from the size of a sigma, which mixes rad, m and px and shrinks as data improve;
    ``bending``: the variance factors by which the tracks' scatter widened the rig's bending modes
    (`lfgraph.refinement.scatter`; ones: the graph's marginals kept); ``graph``: the graph's own marginals before
    that widening (what the verdicts' tests are set on), None when this is them."""

    pose_cov: np.ndarray
    intr_cov: np.ndarray
    cross: np.ndarray
    intrinsics_free: bool
    sigma_px: float
    held: np.ndarray | None = None
    bending: np.ndarray | None = None
    graph: Posterior | None = None

    def held_mask(self, v: int) -> np.ndarray:
        """(10,) directions of view v held by structure (all intrinsics when the graph did not free them)."""
        if self.held is not None:
            return self.held[v]
        mask = np.zeros(10, dtype=bool)
        mask[6:] = not self.intrinsics_free
        return mask


def held_directions(calib: Calibration, stage: Stage, held_views: frozenset[int],
                    priors: ViewPriors | None = None) -> np.ndarray:
    """(V, 10) the directions a stage's graph holds by construction: everything of the reference view and of held
    views; fx, fy, cx, cy unless the stage frees them, and then the principal-point gauge in the free fit (no
    ``priors``); the rotation gauge in a stereo pair under MAP ``priors`` (`lfgraph.factors.scene_graph`, as
    `pose_priors` and `intrinsics_priors` hold them)."""
    n = calib.num_views
    mask = np.zeros((n, 10), dtype=bool)
    mask[calib.grid.reference] = True
    for v in held_views:
        mask[v] = True
    intr_free = Stage(stage).frees_intrinsics
    gauge, rgauge = principal_point_gauge(calib), rotation_gauge(calib)
    if intr_free and gauge is not None and priors is None:  # held exactly only in the free fit
        mask[gauge[0], 6 + gauge[1] - 1] = True  # Cal3DS2 index 3/4 (cx/cy) -> 8/9
    if not intr_free:
        mask[:, 6:] = True
    if rgauge is not None and holds_rotation_gauge(calib, intr_free) and priors is not None:
        mask[rgauge[0], rgauge[1]] = True
    if stage == Stage.INTRINSICS:
        mask[:, :6] = True
    return mask


def posterior(calib: Calibration, fit, config: RefineConfig) -> Posterior | None:
    """Marginals of the last free stage's graph built at the fit's solution (None when no free stage ran) with the
    noise model and priors the fit ran with (`FitResult.noise`, `FitResult.priors`), the bending modes widened to the
    tracks' own scatter where that is larger (`lfgraph.refinement.scatter`)."""
    n = calib.num_views
    if fit.last_stage is None or fit.valid.shape[1] == 0:
        return None
    priors = fit.priors
    model = measurement_noise(config.noise if fit.noise is None else fit.noise, fit.sigma_px)
    intr_free = fit.last_stage.frees_intrinsics

    def build(projections: bool = True):
        return stage_graph(fit.last_stage, fit.calib, fit.pixels, fit.valid, fit.points, model,
                           config.scale_sigma_mm, fit.held, priors, projections)

    try:
        with gtsam_quiet():
            bulk = stage_problem(fit.last_stage, fit.calib, fit.pixels, fit.valid, fit.points, model,
                                 config.scale_sigma_mm, fit.held, priors)
            graph, values = (None, None) if bulk is not None else build()
            marginals = CameraMarginals(graph, values, LANDMARK_CHAR, *(bulk or (None, None)), build=build)
            if bulk is not None:
                layout, scores = bulk[0].layout, track_scores_bulk(*bulk)
                values = bulk[1][0]
            else:
                layout = schur_layout(values, LANDMARK_CHAR)
                scores = track_scores_graph(graph, values, layout)
            keys = [int(k) for k, lm in zip(layout.keys, layout.landmark, strict=True) if not lm]
            cov = marginals.joint(keys)
            prior_info = prior_information(bulk[0].graph if bulk is not None else build(False)[0], values, layout)
    except RuntimeError:  # an indeterminate system: report no posterior rather than a wrong one
        return None
    held = held_directions(calib, fit.last_stage, fit.held, priors)
    wide, factors = widen_bending(cov, bending_functionals(calib, layout, ~held[:, :3]), scores, prior_info)

    def per_view(c: np.ndarray) -> tuple[np.ndarray, ...]:
        pose_cov, intr_cov, cross = np.zeros((n, 6, 6)), np.zeros((n, 4, 4)), np.zeros((n, 6, 4))
        for v in range(n):
            p = camera_block(layout, view_pose_key(v))
            pose_cov[v] = c[p, p]
            if intr_free:
                k = camera_block(layout, calib_key(v)).start + np.array(INTRINSIC_COLUMNS)
                intr_cov[v] = c[np.ix_(k, k)]
                cross[v] = c[p][:, k]
        return pose_cov, intr_cov, cross

    graph_post = Posterior(*per_view(cov), intr_free, fit.sigma_px, held)
    return Posterior(*per_view(wide), intr_free, fit.sigma_px, held, factors, graph_post)


def infinity_rays(calib: Calibration, samples: int = TRANSFER_SAMPLES) -> np.ndarray | tuple[np.ndarray, ...]:
    """(N, 3) rays of ``samples`` x ``samples`` reference pixels over 5-95 % of the image (the reference's own lens
    undistorts them; pixels a folding lens has no ray for are left out): where the transfer at infinity is measured.
    In a free arrangement (a ring: views that do not see the reference's directions) each view's own pixels' rays,
    in the reference frame, one (N_v, 3) array per view."""
    if calib.grid.is_free:
        return tuple(_own_rays(calib, v, samples) @ calib.ref_T_view[v][:3, :3].T for v in range(calib.num_views))
    return _own_rays(calib, calib.grid.reference, samples)


def _own_rays(calib: Calibration, ref: int, samples: int) -> np.ndarray:
    xy = calib.intrinsics[ref].undistort(reference_pixels(calib.image_size(ref), samples))
    xy = xy[np.all(np.isfinite(xy), axis=1)]  # corners a strong barrel lens folds over have no ray
    return np.column_stack([xy, np.ones(len(xy))])


def _transfer(calib: Calibration, v: int, rays: np.ndarray, omega: np.ndarray, dk: np.ndarray) -> np.ndarray:
    """Reference rays at infinity projected into view v turned by body-frame ``omega`` with fx, fy, cx, cy + dk."""
    import dataclasses

    rays = rays[v] if isinstance(rays, tuple) else rays  # a free arrangement's: each view's own (`infinity_rays`)
    R = calib.ref_T_view[v][:3, :3] @ rotation_from_rotvec(omega)  # noqa: N806
    i = calib.intrinsics[v]
    i = dataclasses.replace(i, fx=i.fx + dk[0], fy=i.fy + dk[1], cx=i.cx + dk[2], cy=i.cy + dk[3])
    return i.project(rays @ R).ravel()


def transfer_jacobian(calib: Calibration, v: int, rays: np.ndarray) -> np.ndarray:
    """(2S, 7) derivative of the transfer at infinity into view v by body rotation (3, rad) and fx, fy, cx, cy."""
    base = _transfer(calib, v, rays, np.zeros(3), np.zeros(4))
    cols = []
    for k in range(7):
        step = np.zeros(7)
        step[k] = JACOBIAN_STEP
        cols.append((_transfer(calib, v, rays, step[:3], step[3:]) - base) / JACOBIAN_STEP)
    return np.column_stack(cols)


def predicted_transfer_px(calib: Calibration, post: Posterior, v: int, rays: np.ndarray) -> float:
    """RMS over reference pixels of the 1-sigma transfer error at infinity the posterior predicts for view v."""
    cov = np.zeros((7, 7))
    cov[:3, :3] = post.pose_cov[v][:3, :3]
    cov[3:, 3:] = post.intr_cov[v]
    cov[:3, 3:] = post.cross[v][:3]
    cov[3:, :3] = post.cross[v][:3].T
    J = transfer_jacobian(calib, v, rays)  # noqa: N806
    per_coord = np.einsum("ij,jk,ik->i", J, cov, J)
    return float(np.sqrt(max(np.sum(per_coord) / (len(per_coord) / 2), 0.0)))


def pose_change(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """(6,) body-frame change, rotation (rad) then translation (m): Logmap(before^-1 after), as a Pose3 prior."""
    return np.asarray(gtsam.Pose3.Logmap(to_pose3(before).between(to_pose3(after))))


def group_mask(groups: tuple[str, ...]) -> np.ndarray:
    """(10,) the directions of parameter groups (`GROUPS` names, or ``"rotation"`` for all three rotations)."""
    keep = np.zeros(10, dtype=bool)
    for g in groups:
        keep[list(VIEW_DIRECTIONS[Group(g)])] = True
    return keep


def restricted(post: Posterior, v: int, groups: tuple[str, ...]) -> Posterior:
    """``post`` with view v's covariance kept only in the directions of ``groups`` (the joint ``"rotation"`` group
    only when neither pan/tilt nor roll is among them)."""
    if Group.PAN_TILT in groups or Group.ROLL in groups:
        groups = tuple(g for g in groups if g != Group.ROTATION)
    keep = group_mask(groups)
    pose_cov, intr_cov, cross = post.pose_cov.copy(), post.intr_cov.copy(), post.cross.copy()
    pose_cov[v] = pose_cov[v] * np.outer(keep[:6], keep[:6])
    intr_cov[v] = intr_cov[v] * np.outer(keep[6:], keep[6:])
    cross[v] = cross[v] * np.outer(keep[:6], keep[6:])
    return Posterior(pose_cov, intr_cov, cross, post.intrinsics_free, post.sigma_px, post.held)


def change_size_px(before: Calibration, after: Calibration,
                   groups: dict[int, tuple[str, ...]] | None = None) -> np.ndarray:
    """(V,) how much a change moves each view's image: its transfer at infinity (RMS over the reference image, px),
    the figure disparity and refocusing see and that ``tolerance_px`` is stated in. With ``groups`` (view -> the
    groups whose change was significant) only those groups' part of the change counts: a significant position change
    that carries an insignificant turn is not a turn that matters."""
    from lfgraph.judge.evaluation import transfer_error_at_infinity

    if groups is None:
        return transfer_error_at_infinity(after, before)
    poses = np.array(before.ref_T_view)
    intr = list(before.intrinsics)
    for v, gs in groups.items():
        d = pose_change(before.ref_T_view[v], after.ref_T_view[v])
        poses[v] = before.ref_T_view[v] @ make_T(rotation_from_rotvec(d[:3] * group_mask(gs)[:3]), np.zeros(3))
        if "intrinsics" in gs:
            intr[v] = after.intrinsics[v]
    return transfer_error_at_infinity(before.replace(ref_T_view=poses, intrinsics=tuple(intr)), before)
