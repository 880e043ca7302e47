"""Held-out folds of a refinement: refits each without one fold of the tracks (whole frames when there are several),
and the test that scores a candidate calibration on the tracks each refit did not see (`heldout_test`), which
`lfgraph.refinement.assess` asks of the views it would write and `lfgraph.refinement.whole` of a free arrangement
written whole."""

from __future__ import annotations

import warnings

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.observer import SilentObserver
from lfgraph.engine.triangulate import reprojection_errors, triangulate_dlt
from lfgraph.refinement.config import RefineConfig
from lfgraph.refinement.fit import fit_auto, gate_rms, has_kernel
from lfgraph.refinement.verdicts import MIN_TRACK_RMS_PX

FOLD_SEED = 14
MAX_FRAME_FOLDS = 5  # with several frames, at most this many folds of whole frames (the jackknife's units)
HELDOUT_CONSISTENCY = 10.0  # held-out RMS of the candidate at most this x the full fit's RMS of its own tracks:
# legitimate thin fits predicted held-out tracks at up to ~5x (one frame of a 3x3 rig: 0.40 px vs 0.08 px); fits of
# mismatches at 17-39x (keyboard textures in benchmarks/sweep.py)
# ... floored at MIN_TRACK_RMS_PX; a refit leaving more than MAX_TRACK_SIGMA_PX has fitted mismatches (verdicts)
ONE_PLACE = 1e-3  # views whose centres lie within this share of the rig's span stand at one place


