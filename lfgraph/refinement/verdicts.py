"""A view's verdict after a refinement (OK, DRIFTED, UNCERTAIN, REFERENCE): the decision `assess` took, the
view's posterior sigmas and what it would need to be judged (`data_needs`); `ViewVerdict` is what a report lists.
And the causes a refusal names: another camera's intrinsics (`intrinsics_mismatch`) or wrong matches
(`outlier_evidence`, `refusal_cause`), each judged under the noise model the fit ran with."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.observer import SilentObserver
from lfgraph.core.sigmas import Sigmas
from lfgraph.engine.triangulate import RAYLEIGH_MEDIAN, finite_rms, reprojection_errors, tail_ratio
from lfgraph.factors.scene_graph import rotation_gauge
from lfgraph.refinement.config import RefineConfig
from lfgraph.refinement.fit import fit_tracks, has_kernel, same_track_costs
from lfgraph.refinement.posterior import Posterior, predicted_transfer_px
from lfgraph.refinement.report import DRIFTED, OK, REFERENCE, UNCERTAIN

MIN_TRACK_RMS_PX = 0.05  # KLT tracks are not better than this (px): the floor of a fit's own RMS
MAX_TRACK_SIGMA_PX = 1.0  # px per coordinate: KLT tracks fit a right rig to ~0.05-0.3 px (rendered and real sets);
# a refit that leaves more has fitted mismatches (sweep: a keyboard texture knocked by 15 px, all 72 tracks a key off)
NARROW_DEPTH_RATIO = 1.5  # 90th / 10th percentile of landmark depths below this: no depth range
COVERAGE_HINT = 0.5  # kept tracks in fewer than half of the 8x8 cells: poor coverage
FEW_OBSERVATIONS = 100  # a view with fewer observations than this wants more texture or frames
OUTLIER_TAIL_RATIO = 3.0  # a fit's residuals hold wrong matches when their RMS is more than this x what their median
# implies for Gaussian noise (`tail_ratio`): a right rig's KLT tracks 1.3-1.6, another unit's calibration 1.1 (issue
# 27's trial), 5 % wrong matches of 2-8 px on a knocked 3x3 7.7-12.6 (issue 40)
OUTLIER_SIGMAS = 5.0  # ... and the share of residuals beyond this many robust sigmas is reported (Gaussian: 4e-6)
INTRINSICS_CHECK_SIGMA_PX = 0.2  # px per coordinate: a poses-only fit about to change views that leaves more than
# this is compared with a fit whose intrinsics are free too (rendered knocks leave 0.03-0.1 px; another unit's
# calibration of the same model 0.33 px)
INTRINSICS_MISMATCH_RATIO = 0.5  # ... other intrinsics explain the tracks when that fit's RMS is below this share of
# the poses-only fit's: another unit 0.27-0.29; the own unit knocked (small-2x2, sweep seeds 3, 16, 17, 59) 1.2-2.7


@dataclass(frozen=True)
class OutlierEvidence:
    """Why a fit's residuals are wrong matches rather than other intrinsics: their RMS, their robust sigma per
    coordinate (median / sqrt(2 ln 2)), the RMS over what that sigma implies, and the share beyond `OUTLIER_SIGMAS`
    robust sigmas; ``robust``: whether the fit used a robust kernel."""

    rms_px: float
    sigma_px: float
    tail: float
    share: float
    robust: bool

    def text(self) -> str:
        """One line naming the cause, with the numbers and what to do."""
        advice = ("the kernel did not keep them from the fit: a kernel that ignores far residuals (cauchy, tukey) or "
                  "the clean stage" if self.robust else
                  "a least-squares fit is pulled by them: a robust kernel (--robust huber, cauchy, tukey) or the clean "
                  "stage")
        return (f"wrong matches: {100 * self.share:.1f} % of the observations lie beyond {OUTLIER_SIGMAS:g} robust "
                f"sigmas ({OUTLIER_SIGMAS * self.sigma_px:.2f} px) of the fit, whose RMS {self.rms_px:.3f} px is "
                f"{self.tail:.1f}x what its median residual implies; {advice}")


def outlier_evidence(errors: np.ndarray, robust: bool) -> OutlierEvidence | None:
    """`OutlierEvidence` of a fit's (V, N) residuals when their tail says wrong matches (`OUTLIER_TAIL_RATIO`), else
    None (Gaussian-like residuals, and the smooth misfit of other intrinsics)."""
    tail = tail_ratio(errors)
    if not tail > OUTLIER_TAIL_RATIO:
        return None
    e = errors[np.isfinite(errors)]
    sigma = float(np.median(e) / RAYLEIGH_MEDIAN)
    return OutlierEvidence(finite_rms(errors), sigma, tail, float(np.mean(e > OUTLIER_SIGMAS * sigma)), robust)


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
        """JSON-ready figures: the view's name under ``view``, the verdict, reason and needs, arrays as lists of
        floats (None where there is no number: no posterior, an undetermined system)."""
        def num(v) -> float | None:
            return float(v) if np.isfinite(v) else None

        def f(x):
            return [num(v) for v in np.ravel(x)] if np.ndim(x) else num(x)

        return {"view": self.name, "verdict": self.verdict, "applied": self.applied, "reason": self.reason,
                "needs": list(self.needs), "change_sigma": f(self.change_sigma),
                "rotation_change_deg": f(self.rotation_change_deg), "position_change_mm": f(self.position_change_mm),
                "intrinsics_change_px": f(self.intrinsics_change_px), "transfer_change_px": f(self.transfer_change_px),
                "sigma_rotation_deg": f(self.sigma_rotation_deg), "sigma_position_mm": f(self.sigma_position_mm),
                "sigma_intrinsics_px": f(self.sigma_intrinsics_px),
                "predicted_transfer_px": f(self.predicted_transfer_px), "observations": self.observations}




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


@dataclass(frozen=True)
class Decision:
    """What `assess` decided, view by view, for `verdict_of` to word."""

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
    foreign: tuple[float, float] | None = None  # (poses-only RMS, RMS with the intrinsics free) px: another unit's?
    outliers: OutlierEvidence | None = None  # wrong matches named as the cause of a refusal
    untested: frozenset[int] = frozenset()  # significant views no held-out fold refitted (free arrangements)
    whole: frozenset[int] = frozenset()  # a free arrangement's views written together (`lfgraph.refinement.whole`)

    @property
    def disagreement(self) -> float:
        """How many times worse the refits predict held-out tracks than the fit its own."""
        return self.heldout_after / max(self.fit_rms, MIN_TRACK_RMS_PX)


def view_sigmas(calib: Calibration, post: Posterior | None, v: int, rays: np.ndarray,
                 own: Sigmas | None, gauge_sigma: np.ndarray, reported: bool = False
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """View v's reported 1-sigmas (rotation deg, position mm, intrinsics px) and its predicted transfer at
    infinity (px), from the posterior; intrinsics a stage held report the input's own sigmas, a rotation held as a
    gauge its drift prior's (the graph's ~0 is no knowledge). With ``reported`` the predicted transfer includes that
    held rotation too (a stereo pair's pan: the scene cannot tell it from depth, so it stays as it was, unknown to
    its drift prior's sigma); without, it is the data's part, what the verdicts' tests judge by."""
    if post is None:
        return np.full(3, np.nan), np.full(3, np.nan), np.full(4, np.nan), float("nan")
    s_rot = np.degrees(np.sqrt(np.maximum(np.diag(post.pose_cov[v])[:3], 0.0)))
    s_pos = 1e3 * np.sqrt(np.maximum(np.diag(post.pose_cov[v])[3:], 0.0))
    s_int = np.sqrt(np.maximum(np.diag(post.intr_cov[v]), 0.0))
    if not post.intrinsics_free and own is not None:
        s_int = own.intrinsics[v]
    gauge_axis = rotation_gauge(calib)
    held_gauge = gauge_axis is not None and gauge_axis[0] == v and post.held_mask(v)[gauge_axis[1]]
    if held_gauge and reported:
        pose_cov = post.pose_cov.copy()
        pose_cov[v, gauge_axis[1], gauge_axis[1]] += gauge_sigma[v, gauge_axis[1]] ** 2
        post = dataclasses.replace(post, pose_cov=pose_cov)
    pred = predicted_transfer_px(calib, post, v, rays) if v != calib.grid.reference else 0.0
    if held_gauge:
        s_rot[gauge_axis[1]] = np.degrees(gauge_sigma[v, gauge_axis[1]])
    return s_rot, s_pos, s_int, pred


def verdict_of(v: int, dec: Decision, calib: Calibration, fit, config: RefineConfig, change_px: float, pred: float,
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
    if v in dec.whole:
        confirmed = (f"the held-out tracks confirm the refit of every view written together ({dec.heldout_before:.3f}"
                     f" px with the input, {dec.heldout_after:.3f} px with it)")
        if dec.significant.get(v):
            return DRIFTED, (", ".join(f"{g} {dec.zg[v][g]:.1f} sigma" for g in dec.significant[v])
                             + f" changed ({change_px:.2f} px); {confirmed}: written from the full fit"), None
        return UNCERTAIN, (f"no significant change of its own ({z:.1f} sigma, {change_px:.2f} px; 1 sigma = "
                           f"{pred:.2f} px at infinity), written with the whole arrangement: {confirmed}"), ask
    if v in dec.sig_views and dec.accepted:
        return DRIFTED, (", ".join(f"{g} {dec.zg[v][g]:.1f} sigma" for g in dec.significant[v])
                         + f" changed ({change_px:.2f} px > tolerance {config.tolerance_px:g} px), confirmed by "
                         "held-out tracks; the view is written from the full fit"), None
    if dec.inconsistent and v not in dec.sig_views:
        return UNCERTAIN, (f"a {z:.1f}-sigma change of {change_px:.2f} px, but the frames disagree: refits predict "
                           f"held-out tracks {dec.disagreement:.0f}x worse than they fit their own (mismatches, or "
                           f"too few tracks): kept"), ask
    if v in dec.untested:
        return UNCERTAIN, (f"a {z:.1f}-sigma change of {change_px:.2f} px that no held-out fold could test (the view "
                           f"has too few tracks to be refitted without one): kept"), ask
    if v in dec.unsure_mismatch and dec.foreign is not None:
        return UNCERTAIN, (f"a {z:.1f}-sigma change of {change_px:.2f} px, but other intrinsics explain the tracks "
                           f"far better than any poses ({dec.foreign[0]:.3f} px RMS with the poses alone, "
                           f"{dec.foreign[1]:.3f} px with the intrinsics free): this calibration is probably another "
                           f"camera's (re-calibrate): kept"), ()
    if v in dec.unsure_mismatch and dec.outliers is not None:
        return UNCERTAIN, f"a {z:.1f}-sigma change of {change_px:.2f} px, but {dec.outliers.text()}: kept", ()
    if v in dec.unsure_mismatch:
        return UNCERTAIN, (f"a {z:.1f}-sigma change of {change_px:.2f} px, but the tracks fit no rig better than "
                           f"{fit.sigma_px:.2f} px per coordinate (> {MAX_TRACK_SIGMA_PX:g} px: mismatches on a "
                           f"repeated pattern?): kept"), ("texture that does not repeat (or a scene farther away)",)
    determined = have_posterior and pred <= config.uncertain_transfer_px
    if v in dec.small and determined:
        return OK, (f"a significant ({z:.1f} sigma) change of {change_px:.3f} px, within the tolerance "
                    f"{config.tolerance_px:g} px: not applied"), None
    if v in dec.small:  # what changed significantly does not show at infinity; what would show is undetermined
        return UNCERTAIN, (f"a significant ({z:.1f} sigma) change of {change_px:.3f} px at infinity, but the data "
                           f"leave {pred:.2f} px (1 sigma) there undetermined: kept"), ask
    if v in dec.unsure:
        return UNCERTAIN, (f"a {z:.1f}-sigma change of {change_px:.2f} px, but applied it would leave "
                           f"{dec.unsure[v]:.2f} px (1 sigma) undetermined at infinity: kept"), ask
    if v in dec.sig_views:
        return UNCERTAIN, (f"a {z:.1f}-sigma change of {change_px:.2f} px that the held-out tracks did not confirm "
                           f"({dec.heldout_before:.3f} px with the input, {dec.heldout_after:.3f} px with the change"
                           + (f", {dec.disagreement:.0f}x what it leaves on its own tracks: the frames disagree"
                              if dec.inconsistent else "") + "): kept"), ask
    if not determined:
        return UNCERTAIN, (f"no significant change ({z:.1f} sigma) but the data leave {pred:.2f} px (1 sigma) at "
                           f"infinity undetermined: kept"), ask
    return OK, f"no significant change ({z:.1f} sigma; 1 sigma = {pred:.3f} px at infinity)", None


def intrinsics_mismatch(calib: Calibration, px: np.ndarray, ok: np.ndarray, fit, config: RefineConfig,
                        observer) -> tuple[float, float] | None:
    """(RMS of the poses-only fit, RMS with the intrinsics free too) (px) when other intrinsics explain the tracks far
    better than any poses (`INTRINSICS_MISMATCH_RATIO`): the calibration is probably another unit's, and the poses
    would absorb its intrinsics (issue 27's trial: rotations 0.61 -> 1.17 deg, positions 0.35 -> 7.7 mm, "DRIFTED").
    None when it does not, or when the fit freed intrinsics or left at most `INTRINSICS_CHECK_SIGMA_PX`, or for a
    stereo pair: there the second view's pan is held (the hidden rotation gauge), so a real pan knock only a
    principal point can absorb looks the same (sweep #101, #187: pairs knocked 1.4-1.8 deg).

    Under a robust kernel both fits are scored on the same tracks (``px``, ``ok``) with the kernel's cost
    (`same_track_costs`), the free fit run at the fit's sigma: wrong matches that a kernel weighs down are no
    evidence of other intrinsics (issue 40: the poses-only fit scored on its tracks before the mismatch rule, the free
    fit on those after it, 0.83 vs 0.08 px, "another camera"; on the same tracks 0.101 vs 0.085 px). Under the
    Gaussian model the test is as it was."""
    if fit.last_stage.frees_intrinsics or not fit.sigma_px > INTRINSICS_CHECK_SIGMA_PX or calib.num_views < 3:
        return None
    free_config = dataclasses.replace(config, stages="points,all")
    if has_kernel(fit.noise):
        free = fit_tracks(calib, px, ok, free_config, SilentObserver(), sigma_px=fit.sigma_px)
        poses_rms, free_rms = same_track_costs([fit.calib, free.calib], px, ok, fit.noise, fit.sigma_px,
                                               config.max_iterations)
    else:
        free = fit_tracks(calib, px, ok, free_config, SilentObserver())
        poses_rms = finite_rms(reprojection_errors(fit.calib, fit.points, fit.pixels, fit.valid))
        free_rms = finite_rms(reprojection_errors(free.calib, free.points, free.pixels, free.valid))
    observer.log(f"poses alone fit the tracks to {poses_rms:.4f} px; with the intrinsics free too, {free_rms:.4f} px"
                 + " (the kernel's cost as an RMS, on the same tracks)" * has_kernel(fit.noise))
    return (poses_rms, free_rms) if free_rms < INTRINSICS_MISMATCH_RATIO * poses_rms else None


def refusal_cause(fit, foreign: tuple[float, float] | None, accepted: bool,
                  observer) -> tuple[tuple[float, float] | None, OutlierEvidence | None]:
    """(another camera's evidence, wrong matches' evidence) of a refusal: the fit's own residuals are judged when
    nothing is changed; when their tail says wrong matches (`outlier_evidence`) and the another-camera test was the
    least-squares one (RMS of the poses-only fit's tracks before the mismatch rule against the free fit's after it,
    which the wrong matches alone can fail: issue 40), the wrong matches are named instead. The decision is the same:
    nothing the poses-only fit suggests is applied."""
    if accepted:
        return foreign, None
    evidence = outlier_evidence(reprojection_errors(fit.calib, fit.points, fit.pixels, fit.valid),
                                has_kernel(fit.noise))
    if evidence is not None:
        observer.log(f"the fit's residuals: {evidence.text()}")
        if foreign is not None and not evidence.robust:
            return None, evidence
    return foreign, evidence
