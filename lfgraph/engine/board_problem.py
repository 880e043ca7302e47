"""Pattern calibration's joint graph as a bulk problem: every board corner's projection into every view evaluated in
numpy, the normal equations assembled by batched products, solved by the engine's Levenberg–Marquardt
(`lfgraph.engine.schur.optimize_problem`) and read by its one posterior path (`CameraMarginals`).

The model is `lfgraph.factors.board_graph`'s: corner j of frame f seen by view v through the camera
``board_T_ref(f).compose(ref_T_view(v))`` (GTSAM's ``ProjectionFactorPPPC``), each view's lens model
(`lfgraph.lenses`, its ``coefficient_jacobian``), the other factors (corner priors, the gauge, the intrinsics pins)
as a small GTSAM graph on the same variables. Residuals and Jacobians are GTSAM's (poses perturbed on the right,
``pose * Exp([w, v])``; checked against GTSAM's factors in tests/engine/test_board_problem.py), so the fit converges
to the minimum GTSAM's optimiser finds, without a C++ factor per observation or a sparse elimination: the system
(9 V + 6 V + 6 F + 3 C unknowns, a few hundred) is small and dense.
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
    schur_layout,
    sparse_jacobian,
    vector_values,
)
from lfgraph.factors.keys import board_corner_key, board_pose_key, calib_key, view_pose_key
from lfgraph.lenses import COEFFICIENTS, HEAD, lens_code, lens_coefficient_jacobian, lens_distort, lens_model

POSE_DIM = 6
POINT_DIM = 3


def _cross_rows(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(..., 2, 3): each row a of ``q`` (..., 2, 3) crossed with ``p`` (..., 3): ``a [p]x`` = (a x p)^T."""
    return np.cross(q, p[..., None, :])


