"""Weakly seen views of a long line: does the robust screen drop good view-frames, and do the end views predict held-out
board positions as well as their own uncertainty says they should?

A rendered look-alike of a long real line array (1920x1200 views on one line, a board shown at a few *positions*
spread along the line, several hand-held frames at each: the board jittered by ~1 cm and ~1.5 deg), so that the views
at the ends see only 2-3 of the positions. Corners are the true projections plus Gaussian noise (corner-only: no
rendering, so the truth and the noise are exact).

**Leave one position out** (LOPO): every position whose removal leaves each view at least one frame is held out in
turn; the rig is calibrated from the other positions (lfgraph's default route, radtan lens, with and without the
robust screen) and each held-out view-frame is predicted from the rest: its board pose fitted through the frame's
*other* views with the rig held fixed, its corners projected into the view. Per view: the RMS of the held-out
corners, and the RMS the Cramér–Rao prediction gives for them (`lfgraph.pattern.prediction`: the joint posterior of
the view's and the other views' intrinsics and poses from the calibration's own graph, the board pose's uncertainty
from its fit and the corner noise the fit's residuals give). Leave-one-*frame*-out hides the weak views' trouble: a
held-out frame always has jittered twins at its position in the fit.

Printed per setting: the view-frames the screen dropped; per weak view (one seeing at most `WEAK_POSITIONS`
positions) the held-out RMS with the screen, without, and the predicted RMS; and the worst ratio of held-out to
predicted over the weak views (the target: within `TARGET_RATIO`).

One draw of the corner noise gives each view one draw of its calibration error, which its held-out frames (near
copies of one position) see through a few directions: a view's held-out / predicted ratio from one draw scatters like
the square root of a chi-square of few degrees of freedom divided by them, and the worst of many weak views is well
above 1 even when the prediction is exact (1x30, seed 1: every view is weak; over 19 draws the ratios pooled over all
weak views gave 1.01, 8 % of single view-draws were above 1.5, and the worst of the 30 views was 1.2-2.4 per draw).
``--draws N`` redraws the noise N - 1 more times on the same rig and board poses (draw 0 is the single-draw run's
noise) and pools each view's held-out and predicted squares over the draws: the target is then each weak view's
ratio pooled over the draws, the prediction's calibration view by view, not one draw's scatter.

Two kinds of true lenses (``--tangential``): radtan k1, k2 that the model fits (0), and lenses decentred by p1, p2 of
std `TANGENTIAL_SIGMA`, which the default model holds at 0: a real lens's misfit, which is what makes a robust fit
miss good view-frames of the weak views (with Gaussian corners and a fitting model the screen drops nothing). The
Cramér–Rao prediction knows the noise, not a misfit: the ratio is a target only where the model fits.

Usage: ``python benchmarks/weak_views.py [--views 20 12 30] [--sigma 0.1 0.3] [--seeds 0 1] [--tangential 0 0.002]
[--draws 16]``.
Exit code 1 when a setting misses the target or the default is worse than ``--no-screen`` on a weak view by more than
`NOISE_TOLERANCE`.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import sys
import time

import numpy as np

import lfgraph as lf
from lfgraph.core.geometry import invert_T, make_T, rotation_from_rotvec
from lfgraph.datasets.board_render import CheckerboardConfig
from lfgraph.datasets.checkerboard import make_checkerboard_truth, make_corner_observations
from lfgraph.datasets.rig import RigConfig, make_rig
from lfgraph.detect.board import BoardSpec
from lfgraph.detect.detections import BoardObservations, observations_from_arrays
from lfgraph.pattern.initial import CalibrationInputError, initial_board_T_ref, pnp_all
from lfgraph.pattern.prediction import frame_jacobians, predict_view_frame, rig_marginals
from lfgraph.pattern.scoring import fit_board_poses

IMAGE_SIZE_PX = (1920, 1200)
FOCAL_PX = 1600.0
PITCH_M = 0.06
BOARD = BoardSpec(11, 8, 0.05)  # 12x9 squares of 5 cm: a 0.6 x 0.45 m board
DISTANCE_M = 1.5  # the board positions' mean distance
POSITIONS = 5
FRAMES_PER_POSITION = 4
FRAME_JITTER_M = 0.01  # a hand-held board: each frame of a position moved by ~1 cm ...
FRAME_JITTER_DEG = 1.5  # ... and turned by ~1.5 deg
POSITION_TILT_DEG = 25.0  # each position turned by up to this much (its own side of the board to the line)
TANGENTIAL_SIGMA = 2e-3  # each true lens decentred: p1, p2 drawn with this std, which the default model holds at 0 (a
# real lens's misfit: without it the screen never drops a good view-frame of Gaussian corners)
WEAK_POSITIONS = 3  # a view seeing at most this many positions is weak
TARGET_RATIO = 1.5  # weak views' held-out RMS within this factor of their predicted RMS
NOISE_DRAW_SEED = 1000  # --draws: noise draw d > 0 from the seed [seed, NOISE_DRAW_SEED + d - 1]
NOISE_TOLERANCE = 0.05  # the default may be worse than --no-screen on a weak view by this share (the fits' noise)
CONFIG = lf.CalibrateConfig(lens="radtan", marginals=False)


def line_rig(views: int, seed: int, tangential: float = TANGENTIAL_SIGMA) -> lf.Calibration:
    """A 1 x ``views`` line of 1920x1200 views 6 cm apart (reference: view 0, one end), lenses decentred by
    ``tangential`` (std of p1, p2; default `TANGENTIAL_SIGMA`)."""
    config = RigConfig(rows=1, cols=views, pitch_m=PITCH_M, image_size_px=IMAGE_SIZE_PX, focal_px=FOCAL_PX,
                       k1=-0.12, k2=0.05, focal_jitter_px=10.0, principal_jitter_px=10.0, rot_jitter_deg=0.5,
                       trans_jitter_mm=1.0)
    calib = make_rig(config, np.random.default_rng(seed))
    rng = np.random.default_rng([seed, 7])
    return calib.replace(intrinsics=tuple(dataclasses.replace(i, p1=p1, p2=p2) for i, (p1, p2) in zip(
        calib.intrinsics, tangential * rng.standard_normal((views, 2)), strict=True)))


def board_poses(calib: lf.Calibration, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(F, 4, 4) ``ref_T_board`` and (F,) position index: `POSITIONS` positions spread along the line (the outer ones
    beyond its ends), `FRAMES_PER_POSITION` jittered frames each."""
    span = (calib.num_views - 1) * PITCH_M
    centre_b = np.array([(BOARD.cols - 1) * BOARD.square_m / 2, (BOARD.rows - 1) * BOARD.square_m / 2, 0.0])
    poses, labels = [], []
    xs = span / 2 + np.linspace(-0.8, 0.8, POSITIONS) * (span / 2 + 0.3)
    for p, x in enumerate(xs):
        tilt = np.radians(POSITION_TILT_DEG) * rng.uniform(-1, 1, 2)
        centre = np.array([x, rng.uniform(-0.1, 0.1), DISTANCE_M * rng.uniform(0.85, 1.15)])
        for _ in range(FRAMES_PER_POSITION):
            rot = rotation_from_rotvec([*tilt, 0.0]) @ rotation_from_rotvec(
                np.radians(FRAME_JITTER_DEG) * rng.standard_normal(3))
            c = centre + FRAME_JITTER_M * rng.standard_normal(3)
            poses.append(make_T(rot, c - rot @ centre_b))
            labels.append(p)
    return np.stack(poses), np.array(labels)


