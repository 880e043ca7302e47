"""Robust kernels x stage schedules x wrong matches (issue 40): a 3x3 of paper-5x5's cameras (2 frames, knocked by up
to 1 deg / 3 mm about random axes) refined from its unknocked calibration, its tracks given a share of wrong matches
by `lfgraph.refinement.tracks.OutlierTracker` (non-reference observations moved 2-8 px, or 0.5-2 px, in random
directions). Per cell: the transfer error at infinity against the knocked truth (worst view and RMS over views, px),
the verdict counts, the measurement sigma and why nothing changed when nothing did.

    python benchmarks/robust_schedules.py [--seeds 1,2] [--outliers 0:2-8,0.05:2-8] [--kernels none,huber]
        [--grid 4x4] [--draws 3]

``--draws N`` refines each seed's capture with N independent draws of the wrong matches (draw d seeds them with
seed + DRAW_STRIDE d; draw 0 is the default run's) and ends with, per kernel and wrong-match setting, the geometric
mean of the ``points,poses`` over default ratio (worst view), the spread of its logarithm and how many cells pass 1.5x:
one scene's ratio moves with the draw as much as between scenes.

The targets (issue 40's "done"): with 5 % wrong matches of 2-8 px and ``points,poses`` (no clean stage), Huber,
Cauchy and Tukey repair the rig to within 1.5x of their own default-schedule transfer (worst view), no noise model is
refused as another camera, and the Gaussian is worse than its default-schedule result or refused with the wrong
matches named.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from lfgraph.apps.synth import scene_capture
from lfgraph.cli.tables import format_table
from lfgraph.engine.bulk_noise import vectorised_estimator
from lfgraph.judge.alignment import transfer_error_at_infinity
from lfgraph.refinement import RefineConfig, refine
from lfgraph.refinement.tracks import OutlierTracker

KNOCK_DEG, KNOCK_MM, FRAMES = 1.0, 3.0, 2  # the rig (a 3x3: --grid): seed 1 is its 4.611 px input
SCHEDULES = ("default", "points,poses")
KERNELS = ("none", "huber", "cauchy", "tukey", "gm-robust", "custom", "vectorised")
TARGET_RATIO = 1.5  # a kernel's points,poses transfer (worst view) within this x its default-schedule transfer
TARGET_KERNELS = ("huber", "cauchy", "tukey")
TARGET_OUTLIERS = "0.05:2-8"
DRAW_STRIDE = 100  # draw d of the wrong matches is seeded with seed + DRAW_STRIDE d (draw 0: the seed itself)
CAUCHY_K = 2.385  # sigmas: the Cauchy of the user's own estimators below


def noise_model(name: str):
    """A kernel name, or one of the issue's user-made models: GTSAM's Robust(GemanMcClure) around an isotropic
    0.05 px model, a Cauchy as ``mEstimator.Custom`` callbacks, the same Cauchy as `vectorised_estimator`."""
    import gtsam

    k2 = CAUCHY_K**2
    if name == "gm-robust":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.GemanMcClure.Create(3.787),
                                              gtsam.noiseModel.Isotropic.Sigma(2, 0.05))
    if name == "custom":
        return gtsam.noiseModel.mEstimator.Custom.Create(lambda d: k2 / (k2 + d * d),
                                                          lambda d: 0.5 * k2 * np.log1p(d * d / k2))
    if name == "vectorised":
        return vectorised_estimator(lambda d: k2 / (k2 + d * d), lambda d: 0.5 * k2 * np.log1p(d * d / k2))
    return name


def cause(report) -> str:
    """Why nothing changed, in a word or two (empty when something did)."""
    if report.accepted:
        return ""
    text = " ".join(report.warnings)
    for key, word in (("wrong matches", "wrong matches"), ("other intrinsics", "ANOTHER CAMERA"),
                      ("for this camera", "ANOTHER CAMERA?"), ("held-out", "held-out"),
                      ("no change was significant", "not significant"), ("disagree", "frames disagree")):
        if key in text:
            return word
    return "refused"


def run_cell(cap, schedule: str, kernel: str, outliers: str, seed: int) -> dict:
    """One refinement: ``seed`` seeds the wrong matches."""
    tracker = OutlierTracker.parse(outliers, seed=seed)
    t0 = time.perf_counter()
    refined, report = refine(cap.original, cap.frames, RefineConfig(stages=schedule, robust=noise_model(kernel),
                                                                    tracker=tracker))
    te = transfer_error_at_infinity(refined, cap.truth)
    counts = report.verdict_counts()
    return {"worst": float(np.max(te)), "rms": float(np.sqrt(np.mean(te**2))), "sigma": report.sigma_px,
            "verdicts": f"{counts['DRIFTED']}D {counts['OK']}O {counts['UNCERTAIN']}U", "cause": cause(report),
            "seconds": time.perf_counter() - t0}


def targets(results: dict, seeds: list[int], kernels: list[str], draws: int = 1) -> list[str]:
    """The issue's targets missed (see the module docstring), for every draw of the wrong matches."""
    missed = []
    for seed in seeds:
        for kernel, draw in ((k, d) for k in kernels for d in range(draws)):
            pp = results.get((TARGET_OUTLIERS, "points,poses", kernel, seed, draw))
            de = results.get((TARGET_OUTLIERS, "default", kernel, seed, draw))
            if pp is None or de is None:
                continue
            label = f"{seed} draw {draw}" if draw else seed
            if pp["cause"].startswith("ANOTHER"):
                missed.append(f"{kernel}, seed {label}: refused as another camera")
            if kernel in TARGET_KERNELS and not pp["worst"] <= TARGET_RATIO * de["worst"]:
                missed.append(f"{kernel}, seed {label}: points,poses {pp['worst']:.3f} px > {TARGET_RATIO:g}x the "
                              f"default schedule's {de['worst']:.3f} px")
            if kernel == "none" and not (pp["worst"] > de["worst"] or pp["cause"] == "wrong matches"):
                missed.append(f"gaussian, seed {label}: neither worse than the default schedule nor refused naming the "
                              f"wrong matches ({pp['cause'] or 'accepted'})")
    return missed