class BoardProblem:
    """Board corners seen by views with free intrinsics and poses, the board pose of every frame and the board's
    corners free (with their priors in ``graph``); state: `gtsam.Values` holding every variable.

    Args:
        graph: the other factors (corner priors, gauge, intrinsics pins) on the same keys.
        values: the start: every view's calibration and pose, every used frame's board pose, every corner.
        corners_px: (V, F, C, 2) observed corners of the used ``frames`` (in that order); valid: (V, F, C).
        frames: the frame index of each of the F used frames (their board-pose keys).
        noise: the measurement noise model of every observation (a 2-D Gaussian, optionally robust).
        lenses: each view's lens model (its ``coefficient_jacobian`` is needed).

    Raises:
        NotReducible: a noise model that is not a 2-D Gaussian, a lens without coefficient Jacobian, a corner
            behind its camera at the start.
    """

    def __init__(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, corners_px: np.ndarray,
                 valid: np.ndarray, frames: Sequence[int], noise: gtsam.noiseModel.Base, lenses: Sequence[str]):
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
        self.models, self.codes = models, np.array([lens_code(m.name) for m in models])
        self.n_coef = max(len(m.tangent) for m in models)
        self.extrapolate = self.noise.kernel is not None and self.noise.kernel.vectorised
        self.noise_cost = float(self.valid.sum())
        self.layout = schur_layout(values, "\0")
        self.n_c = self.layout.n_camera
        self._indices()
        if self._residuals(values, False) is None:
            raise NotReducible("a board corner behind its camera at the start")

    def _indices(self) -> None:
        """Column indices of every block in the state's layout; a view's unused coefficient columns (a model with
        fewer than ``n_coef``) point at a dummy column ``n_c``, dropped after assembly."""
        lay, n = self.layout, self.n_c
        cam = np.full((self.n_views, len(HEAD) + self.n_coef + POSE_DIM), n, dtype=np.int64)
        for v in range(self.n_views):
            k = camera_block(lay, calib_key(v))
            cam[v, :k.stop - k.start] = np.arange(k.start, k.stop)
            p = camera_block(lay, view_pose_key(v))
            cam[v, -POSE_DIM:] = np.arange(p.start, p.stop)
        self.cam_idx = cam
        self.board_idx = np.array([np.arange(s.start, s.stop) for s in
                                   (camera_block(lay, board_pose_key(f)) for f in self.frames)]).reshape(-1, POSE_DIM)
        self.corner_idx = np.array([np.arange(s.start, s.stop) for s in
                                    (camera_block(lay, board_corner_key(c)) for c in range(self.n_corners))])

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
        corners = np.stack([np.asarray(values.atPoint3(board_corner_key(c))) for c in range(self.n_corners)])
        return head, coef, poses, boards, corners

    def _residuals(self, values: gtsam.Values, jacobians: bool):
        """Whitened residuals (V, F, C, 2) (0 where not observed) and, with ``jacobians``, those of the camera
        (V, F, C, 2, 5 + n_coef + 6), board pose (.., 6) and corner (.., 3) blocks; None when an observed corner is
        behind its camera."""
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
        xd, yd, d00, d01, d10, d11 = lens_distort(code, cf, x, y, jacobian=True)
        fx, fy, s, cx, cy = (head[:, i, None, None] for i in range(5))
        r = np.stack([fx * xd + s * yd + cx, fy * yd + cy], axis=-1) - self.uv
        r[~self.valid] = 0.0
        e = self.noise.whiten(r.reshape(-1, 2)).reshape(r.shape)
        if not jacobians:
            return e
        sw = self.noise.sqrt_weights(e.reshape(-1, 2))
        w = self.noise.whiten(np.broadcast_to(np.eye(2), (1, 2, 2)))[0]  # whitening matrix (2, 2)
        if sw is not None:
            e = e * sw.reshape(e.shape)
        scale = (sw.reshape(e.shape) if sw is not None else np.ones(e.shape)) * self.valid[..., None]
        # d pixel / d (xd, yd) = [[fx, s], [0, fy]], whitened and weighted: (V, F, C, 2, 2)
        kd = np.zeros((V, 1, 1, 2, 2))
        kd[:, 0, 0, 0, 0], kd[:, 0, 0, 0, 1], kd[:, 0, 0, 1, 1] = head[:, 0], head[:, 2], head[:, 1]
        kd = np.matmul(w, kd) * scale[..., None]
        dist = np.stack([np.stack([d00, d01], -1), np.stack([d10, d11], -1)], -2)  # d (xd, yd) / d (x, y)
        jxy = np.matmul(kd, dist)  # d pixel / d (x, y)
        iz = 1.0 / z
        jpc = np.concatenate([jxy * iz[..., None, None],
                              -(jxy[..., 0] * x[..., None] + jxy[..., 1] * y[..., None])[..., None] * iz[..., None,
                                                                                                         None]],
                             axis=-1)  # d pixel / d pc: (V, F, C, 2, 3)
        jhead = np.zeros((V, F, C, 2, len(HEAD)))
        jhead[..., 0, 0], jhead[..., 0, 2], jhead[..., 1, 1] = xd, yd, yd
        jhead[..., 0, 3] = jhead[..., 1, 4] = 1.0
        jhead = np.matmul(w, jhead) * scale[..., None]
        jcoef = np.matmul(kd, lens_coefficient_jacobian(code, cf, x, y, self.n_coef))
        jpose = np.concatenate([_cross_rows(jpc, pc), -jpc], axis=-1)  # d pc / d view pose: [[pc]x, -I]
        q = np.matmul(jpc, np.swapaxes(ra, 1, 2)[:, None, None])  # jpc R_A^T
        jboard = np.concatenate([_cross_rows(q, np.broadcast_to(x_ref[None], pc.shape)), -q], axis=-1)
        jcorner = np.matmul(q, np.swapaxes(rb, 1, 2)[None, :, None])  # jpc R_A^T R_B^T
        return e, np.concatenate([jhead, jcoef, jpose], axis=-1), jboard, jcorner

    def error(self, state: gtsam.Values) -> float:
        """Cost at ``state``: the observations' noise-model error plus the other factors' GTSAM error; inf when a
        corner is behind its camera."""
        e = self._residuals(state, False)
        if e is None:
            return float("inf")
        other = float(self.graph.error(state)) if self.graph.size() else 0.0
        return self.noise.cost(e[self.valid]) + other

    def system(self, state: gtsam.Values) -> ReducedSystem:
        """The undamped normal equations at ``state``, every variable in the camera block (no landmarks).

        Raises:
            NotReducible: a corner behind its camera at ``state``.
        """
        out = self._residuals(state, True)
        if out is None:
            raise NotReducible("a board corner behind its camera at the linearisation point")
        H, g = _normal_equations(*out, self.cam_idx, self.board_idx, self.corner_idx, self.n_c)  # noqa: N806
        if self.graph.size():
            rows, cols, vals, _ = sparse_jacobian(self.graph.linearize(state), self.layout)
            A = np.zeros((int(rows.max()) + 1, self.n_c + 1))  # noqa: N806
            np.add.at(A, (rows, cols), vals)
            H += A[:, :self.n_c].T @ A[:, :self.n_c]
            g += A[:, :self.n_c].T @ A[:, self.n_c]
        return ReducedSystem(np.zeros((0, 3, 3)), np.zeros((0, 3, self.n_c)), np.zeros((0, 3)), H, g)

    def retract(self, state: gtsam.Values, dl: np.ndarray, dc: np.ndarray) -> gtsam.Values:
        """``state`` moved by the step ``dc`` (every variable; ``dl`` is empty)."""
        return state.retract(vector_values(self.layout, dc))


