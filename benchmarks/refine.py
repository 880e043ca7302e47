"""Auto-refinement on shaken paper-5x5 scenes: accuracy against the shaken truth, the paper's schedule vs lfgraph's
default, and the time per frame (matching + filters, staged adjustment; wall and process CPU — the wall time on an
idle 2-core machine is the one checked against the target: OpenCV's KLT runs on both cores, so its CPU seconds are
about twice its wall seconds; the load average is printed beside) with peak memory; then the thin and hostile
grid of issue 14 (1-2 frames, 2x2 and 3x3 rigs, wide and narrow fields of view, near and far scenes, repetitive
texture, no shake) and the real OpenCV stereo set, where the rule is: after <= before against the truth.

Scenes are rendered once into ``out/bench-refine`` (re-used on later runs). For every shake level (each view turned
by up to R degrees about a random axis — pan, tilt and roll, as a real knock; the paper turned views about their
optical axes only — and moved up to T mm per axis) the refinement starts from the original (unshaken) calibration.
Figures: RMS over views of the rotation error (deg), the transfer error at infinity (px: a reference pixel at
infinite depth projected with estimated vs true cameras), the final reprojection RMS over the noise floor (the
same kept tracks reprojected with the *true* cameras), and per view the worst applied view's transfer error over
its reported sigma; the sigmas across the grid (issue 40: paper-5x5, 3 frames, 1 deg / 3 mm, three seeds) the
same per view.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lfgraph.cli.tables import format_table
from lfgraph.core.calibration import Calibration
from lfgraph.datasets.rig import ShakeConfig, make_rig, shake_rig
from lfgraph.datasets.scene import SceneConfig, write_scene_dataset
from lfgraph.datasets.scenes import get_scene
from lfgraph.engine.bulk_noise import vectorised_estimator
from lfgraph.engine.triangulate import reprojection_errors, triangulate_dlt
from lfgraph.io.capture import open_capture
from lfgraph.judge.alignment import transfer_error_at_infinity
from lfgraph.judge.evaluation import evaluate_calibration
from lfgraph.refinement import RefineConfig, refine

SHAKES = [(0.0, 0.0), (0.25, 1.0), (0.5, 2.0), (1.0, 5.0)]
AXIS = "any"  # knocks about random axes (pan, tilt and roll; issue 24); "optical" is the paper's roll-only shake
FRAMES = 4
TARGET_ROT_DEG = 0.01
TARGET_TRANSFER_PX = 0.1
TARGET_FLOOR_RATIO = 1.5
TARGET_NO_SHAKE_ROT_DEG = 0.003
TARGET_NO_SHAKE_POS_MM = 0.1
TARGET_FRAME_S = 0.5  # issue 16: matching + filters + staged adjustment per 5x5 frame of 512x512 views
TARGET_MEMORY_MB = 1000.0
MEMORY_FRAMES = 10


def dataset(cache: Path, rot: float, trans: float, frames: int, kind: str = "dead-leaves") -> Path:
    out = cache / f"paper-5x5{'_' + kind if kind != 'dead-leaves' else ''}_{AXIS}_rot{rot:g}_trans{trans:g}_f{frames}"
    if (out / "truth.json").exists() and len(list(out.glob("*/r04_c04.png"))) == frames:
        return out
    scene = get_scene("paper-5x5")
    original = make_rig(scene.rig, np.random.default_rng(0))
    truth = shake_rig(original, ShakeConfig(rot_deg=rot, trans_mm=trans, axis=AXIS), np.random.default_rng([0, 1])) \
        if rot or trans else original
    near, far = scene.scene_depth_m
    cfg = SceneConfig(depth_m=(near, far), background_depth_m=far * 1.4, kind=kind)
    print(f"rendering {out.name} ...", flush=True)
    write_scene_dataset(out, truth, cfg, frames=frames, seed=11, progress=False, original=original)
    if not (out / "original.json").exists():
        original.save(out / "original.json")
    return out


def evaluate(refined: Calibration, truth: Calibration, report) -> dict[str, float]:
    e = evaluate_calibration(refined, truth)
    te = transfer_error_at_infinity(refined, truth)
    return {"rot": float(np.sqrt(np.mean(e.rotation_deg**2))), "rot_max": float(np.max(e.rotation_deg)),
            "pos": float(np.sqrt(np.mean(np.sum(e.position_mm**2, axis=1)))),
            "pos_max": float(np.max(np.linalg.norm(e.position_mm, axis=1))),
            "transfer": float(np.sqrt(np.mean(te**2)))}


def worst_view_ratio(refined: Calibration, truth: Calibration, report) -> tuple[float, str]:
    """The worst applied view's transfer error at infinity over its reported 1-sigma (`predicted_transfer_px`), and
    that view's name ("-" when no view was applied): per view, not an RMS over views, where a mode growing with the
    offset from the reference shows."""
    te = transfer_error_at_infinity(refined, truth)
    ratios = {v.name: te[v.view] / v.predicted_transfer_px for v in report.verdicts
              if v.applied and v.predicted_transfer_px > 0}
    if not ratios:
        return float("nan"), "-"
    name = max(ratios, key=ratios.get)
    return float(ratios[name]), name


SIGMA_SEEDS = (0, 1, 2)  # issue 40: paper-5x5, 3 frames, knocked 1 deg / 3 mm about random axes
SIGMA_KNOCK = (1.0, 3.0)
SIGMA_FRAMES = 3
TARGET_VIEW_RATIO = 2.0  # every applied view's transfer error at infinity within 2x its reported sigma


def sigma_grid(failures: list[str]) -> None:
    """Issue 40's sigmas across the grid: per seed, the worst applied view's transfer error over its sigma."""
    from lfgraph.apps.synth import scene_capture

    rows = []
    for seed in SIGMA_SEEDS:
        cap = scene_capture("paper-5x5", SIGMA_FRAMES, shake_rot_deg=SIGMA_KNOCK[0], shake_trans_mm=SIGMA_KNOCK[1],
                            seed=seed)
        refined, report = refine(cap.original, cap.frames)
        ratio, view = worst_view_ratio(refined, cap.truth, report)
        te = transfer_error_at_infinity(refined, cap.truth)
        applied = [v for v in report.verdicts if v.applied]
        rows.append([str(seed), f"{len(applied)}", f"{np.max(te):.3f}",
                     f"{np.median([v.predicted_transfer_px for v in applied]):.3f}" if applied else "-",
                     f"{ratio:.2f} ({view})", verdict_summary(report)])
        if ratio > TARGET_VIEW_RATIO:
            failures.append(f"sigmas across the grid, seed {seed}: {view}'s transfer error is {ratio:.2f}x its sigma")
    print(f"sigmas across the grid (paper-5x5, {SIGMA_FRAMES} frames, {SIGMA_KNOCK[0]:g} deg / {SIGMA_KNOCK[1]:g} mm; "
          f"transfer at infinity against the truth; target: every applied view within {TARGET_VIEW_RATIO:g}x its "
          f"reported sigma):")
    print(format_table(["seed", "applied views", "worst view px", "median sigma px", "worst view error/sigma",
                        "verdicts"], rows))


def noise_floor(truth: Calibration, refined: Calibration, frames: list[np.ndarray], settings: RefineConfig) -> float:
    """Final RMS / RMS of the same tracks under the true cameras (tracks re-made here, as refine makes them)."""
    from lfgraph.refinement.matching import track_chain
    from lfgraph.refinement.tracks import collect_tracks

    ratios_num, ratios_den = [], []
    for images in frames:
        kept, _ = collect_tracks(refined, track_chain(images, truth.grid, settings.match),
                                 settings.triangulation_filter)
        for calib, acc in ((refined, ratios_num), (truth, ratios_den)):
            pts = triangulate_dlt(calib, kept.points_px, kept.valid)
            acc.append(reprojection_errors(calib, pts, kept.points_px, kept.valid))
    num = np.concatenate([np.ravel(x) for x in ratios_num])
    den = np.concatenate([np.ravel(x) for x in ratios_den])
    return float(np.sqrt(np.nanmean(num**2)) / np.sqrt(np.nanmean(den**2)))


@dataclass(frozen=True)
class ThinCase:
    """One case of the thin-data grid: paper-5x5's rig shrunk and changed, rendered in memory."""

    name: str
    grid: tuple[int, int] = (3, 3)
    frames: int = 1
    rot_deg: float = 1.0
    trans_mm: float = 5.0
    image_px: int = 320
    focal_px: float = 700.0
    depth_m: tuple[float, float] = (2.0, 6.0)
    kind: str = "dead-leaves"
    seed: int = 0


