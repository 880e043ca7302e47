"""The ``lfgraph`` command. Thin: parse, call the library, print a report.

Exit codes: 0 success, 1 bad input (the message names the file and what was wrong), 2 usage error.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np

EXIT_OK, EXIT_BAD_INPUT, EXIT_USAGE = 0, 1, 2


class UsageError(ValueError):
    """A command-line value that makes no sense; exit code 2."""


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"image size must be WIDTHxHEIGHT such as 960x960, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"image size must be positive, got {text!r}")
    return w, h


def _grid(text: str) -> tuple[int, int]:
    from lfgraph.grid import parse_grid

    try:
        return parse_grid(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a number >= 1, got {value}")
    return value


def _non_negative(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not np.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not np.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


LAYOUT_CHOICES = ("auto", "folders", "mosaic", "hci", "pairs")


def _check_rerun(args: argparse.Namespace) -> bool:
    """Validate the rerun flags before any work; True when logging was asked for."""
    from lfgraph.viz.rerun_log import check_save_path, wants_logging

    if not wants_logging(args):
        return False
    if getattr(args, "save", None):
        try:
            check_save_path(args.save)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    return True


def _jobs_default() -> int:
    return max(1, os.cpu_count() or 1)


# --------------------------------------------------------------------------------------------- synth
def _synth_rig(args: argparse.Namespace, named):
    """The named scene's rig with the command line's overrides."""
    import dataclasses

    rig = named.rig
    changes = {}
    if args.grid is not None:
        changes.update(rows=args.grid[0], cols=args.grid[1])
    if args.image_size is not None:
        changes["image_size_px"] = args.image_size
    if args.reference is not None:
        changes["reference"] = args.reference
    if changes:
        try:
            rig = dataclasses.replace(rig, **changes)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    return rig


def cmd_synth_checkerboard(args: argparse.Namespace) -> int:
    import dataclasses

    from lfgraph.board import BoardSpec
    from lfgraph.datasets.checkerboard import make_checkerboard_truth, write_checkerboard_dataset
    from lfgraph.datasets.rig import make_rig
    from lfgraph.datasets.scenes import get_scene

    named = get_scene(args.scene)
    rig = _synth_rig(args, named)
    cfg = named.checkerboard
    changes = {}
    if args.frames is not None:
        changes["frames"] = args.frames
    if args.board is not None or args.square_mm is not None:
        pattern = args.board or f"{cfg.board.cols}x{cfg.board.rows}"
        square_mm = args.square_mm if args.square_mm is not None else cfg.board.square_m * 1000
        changes["board"] = BoardSpec.parse(pattern, square_mm)
    if changes:
        cfg = dataclasses.replace(cfg, **changes)
    rng = np.random.default_rng(args.seed)
    calib = make_rig(rig, rng)
    truth = make_checkerboard_truth(calib, cfg, rng)
    start = time.perf_counter()
    write_checkerboard_dataset(args.out, calib, truth, cfg, seed=args.seed, layout=args.layout, jobs=args.jobs,
                               progress=not args.quiet)
    seconds = time.perf_counter() - start
    seen = truth.board_visible
    print(f"wrote {cfg.frames} frames x {calib.num_views} views ({args.layout}) to {args.out} in {seconds:.1f} s")
    print(f"board {cfg.board}; whole board inside a view in {seen.sum()} of {seen.size} view-frames "
          f"(per view min {seen.sum(axis=1).min()}, max {seen.sum(axis=1).max()})")
    print(f"ground truth: {Path(args.out) / 'truth.json'}, corners: {Path(args.out) / 'truth_corners.npz'}")
    return EXIT_OK


def cmd_synth_scene(args: argparse.Namespace) -> int:
    from lfgraph.datasets.rig import ShakeConfig, make_rig, shake_rig
    from lfgraph.datasets.scene import SceneConfig, write_scene_dataset
    from lfgraph.datasets.scenes import get_scene

    named = get_scene(args.scene)
    rig = _synth_rig(args, named)
    near, far = named.scene_depth_m
    cfg = SceneConfig(depth_m=(near, far), background_depth_m=far * 1.4,
                      kind="keyboard" if args.keyboard else "dead-leaves")
    frames = args.frames if args.frames is not None else named.frames
    original = make_rig(rig, np.random.default_rng(args.seed))
    shaken = args.shake_rot_deg > 0 or args.shake_trans_mm > 0
    truth = original
    if shaken:
        shake = ShakeConfig(rot_deg=args.shake_rot_deg, trans_mm=args.shake_trans_mm, axis=args.shake_axis)
        truth = shake_rig(original, shake, np.random.default_rng([args.seed, 1]))
    start = time.perf_counter()
    write_scene_dataset(args.out, truth, cfg, frames=frames, seed=args.seed, layout=args.layout, jobs=args.jobs,
                        progress=not args.quiet, original=original if shaken else None)
    seconds = time.perf_counter() - start
    print(f"wrote {frames} frames x {truth.num_views} views ({args.layout}) to {args.out} in {seconds:.1f} s")
    print(f"ground truth: {Path(args.out) / 'truth.json'}"
          + (f"; the rig before the shake: {Path(args.out) / 'original.json'}" if shaken else ""))
    return EXIT_OK


def cmd_info(args: argparse.Namespace) -> int:
    from lfgraph.calibration import Calibration
    from lfgraph.report import calibration_summary

    calib = Calibration.load(args.calibration)
    print(f"{args.calibration}:")
    print(calibration_summary(calib))
    return EXIT_OK


def cmd_demo(args: argparse.Namespace) -> int:
    from lfgraph.demo import run_demo

    return run_demo(Path(args.out), jobs=args.jobs, quiet=args.quiet, scene_name=args.scene,
                    with_refinement=not args.no_refine)


# --------------------------------------------------------------------------------------------- calibrate
def cmd_calibrate(args: argparse.Namespace) -> int:
    from lfgraph.board import BoardSpec
    from lfgraph.capture import open_capture
    from lfgraph.detections import detect_capture
    from lfgraph.grid import ViewGrid
    from lfgraph.pattern import JointSettings, calibrate
    from lfgraph.report import calibration_report_text

    try:
        board = BoardSpec.parse(args.board, args.square_mm)
        grid = ViewGrid(args.grid[0], args.grid[1], args.reference)
        settings = JointSettings(robust=args.robust, tangential=args.tangential, board_sigma_mm=args.board_sigma_mm)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.output.exists() and args.output.is_dir():
        raise UsageError(f"-o {args.output} is a folder; give the calibration file's path")
    if not args.output.parent.exists():
        raise UsageError(f"-o {args.output}: folder {args.output.parent} does not exist")
    logging = _check_rerun(args)
    start = time.perf_counter()
    capture = open_capture(args.input, grid, args.layout)
    print(f"{args.input}: {capture.layout} layout, {len(capture)} frames x {grid.num_views} views of "
          f"{capture.image_size_px[0]}x{capture.image_size_px[1]} px; board {board}")
    obs, cached = detect_capture(capture, board, jobs=args.jobs, progress=not args.quiet, cache=not args.no_cache)
    seen = obs.seen
    print(f"detections{' (from the cache)' if cached else ''}: board found in {seen.sum()} of {seen.size} images "
          f"({time.perf_counter() - start:.1f} s)")
    with _rerun_session(args, grid, logging) as logger:
        if logger is not None:
            logger.set_measurements(obs.num_observations)
        calib, report = calibrate(obs, method=args.method, init=args.init, settings=settings, focal_px=args.focal_px,
                                  pitch_m=None if args.pitch_mm is None else args.pitch_mm / 1000, log=print,
                                  callback=None if logger is None else logger.on_iteration)
        calib.save(args.output)
        if logger is not None:
            logger.calibration_result(calib, obs, report, capture.load_frame(0))
    print(calibration_report_text(calib, report))
    print(f"wrote {args.output} ({time.perf_counter() - start:.1f} s in all)")
    return EXIT_OK


def cmd_evaluate(args: argparse.Namespace) -> int:
    import json

    from lfgraph.calibration import Calibration
    from lfgraph.evaluation import evaluate_calibration
    from lfgraph.report import evaluation_table

    estimate = Calibration.load(args.calibration)
    truth = Calibration.load(args.truth)
    errors = evaluate_calibration(estimate, truth)
    if args.json:
        print(json.dumps(errors.summary(), indent=1))
    else:
        print(f"{args.calibration} against {args.truth}:")
        print(evaluation_table(errors, "truth"))
    return EXIT_OK


# --------------------------------------------------------------------------------------------- rectify / check
def _rectify_frame_task(task: tuple) -> int:
    capture, frame, calib_json, crop, out_dir, out_layout = task
    from lfgraph.calibration import Calibration
    from lfgraph.capture import write_frame
    from lfgraph.rectification import build_maps, remap_views, stored_rectification

    calib = Calibration.from_dict(calib_json)
    maps = build_maps(calib, stored_rectification(calib))
    images = capture.load_frame(frame, grayscale=False)
    write_frame(out_dir, capture.frame_names[frame], remap_views(images, maps), capture.grid, out_layout)
    return frame


def cmd_rectify(args: argparse.Namespace) -> int:
    import shutil
    import tempfile

    from lfgraph.calibration import Calibration
    from lfgraph.capture import open_capture
    from lfgraph.parallel import run_tasks
    from lfgraph.rectification import attach, check_compatible, compute_rectification
    from lfgraph.report import rectification_text

    out = args.output
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise UsageError(f"-o {out} exists and is not an empty folder; choose a new output folder")
    calib = Calibration.load(args.calibration)
    capture = open_capture(args.input, calib.grid, args.layout)
    check_compatible(calib, capture.grid, capture.image_size_px, str(args.input))
    logging = _check_rerun(args)
    rect = compute_rectification(calib, args.crop)
    rectified = attach(calib, rect)
    print(rectification_text(calib, rect))
    with _rerun_session(args, calib.grid, logging) as logger:
        if logger is not None:
            from lfgraph.rectification import build_maps, remap_views

            logger.rig(calib, capture.load_frame(0))
            logger.rectified(calib, remap_views(capture.load_frame(0), build_maps(calib, rect)))
    out_layout = "folders" if capture.layout == "pairs" else capture.layout
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        tasks = [(capture, f, rectified.to_dict(), args.crop, tmp, out_layout) for f in range(len(capture))]
        run_tasks(_rectify_frame_task, tasks, args.jobs, desc="rectifying", unit="frame", progress=not args.quiet)
        rectified.save(tmp / "calibration.json")
        if out.exists():
            out.rmdir()  # empty, checked above
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    print(f"wrote {len(capture)} rectified frames ({out_layout}) and {out / 'calibration.json'} "
          f"(with the rectification) to {out}")
    return EXIT_OK


EXIT_DRIFT = 2


def cmd_check(args: argparse.Namespace) -> int:
    from lfgraph.calibration import Calibration
    from lfgraph.capture import open_capture
    from lfgraph.drift import check_capture
    from lfgraph.rectification import check_compatible, compute_rectification, stored_rectification
    from lfgraph.report import drift_text

    calib = Calibration.load(args.calibration)
    capture = open_capture(args.input, calib.grid, args.layout)
    check_compatible(calib, capture.grid, capture.image_size_px, str(args.input))
    rect = stored_rectification(calib) or compute_rectification(calib)
    n = min(len(capture), args.max_frames)
    report = check_capture(calib, rect, (capture.load_frame(f) for f in range(n)))
    print(drift_text(calib, report))
    if report.rms_px > args.max_px:
        print(f"DRIFT: reprojection RMS {report.rms_px:.3f} px is above --max-px {args.max_px:g}; "
              f"re-calibrate or run lfgraph refine")
        return EXIT_DRIFT
    print(f"OK: reprojection RMS {report.rms_px:.3f} px <= --max-px {args.max_px:g}")
    return EXIT_OK


# --------------------------------------------------------------------------------------------- refine
def cmd_refine(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from lfgraph.calibration import Calibration
    from lfgraph.capture import open_capture
    from lfgraph.rectification import check_compatible
    from lfgraph.refinement.staged import RefineSettings, refine, with_reference
    from lfgraph.report import refinement_text

    try:
        settings = RefineSettings(stages=args.stages, robust=args.robust, max_frames=args.max_frames,
                                  target_rms_px=args.target_rms, triangulation_filter=args.triangulation_filter)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if not args.output.parent.exists():
        raise UsageError(f"-o {args.output}: folder {args.output.parent} does not exist")
    logging = _check_rerun(args)
    calib = Calibration.load(args.calibration)
    if args.reference is not None:
        if not 0 <= args.reference < calib.num_views:
            raise UsageError(f"--reference {args.reference} is not a view of the {calib.grid} grid")
        calib = with_reference(calib, args.reference)
    capture = open_capture(args.input, calib.grid, args.layout)
    check_compatible(calib, capture.grid, capture.image_size_px, str(args.input))
    n = len(capture) if args.max_frames is None else min(len(capture), args.max_frames)
    print(f"{args.input}: {capture.layout} layout, {len(capture)} frames; stages {','.join(settings.stages)}, "
          f"triangulation filter {settings.triangulation_filter}, robust {settings.robust}")
    frames = (capture.load_frame(f) for f in range(n))
    bar = tqdm(frames, total=n, desc="refining", unit="frame", disable=args.quiet)
    with _rerun_session(args, calib.grid, logging) as logger:
        if logger is not None:
            logger.rig(calib, capture.load_frame(0))
        refined, report = refine(calib, bar, settings, log=None if args.quiet else bar.write,
                                 callback=None if logger is None else logger.on_iteration,
                                 events=None if logger is None else logger.refine_event)
        refined.save(args.output)
    print(refinement_text(calib, refined, report))
    print(f"wrote {args.output}")
    return EXIT_OK


# --------------------------------------------------------------------------------------------- depth error
def cmd_depth_error(args: argparse.Namespace) -> int:
    import json

    from lfgraph.depth import depth_error_m
    from lfgraph.report import format_table

    near, far = args.range_m
    if not 0 < near <= far:
        raise UsageError(f"--range-m needs 0 < NEAR <= FAR, got {near} {far}")
    depths = np.linspace(near, far, args.steps)
    errors = depth_error_m(args.focal_px, args.baseline_m, args.error_px, depths)
    if args.json:
        print(json.dumps({"focal_px": args.focal_px, "baseline_m": args.baseline_m, "error_px": args.error_px,
                          "depth_m": depths.tolist(),
                          "depth_error_m": [None if not np.isfinite(e) else float(e) for e in errors]}))
    else:
        print(f"depth error for f = {args.focal_px:g} px, b = {args.baseline_m:g} m, reprojection error "
              f"{args.error_px:g} px (half the spread of the depths at disparity d - E and d + E):")
        print(format_table(["depth_m", "disparity_px", "depth_error_m", "relative_%"],
                           [[f"{z:.3f}", f"{args.focal_px * args.baseline_m / z:.3f}", f"{e:.4f}",
                             f"{100 * e / z:.2f}"] for z, e in zip(depths, errors, strict=True)]))
    if args.plot is not None:
        from lfgraph.plot import line_plot

        line_plot(args.plot, [(f"E = {args.error_px:g} px", depths, errors)],
                  f"depth error, f = {args.focal_px:g} px, b = {args.baseline_m:g} m", "depth (m)",
                  "depth error (m)")
        if not args.json:
            print(f"plot: {args.plot}")
    return EXIT_OK


# --------------------------------------------------------------------------------------------- studies
def _number_list(text: str, kind: type, minimum: float, what: str) -> list:
    try:
        values = [kind(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated {what}, got {text!r}") from None
    if not values or any(not np.isfinite(v) or v < minimum for v in values):
        raise argparse.ArgumentTypeError(f"expected comma-separated {what} >= {minimum:g}, got {text!r}")
    return values


def _floats(text: str) -> list[float]:
    return _number_list(text, float, 0.0, "numbers")


def _ints(text: str) -> list[int]:
    return _number_list(text, int, 1, "whole numbers")


def _study_common(args: argparse.Namespace) -> None:
    from lfgraph.executor import parse_executor

    try:
        parse_executor(args.executor)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if not args.output.parent.exists():
        raise UsageError(f"-o {args.output}: folder {args.output.parent} does not exist")


def cmd_study_shake(args: argparse.Namespace) -> int:
    from lfgraph.datasets.scenes import get_scene
    from lfgraph.factors.noise import parse_robust
    from lfgraph.refinement.staged import parse_stages
    from lfgraph.study import (
        SHAKE_COLUMNS,
        make_shake_trials,
        run_shake_trial,
        run_study,
        shake_plots,
        shake_row_key,
        shake_trial_rows,
    )

    _study_common(args)
    try:
        get_scene(args.scene)
        stages = [s.strip() for s in args.stages.split(",")]
        for name in stages:
            parse_stages(name)
        robust = [r.strip() for r in args.robust.split(",")]
        for r in robust:
            parse_robust(r)
        trials = make_shake_trials(args.scene, args.rot_deg, args.trans_mm, args.trials, args.frames, stages,
                                   robust, args.seed)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    logging = _check_rerun(args)
    print(f"shake study on {args.scene}: {len(trials)} trials ({len(trials) // args.trials} levels x {args.trials} "
          f"seeds), {len(stages) * len(robust)} configurations each, executor {args.executor}")
    with _rerun_session(args, None, logging) as logger:
        rows = run_study(trials, run_shake_trial, args.output, SHAKE_COLUMNS, shake_trial_rows, shake_row_key,
                         args.executor, args.jobs, progress=not args.quiet,
                         on_rows=None if logger is None else logger.study_rows)
    plots = shake_plots(rows, args.output)
    print(_shake_summary(rows))
    print(f"wrote {args.output} and {', '.join(str(p) for p in plots)}")
    return EXIT_OK


def _shake_summary(rows) -> str:
    from lfgraph.report import format_table
    from lfgraph.study import summarise

    metrics = ["transfer_before_px", "transfer_px", "rot_err_deg", "rms_after_px"]
    summary = summarise(rows, ("stages", "robust"), "rot_deg", metrics)
    table = []
    for (stages, robust), d in sorted(summary.items()):
        for i, x in enumerate(d["rot_deg"]):
            table.append([stages, robust, f"{x:g}", *(f"{d[m][i]:.4f}" for m in metrics)])
    return "mean over seeds:\n" + format_table(["stages", "robust", "rot_shake_deg", "transfer_before_px",
                                                 "transfer_after_px", "rot_err_deg", "rms_after_px"], table)


def cmd_study_calibration(args: argparse.Namespace) -> int:
    from lfgraph.datasets.scenes import get_scene
    from lfgraph.report import format_table
    from lfgraph.study import (
        CALIBRATION_COLUMNS,
        CalibrationTrial,
        calibration_plots,
        calibration_row_key,
        calibration_trial_rows,
        run_calibration_trial,
        run_study,
        summarise,
    )

    _study_common(args)
    try:
        named = get_scene(args.scene)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if max(args.frames) > named.checkerboard.frames:
        raise UsageError(f"--frames up to {named.checkerboard.frames} for {args.scene}, got {max(args.frames)}")
    trials = [CalibrationTrial(args.scene, f, s, args.seed + i) for f in args.frames for s in args.sigma_px
              for i in range(args.trials)]
    print(f"calibration study on {args.scene}: {len(trials)} trials, executor {args.executor}")
    rows = run_study(trials, run_calibration_trial, args.output, CALIBRATION_COLUMNS, calibration_trial_rows,
                     calibration_row_key, args.executor, args.jobs, progress=not args.quiet)
    plots = calibration_plots(rows, args.output)
    metrics = ["fx_err_px", "pos_err_mm", "rot_err_deg"]
    sq = [{**r, **{m: float(r[m]) ** 2 for m in metrics}} for r in rows]
    table = []
    for (method, sigma), d in sorted(summarise(sq, ("method", "sigma_px"), "frames", metrics).items()):
        for i, f in enumerate(d["frames"]):
            table.append([method, sigma, int(f), *(f"{np.sqrt(d[m][i]):.4g}" for m in metrics)])
    print("RMS over seeds:")
    print(format_table(["method", "sigma_px", "frames", "fx_err_px", "pos_err_mm", "rot_err_deg"], table))
    print(f"wrote {args.output} and {len(plots)} plots ({plots[0].parent if plots else ''})")
    return EXIT_OK


# --------------------------------------------------------------------------------------------- parser
@contextmanager
def _rerun_session(args: argparse.Namespace, grid, logging: bool) -> Iterator:
    """rerun's logger for a ``with`` block when ``logging``, else None (no recording is created)."""
    if not logging:
        yield None
        return
    from lfgraph.viz.rerun_log import rerun_session

    with rerun_session(args, grid) as logger:
        yield logger