@dataclasses.dataclass(frozen=True)
class Line:
    calib: lf.Calibration
    obs: BoardObservations
    position: np.ndarray  # (F,) board position of every frame
    sigma_px: float

    def positions_seen(self) -> np.ndarray:
        """(V,) how many positions each view sees."""
        return np.array([len(set(self.position[self.obs.seen[v]])) for v in range(self.obs.num_views)])


def make_line(views: int, sigma_px: float, seed: int, tangential: float = TANGENTIAL_SIGMA, draw: int = 0) -> Line:
    """The line, its board poses and noisy corners; ``draw`` > 0 redraws the corner noise alone (seed
    ``[seed, NOISE_DRAW_SEED + draw - 1]``) on the same rig and board poses."""
    calib = line_rig(views, seed, tangential)
    rng = np.random.default_rng([seed, 1])
    poses, labels = board_poses(calib, rng)
    config = CheckerboardConfig(board=BOARD, frames=len(poses), margin_px=3.0)
    truth = make_checkerboard_truth(calib, config, rng, ref_T_board=poses)
    noise = rng if draw == 0 else np.random.default_rng([seed, NOISE_DRAW_SEED + draw - 1])
    corners, valid = make_corner_observations(truth, sigma_px, noise)
    obs = observations_from_arrays(BOARD, calib.grid, calib.image_size_px, corners, valid)
    keep = obs.seen.any(axis=0)
    return Line(calib, obs.subset_frames(np.nonzero(keep)[0]), labels[keep], sigma_px)