THIN_CASES = [
    ThinCase("3x3, 1 frame, 1 deg / 5 mm (the issue)"),
    ThinCase("3x3, 1 frame, 0.25 deg / 1 mm", rot_deg=0.25, trans_mm=1.0),
    ThinCase("3x3, 1 frame, 1 deg / 5 mm, seed 3", seed=3),
    ThinCase("3x3, 2 frames, 1 deg / 5 mm", frames=2),
    ThinCase("2x2, 1 frame, 1 deg / 5 mm", grid=(2, 2)),
    ThinCase("2x2, 2 frames, 0.25 deg / 1 mm", grid=(2, 2), frames=2, rot_deg=0.25, trans_mm=1.0),
    ThinCase("3x3 wide (f 200 px, 77 deg)", focal_px=200.0),
    ThinCase("3x3 narrow (f 1400 px, 13 deg)", focal_px=1400.0),
    ThinCase("3x3 near scene (0.6-1.5 m)", depth_m=(0.6, 1.5)),
    ThinCase("3x3 far scene (15-40 m)", depth_m=(15.0, 40.0)),
    ThinCase("3x3 keyboard (repetitive)", kind="keyboard"),
    ThinCase("3x3, 1 frame, no shake", rot_deg=0.0, trans_mm=0.0),
    ThinCase("2x2, 1 frame, no shake", grid=(2, 2), rot_deg=0.0, trans_mm=0.0),
]
THIN_NOISE_PX = 0.05  # "after <= before" within this (transfer at infinity)
THIN_NOISE_DEG = 0.005  # ... and this (rotation)
STEREO = Path(__file__).resolve().parents[2] / "shared" / "data" / "opencv_stereo_left_right"
STEREO_BOARD, STEREO_SQUARE_MM = "9x6", 25.0
STEREO_BASELINE_TOL_MM = 0.1
STEREO_ROW_TOL_PX = 0.02