def _add_rerun_args(p: argparse.ArgumentParser) -> None:
    group = p.add_argument_group("rerun visual debugging (nothing is logged without --save/--connect/--serve/--stdout)")
    from lfgraph.viz.rerun_log import add_args

    add_args(group)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lfgraph",
        description="Calibrate, rectify and auto-refine light-field cameras built as camera arrays.")
    sub = parser.add_subparsers(dest="command", required=True)

    synth = sub.add_parser("synth", help="render synthetic light fields with ground truth")
    synth_sub = synth.add_subparsers(dest="synth_command", required=True)

    def common_synth(p: argparse.ArgumentParser, default_scene: str) -> None:
        p.add_argument("out", type=Path, help="output directory")
        p.add_argument("--scene", default=default_scene, help=f"named scene (default {default_scene})")
        p.add_argument("--grid", type=_grid, help="ROWSxCOLS, overrides the scene's grid")
        p.add_argument("--image-size", type=_size, help="WIDTHxHEIGHT per view in pixels")
        p.add_argument("--reference", type=int, help="reference view index (row-major)")
        p.add_argument("--frames", type=_positive_int, help="number of frames")
        p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
        p.add_argument("--layout", choices=("folders", "mosaic"), default="folders",
                       help="folders: OUT/<frame>/rRR_cCC.png; mosaic: OUT/<frame>.png with views tiled")
        p.add_argument("--jobs", type=_positive_int, default=_jobs_default(), help="worker processes")
        p.add_argument("--quiet", action="store_true", help="no progress bar")

    cb = synth_sub.add_parser("checkerboard", help="checkerboard captures rendered as images")
    common_synth(cb, "paper-4x4")
    cb.add_argument("--board", help="inner corners COLSxROWS, OpenCV patternSize (e.g. 11x8)")
    cb.add_argument("--square-mm", type=float, help="square side in millimetres")
    cb.set_defaults(func=cmd_synth_checkerboard)

    sc = synth_sub.add_parser("scene", help="textured scenes (for auto-refinement), optionally after a shake")
    common_synth(sc, "paper-5x5")
    sc.add_argument("--keyboard", action="store_true", help="the hard scene with repetitive texture")
    sc.add_argument("--shake-rot-deg", type=_non_negative, default=0.0,
                    help="shake: turn each non-reference view by up to this many degrees")
    sc.add_argument("--shake-trans-mm", type=_non_negative, default=0.0,
                    help="shake: move each non-reference view by up to this many millimetres per axis")
    sc.add_argument("--shake-axis", choices=("optical", "any"), default="optical",
                    help="rotation axis of the shake (default: each view's optical axis, as in the paper)")
    sc.set_defaults(func=cmd_synth_scene)

    info = sub.add_parser("info", help="print a calibration file as a table")
    info.add_argument("calibration", type=Path)
    info.set_defaults(func=cmd_info)

    cal = sub.add_parser("calibrate", help="calibrate the array from checkerboard captures (paper Section 3.2)")
    cal.add_argument("input", type=Path, help="capture folder (see --layout)")
    cal.add_argument("--grid", type=_grid, required=True, help="ROWSxCOLS of the array, e.g. 4x4")
    cal.add_argument("--board", required=True, help="inner corners COLSxROWS (OpenCV patternSize), e.g. 11x8")
    cal.add_argument("--square-mm", type=_positive_float, required=True, help="square side in millimetres")
    cal.add_argument("--layout", choices=LAYOUT_CHOICES, default="auto", help="input layout (default: detect)")
    cal.add_argument("--reference", type=int, default=0, help="reference view, row-major index (default 0)")
    cal.add_argument("--method", choices=("joint", "paper"), default="joint",
                     help="joint: one GTSAM graph over all views and frames (default); paper: per-view Zhang + "
                          "relative PnP/LM as in the paper")
    cal.add_argument("--init", choices=("paper", "design"), default="paper",
                     help="start of the joint route: the paper route (default) or design values")
    cal.add_argument("--robust", default="none",
                     help="robust kernel NAME[:THRESHOLD_PX]: none, huber:1.0, cauchy:..., tukey:..., gm, dcs, ...")
    cal.add_argument("--tangential", action="store_true", help="estimate p1, p2 (held at 0 by default)")
    cal.add_argument("--board-sigma-mm", type=_positive_float,
                     help="board flatness tolerance: estimate the corners' positions within it (default: rigid)")
    cal.add_argument("--focal-px", type=_positive_float, help="design focal length for --init design")
    cal.add_argument("--pitch-mm", type=_positive_float, help="design grid pitch for --init design")
    cal.add_argument("--jobs", type=_positive_int, default=_jobs_default(), help="detection processes")
    cal.add_argument("--no-cache", action="store_true", help="re-detect even if INPUT/.lfgraph-detections.npz is valid")
    cal.add_argument("--quiet", action="store_true", help="no progress bar")
    cal.add_argument("-o", "--output", type=Path, required=True, help="calibration.json to write")
    _add_rerun_args(cal)
    cal.set_defaults(func=cmd_calibrate)

    ev = sub.add_parser("evaluate", help="compare a calibration with ground truth (e.g. a synthetic truth.json)")
    ev.add_argument("calibration", type=Path)
    ev.add_argument("--truth", type=Path, required=True, help="ground-truth calibration.json")
    ev.add_argument("--json", action="store_true", help="print the RMS errors as JSON")
    ev.set_defaults(func=cmd_evaluate)

    rc = sub.add_parser("rectify", help="rectify a capture with a calibration (paper Section 3.3)")
    rc.add_argument("calibration", type=Path, help="calibration.json")
    rc.add_argument("input", type=Path, help="capture folder")
    rc.add_argument("-o", "--output", type=Path, required=True, help="new folder for the rectified capture")
    rc.add_argument("--crop", choices=("valid", "full"), default="valid",
                    help="valid: the rectangle every view fills (default); full: keep the source size")
    rc.add_argument("--layout", choices=LAYOUT_CHOICES, default="auto")
    rc.add_argument("--jobs", type=_positive_int, default=_jobs_default())
    rc.add_argument("--quiet", action="store_true")
    _add_rerun_args(rc)
    rc.set_defaults(func=cmd_rectify)

    ck = sub.add_parser("check", help="drift check: does the calibration still fit an ordinary capture? "
                                      "(exit 2 when not)")
    ck.add_argument("calibration", type=Path, help="calibration.json")
    ck.add_argument("input", type=Path, help="capture folder of any textured scene")
    ck.add_argument("--max-px", type=_positive_float, default=0.5,
                    help="largest acceptable reprojection RMS (default 0.5 px)")
    ck.add_argument("--max-frames", type=_positive_int, default=3, help="frames to use (default 3)")
    ck.add_argument("--layout", choices=LAYOUT_CHOICES, default="auto")
    ck.set_defaults(func=cmd_check)

    rf = sub.add_parser("refine", help="auto-refine a calibration from ordinary scene captures (paper Section 4)")
    rf.add_argument("calibration", type=Path, help="calibration.json to refine")
    rf.add_argument("input", type=Path, help="capture folder of a textured scene")
    rf.add_argument("-o", "--output", type=Path, required=True, help="refined calibration.json to write")
    rf.add_argument("--stages", default="default",
                    help="schedule: default (points,poses,clean), paper (points,intrinsics,all) or a comma list of "
                         "points, intrinsics, poses, all, clean")
    rf.add_argument("--robust", default="none", help="robust kernel NAME[:THRESHOLD_PX] (none, huber:1.345, "
                                                     "cauchy:..., tukey:..., gm:..., dcs:...)")
    rf.add_argument("--triangulation-filter", choices=("median", "worst", "none"),
                    help="median: the paper's (default with --stages paper); worst: drop outlying tracks (default)")
    rf.add_argument("--max-frames", type=_positive_int, help="use at most this many frames")
    rf.add_argument("--target-rms", type=_positive_float,
                    help="stop adding frames once a new frame fits the calibration at this RMS (px)")
    rf.add_argument("--reference", type=int, help="re-express the calibration relative to this view first")
    rf.add_argument("--layout", choices=LAYOUT_CHOICES, default="auto")
    rf.add_argument("--quiet", action="store_true")
    _add_rerun_args(rf)
    rf.set_defaults(func=cmd_refine)

    de = sub.add_parser("depth-error", help="the depth error a reprojection error causes (paper Section 5.1)")
    de.add_argument("--focal-px", type=_positive_float, required=True, help="focal length in pixels")
    de.add_argument("--baseline-m", type=_positive_float, required=True, help="baseline in metres")
    de.add_argument("--error-px", type=_non_negative, required=True, help="reprojection (disparity) error, px")
    de.add_argument("--range-m", type=_positive_float, nargs=2, metavar=("NEAR", "FAR"), default=(0.5, 2.0),
                    help="depth range in metres (default 0.5 2.0)")
    de.add_argument("--steps", type=_positive_int, default=7, help="depths in the table (default 7)")
    de.add_argument("--json", action="store_true", help="print JSON instead of a table")
    de.add_argument("--plot", type=Path, help="write a PNG plot of depth error against depth")
    de.set_defaults(func=cmd_depth_error)

    st = sub.add_parser("study", help="studies: the paper's shake experiment, calibration accuracy vs frames")
    st_sub = st.add_subparsers(dest="study_command", required=True)

    def common_study(p: argparse.ArgumentParser, default_scene: str, default_out: str) -> None:
        p.add_argument("--scene", default=default_scene, help=f"named scene (default {default_scene})")
        p.add_argument("--trials", type=_positive_int, default=3, help="seeded trials per level (default 3)")
        p.add_argument("--seed", type=int, default=0, help="first seed (default 0)")
        p.add_argument("--executor", default="local",
                       help="local (process pool, default), dask-local (a LocalCluster) or dask://HOST:PORT")
        p.add_argument("--jobs", type=_positive_int, default=_jobs_default(), help="processes / Dask workers")
        p.add_argument("-o", "--output", type=Path, default=Path(default_out),
                       help=f"tidy CSV (default {default_out}); a re-run skips trials already in it")
        p.add_argument("--quiet", action="store_true")

    ss = st_sub.add_parser("shake", help="refine shaken rigs (the paper's Fig. avg_synth)")
    common_study(ss, "paper-5x5", "shake_study.csv")
    ss.add_argument("--rot-deg", type=_floats, default=[0.0, 0.25, 0.5, 1.0],
                    help="rotation shake levels about each optical axis, deg (default 0,0.25,0.5,1)")
    ss.add_argument("--trans-mm", type=_floats, default=[0.0, 1.0, 2.0, 5.0],
                    help="translation shake levels paired with --rot-deg, mm per axis (default 0,1,2,5)")
    ss.add_argument("--frames", type=_positive_int, default=1, help="scene frames per trial (default 1)")
    ss.add_argument("--stages", default="paper,default", help="schedules to compare (default paper,default)")
    ss.add_argument("--robust", default="none", help="robust kernels to compare, e.g. none,huber:1.345,cauchy:1.0")
    _add_rerun_args(ss)
    ss.set_defaults(func=cmd_study_shake)

    sc2 = st_sub.add_parser("calibration", help="calibration accuracy vs frames and corner noise, three methods")
    common_study(sc2, "paper-4x4", "calibration_study.csv")
    sc2.add_argument("--frames", type=_ints, default=[5, 10, 20, 30, 40], help="frame counts (default 5,...,40)")
    sc2.add_argument("--sigma-px", type=_floats, default=[0.1, 0.3], help="corner noise levels (default 0.1,0.3)")
    sc2.set_defaults(func=cmd_study_calibration)

    from lfgraph.interop_cli import add_parsers as add_interop_parsers

    add_interop_parsers(sub, _positive_int)

    demo = sub.add_parser("demo", help="the main job on the embedded synthetic default: render, calibrate, "
                                       "evaluate and rectify paper-4x4, then refine a shaken paper-5x5 (~2 min)")
    demo.add_argument("--out", default="out/demo", help="working directory (default out/demo)")
    demo.add_argument("--scene", default="paper-4x4", help="named scene (default paper-4x4; small-2x2 is quick)")
    demo.add_argument("--no-refine", action="store_true", help="skip the refinement part (shaken paper-5x5)")
    demo.add_argument("--jobs", type=_positive_int, default=_jobs_default())
    demo.add_argument("--quiet", action="store_true")
    demo.set_defaults(func=cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except UsageError as exc:
        parser.error(str(exc))
        return EXIT_USAGE
    except (ValueError, OSError, RuntimeError) as exc:
        print(f"lfgraph: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("lfgraph: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
