"""What the rest of the rig predicts for one view-frame, and how sure it is.

A view-frame (view v's board in frame f) is predicted from everything else: the board pose of frame f fitted through
the frame's other views with the rig held fixed, then f's corners projected into v. The prediction's covariance
propagates the posterior of v's intrinsics and pose (the joint graph's marginals, `rig_marginals`) and the board
pose's own uncertainty (its fit through the other views) into the predicted corners, plus the corner noise:

    S = J_v Sigma_v J_v^T + J_b Sigma_b J_b^T + sigma^2 I        (2N x 2N for N corners)

This is the Cramér–Rao prediction of a held-out view-frame (to first order; the small correlation between the board
pose and the other views' parameters is left out). The screen (`lfgraph.pattern.screen`) uses it to tell a bad image
from a view-frame that is merely weakly constrained; `benchmarks/weak_views.py` compares it with held-out errors.
"""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np

from lfgraph.core.camera import Intrinsics, transform_points
from lfgraph.core.geometry import invert_T
from lfgraph.detect.detections import BoardObservations
from lfgraph.engine.board_problem import BoardProblem
from lfgraph.engine.optimize import gtsam_quiet
from lfgraph.engine.schur import CameraMarginals
from lfgraph.factors.keys import calib_key, view_pose_key
from lfgraph.factors.noise import RobustKernel, measurement_noise
from lfgraph.factors.values import insert_board_corners, insert_board_poses, insert_intrinsics, insert_view_poses
from lfgraph.pattern.config import CalibrateConfig
from lfgraph.pattern.joint import joint_priors
from lfgraph.pattern.scoring import fit_board_poses

FOCAL_STEP_PX = 1e-3  # central-difference steps of the numeric Jacobians: fx, fy, cx, cy (px) ...
COEFFICIENT_STEP = 1e-6  # ... lens coefficients (dimensionless) ...
POSE_STEP = 1e-6  # ... and pose tangents (rad, m)
HEAD_DIM = 5  # fx, fy, skew, cx, cy: the head of every GTSAM calibration's tangent


def rig_marginals(obs: BoardObservations, intrinsics: tuple[Intrinsics, ...], ref_T_view: np.ndarray,  # noqa: N803
                  board_T_ref: np.ndarray, object_points_m: np.ndarray,  # noqa: N803
                  config: CalibrateConfig) -> CameraMarginals:
    """The joint graph's posterior (least squares, corner sigma ``config.corner_sigma_px``) at the given state: the
    bulk board problem of ``obs`` (frames without a finite board pose left out) and its `CameraMarginals`.

    Raises:
        RuntimeError: the system is indeterminate (a parameter these boards do not fix).
    """
    frames = [f for f in range(obs.num_frames) if np.all(np.isfinite(board_T_ref[f]))]
    valid = obs.valid[:, frames]
    values = gtsam.Values()
    insert_intrinsics(values, intrinsics)
    insert_view_poses(values, ref_T_view)
    insert_board_poses(values, board_T_ref, frames)
    insert_board_corners(values, object_points_m)
    noise = measurement_noise(RobustKernel("none"), config.corner_sigma_px)
    problem = BoardProblem(joint_priors(obs, intrinsics, config), values, obs.corners_px[:, frames], valid, frames,
                           noise, tuple(i.lens for i in intrinsics))
    with gtsam_quiet():
        return CameraMarginals(problem=problem, state=values)


def view_covariance(marginals: CameraMarginals, view: int) -> np.ndarray:
    """(P, P) joint covariance of view ``view``'s calibration (GTSAM tangent: fx fy skew cx cy, coefficients) and
    pose (rotation first, on the right of ``ref_T_view``), in the marginals' units (corner sigma 1)."""
    return marginals.joint([calib_key(view), view_pose_key(view)])


def _project(intr: Intrinsics, skew: float, view_T_ref: np.ndarray, points_ref: np.ndarray) -> np.ndarray:  # noqa: N803
    """(N, 2) pixels of ``points_ref`` through a view with skew added (GTSAM's ``u = fx xd + s yd + cx``)."""
    px = intr.project(transform_points(view_T_ref, points_ref))
    return px + np.stack([skew * (px[:, 1] - intr.cy) / intr.fy, np.zeros(len(px))], axis=1)