def render_thin(case: ThinCase) -> tuple[Calibration, Calibration, list[np.ndarray]]:
    """(original, truth, frames) of a thin case, rendered in memory (as `lfgraph.apps.study.run_shake_trial`)."""
    import dataclasses

    from lfgraph.datasets.scene import make_scene, render_scene_view

    named = get_scene("paper-5x5")
    rig_cfg = dataclasses.replace(named.rig, rows=case.grid[0], cols=case.grid[1],
                                  image_size_px=(case.image_px, case.image_px), focal_px=case.focal_px)
    original = make_rig(rig_cfg, np.random.default_rng([case.seed, 0]))
    truth = shake_rig(original, ShakeConfig(rot_deg=case.rot_deg, trans_mm=case.trans_mm, axis=AXIS),
                      np.random.default_rng([case.seed, 1])) if case.rot_deg or case.trans_mm else original
    near, far = case.depth_m
    cfg = SceneConfig(depth_m=(near, far), background_depth_m=far * 1.4, kind=case.kind)
    frames = []
    for f in range(case.frames):
        scene = make_scene(cfg, np.random.default_rng([case.seed, 2, f]))
        frames.append(np.stack([render_scene_view(scene, truth.intrinsics[v], truth.image_size_px,
                                                  truth.view_T_ref(v), cfg, np.random.default_rng([case.seed, 3, f, v]))
                                for v in range(truth.num_views)]))
    return original, truth, frames


def verdict_summary(report) -> str:
    counts = report.verdict_counts()
    return " ".join(f"{counts[k]} {k}" for k in ("DRIFTED", "OK", "UNCERTAIN") if k in counts)


