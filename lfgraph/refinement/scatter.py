"""The posterior widened where the tracks' own scatter says it is too narrow: the rig's bending modes judged by a
covariance that is robust to errors correlated within a track (a "sandwich" over tracks).

Why. The graph's marginals take every observation as an independent draw of the measurement sigma. A track's
errors are not: every view is matched from the reference view's patch, and the error grows with the view's offset
from the reference (paper-5x5, 3 frames, 1 deg / 3 mm: a linear function of the view's position per track explains
40-49 % of the fit's residual variance, 8 % with the views shuffled; the same with no sensor noise, so it is the
tracker's, not the sensor's). Where such errors land is the classic weak mode of a near-planar array: every view
turned by an angle growing linearly with its offset from the reference, every landmark's inverse depth shifted to
match, changes the images only through the field-of-view terms. The refined rigs' pan/tilt error was that mode
(RMS 2-8 mdeg over views, 0.3-1.2 mdeg once it is taken out), 2.9x its graph sigma (RMS over 12 seeds), and every
view's transfer error at infinity ramped with its offset from the reference to 2.9-3.7x its reported sigma.

What. Each track j's contribution to the gradient of the reduced camera system, ``t_j`` (the landmark eliminated),
gives the estimator's covariance under any correlation within a track, ``S^-1 (k sum_j t_j t_j^T + P) S^-1``
(``S``: the reduced system, ``P``: its priors' part, ``k = G / (G - p)``: the dof correction of ``G`` tracks fitting
``p`` effective camera parameters; on exact tracks of a 4x4 rig with known errors growing per track with the offset,
the transfer error at infinity over its sigma has an RMS of 1.07 over views with it, 1.20 without, and 0.88 with
independent errors). It is applied to the bending modes only — each rotation axis of the free views as
a constant and a linear function of the views' positions (`bending_functionals`) — where it is 2-26x the graph's
variance on paper-5x5; elsewhere the graph's marginals were honest (the pan/tilt error left once the modes are taken
out is within them), and a sandwich estimated from a few hundred tracks over ~150 parameters scatters by itself.
The modes' covariance becomes the larger of the two in every direction (never narrower than the graph's), and the
rest of the posterior follows it by the Gaussian update ``Sigma + Z M^-1 (M' - M) M^-1 Z^T`` (``Z = Sigma L^T``,
``M = L Sigma L^T``): a direction uncorrelated with the modes keeps its marginal.
"""

from __future__ import annotations

import gtsam
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.engine.schur_system import SchurLayout, camera_block, landmark_blocks, sparse_jacobian
from lfgraph.factors.keys import view_pose_key

MIN_TRACKS_PER_PARAMETER = 2.0  # the sandwich needs this many tracks per effective camera parameter (fewer: the graph's
# marginals are kept): its dof correction G / (G - p) is 2 there, and it grows without bound as G nears p
PLANE_SPREAD = 0.1  # a principal axis of the views' positions counts when its spread is this share of the largest
# (a grid's two axes, a line's one; the ~0.5 mm scatter of a planar rig out of its plane is not an axis)


