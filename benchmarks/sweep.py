"""Randomized sweep of `refine` on rigs nobody tuned on (issue 24): every scenario draws a grid, image size, focal
length, distortion, scattered view poses, a knock about random axes (a quarter of the rigs not knocked at all),
the number of frames, sensor noise, texture (rich, repetitive, poor) and scene depth; renders the knocked rig's
scenes; refines the *unknocked* calibration with the defaults; and scores what was written against the truth.

Per texture class and overall:
(a) never worse: scenarios whose written calibration is worse than the input beyond 1 sigma — its RMS over views of
    the transfer at infinity, or of the scale-aligned position error, above the input's by more than the RMS of the
    reported sigmas — goal 0; beside it the views worse than the input by more than 3 of their own sigmas (a view
    refitted from an exact input is beyond 1 sigma ~40 % of the time by chance);
(b) false alarms: unknocked rigs with a view DRIFTED — goal <= 1 %;
(c) misses: views whose knock moves the transfer at infinity by >= 3x the tolerance left OK — goal <= 1 %;
(d) honest sigmas: RMS of error / reported sigma over applied views, per group (pan/tilt, roll, position) — goal 0.5-2;
    and per view: each scenario's worst applied view's transfer error at infinity over its reported 1-sigma
    (`predicted_transfer_px`), median and worst over scenarios — goal <= 3 (a ramp of the error with the offset
    from the reference shows in the far views, not in an RMS over views);
(e) accuracy (median and worst transfer at infinity after) and seconds per frame.

    python benchmarks/sweep.py --scenarios 200 [--seed 0] [--csv out/sweep.csv] [--jobs 2]
        [--robust tukey] [--mixed] [--lens fisheye|unified]

Rows are appended to the CSV as scenarios finish (a re-run skips the seeds already there). `tests/test_sweep.py`
runs a fixed-seed subset of the same scenarios.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.geometry import rotvec_from_rotation
from lfgraph.datasets.rig import RigConfig, ShakeConfig, make_rig, resize_views, shake_rig
from lfgraph.datasets.scene import SceneConfig, make_scene, render_scene_views
from lfgraph.judge.alignment import transfer_error_at_infinity
from lfgraph.refinement import RefineConfig, refine
from lfgraph.refinement.report import DRIFTED, OK

GRIDS = [(1, 2), (2, 2), (1, 3), (2, 3), (3, 3), (3, 4), (4, 4), (1, 5), (5, 5), (6, 6), (1, 8)]
IMAGE_SIZES = [(320, 240), (400, 300), (512, 512), (640, 480), (800, 600), (1024, 768), (1280, 960), (1920, 1080)]
TEXTURES = ("rich", "repetitive", "poor")
MAX_PIXELS = 40e6  # rendered pixels per scenario (views x frames x W x H): frames are cut to stay within
UNKNOCKED_SHARE = 0.25
MAX_KNOCK_DEG = 2.0
MAX_KNOCK_MM = 5.0
DISTORTION_JITTER = 0.01  # RigConfig's default spread of k1 (k2: half) between views
MIN_DISTORTION_SLOPE = 0.3  # d(distorted radius)/d(radius) everywhere in the image: a lens, not a fold-over
SIGMA_FLOOR = 1e-3  # px and mm: a reported sigma below this counts as this in the never-worse comparisons
MISS_FACTOR = 3.0  # a view knocked by >= 3x the tolerance (transfer at infinity) must not be left OK
GOAL_FALSE_ALARM = 0.01
GOAL_MISS = 0.01
GOAL_SIGMA_RATIO = (0.5, 2.0)
GOAL_VIEW_RATIO = 3.0  # (d) every applied view's transfer error at infinity within this many of its reported sigmas


@dataclass(frozen=True)
class Scenario:
    seed: int
    rows: int
    cols: int
    width: int
    height: int
    focal_px: float
    pitch_m: float
    k1: float
    k2: float
    rot_jitter_deg: float
    trans_jitter_mm: float
    knock_deg: float
    knock_mm: float
    frames: int
    noise_grey: float
    texture: str
    near_m: float
    far_m: float

    @property
    def knocked(self) -> bool:
        return self.knock_deg > 0 or self.knock_mm > 0

    def label(self) -> str:
        return (f"#{self.seed} {self.rows}x{self.cols} {self.width}x{self.height} f{self.focal_px:.0f} "
                f"{self.texture} {self.frames}fr knock {self.knock_deg:.2f}deg {self.knock_mm:.1f}mm")


def draw(seed: int) -> Scenario:
    """One scenario, a pure function of its seed."""
    rng = np.random.default_rng([24, seed])
    rows, cols = GRIDS[rng.integers(len(GRIDS))]
    if rng.uniform() < 0.5:
        rows, cols = cols, rows  # columns as often as rows
    w, h = IMAGE_SIZES[rng.integers(len(IMAGE_SIZES))]
    # field of view from ~35 to ~95 degrees across the image width, focal 300-2000 px
    focal = float(np.clip(w / (2 * np.tan(np.radians(rng.uniform(17, 47)))), 300, 2000))
    near = float(rng.choice([1.0, 2.0, 3.0]) * rng.uniform(0.8, 1.2))
    far = near * rng.uniform(1.5, 3.0)
    # neighbour disparity at the near depth 8-40 px: what a real array of this field of view would have
    pitch = float(rng.uniform(8, 40) * near / focal)
    # a lens whose distortion stays monotonic out to the image corners (a real one: no fold-over in the image)
    r_max = 1.1 * np.hypot(w, h) / (2 * focal)
    while True:
        k1 = float(rng.uniform(-0.25, 0.05))
        k2 = float(rng.uniform(-0.02, 0.05))
        r2 = np.linspace(0, r_max**2, 50)
        k1j, k2j = k1 - 3 * DISTORTION_JITTER, k2 - 1.5 * DISTORTION_JITTER  # the views' own lenses vary
        if np.all(1 + 3 * k1j * r2 + 5 * k2j * r2**2 > MIN_DISTORTION_SLOPE):
            break
    knocked = rng.uniform() >= UNKNOCKED_SHARE
    knock_deg = float(rng.uniform(0.05, MAX_KNOCK_DEG)) if knocked else 0.0
    knock_mm = float(rng.uniform(0.0, MAX_KNOCK_MM)) if knocked else 0.0
    frames = int(rng.integers(1, 9))
    frames = int(max(1, min(frames, MAX_PIXELS // (rows * cols * w * h))))
    return Scenario(seed, int(rows), int(cols), w, h, focal, pitch, k1, k2, float(rng.uniform(0.0, 1.0)),
                    float(rng.uniform(0.0, 2.0)), knock_deg, knock_mm, frames, float(rng.uniform(0.3, 2.0)),
                    str(TEXTURES[rng.integers(len(TEXTURES))]), near, far)


MIXED_SIZE_SCALES = (0.5, 0.75, 1.5, 2.0)  # --mixed: a view's image size relative to the rig's ...
MIXED_FIELD_SPREAD = 1.25  # ... and its focal length relative to that, within this factor either way


def mixed_sizes(calib: Calibration, seed: int) -> Calibration:
    """``calib`` with about half its views (at least one) at another image size and focal length (`--mixed`)."""
    rng = np.random.default_rng([seed, 5])
    pick = rng.uniform(size=calib.num_views) < 0.5
    pick[rng.integers(calib.num_views)] = True
    scale, focal = np.ones(calib.num_views), np.ones(calib.num_views)
    for v in np.nonzero(pick)[0]:
        scale[v] = rng.choice(MIXED_SIZE_SCALES)
        focal[v] = scale[v] * np.exp(rng.uniform(-1, 1) * np.log(MIXED_FIELD_SPREAD))
    return resize_views(calib, scale, focal)


WIDE_FOCAL_SCALE = 0.6  # --lens fisheye / unified: the scenario's focal length times this (fields ~55-125 deg across)


def wide_lens(s: Scenario, lens: str) -> dict:
    """`RigConfig` fields of a wide lens for the scenario (``--lens``; the radtan draw when ``lens`` is radtan): a
    fisheye's k1 in [-0.04, 0.02] and k2 in [-0.005, 0.005] (monotonic past 70 deg off axis), or a unified lens
    with xi in [0.6, 1.1] and k1 in [-0.15, 0], k2 in [0, 0.03], its focal length (1 + xi) times longer for the
    same field."""
    if lens == "radtan":
        return dict(focal_px=s.focal_px, k1=s.k1, k2=s.k2)
    rng = np.random.default_rng([s.seed, 6])
    focal = WIDE_FOCAL_SCALE * s.focal_px
    if lens == "fisheye":
        return dict(lens=lens, focal_px=focal, k1=float(rng.uniform(-0.04, 0.02)), k2=float(rng.uniform(-0.005, 0.005)),
                    distortion_jitter=0.002)
    xi = float(rng.uniform(0.6, 1.1))
    return dict(lens=lens, xi=xi, focal_px=(1.0 + xi) * focal, k1=float(rng.uniform(-0.15, 0.0)),
                k2=float(rng.uniform(0.0, 0.03)), distortion_jitter=0.005)


def rigs(s: Scenario, mixed: bool = False, lens: str = "radtan") -> tuple[Calibration, Calibration]:
    """(input, truth): the calibrated rig and the same rig after the knock (``mixed``: views of other sizes;
    ``lens``: every view's model, `wide_lens`)."""
    optics = wide_lens(s, lens)
    cfg = RigConfig(rows=s.rows, cols=s.cols, reference=(s.rows // 2) * s.cols + s.cols // 2, pitch_m=s.pitch_m,
                    image_size_px=(s.width, s.height), focal_jitter_px=0.005 * optics["focal_px"],
                    principal_jitter_px=0.01 * s.width, rot_jitter_deg=s.rot_jitter_deg,
                    trans_jitter_mm=s.trans_jitter_mm, **optics)
    original = make_rig(cfg, np.random.default_rng([s.seed, 1]))
    if mixed:
        original = mixed_sizes(original, s.seed)
    if not s.knocked:
        return original, original
    truth = shake_rig(original, ShakeConfig(rot_deg=s.knock_deg, trans_mm=s.knock_mm, axis="any"),
                      np.random.default_rng([s.seed, 2]))
    return original, truth


def scene_config(s: Scenario) -> SceneConfig:
    poor = s.texture == "poor"
    return SceneConfig(depth_m=(s.near_m, s.far_m), background_depth_m=s.far_m * 1.4,
                       objects=3 if poor else 8, texels_per_m_at_1m=120.0 if poor else 700.0,
                       blur_sigma_px=1.2 if poor else 0.5, noise_sigma=s.noise_grey,
                       kind="keyboard" if s.texture == "repetitive" else "dead-leaves", supersample=1)


def render(s: Scenario, truth: Calibration) -> list[np.ndarray]:
    cfg = scene_config(s)
    out = []
    for f in range(s.frames):
        scene = make_scene(cfg, np.random.default_rng([s.seed, 3, f]))
        out.append(render_scene_views(scene, truth, cfg,
                                      rngs=[np.random.default_rng([s.seed, 4, f, v]) for v in range(truth.num_views)]))
    return out


def _align_scale(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Positions (V, 3) of ``est`` scaled to best match ``truth`` (scale is a gauge of a scene refinement)."""
    d = float(np.sum(est * est))
    return est * (float(np.sum(est * truth)) / d if d > 0 else 1.0)


def body_errors(est: Calibration, truth: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) body-frame rotation error (deg) and (V, 3) scale-aligned position error in the view's frame (mm)."""
    rot = np.degrees(np.stack([rotvec_from_rotation(truth.ref_T_view[v][:3, :3].T @ est.ref_T_view[v][:3, :3])
                               for v in range(truth.num_views)]))
    p = _align_scale(est.ref_T_view[:, :3, 3], truth.ref_T_view[:, :3, 3]) - truth.ref_T_view[:, :3, 3]
    pos = 1e3 * np.einsum("vji,vj->vi", truth.ref_T_view[:, :3, :3], p)  # in the view's own axes
    return rot, pos


def score(s: Scenario, inp: Calibration, truth: Calibration, out: Calibration, report, seconds: float,
          tolerance_px: float) -> dict:
    """One scenario's row: the criteria (a)-(e) of the module docstring."""
    ref = truth.grid.reference
    te_in = transfer_error_at_infinity(inp, truth)
    te_out = transfer_error_at_infinity(out, truth)
    _, pos_in = body_errors(inp, truth)
    rot_out, pos_out = body_errors(out, truth)
    verdicts = report.verdicts
    sig_t = np.array([v.predicted_transfer_px if np.isfinite(v.predicted_transfer_px) else 0.0 for v in verdicts])
    sig_p = np.array([np.linalg.norm(v.sigma_position_mm) if np.all(np.isfinite(v.sigma_position_mm)) else 0.0
                      for v in verdicts])
    free = np.arange(truth.num_views) != ref
    pin, pout = np.linalg.norm(pos_in, axis=1), np.linalg.norm(pos_out, axis=1)
    # calibration level (the criterion): RMS over views of the written vs the input, beyond the RMS 1-sigma
    worse_cal_t = _rms(te_out[free]) > _rms(te_in[free]) + max(_rms(sig_t[free]), SIGMA_FLOOR)
    worse_cal_p = _rms(pout[free]) > _rms(pin[free]) + max(_rms(sig_p[free]), SIGMA_FLOOR)
    # per view, beyond 1 and beyond 3 of its own sigmas (a refitted view whose input was exact is beyond 1 sigma
    # ~40 % of the time by chance: the 3-sigma count is the one that says "made worse")
    worse_t = te_out > te_in + np.maximum(sig_t, SIGMA_FLOOR)
    worse_p = pout > pin + np.maximum(sig_p, SIGMA_FLOOR)
    worse3 = (te_out > te_in + 3 * np.maximum(sig_t, SIGMA_FLOOR)) | (pout > pin + 3 * np.maximum(sig_p, SIGMA_FLOOR))
    worse = (worse_t | worse_p)
    worse[ref] = worse3[ref] = False
    drifted = np.array([v.verdict == DRIFTED for v in verdicts])
    ok = np.array([v.verdict == OK for v in verdicts])
    knock_px = te_in  # the input is the unknocked truth: its transfer error is the knock's effect
    big = knock_px >= MISS_FACTOR * tolerance_px
    big[ref] = False
    applied = np.array([v.applied for v in verdicts])
    # per view, not RMS over views: a mode growing with the offset from the reference shows in the far views only
    view_ratio = te_out[applied] / np.maximum(sig_t[applied], SIGMA_FLOOR)
    z = {"pan_tilt": [], "roll": [], "position": []}
    for v in np.nonzero(applied)[0]:
        vd = verdicts[v]
        z["pan_tilt"] += list(rot_out[v, :2] / np.maximum(vd.sigma_rotation_deg[:2], 1e-12))
        z["roll"].append(rot_out[v, 2] / max(vd.sigma_rotation_deg[2], 1e-12))
        z["position"] += list(pos_out[v] / np.maximum(vd.sigma_position_mm, 1e-12))
    return {**asdict(s), "views": truth.num_views, "knock_px_max": float(np.max(knock_px)),
            "transfer_in_px": float(np.sqrt(np.mean(te_in**2))), "transfer_out_px": float(np.sqrt(np.mean(te_out**2))),
            "transfer_out_max_px": float(np.max(te_out)), "transfer_in_max_px": float(np.max(te_in)),
            "pos_in_max_mm": float(np.max(np.linalg.norm(pos_in, axis=1))),
            "pos_out_max_mm": float(np.max(np.linalg.norm(pos_out, axis=1))),
            "worse_calibration": int(worse_cal_t or worse_cal_p), "worse_calibration_transfer": int(worse_cal_t),
            "worse_views": int(worse.sum()), "worse_views_3sigma": int(worse3.sum()),
            "worse_transfer_views": int(np.delete(worse_t, ref).sum()),
            "drifted_views": int(drifted.sum()), "big_knocks": int(big.sum()),
            "missed_views": int((big & ok).sum()), "uncertain_big": int((big & ~ok & ~drifted).sum()),
            "applied_views": int(applied.sum()), "accepted": bool(report.accepted),
            "worst_view_ratio": float(np.max(view_ratio)) if view_ratio.size else "",
            **{f"z_{k}": ";".join(f"{x:.3g}" for x in z[k]) for k in z},
            "seconds": seconds, "seconds_per_frame": seconds / max(report.frames_used, 1)}


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if np.size(x) else 0.0


def run(s: Scenario, config: RefineConfig | None = None, mixed: bool = False, lens: str = "radtan") -> dict:
    """Render, refine from the unknocked calibration, score."""
    config = config or RefineConfig()
    inp, truth = rigs(s, mixed, lens)
    frames = render(s, truth)
    t0 = time.perf_counter()
    try:
        out, report = refine(inp, frames, config)
    except ValueError as e:  # no usable tracks: nothing written, which is never worse
        return {**asdict(s), "views": truth.num_views, "error": str(e)[:120]}
    return score(s, inp, truth, out, report, time.perf_counter() - t0, config.tolerance_px)


def _run_seed(seed: int, robust: str = "none", mixed: bool = False, lens: str = "radtan") -> dict:
    s = draw(seed)
    try:
        row = run(s, RefineConfig(robust=robust), mixed, lens)
    except Exception as e:  # a crash is a finding: recorded, not hidden
        row = {**asdict(s), "views": s.rows * s.cols, "error": f"{type(e).__name__}: {e}"[:160]}
    return row


def summary(rows: list[dict], tolerance_px: float) -> list[list[str]]:
    """The table: per texture class and overall."""
    out = []
    for cls in (*TEXTURES, "all"):
        rs = [r for r in rows if cls == "all" or r["texture"] == cls]
        done = [r for r in rs if not r.get("error")]
        if not rs:
            continue
        errors = len(rs) - len(done)
        never_worse = sum(int(r["worse_calibration"]) > 0 for r in done)
        worse_t = sum(int(r["worse_calibration_transfer"]) > 0 for r in done)
        views3 = sum(int(r["worse_views_3sigma"]) for r in done)
        views_all = sum(int(r["views"]) - 1 for r in done)
        unknocked = [r for r in done if not (float(r["knock_deg"]) > 0 or float(r["knock_mm"]) > 0)]
        false_alarm = sum(int(r["drifted_views"]) > 0 for r in unknocked)
        big = sum(int(r["big_knocks"]) for r in done)
        missed = sum(int(r["missed_views"]) for r in done)
        unc = sum(int(r["uncertain_big"]) for r in done)

        def zrms(key, done=done):
            z = [float(x) for r in done for x in str(r.get(key) or "").split(";") if x]
            return f"{np.sqrt(np.mean(np.square(z))):.2f} ({len(z)})" if z else "-"

        ratios = np.array([float(r["worst_view_ratio"]) for r in done if r.get("worst_view_ratio") not in (None, "")])
        t_out = np.array([float(r["transfer_out_max_px"]) for r in done]) if done else np.zeros(1)
        spf = np.array([float(r["seconds_per_frame"]) for r in done]) if done else np.zeros(1)
        out.append([cls, str(len(rs)), str(errors), f"{never_worse} ({worse_t} in transfer)", f"{views3}/{views_all}",
                    f"{false_alarm}/{len(unknocked)}", f"{missed}/{big} ({unc} unc.)",
                    zrms("z_pan_tilt"), zrms("z_roll"), zrms("z_position"),
                    f"{np.median(ratios):.2f} / {np.max(ratios):.2f} ({ratios.size})" if ratios.size else "-",
                    f"{np.median(t_out):.3f} / {np.max(t_out):.3f}", f"{np.median(spf):.2f} / {np.max(spf):.2f}"])
    return out


HEADER = ["texture", "scenarios", "refused", "(a) calibrations worse", "views worse > 3 sigma", "(b) false alarms",
          "(c) misses", "(d) z pan/tilt", "(d) z roll", "(d) z position",
          "(d) worst view transfer/sigma (med/max)", "(e) transfer after px (med/worst view)",
          "s/frame (med/max)"]


def resumed(csv_path: str, first: int, count: int) -> tuple[Path, list[dict], list[int]]:
    """A resumable sweep's CSV (created with its folder), the rows it holds and the seeds of ``first`` .. ``first +
    count - 1`` still to run."""
    path = Path(csv_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    if path.exists():
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
    done = {int(r["seed"]) for r in rows}
    return path, rows, [s for s in range(first, first + count) if s not in done]


def run_recorded(todo: list, run_one, path: Path, fields: list[str], label, rows: list[dict], jobs: int) -> None:
    """Run ``run_one`` on every item of ``todo`` (``jobs`` processes: ``run_one`` must pickle), each row appended to
    ``path`` as it comes (a header first into an empty file) and to ``rows``, and said in one line under
    ``label(seed)``."""
    def record(row: dict) -> None:
        rows.append(row)
        new = not path.exists() or path.stat().st_size == 0
        with open(path, "a", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=fields, extrasaction="ignore")
            if new:
                w.writeheader()
            w.writerow(row)
        views = f" (views {row['worse_views']}, > 3 sigma " if "worse_views" in row else " (> 3 sigma "
        flag = row.get("error") or (f"worse {row['worse_calibration']}{views}{row['worse_views_3sigma']}) drifted "
                                    f"{row['drifted_views']} missed {row['missed_views']}/{row['big_knocks']} transfer "
                                    f"{row['transfer_in_max_px']:.3f} -> {row['transfer_out_max_px']:.3f} px, "
                                    f"{row['seconds']:.1f} s")
        print(f"{label(int(row['seed']))}: {flag}", flush=True)

    if jobs > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(jobs) as pool:
            for row in pool.map(run_one, todo):
                record(row)
    else:
        for item in todo:
            record(run_one(item))


def main(argv: list[str] | None = None) -> int:
    from lfgraph.cli.tables import format_table

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarios", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0, help="first scenario seed")
    ap.add_argument("--csv", default="out/bench-sweep/sweep.csv")
    ap.add_argument("--jobs", type=int, default=1, help="scenarios in parallel (processes)")
    ap.add_argument("--robust", default="none", help="every scenario refined with this noise model (e.g. tukey)")
    ap.add_argument("--mixed", action="store_true", help="about half of every rig's views at another image size "
                    "(0.5-2x) and field of view (within 1.25x)")
    ap.add_argument("--lens", default="radtan", choices=("radtan", "fisheye", "unified"),
                    help="every view's lens model (fisheye, unified: wider fields, `wide_lens`)")
    args = ap.parse_args(argv)
    path, rows, todo = resumed(args.csv, args.seed, args.scenarios)
    tol = RefineConfig().tolerance_px
    print(f"{len(todo)} scenarios to run ({len(rows)} in {path})", flush=True)
    if args.lens != "radtan":
        print(f"every view {args.lens}: the labels' focal lengths are the radtan draw's, the lenses' are "
              f"{WIDE_FOCAL_SCALE:g}x" + (" (1 + xi)" if args.lens == "unified" else ""), flush=True)
    run_recorded(todo, partial(_run_seed, robust=args.robust, mixed=args.mixed, lens=args.lens), path,
                 list(_run_fields()), lambda seed: draw(seed).label(), rows, args.jobs)
    rows = [r for r in rows if args.seed <= int(r["seed"]) < args.seed + args.scenarios]
    print(format_table(HEADER, summary(rows, tol)))
    print(f"tolerance {tol:g} px; goals: (a) 0, (b) <= {100 * GOAL_FALSE_ALARM:g} %, (c) <= {100 * GOAL_MISS:g} %, "
          f"(d) {GOAL_SIGMA_RATIO[0]}-{GOAL_SIGMA_RATIO[1]}, worst view <= {GOAL_VIEW_RATIO:g}")
    worst = sorted((r for r in rows if not r.get("error")), key=lambda r: -float(r["transfer_out_max_px"]))[:5]
    print("worst cases (transfer at infinity after, worst view): " + "; ".join(
        f"{draw(int(r['seed'])).label()}: {float(r['transfer_in_max_px']):.3f} -> "
        f"{float(r['transfer_out_max_px']):.3f} px" for r in worst))
    return 0 if goals_met(rows) else 1


def goals_met(rows: list[dict]) -> bool:
    """(a) no scenario written worse, (b) false alarms and (c) misses within their goals."""
    done = [r for r in rows if not r.get("error")]
    worse = sum(int(r["worse_calibration"]) > 0 for r in done)
    unknocked = [r for r in done if not (float(r["knock_deg"]) > 0 or float(r["knock_mm"]) > 0)]
    alarms = sum(int(r["drifted_views"]) > 0 for r in unknocked)
    big = sum(int(r["big_knocks"]) for r in done)
    missed = sum(int(r["missed_views"]) for r in done)
    return (worse == 0 and alarms <= GOAL_FALSE_ALARM * max(len(unknocked), 1)
            and missed <= GOAL_MISS * max(big, 1))


def _run_fields() -> list[str]:
    base = list(asdict(draw(0)))
    return [*base, "views", "error", "knock_px_max", "transfer_in_px", "transfer_out_px", "transfer_out_max_px",
            "transfer_in_max_px", "pos_in_max_mm", "pos_out_max_mm", "worse_calibration", "worse_calibration_transfer",
            "worse_views", "worse_views_3sigma", "worse_transfer_views",
            "drifted_views", "big_knocks",
            "missed_views", "uncertain_big", "applied_views", "accepted", "worst_view_ratio", "z_pan_tilt", "z_roll",
            "z_position",
            "seconds", "seconds_per_frame"]


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.exit(main())
