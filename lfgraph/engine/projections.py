"""The refinement's points and poses stages as a `lfgraph.engine.schur` problem: the projections of every landmark into
every view evaluated in bulk in numpy (GTSAM's Cal3DS2, Cal3Fisheye and Cal3Unified projection residuals and
Jacobians, checked against GTSAM's factors in tests/engine/test_schur.py), the priors and gauges as a small GTSAM graph
on the camera variables."""

from __future__ import annotations

import copy

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
from lfgraph.lenses import lens_distort
from lfgraph.lenses.radtan import distort_xy, distortion_jacobian


class ProjectionProblem:
    """Landmarks seen by views with constant intrinsics (GTSAM's ``GenericProjectionFactorCal3DS2`` /
    ``TriangulationFactorCal3DS2`` and their Cal3Fisheye and Cal3Unified twins), evaluated in bulk in numpy, plus a
    small GTSAM graph of everything else on the camera variables (pose priors, gauges). The state is (camera
    `gtsam.Values`, (N, 3) landmarks).

    The residual and Jacobians are GTSAM's: ``h(x) - z`` whitened by the noise model (a robust model's weights
    applied as GTSAM applies them: `lfgraph.engine.bulk_noise`), the pose perturbed on the right (``pose * Exp([w,
    v])``), each view's lens model (`lfgraph.core.camera.LENSES`) without skew.

    Args:
        graph: the other factors (on camera keys only); values: their variables (the camera state).
        view, landmark: (M,) view and landmark index of each observation; uv: (M, 2) pixels.
        noise: the measurement noise model of every observation (a 2-D Gaussian, optionally robust);
        intrinsics, lenses: (V, 11) fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, xi and (V,) each view's lens, its index
            in `LENSES` (`lfgraph.core.camera.lens_table`).
        pose_keys: (V,) key of each view's pose in ``values`` (poses free), or None with ``fixed_poses`` (V, 4, 4).

    Raises:
        NotReducible: an observation behind its camera at the start, a view observed twice by one landmark, or a
            noise model that is not a 2-D Gaussian (robust or not).
    """

    def __init__(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, view: np.ndarray,
                 landmark: np.ndarray, uv: np.ndarray, noise: gtsam.noiseModel.Base, intrinsics: np.ndarray,
                 lenses: np.ndarray, n_landmarks: int, pose_keys: list[int] | None = None,
                 fixed_poses: np.ndarray | None = None):
        self.graph = graph
        self.view, self.landmark = np.asarray(view, dtype=np.int64), np.asarray(landmark, dtype=np.int64)
        self.uv = np.asarray(uv, dtype=np.float64)
        try:
            self.noise = BulkNoise(noise)
        except NotBulk as e:
            raise NotReducible(str(e)) from None
        # a robust model's reweighted steps fall short: stretch them (`lfgraph.engine.schur`), unless each extra cost
        # costs a Python call per residual (an estimator that cannot be tabulated)
        self.extrapolate = self.noise.kernel is not None and self.noise.kernel.vectorised
        # what the observations cost under Gaussian noise at the model's sigma (0.5 |e|^2 of a 2-D whitened residual
        # is 1 on average): a robust stage's stop is relative to that when the kernel's cost is less
        # (`lfgraph.engine.schur`)
        self.noise_cost = float(len(self.view))
        self.intr = np.asarray(intrinsics, dtype=np.float64)
        self.n_views, self.n_landmarks = len(self.intr), int(n_landmarks)
        self.layout = schur_layout(values, "\0") if values.size() else None
        self.n_c = self.layout.n_camera if self.layout is not None else 0
        self.pose_keys = pose_keys
        self.fixed = fixed_poses
        pair = self.view * max(self.n_landmarks, 1) + self.landmark
        if pair.size and not np.all(pair[1:] > pair[:-1]):  # e.g. np.nonzero of a (V, N) mask: sorted by view
            order = np.argsort(pair, kind="stable")
            self.view, self.landmark, self.uv = self.view[order], self.landmark[order], self.uv[order]
            pair = pair[order]
            if np.any(pair[1:] == pair[:-1]):
                raise NotReducible("a landmark observed twice by one view")
        self.obs_intr = [np.ascontiguousarray(self.intr[self.view, i]) for i in range(11)]
        lenses = np.asarray(lenses, dtype=np.int64)
        self.obs_lens = None if not np.any(lenses) else lenses[self.view]  # None: every view radtan (Cal3DS2)
        # every landmark seen by every view (observations in view-major order): per-view matrix products
        self.full = self.n_landmarks > 0 and len(self.view) == self.n_views * self.n_landmarks
        if fixed_poses is not None:
            self.fixed_rm = fixed_poses[self.view, :3, :3]
            self.fixed_t = fixed_poses[self.view, :3, 3]
        bounds = np.searchsorted(self.view, np.arange(self.n_views + 1))  # observations are sorted by view
        self.by_view = [slice(int(bounds[v]), int(bounds[v + 1])) for v in range(self.n_views)]
        if pose_keys is not None:
            self.col0 = np.array([camera_block(self.layout, k).start for k in pose_keys], dtype=np.int64)
            # every landmark in every view and the poses in view order: W is a transpose of the per-observation
            # blocks; otherwise a scatter
            self.dense = len(self.view) == self.n_views * self.n_landmarks \
                and np.array_equal(self.col0, 6 * np.arange(self.n_views)) and self.n_c == 6 * self.n_views
            if not self.dense:
                self.w_index = (((self.landmark * 3)[:, None, None] + np.arange(3)[None, :, None]) * self.n_c
                                + (self.col0[self.view][:, None, None] + np.arange(6)[None, None, :])).reshape(-1)

    def _poses(self, values: gtsam.Values) -> np.ndarray:
        if self.pose_keys is None:
            return self.fixed
        return np.stack([values.atPose3(k).matrix() for k in self.pose_keys])

    def _residuals(self, state, jacobians: bool):
        values, points = state
        poses = self._poses(values)
        if self.full:
            R, Rm = poses[:, :3, :3], None  # noqa: N806
            pc = np.matmul(points[None] - poses[:, None, :3, 3], R).reshape(-1, 3)  # R^T (P - t), view by view
        else:
            Rm, tm = (self.fixed_rm, self.fixed_t) if self.pose_keys is None \
                else (poses[self.view, :3, :3], poses[self.view, :3, 3])  # noqa: N806
            d = points[self.landmark] - tm
            pc = d[:, 0:1] * Rm[:, 0] + d[:, 1:2] * Rm[:, 1] + d[:, 2:3] * Rm[:, 2]  # R^T (P - t)
        z = pc[:, 2]
        if not np.all(z > 0):
            return None
        x, y = pc[:, 0] / z, pc[:, 1] / z
        fx, fy, cx, cy, k1, k2, p1, p2 = self.obs_intr[:8]
        if self.obs_lens is None:
            xd, yd = distort_xy(x, y, k1, k2, p1, p2)
        else:
            lens = lens_distort(self.obs_lens, self.obs_intr[4:], x, y, jacobian=jacobians)
            xd, yd = lens[:2]
        e = self.noise.whiten(np.stack([fx * xd + cx - self.uv[:, 0], fy * yd + cy - self.uv[:, 1]], axis=1))
        if not jacobians:
            return e
        if self.obs_lens is None:
            d00, d01, d11 = distortion_jacobian(x, y, k1, k2, p1, p2)
            d10 = d01
        else:
            d00, d01, d10, d11 = lens[2:]
        s = 1.0 / self.noise.isotropic_sigma if self.noise.isotropic_sigma is not None else 1.0
        a00, a01, a10, a11 = s * fx * d00, s * fx * d01, s * fy * d10, s * fy * d11  # d pixel / d (x, y)
        iz = 1.0 / z
        # d pixel / d pc = A [[1/z, 0, -x/z], [0, 1/z, -y/z]]
        jpc = np.empty((len(z), 2, 3))
        jpc[:, 0, 0], jpc[:, 0, 1], jpc[:, 0, 2] = a00 * iz, a01 * iz, -(a00 * x + a01 * y) * iz
        jpc[:, 1, 0], jpc[:, 1, 1], jpc[:, 1, 2] = a10 * iz, a11 * iz, -(a10 * x + a11 * y) * iz
        if self.noise.isotropic_sigma is None:
            jpc = self.noise.whiten(jpc)
        sw = self.noise.sqrt_weights(e)
        if sw is not None:  # GTSAM's robust reweighting of the whitened rows (the error keeps the loss)
            e = e * sw
            jpc *= sw[:, :, None]
        # d pc / d P = R^T: jl[a, j] = sum_k jpc[a, k] R[j, k]
        if self.full:
            jl = np.matmul(jpc.reshape(self.n_views, -1, 3), np.swapaxes(R, 1, 2)).reshape(-1, 2, 3)
        else:
            jl = np.matmul(jpc, np.swapaxes(Rm, 1, 2))
        jp = None
        if self.pose_keys is not None:  # d pc / d w = [pc]x, d pc / d v = -I
            jp = np.empty((len(z), 2, 6))
            px_, py_, pz_ = pc[:, 0, None], pc[:, 1, None], pc[:, 2, None]
            jp[:, :, 0] = jpc[:, :, 1] * pz_ - jpc[:, :, 2] * py_
            jp[:, :, 1] = jpc[:, :, 2] * px_ - jpc[:, :, 0] * pz_
            jp[:, :, 2] = jpc[:, :, 0] * py_ - jpc[:, :, 1] * px_
            jp[:, :, 3:] = -jpc
        return e, jl, jp

    def observation_jacobians(self, state) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
        """Per observation at ``state``, as `system` sums them: the whitened residual (M, 2) and its Jacobians by the
        landmark (M, 2, 3) and by the view's pose (M, 2, 6; None with fixed poses), robust weights applied; None when a
        landmark is behind a camera. (A posterior robust to errors correlated within a track needs each track's own
        share of the camera gradient: `lfgraph.refinement.scatter`.)"""
        return self._residuals(state, True)

    def error(self, state) -> float:
        """Cost at ``state``: the observations' noise-model error plus the other factors' GTSAM error; inf when a
        landmark is behind a camera."""
        e = self._residuals(state, False)
        if e is None:
            return float("inf")
        other = float(self.graph.error(state[0])) if self.graph.size() else 0.0
        return self.noise.cost(e) + other

    def system(self, state) -> ReducedSystem:
        """The undamped normal equations at ``state`` in Schur form (`ReducedSystem`): landmark blocks from the bulk
        projections; camera blocks from the pose Jacobians (when the poses are free) and the other factors.

        Raises:
            NotReducible: a landmark behind a camera at ``state``.
        """
        out = self._residuals(state, True)
        if out is None:
            raise NotReducible("a landmark behind a camera at the linearisation point")
        e, jl, jp = out
        n, n_c, lm = self.n_landmarks, self.n_c, self.landmark
        if self.full:  # per landmark, its 2V rows: V = J^T J and g = -J^T e in one batched product
            jt = np.ascontiguousarray(jl.reshape(self.n_views, n, 2, 3).transpose(1, 3, 0, 2)).reshape(n, 3, -1)
            V = np.matmul(jt, np.swapaxes(jt, 1, 2))  # noqa: N806
            g_l = -np.matmul(jt, e.reshape(self.n_views, n, 2).transpose(1, 0, 2).reshape(n, -1, 1))[..., 0]
        else:
            V = np.zeros((n, 3, 3))  # noqa: N806
            for a in range(3):
                for b in range(a, 3):
                    V[:, a, b] = V[:, b, a] = np.bincount(
                        lm, weights=jl[:, 0, a] * jl[:, 0, b] + jl[:, 1, a] * jl[:, 1, b], minlength=n)
            gl = -(jl[:, 0] * e[:, 0:1] + jl[:, 1] * e[:, 1:2])
            g_l = np.stack([np.bincount(lm, weights=gl[:, k], minlength=n) for k in range(3)], axis=1)
        H = np.zeros((n_c, n_c))  # noqa: N806
        g_c = np.zeros(n_c)
        W = np.zeros((n, 3, n_c))  # noqa: N806
        if jp is not None:
            for v, obs in enumerate(self.by_view):
                c = slice(int(self.col0[v]), int(self.col0[v]) + 6)
                jv = jp[obs].reshape(-1, 6)
                H[c, c] += jv.T @ jv
                g_c[c] -= jv.T @ e[obs].ravel()
            wl = np.matmul(np.swapaxes(jl, 1, 2), jp)  # (M, 3, 6)
            if self.dense:
                W = np.ascontiguousarray(wl.reshape(self.n_views, n, 3, 6).transpose(1, 2, 0, 3)).reshape(n, 3, n_c)  # noqa: N806
            else:
                W.reshape(-1)[self.w_index] = wl.reshape(-1)
        if self.graph.size():
            rows, cols, vals, _ = sparse_jacobian(self.graph.linearize(state[0]), self.layout)
            m = int(rows.max()) + 1
            A = np.zeros((m, n_c + 1))  # noqa: N806
            np.add.at(A, (rows, cols), vals)
            H += A[:, :n_c].T @ A[:, :n_c]
            g_c += A[:, :n_c].T @ A[:, n_c]
        return ReducedSystem(V.reshape(-1, 3, 3), W, g_l, H, g_c)

    def typical_weights(self, state) -> np.ndarray:
        """(V,) the robust kernel's weight at each view's median whitened residual distance at ``state`` (ones for
        a Gaussian model or a view without observations; zeros where a landmark is behind a camera)."""
        out = np.ones(self.n_views)
        if self.noise.kernel is None:
            return out
        e = self._residuals(state, False)
        if e is None:
            return np.zeros(self.n_views)
        d = np.hypot(e[:, 0], e[:, 1])
        seen = [v for v, obs in enumerate(self.by_view) if obs.stop > obs.start]
        out[seen] = self.noise.kernel.weights(np.array([np.median(d[self.by_view[v]]) for v in seen]))
        return out

    def gaussian(self) -> ProjectionProblem | None:
        """The same problem under the robust model's Gaussian part (None: the model is Gaussian already)."""
        if self.noise.kernel is None:
            return None
        plain = copy.copy(self)
        plain.noise, plain.extrapolate = BulkNoise(self.noise.model.noise()), False
        return plain

    def retract(self, state, dl: np.ndarray, dc: np.ndarray):
        """``state`` moved by a landmark step ``dl`` (N, 3), added to the landmarks, and a camera step ``dc`` (C,),
        retracted on the camera values."""
        values, points = state
        if self.n_c:  # no landmark keys in this layout: its columns are the camera columns
            values = values.retract(vector_values(self.layout, dc))
        return values, points + dl