def dropped(report) -> list[str]:
    return [w for w in report.warnings if "dropped from the calibration" in w]


def held_out(line: Line, p: int, screen: bool) -> tuple[dict[int, tuple[float, float, int]], list[str]]:
    """Position ``p`` held out: per view seeing it, (sum of squared held-out RMS, sum of squared predicted RMS,
    view-frames), and the screen's drops."""
    obs = line.obs
    train, test = np.nonzero(line.position != p)[0], np.nonzero(line.position == p)[0]
    train_obs = obs.subset_frames(train)
    calib, report = lf.calibrate(train_obs, dataclasses.replace(CONFIG, screen=screen))
    marg = rig_marginals(train_obs, calib.intrinsics, calib.ref_T_view, report.board_T_ref,
                         BOARD.object_points(), CONFIG)
    test_obs = obs.subset_frames(test)
    starts = initial_board_T_ref(pnp_all(test_obs, calib.intrinsics), calib.ref_T_view, test_obs.valid.sum(axis=2))
    out: dict[int, tuple[float, float, int]] = {}
    for f in range(test_obs.num_frames):
        seeing = [int(h) for h in np.nonzero(test_obs.seen[:, f])[0]]
        if len(seeing) < 2:
            continue
        board = fit_board_poses(calib.intrinsics, calib.ref_T_view, test_obs.subset_frames([f]), starts[f:f + 1])[0]
        jac = frame_jacobians(test_obs, calib.intrinsics, calib.ref_T_view, f, seeing, invert_T(board))
        for v in seeing:
            helpers = [h for h in seeing if h != v]
            pred = predict_view_frame(test_obs, calib.intrinsics, calib.ref_T_view, marg, v, f, helpers,
                                      report.noise_sigma_px, starts[f], jac)
            a, b, n = out.get(v, (0.0, 0.0, 0))
            out[v] = (a + pred.rms_px**2, b + pred.predicted_rms_px**2, n + 1)
    return out, dropped(report)


def lopo_sums(line: Line, screen: bool) -> tuple[np.ndarray, list[str]]:
    """(V, 3) per view over every position that can be held out: the sums of squared held-out RMS and of squared
    predicted RMS and the view-frames; and the screen's drops."""
    sums = np.zeros((line.obs.num_views, 3))
    drops: list[str] = []
    for p in np.unique(line.position):
        rest = line.obs.seen[:, line.position != p]
        if not np.all(rest.sum(axis=1) >= 1):
            continue
        try:
            per_view, d = held_out(line, int(p), screen)
        except CalibrationInputError as e:  # e.g. the middle position of a long line links its two halves
            print(f"position {p} not held out: {str(e)[:80]}...")
            continue
        drops += [f"position {p}: {w.split(':')[0]}" for w in d]
        for v, (a, b, n) in per_view.items():
            sums[v] += (a, b, n)
    return sums, drops