def thin_grid(failures: list[str]) -> None:
    rows = []
    for case in THIN_CASES:
        t0 = time.perf_counter()
        original, truth, frames = render_thin(case)
        t_render = time.perf_counter() - t0
        try:
            refined, report = refine(original, frames)
            verdicts, seconds = verdict_summary(report), report.seconds
        except ValueError as exc:  # no usable tracks: the input is what the user keeps
            refined, verdicts, seconds = original, f"error: {exc}"[:40], float("nan")
        b, a = evaluate(original, truth, None), evaluate(refined, truth, None)
        worse = a["transfer"] > b["transfer"] + THIN_NOISE_PX or a["rot"] > b["rot"] + THIN_NOISE_DEG
        rows.append([case.name, f"{b['transfer']:.3f}", f"{a['transfer']:.3f}", f"{b['rot']:.4f}", f"{a['rot']:.4f}",
                     "WORSE" if worse else "ok", verdicts, f"{seconds:.1f}", f"{t_render:.0f}"])
        if worse:
            failures.append(f"thin case {case.name}: transfer {b['transfer']:.3f} -> {a['transfer']:.3f} px, "
                            f"rotation {b['rot']:.4f} -> {a['rot']:.4f} deg")
        print(" | ".join(map(str, rows[-1])), flush=True)
    print("thin and hostile data (errors against the shaken truth, RMS over views; after <= before is the rule):")
    print(format_table(["case", "transfer_before_px", "transfer_after_px", "rot_before_deg", "rot_after_deg",
                        "after<=before", "verdicts", "refine_s", "render_s"], rows))


def corner_row_error_px(calib: Calibration, obs) -> float:
    from lfgraph.rectification.rectify import compute_rectification, rectify_points

    rect = compute_rectification(calib)
    ok = obs.valid[0] & obs.valid[1]
    q = [rectify_points(calib, rect, v, obs.corners_px[v][ok]) for v in range(2)]
    return float(np.sqrt(np.mean((q[0][:, 1] - q[1][:, 1]) ** 2)))


def real_stereo(cache: Path, failures: list[str]) -> None:
    """OpenCV's stereo sample: calibrate from the boards, then refine and check on the same images."""
    import contextlib
    import io
    import json

    from lfgraph.cli import main as cli
    from lfgraph.detect.board import BoardSpec
    from lfgraph.detect.detections import detect_capture

    if not STEREO.is_dir():
        failures.append(f"real stereo set not found at {STEREO}")
        return
    calib_json, refined_json = cache / "stereo-calib.json", cache / "stereo-refined.json"
    args = ["--quiet"]
    with contextlib.redirect_stdout(io.StringIO()):
        cli(["calibrate", str(STEREO), "--grid", "1x2", "--board", STEREO_BOARD, "--square-mm",
             str(STEREO_SQUARE_MM), "-o", str(calib_json), *args])
        cli(["refine", str(calib_json), str(STEREO), "-o", str(refined_json), *args])
    before, after = Calibration.load(calib_json), Calibration.load(refined_json)
    obs, _ = detect_capture(open_capture(STEREO, before.grid), BoardSpec.parse(STEREO_BOARD, STEREO_SQUARE_MM),
                            jobs=1, progress=False, cache=False)
    b_mm = [1e3 * float(np.linalg.norm(c.ref_T_view[1][:3, 3])) for c in (before, after)]
    rows = [corner_row_error_px(c, obs) for c in (before, after)]
    verdicts = [v["verdict"] for v in after.metrics["refinement"]["verdicts"]]
    print(f"real stereo (OpenCV left/right, 13 frames): baseline {b_mm[0]:.2f} -> {b_mm[1]:.2f} mm, corner row "
          f"error {rows[0]:.3f} -> {rows[1]:.3f} px; refine verdicts {verdicts}")
    if abs(b_mm[1] - b_mm[0]) > STEREO_BASELINE_TOL_MM or rows[1] > rows[0] + STEREO_ROW_TOL_PX:
        failures.append("real stereo: the refinement changed the baseline or worsened the rows")
    for n in (3, 13):
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            code = cli(["check", str(calib_json), str(STEREO), "--max-frames", str(n), "--json"])
        data = json.loads(buf.getvalue())
        views = [(v["view"], v["verdict"], round(v["change_sigma"], 1)) for v in data["views"]]
        print(f"check on {n} frames: {data['verdict']} (exit {code}), reprojection RMS {data['rms_px']:.2f} px, "
              f"frames dropped {data['frames_dropped']}, views {views}")
        # a good calibration is never called DRIFTED; with 13 frames the data must also confirm it (3 frames leave
        # ~0.27 px undetermined once the board's corners, a repeated texture, are dropped: UNCERTAIN is the answer)
        if data["verdict"] == "DRIFTED" or (n == 13 and data["verdict"] != "OK"):
            failures.append(f"real stereo: check on {n} frames says {data['verdict']}")