def view_jacobian(intr: Intrinsics, ref_T_view: np.ndarray, points_ref: np.ndarray) -> np.ndarray:  # noqa: N803
    """(N, 2, P) d pixels / d (calibration tangent, pose tangent) of a view at ``points_ref`` (N, 3), by central
    differences; the order of `view_covariance`."""
    coefs = intr.model.tangent
    steps = [FOCAL_STEP_PX] * HEAD_DIM + [COEFFICIENT_STEP] * len(coefs) + [POSE_STEP] * 6
    cols = []
    for i, h in enumerate(steps):
        sides = []
        for sign in (1.0, -1.0):
            d = sign * h
            skew, pose, cal = 0.0, ref_T_view, intr
            if i < HEAD_DIM:
                if i == 2:
                    skew = d
                else:
                    name = ("fx", "fy", None, "cx", "cy")[i]
                    cal = dataclasses.replace(intr, **{name: getattr(intr, name) + d})
            elif i < HEAD_DIM + len(coefs):
                name = coefs[i - HEAD_DIM]
                cal = dataclasses.replace(intr, **{name: getattr(intr, name) + d})
            else:
                xi = np.zeros(6)
                xi[i - HEAD_DIM - len(coefs)] = d
                pose = ref_T_view @ gtsam.Pose3.Expmap(xi).matrix()
            sides.append(_project(cal, skew, invert_T(pose), points_ref))
        cols.append((sides[0] - sides[1]) / (2 * h))
    return np.stack(cols, axis=-1)


def _board_jacobian(intrinsics, ref_T_view: np.ndarray, views: list[int], ref_T_board: np.ndarray,  # noqa: N803
                    obj: np.ndarray, masks: list[np.ndarray]) -> list[np.ndarray]:
    """Per view, (N_v, 2, 6) d pixels / d board-pose tangent (on the right of ``ref_T_board``) of its masked
    corners."""
    out = []
    for v, m in zip(views, masks, strict=True):
        view_T_ref = invert_T(ref_T_view[v])  # noqa: N806
        cols = []
        for k in range(6):
            xi = np.zeros(6)
            xi[k] = POSE_STEP
            sides = [intrinsics[v].project(transform_points(view_T_ref @ ref_T_board @ gtsam.Pose3.Expmap(s * xi)
                                                            .matrix(), obj[m])) for s in (1.0, -1.0)]
            cols.append((sides[0] - sides[1]) / (2 * POSE_STEP))
        out.append(np.stack(cols, axis=-1))
    return out


@dataclasses.dataclass(frozen=True)
class ViewFramePrediction:
    """One view-frame predicted from the rest of the rig.

    Attributes:
        residual_px: (N, 2) observed minus predicted corners.
        covariance_px2: (2N, 2N) the prediction error's covariance (rows x0, y0, x1, ...), corner noise included.
        sigma_px: corner noise per coordinate used.
    """

    residual_px: np.ndarray
    covariance_px2: np.ndarray
    sigma_px: float

    @property
    def rms_px(self) -> float:
        """RMS over the corners of the observed-minus-predicted distance."""
        return float(np.sqrt(np.mean(np.sum(self.residual_px**2, axis=1))))

    @property
    def predicted_rms_px(self) -> float:
        """The RMS distance the covariance predicts: sqrt(trace(S) / N)."""
        return float(np.sqrt(np.trace(self.covariance_px2) / len(self.residual_px)))

    @property
    def deflated_rms_px(self) -> float:
        """The miss with the rig's own uncertainty taken out: sqrt(sigma^2 r^T S^-1 r / N), in px. Equals `rms_px`
        when the rest of the rig pins the view-frame; smaller along directions the rig knows only loosely."""
        r = self.residual_px.reshape(-1)
        return float(self.sigma_px * np.sqrt(r @ np.linalg.solve(self.covariance_px2, r) / len(self.residual_px)))


