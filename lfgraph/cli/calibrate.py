"""``lfgraph calibrate``, ``evaluate`` and ``info``."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from lfgraph.cli.args import (
    EXIT_OK,
    LAYOUT_CHOICES,
    UsageError,
    add_rerun_args,
    check_output_file,
    check_rerun,
    check_side_outputs,
    cli_observer,
    grid_size,
    image_sizes,
    jobs_default,
    json_text,
    positive_float,
    positive_int,
    reports_to_stderr,
    rerun_session,
)


def cmd_info(args: argparse.Namespace) -> int:
    """``lfgraph info``: print a calibration file as a table (``--json``: its summary as JSON); returns 0."""
    from lfgraph.cli.tables import calibration_summary
    from lfgraph.core.calibration import Calibration

    calib = Calibration.load(args.calibration)
    if args.json:
        print(json_text({"file": str(args.calibration), **calib.summary_dict()}, indent=1))
        return EXIT_OK
    print(f"{args.calibration}:")
    print(calibration_summary(calib))
    return EXIT_OK


def _board_and_config(args: argparse.Namespace):
    from lfgraph.core.grid import ViewGrid
    from lfgraph.detect.board import BoardSpec
    from lfgraph.pattern import CalibrateConfig
    from lfgraph.pattern.design_check import order_permutation
    from lfgraph.pattern.lenses import resolve_lenses

    try:
        if args.detections is None:
            if args.board is None or args.square_mm is None:
                raise ValueError("--board and --square-mm are needed to detect the board in images (or give "
                                 "--detections with the points another tool found)")
            if args.object_points is not None or args.image_size is not None:
                raise ValueError("--object-points and --image-size go with --detections")
            board = BoardSpec.parse(args.board, args.square_mm, args.marker_mm)
        else:
            given = [f"--{n.replace('_', '-')}" for n in ("board", "square_mm", "marker_mm", "layout", "missing_view")
                     if getattr(args, n) not in (None, "auto")]
            if given:
                raise ValueError(f"{', '.join(given)} appl{'ies' if len(given) == 1 else 'y'} to images; with "
                                 f"--detections the target is given by its object points")
            if args.image_size is None:
                raise ValueError("--detections needs --image-size WIDTHxHEIGHT (the size of the images the points "
                                 "were detected in)")
            if args.detections == "opencv-multiview" and args.object_points is None:
                raise ValueError("--detections opencv-multiview needs --object-points OBJ.npy ((C, 3), metres)")
            board = None
        grid = ViewGrid(args.grid[0], args.grid[1], args.reference)
        config = CalibrateConfig(method=args.method, init=args.init, focal_px=args.focal_px, pitch_mm=args.pitch_mm,
                                 robust=args.robust, tangential=args.tangential, board_sigma_mm=args.board_sigma_mm,
                                 lens=args.lens, screen=not args.no_screen, check_grid=not args.no_grid_check)
        resolve_lenses(config.lens, grid)  # a bad --lens is refused before detection
        if args.view_order:  # ... and a bad --view-order
            order_permutation(grid, args.view_order.split(","))
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return board, grid, config


def _view_label(capture, frame: int, view: int) -> str | None:
    """The file of one view-frame (with the view's name where one file holds several views); None if missing."""
    paths = capture.paths(frame)
    if len(paths) == capture.grid.num_views:
        return None if paths[view] is None else str(paths[view])
    return f"{paths[0]} ({capture.grid.name(view)})"


MAX_MISSED_LISTED = 10  # images without a detected board named in the output


def cmd_calibrate(args: argparse.Namespace) -> int:
    """``lfgraph calibrate``: calibrate from board captures (or loaded detections) and save the result; returns 0 (the
    report goes to stderr when ``--stdout`` carries a rerun recording)."""
    with reports_to_stderr(args):
        return _calibrate(args)


def _printer(args: argparse.Namespace):
    """``print``, or nothing under the global ``-q`` (errors and warnings still reach stderr through the log)."""
    return (lambda *_args, **_kw: None) if getattr(args, "log_quiet", False) else print


def _calibrate(args: argparse.Namespace) -> int:
    from logging import getLogger

    import numpy as np

    from lfgraph.cli.tables import calibration_report_text
    from lfgraph.pattern import calibrate
    from lfgraph.pattern.design_check import order_permutation, view_order

    board, grid, config = _board_and_config(args)
    say = _printer(args)
    check_output_file(args.output)
    check_side_outputs(args, outputs=[args.output])
    logging = check_rerun(args)
    start = time.perf_counter()
    capture = None
    if args.detections is not None:
        from lfgraph.io.points import load_detections

        sources = [args.input, *Path(args.input).glob("*"), *([args.object_points] if args.object_points else [])]
        check_output_file(args.output, inputs=sources)
        check_side_outputs(args, inputs=sources, outputs=[args.output])
        obs = load_detections(args.input, args.detections, grid, args.image_size, args.object_points)
        say(f"{args.input}: {args.detections} detections, {obs.num_frames} frames x {grid.num_views} views of "
              f"{obs.image_size_px[0]}x{obs.image_size_px[1]} px; target {obs.board}")
        seen = obs.seen
        say(f"target seen in {seen.sum()} of {seen.size} view-frames ({obs.num_observations} points)")
    else:
        from lfgraph.detect.detections import detect_capture
        from lfgraph.io.capture import open_capture

        capture = open_capture(args.input, grid, args.layout or "auto", missing=args.missing_view or "error")
        check_output_file(args.output, inputs=capture.all_paths())
        check_side_outputs(args, inputs=capture.all_paths(), outputs=[args.output])
        sizes = ", ".join(dict.fromkeys(f"{w}x{h}" for w, h in capture.image_sizes))
        say(f"{args.input}: {capture.layout} layout, {len(capture)} frames x {grid.num_views} views of {sizes} px; "
              f"board {board}")
        for note in capture.notes:
            say(f"note: {note}")
        obs, cached = detect_capture(capture, board, jobs=args.jobs, progress=not args.quiet, cache=not args.no_cache)
        seen = obs.seen
        say(f"detections{' (from the cache)' if cached else ''}: board found in {seen.sum()} of {seen.size} "
              f"images ({time.perf_counter() - start:.1f} s)")
        missed = [_view_label(capture, int(f), int(v)) for f, v in zip(*np.nonzero(~seen.T), strict=True)]
        missed = [m for m in missed if m is not None]
        if missed:
            shown = ", ".join(str(p) for p in missed[:MAX_MISSED_LISTED])
            say(f"board not found in: {shown}" + (f" and {len(missed) - MAX_MISSED_LISTED} more"
                                                    if len(missed) > MAX_MISSED_LISTED else ""))
    frames = capture.load_frame if capture is not None else None
    if args.view_order:  # the streams re-labelled: the grid's view i is the stream captured as names[i]
        names = args.view_order.split(",")
        obs, perm = view_order(obs, names), order_permutation(grid, names)
        say(f"view order: {', '.join(f'{grid.name(i)} <- {n}' for i, n in enumerate(names) if grid.name(i) != n)}")
        frames = None if frames is None else (lambda f, load=frames: [load(f)[p] for p in perm])
    with rerun_session(args, grid, logging, "calibrate") as logger:
        if logger is not None:
            logger.set_measurements(obs.num_observations)
            logger.frames_source = frames
        # the recording hears the result through the observer (run_end): rig, boards, every frame's corners
        calib, report = calibrate(obs, config, cli_observer(logger))
        calib.save(args.output)
    say(calibration_report_text(calib, report))
    if say is not print:  # -q: the report's warnings still reach the log (stderr)
        for warning in report.warnings:
            getLogger("lfgraph").warning(warning)
    if args.plots is not None:
        from lfgraph.viz.figures import calibration_report_figures

        for path in calibration_report_figures(calib, obs, report, args.plots):
            say(f"figure: {path}")
    say(f"wrote {args.output} ({time.perf_counter() - start:.1f} s in all)")
    return EXIT_OK


def cmd_evaluate(args: argparse.Namespace) -> int:
    """``lfgraph evaluate``: print a calibration's errors against a ground truth (``--json``: as JSON); returns 0."""

    from lfgraph.cli.tables import evaluation_table
    from lfgraph.core.calibration import Calibration
    from lfgraph.judge.evaluation import evaluate_calibration

    estimate = Calibration.load(args.calibration)
    truth = Calibration.load(args.truth)
    errors = evaluate_calibration(estimate, truth)
    if args.json:
        print(json_text(errors.summary(), indent=1))
    else:
        print(f"{args.calibration} against {args.truth}:")
        print(evaluation_table(errors, "truth"))
    return EXIT_OK


def add_parsers(sub: Any) -> None:
    """Add this module's commands to the ``lfgraph`` subparsers."""
    info = sub.add_parser("info", help="print a calibration file as a table")
    info.add_argument("calibration", type=Path, help="calibration.json or truth.json")
    info.add_argument("--json", action="store_true", help="print grid, per-view parameters and metrics as JSON")
    info.set_defaults(func=cmd_info)

    cal = sub.add_parser("calibrate", help="calibrate the array from checkerboard captures (paper Section 3.2), or "
                                           "from points another tool detected (--detections)")
    cal.add_argument("input", type=Path, help="capture folder (see --layout); with --detections the folder of "
                                              "cam_*.json files (opencv-multiview) or the .npz file (npz)")
    cal.add_argument("--grid", type=grid_size, required=True, help="ROWSxCOLS of the array, e.g. 4x4")
    cal.add_argument("--board",
                     help="checkerboard inner corners COLSxROWS (OpenCV patternSize), e.g. 11x8; or a ChArUco board "
                          "charuco:SQUARESXxSQUARESY:DICT_NAME[:legacy][:inverted] (squares, as OpenCV counts them), "
                          "e.g. charuco:4x5:DICT_4X4_1000 with --marker-mm")
    cal.add_argument("--square-mm", type=positive_float, help="square side in millimetres (with --board)")
    cal.add_argument("--marker-mm", type=positive_float,
                     help="ChArUco marker side in millimetres (with --board charuco:SQUARESXxSQUARESY:DICT_...)")
    cal.add_argument("--layout", choices=LAYOUT_CHOICES, help="input layout (default: detect)")
    cal.add_argument("--missing-view", choices=("error", "unseen"),
                     help="a frame that lacks a view's image: error (default) or treat that view-frame as 'board "
                          "not seen'")
    det = cal.add_argument_group("points detected by another tool (instead of images)")
    det.add_argument("--detections", choices=("opencv-multiview", "npz"),
                     help="opencv-multiview: INPUT holds one cam_*.json per view (OpenCV FileStorage JSON, a "
                          "frame_N node of 2C numbers per frame the camera saw the target); npz: INPUT is a .npz "
                          "with object_points (C, 3) m, image_points (V, F, C, 2) px, valid (V, F, C)")
    det.add_argument("--object-points", type=Path, metavar="OBJ.npy",
                     help="(C, 3) target points in metres, z = 0 (for --detections opencv-multiview)")
    det.add_argument("--image-size", type=image_sizes, metavar="WxH[,VIEW=WxH...]",
                     help="size of the images the points come from; views of another size after it, e.g. "
                          "1920x1080,r00_c02=1280x720")
    cal.add_argument("--reference", type=int, default=0, help="reference view, row-major index (default 0)")
    cal.add_argument("--method", choices=("joint", "paper"), default="joint",
                     help="joint: one GTSAM graph over all views and frames (default); paper: per-view Zhang + "
                          "relative PnP/LM as in the paper")
    cal.add_argument("--init", choices=("paper", "design"), default="paper",
                     help="start of the joint route: the paper route (default) or design values")
    cal.add_argument("--robust", default="none",
                     help="robust kernel NAME[:THRESHOLD] in px (or NAME:Ksigma in corner sigmas; a bare NAME takes "
                          "its usual constant in sigmas): none, huber:1.0, cauchy, tukey:5, gm, dcs, ...")
    cal.add_argument("--tangential", action="store_true", help="estimate p1, p2 (held at 0 by default)")
    cal.add_argument("--no-screen", action="store_true",
                     help="fit every observation by least squares (by default a robust Cauchy fit first drops the "
                          "view-frames the rig cannot explain, naming them)")
    cal.add_argument("--view-order", metavar="NAME,NAME,...",
                     help="the true order of swapped streams: for each view of the grid, row-major, the name its "
                          "images were captured under, e.g. r00_c01,r00_c00,r01_c00,r01_c01 (cables 1 and 2 swapped)")
    cal.add_argument("--no-grid-check", action="store_true",
                     help="accept a result that contradicts the grid (views off the grid, at one place, swapped): "
                          "for a rig that is deliberately no grid; mirrored views are refused regardless")
    cal.add_argument("--lens", default="auto", metavar="MODEL[,VIEW=MODEL...]",
                     help="lens model: auto (default: per view, the model that predicts held-out frames best), "
                          "radtan, fisheye or unified (fitted only when named); per view e.g. auto,r00_c02=fisheye")
    cal.add_argument("--board-sigma-mm", type=positive_float,
                     help="board flatness tolerance: estimate the corners' positions within it (default: rigid)")
    cal.add_argument("--focal-px", type=positive_float, help="design focal length for --init design")
    cal.add_argument("--pitch-mm", type=positive_float, help="design grid pitch for --init design")
    cal.add_argument("--jobs", type=positive_int, default=jobs_default(), help="detection processes")
    cal.add_argument("--no-cache", action="store_true", help="re-detect even if INPUT/.lfgraph-detections.npz is valid")
    cal.add_argument("--quiet", action="store_true", help="no progress bar")
    cal.add_argument("-o", "--output", type=Path, required=True, help="calibration.json to write")
    cal.add_argument("--plots", type=Path, metavar="DIR",
                     help="write the calibration report figures (coverage, residuals, per-frame RMS, grid deviation) "
                          "as PNG and PDF to this folder")
    add_rerun_args(cal)
    cal.set_defaults(func=cmd_calibrate)

    ev = sub.add_parser("evaluate", help="compare a calibration with ground truth (e.g. a synthetic truth.json)")
    ev.add_argument("calibration", type=Path, help="calibration.json to evaluate")
    ev.add_argument("--truth", type=Path, required=True, help="ground-truth calibration.json")
    ev.add_argument("--json", action="store_true", help="print the RMS errors as JSON")
    ev.set_defaults(func=cmd_evaluate)