KERNEL_SHAKE = (0.5, 2.0)  # the kernel table's dataset (deg, mm)
TARGET_KERNEL_RATIO = 1.5  # issue 26: every noise model within 1.5x the Gaussian's time
KERNEL_ROUNDS = 5  # every case runs once a round; its time is the median over the rounds, its ratio the median of
# its round-by-round ratios to the Gaussian's (paired: a machine that speeds up or slows down hits both alike)


def _cauchy_callbacks():
    """Cauchy (k = 2.385 sigmas) as Python callbacks: a user's own `mEstimator.Custom`."""
    import gtsam

    k2 = 2.385**2
    return gtsam.noiseModel.mEstimator.Custom.Create(lambda d: k2 / (k2 + d * d),
                                                      lambda d: 0.5 * k2 * np.log1p(d * d / k2))


def _cauchy_arrays():
    """The same Cauchy as functions of arrays (`lfgraph.vectorised_estimator`): a kernel of your own at full speed."""
    k2 = 2.385**2
    return vectorised_estimator(lambda d: k2 / (k2 + d * d), lambda d: 0.5 * k2 * np.log1p(d * d / k2))


def _pin_reference_neighbour(ctx) -> None:
    """A user hook: a loose prior (1 deg, 10 mm) on view 1's pose where the stage holds it."""
    import gtsam

    from lfgraph.factors.keys import view_pose_key
    from lfgraph.factors.noise import pose_noise

    key = view_pose_key(1)
    if ctx.initial.exists(key):
        ctx.graph.add(gtsam.PriorFactorPose3(key, ctx.initial.atPose3(key), pose_noise(np.radians(1.0), 0.01)))


