"""Pattern calibration's joint graph as a bulk problem: every board corner's projection into every view evaluated in
numpy, the normal equations assembled by batched products, solved by the engine's Levenberg–Marquardt
(`lfgraph.engine.schur.optimize_problem`) and read by its one posterior path (`CameraMarginals`).

The model is `lfgraph.factors.board_graph`'s: corner j of frame f seen by view v through the camera
``board_T_ref(f).compose(ref_T_view(v))`` (GTSAM's ``ProjectionFactorPPPC``), each view's lens model
(`lfgraph.lenses`, its ``coefficient_jacobian``), the other factors (corner priors, the gauge, the intrinsics pins)
as a small GTSAM graph on the same variables. Residuals and Jacobians are GTSAM's (poses perturbed on the right,
``pose * Exp([w, v])``; checked against GTSAM's factors in tests/engine/test_board_problem.py), so the fit converges
to the minimum GTSAM's optimiser finds, without a C++ factor per observation. The board poses are eliminated as a
refinement's landmarks are (6x6 blocks in the Schur complement: no factor ties two frames), leaving a small dense
system of the views' intrinsics and poses and the board's corners.
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from lfgraph.engine.bulk_noise import BulkNoise, NotBulk
from lfgraph.engine.schur_system import (
    NotReducible,
    ReducedSystem,
    camera_block,
    full_step,
    schur_layout,
    sparse_jacobian,
    vector_values,
)
from lfgraph.factors.keys import board_corner_key, board_pose_key, calib_key, view_pose_key
from lfgraph.lenses import COEFFICIENTS, HEAD, lens_code, lens_coefficient_jacobian, lens_distort, lens_model

POSE_DIM = 6
POINT_DIM = 3
BOARD_POSE_CHAR = chr(gtsam.Symbol(board_pose_key(0)).chr())  # the landmarks of this problem


def _cross_rows(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(..., 2, 3): each row a of ``q`` (..., 2, 3) crossed with ``p`` (..., 3): ``a [p]x`` = (a x p)^T."""
    p0, p1, p2 = p[..., None, 0], p[..., None, 1], p[..., None, 2]
    q0, q1, q2 = q[..., 0], q[..., 1], q[..., 2]
    return np.stack([q1 * p2 - q2 * p1, q2 * p0 - q0 * p2, q0 * p1 - q1 * p0], axis=-1)


def _times(j: np.ndarray, R: np.ndarray, axis: int) -> np.ndarray:  # noqa: N803
    """(V, F, C, 2, 3) rows times ``R^T`` of their view (``axis`` 0, R (V, 3, 3)) or frame (``axis`` 1, (F, 3, 3)):
    one matrix product per view or frame."""
    moved = np.moveaxis(j, axis, 0)
    out = np.matmul(moved.reshape(len(R), -1, 3), np.swapaxes(R, 1, 2)).reshape(moved.shape)
    return np.moveaxis(out, 0, axis)