def bending_functionals(calib: Calibration, layout: SchurLayout, free_axes: np.ndarray) -> np.ndarray:
    """(K, C) linear functionals of the camera vector (``layout``'s camera columns) reading the bending modes of the
    views with a free rotation axis (``free_axes`` (V, 3): pan, tilt, roll not held by structure): each axis fitted
    over those views as a constant plus a linear function of their positions along the array's principal axes
    (orthonormal over the views, so a row is the mode's least-squares coefficient; a held axis reads nothing).
    Empty without such views."""
    views = [v for v in range(calib.num_views) if free_axes[v].any()]
    if not views:
        return np.zeros((0, layout.n_camera))
    c = calib.ref_T_view[views, :3, 3]
    centred = c - c.mean(axis=0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    axes = vt[s > PLANE_SPREAD * s[0]] if s.size and s[0] > 0 else vt[:0]
    q, r = np.linalg.qr(np.column_stack([np.ones(len(views)), centred @ axes.T]))
    q = q[:, np.abs(np.diag(r)) > 1e-9 * np.abs(r[0, 0])]
    m = q.shape[1]
    rows = np.zeros((3 * m, layout.n_camera))
    for i, v in enumerate(views):
        first = camera_block(layout, view_pose_key(v)).start  # Pose3 tangent: rotation x, y, z first
        for axis in np.nonzero(free_axes[v])[0]:
            rows[axis * m:(axis + 1) * m, first + axis] = q[i]
    return rows[np.any(rows != 0, axis=1)]


def track_scores_bulk(problem, state) -> np.ndarray:
    """(N, C) each track's reduced score t_j on a bulk `ProjectionProblem` at ``state`` (its camera columns): the pose
    gradient of the track's whitened residuals once its own landmark took its Gauss-Newton step (the landmark
    eliminated: ``J_c^T (e - J_l V^-1 J_l^T e)``)."""
    e, jl, jp = problem.observation_jacobians(state)
    lm, n = problem.landmark, problem.n_landmarks
    v_blocks = np.zeros((n, 3, 3))
    np.add.at(v_blocks, lm, np.matmul(np.swapaxes(jl, 1, 2), jl))
    g = np.zeros((n, 3))
    np.add.at(g, lm, np.einsum("mka,mk->ma", jl, e))
    step = np.matmul(np.linalg.pinv(v_blocks, hermitian=True), g[..., None])[..., 0]
    after = e - np.einsum("mka,ma->mk", jl, step[lm])
    scores = np.zeros((n, problem.n_c))
    cols = problem.col0[problem.view][:, None] + np.arange(6)
    np.add.at(scores, (lm[:, None], cols), np.einsum("mki,mk->mi", jp, after))
    return scores


def track_scores_graph(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, layout: SchurLayout) -> np.ndarray:
    """(N, C) each track's reduced score t_j from a GTSAM graph of projections at ``values`` (`track_scores_bulk`'s,
    for graphs the bulk solver does not take: intrinsics free)."""
    rows, cols, vals, b, row_lm, al, v_blocks, g = landmark_blocks(graph.linearize(values), layout)
    step = np.matmul(np.linalg.pinv(v_blocks, hermitian=True), g[..., None])[..., 0]
    seen = row_lm >= 0
    after = np.where(seen, b - np.einsum("ma,ma->m", al, step[np.maximum(row_lm, 0)]), 0.0)
    cam = (layout.col_cam[cols] >= 0) & seen[rows]
    n, n_c = layout.n_landmarks, layout.n_camera
    flat = row_lm[rows[cam]] * n_c + layout.col_cam[cols[cam]]
    # GTSAM's linear factors are |A x - b| with b the negated whitened error
    return -np.bincount(flat, weights=vals[cam] * after[rows[cam]], minlength=n * n_c).reshape(n, n_c)


def prior_information(priors: gtsam.NonlinearFactorGraph, values: gtsam.Values, layout: SchurLayout) -> np.ndarray:
    """(C, C) the information the camera-only factors (priors, gauges) give, in ``layout``'s camera columns."""
    out = np.zeros((layout.n_camera, layout.n_camera))
    if not priors.size():
        return out
    rows, cols, vals, is_b = sparse_jacobian(priors.linearize(values), layout)
    a = np.zeros((int(rows.max()) + 1, layout.n_camera))
    np.add.at(a, (rows[~is_b], layout.col_cam[cols[~is_b]]), vals[~is_b])
    return a.T @ a


def widen_bending(cov: np.ndarray, functionals: np.ndarray, scores: np.ndarray,
                  prior_info: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``cov`` (C, C), the graph's joint camera covariance (the inverse of its reduced system S), with its bending
    modes (``functionals`` (K, C)) widened to the tracks' sandwich where that is larger (module docstring);
    ``scores`` (N, C): the tracks' reduced scores; ``prior_info`` (C, C): the camera-only factors' part of S.
    Returns the covariance and the modes' variance factors (K,), the sandwich's over the graph's along its principal
    directions (ones: unchanged)."""
    k = functionals.shape[0]
    tracks = int(np.count_nonzero(np.any(scores != 0, axis=1)))
    p_eff = cov.shape[0] - float(np.trace(cov @ prior_info))  # the parameters the tracks determine: tr(S^-1 S_data)
    if k == 0 or tracks < MIN_TRACKS_PER_PARAMETER * p_eff or tracks <= p_eff:
        return cov, np.ones(k)
    dof = tracks / (tracks - p_eff)
    z = cov @ functionals.T  # (C, K)
    m_graph = functionals @ z
    zs = scores @ z  # (N, K): each track's share of the modes' estimate
    m_tracks = dof * zs.T @ zs + z.T @ prior_info @ z  # L S^-1 (k sum t t^T + P) S^-1 L^T
    w, u = np.linalg.eigh(m_graph)
    keep = w > 1e-12 * max(w.max(initial=0.0), 1e-300)
    if not keep.any():
        return cov, np.ones(k)
    half = u[:, keep] / np.sqrt(w[keep])  # whitens the graph's mode covariance (its held directions left out)
    lam, rot = np.linalg.eigh(half.T @ m_tracks @ half)
    grow = np.maximum(lam, 1.0) - 1.0
    if not np.any(grow > 0):
        return cov, np.ones(k)
    # M' - M in the whitened basis is rot diag(grow) rot^T; mapped back through M^-1 Z^T = half half^T Z^T
    a = z @ half @ rot  # (C, K')
    factors = np.ones(k)
    factors[:lam.size] = np.sort(np.maximum(lam, 1.0))[::-1]
    return cov + (a * grow) @ a.T, factors