def kernel_table(cache: Path, frames: int, failures: list[str]) -> None:
    """Time and accuracy of `refine` with every kind of noise model a study swaps in, against the Gaussian's."""
    import gtsam

    root = dataset(cache, *KERNEL_SHAKE, frames)
    truth = Calibration.load(root / "truth.json")
    original = Calibration.load(root / "original.json")
    capture = open_capture(root, truth.grid)
    images = [capture.load_frame(f) for f in range(len(capture))]
    cases = [("gaussian (none)", RefineConfig()),
             ("huber (1.345 sigma)", RefineConfig(robust="huber")),
             ("cauchy (2.385 sigma)", RefineConfig(robust="cauchy")),
             ("cauchy:0.2 (px)", RefineConfig(robust="cauchy:0.2")),
             ("tukey (4.685 sigma)", RefineConfig(robust="tukey")),
             ("tukey:1 (px)", RefineConfig(robust="tukey:1")),
             ("gm (3.787 sigma)", RefineConfig(robust="gm")),
             ("gm:1sigma", RefineConfig(robust="gm:1sigma")),
             ("Custom (Cauchy callbacks)", RefineConfig(robust=_cauchy_callbacks())),
             ("vectorised_estimator (Cauchy, numpy)", RefineConfig(robust=_cauchy_arrays())),
             ("Diagonal Gaussian model", RefineConfig(robust=gtsam.noiseModel.Diagonal.Sigmas(np.array([0.05, 0.08])))),
             ("hook (a pose prior)", RefineConfig(graph_hooks=(_pin_reference_neighbour,)))]
    rows = []
    seconds: dict[str, list[float]] = {name: [] for name, _ in cases}
    results = {}
    for _ in range(KERNEL_ROUNDS):  # round by round, every case once a round: drifts of the machine hit all alike
        for name, config in cases:
            t0 = time.perf_counter()
            results[name] = refine(original, images, config)
            seconds[name].append(time.perf_counter() - t0)
    base = np.array(seconds[cases[0][0]])
    for name, _ in cases:
        refined, report = results[name]
        t = np.array(seconds[name])
        ratios = t / base
        ratio = float(np.median(ratios))
        r = evaluate(refined, truth, report)
        rows.append([name, f"{np.median(t):.2f}", f"{ratio:.2f}", f"{ratios.min():.2f}-{ratios.max():.2f}",
                     f"{r['transfer']:.4f}", f"{r['rot']:.4f}", f"{report.seconds_adjustment:.2f}"])
        if ratio > TARGET_KERNEL_RATIO:
            failures.append(f"noise model {name}: {ratio:.2f}x the Gaussian's time "
                            f"(target {TARGET_KERNEL_RATIO:g}x)")
    print(f"noise models (paper-5x5, {KERNEL_SHAKE[0]:g} deg / {KERNEL_SHAKE[1]:g} mm, {frames} frames; the "
          f"measurement sigma is estimated, ~0.05 px; medians of {KERNEL_ROUNDS} rounds, the ratio paired round by "
          f"round; load average {os.getloadavg()[0]:.1f}):")
    print(format_table(["noise model", "seconds", "x gaussian", "x range", "transfer_px", "rot_err_deg",
                        "adjustment_s"], rows))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", type=Path, default=Path("out/bench-refine"))
    parser.add_argument("--frames", type=int, default=FRAMES)
    parser.add_argument("--thin-only", action="store_true", help="only the thin grid and the real stereo set")
    parser.add_argument("--kernels-only", action="store_true", help="only the noise-model table")
    parser.add_argument("--sigmas-only", action="store_true", help="only the sigmas across the grid (issue 40)")
    args = parser.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    rows, failures, timing = [], [], []
    if args.sigmas_only:
        sigma_grid(failures)
        print("targets missed: " + ("; ".join(failures) if failures else "none"))
        return 1 if failures else 0
    if args.kernels_only:
        kernel_table(args.cache, args.frames, failures)
        print("targets missed: " + ("; ".join(failures) if failures else "none"))
        return 1 if failures else 0
    thin_grid(failures)
    real_stereo(args.cache, failures)
    if args.thin_only:
        print("targets missed: " + ("; ".join(failures) if failures else "none"))
        return 1 if failures else 0
    for rot, trans in SHAKES:
        root = dataset(args.cache, rot, trans, args.frames)
        truth = Calibration.load(root / "truth.json")
        original = Calibration.load(root / "original.json")
        capture = open_capture(root, truth.grid)
        frames = [capture.load_frame(f) for f in range(len(capture))]
        before = evaluate(original, truth, None)
        rows.append([f"{rot:g} deg / {trans:g} mm", "input (original)", f"{before['rot']:.4f}",
                     f"{before['transfer']:.3f}", f"{before['pos']:.3f}", "-", "-", "-"])
        for schedule in ("paper", "default"):
            settings = RefineConfig(stages=schedule)
            cpu0, wall0 = time.process_time(), time.perf_counter()
            refined, report = refine(original, frames, settings)
            cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
            r = evaluate(refined, truth, report)
            floor = noise_floor(truth, refined, frames, settings)
            ratio, view = worst_view_ratio(refined, truth, report)
            rows.append(["", f"{schedule} ({','.join(settings.stages)})", f"{r['rot']:.4f}", f"{r['transfer']:.3f}",
                         f"{r['pos']:.3f}", f"{report.rms_after_px:.3f}", f"{floor:.2f}", f"{ratio:.2f} ({view})"])
            if schedule == "default":
                n = len(frames)
                cpu_match = getattr(report, "cpu_seconds_matching", float("nan")) / n
                cpu_ba = getattr(report, "cpu_seconds_adjustment", float("nan")) / n
                timing.append([f"{rot:g} deg / {trans:g} mm", f"{report.seconds_matching / n:.3f}",
                               f"{cpu_match:.3f}", f"{report.seconds_adjustment / n:.3f}", f"{cpu_ba:.3f}",
                               f"{wall / n:.3f}", f"{cpu / n:.3f}", f"{TARGET_FRAME_S:g}",
                               report.stages[-1].landmarks])
                if rot == 0 and trans == 0:
                    if r["rot_max"] >= TARGET_NO_SHAKE_ROT_DEG:
                        failures.append(f"no shake: rotation changed by up to {r['rot_max']:.4f} deg")
                    if r["pos_max"] >= TARGET_NO_SHAKE_POS_MM:
                        failures.append(f"no shake: position changed by up to {r['pos_max']:.3f} mm")
                if r["rot"] > TARGET_ROT_DEG:
                    failures.append(f"{rot:g} deg / {trans:g} mm: rotation error {r['rot']:.4f} deg")
                if r["transfer"] > TARGET_TRANSFER_PX:
                    failures.append(f"{rot:g} deg / {trans:g} mm: transfer error {r['transfer']:.3f} px")
                if floor > TARGET_FLOOR_RATIO:
                    failures.append(f"{rot:g} deg / {trans:g} mm: final RMS {floor:.2f} x the noise floor")
                if wall / n > TARGET_FRAME_S:
                    failures.append(f"{rot:g} deg / {trans:g} mm: refinement {wall / n:.2f} s per frame "
                                    f"(target {TARGET_FRAME_S:g} s on an idle machine; load {os.getloadavg()[0]:.1f})")
    print(f"paper-5x5, {args.frames} frames per shake level, refined from the original calibration "
          "(errors against the shaken truth, RMS over views)")
    print(format_table(["shake", "schedule", "rot_err_deg", "transfer_px", "pos_err_mm", "final_rms_px",
                        "rms / floor", "worst view error/sigma"], rows))
    sigma_grid(failures)
    print(f"time per frame, default schedule (wall and process CPU; the whole refine call, target <= "
          f"{TARGET_FRAME_S:g} s wall per frame on an idle machine; load average now "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores):")
    print(format_table(["shake", "matching+filters_s", "matching_cpu_s", "staged_adjustment_s", "adjustment_cpu_s",
                        "total_s", "total_cpu_s", "target_s", "landmarks"], timing))
    kernel_table(args.cache, args.frames, failures)
    # the hard case: repetitive texture; the refinement must improve or keep the input, and warn
    kb = dataset(args.cache, 0.5, 2.0, 2, kind="keyboard")
    truth = Calibration.load(kb / "truth.json")
    original = Calibration.load(kb / "original.json")
    capture = open_capture(kb, truth.grid)
    refined, report = refine(original, [capture.load_frame(f) for f in range(len(capture))])
    before, after = evaluate(original, truth, None), evaluate(refined, truth, report)
    print(f"keyboard scene (0.5 deg / 2 mm, 2 frames): transfer {before['transfer']:.3f} -> "
          f"{after['transfer']:.3f} px, "
          f"rotation error {before['rot']:.4f} -> {after['rot']:.4f} deg; accepted {report.accepted}; warnings: "
          + ("; ".join(report.warnings) or "none"))
    if after["transfer"] > before["transfer"] + 1e-9:
        failures.append("keyboard scene: the refinement made the calibration worse")
    if report.accepted and after["transfer"] > TARGET_TRANSFER_PX and not report.warnings:
        failures.append("keyboard scene: a poor result without a warning")
    # memory and wall time of the whole command on MEMORY_FRAMES frames, in a fresh process (rendering excluded)
    big = dataset(args.cache, 1.0, 5.0, MEMORY_FRAMES)
    out_json = args.cache / "refined-memory-run.json"
    code = ("import sys, time; from lfgraph.cli import main; t = time.perf_counter(); p = time.process_time(); "
            "c = main(sys.argv[1:]); print('WALL', time.perf_counter() - t); print('CPU', time.process_time() - p); "
            "hwm = [int(x.split()[1]) for x in open('/proc/self/status') if x.startswith('VmHWM')][0]; "
            "print('PEAK_MB', hwm / 1024); sys.exit(c)")
    # (VmHWM, not ru_maxrss: Linux keeps ru_maxrss across fork+exec, so a child would report this process's peak)
    proc = subprocess.run([sys.executable, "-c", code, "refine", str(big / "original.json"), str(big), "-o",
                           str(out_json), "--quiet"], capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        failures.append(f"lfgraph refine on {MEMORY_FRAMES} frames failed: {proc.stderr.strip()[-300:]}")
        peak = float("nan")
    else:
        peak = float(proc.stdout.split("PEAK_MB")[1].split()[0])
        wall = float(proc.stdout.split("WALL")[1].split()[0])
        cpu = float(proc.stdout.split("CPU")[1].split()[0])
        truth = Calibration.load(big / "truth.json")
        r = evaluate(Calibration.load(out_json), truth, None)
        print(f"lfgraph refine on {MEMORY_FRAMES} frames (1 deg / 5 mm): {wall:.1f} s ({cpu:.1f} s CPU, "
              f"{cpu / MEMORY_FRAMES:.2f} s per frame), peak memory {peak:.0f} MB "
              f"(target < {TARGET_MEMORY_MB:g} MB); rotation error {r['rot']:.4f} deg, transfer {r['transfer']:.3f} px")
    if peak > TARGET_MEMORY_MB:
        failures.append(f"peak memory {peak:.0f} MB")
    print("targets missed: " + ("; ".join(failures) if failures else "none"))
    return 1 if failures else 0


if __name__ == "__main__":
    t0 = time.perf_counter()
    code = main()
    print(f"({time.perf_counter() - t0:.0f} s)")
    sys.exit(code)