def frame_jacobians(obs: BoardObservations, intrinsics: tuple[Intrinsics, ...], ref_T_view: np.ndarray,  # noqa: N803
                    frame: int, views: list[int], ref_T_board: np.ndarray  # noqa: N803
                    ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per view of ``views``, the (2N, P) Jacobian of its corners of ``frame`` by its parameters (`view_jacobian`)
    and the (2N, 6) one by the board pose, at ``ref_T_board``: computed once for a frame whose views are predicted in
    turn."""
    obj = obs.board.object_points()
    masks = [obs.valid[v, frame] for v in views]
    boards = _board_jacobian(intrinsics, ref_T_view, views, ref_T_board, obj, masks)
    out = {}
    for v, m, jb in zip(views, masks, boards, strict=True):
        jv = view_jacobian(intrinsics[v], ref_T_view[v], transform_points(ref_T_board, obj[m]))
        out[v] = (jv.reshape(-1, jv.shape[-1]), jb.reshape(-1, 6))
    return out


def predict_view_frame(obs: BoardObservations, intrinsics: tuple[Intrinsics, ...], ref_T_view: np.ndarray,  # noqa: N803
                       marginals: CameraMarginals, view: int, frame: int, helpers: list[int], sigma_px: float,
                       start_board_T_ref: np.ndarray,  # noqa: N803
                       jacobians: dict[int, tuple[np.ndarray, np.ndarray]] | None = None) -> ViewFramePrediction:
    """View ``view``'s corners of frame ``frame`` predicted through the fixed rig, the board pose fitted through the
    ``helpers`` (other views seeing the frame; empty: through ``view`` itself, then only its own fit is judged).

    The covariance propagates the joint posterior of the view's and the helpers' calibrations and poses (their
    errors are correlated: a far view's position and focal length move with the views that place the board), the
    board pose's fit to the helpers' corner noise, and the view's own corner noise.

    Args:
        obs: the corners; intrinsics, ref_T_view: the rig.
        marginals: the rig's posterior (`rig_marginals`), in units of a 1 px corner sigma.
        sigma_px: corner noise per coordinate (scales the posterior).
        start_board_T_ref: (4, 4) a start for the board pose of the frame.
        jacobians: `frame_jacobians` of the view and the helpers, when several views of the frame are predicted
            (the Jacobians are linearised there instead of at this prediction's board pose).
    """
    used = helpers or [view]
    valid = np.zeros_like(obs.valid)
    valid[used, frame] = obs.valid[used, frame]
    starts = np.full((obs.num_frames, 4, 4), np.nan)
    starts[frame] = start_board_T_ref
    board_T_ref = fit_board_poses(intrinsics, ref_T_view, dataclasses.replace(obs, valid=valid), starts)[frame]  # noqa: N806
    ref_T_board = invert_T(board_T_ref)  # noqa: N806
    obj = obs.board.object_points()
    m = obs.valid[view, frame]
    residual = obs.corners_px[view, frame][m] - intrinsics[view].project(
        transform_points(invert_T(ref_T_view[view]) @ ref_T_board, obj[m]))
    jac = jacobians or frame_jacobians(obs, intrinsics, ref_T_view, frame, [view, *helpers], ref_T_board)
    jv, jb = jac[view]
    n = len(jv)
    if not helpers:
        cov = sigma_px**2 * (jv @ view_covariance(marginals, view) @ jv.T + np.eye(n))
        return ViewFramePrediction(residual, cov, sigma_px)
    jhb = np.concatenate([jac[h][1] for h in helpers])
    info_inv = np.linalg.pinv(jhb.T @ jhb)
    # d prediction / d helper parameters through the board's fit: J_b (J^T J)^-1 J^T J_theta, per helper
    gain = jb @ info_inv
    blocks = [-gain @ jac[h][1].T @ jac[h][0] for h in helpers]
    g = np.concatenate([jv, *blocks], axis=1)  # the miss moves against the view's parameters, with the helpers'
    keys = [k for x in [view, *helpers] for k in (calib_key(x), view_pose_key(x))]
    cov = sigma_px**2 * (g @ marginals.joint(keys) @ g.T + np.eye(n) + gain @ jb.T)
    return ViewFramePrediction(residual, cov, sigma_px)