class BoardProblem:
    """Board corners seen by views with free intrinsics and poses, the board pose of every frame (the landmarks,
    6x6 blocks) and the board's corners free (with their priors in ``graph``); state: `gtsam.Values` of every
    variable.

    Args:
        graph: the other factors (corner priors, gauge, intrinsics pins) on the same keys, none on a board pose.
        values: the start: every view's calibration and pose, every used frame's board pose, every corner.
        corners_px: (V, F, C, 2) observed corners of the used ``frames`` (in that order); valid: (V, F, C).
        frames: the frame index of each of the F used frames (their board-pose keys), increasing.
        noise: the measurement noise model of every observation (a 2-D Gaussian, optionally robust).
        lenses: each view's lens model (its ``coefficient_jacobian`` is needed).
        fixed_corners: (C, 3) the board's corners as constants (then not among ``values``: a pair's relative pose,
            as ``cv2.stereoCalibrate`` fits it); None: they are variables (with their priors in ``graph``).

    Raises:
        NotReducible: a noise model that is not a 2-D Gaussian, a lens without coefficient Jacobian, a factor of
            ``graph`` on a board pose, a corner behind its camera at the start.
    """

    def __init__(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, corners_px: np.ndarray,
                 valid: np.ndarray, frames: Sequence[int], noise: gtsam.noiseModel.Base, lenses: Sequence[str],
                 fixed_corners: np.ndarray | None = None):
        try:
            self.noise = BulkNoise(noise)
        except NotBulk as e:
            raise NotReducible(str(e)) from None
        models = [lens_model(lens) for lens in lenses]
        if any(m.coefficient_jacobian is None for m in models):
            raise NotReducible("a lens model without coefficient Jacobian")
        self.graph, self.uv, self.valid = graph, np.asarray(corners_px, dtype=np.float64), np.asarray(valid, bool)
        self.n_views, self.n_frames, self.n_corners = self.valid.shape
        self.frames = [int(f) for f in frames]
        self.fixed_corners = None if fixed_corners is None else np.asarray(fixed_corners, dtype=np.float64)
        self.models, self.codes = models, np.array([lens_code(m.name) for m in models])
        self.n_coef = max(len(m.tangent) for m in models)
        self.extrapolate = self.noise.kernel is not None and self.noise.kernel.vectorised
        self.noise_cost = float(self.valid.sum())
        self.layout = schur_layout(values, BOARD_POSE_CHAR, POSE_DIM)
        if self.layout.n_landmarks != self.n_frames or np.any(np.diff(self.frames) <= 0):
            raise NotReducible("the board poses of the values are not the frames'")
        self.n_c = self.layout.n_camera
        self._indices()
        keys = graph.keys()  # held: iterating GTSAM's temporary key set directly crashes
        if any(gtsam.Symbol(k).chr() == ord(BOARD_POSE_CHAR) for k in list(keys)):
            raise NotReducible("a factor on a board pose")
        self._last: tuple[gtsam.Values, np.ndarray | None] | None = None
        if self._whitened_residuals(values) is None:
            raise NotReducible("a board corner behind its camera at the start")

    def _indices(self) -> None:
        """Camera-column indices of every view's (intrinsics, pose) and every corner; a view's unused coefficient
        columns (a model with fewer than ``n_coef``) point at a dummy column ``n_c``, dropped after assembly."""
        lay, n = self.layout, self.n_c
        cam = np.full((self.n_views, len(HEAD) + self.n_coef + POSE_DIM), n, dtype=np.int64)
        for v in range(self.n_views):
            k = camera_block(lay, calib_key(v))
            cam[v, :k.stop - k.start] = np.arange(k.start, k.stop)
            p = camera_block(lay, view_pose_key(v))
            cam[v, -POSE_DIM:] = np.arange(p.start, p.stop)
        self.cam_idx = cam
        self.corner_idx = None
        if self.fixed_corners is None:
            blocks = [camera_block(lay, board_corner_key(c)) for c in range(self.n_corners)]
            self.corner_idx = np.array([np.arange(b.start, b.stop) for b in blocks])

    def _read(self, values: gtsam.Values) -> tuple[np.ndarray, ...]:
        """(V, 5) fx fy s cx cy, (7, V) coefficients (`COEFFICIENTS`), (V, 4, 4) poses, (F, 4, 4) board poses,
        (C, 3) corners."""
        cals = [getattr(values, f"at{m.gtsam_name}")(calib_key(v)) for v, m in enumerate(self.models)]
        head = np.array([[c.fx(), c.fy(), c.skew(), c.px(), c.py()] for c in cals])
        coef = np.zeros((len(COEFFICIENTS), self.n_views))
        for v, (c, m) in enumerate(zip(cals, self.models, strict=True)):
            for k in m.tangent:
                coef[COEFFICIENTS.index(k), v] = float(getattr(c, k)())
        poses = np.stack([values.atPose3(view_pose_key(v)).matrix() for v in range(self.n_views)])
        boards = np.stack([values.atPose3(board_pose_key(f)).matrix() for f in self.frames])
        corners = self.fixed_corners if self.fixed_corners is not None else np.stack(
            [np.asarray(values.atPoint3(board_corner_key(c))) for c in range(self.n_corners)])
        return head, coef, poses, boards, corners

    def _project(self, values: gtsam.Values):
        """Every slot's points in the reference frame and in its camera, and their normalised coordinates, or None
        when an observed corner is behind its camera: (head, coef, ra, rb, x_ref, pc, x, y, z, lens codes, the
        coefficients broadcast to the slots)."""
        head, coef, poses, boards, corners = self._read(values)
        V, F, C = self.n_views, self.n_frames, self.n_corners  # noqa: N806
        rb, tb, ra, ta = boards[:, :3, :3], boards[:, :3, 3], poses[:, :3, :3], poses[:, :3, 3]
        x_ref = np.matmul(corners[None] - tb[:, None], rb)  # (F, C, 3): R_B^T (X - t_B)
        pc = np.matmul((x_ref[None] - ta[:, None, None]).reshape(V, F * C, 3), ra).reshape(V, F, C, 3)
        z = pc[..., 2]
        if not np.all(z[self.valid] > 0):
            return None
        z = np.where(self.valid, z, 1.0)
        x, y = pc[..., 0] / z, pc[..., 1] / z
        code = np.broadcast_to(self.codes[:, None, None], x.shape)
        cf = np.broadcast_to(coef[:, :, None, None], (len(COEFFICIENTS), V, F, C))
        return head, coef, ra, rb, x_ref, pc, x, y, z, code, cf

    def _residuals(self, values: gtsam.Values, jacobians: bool):
        """Whitened residuals (V, F, C, 2) (0 where not observed) and, with ``jacobians``, those of the camera
        (V, F, C, 2, 5 + n_coef + 6), board pose (.., 6) and corner (.., 3) blocks; None when an observed corner is
        behind its camera."""
        projected = self._project(values)
        if projected is None:
            return None
        head, coef, ra, rb, x_ref, pc, x, y, z, code, cf = projected
        lens = lens_distort(code, cf, x, y, jacobian=jacobians)
        xd, yd = lens[:2]
        fx, fy, s, cx, cy = (head[:, i, None, None] for i in range(5))
        r = np.stack([fx * xd + s * yd + cx, fy * yd + cy], axis=-1) - self.uv
        r[~self.valid] = 0.0
        e = self.noise.whiten(r.reshape(-1, 2)).reshape(r.shape)
        if not jacobians:
            return e
        sw = self.noise.sqrt_weights(e.reshape(-1, 2))
        if sw is not None:
            e = e * sw.reshape(e.shape)
        rows = self._row_weights(sw)
        d00, d01, d10, d11 = lens[2:]
        V, F, C = self.valid.shape  # noqa: N806
        nk = len(HEAD) + self.n_coef
        jcam = np.zeros((V, F, C, 2, nk + POSE_DIM))
        # the head's and coefficients' pixel derivatives (K2 = [[fx, s], [0, fy]] times the lens's), then whitened
        jcam[..., 0, 0], jcam[..., 0, 2], jcam[..., 0, 3] = xd, yd, 1.0
        jcam[..., 1, 1], jcam[..., 1, 4] = yd, 1.0
        cj = lens_coefficient_jacobian(code, cf, x, y, self.n_coef)
        jcam[..., 0, len(HEAD):nk] = fx[..., None] * cj[..., 0, :] + s[..., None] * cj[..., 1, :]
        jcam[..., 1, len(HEAD):nk] = fy[..., None] * cj[..., 1, :]
        jcam[..., :nk] = rows(jcam[..., :nk])
        # whitened d pixel / d (x, y), then d pixel / d pc: (V, F, C, 2, 3)
        jxy = rows(np.stack([np.stack([fx * d00 + s * d10, fx * d01 + s * d11], -1),
                             np.stack([fy * d10, fy * d11], -1)], -2))
        iz = (1.0 / z)[..., None, None]
        jpc = np.concatenate([jxy, -(jxy[..., 0:1] * x[..., None, None] + jxy[..., 1:2] * y[..., None, None])],
                             axis=-1) * iz
        jcam[..., nk:nk + 3] = _cross_rows(jpc, pc)
        jcam[..., nk + 3:] = -jpc
        q = _times(jpc, ra, 0)  # jpc R_A^T
        jboard = np.concatenate([_cross_rows(q, np.broadcast_to(x_ref[None], pc.shape)), -q], axis=-1)
        # d pc / d corner: R_A^T R_B^T (none for constant corners)
        return e, jcam, jboard, None if self.fixed_corners is not None else _times(q, rb, 1)

    def _row_weights(self, sw: np.ndarray | None):
        """The map whitening raw (V, F, C, 2, k) Jacobian rows by the noise model, weighting them by the robust
        kernel and zeroing them where nothing was observed (rows are mixed by a non-isotropic model's R, then scaled:
        it commutes with everything built from them row by row)."""
        scale = self.valid[..., None] if sw is None else sw.reshape(*self.valid.shape, 2) * self.valid[..., None]
        if self.noise.isotropic_sigma is not None:
            scale = scale * (1.0 / self.noise.isotropic_sigma)
            return lambda j: j * scale[..., None]
        return lambda j: np.einsum("ij,...jk->...ik", self.noise.sqrt_information, j) * scale[..., None]

    def _whitened_residuals(self, state: gtsam.Values) -> np.ndarray | None:
        """`_residuals` without Jacobians, kept for the last state asked (the optimiser's states are new objects,
        never modified in place: its start's error follows the constructor's check, the result's RMS its last
        error)."""
        if self._last is None or self._last[0] is not state:
            self._last = (state, self._residuals(state, False))
        return self._last[1]

    def rms_px(self, state: gtsam.Values) -> float:
        """RMS over the observations of the whitened residual's length (px for a 1-px isotropic noise model; what
        OpenCV's calibration functions return as their RMS)."""
        e = self._whitened_residuals(state)
        return float(np.sqrt(np.sum(e[self.valid] ** 2) / max(int(self.valid.sum()), 1)))

    def error(self, state: gtsam.Values) -> float:
        """Cost at ``state``: the observations' noise-model error plus the other factors' GTSAM error; inf when a
        corner is behind its camera."""
        e = self._whitened_residuals(state)
        if e is None:
            return float("inf")
        other = float(self.graph.error(state)) if self.graph.size() else 0.0
        return self.noise.cost(e[self.valid]) + other

    def system(self, state: gtsam.Values) -> ReducedSystem:
        """The undamped normal equations at ``state`` in Schur form: the board poses' 6x6 blocks V (F, 6, 6), their
        coupling W (F, 6, n_c) to the camera variables (intrinsics, view poses, corners) and those's H (n_c, n_c).

        Raises:
            NotReducible: a corner behind its camera at ``state``.
        """
        out = self._residuals(state, True)
        if out is None:
            raise NotReducible("a board corner behind its camera at the linearisation point")
        sys_ = _normal_equations(*out, self.cam_idx, self.corner_idx, self.n_c)
        if self.graph.size():
            rows, cols, vals, _ = sparse_jacobian(self.graph.linearize(state), self.layout)
            A = np.zeros((int(rows.max()) + 1, self.n_c + 1))  # noqa: N806
            np.add.at(A, (rows, np.where(cols < self.layout.n, self.layout.col_cam[np.minimum(cols, self.layout.n - 1)],
                                         self.n_c)), vals)
            sys_.H += A[:, :self.n_c].T @ A[:, :self.n_c]
            sys_.g_c += A[:, :self.n_c].T @ A[:, self.n_c]
        return sys_

    def retract(self, state: gtsam.Values, dl: np.ndarray, dc: np.ndarray) -> gtsam.Values:
        """``state`` moved by the board poses' step ``dl`` (F, 6) and the other variables' ``dc`` (n_c,)."""
        return state.retract(vector_values(self.layout, full_step(self.layout, dl, dc)))