def heldoutfinite_rms(calib: Calibration, pixels: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(V, N) reprojection errors of tracks triangulated with ``calib`` (not refitted: they test it); NaN for a
    track seen from one place only (`one_place`)."""
    errors = reprojection_errors(calib, triangulate_dlt(calib, pixels, valid), pixels, valid)
    errors[:, one_place(calib, valid)] = np.nan
    return errors


def one_place(calib: Calibration, valid: np.ndarray) -> np.ndarray:
    """(N,) tracks whose views stand at one place (their centres within `ONE_PLACE` of the rig's span): their depth
    is undetermined and the linear triangulation puts them anywhere on the ray, near a centre too, where the smallest
    turn moves them by hundreds of pixels (templeSparseRing's views 0 and 10, captured at one place: one held-out
    track 670 px off with every view 0.004-0.36 deg from the truth). They test no geometry."""
    centres = calib.ref_T_view[:, :3, 3]
    span = float(np.max(np.linalg.norm(centres - centres.mean(axis=0), axis=1)))
    at = np.where(valid[:, :, None], centres[:, None, :], np.nan)  # (V, N, 3)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns (tracks of no view) compare False
        extent = np.linalg.norm(np.nanmax(at, axis=0) - np.nanmin(at, axis=0), axis=1)
    return extent <= ONE_PLACE * span


def fold_split(n: int, folds: int) -> np.ndarray:
    """(n,) fold index of each track, seeded."""
    return np.random.default_rng(FOLD_SEED).permutation(np.arange(n) % folds)


def combine(calib: Calibration, refined: Calibration, views: set[int]) -> Calibration:
    """``calib`` with ``views`` taken from ``refined`` (poses and intrinsics)."""
    poses = np.array(calib.ref_T_view)
    intr = list(calib.intrinsics)
    for v in views:
        poses[v] = refined.ref_T_view[v]
        intr[v] = refined.intrinsics[v]
    return calib.replace(ref_T_view=poses, intrinsics=tuple(intr))


def fold_refits(calib: Calibration, fit, px: np.ndarray, ok: np.ndarray, frame_of: np.ndarray | None,
                config: RefineConfig) -> tuple[list[Calibration], list[np.ndarray], list[frozenset[int]]]:
    """The fold refits (each without one fold of the fit's tracks) and, for each, the (N,) mask of the tracks it did
    not see and the views it held (too few observations without its fold). Folds are whole frames when ``frame_of``
    (the frame of each kept track) is given — errors within a frame are correlated —, else random tracks; none when
    ``config.folds`` is 0."""
    if not config.folds:
        return [], [], []
    if frame_of is not None:
        uniq = np.unique(frame_of)
        k = min(len(uniq), max(config.folds, MAX_FRAME_FOLDS))
        order = {f: i % k for i, f in enumerate(uniq)}
        fold = np.array([order[f] for f in frame_of], dtype=int)
    else:
        fold = fold_split(px.shape[1], config.folds)
    calibs, tests, held = [], [], []
    for k in range(int(fold.max()) + 1 if fold.size else 0):
        train, test = fold != k, fold == k
        if not test.any() or not train.any():
            continue
        try:
            fk = fit_auto(calib, px[:, train], ok[:, train], config, SilentObserver(), fit.held, fit.sigma_px)
        except (RuntimeError, ValueError):
            continue
        calibs.append(fk.calib)
        held.append(fk.held)
        tests.append(test)
    return calibs, tests, held


def heldout_test(calib: Calibration, fit, px: np.ndarray, ok: np.ndarray, sig_views: set[int],
                 fold_calibs: list[Calibration], fold_tests: list[np.ndarray], config: RefineConfig,
                 obs) -> tuple[Calibration, bool, bool, float, float, float]:
    """The candidate (the input with the views ``sig_views`` from the full fit) and its held-out test, which
    scores what is written: each fold's refit, applied to the same views, on its left-out tracks. Returns
    (candidate, accepted, inconsistent, held-out RMS of the input, of the candidate, the fit's own RMS) (px): RMS
    under the Gaussian model, the kernel's cost as an RMS (`gate_rms`) under a robust one, where a candidate must
    also be strictly better (a bounded kernel scores two far-off calibrations alike)."""
    if not sig_views:
        return calib, False, False, float("nan"), float("nan"), float("nan")
    candidate = combine(calib, fit.calib, sig_views)
    e_before = [heldoutfinite_rms(calib, px[:, t], ok[:, t]) for t in fold_tests]
    e_after = [heldoutfinite_rms(combine(calib, fc, sig_views), px[:, t], ok[:, t])
               for fc, t in zip(fold_calibs, fold_tests, strict=True)]
    if not e_before:
        return candidate, True, False, float("nan"), float("nan"), float("nan")
    robust = has_kernel(fit.noise)
    before = gate_rms(np.concatenate(e_before, axis=1), fit.noise, fit.sigma_px)
    after = gate_rms(np.concatenate(e_after, axis=1), fit.noise, fit.sigma_px)
    accepted = bool(after > 0 and before / after >= config.min_improvement and (after < before or not robust))
    # the candidate must predict tracks it did not see about as well as it fits its own: far worse means the folds
    # disagree (mismatches on a repeated pattern, too few tracks), whatever the input scores
    fit_rms = gate_rms(reprojection_errors(fit.calib, fit.points, fit.pixels, fit.valid), fit.noise, fit.sigma_px)
    inconsistent = bool(after > HELDOUT_CONSISTENCY * max(fit_rms, MIN_TRACK_RMS_PX))
    accepted &= not inconsistent
    obs.log(f"held-out tracks ({len(e_before)} folds): {'robust ' * robust}RMS {before:.4f} px with the input, "
            f"{after:.4f} px with the candidate refitted without them (its own tracks {fit_rms:.4f} px): "
            + ("accepted" if accepted else "rejected"))
    return candidate, accepted, inconsistent, before, after, fit_rms


def untested_views(calib: Calibration, sig_views: set[int], fold_held: list[frozenset[int]]) -> frozenset[int]:
    """In a free arrangement, the views about to be written that every fold refit held (too few observations without
    its fold, `RefineConfig.min_view_observations`): the held-out test never saw them change, so it cannot confirm
    them (dinoSparseRing perturbed, seed 3, with the consistency rule asked of the folds' whole refits, a variant
    measured and not kept: a view of 64 observations written 0.5 -> 2.1 deg off, the held-out RMS the input's to 4
    decimals). Grids keep their rule (their benchmark figures were set with it)."""
    if not calib.grid.is_free or not fold_held:
        return frozenset()
    return frozenset(v for v in sig_views if all(v in h for h in fold_held))
