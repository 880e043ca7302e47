"""Honest acceptance of a refinement: the posterior of the MAP fit, held-out folds, a significance test of each
view's change per parameter group, and a per-view verdict (OK, DRIFTED, UNCERTAIN).

The RMS of the tracks a fit used cannot judge it (any refit lowers it). `assess`:
1. the MAP fit over all tracks (`lfgraph.refinement.fit.fit_auto`) and its marginals (`posterior`);
2. refits on folds (whole frames when there are several, else random thirds of the tracks): their scatter widens
   the marginals where those are too small (`inflate`);
3. per view and group (pan/tilt, roll, position, intrinsics when freed) a chi-square test of the change against the
   widened posterior plus the input's own sigma (`group_significance`), over the directions the graph does not hold
   by its structure; the significant groups' part of the change must move the transfer at infinity by more than
   ``tolerance_px`` (`change_size_px`), and by more than ``significance_sigma`` times what the fit leaves
   undetermined there;
4. the views that pass are written whole from the full fit (`combine`), if each fold's refit, applied to the same
   views, predicts its left-out tracks better than the input (``min_improvement``) and not far worse than the fit
   predicts its own (``HELDOUT_CONSISTENCY``); a fit that leaves more than ``MAX_TRACK_SIGMA_PX`` has fitted
   mismatches and changes nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lfgraph.calibration import Calibration
from lfgraph.factors.scene_graph import rotation_gauge
from lfgraph.observer import SilentObserver
from lfgraph.refinement.config import RefineConfig
from lfgraph.refinement.fit import fit_auto
from lfgraph.refinement.posterior import (
    GROUPS,
    ROTATION,
    Posterior,
    change_size_px,
    chi2_sigma,
    infinity_rays,
    pose_change,
    posterior,
    predicted_transfer_px,
    restricted,
)
from lfgraph.refinement.priors import input_sigmas, view_priors
from lfgraph.refinement.report import DRIFTED, OK, REFERENCE, UNCERTAIN
from lfgraph.refinement.triangulate import finite_rms, reprojection_errors, triangulate_dlt

FOLD_SEED = 14
MAX_FRAME_FOLDS = 5  # with several frames, at most this many folds of whole frames (the jackknife's units)
NARROW_DEPTH_RATIO = 1.5  # 90th / 10th percentile of landmark depths below this: no depth range
COVERAGE_HINT = 0.5  # kept tracks in fewer than half of the 8x8 cells: poor coverage
FEW_OBSERVATIONS = 100  # a view with fewer observations than this wants more texture or frames
HELDOUT_CONSISTENCY = 10.0  # held-out RMS of the candidate at most this x the full fit's RMS of its own tracks:
# legitimate thin fits predicted held-out tracks at up to ~5x (one frame of a 3x3 rig: 0.40 px vs 0.08 px); fits of
# mismatches at 17-39x (keyboard textures in benchmarks/sweep.py)
MIN_TRACK_RMS_PX = 0.05  # ... floored (KLT tracks are not better than this)
MAX_TRACK_SIGMA_PX = 1.0  # px per coordinate: KLT tracks fit a right rig to ~0.05-0.3 px (rendered and real sets);
# a refit that leaves more has fitted mismatches (sweep: a keyboard texture knocked by 15 px, all 72 tracks a key off)


@dataclass(frozen=True)
class ViewVerdict:
    """What the refinement (or the check) concluded for one view.

    Attributes:
        verdict: OK (no significant drift), DRIFTED (changed: significant and confirmed by held-out tracks),
            UNCERTAIN (the data cannot tell: ``needs`` says what would), REFERENCE (the gauge).
        change_sigma: the change's significance (one-sided normal deviate of its chi-square under the posterior).
        rotation_change_deg: (3,) body-frame change of pan/tilt (x, y) and roll (z) the fit proposed.
        position_change_mm: (3,) body-frame change of position the fit proposed.
        intrinsics_change_px: (4,) fx, fy, cx, cy change the fit proposed.
        transfer_change_px: the change's effect on the transfer at infinity (px, RMS over the image): of what was
            written for a DRIFTED view, of the significant groups' part for a view with a significant change, of
            the whole proposal otherwise.
        sigma_rotation_deg, sigma_position_mm, sigma_intrinsics_px: posterior 1-sigma (3, 3, 4), widened to the
            fold refits' scatter when that is larger; intrinsics a stage held report the input's own sigmas, a
            rotation held as a gauge (the second view's pan in a stereo pair) its drift prior's sigma, groups a
            DRIFTED view kept report the full fit's.
        predicted_transfer_px: 1-sigma transfer error at infinity (px) that the posterior of the refined parameters
            predicts (rotation, and intrinsics when freed; the directions the data determine, not a held gauge).
        applied: whether the output carries the change.
        reason: one line of why; needs: what data would decide an UNCERTAIN view.
    """

    view: int
    name: str
    verdict: str
    change_sigma: float
    rotation_change_deg: np.ndarray
    position_change_mm: np.ndarray
    intrinsics_change_px: np.ndarray
    transfer_change_px: float
    sigma_rotation_deg: np.ndarray
    sigma_position_mm: np.ndarray
    sigma_intrinsics_px: np.ndarray
    predicted_transfer_px: float
    observations: int
    applied: bool
    reason: str
    needs: tuple[str, ...] = field(default=())

    def as_dict(self) -> dict:
        def f(x):
            return [float(v) for v in np.ravel(x)] if np.ndim(x) else float(x)

        return {"view": self.name, "verdict": self.verdict, "applied": self.applied, "reason": self.reason,
                "needs": list(self.needs), "change_sigma": f(self.change_sigma),
                "rotation_change_deg": f(self.rotation_change_deg), "position_change_mm": f(self.position_change_mm),
                "intrinsics_change_px": f(self.intrinsics_change_px), "transfer_change_px": f(self.transfer_change_px),
                "sigma_rotation_deg": f(self.sigma_rotation_deg), "sigma_position_mm": f(self.sigma_position_mm),
                "sigma_intrinsics_px": f(self.sigma_intrinsics_px),
                "predicted_transfer_px": f(self.predicted_transfer_px), "observations": self.observations}




def group_significance(before: Calibration, after: Calibration, post: Posterior, v: int) -> dict[str, float]:
    """Per parameter group (pan/tilt, roll, position, and intrinsics when free): the change's deviate under the
    group's marginal posterior covariance. Groups are tested apart: a clear roll must not carry a pan/tilt that
    trades against position and that the data do not support. Directions the graph held by its structure (gauges,
    holds: `Posterior.held_mask`) are left out, however small or large their sigma."""
    d = _change_vector(before, after, v)
    cov = np.zeros((10, 10))
    cov[:6, :6], cov[6:, 6:], cov[:6, 6:], cov[6:, :6] = (post.pose_cov[v], post.intr_cov[v], post.cross[v],
                                                          post.cross[v].T)
    free = ~post.held_mask(v)
    out = {}
    for name, idx in (*GROUPS.items(), ("rotation", ROTATION)):
        idx_a = np.array([i for i in idx if free[i]], dtype=int)
        if idx_a.size == 0:
            continue
        c = cov[np.ix_(idx_a, idx_a)]
        dk = d[idx_a]
        # whiten by the diagonal first: rad, m and px differ by orders of magnitude
        scale = np.sqrt(np.maximum(np.diag(c), 0.0))
        if not np.all(scale > 0):
            out[name] = float("inf") if np.any(np.abs(dk[scale <= 0]) > 0) else 0.0
            continue
        cn, dn = c / np.outer(scale, scale), dk / scale
        d2 = float(dn @ np.linalg.lstsq(cn, dn, rcond=1e-12)[0])
        out[name] = chi2_sigma(d2, int(idx_a.size))
    return out


def data_needs(calib: Calibration, points: np.ndarray, valid: np.ndarray, v: int, coverage: float,
               frames: int) -> tuple[str, ...]:
    """What kind of data would decide view v: depth range, coverage, texture, frames."""
    needs = []
    if int(valid[v].sum()) < FEW_OBSERVATIONS // 4:  # too few tracks to say anything finer
        return (f"texture (only {int(valid[v].sum())} tracks reach this view: more texture, or a scene farther "
                f"away if tracks are lost between neighbouring views)", "more frames of different scenes")
    ref = calib.grid.reference
    m = valid[v] & valid[ref] & np.all(np.isfinite(points), axis=1)
    z = points[m, 2] if m.any() else np.zeros(0)
    z = z[z > 0]
    if z.size >= 2 and np.percentile(z, 90) / np.percentile(z, 10) < NARROW_DEPTH_RATIO:
        needs.append("depth range (texture both near and far in the same frame: pan/tilt trade against position)")
    if coverage < COVERAGE_HINT:
        needs.append("coverage (texture across the whole field of view: rotation about the optical axis)")
    if int(valid[v].sum()) < FEW_OBSERVATIONS:
        needs.append(f"texture (only {int(valid[v].sum())} tracks reach this view)")
    if frames < 2 or not needs:
        needs.append("more frames of different scenes")
    return tuple(needs)


def heldoutfinite_rms(calib: Calibration, pixels: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(V, N) reprojection errors of tracks triangulated with ``calib`` (not refitted: they test it)."""
    return reprojection_errors(calib, triangulate_dlt(calib, pixels, valid), pixels, valid)


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


@dataclass(frozen=True)
class Assessment:
    """The accepted calibration and how it was decided.

    ``heldout_before_px`` / ``heldout_after_px``: RMS reprojection of the held-out folds' tracks with the input and
    with the refits that did not see them (NaN when no change was tested); ``significant``: views whose change was
    significant; ``fit``: the full MAP fit (`lfgraph.refinement.fit.FitResult`)."""

    calib: Calibration
    verdicts: tuple[ViewVerdict, ...]
    accepted: bool
    heldout_before_px: float
    heldout_after_px: float
    sigma_px: float
    fit: object
    posterior: Posterior | None


def _change_vector(before: Calibration, after: Calibration, v: int) -> np.ndarray:
    a, b = after.intrinsics[v], before.intrinsics[v]
    return np.concatenate([pose_change(before.ref_T_view[v], after.ref_T_view[v]),
                           [a.fx - b.fx, a.fy - b.fy, a.cx - b.cx, a.cy - b.cy]])


def inflate(post: Posterior, calib: Calibration, fold_calibs: list[Calibration]) -> tuple[Posterior, np.ndarray]:
    """The posterior widened, per view and parameter group, to the scatter of the fold refits (jackknife).

    Track errors are not independent (a frame's mismatches on a repeated pattern agree with each other), so the
    graph's marginals can be several times too small; the jackknife over folds (frames when there are several)
    sees that. Returns the widened posterior and the (V, 4) factors (pan/tilt, roll, position, intrinsics).
    """
    n = calib.num_views
    factors = np.ones((n, 4))
    k = len(fold_calibs)
    if k < 2:
        return post, factors
    for v in range(n):
        d = np.stack([_change_vector(calib, fc, v) for fc in fold_calibs])
        jk = (k - 1) / k * np.sum((d - d.mean(axis=0)) ** 2, axis=0)  # jackknife variances (10,)
        full_var = np.concatenate([np.diag(post.pose_cov[v]), np.diag(post.intr_cov[v])])
        free = ~post.held_mask(v)
        for gi, idx in enumerate(GROUPS.values()):
            idx_a = np.array([i for i in idx if free[i]], dtype=int)
            if idx_a.size == 0:
                continue
            var = float(np.sum(full_var[idx_a]))  # one unit per group: rad, m or px
            if var > 0:
                factors[v, gi] = max(1.0, float(np.sum(jk[idx_a])) / var)
    return apply_factors(post, factors), factors


def apply_factors(post: Posterior, factors: np.ndarray) -> Posterior:
    """The posterior with each view's groups widened by `inflate`'s (V, 4) variance factors."""
    pose_cov, intr_cov, cross = post.pose_cov.copy(), post.intr_cov.copy(), post.cross.copy()
    for v in range(len(factors)):
        scale = np.ones(10)
        for gi, idx in enumerate(GROUPS.values()):
            scale[np.array(idx)] = np.sqrt(factors[v, gi])
        pose_cov[v] = post.pose_cov[v] * np.outer(scale[:6], scale[:6])
        intr_cov[v] = post.intr_cov[v] * np.outer(scale[6:], scale[6:])
        cross[v] = post.cross[v] * np.outer(scale[:6], scale[6:])
    return Posterior(pose_cov, intr_cov, cross, post.intrinsics_free, post.sigma_px, post.held)


def with_input_uncertainty(post: Posterior, calib: Calibration) -> Posterior:
    """The covariance of (refined - input): the posterior plus the input's own (calibrate's marginals, when
    stored). A change within what the input calibration itself could not pin down is no drift."""
    own = input_sigmas(calib)
    if own is None:
        return post
    pose_cov = post.pose_cov + np.stack([np.diag(s**2) for s in own[0]])
    intr_cov = post.intr_cov if not post.intrinsics_free else post.intr_cov + np.stack([np.diag(s**2) for s in own[1]])
    return Posterior(pose_cov, intr_cov, post.cross, post.intrinsics_free, post.sigma_px, post.held)


def fold_refits(calib: Calibration, fit, px: np.ndarray, ok: np.ndarray, frame_of: np.ndarray | None,
                config: RefineConfig) -> tuple[list[Calibration], list[np.ndarray]]:
    """The fold refits (each without one fold of the fit's tracks) and, for each, the (N,) mask of the tracks it did
    not see. Folds are whole frames when ``frame_of`` (the frame of each kept track) is given — errors within a frame
    are correlated —, else random tracks; none when ``config.folds`` is 0."""
    if not config.folds:
        return [], []
    if frame_of is not None:
        uniq = np.unique(frame_of)
        k = min(len(uniq), max(config.folds, MAX_FRAME_FOLDS))
        order = {f: i % k for i, f in enumerate(uniq)}
        fold = np.array([order[f] for f in frame_of], dtype=int)
    else:
        fold = fold_split(px.shape[1], config.folds)
    calibs, tests = [], []
    for k in range(int(fold.max()) + 1 if fold.size else 0):
        train, test = fold != k, fold == k
        if not test.any() or not train.any():
            continue
        try:
            fk = fit_auto(calib, px[:, train], ok[:, train], config, SilentObserver(), fit.held, fit.sigma_px)
        except (RuntimeError, ValueError):
            continue
        calibs.append(fk.calib)
        tests.append(test)
    return calibs, tests


def heldout_test(calib: Calibration, fit, px: np.ndarray, ok: np.ndarray, sig_views: set[int],
                 fold_calibs: list[Calibration], fold_tests: list[np.ndarray], config: RefineConfig,
                 obs) -> tuple[Calibration, bool, bool, float, float, float]:
    """The candidate (the input with the views ``sig_views`` from the full fit) and its held-out test, which
    scores what is written: each fold's refit, applied to the same views, on its left-out tracks. Returns
    (candidate, accepted, inconsistent, held-out RMS of the input, of the candidate, the fit's own RMS) (px)."""
    if not sig_views:
        return calib, False, False, float("nan"), float("nan"), float("nan")
    candidate = combine(calib, fit.calib, sig_views)
    e_before = [heldoutfinite_rms(calib, px[:, t], ok[:, t]) for t in fold_tests]
    e_after = [heldoutfinite_rms(combine(calib, fc, sig_views), px[:, t], ok[:, t])
               for fc, t in zip(fold_calibs, fold_tests, strict=True)]
    if not e_before:
        return candidate, True, False, float("nan"), float("nan"), float("nan")
    before = finite_rms(np.concatenate(e_before, axis=1))
    after = finite_rms(np.concatenate(e_after, axis=1))
    accepted = bool(after > 0 and before / after >= config.min_improvement)
    # the candidate must predict tracks it did not see about as well as it fits its own: far worse means the folds
    # disagree (mismatches on a repeated pattern, too few tracks), whatever the input scores
    fit_rms = finite_rms(reprojection_errors(fit.calib, fit.points, fit.pixels, fit.valid))
    inconsistent = bool(after > HELDOUT_CONSISTENCY * max(fit_rms, MIN_TRACK_RMS_PX))
    accepted &= not inconsistent
    obs.log(f"held-out tracks ({len(e_before)} folds): RMS {before:.4f} px with the input, {after:.4f} px with the "
            f"candidate refitted without them (its own tracks {fit_rms:.4f} px): "
            + ("accepted" if accepted else "rejected"))
    return candidate, accepted, inconsistent, before, after, fit_rms


def assess(calib: Calibration, pixels: np.ndarray, valid: np.ndarray, config: RefineConfig, observer,
           coverage: float, frames: int, frame_of: np.ndarray | None = None,
           sigma_estimate: float | None = None) -> Assessment:
    """MAP fit, posterior, fold refits (held-out tracks and the jackknife), significance, verdicts (see the
    module docstring). ``frame_of``: (N,) frame of each track; with several frames the folds are whole frames.
    ``sigma_estimate``: the measurement sigma the fit of the previous frames supported (`fit_auto`)."""

    fit = fit_auto(calib, pixels, valid, config, observer, sigma_estimate=sigma_estimate)
    post = posterior(calib, fit, config)
    n, ref = calib.num_views, calib.grid.reference
    rays = infinity_rays(calib)
    px, ok = pixels[:, fit.keep], valid[:, fit.keep]  # mismatches the full fit dropped are not evidence
    several = frame_of is not None and len(np.unique(frame_of)) >= 2  # folds of whole frames
    fold_calibs, fold_tests = fold_refits(calib, fit, px, ok, frame_of[fit.keep] if several else None, config)
    factors = np.ones((n, 4))
    if post is not None:
        post, factors = inflate(post, calib, fold_calibs)
        if np.any(factors > 1.0):
            worst = np.unravel_index(np.argmax(factors), factors.shape)
            observer.log(f"fold refits scatter up to {np.sqrt(factors.max()):.1f}x more than the graph's marginals "
                         f"({calib.grid.name(int(worst[0]))}, {list(GROUPS)[int(worst[1])]}): sigmas widened")
    test_post = with_input_uncertainty(post, calib) if post is not None else None
    free = [v for v in range(n) if v != ref and v not in fit.held]
    zg = {v: group_significance(calib, fit.calib, test_post, v) if test_post is not None else {} for v in free}
    z = {v: max(zg[v].values(), default=0.0) for v in free}
    significant = {v: tuple(g for g, x in zg[v].items() if x > config.significance_sigma) for v in free}
    # significant is not the same as mattering: only the significant groups' part of a change counts towards the
    # tolerance, and a change within it is reported, not applied
    size_px = change_size_px(calib, fit.calib, significant)
    proposed_px = change_size_px(calib, fit.calib)  # the whole proposal, shown for views with nothing significant
    sig_views = {v for v in free if significant[v]}
    small = {v for v in sig_views if not size_px[v] > config.tolerance_px}
    sig_views -= small
    # tracks that no rig explains to within MAX_TRACK_SIGMA_PX are mismatches (a repeated pattern shifted by whole
    # periods looks like a turned camera): nothing they suggest is applied
    mismatched = not fit.sigma_px <= MAX_TRACK_SIGMA_PX
    if mismatched:
        observer.log(f"the refit leaves {fit.sigma_px:.2f} px per coordinate (> {MAX_TRACK_SIGMA_PX:g} px): the tracks "
                     f"are mismatched, nothing is changed")
        unsure_mismatch = set(sig_views) | small
        sig_views, small = set(), set()
    else:
        unsure_mismatch = set()
    # a drifted view is written whole from the full MAP fit, in which every view was free: holding its groups that
    # were not significant let the others absorb their real change (sweep: pan/tilt error/sigma 5.8 -> 3.1, misses
    # 1 -> 0 of 267), and a refit holding the views that did not drift let a weakly seen view's insignificant but
    # real error pull every other view (sweep #166: all positions 1.2 mm off, 50 sigma). Its change at infinity must
    # stand out (significance_sigma times) against what the fit leaves undetermined there in the same groups: a
    # change significant in a position that is small against that uncertainty cannot be trusted to improve the view
    # (the groups that did not change significantly are about as uncertain in the input as in the fit).
    unsure: dict[int, float] = {}  # significant, but what would be applied leaves this much undetermined (px)
    for v in sorted(sig_views):
        x = predicted_transfer_px(calib, restricted(post, v, significant[v]), v, rays) if post is not None \
            else float("inf")
        if not x <= size_px[v] / config.significance_sigma:
            unsure[v] = x
    sig_views -= set(unsure)
    candidate, accepted, inconsistent, heldout_before, heldout_after, fit_rms = heldout_test(
        calib, fit, px, ok, sig_views, fold_calibs, fold_tests, config, observer)
    out = candidate if accepted else calib
    dec = _Decision(significant, zg, z, frozenset(sig_views), frozenset(small), unsure, frozenset(unsure_mismatch),
                    accepted, inconsistent, heldout_before, heldout_after, fit_rms)
    written_size = change_size_px(calib, out, significant)
    own = input_sigmas(calib)
    gauge_sigma = view_priors(calib, config.drift).pose_sigmas
    verdicts = []
    for v in range(n):
        applied = v in sig_views and accepted
        shown = out if applied else fit.calib  # an applied view reports what was written, the others the proposal
        d = pose_change(calib.ref_T_view[v], shown.ref_T_view[v])
        a, b = shown.intrinsics[v], calib.intrinsics[v]
        dk = np.array([a.fx - b.fx, a.fy - b.fy, a.cx - b.cx, a.cy - b.cy])
        s_rot, s_pos, s_int, pred = _view_sigmas(calib, post, v, rays, own, gauge_sigma)
        change_px = float(written_size[v] if applied else size_px[v] if significant.get(v) else proposed_px[v])
        verdict, reason, needs = _verdict(v, dec, calib, fit, config, change_px, pred, post is not None)
        needs = () if needs is None else (*needs, *data_needs(calib, fit.points, fit.valid, v, coverage, frames))
        verdicts.append(ViewVerdict(v, calib.grid.name(v), verdict, float(z.get(v, 0.0)), np.degrees(d[:3]),
                                    1e3 * d[3:], dk, change_px, s_rot, s_pos, s_int, float(pred),
                                    int(fit.valid[v].sum()), applied, reason, needs))
    return Assessment(out, tuple(verdicts), accepted, heldout_before, heldout_after, fit.sigma_px, fit, post)


@dataclass(frozen=True)
class _Decision:
    """What `assess` decided, view by view, for `_verdict` to word."""

    significant: dict[int, tuple[str, ...]]
    zg: dict[int, dict[str, float]]
    z: dict[int, float]
    sig_views: frozenset[int]
    small: frozenset[int]
    unsure: dict[int, float]
    unsure_mismatch: frozenset[int]
    accepted: bool
    inconsistent: bool
    heldout_before: float
    heldout_after: float
    fit_rms: float

    @property
    def disagreement(self) -> float:
        """How many times worse the refits predict held-out tracks than the fit its own."""
        return self.heldout_after / max(self.fit_rms, MIN_TRACK_RMS_PX)


def _view_sigmas(calib: Calibration, post: Posterior | None, v: int, rays: np.ndarray,
                 own: tuple[np.ndarray, np.ndarray] | None, gauge_sigma: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """View v's reported 1-sigmas (rotation deg, position mm, intrinsics px) and its predicted transfer at
    infinity (px), from the posterior; intrinsics a stage held report the input's own sigmas, a rotation held as a
    gauge its drift prior's (the graph's ~0 is no knowledge)."""
    if post is None:
        return np.full(3, np.nan), np.full(3, np.nan), np.full(4, np.nan), float("nan")
    s_rot = np.degrees(np.sqrt(np.maximum(np.diag(post.pose_cov[v])[:3], 0.0)))
    s_pos = 1e3 * np.sqrt(np.maximum(np.diag(post.pose_cov[v])[3:], 0.0))
    s_int = np.sqrt(np.maximum(np.diag(post.intr_cov[v]), 0.0))
    if not post.intrinsics_free and own is not None:
        s_int = own[1][v]
    pred = predicted_transfer_px(calib, post, v, rays) if v != calib.grid.reference else 0.0
    gauge_axis = rotation_gauge(calib)
    if gauge_axis is not None and gauge_axis[0] == v and post.held_mask(v)[gauge_axis[1]]:
        s_rot[gauge_axis[1]] = np.degrees(gauge_sigma[v, gauge_axis[1]])  # predicted_transfer_px: the data's part
    return s_rot, s_pos, s_int, pred


def _verdict(v: int, dec: _Decision, calib: Calibration, fit, config: RefineConfig, change_px: float, pred: float,
             have_posterior: bool) -> tuple[str, str, tuple[str, ...] | None]:
    """(verdict, reason, needs) of view v: ``needs`` None when the verdict wants no more data, else the specific
    needs that come before `data_needs` (which the caller appends)."""
    z = dec.z.get(v, 0.0)
    ask: tuple[str, ...] = ()
    if v == calib.grid.reference:
        return REFERENCE, "the reference view (the gauge)", None
    if v in fit.held:
        return UNCERTAIN, (f"only {int(fit.valid[v].sum())} observations (< {config.min_view_observations}): "
                           f"held"), ask
    if v in dec.sig_views and dec.accepted:
        return DRIFTED, (", ".join(f"{g} {dec.zg[v][g]:.1f} sigma" for g in dec.significant[v])
                         + f" changed ({change_px:.2f} px > tolerance {config.tolerance_px:g} px), confirmed by "
                         "held-out tracks; the view is written from the full fit"), None
    if dec.inconsistent and v not in dec.sig_views:
        return UNCERTAIN, (f"a {z:.1f}-sigma change of {change_px:.2f} px, but the frames disagree: refits predict "
                           f"held-out tracks {dec.disagreement:.0f}x worse than they fit their own (mismatches, or "
                           f"too few tracks): kept"), ask
    if v in dec.unsure_mismatch:
        return UNCERTAIN, (f"a {z:.1f}-sigma change of {change_px:.2f} px, but the tracks fit no rig better than "
                           f"{fit.sigma_px:.2f} px per coordinate (> {MAX_TRACK_SIGMA_PX:g} px: mismatches on a "
                           f"repeated pattern?): kept"), ("texture that does not repeat (or a scene farther away)",)
    if v in dec.small:
        return OK, (f"a significant ({z:.1f} sigma) change of {change_px:.3f} px, within the tolerance "
                    f"{config.tolerance_px:g} px: not applied"), None
    if v in dec.unsure:
        return UNCERTAIN, (f"a {z:.1f}-sigma change of {change_px:.2f} px, but applied it would leave "
                           f"{dec.unsure[v]:.2f} px (1 sigma) undetermined at infinity: kept"), ask
    if v in dec.sig_views:
        return UNCERTAIN, (f"a {z:.1f}-sigma change of {change_px:.2f} px that the held-out tracks did not confirm "
                           f"({dec.heldout_before:.3f} px with the input, {dec.heldout_after:.3f} px with the change"
                           + (f", {dec.disagreement:.0f}x what it leaves on its own tracks: the frames disagree"
                              if dec.inconsistent else "") + "): kept"), ask
    if not have_posterior or not pred <= config.uncertain_transfer_px:
        return UNCERTAIN, (f"no significant change ({z:.1f} sigma) but the data leave {pred:.2f} px (1 sigma) at "
                           f"infinity undetermined: kept"), ask
    return OK, f"no significant change ({z:.1f} sigma; 1 sigma = {pred:.3f} px at infinity)", None
