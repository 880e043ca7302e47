"""`lfgraph demo` / `make demo`: the main job on the embedded synthetic default (paper-4x4).

Render the paper's 4x4 array looking at a checkerboard (ground truth known), detect the corners, calibrate with the
paper's route and with the joint factor graph, and print both against the truth.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from lfgraph.cli.tables import (
    alignment_table,
    calibration_report_text,
    evaluation_table,
    format_table,
    rectification_text,
    refinement_text,
)
from lfgraph.core.files import OutputError, staged_folder
from lfgraph.core.observer import BaseObserver
from lfgraph.datasets.checkerboard import make_checkerboard_truth, write_checkerboard_dataset
from lfgraph.datasets.rig import ShakeConfig, make_rig, shake_rig
from lfgraph.datasets.scene import SceneConfig, write_scene_dataset
from lfgraph.datasets.scenes import SCENES, get_scene
from lfgraph.detect.detections import detect_capture
from lfgraph.io.capture import open_capture, write_frame
from lfgraph.judge.alignment import align_points, infinity_alignment, transfer_error_at_infinity
from lfgraph.judge.evaluation import evaluate_calibration
from lfgraph.pattern import CalibrateConfig, calibrate
from lfgraph.rectification.rectify import build_maps, compute_rectification, remap_views
from lfgraph.refinement import refine

DEMO_SCENE = "paper-4x4"
DEMO_SEED = 0


class _Indented(BaseObserver):
    """Prints the calibration's log lines indented under the demo's step."""

    def log(self, message: str) -> None:
        print(f"      {message}")


def _demo_steps(out: Path, shown: Path, jobs: int, quiet: bool, scene_name: str, with_refinement: bool) -> int:
    """`run_demo`'s steps, writing into ``out`` (the staged folder) and naming the files as they will be: in
    ``shown``."""
    demo_start = time.perf_counter()
    scene = get_scene(scene_name)
    rng = np.random.default_rng(DEMO_SEED)
    truth_calib = make_rig(scene.rig, rng)
    truth = make_checkerboard_truth(truth_calib, scene.checkerboard, rng)
    data_dir = out / scene_name
    print(f"[1/5] rendering {scene_name}: {scene.description}")
    start = time.perf_counter()
    write_checkerboard_dataset(data_dir, truth_calib, truth, scene.checkerboard, seed=DEMO_SEED, jobs=jobs,
                               progress=not quiet)
    n_images = truth_calib.num_views * scene.checkerboard.frames
    print(f"      {n_images} images in {time.perf_counter() - start:.1f} s -> {shown / scene_name} "
          f"(truth: {shown / scene_name / 'truth.json'})")

    print("[2/5] lfgraph calibrate: detection, the paper's route, the joint factor graph")
    start = time.perf_counter()
    capture = open_capture(data_dir, truth_calib.grid)
    obs, _ = detect_capture(capture, scene.checkerboard.board, jobs=jobs, progress=not quiet, cache=False)
    both = obs.valid & truth.corner_valid
    det_rms = float(np.sqrt(np.mean(np.sum((obs.corners_px[both] - truth.corners_px[both]) ** 2, axis=-1))))
    print(f"      board found in {obs.seen.sum()} of {obs.seen.size} images; detected corners are "
          f"{det_rms:.4f} px RMS from the true projections")
    paper, _ = calibrate(obs, CalibrateConfig(method="paper"))
    joint, report = calibrate(obs, observer=_Indented())
    out_json = out / "calibration.json"
    joint.save(out_json)
    print(calibration_report_text(joint, report))
    print(f"      calibrated in {time.perf_counter() - start:.1f} s -> {shown / 'calibration.json'}")

    print("[3/5] lfgraph evaluate: the joint calibration against the ground truth")
    errors = evaluate_calibration(joint, truth_calib)
    print(evaluation_table(errors))
    p, j = evaluate_calibration(paper, truth_calib).summary(), errors.summary()
    rows = [[name, f"{p[key]:.4g}", f"{j[key]:.4g}", f"{p[key] / j[key]:.1f}x" if j[key] > 0 else "-"]
            for name, key in (("fx (px)", "rms_fx_px"), ("cx (px)", "rms_cx_px"), ("k1", "rms_k1"),
                              ("view position (mm)", "rms_position_mm"), ("view rotation (deg)", "rms_rotation_deg"))]
    print("RMS error against truth, paper route vs joint graph:")
    print(format_table(["parameter", "paper route", "joint (lfgraph)", "paper / joint"], rows))

    print("[4/5] lfgraph rectify: common K_r and rotation, grid deviation, alignment before/after")
    rect = compute_rectification(joint)
    print(rectification_text(joint, rect))
    maps = build_maps(joint, rect)
    write_frame(out / "rectified", capture.frame_names[0], remap_views(capture.load_frame(0), maps), joint.grid)
    n = joint.num_views
    report_pts = align_points(joint, rect, obs.corners_px.reshape(n, -1, 2), obs.valid.reshape(n, -1))
    print("alignment of the detected corners (all frames) and of directions at infinity, RMS px:")
    print(alignment_table([
        ("corners, original views", report_pts.before), ("corners, rectified", report_pts.after),
        ("  off-grid parallax alone", report_pts.parallax), ("  rectified, parallax removed", report_pts.compensated),
        ("infinity, true cameras", infinity_alignment(joint, rect, seen_by=truth_calib))]))
    print(f"      rectified frame {capture.frame_names[0]} -> {shown / 'rectified'}")
    if with_refinement:
        run_refinement_demo(out, shown, jobs, quiet)
    print(f"demo done in {time.perf_counter() - demo_start:.0f} s; everything is in {shown}: the rendered boards and "
          f"truth ({shown / scene_name}), the calibration ({shown / 'calibration.json'}), the rectified frame "
          f"({shown / 'rectified'})" + (f", the refined calibration ({shown / 'refined.json'}) and its rerun "
                                        f"recording (rerun {shown / 'refine.rrd'})" if with_refinement else ""))
    return 0


REFINE_SCENE = "paper-5x5"
REFINE_SHAKE = (1.0, 5.0)  # degrees about a random axis per view (pan, tilt and roll, as a real knock), millimetres
# per axis: the paper's largest shake (which turned views about their optical axes only)
REFINE_FRAMES = 2


def _earlier_demo(out: Path) -> bool:
    """Whether ``out`` holds an earlier demo to replace (False: absent or empty). A folder holding anything the demo
    does not write is refused (the demo replaces its folder whole)."""
    if not out.is_dir() or not any(out.iterdir()):
        return False
    ours = {"calibration.json", "rectified", "refined.json", "refine.rrd", f"{REFINE_SCENE}-shaken", *SCENES}
    foreign = sorted(c.name for c in out.iterdir() if c.name not in ours)
    if foreign:
        raise OutputError(f"{out}: holds files the demo did not write ({', '.join(foreign[:5])}); the demo replaces "
                          f"its folder whole: give another --out, or move them")
    return True


def run_demo(out: Path, jobs: int, quiet: bool = False, scene_name: str = DEMO_SCENE,
             with_refinement: bool = True) -> int:
    """``make demo``: render a named board capture, detect, calibrate by both routes, rectify and (``with_refinement``)
    refine a knocked paper-5x5 capture, printing each step's errors against the truth; everything goes into ``out``,
    which appears complete or not at all (an earlier demo there is replaced). Returns the exit code."""
    out = Path(out)
    with staged_folder(out, replaceable=_earlier_demo(out)) as work:
        return _demo_steps(work, out, jobs, quiet, scene_name, with_refinement)


def run_refinement_demo(out: Path, shown: Path, jobs: int, quiet: bool) -> None:
    """Shake paper-5x5, render textured scenes with the shaken rig, refine from the original calibration (written
    into ``out``, named as in ``shown``)."""
    scene = get_scene(REFINE_SCENE)
    original = make_rig(scene.rig, np.random.default_rng(DEMO_SEED))
    rot, trans = REFINE_SHAKE
    truth = shake_rig(original, ShakeConfig(rot_deg=rot, trans_mm=trans, axis="any"),
                      np.random.default_rng([DEMO_SEED, 1]))
    data_dir = out / f"{REFINE_SCENE}-shaken"
    print(f"[5/5] lfgraph refine: {REFINE_SCENE} knocked by up to {rot:g} deg about a random axis per view and "
          f"{trans:g} mm; "
          f"{REFINE_FRAMES} textured frames rendered with the shaken rig")
    near, far = scene.scene_depth_m
    start = time.perf_counter()
    write_scene_dataset(data_dir, truth, SceneConfig(depth_m=(near, far), background_depth_m=far * 1.4),
                        frames=REFINE_FRAMES, seed=DEMO_SEED, jobs=jobs, progress=not quiet, original=original)
    print(f"      rendered in {time.perf_counter() - start:.1f} s -> {shown / data_dir.name}")
    capture = open_capture(data_dir, original.grid)
    from lfgraph.viz.rerun_log import RerunLogger

    recording = out / "refine.rrd"
    with RerunLogger.to_file(recording, original.grid, "refine") as logger:
        refined, report = refine(original, capture.frames(), observer=logger)  # it logs the result too (run_end)
    refined.save(out / "refined.json")
    print(refinement_text(original, refined, report).split("changes per view")[0].rstrip())
    rows = []
    for name, calib in (("original calibration", original), ("refined (lfgraph default)", refined)):
        e = evaluate_calibration(calib, truth)
        te = transfer_error_at_infinity(calib, truth)
        rows.append([name, f"{np.sqrt(np.mean(e.rotation_deg ** 2)):.4f}", f"{np.max(e.rotation_deg):.4f}",
                     f"{np.sqrt(np.mean(te ** 2)):.3f}", f"{np.sqrt(np.mean(np.sum(e.position_mm ** 2, axis=1))):.3f}"])
    print("errors against the shaken truth (RMS over views):")
    print(format_table(["calibration", "rot_err_deg", "max_rot_err_deg", "transfer_at_infinity_px", "pos_err_mm"],
                       rows))
    print(f"      refined calibration -> {shown / 'refined.json'}")
    print(f"      rerun recording of the refinement (input and refined rig, per-frame tracks) -> "
          f"{shown / recording.name}; open it with: .venv/bin/rerun {shown / recording.name}")
