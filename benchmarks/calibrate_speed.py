"""The whole `lfgraph.calibrate` beside OpenCV 5's `cv2.calibrateMultiview` on the same corners, in one run.

Corner-only ``paper-4x4`` (16 views, full boards only: calibrateMultiview misbehaves with partial ones), SEEDS noise
draws per condition. Each draw runs both solvers on identical corners, alternating which goes first, and times each
call (wall clock, after a warm-up of both). Errors against the rig's truth, per view relative to the reference: fx,
position, rotation, and the transfer error at infinity (`lfgraph.judge.evaluation`); the table gives the worst view
of every draw's RMS over draws, and the ratio OpenCV / lfgraph. lfgraph runs with ``lens="radtan"`` (the model
OpenCV is given: pinhole, k1 k2) and with its default ``lens="auto"`` (which also fits a fisheye model per view).

Exit code 1 when a target of issue 39 is missed: lfgraph (radtan) slower than calibrateMultiview (median time), or
less than 5x more accurate in fx, position, rotation or transfer at infinity.

    python benchmarks/calibrate_speed.py [--seeds N]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

import lfgraph as lf
from lfgraph.cli.tables import format_table
from lfgraph.core.calibration import Calibration
from lfgraph.datasets.checkerboard import make_checkerboard_truth, make_corner_observations
from lfgraph.datasets.rig import make_rig
from lfgraph.datasets.scenes import get_scene
from lfgraph.detect.detections import observations_from_arrays
from lfgraph.judge.evaluation import evaluate_calibration
from lfgraph.judge.peers import calibrate_multiview

SEEDS = 5
CONDITIONS = [(0.1, 40), (0.3, 40), (0.1, 10)]  # corner noise (px), frames
TARGET_TIME_RATIO = 1.0  # lfgraph (radtan) time / calibrateMultiview time, at most
TARGET_GAIN = 5.0  # calibrateMultiview error / lfgraph error, at least (fx, position, rotation, transfer)
KEYS = ("fx_px", "pos_mm", "rot_deg", "transfer_px")


def _errors(intrinsics, ref_T_view, truth: Calibration) -> dict[str, float]:  # noqa: N803
    """The worst non-reference view's error of each kind (fx: every view)."""
    est = Calibration(truth.grid, truth.image_size_px, intrinsics, ref_T_view)
    e = evaluate_calibration(est, truth)
    other = np.arange(truth.num_views) != truth.grid.reference
    return {"fx_px": float(np.max(np.abs(e.intrinsics[:, 0]))),
            "pos_mm": float(np.max(np.linalg.norm(e.position_mm[other], axis=1))),
            "rot_deg": float(np.max(e.rotation_deg[other])),
            "transfer_px": float(np.nanmax(e.transfer_px[other]))}


def _timed(run):
    t0 = time.perf_counter()
    out = run()
    return out, time.perf_counter() - t0


def _draw(obs, truth: Calibration, order: int) -> dict[str, tuple[dict[str, float], float]]:
    """One draw: every solver on ``obs``; the order alternates with ``order``."""
    runs = {
        "lfgraph (radtan)": lambda: lf.calibrate(obs, lf.CalibrateConfig(lens="radtan"))[0],
        "lfgraph (auto)": lambda: lf.calibrate(obs)[0],
        "cv2.calibrateMultiview": lambda: calibrate_multiview(obs),
    }
    names = list(runs)
    names = names if order % 2 == 0 else names[::-1]
    out = {}
    for name in names:
        result, seconds = _timed(runs[name])
        intr, poses = (result.intrinsics, result.ref_T_view) if isinstance(result, Calibration) else result
        out[name] = (_errors(intr, poses, truth), seconds)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=SEEDS)
    args = parser.parse_args()
    scene = get_scene("paper-4x4")
    rng = np.random.default_rng(2024)
    truth = make_rig(scene.rig, rng)
    boards = make_checkerboard_truth(truth, scene.checkerboard, rng)
    warm = observations_from_arrays(boards.board, truth.grid, truth.image_size_px,
                                    *make_corner_observations(boards, 0.1, np.random.default_rng(0)))
    _draw(warm.subset_frames(np.arange(10)), truth, 0)  # imports, caches, first allocations of both
    rows, failures = [], []
    for sigma, n_frames in CONDITIONS:
        draws = []
        for seed in range(args.seeds):
            c, v = make_corner_observations(boards, sigma, np.random.default_rng([seed, int(sigma * 10), n_frames]))
            obs = observations_from_arrays(boards.board, truth.grid, truth.image_size_px, c, v)
            draws.append(_draw(obs.subset_frames(np.arange(n_frames)), truth, seed))
        names = list(draws[0])
        err = {n: {k: float(np.sqrt(np.mean([d[n][0][k] ** 2 for d in draws]))) for k in KEYS} for n in names}
        secs = {n: float(np.median([d[n][1] for d in draws])) for n in names}
        peer = "cv2.calibrateMultiview"
        for n in names:
            gains = "-" if n == peer else " ".join(f"{err[peer][k] / err[n][k]:.1f}" for k in KEYS)
            rows.append([f"{sigma:g} px, {n_frames} fr", n, *(f"{err[n][k]:.3g}" for k in KEYS), f"{secs[n]:.2f}",
                         "-" if n == peer else f"{secs[n] / secs[peer]:.2f}", gains])
        ratio = secs["lfgraph (radtan)"] / secs[peer]
        if ratio > TARGET_TIME_RATIO:
            failures.append(f"{sigma:g} px, {n_frames} fr: lfgraph (radtan) takes {ratio:.2f}x calibrateMultiview's "
                            f"time (target <= {TARGET_TIME_RATIO:g})")
        for k in KEYS:
            gain = err[peer][k] / err["lfgraph (radtan)"][k]
            if gain < TARGET_GAIN:
                failures.append(f"{sigma:g} px, {n_frames} fr: {k} only {gain:.1f}x lower than calibrateMultiview's "
                                f"(target >= {TARGET_GAIN:g})")
    print(f"lf.calibrate vs cv2.calibrateMultiview on the same corners, corner-only paper-4x4, {args.seeds} draws per "
          f"row (worst view per draw, RMS over draws; time: median wall clock per call)")
    print(format_table(["data", "solver", *KEYS, "seconds", "time / OpenCV", "OpenCV error / this (fx pos rot tr)"],
                       rows))
    for f in failures:
        print("TARGET MISSED:", f)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