def ratio_summary(results: dict, kernels: list[str]) -> list[list]:
    """Per wrong-match setting and kernel: cells with both schedules repairing the rig, the geometric mean of the
    points,poses over default ratio (worst view), the standard deviation of its natural logarithm, the largest ratio
    and the cells within `TARGET_RATIO`."""
    rows = []
    for outliers in dict.fromkeys(k[0] for k in results):
        for kernel in kernels:
            pairs = [(r["worst"], results[(o, "default", k, s, d)]["worst"]) for (o, sc, k, s, d), r in results.items()
                     if o == outliers and sc == "points,poses" and k == kernel and not r["cause"]
                     and (o, "default", k, s, d) in results and not results[(o, "default", k, s, d)]["cause"]]
            if len(pairs) < 2:
                continue
            logs = np.log([p / d for p, d in pairs])
            rows.append([outliers, kernel, len(pairs), f"{np.exp(logs.mean()):.2f}", f"{logs.std(ddof=1):.2f}",
                         f"{np.exp(logs.max()):.2f}", int(np.sum(logs <= np.log(TARGET_RATIO)))])
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1,2", help="rig, knock, scene and wrong-match seeds (default 1,2)")
    parser.add_argument("--outliers", default="0:2-8,0.05:2-8,0.05:0.5-2,0.1:2-8",
                        help="shares of wrong matches and their size, SHARE:MIN-MAX px, comma-separated")
    parser.add_argument("--kernels", default=",".join(KERNELS), help=f"noise models (default {','.join(KERNELS)})")
    parser.add_argument("--schedules", default=";".join(SCHEDULES), help="schedules, ';'-separated")
    parser.add_argument("--grid", default="3x3", help="ROWSxCOLS of paper-5x5's cameras (default 3x3, the issue's)")
    parser.add_argument("--draws", type=int, default=1, help="independent draws of the wrong matches per seed "
                        "(default 1; the summary of ratios needs several seeds or draws)")
    args = parser.parse_args()
    grid = tuple(int(n) for n in args.grid.lower().split("x"))
    seeds = [int(s) for s in args.seeds.split(",")]
    shares = [s.strip() for s in args.outliers.split(",")]
    kernels = [k.strip() for k in args.kernels.split(",")]
    schedules = [s.strip() for s in args.schedules.split(";")]
    results, rows = {}, []
    for seed in seeds:
        cap = scene_capture("paper-5x5", frames=FRAMES, shake_rot_deg=KNOCK_DEG, shake_trans_mm=KNOCK_MM, seed=seed,
                            rows=grid[0], cols=grid[1])
        te = transfer_error_at_infinity(cap.original, cap.truth)
        print(f"seed {seed}: input transfer at infinity {np.max(te):.3f} px worst view, {np.sqrt(np.mean(te**2)):.3f} "
              f"px RMS", flush=True)
        for outliers, draw in ((o, d) for o in shares for d in range(args.draws)):
            for schedule in schedules:
                for kernel in kernels:
                    r = results[(outliers, schedule, kernel, seed, draw)] = run_cell(cap, schedule, kernel, outliers,
                                                                                     seed + DRAW_STRIDE * draw)
                    rows.append([outliers, schedule, kernel, seed if not draw else f"{seed}.{draw}",
                                 f"{r['worst']:.3f}", f"{r['rms']:.3f}", r["verdicts"], f"{r['sigma']:.3f}",
                                 r["cause"], f"{r['seconds']:.1f}"])
                    print(" | ".join(map(str, rows[-1])), flush=True)
    print(f"\n{grid[0]}x{grid[1]} of paper-5x5's cameras, {FRAMES} frames, knocked {KNOCK_DEG:g} deg / "
          f"{KNOCK_MM:g} mm; transfer error at infinity against the truth (px); verdicts D(RIFTED) O(K) "
          f"U(NCERTAIN); sigma: the measurement sigma (px per coordinate); refused: why nothing changed")
    print(format_table(["outliers", "schedule", "noise model", "seed", "worst_px", "rms_px", "verdicts", "sigma_px",
                        "refused", "seconds"], rows))
    summary = ratio_summary(results, kernels)
    if summary:
        print(f"\npoints,poses over default, worst view (cells both repaired; seed.draw: draw d of the wrong matches "
              f"seeded with seed + {DRAW_STRIDE}d)")
        print(format_table(["outliers", "noise model", "cells", "geo_mean", "sd_log", "max", f"<={TARGET_RATIO:g}x"],
                           summary))
    missed = targets(results, seeds, kernels, args.draws)
    print("targets missed: " + ("; ".join(missed) if missed else "none"))
    return 1 if missed else 0


if __name__ == "__main__":
    t0 = time.perf_counter()
    code = main()
    print(f"({time.perf_counter() - t0:.0f} s)")
    sys.exit(code)