def _gram(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Batched a^T b of (..., m, i) and (..., m, j)."""
    return np.matmul(np.swapaxes(a, -1, -2), b)


def _normal_equations(e: np.ndarray, jc: np.ndarray, jb: np.ndarray, jx: np.ndarray, cam_idx: np.ndarray,
                      board_idx: np.ndarray, corner_idx: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """J^T J and -J^T e of the observations, assembled block by block (camera x camera per view, camera x board
    per view and frame, ..., corner x corner per corner) into (n, n) and (n,)."""
    V, F, C = e.shape[:3]  # noqa: N806
    kc = jc.shape[-1]
    blocks = {  # (rows' indices, columns' indices, block) for the upper triangle and the diagonal
        "cc": (cam_idx, cam_idx, _gram(jc.reshape(V, -1, kc), jc.reshape(V, -1, kc))),
        "cb": (cam_idx[:, None], board_idx[None], _gram(jc.reshape(V, F, -1, kc), jb.reshape(V, F, -1, POSE_DIM))),
        "cx": (cam_idx[:, None], corner_idx[None],
               _gram(jc.transpose(0, 2, 1, 3, 4).reshape(V, C, -1, kc),
                     jx.transpose(0, 2, 1, 3, 4).reshape(V, C, -1, POINT_DIM))),
        "bb": (board_idx, board_idx, _gram(*(jb.transpose(1, 0, 2, 3, 4).reshape(F, -1, POSE_DIM),) * 2)),
        "bx": (board_idx[:, None], corner_idx[None],
               _gram(jb.transpose(1, 2, 0, 3, 4).reshape(F, C, -1, POSE_DIM),
                     jx.transpose(1, 2, 0, 3, 4).reshape(F, C, -1, POINT_DIM))),
        "xx": (corner_idx, corner_idx, _gram(*(jx.transpose(2, 0, 1, 3, 4).reshape(C, -1, POINT_DIM),) * 2)),
    }
    H = np.zeros((n + 1, n + 1))  # noqa: N806  (the last row and column collect the padding)
    for name, (ri, ci, block) in blocks.items():
        H[ri[..., :, None], ci[..., None, :]] += block
        if name[0] != name[1]:
            H[ci[..., :, None], ri[..., None, :]] += np.swapaxes(block, -1, -2)
    g = np.zeros(n + 1)
    ev = e[..., None]
    np.add.at(g, cam_idx, -_gram(jc.reshape(V, -1, kc), ev.reshape(V, -1, 1))[..., 0])
    np.add.at(g, board_idx, -_gram(jb.transpose(1, 0, 2, 3, 4).reshape(F, -1, POSE_DIM),
                                   ev.transpose(1, 0, 2, 3, 4).reshape(F, -1, 1))[..., 0])
    np.add.at(g, corner_idx, -_gram(jx.transpose(2, 0, 1, 3, 4).reshape(C, -1, POINT_DIM),
                                    ev.transpose(2, 0, 1, 3, 4).reshape(C, -1, 1))[..., 0])
    return H[:n, :n], g[:n]
