"""Tracks a fit bent itself to fit: each track judged by what the fit of the others predicts for it.

Why. A ring's neighbours share mostly 2-view tracks, each of which leaves one degree of freedom once its landmark is
fitted, and a pair's far tracks at one depth leave its relative turn and sideways motion nearly one mode. One wrong
match that triangulates near (rendered ring, seed 50 of `benchmarks/ring_sweep.py`: 8.8 px off the truth, at 0.6 m
among tracks at 3.4-4.4 m) decides that mode alone: the fit turned its view 0.26 deg and moved it 20 mm to fit it to
0.09 px, 12.7 and 11 of its reported sigmas off the truth; without it, 0.08 deg and 4 mm. Its residual under the fit
cannot show it (the clean stage's test), its deleted residual does.

What. For track j with residuals r_j (whitened, its landmark eliminated) and reduced Jacobian A_j by the cameras, the
fit's joint camera covariance Sigma gives the hat block H_j = A_j Sigma A_j^T; deleting the track raises the fit's
cost by r_j^T (I - H_j)^-1 r_j, a chi-square of the track's 2k - 3 degrees of freedom under the noise model (Cook's
deletion identity for least squares; with the priors in Sigma, exact for the linearised MAP fit). A track whose
deletion stands out beyond ``DELETION_SIGMA`` (as a normal deviate) is dropped and the tracks refitted once (seed 50:
the wrong match at 6.2, the next of 1883 tracks at 2.45). Free arrangements only: a grid's chain tracks span most
views, so no one track decides a mode, and its benchmark figures were set without this.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.observer import Observer
from lfgraph.engine.optimize import gtsam_quiet
from lfgraph.engine.schur import CameraMarginals
from lfgraph.factors.keys import LANDMARK_CHAR
from lfgraph.factors.noise import measurement_noise
from lfgraph.refinement.config import RefineConfig
from lfgraph.refinement.fit import FitResult, fit_auto
from lfgraph.refinement.stages import stage_problem

DELETION_SIGMA = 5.0  # a track's deletion chi-square beyond this normal deviate (one-sided, p ~3e-7: under Gaussian
# noise ~1e-3 tracks of a ring's ~2000 by chance) was a wrong match the fit bent itself to
HAT_FLOOR = 1e-9  # eigenvalues of I - H_j below this are the landmark's own directions (projected out exactly)


def deletion_chi2(problem, state, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per track of a bulk `ProjectionProblem` at ``state`` with camera covariance ``cov`` (C, C; its layout's
    camera columns): (N,) the rise of the cost when the track is deleted, r^T (I - H)^-1 r (whitened units), and
    (N,) its degrees of freedom 2k - 3 (k: its observations)."""
    out = problem.observation_jacobians(state)
    n = problem.n_landmarks
    chi2, dof = np.zeros(n), np.zeros(n, dtype=int)
    if out is None or out[2] is None:
        return chi2, dof
    e, jl, jp = out
    lm = problem.landmark
    order = np.argsort(lm, kind="stable")
    counts = np.bincount(lm, minlength=n)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    for k in np.unique(counts[counts >= 2]):
        tracks = np.nonzero(counts == k)[0]
        obs = order[starts[tracks][:, None] + np.arange(k)]  # (T, k) observation indices of each track
        t = len(tracks)
        el = e[obs].reshape(t, 2 * k)
        jll = jl[obs].reshape(t, 2 * k, 3)
        proj = np.eye(2 * k) - jll @ np.linalg.pinv(np.swapaxes(jll, 1, 2) @ jll, hermitian=True) \
            @ np.swapaxes(jll, 1, 2)  # removes the landmark's own directions
        jc = np.zeros((t, 2 * k, 6 * k))
        for i in range(k):
            jc[:, 2 * i:2 * i + 2, 6 * i:6 * i + 6] = jp[obs[:, i]]
        a = proj @ jc
        cols = (problem.col0[problem.view[obs]][:, :, None] + np.arange(6)).reshape(t, 6 * k)
        hat = a @ cov[cols[:, :, None], cols[:, None, :]] @ np.swapaxes(a, 1, 2)
        r = np.einsum("tij,tj->ti", proj, el)
        w, u = np.linalg.eigh(proj - hat)
        ur = np.einsum("tji,tj->ti", u, r)
        inv = np.where(w > HAT_FLOOR, 1.0 / np.maximum(w, HAT_FLOOR), 0.0)
        chi2[tracks] = np.sum(ur**2 * inv, axis=1)
        dof[tracks] = 2 * k - 3
    return chi2, dof


def fit_deletion_chi2(calib, fit, config: RefineConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """`deletion_chi2` of a `FitResult`'s tracks (its last free stage, with the priors and noise model it ran with),
    or None where the bulk solver does not take the stage or the system is indeterminate."""
    if fit.last_stage is None or fit.valid.shape[1] == 0:
        return None
    priors = fit.priors
    model = measurement_noise(config.noise if fit.noise is None else fit.noise, fit.sigma_px)
    try:
        with gtsam_quiet():
            bulk = stage_problem(fit.last_stage, fit.calib, fit.pixels, fit.valid, fit.points, model,
                                 config.scale_sigma_mm, fit.held, priors)
            if bulk is None:
                return None
            problem, state = bulk
            marginals = CameraMarginals(None, None, LANDMARK_CHAR, problem, state)
            layout = problem.layout
            keys = [int(k) for k, is_lm in zip(layout.keys, layout.landmark, strict=True) if not is_lm]
            cov = marginals.joint(keys)
    except RuntimeError:
        return None
    return deletion_chi2(problem, state, cov)


def deletion_deviates(chi2: np.ndarray, dof: np.ndarray) -> np.ndarray:
    """(N,) one-sided normal deviates of chi-square values (Wilson-Hilferty, as `posterior.chi2_sigma`); 0 where
    ``dof`` is 0."""
    d = np.maximum(dof, 1).astype(float)
    a = 2.0 / (9.0 * d)
    z = (np.cbrt(np.maximum(chi2, 0.0) / d) - (1.0 - a)) / np.sqrt(a)
    return np.where(dof > 0, z, 0.0)


def without_bent_tracks(calib: Calibration, pixels: np.ndarray, valid: np.ndarray, fit: FitResult,
                        config: RefineConfig, observer: Observer) -> FitResult:
    """In a free arrangement, ``fit`` (of ``pixels`` (V, N, 2), ``valid`` (V, N)) refitted without the tracks whose
    deletion stands out beyond ``DELETION_SIGMA`` (module docstring), its ``keep`` over all N tracks; ``fit`` itself
    when there are none, and on a grid."""
    if not calib.grid.is_free:
        return fit
    out = fit_deletion_chi2(calib, fit, config)
    if out is None:
        return fit
    dev = deletion_deviates(*out)
    bent = dev > DELETION_SIGMA
    if not bent.any():
        return fit
    sub = fit.keep.copy()
    sub[np.nonzero(fit.keep)[0][bent]] = False
    worst = ", ".join(f"{x:.1f}" for x in np.sort(dev[bent])[::-1][:3])
    observer.log(f"{int(bent.sum())} tracks the fit bent itself to fit (deleting them raises its cost by {worst} "
                 f"sigma; wrong matches deciding a weak mode): refitted without them")
    refit = fit_auto(calib, pixels[:, sub], valid[:, sub], config, observer, sigma_estimate=fit.sigma_px)
    keep = np.zeros_like(fit.keep)
    keep[np.nonzero(sub)[0][refit.keep]] = True
    return dataclasses.replace(refit, keep=keep)
