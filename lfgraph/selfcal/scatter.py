"""The weak modes' covariance as the tracks' errors really scatter: a sandwich with tracks as clusters.

The final stage weighs every observation alike at the measured noise. Tracks are not alike: one near a depth edge
or on a slanted face errs 3-10x more than one on a flat face, and alike in every view, so the least-squares
posterior (the inverse information, `solve.posterior`) understates what such tracks do to the near-gauges. The
sandwich keeps the fit and replaces, in the weak modes' covariance, the data's part the graph assumes by the one
the residuals show: for mode m, x_m = H^-1 r_m (r_m the mode's row, H the information with the landmarks
eliminated: the camera covariance times r_m), each observation's pull on the mode is a_i = J_i x_m / sigma^2
(J_i x_m: how the observation's prediction moves when the cameras move along x_m and its landmark follows), and

    assumed  B = sum_i sigma^2 a_i a_i^T;   seen  G = sum over tracks of g g^T,  g = sum_(i in the track) a_i r_i

with r_i the residuals. The modes' covariance becomes S + max(G - B, 0) (its positive part: never narrower than the
graph's). Measured on paper-4x4 seed 5 (10 frames) against the ray-cast truth (docs/results.md, "What the zoom's
error was made of"; `benchmarks/targetless_zoom_anatomy.py`): the zoom's spread from the tracks' true errors, summed
per track, 2.12 px; from the residuals (G) 2.11 px. Frames as clusters do not work: each frame's shared error is
absorbed by the fit and leaves its residuals (1.13 px from the residuals against 2.37 px from the truth).
"""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.engine.triangulate import project_views
from lfgraph.factors.keys import calib_key, view_pose_key
from lfgraph.factors.values import read_intrinsics, read_view_poses

STEP_SIGMAS = 1e-3  # the cameras are moved along x_m by this many of the mode's sigmas (the pull is linear there)
POINT_STEP_M = 1e-6  # central differences of a projection in its landmark


def _moved(calib: Calibration, values: gtsam.Values, step: np.ndarray) -> Calibration:
    """``calib`` with its cameras moved by the tangent ``step`` (every view's calibration, then every pose)."""
    n = calib.num_views
    dim = (len(step) - 6 * n) // n
    delta = gtsam.VectorValues()
    for v in range(n):
        delta.insert(calib_key(v), step[v * dim:(v + 1) * dim])
        delta.insert(view_pose_key(v), step[n * dim + 6 * v:n * dim + 6 * (v + 1)])
    moved = values.retract(delta)
    return dataclasses.replace(calib, intrinsics=read_intrinsics(moved, n, lenses=calib.lenses),
                               ref_T_view=read_view_poses(moved, n))


def _landmark_jacobians(calib: Calibration, points: np.ndarray) -> np.ndarray:
    """(V, N, 2, 3) each projection's derivative in its landmark (central differences)."""
    h = POINT_STEP_M
    return np.stack([(project_views(calib, points + h * e) - project_views(calib, points - h * e)) / (2 * h)
                     for e in np.eye(3)], axis=-1)


def mode_pulls(calib: Calibration, values: gtsam.Values, points: np.ndarray, valid: np.ndarray, cameras_cov: np.ndarray,
               rows: np.ndarray) -> np.ndarray:
    """(M, V, N, 2) how each observation moves each mode's prediction, J_i x_m (module docstring), px per unit of the
    mode's information-weighted shift.

    Args:
        calib, values: the final fit's optimum; points: (N, 3) its landmarks; valid: (V, N).
        cameras_cov: (DV + 6V, DV + 6V) the covariance of every view's calibration then every pose (tangent order).
        rows: (M, DV) the modes as rows over every view's calibration (`pinned.mode_rows`).
    """
    n_cal = rows.shape[1]
    x = cameras_cov[:, :n_cal] @ rows.T  # (DV + 6V, M): x_m = H^-1 r_m
    base = project_views(calib, points)
    jac = np.where(valid[..., None, None], _landmark_jacobians(calib, points), 0.0)
    normal = np.einsum("vnik,vnil->nkl", jac, jac)
    out = np.zeros((len(rows), *valid.shape, 2))
    for m in range(len(rows)):
        var = float(rows[m] @ x[:n_cal, m])
        if var <= 0:
            continue
        eps = STEP_SIGMAS / np.sqrt(var)
        moved = project_views(_moved(calib, values, eps * x[:, m]), points)
        cams = np.where(valid[..., None], (moved - base) / eps, 0.0)
        # the landmark follows the cameras: its least-squares response to them
        follow = -np.linalg.solve(normal, np.einsum("vnik,vni->nk", jac, cams)[..., None])[..., 0]
        out[m] = np.where(valid[..., None], cams + np.einsum("vnik,nk->vni", jac, follow), 0.0)
    return out


def track_sandwich(pulls: np.ndarray, residuals: np.ndarray, noise_px: float) -> tuple[np.ndarray, np.ndarray]:
    """(M, M) the data's part of the modes' covariance as the graph assumes it (B) and as the residuals show it with
    tracks as clusters (G) (module docstring).

    Args:
        pulls: (M, V, N, 2) `mode_pulls`; residuals: (V, N, 2) observed minus predicted, px (0 where not seen).
        noise_px: the graph's measurement sigma.
    """
    a = pulls / noise_px**2
    assumed = noise_px**2 * np.einsum("mvni,kvni->mk", a, a)
    g = np.einsum("mvni,vni->mn", a, residuals)  # (M, N): each track's pull on each mode
    return assumed, g @ g.T


def robust_joint(joint: np.ndarray, rows: np.ndarray, assumed: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """The (DV, DV) ``joint`` covariance of every view's calibration with the modes ``rows`` (M, DV) widened by the
    positive part of ``seen`` - ``assumed`` (`track_sandwich`): rows @ result @ rows.T is the modes' covariance plus
    that part; every combination of the calibration orthogonal to the rows keeps its covariance."""
    lam, u = np.linalg.eigh(seen - assumed)
    extra = (u * np.maximum(lam, 0.0)) @ u.T
    lift = np.linalg.pinv(rows)  # (DV, M): rows @ lift = I
    return joint + lift @ extra @ lift.T
