"""Pattern calibration accuracy and speed: paper route vs joint GTSAM graph vs OpenCV 5's calibrateMultiview.

Part 1 (Monte-Carlo, corner-only ``paper-4x4``): identical noisy corners for the three methods, sigma 0.1 and 0.3 px,
40 and 10 frames, SEEDS noise seeds. Errors are RMS over seeds and non-reference views against ground truth; the
Cramér–Rao floor is the RMS of the joint graph's marginal sigmas. calibrateMultiview misbehaves with partially
visible boards, so every method gets full boards only.

Part 2 (end to end): ``lfgraph calibrate`` on the rendered ``paper-4x4`` images (rendered first unless --images
points at them), wall time and peak memory of the whole command, accuracy against truth.json.

Exit code 1 when a target of issue 3 is missed (printed).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from lfgraph.cli.tables import format_table
from lfgraph.core.calibration import Calibration
from lfgraph.datasets.checkerboard import make_checkerboard_truth, make_corner_observations
from lfgraph.datasets.rig import make_rig
from lfgraph.datasets.scenes import get_scene
from lfgraph.detect.detections import observations_from_arrays
from lfgraph.judge.evaluation import evaluate_calibration
from lfgraph.judge.peers import calibrate_multiview
from lfgraph.pattern import CalibrateConfig, calibrate_joint, calibrate_paper
from lfgraph.pattern.initial import initial_board_T_ref

SEEDS = 20
CONDITIONS = [(0.1, 40), (0.3, 40), (0.1, 10), (0.3, 10)]
TARGET_ERROR_OVER_FLOOR = 1.2  # joint RMS error <= 1.2 x marginal sigma (fx, position, rotation)
TARGET_GAIN = 4.0  # joint >= 4x smaller error than paper route and calibrateMultiview (same three)
TARGET_JOINT_SOLVE_S = 1.0  # 4x4x40 joint solve without marginals
TARGET_E2E_S = 20.0  # whole `lfgraph calibrate` on the rendered paper-4x4
TARGET_E2E_MB = 1500.0
TARGET_E2E_FX_REL = 5e-4  # fx within 0.05 %
TARGET_E2E_POS_MM = 0.05
TARGET_E2E_RIG_RMS_PX = 0.1
TARGET_LOGGING_RATIO = 1.15  # issue 6: logging costs < 15 % of calibrate's run time


def multiview(obs):
    """cv2.calibrateMultiview on the same corners: (intrinsics, ref_T_view, seconds)."""
    t0 = time.perf_counter()
    intr, poses = calibrate_multiview(obs)
    return intr, poses, time.perf_counter() - t0


def errors(intr, poses, truth_calib):
    est = Calibration(truth_calib.grid, truth_calib.image_size_px, intr, poses)
    e = evaluate_calibration(est, truth_calib)
    mask = np.arange(truth_calib.num_views) != truth_calib.grid.reference
    return {"fx": e.intrinsics[:, 0], "cx": e.intrinsics[:, 2], "k1": e.intrinsics[:, 4], "k2": e.intrinsics[:, 5],
            "pos": np.linalg.norm(e.position_mm[mask], axis=1), "rot": e.rotation_deg[mask]}


def floors(sigmas, ref):
    s = [x for v, x in enumerate(sigmas)]
    mask = [v != ref for v in range(len(s))]
    return {"fx": np.array([x["fx_px"] for x in s]), "cx": np.array([x["cx_px"] for x in s]),
            "k1": np.array([x["k1"] for x in s]), "k2": np.array([x["k2"] for x in s]),
            "pos": np.array([np.linalg.norm(x["position_mm"]) for x, m in zip(s, mask, strict=True) if m]),
            "rot": np.array([np.linalg.norm(x["rotation_deg"]) for x, m in zip(s, mask, strict=True) if m])}


def rms(chunks):
    a = np.concatenate([np.ravel(c) for c in chunks])
    return float(np.sqrt(np.mean(a**2)))


def monte_carlo(seeds: int) -> tuple[list[list], list[str], dict]:
    scene = get_scene("paper-4x4")
    rng = np.random.default_rng(2024)
    truth_calib = make_rig(scene.rig, rng)
    truth = make_checkerboard_truth(truth_calib, scene.checkerboard, rng)
    keys = ["fx", "cx", "k1", "k2", "pos", "rot"]
    rows, failures, timing = [], [], {}
    settings_nomarg = CalibrateConfig(marginals=False)
    # warm up GTSAM once so the first timed solve does not pay the import/allocation cost
    c, v = make_corner_observations(truth, 0.1, np.random.default_rng(0))
    warm = observations_from_arrays(truth.board, truth_calib.grid, truth_calib.image_size_px, c, v)
    p = calibrate_paper(warm)
    calibrate_joint(warm, p.intrinsics, p.ref_T_view, initial_board_T_ref(p.view_T_board, p.ref_T_view,
                                                                       warm.valid.sum(axis=2)), settings_nomarg)
    for sigma, n_frames in CONDITIONS:
        acc = {m: {k: [] for k in keys} for m in ("paper", "joint", "multiview", "floor")}
        secs = {"paper": [], "joint": [], "multiview": []}
        for seed in range(seeds):
            c, v = make_corner_observations(truth, sigma, np.random.default_rng([seed, int(sigma * 10), n_frames]))
            obs = observations_from_arrays(truth.board, truth_calib.grid, truth_calib.image_size_px, c, v)
            obs = obs.subset_frames(np.arange(n_frames))
            t0 = time.perf_counter()
            paper = calibrate_paper(obs)
            secs["paper"].append(time.perf_counter() - t0)
            start_boards = initial_board_T_ref(paper.view_T_board, paper.ref_T_view, obs.valid.sum(axis=2))
            t0 = time.perf_counter()
            joint_fast = calibrate_joint(obs, paper.intrinsics, paper.ref_T_view, start_boards, settings_nomarg)
            secs["joint"].append(time.perf_counter() - t0)
            joint = calibrate_joint(obs, paper.intrinsics, paper.ref_T_view, start_boards)
            assert np.allclose(joint.ref_T_view, joint_fast.ref_T_view, atol=1e-9)
            mv_intr, mv_poses, mv_s = multiview(obs)
            secs["multiview"].append(mv_s)
            for name, (intr, poses) in (("paper", (paper.intrinsics, paper.ref_T_view)),
                                        ("joint", (joint.intrinsics, joint.ref_T_view)),
                                        ("multiview", (mv_intr, mv_poses))):
                for k, e in errors(intr, poses, truth_calib).items():
                    acc[name][k].append(e)
            for k, s in floors(joint.sigmas, truth_calib.grid.reference).items():
                acc["floor"][k].append(s)
        res = {m: {k: rms(acc[m][k]) for k in keys} for m in acc}
        label = f"{sigma:g} px, {n_frames} fr"
        for m in ("floor", "joint", "paper", "multiview"):
            row = [label, {"floor": "Cramér-Rao (marginals)", "joint": "joint (lfgraph)", "paper": "paper route",
                           "multiview": "cv2.calibrateMultiview"}[m]]
            row += [f"{res[m][k]:.3g}" for k in keys]
            if m == "floor":
                row += ["-", "-"]
            else:
                row += [f"{np.median(secs[m]):.3f}",
                        " ".join(f"{res[m][k] / res['joint'][k]:.1f}" for k in ("fx", "pos", "rot"))
                        if m != "joint" else " ".join(f"{res['joint'][k] / res['floor'][k]:.2f}"
                                                      for k in ("fx", "pos", "rot"))]
            rows.append(row)
        timing[label] = {m: float(np.median(s)) for m, s in secs.items()}
        if (sigma, n_frames) == (0.1, 40):
            for k in ("fx", "pos", "rot"):
                ratio = res["joint"][k] / res["floor"][k]
                if ratio > TARGET_ERROR_OVER_FLOOR:
                    failures.append(f"joint {k} error {ratio:.2f} x the marginal sigma (target <= "
                                    f"{TARGET_ERROR_OVER_FLOOR})")
                for other in ("paper", "multiview"):
                    gain = res[other][k] / res["joint"][k]
                    if gain < TARGET_GAIN:
                        failures.append(f"{other} {k} error only {gain:.1f} x the joint's (target >= {TARGET_GAIN})")
            if timing[label]["joint"] > TARGET_JOINT_SOLVE_S:
                failures.append(f"joint solve {timing[label]['joint']:.2f} s (target < {TARGET_JOINT_SOLVE_S} s)")
    headers = ["data", "method", "fx_px", "cx_px", "k1", "k2", "pos_mm", "rot_deg", "solve_s",
               "ratio fx pos rot"]
    print(f"Monte-Carlo over {seeds} seeds, corner-only paper-4x4 (full boards only; RMS over seeds and views; "
          "ratio: vs joint for peers, joint / floor for the joint route)")
    print(format_table(headers, rows))
    return rows, failures, timing


def end_to_end(images: Path | None) -> list[str]:
    failures = []
    with tempfile.TemporaryDirectory() as tmp:
        if images is None:
            images = Path(tmp) / "paper-4x4"
            print("rendering paper-4x4 (640 images) for the end-to-end run ...", flush=True)
            subprocess.run([sys.executable, "-m", "lfgraph.cli", "synth", "checkerboard", str(images), "--quiet"],
                           check=True, stdout=subprocess.DEVNULL)
        out = Path(tmp) / "calibration.json"
        cmd = [sys.executable, "-c", "import resource, sys; from lfgraph.cli import main; code = main(sys.argv[1:]); "
               "hwm = [int(x.split()[1]) for x in open('/proc/self/status') if x.startswith('VmHWM')][0]; "
               "print('PEAK_MB', max(hwm, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss) / 1024); "
               "sys.exit(code)",
               "calibrate", str(images), "--grid", "4x4", "--board", "11x8", "--square-mm", "20", "--quiet",
               "--no-cache", "-o", str(out)]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        seconds = time.perf_counter() - t0
        if proc.returncode != 0:
            return [f"lfgraph calibrate failed: {proc.stderr.strip()}"]
        rrd = Path(tmp) / "calibrate.rrd"
        t0 = time.perf_counter()
        logged = subprocess.run([*cmd, "--save", str(rrd)], capture_output=True, text=True, check=False)
        seconds_logged = time.perf_counter() - t0
        if logged.returncode != 0:
            return [f"lfgraph calibrate --save failed: {logged.stderr.strip()}"]
        rrd_mb = rrd.stat().st_size / 2**20
        peak = float(proc.stdout.split("PEAK_MB")[1].split()[0])
        est = Calibration.load(out)
        truth = Calibration.load(images / "truth.json")
        e = evaluate_calibration(est, truth)
        fx_rel = float(np.max(np.abs(e.intrinsics[:, 0]) / np.array([i.fx for i in truth.intrinsics])))
        pos = float(np.max(np.linalg.norm(e.position_mm, axis=1)))
        rig = est.metrics["rig_rms_px"]
        rows = [["wall time (s)", f"{seconds:.1f}", f"< {TARGET_E2E_S:g}"],
                ["peak memory (MB)", f"{peak:.0f}", f"< {TARGET_E2E_MB:g}"],
                ["max |fx error| (relative)", f"{fx_rel:.2e}", f"<= {TARGET_E2E_FX_REL:g}"],
                ["max view position error (mm)", f"{pos:.4f}", f"<= {TARGET_E2E_POS_MM:g}"],
                ["max rotation error (deg)", f"{float(np.max(e.rotation_deg)):.5f}", "-"],
                ["rig-consistent RMS (px)", f"{rig:.4f}", f"<= {TARGET_E2E_RIG_RMS_PX:g}"],
                ["views calibrated", f"{est.num_views}", "16"],
                ["with rerun --save: wall time (s)", f"{seconds_logged:.1f}", "-"],
                ["rerun logging cost (ratio)", f"{seconds_logged / seconds:.2f}", f"< {TARGET_LOGGING_RATIO:g}"],
                [".rrd size (MB)", f"{rrd_mb:.1f}", "-"]]
        print("end to end: lfgraph calibrate on the rendered paper-4x4 (640 images of 960x960, detection included)")
        print(format_table(["figure", "measured", "target"], rows))
        for ok, msg in ((seconds < TARGET_E2E_S, f"end-to-end {seconds:.1f} s"),
                        (peak < TARGET_E2E_MB, f"peak memory {peak:.0f} MB"),
                        (fx_rel <= TARGET_E2E_FX_REL, f"fx error {fx_rel:.2e}"),
                        (pos <= TARGET_E2E_POS_MM, f"position error {pos:.4f} mm"),
                        (rig <= TARGET_E2E_RIG_RMS_PX, f"rig RMS {rig:.4f} px"),
                        (seconds_logged / seconds < TARGET_LOGGING_RATIO,
                         f"rerun logging costs {100 * (seconds_logged / seconds - 1):.0f} %")):
            if not ok:
                failures.append(msg)
    return failures


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=SEEDS)
    parser.add_argument("--images", type=Path, help="rendered paper-4x4 folder (rendered into a temp dir otherwise)")
    parser.add_argument("--skip-images", action="store_true", help="Monte-Carlo part only")
    args = parser.parse_args()
    _, failures, _ = monte_carlo(args.seeds)
    if not args.skip_images:
        failures += end_to_end(args.images)
    print("targets missed: " + ("; ".join(failures) if failures else "none"))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