def _gram(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Batched a^T b of (..., m, i) and (..., m, j)."""
    return np.matmul(np.swapaxes(a, -1, -2), b)


def _normal_equations(e: np.ndarray, jc: np.ndarray, jb: np.ndarray, jx: np.ndarray, cam_idx: np.ndarray,
                      corner_idx: np.ndarray, n: int) -> ReducedSystem:
    """The observations' J^T J and -J^T e in Schur form: the board poses' blocks (per frame), their coupling to the
    camera variables (per view and frame: a view's intrinsics and pose; per frame and corner) and the camera
    variables' block (per view, per view and corner, per corner), scattered by index."""
    V, F, C = e.shape[:3]  # noqa: N806
    kc = jc.shape[-1]
    jb_f = np.moveaxis(jb, 1, 0)  # (F, V, C, 2, 6)
    jx_c = None if jx is None else np.moveaxis(jx, 2, 0)  # (C, V, F, 2, 3)
    jc_vc = np.moveaxis(jc, 2, 1)  # (V, C, F, 2, kc)
    H = np.zeros((n + 1, n + 1))  # noqa: N806  (the last row and column collect the padding)
    blocks = [(cam_idx, cam_idx, _gram(jc.reshape(V, -1, kc), jc.reshape(V, -1, kc)))]
    if corner_idx is not None:
        blocks += [(cam_idx[:, None], corner_idx[None], _gram(jc_vc.reshape(V, C, -1, kc),
                                                              np.moveaxis(jx, 2, 1).reshape(V, C, -1, POINT_DIM))),
                   (corner_idx, corner_idx, _gram(*(jx_c.reshape(C, -1, POINT_DIM),) * 2))]
    for i, (ri, ci, block) in enumerate(blocks):
        H[ri[..., :, None], ci[..., None, :]] += block
        if i == 1:
            H[ci[..., :, None], ri[..., None, :]] += np.swapaxes(block, -1, -2)
    W = np.zeros((F, POSE_DIM, n + 1))  # noqa: N806
    cb = _gram(jb.reshape(V, F, -1, POSE_DIM), jc.reshape(V, F, -1, kc))  # (V, F, 6, kc)
    frame = np.arange(F)[None, :, None, None]
    W[frame, np.arange(POSE_DIM)[None, None, :, None], cam_idx[:, None, None, :]] += cb
    if corner_idx is not None:
        bx = _gram(np.moveaxis(jb_f, 2, 1).reshape(F, C, -1, POSE_DIM), np.moveaxis(jx, 1, 0).swapaxes(1, 2).reshape(
            F, C, -1, POINT_DIM))  # (F, C, 6, 3)
        frame_c = np.arange(F)[:, None, None, None]
        W[frame_c, np.arange(POSE_DIM)[None, None, :, None], corner_idx[None, :, None, :]] += bx
    ev = e[..., None]
    g = np.zeros(n + 1)
    np.add.at(g, cam_idx, -_gram(jc.reshape(V, -1, kc), ev.reshape(V, -1, 1))[..., 0])
    if corner_idx is not None:
        g_x = _gram(jx_c.reshape(C, -1, POINT_DIM), np.moveaxis(ev, 2, 0).reshape(C, -1, 1))[..., 0]
        np.add.at(g, corner_idx, -g_x)
    jbr = jb_f.reshape(F, -1, POSE_DIM)
    return ReducedSystem(_gram(jbr, jbr), W[:, :, :n], -_gram(jbr, np.moveaxis(ev, 1, 0).reshape(F, -1, 1))[..., 0],
                         H[:n, :n], g[:n])