def _ratios(sums: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    with np.errstate(invalid="ignore"):
        return np.sqrt(sums[:, 0] / sums[:, 2]), np.sqrt(sums[:, 1] / sums[:, 2])


def lopo(line: Line, screen: bool) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(V,) held-out RMS and predicted RMS per view over every position that can be held out, and the drops."""
    sums, drops = lopo_sums(line, screen)
    return *_ratios(sums), drops


def run(views: int, sigma_px: float, seed: int, tangential: float, draws: int = 1) -> tuple[float, float, bool]:
    line = make_line(views, sigma_px, seed, tangential)
    seen = line.positions_seen()
    weak = np.nonzero(seen <= WEAK_POSITIONS)[0]
    print(f"\n## 1x{views}, corner noise {sigma_px} px, p1 p2 std {tangential:g}, seed {seed}: "
          f"{line.obs.num_frames} frames; positions seen "
          f"per view {seen.tolist()}; weak views {weak.tolist()}" + (f"; {draws} noise draws" if draws > 1 else ""),
          flush=True)
    t0 = time.perf_counter()
    sums = {s: np.zeros((line.obs.num_views, 3)) for s in (True, False)}
    drops: dict[bool, list[str]] = {True: [], False: []}
    single = []  # per draw, the weak views' held-out / predicted ratio of that draw alone (screen on)
    for d in range(draws):
        draw_line = line if d == 0 else make_line(views, sigma_px, seed, tangential, draw=d)
        for s in (True, False):
            part, dropped_here = lopo_sums(draw_line, s)
            sums[s] += part
            drops[s] += [f"draw {d}, {w}" if draws > 1 else w for w in dropped_here]
            if s:
                on_d, pred_d = _ratios(part)
                single.append((on_d / pred_d)[weak])
    res = {s: (*_ratios(sums[s]), drops[s]) for s in (True, False)}
    print(f"({time.perf_counter() - t0:.0f} s)")
    for s, (_, _, dropped_list) in res.items():
        print(f"screen {'on ' if s else 'off'}: {len(dropped_list)} view-frames dropped"
              + (": " + "; ".join(dropped_list[:8]) if dropped_list else ""))
    pooled = " (held-out and predicted squares pooled over the draws)" if draws > 1 else ""
    print(f"| view | positions | held-out px, screen | no screen | predicted px | ratio (screen){pooled} |")
    print("| --- | --- | --- | --- | --- | --- |")
    for v in weak:
        print(f"| {v} | {seen[v]} | {res[True][0][v]:.3f} | {res[False][0][v]:.3f} | {res[True][1][v]:.3f} | "
              f"{res[True][0][v] / res[True][1][v]:.2f} |")
    on, off, pred = res[True][0][weak], res[False][0][weak], res[True][1][weak]
    ok = np.isfinite(on) & np.isfinite(off)
    worst = float(np.max(on[ok] / pred[ok])) if ok.any() else float("nan")
    worse = float(np.max(on[ok] / off[ok])) if ok.any() else float("nan")
    all_ratio = res[True][0] / res[True][1]
    print(f"weak views: worst held-out / predicted {worst:.2f} (target {TARGET_RATIO}); worst screen / no screen "
          f"{worse:.3f}; all views: held-out / predicted {np.nanmin(all_ratio):.2f}-{np.nanmax(all_ratio):.2f}")
    if draws > 1:
        w = sums[True][weak]
        ratios = np.concatenate(single)
        ratios = ratios[np.isfinite(ratios)]
        per_draw = [float(np.nanmax(r)) for r in single if np.isfinite(r).any()]
        pooled_all = np.sqrt(w[:, 0].sum() / w[:, 1].sum())
        print(f"over the draws: the weak views' held-out / predicted pooled {pooled_all:.2f}; one draw's per-view "
              f"ratios: median {np.median(ratios):.2f}, {100 * np.mean(ratios > TARGET_RATIO):.0f} % above "
              f"{TARGET_RATIO}; one draw's worst weak view {min(per_draw):.2f}-{max(per_draw):.2f} "
              f"(median {np.median(per_draw):.2f})")
    # the Cramér–Rao prediction is of noise alone: with lenses the model cannot fit, their misfit adds a bias it does
    # not know, so the ratio is a target only where the model fits (tangential 0); the screen's is one everywhere
    return worst, worse, (worst <= TARGET_RATIO or tangential > 0) and worse <= 1 + NOISE_TOLERANCE


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, nargs="+", default=[20])
    parser.add_argument("--sigma", type=float, nargs="+", default=[0.1])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--tangential", type=float, nargs="+", default=[0.0, TANGENTIAL_SIGMA],
                        help="std of the true p1, p2 (0: the model fits the lenses)")
    parser.add_argument("--draws", type=int, default=1,
                        help="noise draws on each rig, each view's held-out and predicted squares pooled over them")
    args = parser.parse_args()
    missed = []
    for views, sigma, seed, tangential in itertools.product(args.views, args.sigma, args.seeds, args.tangential):
        worst, worse, ok = run(views, sigma, seed, tangential, args.draws)
        if not ok:
            missed.append(f"1x{views} sigma {sigma} p1 p2 {tangential:g} seed {seed}: ratio {worst:.2f}, screen / "
                          f"no screen {worse:.3f}")
    print("targets missed: " + ("; ".join(missed) if missed else "none"))
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
